"""Calibration with extra inputs (temperatures, spindle load, ambient): which to keep, and how.

Each candidate input enters as a static term or through a first-order lag (``TAUS_S``), relative
to the run's start (``reference="start"``) or to a stated value. The speed part keeps the time
constants of the best speed-only output-error form; its gains are refitted jointly with the input
gains (one least-squares solve per evaluation, the variable-projection idea of
:mod:`calibration.fitting`). Once the inputs are chosen, the time constants and each input's lag
are re-optimised with the inputs in, and kept if the held-out error does not grow.

Selection is forward stepwise, judged on held-out runs: at each step every remaining input at
every lag is scored by leave-one-run-out free-run RMS, and the best is added only if it cuts that
error by ``MIN_GAIN`` (3 %) and 0.02 um; it stops otherwise, or at ``MAX_INPUTS``. With 16
sensors that is at most 16 x 5 x folds small solves per step, and an input that only fits noise
does not survive the held-out run. Pure computation: no file I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from compensator.errors import CalibrationError
from compensator.inputs import AugmentedModel, InputTerm, first_order

from .calibrate import Calibration, residual_stats
from .data import Run
from .fitting import refine_theta, solve_output_error, speed_design

TAUS_S = (0.0, 300.0, 900.0, 1800.0, 3600.0)
MIN_GAIN = 0.03
MIN_GAIN_UM = 0.02
MAX_INPUTS = 6
COLLINEAR_R = 0.95


@dataclass(frozen=True)
class InputRun:
    """A calibration run with its input channels (same rows)."""

    run: Run
    inputs: dict[str, np.ndarray]


def unit_of(name: str) -> str:
    for suffix, unit in (("_c", "degC"), ("_k", "K"), ("_pct", "%"), ("_kw", "kW"), ("_w", "W"),
                         ("_a", "A"), ("_nm", "N m"), ("_bar", "bar")):
        if name.endswith(suffix):
            return unit
    return "1"


@dataclass
class InputFit:
    model: AugmentedModel
    speed_only_cv: dict[str, Any]
    augmented_cv: dict[str, Any]
    steps: list[dict[str, Any]]
    warnings: list[str] = field(default_factory=list)
    predictions: dict[str, np.ndarray] = field(default_factory=dict)

    def report(self) -> dict[str, Any]:
        return {
            "format": "thermocomp.input-selection/1",
            "inputs": [t.model_dump() for t in self.model.inputs],
            "speed_only_held_out": self.speed_only_cv,
            "with_inputs_held_out": self.augmented_cv,
            "steps": self.steps,
            "warnings": self.warnings,
        }


def _column(ir: InputRun, name: str, tau_s: float, reference: str, fixed: dict[str, float]) -> np.ndarray:
    u = ir.inputs[name]
    ref = u[0] if reference == "start" else fixed[name]
    drive = u - ref
    return first_order(drive, np.diff(ir.run.time_s, prepend=ir.run.time_s[0]), tau_s, float(drive[0]))


def fit_with_inputs(cal: Calibration, runs: Sequence[InputRun], names: Sequence[str], *,
                    reference: str = "start", fixed: dict[str, float] | None = None,
                    max_inputs: int = MAX_INPUTS, progress=None) -> InputFit:
    """Choose inputs among ``names`` on held-out runs and fit the augmented model.

    ``cal`` is the speed-only calibration of the same runs (its best output-error form gives the
    speed part's time constants and the fallback model).
    """
    say = progress or (lambda _m: None)
    if len(runs) < 2:
        raise CalibrationError("choosing inputs needs two runs or more: they are judged on held-out runs")
    if reference not in ("start", "fixed"):
        raise CalibrationError("input reference is 'start' or 'fixed'")
    fixed = dict(fixed or {})
    missing = [(n, ir.run.name) for ir in runs for n in names if n not in ir.inputs]
    if missing:
        n, r = missing[0]
        raise CalibrationError(f"{r}: no input column {n!r}")
    if reference == "fixed" and (lack := [n for n in names if n not in fixed]):
        raise CalibrationError(f"fixed reference needs a value for {', '.join(lack)}")
    for ir in runs:
        for n in names:
            if not np.isfinite(ir.inputs[n]).all():
                raise CalibrationError(f"{ir.run.name}: input {n} has non-finite values")
    oe = [c for c in cal.candidates if c.result.form.method == "oe" and c.result.model is not None
          and c.result.theta is not None and math.isfinite(c.score)]
    if not oe:
        raise CalibrationError("no output-error speed form to build on")
    base = min(oe, key=lambda c: c.score)
    form, theta = base.result.form, base.result.theta
    rs = [ir.run for ir in runs]
    # the speed design per run (held-out solves need the rows apart)
    parts = [speed_design(form, theta, [r]) for r in rs]
    xs = [p[0] for p in parts]
    ys = [p[1] for p in parts]
    cols = {(n, tau): [_column(ir, n, tau, reference, fixed) for ir in runs] for n in names for tau in TAUS_S}

    def held_out(chosen: Sequence[tuple[str, float]]) -> dict[str, Any]:
        res = []
        for i in range(len(rs)):
            tr = [j for j in range(len(rs)) if j != i]
            x = np.vstack([np.column_stack([xs[j], *[cols[c][j] for c in chosen]]) for j in tr])
            y = np.concatenate([ys[j] for j in tr])
            g, *_ = np.linalg.lstsq(x, y, rcond=None)
            xi = np.column_stack([xs[i], *[cols[c][i] for c in chosen]])
            res.append(ys[i] - xi @ g)
        return residual_stats(np.concatenate(res))

    warnings: list[str] = []
    # collinear candidates: their gains trade off, the selection keeps at most one of a group
    drives = {n: np.concatenate([ir.inputs[n] - (ir.inputs[n][0] if reference == "start" else fixed[n])
                                 for ir in runs]) for n in names}
    for a_i, a in enumerate(names):
        for b in names[a_i + 1:]:
            if np.std(drives[a]) > 0 and np.std(drives[b]) > 0:
                r = float(np.corrcoef(drives[a], drives[b])[0, 1])
                if abs(r) > COLLINEAR_R:
                    warnings.append(f"inputs {a} and {b} are collinear (r = {r:.3f}): their effects "
                                    "cannot be told apart; at most one is kept")
    flat = [n for n in names if np.std(drives[n]) == 0]
    for n in flat:
        warnings.append(f"input {n} never changes in these runs: it cannot be calibrated")

    chosen: list[tuple[str, float]] = []
    current = held_out([])
    speed_only_cv = dict(current)
    steps: list[dict[str, Any]] = [{"step": 0, "inputs": [], "held_out_rms_um": current["rms_um"],
                                    "note": f"speed only ({form.name}, its time constants kept)"}]
    while len(chosen) < max_inputs:
        best: tuple[float, str, float, dict[str, Any]] | None = None
        for n in names:
            if n in flat or any(n == c[0] for c in chosen):
                continue
            for tau in TAUS_S:
                say(f"trying {n} (tau {tau:g} s)")
                st = held_out([*chosen, (n, tau)])
                if best is None or st["rms_um"] < best[0]:
                    best = (st["rms_um"], n, tau, st)
        if best is None:
            break
        rms, n, tau, st = best
        gain = current["rms_um"] - rms
        if gain < max(MIN_GAIN * current["rms_um"], MIN_GAIN_UM):
            steps.append({"step": len(chosen) + 1, "stopped": True, "best_next": n, "tau_s": tau,
                          "held_out_rms_um": rms,
                          "note": f"adding {n} would cut the held-out error by {gain:.3f} um only "
                                  f"(< {MIN_GAIN:.0%} and {MIN_GAIN_UM} um): stop"})
            break
        chosen.append((n, tau))
        steps.append({"step": len(chosen), "added": n, "tau_s": tau, "held_out_rms_um": rms,
                      "note": f"{n} ({'static' if tau == 0 else f'lag {tau:g} s'}) cuts the held-out "
                              f"error from {current['rms_um']:.3f} to {rms:.3f} um"})
        current = st
    if not chosen:
        raise CalibrationError("no input improves the model on held-out runs: keep the speed-only model "
                               f"(held-out RMS {speed_only_cv['rms_um']:.3f} um)")

    # the speed part's time constants were the speed-only fit's, which had to explain what the
    # inputs now explain: re-optimise them with the inputs in, then each input's lag once more;
    # kept only if the held-out error does not grow
    say("refining the time constants with the inputs")
    stack = lambda sel: np.vstack([np.column_stack([cols[c][j] for c in sel]) for j in range(len(rs))])  # noqa: E731
    theta2 = refine_theta(form, theta, rs, stack(chosen))
    xs_old, ys_old = xs, ys
    parts2 = [speed_design(form, theta2, [r]) for r in rs]
    xs, ys = [p[0] for p in parts2], [p[1] for p in parts2]
    refined = list(chosen)
    for k, (n, _tau) in enumerate(refined):
        scores = [(held_out([*refined[:k], (n, tau), *refined[k + 1:]])["rms_um"], tau) for tau in TAUS_S]
        refined[k] = (n, min(scores)[1])
    st = held_out(refined)
    if st["rms_um"] <= current["rms_um"]:
        steps.append({"step": len(steps), "refined": True, "held_out_rms_um": st["rms_um"],
                      "note": "time constants re-optimised with the inputs; lags "
                              + ", ".join(f"{n} {'static' if tau == 0 else f'{tau:g} s'}" for n, tau in refined)})
        chosen, current, theta = refined, st, theta2
    else:
        xs, ys = xs_old, ys_old

    extra = np.vstack([np.column_stack([cols[c][j] for c in chosen]) for j in range(len(rs))])
    meta = {k: v for k, v in (("spindle_id", cal.model.spindle_id), ("machine_id", cal.model.machine_id),
                                ("created_utc", cal.model.created_utc)) if v is not None}
    res = solve_output_error(form, theta, rs, extra=extra, **meta)
    if res.model is None or res.extra_gains is None:
        raise CalibrationError(f"the speed part with inputs is not usable: {res.note}")
    terms = []
    for (n, tau), g in zip(chosen, res.extra_gains):
        allv = np.concatenate([ir.inputs[n] for ir in runs])
        span = float(np.ptp(allv)) or 1.0
        ref = float(np.mean([ir.inputs[n][0] for ir in runs])) if reference == "start" else fixed[n]
        terms.append(InputTerm(name=n, unit=unit_of(n), reference_mode=reference, reference=ref,
                               gain_um_per_unit=float(g), tau_s=float(tau),
                               valid_range=(float(allv.min()) - span, float(allv.max()) + span)))
    speed_model = res.model.replace(form=f"{form.name}+inputs", fit={"held_out_rms_um": current["rms_um"]})
    model = AugmentedModel(
        spindle_id=cal.model.spindle_id, machine_id=cal.model.machine_id, speed_model=speed_model,
        inputs=tuple(terms), fallback=cal.model, selection=steps, created_utc=cal.model.created_utc,
        fit={"speed_only_held_out_rms_um": speed_only_cv["rms_um"], "held_out_rms_um": current["rms_um"],
             "runs": len(rs), "base_form": form.name},
    )
    preds = {ir.run.name: model.simulate_um(ir.run.speed_rpm, ir.run.time_s, ir.inputs,
                                            float(ir.run.elongation_um[0])) for ir in runs}
    return InputFit(model, speed_only_cv, current, steps, warnings, preds)
