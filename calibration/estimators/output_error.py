"""The physical candidate: output-error forms of the thermal model (paper 001's state with
speed-dependent dissipation, an elastic term, one or two states), fitted in free run. The
identification enters :data:`PHYSICAL_FORM`, refitted per fold (:func:`candidate`).

Output-error fitting uses variable projection: for fixed time constants the free-run output is
linear in every gain, so each evaluation filters the speed powers through each state (one pass
each) and solves one least-squares problem; an outer search covers the one or two nonlinear
parameters. Long logs are searched on a coarser grid, then the gains solved on the full one
(:func:`fit_physical`). The free run covers every row of a uniform grid, the least squares only
the measured ones, so a sparse log (a tool setter's stops) fits the same forms. Every fit runs
each segment from its start, at rest unless its first row was measured, and hides the held-out
rows' targets (:func:`runs_of`).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from compensator.errors import CalibrationError, ModelError
from compensator.model import ThermalModel, ThermalStateCoefficients, filter_state
from compensator.statespace import GAIN_BOUND

from .. import folds as fl
from ..candidate import Candidate
from ..dataset import Dataset
from ..metrics import fold_scores, pooled_stats
from ..runs import Run, resample


@dataclass(frozen=True)
class FormSpec:
    """A candidate model form."""

    name: str
    description: str
    method: str  # "oe": output error
    n_states: int = 1
    speed_state: bool = False
    elastic: bool = False


FORMS: tuple[FormSpec, ...] = (
    FormSpec("paper-oe", "paper's form, refined on free-run (output) error", "oe"),
    FormSpec(
        "speed-state", "paper's form + speed x state dissipation (b5*n*S)", "oe", speed_state=True
    ),
    FormSpec("elastic", "paper's form + instantaneous elastic e1*n + e2*n^2", "oe", elastic=True),
    FormSpec("two-state", "two thermal states (fast and slow)", "oe", n_states=2),
    FormSpec(
        "two-state+elastic", "two thermal states + elastic term", "oe", n_states=2, elastic=True
    ),
    FormSpec(
        "speed-state+elastic",
        "speed x state dissipation + elastic term",
        "oe",
        speed_state=True,
        elastic=True,
    ),
)
FORM_BY_NAME = {f.name: f for f in FORMS}


@dataclass
class FitResult:
    """A fitted candidate; ``model`` is None when the fit failed or is unstable."""

    form: FormSpec
    model: ThermalModel | None
    coefficients: list[dict[str, float | str | None]] = field(default_factory=list)
    one_step_r2: float | None = None
    note: str = ""
    theta: np.ndarray | None = None  # nonlinear parameters of an output-error fit
    extra_gains: np.ndarray | None = None  # gains of extra columns (input terms), with
    extra_stderr: np.ndarray | None = None  # their standard errors


# -- helpers -----------------------------------------------------------------------


def _n_max_krpm(runs: Sequence[Run]) -> float:
    return max(float(r.n_krpm.max()) for r in runs)


def _speed_range(runs: Sequence[Run]) -> tuple[float, float]:
    return (0.0, max(float(np.abs(r.speed_rpm).max()) for r in runs))


def _fit_dt(runs: Sequence[Run]) -> float:
    return float(np.median([r.median_dt_s for r in runs]))


def _ols(x: np.ndarray, y: np.ndarray):
    import statsmodels.api as sm

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return sm.OLS(y, x).fit()


def _response(d0: float, d1: float, power: int, run: Run) -> np.ndarray:
    g = [0.0, 0.0, 0.0, 0.0]
    g[power] = 1.0
    st = ThermalStateCoefficients(
        dissipation_per_s=(d0, d1), generation_um_per_s=(g[0], g[1], g[2], g[3])
    )
    return filter_state(st, run.n_krpm, run.dt_s, 0.0)


def _decay(d0: float, d1: float, run: Run) -> np.ndarray:
    st = ThermalStateCoefficients(dissipation_per_s=(d0, d1), generation_um_per_s=(0, 0, 0, 0))
    return filter_state(st, run.n_krpm, run.dt_s, 1.0)


# -- output-error forms -------------------------------------------------------------


def _design(form: FormSpec, theta: np.ndarray, runs: Sequence[Run], n_max: float):
    """Columns of the free-run output, linear in the gains, for nonlinear params theta."""
    states = _states_from_theta(form, theta, n_max)
    cols_per_run = []
    for r in runs:
        cols = []
        for j, (d0, d1) in enumerate(states):
            for p in _powers(j):
                cols.append(_response(d0, d1, p, r))
        if form.elastic:
            cols += [r.n_krpm, r.n_krpm**2]
        cols_per_run.append(cols)
    return np.vstack([np.column_stack(c) for c in cols_per_run]), len(cols_per_run[0]), states


def _initial_response(states: list[tuple[float, float]], runs: Sequence[Run]) -> np.ndarray:
    """Free decay of each run's first measured elongation, split evenly over the states.

    Fixed, not fitted: a fitted initial state lets a slow state hide a drift
    that the free run then cannot reproduce.
    """
    parts = []
    for r in runs:
        s0 = float(r.elongation_um[0])
        s0 = (
            s0 if math.isfinite(s0) else 0.0
        )  # a sparse log starts at rest, as the free run scores it
        parts.append(sum(_decay(d0, d1, r) for d0, d1 in states) * (s0 / len(states)))
    return np.concatenate(parts)


def _powers(state_index: int) -> tuple[int, ...]:
    # a constant drive in a second state is not identifiable beside the first's
    return (0, 1, 2, 3) if state_index == 0 else (1, 2, 3)


def _states_from_theta(
    form: FormSpec, theta: np.ndarray, n_max: float
) -> list[tuple[float, float]]:
    taus = np.exp(np.sort(theta[: form.n_states]))
    states = [(1.0 / t, 0.0) for t in taus]
    if form.speed_state:
        kappa = float(theta[form.n_states])
        d0 = states[0][0]
        states[0] = (d0, d0 * kappa / max(n_max, 1e-9))  # lambda(n_max) = d0*(1+kappa)
    return states


def _tau_bounds(runs: Sequence[Run]) -> tuple[float, float]:
    """log(tau) bounds: half a sample up to three times the longest run."""
    dt = _fit_dt(runs)
    duration = max(r.duration_s for r in runs)
    return math.log(max(dt, 1.0) * 0.5), math.log(max(duration, 10 * dt) * 3)


def _rss(
    form: FormSpec,
    theta: np.ndarray,
    runs: Sequence[Run],
    y: np.ndarray,
    n_max: float,
    extra: np.ndarray | None = None,
) -> float:
    lo, hi = _tau_bounds(runs)
    if not all(lo <= v <= hi for v in theta[: form.n_states]):
        return math.inf
    if form.speed_state and not (-0.9 < theta[form.n_states] < 20):
        return math.inf
    if form.n_states == 2 and abs(theta[1] - theta[0]) < math.log(1.5):
        return math.inf  # two states must differ to be two
    x, y, _, _ = _measured_system(form, theta, runs, y, n_max, extra)
    if y.size <= x.shape[1]:
        return math.inf
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    r = y - x @ coef
    return float(r @ r)


def _measured_system(
    form: FormSpec,
    theta: np.ndarray,
    runs: Sequence[Run],
    y: np.ndarray,
    n_max: float,
    extra: np.ndarray | None,
):
    """The least-squares problem for the gains at ``theta``: the free-run columns (with the
    ``extra`` ones) and the elongation less the initial state's decay, on the measured rows;
    with the gains' count and the states."""
    x, n_gain, states = _design(form, theta, runs, n_max)
    if extra is not None:
        x = np.column_stack([x, extra])
    y = y - _initial_response(states, runs)
    ok = np.isfinite(y)  # a sparse log or a held-out fold: the measured rows
    return x[ok], y[ok], n_gain, states


