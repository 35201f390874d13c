"""``thermocomp fit``'s default method: every candidate judged by the same cycle folds, in free
run, and the best honest one chosen. Pure computation on in-memory logs: no file I/O.

Candidates (``docs/IDENTIFICATION.md`` says why):

- ``exp-baseline``: paper 001 eqs. 1-3 in dynamic form, one time constant chosen by CV, S∞
  quadratic in n. The bar every other candidate must clear.
- ``physical``: the output-error form ``speed-state+elastic`` of :mod:`calibration.fitting` (one
  thermal state whose dissipation depends on speed, plus an elastic term), refitted per fold.
- ``ridge``: :func:`calibration.ident.fit_ridge_cv` on speed alone (n, n² through a bank of
  first-order filters).
- ``ridge+inputs``: the same with the named inputs (temperatures...) through their own banks.
- ``paper-ols``: the paper's one-step OLS, scored in free run for the comparison; never chosen.

Folds: leave-one-cycle-out when the logs hold two cycles or more (:func:`ident.split_cycles`,
per file); otherwise :data:`BLOCKS` contiguous blocks of equal duration ("blocked"). Every
candidate free-runs each whole file from its start and is scored on the rows of the held-out
fold. A candidate is refused when its honest CV RMS (nested where its hyperparameters were
chosen by CV, else plain) is worse than the baseline's, or when its gains fail the sanity
bound. Among the speed-only candidates left, the lowest honest CV RMS wins, a simpler one when
within :data:`PARSIMONY`; the inputs are kept only when they beat that.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from compensator.errors import CalibrationError, ModelError
from compensator.model import ThermalModel

from . import closedloop, ident
from .ident import PARSIMONY  # a simpler candidate wins within it, as a larger alpha does
from .data import Run, resample
from .fitting import FORM_BY_NAME, fit_physical

BLOCKS = 4
"""Folds of a log that holds one cycle only: this many contiguous blocks of equal duration."""
PHYSICAL_FORM = "speed-state+elastic"
"""The output-error form entered as the physical candidate."""
MIN_FOLD_ROWS = 20


@dataclass(frozen=True)
class LogData:
    """One checked log: time [s], speed [rpm], measured elongation [um], input columns."""

    name: str
    time_s: np.ndarray
    speed_rpm: np.ndarray
    elongation_um: np.ndarray
    inputs: Mapping[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class Joined:
    """The logs end to end (time shifted so it keeps increasing), with file segments and folds."""

    time_s: np.ndarray
    speed_rpm: np.ndarray
    elongation_um: np.ndarray
    inputs: Mapping[str, np.ndarray]
    segments: tuple[tuple[int, int], ...]
    names: tuple[str, ...]
    cycles: tuple[tuple[int, int], ...]
    folds: tuple[tuple[int, int], ...]
    scheme: str
    cycle_lines: tuple[str, ...]


def join(logs: Sequence[LogData], input_names: Sequence[str] = ()) -> Joined:
    """Join the logs and find the folds: cycles per file, or blocks when there is one cycle."""
    if not logs:
        raise CalibrationError("no calibration logs")
    t_parts, s_parts, y_parts, segs, cycles, lines = [], [], [], [], [], []
    ins: dict[str, list[np.ndarray]] = {k: [] for k in input_names}
    offset, start = 0.0, 0
    for log in logs:
        t = np.asarray(log.time_s, float)
        dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
        shift = offset - t[0]
        t_parts.append(t + shift)
        s_parts.append(np.asarray(log.speed_rpm, float))
        y_parts.append(np.asarray(log.elongation_um, float))
        for k in input_names:
            if k not in log.inputs:
                raise CalibrationError(f"{log.name}: no column {k!r} for --inputs")
            ins[k].append(np.asarray(log.inputs[k], float))
        cyc = ident.split_cycles(t, log.speed_rpm)
        for line in ident.describe_cycles(t, log.speed_rpm, cyc):
            lines.append(f"{log.name}: {line}")
        cycles += [(a + start, b + start) for a, b in cyc]
        segs.append((start, start + t.size))
        start += t.size
        offset = float(t[-1] + shift + dt)
    tj = np.concatenate(t_parts)
    if len(cycles) >= 2:
        folds, scheme = tuple(cycles), "leave-one-cycle-out"
    else:
        edges = np.searchsorted(tj, np.linspace(tj[0], tj[-1], BLOCKS + 1)[1:-1])
        bounds = [0, *sorted(set(int(e) for e in edges)), tj.size]
        folds = tuple((a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a)
        scheme = f"blocked ({len(folds)} contiguous blocks of one cycle)"
        if len(folds) < 2 or min(b - a for a, b in folds) < MIN_FOLD_ROWS:
            raise CalibrationError(f"too few rows ({tj.size}) to validate: record a heat-up and a "
                                   "cool-down, at least a few hundred samples")
    return Joined(tj, np.concatenate(s_parts), np.concatenate(y_parts),
                  {k: np.concatenate(v) for k, v in ins.items()}, tuple(segs),
                  tuple(lg.name for lg in logs), tuple(cycles), folds, scheme, tuple(lines))


@dataclass
class Candidate:
    """One candidate and how it scored. ``honest_rms_um`` decides (nested when available)."""

    name: str
    family: str  # "speed", "inputs" or "reference"
    description: str
    cv_rms_um: float = math.inf
    cv_max_abs_um: float = math.inf
    nested_rms_um: float | None = None
    nested_max_abs_um: float | None = None
    folds_rms_um: list[float] = field(default_factory=list)
    in_sample_rms_um: float | None = None
    in_sample_max_abs_um: float | None = None
    accepted: bool = False
    refusals: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    model: Any = None
    details: dict[str, Any] = field(default_factory=dict)
    fit_cpu_s: float = 0.0
    held_out_residual_um: np.ndarray | None = None
    slowest_tau_s: float = 0.0

    @property
    def honest_rms_um(self) -> float:
        return self.nested_rms_um if self.nested_rms_um is not None else self.cv_rms_um

    def row(self) -> dict[str, Any]:
        def num(v: float | None) -> float | None:
            return None if v is None or not math.isfinite(v) else float(v)
        return {"name": self.name, "family": self.family, "description": self.description,
                "cv_rms_um": num(self.cv_rms_um), "cv_max_abs_um": num(self.cv_max_abs_um),
                "nested_rms_um": num(self.nested_rms_um), "nested_max_abs_um": num(self.nested_max_abs_um),
                "honest_rms_um": num(self.honest_rms_um), "folds_rms_um": [num(v) for v in self.folds_rms_um],
                "in_sample_rms_um": num(self.in_sample_rms_um),
                "in_sample_max_abs_um": num(self.in_sample_max_abs_um), "accepted": self.accepted,
                "refusals": list(self.refusals), "notes": list(self.notes), **self.details,
                "fit_cpu_s": round(self.fit_cpu_s, 3)}


def _from_ident(name: str, family: str, description: str, res: ident.IdentResult, j: Joined) -> Candidate:
    c = Candidate(name, family, description, res.cv_rms_um, res.cv_max_abs_um, res.nested_rms_um,
                  res.nested_max_abs_um, [f.rms_um for f in res.folds], fit_cpu_s=res.fit_cpu_s)
    pred = res.predict(j.time_s, j.speed_rpm, j.inputs if res.input_names else None, j.segments)
    c.in_sample_rms_um, c.in_sample_max_abs_um = ident.pooled_stats(j.elongation_um - pred)
    c.details = {"grid": res.grid.label, "alpha": res.alpha,
                 "states": len({t for t in (*res.grid.speed_taus_s, *res.grid.input_taus_s) if t > 0}),
                 "steady_range_um": res.steady_range_um()}
    c.notes += list(res.notes)
    c.refusals += [r for r in res.refusals if "baseline" not in r]  # judged below, one way for all
    c.held_out_residual_um = res.held_out_residual_um
    c.slowest_tau_s = max((*res.grid.speed_taus_s, *res.grid.input_taus_s))
    return c


def _runs_of(j: Joined, rows: np.ndarray, dt_s: float) -> list[Run]:
    """Contiguous stretches of ``rows`` within each file, as runs on a uniform grid."""
    runs = []
    for a, b in j.segments:
        for s, e in ident._stretches(rows[a:b]):
            if e - s >= MIN_FOLD_ROWS:
                lo, hi = a + s, a + e
                r = Run(f"{len(runs)}", j.time_s[lo:hi], j.speed_rpm[lo:hi], j.elongation_um[lo:hi])
                runs.append(resample(r, dt_s))
    return runs


def _free_run(model: ThermalModel, j: Joined) -> np.ndarray:
    """Each file from its first measured elongation, never re-anchored."""
    out = np.empty(j.time_s.size)
    with np.errstate(all="ignore"):
        for a, b in j.segments:
            out[a:b] = model.simulate_um(j.speed_rpm[a:b], j.time_s[a:b], None, float(j.elongation_um[a]))
    return out


def _physical(j: Joined, dt_s: float, meta: Mapping[str, Any]) -> Candidate:
    cpu0 = time.process_time()
    spec = FORM_BY_NAME[PHYSICAL_FORM]
    c = Candidate("physical", "speed", f"{PHYSICAL_FORM}: {spec.description} (output error)")
    res = np.full(j.time_s.size, np.nan)
    for a, b in j.folds:
        rows = np.ones(j.time_s.size, bool)
        rows[a:b] = False
        runs = _runs_of(j, rows, dt_s)
        fit = fit_physical(spec, runs, **meta) if runs else None
        if fit is None or fit.model is None:
            c.refusals.append(f"no stable fit without fold rows {a}..{b - 1}"
                              + (f" ({fit.note})" if fit is not None and fit.note else ""))
            c.fit_cpu_s = time.process_time() - cpu0
            return c
        res[a:b] = (j.elongation_um - _free_run(fit.model, j))[a:b]
    c.cv_rms_um, c.cv_max_abs_um = ident.pooled_stats(res)
    c.folds_rms_um = [f.rms_um for f in ident.fold_scores(res, j.folds)]
    c.held_out_residual_um = res
    full = fit_physical(spec, _runs_of(j, np.ones(j.time_s.size, bool), dt_s), **meta)
    if full.model is None:
        c.refusals.append(f"no stable fit on all rows ({full.note})")
    else:
        c.model = full.model
        c.in_sample_rms_um, c.in_sample_max_abs_um = ident.pooled_stats(j.elongation_um - _free_run(full.model, j))
        c.details = {"coefficients": full.coefficients}
        top = abs(full.model.steady_state_um(full.model.speed_range_rpm[1]))
        bound = ident.GAIN_BOUND * float(np.max(np.abs(j.elongation_um)))
        if not math.isfinite(top) or top > bound:
            c.refusals.append(f"steady elongation {top:.4g} um at the top speed is over "
                              f"{ident.GAIN_BOUND:g} x the largest measured")
    c.fit_cpu_s = time.process_time() - cpu0
    return c


def _paper(j: Joined) -> Candidate:
    cpu0 = time.process_time()
    c = Candidate("paper-ols", "reference", "paper 001 eqs. 11-12: OLS one step ahead on the "
                  "measured S[k-1], scored in free run (for comparison; never chosen)")
    try:
        cv = ident.paper_ols_cv(j.time_s, j.speed_rpm, j.elongation_um, j.folds)
        within = np.ones(j.time_s.size, bool)  # no regression row pairs the end of one log with the next
        within[[a for a, _ in j.segments[1:]]] = False
        fit = ident.fit_paper_ols(j.time_s, j.speed_rpm, j.elongation_um, within)
    except CalibrationError as err:
        c.refusals.append(str(err))
        return c
    c.cv_rms_um, c.cv_max_abs_um = cv["cv_rms_um"], cv["cv_max_abs_um"]
    c.folds_rms_um = [f.rms_um for f in cv["folds"]]
    with np.errstate(all="ignore"):
        pred = fit.predict(j.time_s, j.speed_rpm, float(j.elongation_um[0]))
    c.in_sample_rms_um, c.in_sample_max_abs_um = ident.pooled_stats(j.elongation_um - pred)
    c.details = {"a": fit.a, "one_step_r2": fit.one_step_r2, "a_per_fold": cv["a"]}
    if fit.a >= 1:
        c.notes.append(f"pole a = {fit.a:.6f} >= 1: its free run diverges")
    c.fit_cpu_s = time.process_time() - cpu0
    return c


@dataclass
class Identification:
    joined: Joined
    candidates: list[Candidate]
    chosen: Candidate
    model: Any
    reason: str
    warnings: list[str]
    fit_cpu_s: float
    derived: list[dict[str, Any]] = field(default_factory=list)
    closed_loop: closedloop.Plan | None = None

    def free_run_um(self) -> dict[str, np.ndarray]:
        """The model's in-sample free run over each log (by name), from its first measured
        elongation (at rest when the first row is not measured)."""
        j, m = self.joined, self.model
        out = {}
        with np.errstate(all="ignore"):
            for name, (a, b) in zip(j.names, j.segments):
                inputs = {n: v[a:b] for n, v in j.inputs.items()} if m.input_names else None
                y0 = float(j.elongation_um[a])
                out[name] = m.simulate_um(j.speed_rpm[a:b], j.time_s[a:b], inputs,
                                          y0 if math.isfinite(y0) else None)
        return out

    def report(self) -> dict[str, Any]:
        j = self.joined
        return {
            "format": "thermocomp.fit-report/2",
            "method": "cycles",
            "cycle_rule": ident.CYCLE_RULE,
            "cycles": list(j.cycle_lines),
            "scored_by": f"{j.scheme} free run",
            "folds": [[int(a), int(b)] for a, b in j.folds],
            "logs": list(j.names),
            "candidates": [c.row() for c in self.candidates],
            "chosen": self.chosen.name,
            "model_form": self.model.form,
            "reason": self.reason,
            "derived": self.derived,
            "closed_loop": None if self.closed_loop is None else self.closed_loop.report(),
            "warnings": self.warnings,
            "fit_cpu_s": round(self.fit_cpu_s, 2),
        }


def identify(logs: Sequence[LogData], input_names: Sequence[str] = (), *,
             units: Mapping[str, str] | None = None, physical: bool = True, nested: bool = True,
             probe_target_um: float | None = closedloop.DEFAULT_TARGET_UM,
             probe_every_s: float | None = None,
             progress: Callable[[str], None] | None = None, **meta: Any) -> Identification:
    """Fit every candidate, score it on the same folds in free run, choose, and build the model.

    ``meta`` (spindle_id, machine_id, created_utc) goes into the model. Raises
    :class:`CalibrationError` when nothing can be validated.
    """
    cpu0 = time.process_time()
    say = progress or (lambda _m: None)
    names = tuple(sorted(set(input_names)))
    j = join(logs, names)
    dt_s = float(np.median(np.diff(j.time_s)))
    warnings: list[str] = []
    if j.scheme.startswith("blocked"):
        warnings.append("the logs hold one heat-up/cool-down cycle: scored on contiguous blocks of it; "
                        "record another cycle for a leave-one-cycle-out score")
    grid_speed = ident.auto_grid(j.time_s, j.speed_rpm, j.cycles, False)
    grid_inputs = ident.auto_grid(j.time_s, j.speed_rpm, j.cycles, True)
    common = dict(cycles=j.folds, segments=j.segments, nested=nested and len(j.folds) >= 3)

    say("fitting the exponential baseline")
    base = ident.fit_ridge_cv(j.time_s, j.speed_rpm, j.elongation_um,
                              grids=[ident.TauGrid((tau,)) for tau in ident.BASELINE_TAUS_S
                                     if tau >= dt_s], alphas=(0.0,), rule="min", **common)
    cands = [_from_ident("exp-baseline", "speed", "paper 001 eqs. 1-3, dynamic: one time constant "
                         "chosen by CV, S∞ quadratic in n", base, j)]
    cands[0].details["tau_s"] = base.grid.speed_taus_s[0]
    if physical:
        say(f"fitting {PHYSICAL_FORM} per fold")
        cands.append(_physical(j, dt_s, meta))
    say("fitting ridge (speed)")
    ridge = ident.fit_ridge_cv(j.time_s, j.speed_rpm, j.elongation_um, grids=[grid_speed], **common)
    cands.append(_from_ident("ridge", "speed", "ridge over n, n² through first-order filter banks; "
                             "alpha by CV", ridge, j))
    ridge_in = None
    if names:
        say(f"fitting ridge with {len(names)} input(s)")
        ridge_in = ident.fit_ridge_cv(j.time_s, j.speed_rpm, j.elongation_um, j.inputs,
                                      grids=[grid_inputs], **common)
        cands.append(_from_ident("ridge+inputs", "inputs", f"ridge over n, n² and {len(names)} "
                                 "input(s) through filter banks; alpha by CV", ridge_in, j))
    say("scoring the paper's OLS")
    cands.append(_paper(j))

    # with probes planned, a candidate is judged by its closed loop on held-out cycles
    plans: dict[str, closedloop.Plan | None] = {}
    intervals = tuple(sorted({*closedloop.INTERVALS_S, *([probe_every_s] if probe_every_s else [])}))
    target = probe_target_um if probe_target_um is not None else closedloop.DEFAULT_TARGET_UM

    def loop_of(c: Candidate) -> closedloop.Plan | None:
        if c.name not in plans:
            tau = c.slowest_tau_s or (max(c.model.time_constants_s(0.0)) if c.model is not None else 0.0)
            ok = c.held_out_residual_um is not None and tau > 0 and len(j.folds) >= 2
            plans[c.name] = closedloop.plan(j.time_s, c.held_out_residual_um, j.folds, tau, target,
                                            intervals) if ok else None
            if plans[c.name] is not None:
                c.details["closed_loop_rms_um"] = {f"{r['interval_s']:.0f}": round(r["rms_um"], 4)
                                                   for r in plans[c.name].table[1:]}
        return plans[c.name]

    def score(c: Candidate) -> float:
        if probe_every_s is None:
            return c.honest_rms_um
        p = loop_of(c)
        return math.inf if p is None else p.rms_at(probe_every_s)

    what = "CV RMS" if probe_every_s is None else f"closed-loop RMS (a probe every {probe_every_s:g} s)"
    if probe_every_s is not None:
        say(f"scoring every candidate in closed loop, a probe every {probe_every_s:g} s")
    bar = score(cands[0])
    for c in cands:
        if c.family == "reference":
            continue
        if c is not cands[0] and score(c) > bar:
            c.refusals.append(f"{what} {score(c):.2f} um is worse than the exponential "
                              f"baseline's {bar:.2f} um")
        c.accepted = not c.refusals

    # build the models of the candidates the choice may need
    for c, res in ((cands[0], base), (next(c for c in cands if c.name == "ridge"), ridge)):
        if c.accepted:
            try:
                c.model = res.to_model(c.name, fit={}, **meta)
            except ModelError as err:
                c.accepted, c.refusals = False, [*c.refusals, f"model refused: {err}"]
    speed = [c for c in cands if c.family == "speed" and c.accepted and c.model is not None]
    if not speed:
        raise CalibrationError("no speed-only candidate passed the checks: "
                               + "; ".join(f"{c.name}: {', '.join(c.refusals)}" for c in cands
                                           if c.family == "speed"))
    best = min(speed, key=score)
    chosen = next(c for c in speed if score(c) <= score(best) * (1 + PARSIMONY))
    basis = "nested " if chosen.nested_rms_um is not None else ""
    if probe_every_s is None:
        reason = f"{chosen.name} has the lowest {basis}{j.scheme} free-run RMS among the speed-only candidates, "
    else:
        reason = (f"{chosen.name} has the lowest {j.scheme} {what} among the speed-only candidates "
                  f"({', '.join(f'{c.name} {score(c):.2f} um' for c in speed)}); its {basis}free-run RMS ")
    reason += (f"{chosen.honest_rms_um:.2f} um"
               + (f" (within {PARSIMONY:.0%} of {best.name}, and simpler)" if chosen is not best else ""))
    model = _with_fit(chosen, j, reason)
    final = chosen
    if ridge_in is not None:
        c_in = next(c for c in cands if c.name == "ridge+inputs")
        model, final, reason = with_inputs_or_not(c_in, chosen, ridge_in, model, j, reason, warnings,
                                                  score=score, what=what, n_inputs=len(names),
                                                  units=units, meta=meta)
    paper = cands[-1]
    if math.isfinite(paper.cv_rms_um):
        reason += f"; the paper's OLS scores {paper.cv_rms_um:.2f} um"
    derived = _derived(final, ridge_in if final.name == "ridge+inputs" else ridge if final.name == "ridge"
                       else None, j)
    loop = None
    if probe_target_um is not None:
        say("planning the closed loop (probe intervals)")
        loop = loop_of(final)
    if loop is not None:
        fb = model.fallback
        fb_loop = loop_of(chosen) if fb is not None else None
        update: dict[str, Any] = {"fit": {**model.fit, "observer": loop.observer.model_dump()}}
        if fb is not None and fb_loop is not None:  # the fallback keeps the observer fitted to it
            update["fallback"] = fb.model_copy(update={"fit": {**fb.fit, "observer": fb_loop.observer.model_dump()}})
        model = model.model_copy(update=update)
    return Identification(j, cands, final, model, reason, warnings, time.process_time() - cpu0, derived,
                          loop)


def with_inputs_or_not(c_in: Candidate, chosen: Candidate, ridge_in: Any, model: Any, j: Joined,
                       reason: str, warnings: list[str], *, score: Callable[[Candidate], float], what: str,
                       n_inputs: int, units: Any, meta: Mapping[str, Any]) -> tuple[Any, Candidate, str]:
    """The model with inputs when it beats the chosen speed-only one by ``score`` (``what`` names
    the figure), with that one as its fallback; else the speed-only one, and why. Returns
    (model, the candidate chosen, the reason); refusals go to ``c_in`` and ``warnings``."""
    if c_in.accepted and score(c_in) >= score(chosen):
        c_in.accepted = False
        c_in.refusals.append(f"no better than speed only ({what} {score(c_in):.2f} um against "
                             f"{score(chosen):.2f} um)")
    if c_in.accepted:
        try:
            c_in.model = ridge_in.to_model("ridge+inputs", units=units, fallback=model, fit={}, **meta)
        except ModelError as err:
            c_in.accepted, c_in.refusals = False, [*c_in.refusals, f"model refused: {err}"]
    if not c_in.accepted:
        warnings.append(f"the inputs did not help: {'; '.join(c_in.refusals)}")
        return model, chosen, reason + f"; inputs refused: {'; '.join(c_in.refusals)}"
    reason += (f"; with inputs {c_in.honest_rms_um:.2f} um: the model uses {n_inputs} input(s), "
               f"{chosen.name} stands in when one fails")
    return _with_fit(c_in, j, reason), c_in, reason


def _with_fit(c: Candidate, j: Joined, reason: str) -> Any:
    fit = {"method": c.name, "scored_by": f"{j.scheme} free run", "folds": len(j.folds),
           "cv_rms_um": round(c.cv_rms_um, 4), "cv_max_abs_um": round(c.cv_max_abs_um, 4),
           "folds_rms_um": [round(v, 4) for v in c.folds_rms_um], "reason": reason}
    if c.nested_rms_um is not None:
        fit["nested_rms_um"] = round(c.nested_rms_um, 4)
    if "alpha" in c.details:
        fit["alpha"] = c.details["alpha"]
        fit["grid"] = c.details["grid"]
    return c.model.model_copy(update={"fit": fit})


def _derived(c: Candidate, res: ident.IdentResult | None, j: Joined) -> list[dict[str, Any]]:
    """HAC (Newey-West) standard errors of derived quantities of a ridge fit: the steady rise at
    a few speeds and each input's total steady sensitivity. Single bank gains trade off against
    each other, so they are not reported."""
    if res is None:
        return []
    try:
        cov = ident.hac_covariance(res, j.time_s, j.speed_rpm, j.elongation_um,
                                   j.inputs if res.input_names else None)
    except (np.linalg.LinAlgError, ValueError):
        return []
    cov = np.nan_to_num(cov)
    ns = len(res.grid.speed_taus_s)
    out = []
    for frac in (0.5, 1.0):
        rpm = res.speed_max_rpm * frac
        n = rpm / 1000.0
        w = np.zeros(res.gains.size)
        w[:ns] = n
        w[ns:2 * ns] = n * n
        out.append({"quantity": f"steady rise at {rpm:.0f} rpm", "unit": "um",
                    "value": float(w @ res.gains), "hac_stderr": float(math.sqrt(max(w @ cov @ w, 0.0)))})
    ni = len(res.grid.input_taus_s)
    for i, nm in enumerate(res.input_names):
        w = np.zeros(res.gains.size)
        w[2 * ns + i * ni: 2 * ns + (i + 1) * ni] = 1.0
        out.append({"quantity": f"steady sensitivity to {nm}", "unit": "um per unit",
                    "value": float(w @ res.gains), "hac_stderr": float(math.sqrt(max(w @ cov @ w, 0.0)))})
    return out
