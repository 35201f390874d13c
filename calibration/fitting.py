"""Model fitting: the paper's OLS reference, output-error forms, and the exponential baseline.

Every candidate is turned into a :class:`~compensator.model.ThermalModel` and
judged in **free run** (the model feeds on its own output), with
leave-one-run-out cross-validation when there are two or more runs
(a one-step fit can score R² = 0.9999 and still drift in free run).

Output-error fitting uses variable projection: for fixed time constants the
free-run output is linear in every gain, so each evaluation filters the speed
powers through each state (one pass each) and solves one least-squares
problem; an outer search covers the one or two nonlinear parameters.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize

from compensator.errors import CalibrationError, ModelError
from compensator.model import ThermalModel, ThermalStateCoefficients, filter_state
from compensator.units import SPEED_SCALE_RPM

from .data import Run

_UNIT = (
    ThermalStateCoefficients(dissipation_per_s=(1.0, 0.0), generation_um_per_s=(1, 0, 0, 0)),
)


@dataclass(frozen=True)
class FormSpec:
    """A candidate model form."""

    name: str
    description: str
    method: str  # "ols" | "oe" | "baseline"
    n_states: int = 1
    speed_state: bool = False
    elastic: bool = False


FORMS: tuple[FormSpec, ...] = (
    FormSpec("paper-ols", "paper 001 eqs. 11-12, OLS one step ahead on measured S[k-1]", "ols"),
    FormSpec("exp-baseline", "paper 001 eqs. 1-3: exponential per constant-speed segment", "baseline"),
    FormSpec("paper-oe", "paper's form, refined on free-run (output) error", "oe"),
    FormSpec("speed-state", "paper's form + speed x state dissipation (b5*n*S)", "oe", speed_state=True),
    FormSpec("elastic", "paper's form + instantaneous elastic e1*n + e2*n^2", "oe", elastic=True),
    FormSpec("two-state", "two thermal states (fast and slow)", "oe", n_states=2),
    FormSpec("two-state+elastic", "two thermal states + elastic term", "oe", n_states=2, elastic=True),
    FormSpec(
        "speed-state+elastic", "speed x state dissipation + elastic term", "oe",
        speed_state=True, elastic=True,
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
    st = ThermalStateCoefficients(dissipation_per_s=(d0, d1), generation_um_per_s=tuple(g))
    return filter_state(st, run.n_krpm, run.dt_s, 0.0)


def _decay(d0: float, d1: float, run: Run) -> np.ndarray:
    st = ThermalStateCoefficients(dissipation_per_s=(d0, d1), generation_um_per_s=(0, 0, 0, 0))
    return filter_state(st, run.n_krpm, run.dt_s, 1.0)


# -- the paper's OLS reference ----------------------------------------------------


def fit_paper_ols(runs: Sequence[Run], dt_s: float, **meta) -> FitResult:
    """``S_k = a*S_{k-1} + b0 + b1*n + b2*n^2 + b3*n^3`` by OLS (statsmodels).

    Rows never cross from one run to the next. The runs must be on the
    uniform grid ``dt_s``.
    """
    form = FORM_BY_NAME["paper-ols"]
    xs, ys = [], []
    for r in runs:
        n = r.n_krpm[1:]
        xs.append(np.column_stack([np.ones_like(n), r.elongation_um[:-1], n, n**2, n**3]))
        ys.append(r.elongation_um[1:])
    x, y = np.vstack(xs), np.concatenate(ys)
    res = _ols(x, y)
    b0, a, b1, b2, b3 = (float(v) for v in res.params)
    se = [float(v) for v in res.bse]
    names = [("b0", "um"), ("a", "-"), ("b1", "um/krpm"), ("b2", "um/krpm^2"), ("b3", "um/krpm^3")]
    coefs = [
        {"name": nm, "value": float(v), "stderr": s, "unit": u}
        for (nm, u), v, s in zip(names, res.params, se)
    ]
    try:
        model = ThermalModel.from_discrete(
            a, (b0, b1, b2, b3), dt_s, speed_range_rpm=_speed_range(runs), form=form.name, **meta
        )
        note = f"a = {a:.6f} at dt = {dt_s:g} s (tau = {-dt_s / math.log(a) / 60:.1f} min)"
    except ModelError as err:
        model, note = None, f"not usable: {err}"
    return FitResult(form, model, coefs, float(res.rsquared), note)


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
        parts.append(sum(_decay(d0, d1, r) for d0, d1 in states) * (s0 / len(states)))
    return np.concatenate(parts)


def _powers(state_index: int) -> tuple[int, ...]:
    # a constant drive in a second state is not identifiable beside the first's
    return (0, 1, 2, 3) if state_index == 0 else (1, 2, 3)


def _states_from_theta(form: FormSpec, theta: np.ndarray, n_max: float) -> list[tuple[float, float]]:
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


def _rss(form: FormSpec, theta: np.ndarray, runs: Sequence[Run], y: np.ndarray, n_max: float,
         extra: np.ndarray | None = None) -> float:
    lo, hi = _tau_bounds(runs)
    if not all(lo <= v <= hi for v in theta[: form.n_states]):
        return math.inf
    if form.speed_state and not (-0.9 < theta[form.n_states] < 20):
        return math.inf
    if form.n_states == 2 and abs(theta[1] - theta[0]) < math.log(1.5):
        return math.inf  # two states must differ to be two
    x, _, states = _design(form, theta, runs, n_max)
    if extra is not None:
        x = np.column_stack([x, extra])
    y = y - _initial_response(states, runs)
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    r = y - x @ coef
    return float(r @ r)


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

    candidates = sorted(((obj(th), i, th) for i, th in enumerate(_grid(form, runs))),
                        key=lambda c: (c[0], c[1]))
    best_val, _, best = candidates[0]
    if not math.isfinite(best_val):
        return FitResult(form, None, note="no stable parameters found")
    res = minimize(obj, best, method="Nelder-Mead",
                   options={"xatol": 1e-4, "fatol": 1e-10 * max(best_val, 1e-12), "maxiter": 400})
    if res.fun < best_val:
        best = np.asarray(res.x)
    return solve_output_error(form, best, runs, **meta)


def speed_design(form: FormSpec, theta: np.ndarray, runs: Sequence[Run]) -> tuple[np.ndarray, np.ndarray]:
    """Free-run columns of the speed part for fixed nonlinear parameters, and the target
    (measured elongation less the fixed initial decay), rows of all runs stacked."""
    x, _, states = _design(form, theta, runs, _n_max_krpm(runs))
    y = np.concatenate([r.elongation_um for r in runs]) - _initial_response(states, runs)
    return x, y


def refine_theta(form: FormSpec, theta: np.ndarray, runs: Sequence[Run], extra: np.ndarray) -> np.ndarray:
    """The speed part's nonlinear parameters re-optimised with extra (input) columns present."""
    n_max = _n_max_krpm(runs)
    y = np.concatenate([r.elongation_um for r in runs])

    def obj(th: np.ndarray) -> float:
        return _rss(form, np.asarray(th, dtype=float), runs, y, n_max, extra)

    start = obj(theta)
    res = minimize(obj, theta, method="Nelder-Mead",
                   options={"xatol": 1e-4, "fatol": 1e-10 * max(start, 1e-12), "maxiter": 300})
    return np.asarray(res.x) if res.fun < start else np.asarray(theta)