def _grid(form: FormSpec, runs: Sequence[Run]) -> list[np.ndarray]:
    lo, hi = _tau_bounds(runs)
    taus = np.linspace(lo, hi, 18 if form.n_states == 1 else 10)
    if form.n_states == 1:
        base = [np.array([t]) for t in taus]
    else:
        base = [np.array([a, b]) for a in taus for b in taus if b - a >= math.log(1.5)]
    if form.speed_state:
        return [np.append(b, k) for b in base for k in (-0.5, 0.0, 1.0, 3.0)]
    return base


def fit_output_error(form: FormSpec, runs: Sequence[Run], **meta) -> FitResult:
    """Variable projection: outer search over time constants, OLS for the gains."""
    n_max = _n_max_krpm(runs)
    y = np.concatenate([r.elongation_um for r in runs])

    def obj(th: np.ndarray) -> float:
        return _rss(form, np.asarray(th, dtype=float), runs, y, n_max)

    candidates = sorted(
        ((obj(th), i, th) for i, th in enumerate(_grid(form, runs))), key=lambda c: (c[0], c[1])
    )
    best_val, _, best = candidates[0]
    if not math.isfinite(best_val):
        return FitResult(form, None, note="no stable parameters found")
    from scipy.optimize import (
        minimize,
    )  # 1.6 s to import: not for the commands that only read a log

    res = minimize(
        obj,
        best,
        method="Nelder-Mead",
        options={"xatol": 1e-4, "fatol": 1e-10 * max(best_val, 1e-12), "maxiter": 400},
    )
    if res.fun < best_val:
        best = np.asarray(res.x)
    return solve_output_error(form, best, runs, **meta)


