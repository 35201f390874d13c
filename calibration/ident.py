"""Identification that holds on real machines (issue 16): a prototype. Pure: no file I/O.

Design (``docs/IDENTIFICATION.md`` has the measured figures and the integration plan):

1. **Cycles.** A long log is cut into cycles, each a heat-up and the cool-down that follows
   (:func:`split_cycles`, rule in :data:`CYCLE_RULE`). Every score is leave-one-cycle-out
   **free-run** error: the model runs over the whole log on its inputs alone (no measured
   elongation anywhere) and the rows of the held-out cycle are scored with gains fitted on the
   other cycles' rows. One-step R² is never used to choose anything.
2. **One joint, regularised linear identification.** For fixed time constants the free-run
   output of parallel first-order states is linear in every gain, so the whole model is one
   design matrix: the speed terms n and n² (|speed| in krpm) each through a bank of first-order
   filters (:func:`filter_bank`, exact zero-order hold at any Δt, each filter starting at
   equilibrium with its first input), and each extra input (temperatures...) as a deviation from
   a *fixed* reference stored in the model (the training mean) through its own bank. A time
   constant of 0 is a static (instantaneous) term. Gains by ridge regression on standardised
   columns with an unpenalised intercept; α (and, on request, the τ grid among a few candidates)
   is chosen by leave-one-cycle-out free-run RMS (:func:`fit_ridge_cv`); ``nested=True`` also
   gives the honest figure where the held-out cycle took no part in choosing α or the grid. The
   default grid follows from the log (:func:`auto_grid`): a static term and a ladder of time
   constants, ratio 3, from 10 min up to the longest stretch a cycle holds.
3. **State-space form.** Filters sharing a time constant add up, so the model is one first-order
   state per distinct τ, driven by a linear combination of n, n² and the input deviations, plus
   a static feed-through and a constant (:meth:`IdentResult.state_space`). The speed-only part
   maps exactly onto :class:`compensator.model.ThermalModel` (:meth:`IdentResult.to_thermal_model`).
4. **Physical sanity.** Time constants between the sample period and :data:`MAX_TAU_S` (or 0 for a
   static term); the steady elongation the gains imply over the calibrated ranges at most
   :data:`GAIN_BOUND` times the largest measured; a candidate worse in cross-validation than the
   exponential baseline (paper 001 eqs. 1-3 in dynamic form: one τ, S∞ quadratic in n, OLS) is
   refused (``accepted`` False, reasons in ``refusals``).

The paper's one-step OLS, ``S_k = a*S_{k-1} + b0 + b1*n + b2*n^2 + b3*n^3``, is here for the
comparison (:func:`fit_paper_ols`, :func:`paper_ols_cv`), scored in free run like the rest.

Units are in the names: ``time_s``, ``speed_rpm``, ``elongation_um``, ``tau_s``; inputs in their
own unit (degC...). n is always |speed| / 1000 (krpm).
"""

from __future__ import annotations

import itertools
import math
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from compensator.errors import CalibrationError, ModelError, NonFiniteInputError
from compensator.filters import filter_bank, series, times
from compensator.model import ModelState, ThermalModel, ThermalStateCoefficients
from compensator.statespace import (
    GAIN_BOUND,
    MAX_TAU_S,
    SPEED_CLIP,
    InputChannel,
    StateSpaceModel,
    steady_range_um,
)
from compensator.units import SPEED_SCALE_RPM

# -- constants ------------------------------------------------------------------------------

IDLE_RPM = 1.0
"""At or below this |speed| the spindle is at rest."""
MIN_REST_S = 1800.0
"""A rest shorter than this (a tool change, a pause) does not end a heat-up."""
MIN_RUN_S = 600.0
"""A run shorter than this (a blip during a cool-down) does not start a heat-up."""

CYCLE_RULE = (
    "a cycle is a heat-up and the cool-down that follows: the spindle runs when |speed| > "
    f"{IDLE_RPM:g} rpm; rests shorter than {MIN_REST_S / 60:g} min are bridged (they belong to the "
    f"run), then runs shorter than {MIN_RUN_S / 60:g} min are ignored (they belong to the rest); "
    "each remaining run starts a cycle, which ends where the next one starts; samples before the "
    "first run join the first cycle, and the last cycle ends with the log (it may have no "
    "cool-down). Durations are measured on the time stamps, a logged value held over the interval "
    "that ends at its sample."
)

PARSIMONY = 0.02
"""A simpler grid (or a larger α), or a simpler candidate, wins when its CV RMS is within 2 % of
the best."""


H = 3600.0


@dataclass(frozen=True)
class TauGrid:
    """The filter banks: time constants [s] for the speed terms and for each input (0 = static)."""

    speed_taus_s: tuple[float, ...]
    input_taus_s: tuple[float, ...] = ()

    @property
    def label(self) -> str:
        def fmt(taus: tuple[float, ...]) -> str:
            return ",".join("static" if t == 0 else (f"{t / H:g}h" if t >= H else f"{t / 60:g}min")
                            for t in taus) or "-"
        return f"speed[{fmt(self.speed_taus_s)}] inputs[{fmt(self.input_taus_s)}]"

    @property
    def size(self) -> int:
        return len(self.speed_taus_s) + len(self.input_taus_s)


FIRST_TAU_S = 600.0
"""The shortest non-static time constant of the default banks (or four samples, if longer)."""
TAU_RATIO = 3.0
"""Ratio between neighbouring time constants of the default speed bank."""