def solve_output_error(form: FormSpec, theta: np.ndarray, runs: Sequence[Run],
                       extra: np.ndarray | None = None, **meta) -> FitResult:
    """Gains by OLS (statsmodels, with standard errors) for fixed nonlinear parameters;
    ``extra`` columns (input terms) are fitted jointly and their gains returned apart."""
    n_max = _n_max_krpm(runs)
    dt = _fit_dt(runs)
    y = np.concatenate([r.elongation_um for r in runs])
    x, n_gain, states = _design(form, theta, runs, n_max)
    if extra is not None:
        x = np.column_stack([x, extra])
    ols = _ols(x, y - _initial_response(states, runs))
    gains = np.asarray(ols.params)
    se = np.asarray(ols.bse)
    extra_gains, extra_se = (gains[n_gain:], se[n_gain:]) if extra is not None else (None, None)
    gains, se = gains[:n_gain], se[:n_gain]
    assert gains.size == n_gain
    st_coefs, coefs, k = [], [], 0
    for j, (d0, d1) in enumerate(states):
        g = [0.0, 0.0, 0.0, 0.0]
        for p in _powers(j):
            g[p] = float(gains[k])
            coefs.append({"name": f"g{p}[{j + 1}]", "value": float(gains[k]),
                          "stderr": float(se[k]), "unit": f"um/s/krpm^{p}"})
            k += 1
        st_coefs.append(ThermalStateCoefficients(dissipation_per_s=(d0, d1), generation_um_per_s=tuple(g)))
        coefs.append({"name": f"tau[{j + 1}]", "value": 1.0 / d0, "stderr": None, "unit": "s"})
        if d1:
            coefs.append({"name": f"d1[{j + 1}]", "value": d1, "stderr": None, "unit": "1/s/krpm"})
    elastic = (0.0, 0.0)
    if form.elastic:
        elastic = (float(gains[k]), float(gains[k + 1]))
        coefs.append({"name": "e1", "value": elastic[0], "stderr": float(se[k]), "unit": "um/krpm"})
        coefs.append({"name": "e2", "value": elastic[1], "stderr": float(se[k + 1]), "unit": "um/krpm^2"})
    try:
        model = ThermalModel(
            form=form.name, fitted_dt_s=dt, speed_range_rpm=_speed_range(runs),
            states=tuple(st_coefs), elastic_um=elastic, **meta,
        )
    except ModelError as err:
        return FitResult(form, None, coefs, note=f"not usable: {err}", theta=theta)
    taus = ", ".join(f"{1 / d0 / 60:.1f}" for d0, _ in states)
    return FitResult(form, model, coefs, note=f"tau = {taus} min", theta=theta,
                     extra_gains=extra_gains, extra_stderr=extra_se)