def solve_output_error(
    form: FormSpec, theta: np.ndarray, runs: Sequence[Run], extra: np.ndarray | None = None, **meta
) -> FitResult:
    """Gains by OLS (statsmodels, with standard errors) for fixed nonlinear parameters;
    ``extra`` columns (input terms) are fitted jointly and their gains returned apart."""
    n_max = _n_max_krpm(runs)
    dt = _fit_dt(runs)
    x, y, n_gain, states = _measured_system(
        form, theta, runs, np.concatenate([r.elongation_um for r in runs]), n_max, extra
    )
    if y.size < 2 * x.shape[1]:  # no residual degrees of freedom left to judge the gains by
        return FitResult(
            form, None, note=f"{y.size} measurements for {x.shape[1]} gains", theta=theta
        )
    ols = _ols(x, y)
    gains = np.asarray(ols.params)
    se = np.asarray(ols.bse)
    extra_gains, extra_se = (gains[n_gain:], se[n_gain:]) if extra is not None else (None, None)
    gains, se = gains[:n_gain], se[:n_gain]
    assert gains.size == n_gain
    st_coefs: list[ThermalStateCoefficients] = []
    coefs: list[dict[str, float | str | None]] = []
    k = 0
    for j, (d0, d1) in enumerate(states):
        g = [0.0, 0.0, 0.0, 0.0]
        for p in _powers(j):
            g[p] = float(gains[k])
            coefs.append(
                {
                    "name": f"g{p}[{j + 1}]",
                    "value": float(gains[k]),
                    "stderr": float(se[k]),
                    "unit": f"um/s/krpm^{p}",
                }
            )
            k += 1
        st_coefs.append(
            ThermalStateCoefficients(
                dissipation_per_s=(d0, d1), generation_um_per_s=(g[0], g[1], g[2], g[3])
            )
        )
        coefs.append({"name": f"tau[{j + 1}]", "value": 1.0 / d0, "stderr": None, "unit": "s"})
        if d1:
            coefs.append({"name": f"d1[{j + 1}]", "value": d1, "stderr": None, "unit": "1/s/krpm"})
    elastic = (0.0, 0.0)
    if form.elastic:
        elastic = (float(gains[k]), float(gains[k + 1]))
        coefs.append({"name": "e1", "value": elastic[0], "stderr": float(se[k]), "unit": "um/krpm"})
        coefs.append(
            {"name": "e2", "value": elastic[1], "stderr": float(se[k + 1]), "unit": "um/krpm^2"}
        )
    try:
        model = ThermalModel(
            form=form.name,
            fitted_dt_s=dt,
            speed_range_rpm=_speed_range(runs),
            states=tuple(st_coefs),
            elastic_um=elastic,
            **meta,
        )
    except ModelError as err:
        return FitResult(form, None, coefs, note=f"not usable: {err}", theta=theta)
    taus = ", ".join(f"{1 / d0 / 60:.1f}" for d0, _ in states)
    return FitResult(
        form,
        model,
        coefs,
        note=f"tau = {taus} min",
        theta=theta,
        extra_gains=extra_gains,
        extra_stderr=extra_se,
    )


