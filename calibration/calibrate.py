"""Fit every candidate, judge it in free run (leave-one-run-out when possible), pick one.

Pure computation on in-memory runs; the CLI in :mod:`calibration.commands`
does the file I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from compensator.errors import CalibrationError
from compensator.model import ThermalModel

from .data import Run, has_cooldown, resample, transient_mask
from .fitting import FORM_BY_NAME, FORMS, FitResult, FormSpec, fit_form, solve_output_error

PARSIMONY = 0.02
"""A simpler form wins when its score is within 2 % of the best."""
SEARCH_ROWS = 20000
"""Output-error searches run on at most this many rows (a coarser grid)."""


def free_run(model: ThermalModel, run: Run) -> np.ndarray:
    """Predicted elongation, starting from the first measured value, never re-anchored."""
    state = model.state_at(float(run.elongation_um[0]), float(run.speed_rpm[0]))
    return model.simulate(run.speed_rpm, run.time_s, state).elongation_um


def residual_stats(residual: np.ndarray) -> dict[str, float | int | None]:
    if residual.size == 0:
        return {"samples": 0, "rms_um": None, "max_abs_um": None, "mean_abs_um": None,
                "mean_um": None, "std_um": None}
    return {
        "samples": int(residual.size),
        "rms_um": float(np.sqrt(np.mean(residual**2))),
        "max_abs_um": float(np.max(np.abs(residual))),
        "mean_abs_um": float(np.mean(np.abs(residual))),
        "mean_um": float(np.mean(residual)),
        "std_um": float(np.std(residual)),
    }


def phase_stats(run: Run, residual: np.ndarray, max_rpm: float) -> dict[str, Any]:
    mask = transient_mask(run.time_s, run.speed_rpm, max_rpm)
    return {"steady": residual_stats(residual[~mask]), "transient": residual_stats(residual[mask])}


@dataclass
class Candidate:
    result: FitResult
    in_sample: dict[str, Any] | None = None
    cv: dict[str, Any] | None = None

    @property
    def score(self) -> float:
        src = self.cv if self.cv is not None else self.in_sample
        if not src or src.get("rms_um") is None:
            return math.inf
        return float(src["rms_um"])


@dataclass
class Calibration:
    model: ThermalModel
    chosen: Candidate
    candidates: list[Candidate]
    runs: list[Run]
    fit_dt_s: float
    reason: str
    warnings: list[str] = field(default_factory=list)
    predictions: dict[str, np.ndarray] = field(default_factory=dict)

    def report(self) -> dict[str, Any]:
        max_rpm = self.model.speed_range_rpm[1]
        per_run = []
        for r in self.runs:
            res = r.elongation_um - self.predictions[r.name]
            per_run.append({"run": r.name, **residual_stats(res), "phases": phase_stats(r, res, max_rpm)})
        ref = next(c for c in self.candidates if c.result.form.name == "paper-ols")
        return {
            "format": "thermocomp.fit-report/1",
            "chosen": self.chosen.result.form.name,
            "reason": self.reason,
            "fit_dt_s": self.fit_dt_s,
            "scored_by": "leave-one-run-out free run" if len(self.runs) > 1 else "in-sample free run",
            "runs": [
                {"name": r.name, "samples": len(r), "duration_s": r.duration_s,
                 "dt_s": r.median_dt_s, "max_speed_rpm": float(np.abs(r.speed_rpm).max()),
                 "has_cooldown": has_cooldown(r)}
                for r in self.runs
            ],
            "reference_one_step_r2": ref.result.one_step_r2,
            "candidates": [
                {
                    "form": c.result.form.name,
                    "description": c.result.form.description,
                    "usable": c.result.model is not None,
                    "one_step_r2": c.result.one_step_r2,
                    "free_run": c.in_sample,
                    "cross_validation": c.cv,
                    "score_rms_um": None if math.isinf(c.score) else c.score,
                    "note": c.result.note,
                }
                for c in self.candidates
            ],
            "coefficients": self.chosen.result.coefficients,
            "residuals": per_run,
            "warnings": self.warnings,
        }


def choose_fit_dt(runs: Sequence[Run], dt_s: float | None) -> float:
    if dt_s is not None:
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise CalibrationError(f"--dt must be > 0, got {dt_s}")
        return float(dt_s)
    return float(max(r.median_dt_s for r in runs))


def _coarse(runs: Sequence[Run]) -> list[Run]:
    rows = sum(len(r) for r in runs)
    if rows <= SEARCH_ROWS:
        return list(runs)
    k = math.ceil(rows / SEARCH_ROWS)
    dt = runs[0].median_dt_s * k
    return [resample(r, dt) for r in runs]


def _fit(form: FormSpec, fit_runs: Sequence[Run], **meta) -> FitResult:
    if form.method == "oe" and sum(len(r) for r in fit_runs) > SEARCH_ROWS:
        # search the time constants on a coarser grid, then solve the gains on the full one
        coarse = fit_form(form, _coarse(fit_runs), **meta)
        if coarse.model is None:
            return coarse
        return _refit_gains(form, coarse, fit_runs, **meta)
    return fit_form(form, fit_runs, **meta)


def _refit_gains(form: FormSpec, coarse: FitResult, runs: Sequence[Run], **meta) -> FitResult:
    assert coarse.theta is not None
    return solve_output_error(form, coarse.theta, runs, **meta)


def calibrate(
    runs: Sequence[Run],
    *,
    dt_s: float | None = None,
    form: str = "auto",
    progress: Callable[[str], None] | None = None,
    **meta: Any,
) -> Calibration:
    """Fit all candidate forms and pick the best in free run."""
    if not runs:
        raise CalibrationError("no calibration runs")
    names = [r.name for r in runs]
    if len(set(names)) != len(names):
        raise CalibrationError("two runs share a name")
    if form != "auto" and form not in FORM_BY_NAME:
        raise CalibrationError(f"unknown form {form!r}; choose from auto, {', '.join(FORM_BY_NAME)}")
    say = progress or (lambda _msg: None)
    fit_dt = choose_fit_dt(runs, dt_s)
    fit_runs = [resample(r, fit_dt) for r in runs]
    warnings: list[str] = []
    if any(abs(r.median_dt_s - fit_dt) > 1e-6 * fit_dt for r in runs):
        warnings.append(f"runs resampled to {fit_dt:g} s for fitting; scored at their own samples")

    candidates: list[Candidate] = []
    for spec in FORMS:
        say(f"fitting {spec.name}")
        result = _fit(spec, fit_runs, **meta)
        cand = Candidate(result)
        if result.model is not None:
            res = np.concatenate([r.elongation_um - free_run(result.model, r) for r in runs])
            cand.in_sample = residual_stats(res)
        candidates.append(cand)

    if len(runs) > 1:
        for cand in candidates:
            spec = cand.result.form
            if cand.result.model is None:
                continue
            say(f"cross-validating {spec.name}")
            held = []
            for i, r in enumerate(runs):
                others = [fr for j, fr in enumerate(fit_runs) if j != i]
                sub = _fit(spec, others, **meta)
                if sub.model is None:
                    held = []
                    break
                held.append(r.elongation_um - free_run(sub.model, r))
            if held:
                cand.cv = residual_stats(np.concatenate(held))
    else:
        warnings.append(
            "one run only: scores are in-sample; record a second, different run to validate"
        )

    usable = [c for c in candidates if c.result.model is not None and math.isfinite(c.score)]
    if not usable:
        raise CalibrationError("no candidate form produced a stable model from these runs")
    if form != "auto":
        chosen = next((c for c in usable if c.result.form.name == form), None)
        if chosen is None:
            raise CalibrationError(f"form {form} did not produce a stable model")
        reason = f"form {form} was requested"
    else:
        best = min(usable, key=lambda c: c.score)
        # FORMS is ordered from simple to rich: the first within PARSIMONY of the best wins
        chosen = next(c for c in usable if c.score <= best.score * (1 + PARSIMONY))
        basis = "leave-one-run-out free-run" if len(runs) > 1 else "in-sample free-run"
        ref = next(c for c in candidates if c.result.form.name == "paper-ols")
        vs = (
            f"; the paper's OLS form scores {ref.score:.2f} um"
            if math.isfinite(ref.score) else "; the paper's OLS form is not usable on these runs"
        )
        reason = (
            f"{chosen.result.form.name} has the lowest {basis} RMS, {chosen.score:.2f} um"
            + (f" (within {PARSIMONY:.0%} of {best.result.form.name}, and simpler)" if chosen is not best else "")
            + vs
        )
        cv, ins = chosen.cv, chosen.in_sample
        if cv and ins and cv["rms_um"] > 2 * ins["rms_um"] + 0.2:
            warnings.append(
                f"held-out error ({cv['rms_um']:.2f} um) is much larger than in-sample "
                f"({ins['rms_um']:.2f} um): the runs differ in ways the model does not see "
                "(ambient, tooling, cutting load); record another run"
            )

    if not any(has_cooldown(r) for r in runs):
        warnings.append(
            "no run has a cool-down (10 min or more at rest after running): the dissipation "
            "(cooling) time constant is not identifiable; a slow heat-up looks like a long "
            "time constant. Record a cool-down at 0 rpm"
        )
    levels = np.unique(np.round(np.concatenate([np.abs(r.speed_rpm) for r in runs]), -2))
    if levels.size < 5:
        warnings.append(
            f"only {levels.size} distinct speed levels: the n, n^2, n^3 terms are poorly "
            "separated; use a staircase of five or more speeds"
        )

    stats = {
        "scored_by": "loro" if len(runs) > 1 else "in-sample",
        "score_rms_um": chosen.score,
        "in_sample_rms_um": chosen.in_sample["rms_um"] if chosen.in_sample else None,
        "cv_rms_um": chosen.cv["rms_um"] if chosen.cv else None,
        "runs": len(runs),
        "fit_dt_s": fit_dt,
    }
    assert chosen.result.model is not None
    model = chosen.result.model.replace(fit=stats)
    preds = {r.name: free_run(model, r) for r in runs}
    return Calibration(model, chosen, candidates, list(runs), fit_dt, reason, warnings, preds)