# -- the exponential baseline (paper 001 eqs. 1-3) ----------------------------------


def _segments(run: Run, min_len: int = 5) -> list[tuple[int, int]]:
    n = np.round(np.abs(run.speed_rpm), 0)
    cut = np.flatnonzero(np.diff(n) != 0) + 1
    edges = np.concatenate([[0], cut, [n.size]])
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b - a >= min_len]


def fit_exponential_baseline(runs: Sequence[Run], **meta) -> FitResult:
    """S(t) = S0 + (Sinf - S0)(1 - exp(-t/tau)) per constant-speed segment,
    Sinf(n) = c1*n^2 + c2*n + c3, tau the median over segments."""
    form = FORM_BY_NAME["exp-baseline"]
    points, taus = [], []
    for r in runs:
        for a, b in _segments(r):
            t = r.time_s[a - 1 : b] - r.time_s[a - 1] if a > 0 else r.time_s[a:b] - r.time_s[a]
            s = r.elongation_um[a - 1 : b] if a > 0 else r.elongation_um[a:b]
            best = None
            for tau in np.geomspace(max(r.median_dt_s, 1.0), 20 * max(t[-1], 1.0), 60):
                e = np.exp(-t / tau)
                x = np.column_stack([np.ones_like(t), e])
                c, *_ = np.linalg.lstsq(x, s, rcond=None)
                rss = float(np.sum((s - x @ c) ** 2))
                if best is None or rss < best[0]:
                    best = (rss, tau, float(c[0]))
            assert best is not None
            points.append((float(np.abs(r.speed_rpm[b - 1]) / SPEED_SCALE_RPM), best[2]))
            if t[-1] > 2 * best[1]:  # only segments long enough to see tau
                taus.append(best[1])
    speeds = np.array([p[0] for p in points])
    if len(points) < 3 or np.unique(np.round(speeds, 3)).size < 3:
        return FitResult(form, None, note="needs three or more constant-speed segments")
    c1, c2, c3 = np.polyfit(speeds, [p[1] for p in points], 2)
    tau = float(np.median(taus)) if taus else float(max(r.duration_s for r in runs) / 3)
    lam = 1.0 / tau
    coefs = [
        {"name": "c1", "value": float(c1), "stderr": None, "unit": "um/krpm^2"},
        {"name": "c2", "value": float(c2), "stderr": None, "unit": "um/krpm"},
        {"name": "c3", "value": float(c3), "stderr": None, "unit": "um"},
        {"name": "tau", "value": tau, "stderr": None, "unit": "s"},
    ]
    st = ThermalStateCoefficients(
        dissipation_per_s=(lam, 0.0), generation_um_per_s=(c3 * lam, c2 * lam, c1 * lam, 0.0)
    )
    model = ThermalModel(form=form.name, fitted_dt_s=_fit_dt(runs),
                         speed_range_rpm=_speed_range(runs), states=(st,), **meta)
    return FitResult(form, model, coefs, note=f"{len(points)} segments, tau = {tau / 60:.1f} min")


def fit_form(form: FormSpec, fit_runs: Sequence[Run], **meta) -> FitResult:
    """Fit one form on runs that share the uniform grid period."""
    try:
        if form.method == "ols":
            return fit_paper_ols(fit_runs, _fit_dt(fit_runs), **meta)
        if form.method == "baseline":
            return fit_exponential_baseline(fit_runs, **meta)
        return fit_output_error(form, fit_runs, **meta)
    except (np.linalg.LinAlgError, ValueError) as err:
        if isinstance(err, CalibrationError):
            raise
        return FitResult(form, None, note=f"fit failed: {err}")