# -- the estimator ------------------------------------------------------------------


SEARCH_ROWS = 20000
"""The time constants are searched on at most this many rows (a coarser grid)."""


def _coarse(runs: Sequence[Run]) -> list[Run]:
    rows = sum(len(r) for r in runs)
    if rows <= SEARCH_ROWS:
        return list(runs)
    k = math.ceil(rows / SEARCH_ROWS)
    return [resample(r, runs[0].median_dt_s * k) for r in runs]


def fit_physical(form: FormSpec, runs: Sequence[Run], **meta) -> FitResult:
    """Fit one output-error form on runs that share a uniform grid period: the time constants
    searched on at most :data:`SEARCH_ROWS` rows, the gains solved on all of them. A fit that
    fails numerically is a result without a model, and says why."""
    try:
        if sum(len(r) for r in runs) <= SEARCH_ROWS:
            return fit_output_error(form, runs, **meta)
        coarse = fit_output_error(form, _coarse(runs), **meta)
        if coarse.model is None or coarse.theta is None:
            return coarse
        return solve_output_error(form, coarse.theta, runs, **meta)
    except (np.linalg.LinAlgError, ValueError) as err:
        if isinstance(err, CalibrationError):
            raise
        return FitResult(form, None, note=f"fit failed: {err}")


# -- the candidate ------------------------------------------------------------------


PHYSICAL_FORM = "speed-state+elastic"
"""The output-error form entered as the physical candidate."""
NAME = "physical"


MIN_SPARSE_MEASUREMENTS = 3
"""A sparse stretch with fewer measurements than this is not fitted on."""


def runs_of(ds: Dataset, rows: np.ndarray) -> list[Run]:
    """The runs to fit on ``rows``, on a uniform grid: each segment from its start, as
    :func:`free_run` scores it, to its last measured row among ``rows``; the measurements outside
    ``rows`` are hidden, not cut out.

    The speed is known on every row, so a held-out fold costs its targets, not the state after
    it. Restarting after the fold from its next measurement instead put that measurement's
    elastic growth (taken at speed) and noise into the thermal state: with a tool setter's
    sparse measurements it cost up to 3x the eddy-current model's error."""
    runs: list[Run] = []
    for a, b in ds.segments:
        hit = np.flatnonzero(rows[a:b] & ds.measured[a:b])
        hi = a + int(hit[-1]) + 1 if hit.size else a
        if hi - a < fl.MIN_FOLD_ROWS or (not ds.dense and hit.size < MIN_SPARSE_MEASUREMENTS):
            continue
        y = np.where(rows[a:hi], ds.elongation_um[a:hi], np.nan)
        y[0] = ds.elongation_um[
            a
        ]  # the free run's anchor, as free_run takes it: an input, not a target
        runs.append(resample(Run(f"{len(runs)}", ds.time_s[a:hi], ds.speed_rpm[a:hi], y), ds.dt_s))
    return runs


