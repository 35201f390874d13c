"""``thermocomp fit`` on sparse targets: the elongation measured on some rows only (a journal
export, ``thermocomp journal export``: the probe measurements, NaN on the other rows).

The cycles method (:mod:`calibration.identify`) needs no change of idea, only of rows: the speed
(and every input) is known on every row, so the cycles are still cut from the speed
(:func:`calibration.ident.split_cycles`) and the filter banks still run over every row in free run;
the gains are fitted, and every candidate scored, on the **measured rows** only. A fold (a cycle,
or a block of a one-cycle log) without a measurement is run through but neither fitted nor
scored. On a log measured on every row this gives :func:`calibration.ident.fit_ridge_cv`'s
figures (the same folds, rule and α grid; the pooled CV error is the mean over the scored rows).

What needs the elongation on every row is left out, and the report says so: the physical
output-error form (it fits on a resampled grid), the paper's one-step OLS (it regresses on the
previous sample), the closed-loop plan (it simulates probes on a dense held-out residual) and the
HAC standard errors (their lags are rows one period apart). Pure computation: no file I/O.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from compensator.errors import CalibrationError, ModelError
from compensator.statespace import GAIN_BOUND

from . import ident
from .data import MIN_MEASURED_ROWS
from .identify import (
    Candidate,
    Identification,
    Joined,
    LogData,
    _with_fit,
    join,
    with_inputs_or_not,
)

Folds = Sequence[tuple[int, int]]


def _cv(x: np.ndarray, y: np.ndarray, measured: np.ndarray, folds: Folds, alphas: Sequence[float],
        train: np.ndarray | None = None) -> np.ndarray:
    """Held-out residuals [um] (rows, alphas) of leave-one-fold-out ridge fitted on the measured
    rows (within ``train``); NaN on every row not measured or in no fold."""
    base = measured if train is None else measured & train
    res = np.full((y.size, len(alphas)), np.nan)
    for a, b in folds:
        tr = base.copy()
        tr[a:b] = False
        if tr.sum() < 2:
            raise CalibrationError(f"rows {a}..{b - 1} held out leave fewer than two measured rows to fit on")
        g, c = ident._ridge_path(x[tr], y[tr], alphas)
        rows = a + np.flatnonzero(measured[a:b])
        res[rows] = y[rows, None] - (x[rows] @ g + c)
    return res


def _pooled_mse(res: np.ndarray, measured: np.ndarray, folds: Folds) -> np.ndarray:
    """Mean square [um²] per alpha over the measured rows of ``folds``; inf where not finite."""
    rows = np.concatenate([a + np.flatnonzero(measured[a:b]) for a, b in folds])
    with np.errstate(over="ignore", invalid="ignore"):
        mse = np.mean(res[rows] ** 2, axis=0)
    return np.where(np.isfinite(mse), mse, np.inf)


def _select(bank: ident._Bank, y: np.ndarray, measured: np.ndarray, configs: Sequence[ident._Config],
            folds: Folds, train: np.ndarray | None = None, rule: str = "parsimony") -> tuple[int, float]:
    """(config index, alpha) by leave-one-fold-out error on the measured rows, with the rules of
    :func:`calibration.ident._select`: ``parsimony`` (the simplest config, then its largest
    alpha, within :data:`calibration.ident.PARSIMONY` of the best) or ``min``."""
    pooled = [_pooled_mse(_cv(bank.design(c.grid, c.names), y, measured, folds, c.alphas, train),
                          measured, folds) for c in configs]
    best = min(float(p.min()) for p in pooled)
    limit = best if rule == "min" else best * (1 + ident.PARSIMONY) ** 2
    for k, (cfg, p) in enumerate(zip(configs, pooled)):
        ok = np.flatnonzero(p <= limit)
        if ok.size:
            return k, cfg.alphas[int(ok[np.argmax(np.asarray(cfg.alphas)[ok])])]
    raise CalibrationError("no configuration could be scored")  # unreachable: best is one of them


def _stats(residual: np.ndarray) -> tuple[float, float]:
    """RMS and max |residual| [um] over the rows that have one (a measured row)."""
    r = residual[~np.isnan(residual)]
    return ident.pooled_stats(r) if r.size else (math.inf, math.inf)


def fit_ridge_sparse(time_s: Any, speed_rpm: Any, elongation_um: Any,
                     inputs: Mapping[str, Any] | None = None, *, folds: Folds,
                     grids: Sequence[ident.TauGrid], alphas: Sequence[float] = ident.DEFAULT_ALPHAS,
                     nested: bool = False, rule: str = "parsimony",
                     segments: Sequence[tuple[int, int]] | None = None) -> ident.IdentResult:
    """:func:`calibration.ident.fit_ridge_cv` with the elongation [um] NaN where not measured:
    the banks over every row, the gains fitted and scored on the measured rows of ``folds``
    (each must hold one; two folds at least). Its refusals: the gain bound only (the baseline is
    judged by the caller)."""
    cpu0 = time.process_time()
    t = ident._times(time_s)
    sp = ident._series("speed_rpm", speed_rpm, t.size)
    y = np.asarray(elongation_um, dtype=float)
    if y.shape != t.shape or np.isinf(y).any():
        raise CalibrationError("elongation_um: one value per row, a number or NaN (not measured)")
    measured = np.isfinite(y)
    folds = tuple(folds)
    if len(folds) < 2 or any(not measured[a:b].any() for a, b in folds):
        raise CalibrationError("two folds or more, each with a measured row, are needed to validate")
    names = tuple(sorted(inputs)) if inputs else ()
    dt_s = float(np.median(np.diff(t)))
    for g in grids:
        ident._validate_grid(g, dt_s)
        if names and not g.input_taus_s:
            raise CalibrationError(f"grid {g.label} has no input bank")
    drives = ident.speed_terms(sp)
    refs: dict[str, float] = {}
    ranges: dict[str, tuple[float, float]] = {}
    trained: dict[str, tuple[float, float]] = {}
    for nm in names:
        u = ident._series(nm, inputs[nm], t.size)  # type: ignore[index]
        refs[nm] = float(u.mean())
        lo, hi = float(u.min()), float(u.max())
        ranges[nm], trained[nm] = (lo - (hi - lo), hi + (hi - lo)), (lo, hi)
        drives[f"in:{nm}"] = u - refs[nm]
    bank = ident._Bank(t, drives, segments)
    y0 = np.where(measured, y, 0.0)  # never read off the measured rows; keeps the arithmetic finite
    configs = [ident._Config(g, tuple(alphas), names) for g in grids]
    k, alpha = _select(bank, y0, measured, configs, folds, rule=rule)
    cfg = configs[k]
    x = bank.design(cfg.grid, names)
    res = _cv(x, y0, measured, folds, (alpha,))[:, 0]
    res[~measured] = np.nan
    fold_scores = tuple(ident.FoldScore(i, a, b, *_stats(res[a:b])) for i, (a, b) in enumerate(folds, 1))
    cv_rms, cv_max = _stats(res)
    nested_folds = nested_rms = nested_max = None
    outer = None
    if nested and len(folds) >= 3:
        outer = np.full(t.size, np.nan)
        for i, (a, b) in enumerate(folds):
            inner = [f for j, f in enumerate(folds) if j != i]
            mask = np.ones(t.size, bool)
            mask[a:b] = False
            ki, al = _select(bank, y0, measured, configs, inner, mask, rule=rule)
            xi = bank.design(configs[ki].grid, names)
            tr = measured & mask
            g, c = ident._ridge_path(xi[tr], y0[tr], (al,))
            rows = a + np.flatnonzero(measured[a:b])
            outer[rows] = y0[rows] - (xi[rows] @ g[:, 0] + c[0])
        nested_folds = tuple(ident.FoldScore(i, a, b, *_stats(outer[a:b])) for i, (a, b) in enumerate(folds, 1))
        nested_rms, nested_max = _stats(outer)
    g, c = ident._ridge_path(x[measured], y0[measured], (alpha,))
    gains, intercept = g[:, 0], float(c[0])
    ns = len(cfg.grid.speed_taus_s)
    result = ident.IdentResult(
        grid=cfg.grid, input_names=names, references=refs, intercept_um=intercept,
        speed_gains_um=gains[: 2 * ns].reshape(2, ns),
        input_gains_um=gains[2 * ns:].reshape(len(names), len(cfg.grid.input_taus_s)),
        alpha=alpha, cycles=folds, folds=fold_scores, cv_rms_um=cv_rms, cv_max_abs_um=cv_max,
        speed_max_rpm=float(np.abs(sp).max()), valid_ranges=ranges,
        max_measured_um=float(np.abs(y[measured]).max()), nested_folds=nested_folds,
        nested_rms_um=nested_rms, nested_max_abs_um=nested_max, fitted_dt_s=dt_s,
        segments=tuple(segments) if segments else ((0, int(t.size)),), trained_ranges=trained,
        held_out_residual_um=outer if outer is not None else res)
    refusals, notes = [], []
    steady = result.steady_range_um()
    if steady > GAIN_BOUND * result.max_measured_um:
        refusals.append(f"the gains imply a steady elongation of {steady:.0f} um, over {GAIN_BOUND:g} x "
                        f"the largest measured ({result.max_measured_um:.1f} um)")
    if alpha in (alphas[0], alphas[-1]) and len(alphas) > 1:
        notes.append(f"alpha {alpha:.3g} is at the end of the grid tried")
    if nested and len(folds) < 3:
        notes.append("nested cross-validation needs three folds or more: not done")
    return replace(result, accepted=not refusals, refusals=tuple(refusals), notes=tuple(notes),
                   fit_cpu_s=time.process_time() - cpu0)


def _candidate(name: str, family: str, description: str, res: ident.IdentResult, j: Joined,
               measured: np.ndarray) -> Candidate:
    c = Candidate(name, family, description, res.cv_rms_um, res.cv_max_abs_um, res.nested_rms_um,
                  res.nested_max_abs_um, [f.rms_um for f in res.folds], fit_cpu_s=res.fit_cpu_s)
    pred = res.predict(j.time_s, j.speed_rpm, j.inputs if res.input_names else None, j.segments)
    c.in_sample_rms_um, c.in_sample_max_abs_um = _stats(np.where(measured, j.elongation_um - pred, np.nan))
    c.details = {"grid": res.grid.label, "alpha": res.alpha,
                 "states": len({t for t in (*res.grid.speed_taus_s, *res.grid.input_taus_s) if t > 0}),
                 "steady_range_um": res.steady_range_um()}
    c.notes += list(res.notes)
    c.refusals += list(res.refusals)
    c.held_out_residual_um = res.held_out_residual_um
    c.slowest_tau_s = max((*res.grid.speed_taus_s, *res.grid.input_taus_s))
    return c


def identify_sparse(logs: Sequence[LogData], input_names: Sequence[str] = (), *,
                    units: Mapping[str, str] | None = None, nested: bool = True,
                    progress: Callable[[str], None] | None = None, **meta: Any) -> Identification:
    """:func:`calibration.identify.identify` for logs whose elongation is NaN where not measured:
    the exponential baseline, ridge and ridge with inputs, fitted and scored on the measured
    rows of the same cycle folds (see the module's docstring), chosen by the same rules."""
    cpu0 = time.process_time()
    say = progress or (lambda _m: None)
    names = tuple(sorted(set(input_names)))
    j = join(logs, names)
    measured = np.isfinite(j.elongation_um)
    if measured.sum() < MIN_MEASURED_ROWS:
        raise CalibrationError(f"the elongation is measured on {int(measured.sum())} rows; a calibration "
                               f"needs at least {MIN_MEASURED_ROWS}")
    folds = tuple((a, b) for a, b in j.folds if measured[a:b].any())
    unit = "cycle" if j.scheme == "leave-one-cycle-out" else "block"
    if len(folds) < 2:
        raise CalibrationError(f"the {int(measured.sum())} measurements fall in one {unit} of {len(j.folds)}: "
                               f"nothing to validate on; measure in another {unit} too")
    dropped = len(j.folds) - len(folds)
    j = replace(j, folds=folds, scheme=f"{j.scheme} (on the measured rows)")
    dt_s = float(np.median(np.diff(j.time_s)))
    warnings = [(f"sparse targets: fitted and scored on the {int(measured.sum())} measured rows of "
                 f"{measured.size} (the cycles and the free run on every row); the physical form, the "
                 "paper's OLS, the closed-loop plan and the HAC standard errors need the elongation on "
                 "every row and are left out")]
    if dropped:
        warnings.append(f"{dropped} {unit}(s) without a measurement: run through, not fitted or scored")
    if unit == "block":
        warnings.append("the logs hold one heat-up/cool-down cycle: scored on contiguous blocks of it; "
                        "record another cycle for a leave-one-cycle-out score")
    y = j.elongation_um
    common: dict[str, Any] = {"folds": folds, "segments": j.segments, "nested": nested and len(folds) >= 3}
    say("fitting the exponential baseline (measured rows)")
    base = fit_ridge_sparse(j.time_s, j.speed_rpm, y, grids=[ident.TauGrid((tau,)) for tau in
                                                             ident.BASELINE_TAUS_S if tau >= dt_s],
                            alphas=(0.0,), rule="min", **common)
    cands = [_candidate("exp-baseline", "speed", "paper 001 eqs. 1-3, dynamic: one time constant "
                        "chosen by CV, S∞ quadratic in n", base, j, measured)]
    cands[0].details["tau_s"] = base.grid.speed_taus_s[0]
    say("fitting ridge (speed, measured rows)")
    ridge = fit_ridge_sparse(j.time_s, j.speed_rpm, y,
                             grids=[ident.auto_grid(j.time_s, j.speed_rpm, j.cycles, False)], **common)
    cands.append(_candidate("ridge", "speed", "ridge over n, n² through first-order filter banks; "
                            "alpha by CV", ridge, j, measured))
    ridge_in = None
    if names:
        say(f"fitting ridge with {len(names)} input(s) (measured rows)")
        ridge_in = fit_ridge_sparse(j.time_s, j.speed_rpm, y, j.inputs,
                                    grids=[ident.auto_grid(j.time_s, j.speed_rpm, j.cycles, True)], **common)
        cands.append(_candidate("ridge+inputs", "inputs", f"ridge over n, n² and {len(names)} input(s) "
                                "through filter banks; alpha by CV", ridge_in, j, measured))

    bar = cands[0].honest_rms_um
    for c in cands[1:]:
        if c.honest_rms_um > bar:
            c.refusals.append(f"CV RMS {c.honest_rms_um:.2f} um is worse than the exponential "
                              f"baseline's {bar:.2f} um")
    for c in cands:
        c.accepted = not c.refusals
    for c, res in ((cands[0], base), (cands[1], ridge)):
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
    best = min(speed, key=lambda c: c.honest_rms_um)
    chosen = next(c for c in speed if c.honest_rms_um <= best.honest_rms_um * (1 + ident.PARSIMONY))
    basis = "nested " if chosen.nested_rms_um is not None else ""
    reason = (f"{chosen.name} has the lowest {basis}{j.scheme} free-run RMS among the speed-only "
              f"candidates, {chosen.honest_rms_um:.2f} um"
              + (f" (within {ident.PARSIMONY:.0%} of {best.name}, and simpler)" if chosen is not best else ""))
    model = _with_fit(chosen, j, reason)
    final = chosen
    if ridge_in is not None:
        model, final, reason = with_inputs_or_not(cands[2], chosen, ridge_in, model, j, reason, warnings,
                                                  score=lambda c: c.honest_rms_um, what="CV RMS",
                                                  n_inputs=len(names), units=units, meta=meta)
    return Identification(j, cands, final, model, reason, warnings, time.process_time() - cpu0)