DEFAULT_ALPHAS = tuple(float(a) for a in np.geomspace(1e-8, 100.0, 31))
"""Ridge penalties tried, per row on standardised columns: ||y - Xb||^2/m + alpha*||b||^2."""

BASELINE_TAUS_S = tuple(float(t) for t in np.geomspace(300.0, 24 * H, 16))
"""Time constants the exponential baseline chooses among."""


def longest_stretch_s(time_s: Any, speed_rpm: Any, cycles: Sequence[tuple[int, int]],
                      idle_rpm: float = IDLE_RPM) -> float:
    """The median over cycles of the longer of its run and its rest [s]: the longest time
    constant the log can pin down (a slow heat-up looks like a long time constant otherwise)."""
    t = np.asarray(time_s, float)
    n = np.abs(np.asarray(speed_rpm, float))
    held = np.diff(t, prepend=t[:1])
    out = []
    for a, b in cycles:
        run = float(np.sum(held[a:b][n[a:b] > idle_rpm]))
        out.append(max(run, _duration_s(t, a, b) - run))
    return float(np.median(out)) if out else 0.0


def auto_grid(time_s: Any, speed_rpm: Any, cycles: Sequence[tuple[int, int]],
              with_inputs: bool) -> TauGrid:
    """The default banks, from the log: a static term and a ladder of time constants, ratio
    :data:`TAU_RATIO`, from :data:`FIRST_TAU_S` up to the first at or beyond
    :func:`longest_stretch_s`; the inputs get the static term and every other rung from the
    second (fewer columns: 16 sensors already bring many)."""
    t = np.asarray(time_s, float)
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    first = max(FIRST_TAU_S, 4 * dt)
    longest = min(max(longest_stretch_s(t, speed_rpm, cycles), first), MAX_TAU_S)
    ladder = [first]
    while ladder[-1] < longest and ladder[-1] * TAU_RATIO <= MAX_TAU_S:
        ladder.append(ladder[-1] * TAU_RATIO)
    speed = (0.0, *ladder)
    inputs = (0.0, *ladder[1::2]) if with_inputs else ()
    return TauGrid(speed, inputs)


def candidate_grids(base: TauGrid) -> list[TauGrid]:
    """Optional grid search (``fit_ridge_cv(grids=...)``), simple to rich: the speed ladder cut
    short or extended by one rung, inputs static only, on every other rung or on every rung."""
    sp = [t for t in base.speed_taus_s if t > 0]
    longer = (*sp, sp[-1] * TAU_RATIO) if sp[-1] * TAU_RATIO <= MAX_TAU_S else tuple(sp)
    speeds = [(0.0, *sp[:-1]) if len(sp) > 1 else (0.0, *sp), (0.0, *sp), (0.0, *longer)]
    if not base.input_taus_s:
        return [TauGrid(s) for s in speeds]
    inputs = [(0.0,), base.input_taus_s, (0.0, *sp)]
    return [TauGrid(s, i) for i in inputs for s in speeds]


# -- checks ---------------------------------------------------------------------------------


def _series(name: str, values: Any, size: int | None = None) -> np.ndarray:
    try:
        return series(name, values, size)
    except NonFiniteInputError:
        raise
    except ModelError as err:
        raise CalibrationError(str(err)) from err


def _times(time_s: Any) -> np.ndarray:
    try:
        return times(time_s)
    except NonFiniteInputError:
        raise
    except ModelError as err:
        raise CalibrationError(str(err)) from err


# -- cycles ---------------------------------------------------------------------------------