def fit(
    ds: Dataset, rows: np.ndarray | None = None, form: str = PHYSICAL_FORM, **meta: Any
) -> FitResult:
    """:data:`PHYSICAL_FORM` fitted on the stretches of ``rows`` (default: all), resampled to the
    dataset's period. A fit without a usable stretch is a result without a model."""
    runs = runs_of(ds, np.ones(ds.time_s.size, bool) if rows is None else rows)
    spec = FORM_BY_NAME[form]
    if not runs:
        return FitResult(spec, None, note=f"no stretch of {fl.MIN_FOLD_ROWS} rows or more")
    return fit_physical(spec, runs, **meta)


def free_run(model: ThermalModel, ds: Dataset) -> np.ndarray:
    """Each segment from its first row's elongation (at rest when it was not measured), never
    re-anchored."""
    out = np.empty(ds.time_s.size)
    with np.errstate(all="ignore"):
        for a, b in ds.segments:
            y0 = float(ds.elongation_um[a])
            out[a:b] = model.simulate_um(
                ds.speed_rpm[a:b], ds.time_s[a:b], None, y0 if math.isfinite(y0) else None
            )
    return out


def candidate(ds: Dataset, ctx: Mapping[str, Any]) -> tuple[Candidate, Any]:
    """The physical candidate: refitted without each fold, scored on it in free run."""
    cpu0 = time.process_time()
    spec = FORM_BY_NAME[PHYSICAL_FORM]
    c = Candidate(NAME, "speed", f"{PHYSICAL_FORM}: {spec.description} (output error)")
    meta = ctx.get("meta", {})
    res = np.full(ds.time_s.size, np.nan)
    for a, b in ds.folds:
        f = fit(ds, fl.without(ds.time_s.size, (a, b)), **meta)
        if f.model is None:
            c.refusals.append(
                f"no stable fit without fold rows {a}..{b - 1}" + (f" ({f.note})" if f.note else "")
            )
            c.fit_cpu_s = time.process_time() - cpu0
            return c, None
        res[a:b] = (ds.elongation_um - free_run(f.model, ds))[a:b]
    c.cv_rms_um, c.cv_max_abs_um = pooled_stats(res, ds.measured)
    c.folds_rms_um = [f.rms_um for f in fold_scores(res, ds.folds)]
    c.held_out_residual_um = res
    splits = fl.forward_of(ds.time_s, ds.speed_rpm, ds.folds, ds.unit == "cycle", ds.measured)
    if splits:  # rolling origin: fitted on the folds before, scored on the next
        ahead = np.full(ds.time_s.size, np.nan)
        for past, (a, b) in splits:
            f = fit(ds, fl.rows_of(ds.time_s.size, past), **meta)
            if f.model is None:
                c.refusals.append(
                    f"no stable fit on the folds before rows {a}..{b - 1}"
                    + (f" ({f.note})" if f.note else "")
                )
                c.fit_cpu_s = time.process_time() - cpu0
                return c, None
            ahead[a:b] = (ds.elongation_um - free_run(f.model, ds))[a:b]
        c.forward_rms_um, c.forward_max_abs_um = pooled_stats(
            ahead, fl.rows_of(ahead.size, [f for _, f in splits]) & ds.measured
        )
        c.forward_folds_rms_um = [f.rms_um for f in fold_scores(ahead, [f for _, f in splits])]
        c.forward_residual_um = ahead
    full = fit(ds, **meta)
    if full.model is None:
        c.refusals.append(f"no stable fit on all rows ({full.note})")
    else:
        c.model = full.model
        c.in_sample_rms_um, c.in_sample_max_abs_um = pooled_stats(
            ds.elongation_um - free_run(full.model, ds), ds.measured
        )
        c.details = {"coefficients": full.coefficients}
        top = abs(full.model.steady_state_um(full.model.speed_range_rpm[1]))
        bound = GAIN_BOUND * float(np.nanmax(np.abs(ds.elongation_um)))
        if not math.isfinite(top) or top > bound:
            c.refusals.append(
                f"steady elongation {top:.4g} um at the top speed is over "
                f"{GAIN_BOUND:g} x the largest measured"
            )
    c.fit_cpu_s = time.process_time() - cpu0
    return c, full