def _stretches(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def _duration_s(t: np.ndarray, a: int, b: int) -> float:
    """Time covered by samples a..b-1, each held over the interval ending at it."""
    return float(t[b - 1] - t[max(a - 1, 0)])


def split_cycles(time_s: Any, speed_rpm: Any, *, idle_rpm: float = IDLE_RPM,
                 min_rest_s: float = MIN_REST_S, min_run_s: float = MIN_RUN_S) -> list[tuple[int, int]]:
    """Cut a log into cycles: half-open index ranges ``(start, stop)`` that cover it in order.

    The rule (:data:`CYCLE_RULE`): the spindle runs when |speed| > ``idle_rpm``; rests shorter
    than ``min_rest_s`` are bridged, then runs shorter than ``min_run_s`` are ignored; each run
    left starts a cycle that ends where the next starts. Samples before the first run join the
    first cycle; the last cycle ends with the log. A log with no run is one cycle.
    """
    t = _times(time_s)
    n = np.abs(_series("speed_rpm", speed_rpm, t.size))
    if t.size == 0:
        return []
    running = n > idle_rpm
    for a, b in _stretches(~running):
        if a > 0 and b < t.size and _duration_s(t, a, b) < min_rest_s:
            running[a:b] = True  # a pause between two runs
    for a, b in _stretches(running):
        if _duration_s(t, a, b) < min_run_s:
            running[a:b] = False
    starts = [a for a, _ in _stretches(running)]
    if not starts:
        return [(0, int(t.size))]
    bounds = [0, *starts[1:], int(t.size)]
    return [(int(a), int(b)) for a, b in itertools.pairwise(bounds)]


def describe_cycles(time_s: Any, speed_rpm: Any, cycles: Sequence[tuple[int, int]],
                    idle_rpm: float = IDLE_RPM) -> list[str]:
    """One line per cycle: when, how long it ran and at what speed, how long it rested."""
    t = np.asarray(time_s, float)
    n = np.abs(np.asarray(speed_rpm, float))
    held = np.diff(t, prepend=t[:1])  # the interval each sample is held over
    lines = []
    for i, (a, b) in enumerate(cycles, start=1):
        run = n[a:b] > idle_rpm
        run_s = float(np.sum(held[a:b][run]))
        top = float(n[a:b].max()) if b > a else 0.0
        lines.append(f"cycle {i}: samples {a}..{b - 1}, {t[a] / H:.2f}-{t[b - 1] / H:.2f} h, "
                     f"running {run_s / H:.2f} h up to {top:.0f} rpm, "
                     f"at rest {(_duration_s(t, a, b) - run_s) / H:.2f} h")
    return lines


# -- the filter bank -------------------------------------------------------------------------


# -- design ------------------------------------------------------------------------------------


def speed_terms(speed_rpm: np.ndarray) -> dict[str, np.ndarray]:
    """The speed drives: n and n^2, n = |speed| in krpm."""
    n = np.abs(speed_rpm) / SPEED_SCALE_RPM
    return {"n": n, "n2": n * n}


class _Bank:
    """Filtered columns of one log (or of several files, one segment each: every filter restarts
    at equilibrium at a segment's start), computed once per (drive, tau) and reused."""

    def __init__(self, time_s: np.ndarray, drives: Mapping[str, np.ndarray],
                 segments: Sequence[tuple[int, int]] | None = None):
        self.time_s = time_s
        self.drives = drives
        self.segments = tuple(segments) if segments else ((0, int(time_s.size)),)
        self.cache: dict[tuple[str, float], np.ndarray] = {}

    def column(self, drive: str, tau: float) -> np.ndarray:
        key = (drive, tau)
        if key not in self.cache:
            u = self.drives[drive]
            self.cache[key] = np.concatenate([filter_bank(self.time_s[a:b], u[a:b], (tau,))[:, 0]
                                              for a, b in self.segments])
        return self.cache[key]

    def design(self, grid: TauGrid, names: Sequence[str]) -> np.ndarray:
        cols = [self.column(d, tau) for d in ("n", "n2") for tau in grid.speed_taus_s]
        cols += [self.column(f"in:{nm}", tau) for nm in names for tau in grid.input_taus_s]
        return np.column_stack(cols)


# -- ridge ----------------------------------------------------------------------------------


def _ridge_path(x: np.ndarray, y: np.ndarray, alphas: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Gains (p, len(alphas)) and intercepts (len(alphas),) of ridge on standardised columns,
    ``||y - c - Xb||^2/m + alpha*||b_std||^2``; the intercept is not penalised."""
    m = y.size
    mu = x.mean(axis=0)
    sd = x.std(axis=0)
    keep = sd > 1e-12 * np.maximum(np.abs(mu), 1.0)  # a constant column cannot be told from c
    z = (x[:, keep] - mu[keep]) / sd[keep]
    ym = float(y.mean())
    u, s, vt = np.linalg.svd(z, full_matrices=False)
    uty = u.T @ (y - ym)
    small = s <= s[0] * 1e-12 if s.size else np.zeros(0, bool)
    gains = np.zeros((x.shape[1], len(alphas)))
    for i, alpha in enumerate(alphas):
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.where(small, 0.0, s / (s * s + alpha * m))
        gains[keep, i] = (vt.T @ (d * uty)) / sd[keep]
    intercepts = ym - mu @ gains
    return gains, intercepts


@dataclass(frozen=True)
class FoldScore:
    """Free-run error on one held-out cycle."""

    cycle: int
    start: int
    stop: int
    rms_um: float
    max_abs_um: float


def _finite(residual: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(residual), residual, 1e9)  # a diverging free run scores huge, not NaN


def fold_scores(residual: np.ndarray, cycles: Sequence[tuple[int, int]]) -> tuple[FoldScore, ...]:
    """RMS and max |residual| on each fold; a non-finite residual counts as 1e9 um."""
    return tuple(FoldScore(i, a, b, *pooled_stats(residual[a:b])) for i, (a, b) in enumerate(cycles, start=1))


def residual_stats(residual: np.ndarray) -> dict[str, float | int | None]:
    """Samples, RMS, max |r|, mean |r|, mean and standard deviation of a residual [um]; None
    for each figure of an empty one."""
    r = np.asarray(residual, dtype=float)
    if r.size == 0:
        return {"samples": 0, "rms_um": None, "max_abs_um": None, "mean_abs_um": None,
                "mean_um": None, "std_um": None}
    return {"samples": int(r.size), "rms_um": float(np.sqrt(np.mean(r**2))),
            "max_abs_um": float(np.max(np.abs(r))), "mean_abs_um": float(np.mean(np.abs(r))),
            "mean_um": float(np.mean(r)), "std_um": float(np.std(r))}


def pooled_stats(residual: np.ndarray) -> tuple[float, float]:
    """RMS and max |residual| over all rows; a non-finite residual counts as 1e9 um."""
    r = _finite(residual)
    return float(np.sqrt(np.mean(r * r))), float(np.max(np.abs(r)))


def _cv_residuals(x: np.ndarray, y: np.ndarray, cycles: Sequence[tuple[int, int]],
                  alphas: Sequence[float], train_mask: np.ndarray | None = None) -> np.ndarray:
    """Held-out residuals (rows, alphas) of leave-one-cycle-out ridge; rows outside
    ``train_mask`` are never used for fitting (nested CV's outer cycle)."""
    base = np.ones(y.size, bool) if train_mask is None else train_mask
    res = np.full((y.size, len(alphas)), np.nan)
    for a, b in cycles:
        tr = base.copy()
        tr[a:b] = False
        g, c = _ridge_path(x[tr], y[tr], alphas)
        res[a:b] = y[a:b, None] - (x[a:b] @ g + c)
    return res


@dataclass(frozen=True)
class _Config:
    grid: TauGrid
    alphas: tuple[float, ...]
    names: tuple[str, ...]


def _select(bank: _Bank, y: np.ndarray, configs: Sequence[_Config], cycles: Sequence[tuple[int, int]],
            train_mask: np.ndarray | None = None, rule: str = "parsimony") -> tuple[int, float, list[dict[str, Any]]]:
    """(config index, alpha, table) chosen by leave-one-cycle-out free-run error.

    ``rule="parsimony"`` (the default, as :mod:`calibration.calibrate`): the simplest config
    (configs run from simple to rich), then its largest alpha, whose pooled CV RMS is within
    :data:`PARSIMONY` of the best; ``rule="1se"``: whose mean square is within one standard error
    (over folds) of the best's; ``rule="min"``: the best itself."""
    table, mse = [], []
    for cfg in configs:
        x = bank.design(cfg.grid, cfg.names)
        res = _cv_residuals(x, y, cycles, cfg.alphas, train_mask)
        fold = np.array([np.mean(res[a:b] ** 2, axis=0) for a, b in cycles])  # (folds, alphas)
        fold = np.where(np.isfinite(fold), fold, np.inf)
        mse.append(fold)
    pooled = [np.sum(f * np.array([b - a for a, b in cycles])[:, None], axis=0)
              / sum(b - a for a, b in cycles) for f in mse]
    k_best = int(np.argmin([p.min() for p in pooled]))
    i_best = int(np.argmin(pooled[k_best]))
    best = float(pooled[k_best][i_best])
    if rule == "min":
        limit = best
    elif rule == "1se":
        f = mse[k_best][:, i_best]
        limit = best + (float(np.std(f, ddof=1) / math.sqrt(f.size)) if f.size > 1 else 0.0)
    else:
        limit = best * (1 + PARSIMONY) ** 2
    choice = None
    for k, (cfg, p) in enumerate(zip(configs, pooled)):
        ok = np.flatnonzero(p <= limit)
        j = int(ok[np.argmax(np.asarray(cfg.alphas)[ok])]) if ok.size else int(np.argmin(p))
        if choice is None and ok.size:
            choice = (k, j)
        table.append({"grid": cfg.grid.label, "alpha": cfg.alphas[j], "cv_rms_um": math.sqrt(p[j]),
                      "best_alpha": cfg.alphas[int(np.argmin(p))], "best_cv_rms_um": math.sqrt(p.min())})
    assert choice is not None
    k, j = choice
    return k, configs[k].alphas[j], table


# -- the result -------------------------------------------------------------------------------


@dataclass(frozen=True)
class StateSpace:
    """``y = offset + D.v + sum_j x_j``, ``dx_j/dt = (B_j.v - x_j)/tau_j``, v = [n, n^2, u - ref]
    (n in krpm, u in the inputs' units); exact zero-order hold with v held over each step."""

    taus_s: tuple[float, ...]
    drive: np.ndarray  # (states, 2 + inputs): B
    feedthrough: np.ndarray  # (2 + inputs,): D
    offset_um: float
    input_names: tuple[str, ...]
    references: Mapping[str, float]

    def signals(self, speed_rpm: float, inputs: Mapping[str, float] | None = None) -> np.ndarray:
        n = abs(float(speed_rpm)) / SPEED_SCALE_RPM
        u = [float((inputs or {})[k]) - self.references[k] for k in self.input_names]
        return np.array([n, n * n, *u])

    def equilibrium(self, speed_rpm: float, inputs: Mapping[str, float] | None = None) -> np.ndarray:
        return self.drive @ self.signals(speed_rpm, inputs)

    def output_um(self, x: np.ndarray, speed_rpm: float, inputs: Mapping[str, float] | None = None) -> float:
        return float(self.offset_um + self.feedthrough @ self.signals(speed_rpm, inputs) + x.sum())

    def step(self, x: np.ndarray, speed_rpm: float, dt_s: float,
             inputs: Mapping[str, float] | None = None) -> np.ndarray:
        a = np.exp(-dt_s / np.asarray(self.taus_s))
        return a * x + (1 - a) * self.equilibrium(speed_rpm, inputs)


@dataclass(frozen=True, eq=False)
class IdentResult:
    """A fitted model and how it was judged. Gains are per krpm**p (speed) or per unit (inputs)."""

    grid: TauGrid
    input_names: tuple[str, ...]
    references: Mapping[str, float]
    intercept_um: float
    speed_gains_um: np.ndarray  # (2, len(speed_taus)): rows n [um/krpm], n^2 [um/krpm^2]
    input_gains_um: np.ndarray  # (inputs, len(input_taus)) [um/unit]
    alpha: float
    cycles: tuple[tuple[int, int], ...]
    folds: tuple[FoldScore, ...]
    cv_rms_um: float
    cv_max_abs_um: float
    speed_max_rpm: float
    valid_ranges: Mapping[str, tuple[float, float]]
    max_measured_um: float
    baseline: Mapping[str, Any] = field(default_factory=dict)
    nested_folds: tuple[FoldScore, ...] | None = None
    nested_rms_um: float | None = None
    nested_max_abs_um: float | None = None
    selection: tuple[Mapping[str, Any], ...] = ()
    accepted: bool = True
    refusals: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    fit_cpu_s: float = 0.0
    fitted_dt_s: float = 0.0
    segments: tuple[tuple[int, int], ...] = ()
    trained_ranges: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    held_out_residual_um: np.ndarray | None = None
    """Each cycle's free-run residual from a model fitted without it (nested when done)."""

    # -- prediction ---------------------------------------------------------------------

    def _drives(self, t: np.ndarray, speed_rpm: Any, inputs: Mapping[str, Any] | None) -> dict[str, np.ndarray]:
        sp = np.abs(_series("speed_rpm", speed_rpm, t.size))
        np.minimum(sp, SPEED_CLIP * max(self.speed_max_rpm, 1.0), out=sp)
        drives = speed_terms(sp)
        for nm in self.input_names:
            if inputs is None or nm not in inputs:
                raise CalibrationError(f"the model needs input {nm!r}")
            lo, hi = self.valid_ranges[nm]
            u = np.clip(_series(nm, inputs[nm], t.size), lo, hi)
            drives[f"in:{nm}"] = u - self.references[nm]
        return drives

    def predict(self, time_s: Any, speed_rpm: Any, inputs: Mapping[str, Any] | None = None,
                segments: Sequence[tuple[int, int]] | None = None) -> np.ndarray:
        """Free-run elongation [um] over a log: no measured elongation is used. Every state starts
        at equilibrium with the first sample; inputs are deviations from the stored references,
        so after :meth:`settling_time_s` the prediction does not depend on where the log starts.
        |speed| is clipped to ``SPEED_CLIP`` times the calibrated maximum and inputs to their
        valid ranges, so any finite input gives a finite output."""
        t = _times(time_s)
        x = _Bank(t, self._drives(t, speed_rpm, inputs), segments).design(self.grid, self.input_names)
        return self.intercept_um + x @ self.gains

    @property
    def gains(self) -> np.ndarray:
        """All gains in design-column order (speed n, speed n^2, then each input's bank)."""
        return np.concatenate([self.speed_gains_um.ravel(), self.input_gains_um.ravel()])

    def settling_time_s(self, fraction: float = 1e-3) -> float:
        """Time after which a wrong initial state has decayed to ``fraction`` of itself."""
        taus = [*self.grid.speed_taus_s, *self.grid.input_taus_s]
        return max(taus, default=0.0) * math.log(1 / fraction)

    # -- state-space form -----------------------------------------------------------------

    def state_space(self) -> StateSpace:
        """One first-order state per distinct non-zero time constant; static terms feed through."""
        ni = len(self.input_names)
        taus = sorted({t for t in (*self.grid.speed_taus_s, *self.grid.input_taus_s) if t > 0})
        drive = np.zeros((len(taus), 2 + ni))
        feed = np.zeros(2 + ni)
        for j, tau in enumerate(self.grid.speed_taus_s):
            row = feed if tau == 0 else drive[taus.index(tau)]
            row[0] += self.speed_gains_um[0, j]
            row[1] += self.speed_gains_um[1, j]
        for i in range(ni):
            for j, tau in enumerate(self.grid.input_taus_s):
                row = feed if tau == 0 else drive[taus.index(tau)]
                row[2 + i] += self.input_gains_um[i, j]
        return StateSpace(tuple(taus), drive, feed, self.intercept_um, self.input_names,
                          dict(self.references))

    def to_thermal_model(self, dt_s: float, **fields: Any) -> tuple[ThermalModel, ModelState, float]:
        """The speed-only part as the runtime's :class:`ThermalModel`, its state at rest, and the
        constant it lacks: elongation = ``model`` output + ``offset_um``. Exact: state j has
        dissipation 1/tau_j and generation (g_n*n + g_n2*n^2)/tau_j; static terms are elastic."""
        if self.input_names:
            raise CalibrationError("a model with inputs has no ThermalModel form (see state_space)")
        ss = self.state_space()
        states = tuple(ThermalStateCoefficients(
            dissipation_per_s=(1 / tau, 0.0),
            generation_um_per_s=(0.0, float(b[0]) / tau, float(b[1]) / tau, 0.0))
            for tau, b in zip(ss.taus_s, ss.drive))
        model = ThermalModel(fitted_dt_s=dt_s, speed_range_rpm=(0.0, self.speed_max_rpm),
                             states=states, elastic_um=(float(ss.feedthrough[0]), float(ss.feedthrough[1])),
                             form="ident-ridge", **fields)
        return model, ModelState((0.0,) * len(states), 0.0), self.intercept_um

    def to_model(self, form: str, units: Mapping[str, str] | None = None,
                 fallback: Any = None, fit: Mapping[str, Any] | None = None,
                 **fields: Any) -> StateSpaceModel:
        """The runtime's :class:`~compensator.statespace.StateSpaceModel`: exact (the same
        states, gains, references and ranges), so it free-runs a log to :meth:`predict`."""
        ss = self.state_space()
        inputs = []
        for nm in self.input_names:
            lo, hi = self.valid_ranges[nm]
            span = (hi - lo) / 3
            tlo, thi = self.trained_ranges.get(nm, (lo + span, hi - span))
            inputs.append(InputChannel(name=nm, unit=(units or {}).get(nm, "1"),
                                       reference=float(self.references[nm]),
                                       trained_range=(min(tlo, thi), max(tlo, thi)), valid_range=(lo, hi)))
        return StateSpaceModel(
            form=form, fitted_dt_s=self.fitted_dt_s, speed_range_rpm=(0.0, self.speed_max_rpm),
            taus_s=ss.taus_s, drive_um=tuple(tuple(float(v) for v in row) for row in ss.drive),
            feedthrough_um=tuple(float(v) for v in ss.feedthrough), offset_um=float(ss.offset_um),
            inputs=tuple(inputs), max_measured_um=max(self.max_measured_um, 1e-3),
            fallback=fallback, fit=dict(fit or {}), **fields)

    # -- sanity -----------------------------------------------------------------------------

    def steady_range_um(self) -> float:
        """Largest |steady elongation change| the gains imply over the calibrated speed range and
        the inputs' measured ranges (:func:`compensator.statespace.steady_range_um`)."""
        gains = [*self.speed_gains_um.sum(axis=1), *self.input_gains_um.sum(axis=1)]
        inputs = []
        for nm in self.input_names:
            lo, hi = self.valid_ranges[nm]
            span = (hi - lo) / 3  # valid range = measured range widened by its span each side
            inputs.append((self.references[nm], self.trained_ranges.get(nm, (lo + span, hi - span))))
        return steady_range_um(gains, self.speed_max_rpm, inputs)

    def describe(self) -> list[str]:
        lines = [(f"grid {self.grid.label}, alpha {self.alpha:.3g}, "
                  f"{'accepted' if self.accepted else 'REFUSED'}"),
                 f"  leave-one-cycle-out free run: RMS {self.cv_rms_um:.2f} um, max {self.cv_max_abs_um:.2f} um"]
        if self.nested_rms_um is not None:
            lines.append(f"  nested (held-out cycle not used to choose): RMS {self.nested_rms_um:.2f} um, "
                         f"max {self.nested_max_abs_um:.2f} um")
        if self.baseline:
            lines.append(f"  exponential baseline: tau {self.baseline['tau_s'] / 60:.0f} min, "
                         f"RMS {self.baseline['cv_rms_um']:.2f} um")
        lines += [f"  refused: {r}" for r in self.refusals] + [f"  note: {n}" for n in self.notes]
        return lines


# -- fitting --------------------------------------------------------------------------------------


def _validate_grid(grid: TauGrid, dt_s: float) -> None:
    for tau in (*grid.speed_taus_s, *grid.input_taus_s):
        if tau != 0 and not (dt_s <= tau <= MAX_TAU_S):
            raise CalibrationError(f"time constant {tau:g} s is outside {dt_s:g} s (the sample "
                                   f"period) .. {MAX_TAU_S / 86400:g} days")
    if not grid.speed_taus_s:
        raise CalibrationError("the speed bank needs at least one time constant")


def _fit_config(bank: _Bank, y: np.ndarray, cfg: _Config, alpha: float, rows: np.ndarray):
    x = bank.design(cfg.grid, cfg.names)
    g, c = _ridge_path(x[rows], y[rows], (alpha,))
    return g[:, 0], float(c[0])


def fit_ridge_cv(time_s: Any, speed_rpm: Any, elongation_um: Any,
                 inputs: Mapping[str, Any] | None = None, *,
                 cycles: Sequence[tuple[int, int]] | None = None,
                 grids: Sequence[TauGrid] | None = None,
                 alphas: Sequence[float] = DEFAULT_ALPHAS,
                 nested: bool = False, rule: str = "parsimony",
                 segments: Sequence[tuple[int, int]] | None = None) -> IdentResult:
    """Joint ridge identification, α and grid chosen by leave-one-cycle-out free-run RMS.

    ``inputs`` maps a name to a column of the log (temperatures...); their references are the
    log's means. ``cycles`` defaults to :func:`split_cycles`; two or more are needed. ``grids``
    are candidates ordered from simple to rich (default: the one :func:`auto_grid`;
    :func:`candidate_grids` for a search). With ``nested`` every cycle is also predicted by a
    model whose α and grid were chosen without it (the honest figure). ``segments`` are the
    files a log was joined from: the filters restart at each (default: one file).
    """
    cpu0 = time.process_time()
    t = _times(time_s)
    sp = _series("speed_rpm", speed_rpm, t.size)
    y = _series("elongation_um", elongation_um, t.size)
    names = tuple(sorted(inputs)) if inputs else ()
    cyc = tuple(cycles) if cycles is not None else tuple(split_cycles(t, sp))
    if len(cyc) < 2:
        raise CalibrationError("one cycle only: nothing to validate on; record a heat-up and a "
                               "cool-down more (see CYCLE_RULE)")
    if (cyc[0][0] != 0 or cyc[-1][1] != t.size or any(b <= a for a, b in cyc)
            or any(a[1] != b[0] for a, b in itertools.pairwise(cyc))):
        raise CalibrationError("cycles must be non-empty and cover the log in order")
    dt_s = float(np.median(np.diff(t)))
    segs = tuple(segments) if segments else ((0, int(t.size)),)
    cand = list(grids) if grids is not None else [auto_grid(t, sp, cyc, bool(names))]
    for g in cand:
        _validate_grid(g, dt_s)
        if names and not g.input_taus_s:
            raise CalibrationError(f"grid {g.label} has no input bank")
    refs: dict[str, float] = {}
    ranges: dict[str, tuple[float, float]] = {}
    trained: dict[str, tuple[float, float]] = {}
    drives = speed_terms(sp)
    for nm in names:
        u = _series(nm, inputs[nm], t.size)  # type: ignore[index]
        refs[nm] = float(u.mean())
        lo, hi = float(u.min()), float(u.max())
        span = hi - lo
        ranges[nm] = (lo - span, hi + span)
        trained[nm] = (lo, hi)
        drives[f"in:{nm}"] = u - refs[nm]
    bank = _Bank(t, drives, segments)
    configs = [_Config(g, tuple(alphas), names) for g in cand]
    base_cfgs = [_Config(TauGrid((tau,)), (0.0,), ()) for tau in BASELINE_TAUS_S]
    everything = np.ones(t.size, bool)

    k, alpha, table = _select(bank, y, configs, cyc, rule=rule)
    cfg = configs[k]
    res = _cv_residuals(bank.design(cfg.grid, names), y, cyc, (alpha,))[:, 0]
    folds = fold_scores(res, cyc)
    cv_rms, cv_max = pooled_stats(res)

    kb, _, _ = _select(bank, y, base_cfgs, cyc, rule="min")
    bres = _cv_residuals(bank.design(base_cfgs[kb].grid, ()), y, cyc, (0.0,))[:, 0]
    brms, bmax = pooled_stats(bres)
    baseline = {"tau_s": base_cfgs[kb].grid.speed_taus_s[0], "cv_rms_um": brms, "cv_max_abs_um": bmax}

    nested_folds = nested_rms = nested_max = outer = None
    if nested and len(cyc) >= 3:
        outer = np.empty(t.size)
        bouter = np.empty(t.size)
        for i, (a, b) in enumerate(cyc):
            inner = [c for j, c in enumerate(cyc) if j != i]
            mask = everything.copy()
            mask[a:b] = False
            ki, al, _ = _select(bank, y, configs, inner, mask, rule=rule)
            g, c = _fit_config(bank, y, configs[ki], al, mask)
            outer[a:b] = y[a:b] - (bank.design(configs[ki].grid, names)[a:b] @ g + c)
            kbi, _, _ = _select(bank, y, base_cfgs, inner, mask, rule="min")
            g, c = _fit_config(bank, y, base_cfgs[kbi], 0.0, mask)
            bouter[a:b] = y[a:b] - (bank.design(base_cfgs[kbi].grid, ())[a:b] @ g + c)
        nested_folds = fold_scores(outer, cyc)
        nested_rms, nested_max = pooled_stats(outer)
        baseline = {**baseline, "nested_rms_um": pooled_stats(bouter)[0], "nested_max_abs_um": pooled_stats(bouter)[1]}

    gains, intercept = _fit_config(bank, y, cfg, alpha, everything)
    ns = len(cfg.grid.speed_taus_s)
    result = IdentResult(
        grid=cfg.grid, input_names=names, references=refs, intercept_um=intercept,
        speed_gains_um=gains[: 2 * ns].reshape(2, ns),
        input_gains_um=gains[2 * ns:].reshape(len(names), len(cfg.grid.input_taus_s)),
        alpha=alpha, cycles=cyc, folds=folds, cv_rms_um=cv_rms, cv_max_abs_um=cv_max,
        speed_max_rpm=float(np.abs(sp).max()), valid_ranges=ranges,
        max_measured_um=float(np.abs(y).max()), baseline=baseline,
        nested_folds=nested_folds, nested_rms_um=nested_rms, nested_max_abs_um=nested_max,
        selection=tuple(table), fitted_dt_s=dt_s, segments=segs, trained_ranges=trained,
        held_out_residual_um=outer if nested_folds is not None else res,
    )
    refusals, notes = [], []
    if cv_rms > brms:
        refusals.append(f"CV RMS {cv_rms:.2f} um is worse than the exponential baseline's {brms:.2f} um")
    if nested_rms is not None and nested_rms > baseline["nested_rms_um"]:
        refusals.append(f"nested CV RMS {nested_rms:.2f} um is worse than the baseline's "
                        f"{baseline['nested_rms_um']:.2f} um")
    steady = result.steady_range_um()
    if steady > GAIN_BOUND * result.max_measured_um:
        refusals.append(f"the gains imply a steady elongation of {steady:.0f} um, over {GAIN_BOUND:g} x "
                        f"the largest measured ({result.max_measured_um:.1f} um)")
    if alpha in (alphas[0], alphas[-1]) and len(alphas) > 1:
        notes.append(f"alpha {alpha:.3g} is at the end of the grid tried")
    if nested and len(cyc) < 3:
        notes.append("nested cross-validation needs three cycles or more: not done")
    if not any(b - a > 1 and (np.abs(sp[a:b]) <= IDLE_RPM).any() for a, b in cyc):
        notes.append("no cycle has a rest: the cooling time constants are not identifiable")
    cpu = time.process_time() - cpu0
    return replace(result, accepted=not refusals, refusals=tuple(refusals), notes=tuple(notes),
                   fit_cpu_s=cpu)


def hac_covariance(result: IdentResult, time_s: Any, speed_rpm: Any, elongation_um: Any,
                   inputs: Mapping[str, Any] | None = None, maxlags: int | None = None) -> np.ndarray:
    """Newey-West (HAC) covariance of the gains, design-column order (NaN for a constant column).

    Sandwich of the ridge estimator, ``(Z'Z + a*m*I)^-1 S (Z'Z + a*m*I)^-1`` on the standardised
    design Z, ``S`` the HAC covariance of ``z_k * e_k`` (statsmodels' ``S_hac_simple``). Free-run
    residuals are correlated over hours: ``maxlags`` defaults to one hour of samples. It measures
    the variance of the regularised gains, not their bias. Gains of one bank trade off against
    each other, so report derived quantities (a steady elongation, ``w' C w``), not single gains.
    """
    from statsmodels.stats.sandwich_covariance import S_hac_simple

    t = _times(time_s)
    y = _series("elongation_um", elongation_um, t.size)
    segs = result.segments if result.segments and result.segments[-1][1] == t.size else None
    x = _Bank(t, result._drives(t, speed_rpm, inputs), segs).design(result.grid, result.input_names)
    e = y - (result.intercept_um + x @ result.gains)
    mu, sd = x.mean(axis=0), x.std(axis=0)
    keep = sd > 1e-12 * np.maximum(np.abs(mu), 1.0)
    z = (x[:, keep] - mu[keep]) / sd[keep]
    m = y.size
    if maxlags is None:
        maxlags = max(1, round(H / float(np.median(np.diff(t)))))
    bread = np.linalg.inv(z.T @ z + result.alpha * m * np.eye(z.shape[1]))
    meat = S_hac_simple(z * e[:, None], nlags=maxlags)  # a sum over rows, not a mean
    cov_z = bread @ meat @ bread
    cov = np.full((x.shape[1], x.shape[1]), np.nan)
    cov[np.ix_(keep, keep)] = cov_z / np.outer(sd[keep], sd[keep])
    return cov


def hac_stderr(result: IdentResult, time_s: Any, speed_rpm: Any, elongation_um: Any,
               inputs: Mapping[str, Any] | None = None, maxlags: int | None = None) -> np.ndarray:
    """HAC standard errors of the gains (:func:`hac_covariance`), design-column order."""
    cov = hac_covariance(result, time_s, speed_rpm, elongation_um, inputs, maxlags)
    return np.sqrt(np.clip(np.diag(cov), 0, None))


# -- the paper's one-step OLS, scored in free run ---------------------------------------------------


@dataclass(frozen=True)
class PaperFit:
    """``S_k = a*S_{k-1} + b0 + b1*n + b2*n^2 + b3*n^3`` (n in krpm) fitted at period ``dt_s``."""

    a: float
    b_um: tuple[float, float, float, float]
    dt_s: float
    one_step_r2: float

    def predict(self, time_s: Any, speed_rpm: Any, initial_um: float) -> np.ndarray:
        """Free run from ``initial_um`` (its own output fed back). At the fitted period the
        recursion itself; at another Δt its exact zero-order-hold equivalent (0 < a < 1 only)."""
        from scipy.signal import lfilter

        t = _times(time_s)
        n = np.abs(_series("speed_rpm", speed_rpm, t.size)) / SPEED_SCALE_RPM
        b0, b1, b2, b3 = self.b_um
        f = ((b3 * n + b2) * n + b1) * n + b0
        out = np.empty(t.size)
        if t.size == 0:
            return out
        out[0] = initial_um
        dt = np.diff(t)
        with np.errstate(over="ignore", invalid="ignore"):
            if np.allclose(dt, self.dt_s, rtol=1e-9, atol=0):
                y, _ = lfilter([1.0], [1.0, -self.a], f[1:], zi=[self.a * initial_um])
                out[1:] = y
                return out
            if not 0 < self.a < 1:
                raise CalibrationError(f"a = {self.a:.6g}: no continuous form to step at another dt")
            lam = -math.log(self.a) / self.dt_s
            ak = np.exp(-lam * dt)
            gk = -np.expm1(-lam * dt) / (1 - self.a)
            for k in range(1, t.size):
                out[k] = ak[k - 1] * out[k - 1] + gk[k - 1] * f[k]
        return out


def fit_paper_ols(time_s: Any, speed_rpm: Any, elongation_um: Any,
                  train: np.ndarray | None = None) -> PaperFit:
    """The paper's eqs. 11-12 by OLS one step ahead on the measured S[k-1]; a row k is used when
    samples k-1 and k are both in ``train`` (default: all)."""
    t = _times(time_s)
    n = np.abs(_series("speed_rpm", speed_rpm, t.size)) / SPEED_SCALE_RPM
    s = _series("elongation_um", elongation_um, t.size)
    use = np.ones(t.size, bool) if train is None else np.asarray(train, bool)
    rows = np.flatnonzero(use[1:] & use[:-1]) + 1
    if rows.size < 6:
        raise CalibrationError("too few rows for the paper's OLS")
    nk = n[rows]
    x = np.column_stack([s[rows - 1], np.ones_like(nk), nk, nk**2, nk**3])
    coef, *_ = np.linalg.lstsq(x, s[rows], rcond=None)
    r = s[rows] - x @ coef
    r2 = 1 - float(r @ r) / float(np.sum((s[rows] - s[rows].mean()) ** 2))
    dt = float(np.median(np.diff(t)[rows - 1]))
    return PaperFit(float(coef[0]), tuple(float(v) for v in coef[1:]), dt, r2)  # type: ignore[arg-type]


def paper_ols_cv(time_s: Any, speed_rpm: Any, elongation_um: Any,
                 cycles: Sequence[tuple[int, int]], restart: bool = False) -> dict[str, Any]:
    """Leave-one-cycle-out free run of the paper's OLS. The free run starts from the log's first
    measured elongation and runs over the whole log; with ``restart`` it starts again from the
    held-out cycle's first measured value (the most favourable reading of the paper)."""
    t = _times(time_s)
    y = _series("elongation_um", elongation_um, t.size)
    res = np.empty(t.size)
    fits = []
    for a, b in cycles:
        tr = np.ones(t.size, bool)
        tr[a:b] = False
        fit = fit_paper_ols(t, speed_rpm, y, tr)
        fits.append(fit)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if restart:
                pred = fit.predict(t[a:b], np.asarray(speed_rpm, float)[a:b], float(y[a]))
            else:
                pred = fit.predict(t, speed_rpm, float(y[0]))[a:b]
        res[a:b] = y[a:b] - pred
    rms, mx = pooled_stats(res)
    return {"folds": fold_scores(res, cycles), "cv_rms_um": rms, "cv_max_abs_um": mx,
            "a": [f.a for f in fits], "one_step_r2": [f.one_step_r2 for f in fits]}
