"""Ridge filter banks: one joint, regularised linear identification, scored in free run.

For fixed time constants the free-run output of parallel first-order states is linear in every
gain, so the whole model is one design matrix: the speed terms n and n² (|speed| in krpm) each
through a bank of first-order filters (:func:`compensator.filters.filter_bank`, exact
zero-order hold at any Δt, each filter starting at equilibrium with its first input), and each
extra input (temperatures...) as a deviation from a *fixed* reference stored in the model (the
training mean) through its own bank. A time constant of 0 is a static term. Gains by ridge
regression on standardised columns with an unpenalised intercept; α (and, on request, the τ grid
among a few candidates) is chosen by leave-one-fold-out free-run RMS on the measured rows
(:func:`fit`); ``nested=True`` also gives the honest figure where the held-out fold took no part
in choosing α or the grid. The default grid follows from the log (:func:`auto_grid`).

The result maps exactly onto the runtime's :class:`~compensator.statespace.StateSpaceModel`
(:meth:`RidgeFit.to_model`): one first-order state per distinct τ. Its sanity: time constants
between the sample period and :data:`~compensator.statespace.MAX_TAU_S` (or 0), and a steady
elongation over the calibrated ranges at most :data:`~compensator.statespace.GAIN_BOUND` times the
largest measured. Units are in the names; n is always |speed| / 1000 (krpm). Pure.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from compensator.errors import CalibrationError, ModelError
from compensator.expected import distance_outside
from compensator.filters import filter_bank
from compensator.fitrecord import FitRecord
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

from .. import folds as fl
from ..checks import as_series, as_times
from ..dataset import Dataset, from_arrays
from ..metrics import PARSIMONY, FoldScore, fold_scores, measured_stats

H = 3600.0
FIRST_TAU_S = 600.0
"""The shortest non-static time constant of the default banks (or four samples, if longer)."""
TAU_RATIO = 3.0
"""Ratio between neighbouring time constants of the default speed bank."""
DEFAULT_ALPHAS = tuple(float(a) for a in np.geomspace(1e-8, 100.0, 31))
"""Ridge penalties tried, per row on standardised columns: ||y - Xb||^2/m + alpha*||b||^2."""
BASELINE_TAUS_S = tuple(float(t) for t in np.geomspace(300.0, 24 * H, 16))
"""Time constants the exponential baseline (:mod:`.baseline`) chooses among."""

Folds = Sequence[tuple[int, int]]


@dataclass(frozen=True)
class TauGrid:
    """The filter banks: time constants [s] for the speed terms and for each input (0 = static)."""

    speed_taus_s: tuple[float, ...]
    input_taus_s: tuple[float, ...] = ()

    @property
    def label(self) -> str:
        def fmt(taus: tuple[float, ...]) -> str:
            return (
                ",".join(
                    "static" if t == 0 else (f"{t / H:g}h" if t >= H else f"{t / 60:g}min")
                    for t in taus
                )
                or "-"
            )

        return f"speed[{fmt(self.speed_taus_s)}] inputs[{fmt(self.input_taus_s)}]"

    @property
    def size(self) -> int:
        return len(self.speed_taus_s) + len(self.input_taus_s)


def auto_grid(time_s: Any, speed_rpm: Any, cycles: Folds, with_inputs: bool) -> TauGrid:
    """The default banks, from the log: a static term and a ladder of time constants, ratio
    :data:`TAU_RATIO`, from :data:`FIRST_TAU_S` up to the first at or beyond
    :func:`calibration.folds.longest_stretch_s`; the inputs get the static term and every other
    rung from the second (fewer columns: 16 sensors already bring many)."""
    t = np.asarray(time_s, float)
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    first = max(FIRST_TAU_S, 4 * dt)
    longest = min(max(fl.longest_stretch_s(t, speed_rpm, cycles), first), MAX_TAU_S)
    ladder = [first]
    while ladder[-1] < longest and ladder[-1] * TAU_RATIO <= MAX_TAU_S:
        ladder.append(ladder[-1] * TAU_RATIO)
    return TauGrid((0.0, *ladder), (0.0, *ladder[1::2]) if with_inputs else ())


def candidate_grids(base: TauGrid) -> list[TauGrid]:
    """Optional grid search (``fit(grids=...)``), simple to rich: the speed ladder cut short or
    extended by one rung, inputs static only, on every other rung or on every rung."""
    sp = [t for t in base.speed_taus_s if t > 0]
    longer = (*sp, sp[-1] * TAU_RATIO) if sp[-1] * TAU_RATIO <= MAX_TAU_S else tuple(sp)
    speeds = [(0.0, *sp[:-1]) if len(sp) > 1 else (0.0, *sp), (0.0, *sp), (0.0, *longer)]
    if not base.input_taus_s:
        return [TauGrid(s) for s in speeds]
    inputs = [(0.0,), base.input_taus_s, (0.0, *sp)]
    return [TauGrid(s, i) for i in inputs for s in speeds]


def speed_terms(speed_rpm: np.ndarray) -> dict[str, np.ndarray]:
    """The speed drives: n and n^2, n = |speed| in krpm."""
    n = np.abs(speed_rpm) / SPEED_SCALE_RPM
    return {"n": n, "n2": n * n}


class FilterBank:
    """Filtered columns of a dataset (each segment on its own: every filter restarts at
    equilibrium at a segment's start), computed once per (drive, tau) and reused."""

    def __init__(
        self,
        time_s: np.ndarray,
        drives: Mapping[str, np.ndarray],
        segments: Sequence[tuple[int, int]] | None = None,
    ):
        self.time_s = time_s
        self.drives = drives
        self.segments = tuple(segments) if segments else ((0, int(time_s.size)),)
        self.cache: dict[tuple[str, float], np.ndarray] = {}

    def column(self, drive: str, tau: float) -> np.ndarray:
        key = (drive, tau)
        if key not in self.cache:
            u = self.drives[drive]
            self.cache[key] = np.concatenate(
                [filter_bank(self.time_s[a:b], u[a:b], (tau,))[:, 0] for a, b in self.segments]
            )
        return self.cache[key]

    def design(self, grid: TauGrid, names: Sequence[str]) -> np.ndarray:
        cols = [self.column(d, tau) for d in ("n", "n2") for tau in grid.speed_taus_s]
        cols += [self.column(f"in:{nm}", tau) for nm in names for tau in grid.input_taus_s]
        return np.column_stack(cols)


def ridge_path(
    x: np.ndarray, y: np.ndarray, alphas: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
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


def cv_residuals(
    x: np.ndarray,
    y: np.ndarray,
    measured: np.ndarray,
    folds: Folds,
    alphas: Sequence[float],
    train: np.ndarray | None = None,
) -> np.ndarray:
    """Held-out residuals [um] (rows, alphas) of leave-one-fold-out ridge fitted on the measured
    rows (within ``train``); NaN on every row not measured or in no fold."""
    base = measured if train is None else measured & train
    res = np.full((y.size, len(alphas)), np.nan)
    for a, b in folds:
        tr = fl.without(y.size, (a, b), base)
        if tr.sum() < 2:
            raise CalibrationError(
                f"rows {a}..{b - 1} held out leave fewer than two measured rows to fit on"
            )
        g, c = ridge_path(x[tr], y[tr], alphas)
        rows = a + np.flatnonzero(measured[a:b])
        res[rows] = y[rows, None] - (x[rows] @ g + c)
    return res


FORWARD_FIRST = 2
"""Rolling origin starts predicting with this many folds of past: one fold alone (a single
heat-up) says too little about the next to judge a penalty by."""


def forward_residuals(
    x: np.ndarray,
    y: np.ndarray,
    measured: np.ndarray,
    folds: Folds,
    alphas: Sequence[float],
    train: np.ndarray | None = None,
    first: int = FORWARD_FIRST,
    splits: Sequence[fl.Split] | None = None,
) -> np.ndarray:
    """Held-out residuals [um] (rows, alphas) of rolling-origin ridge: each fold from index
    ``first`` predicted by gains fitted on the measured rows of the folds before it (within
    ``train``); NaN on the earlier folds and on every row not measured. ``splits`` (the past,
    the stretch predicted) replace the whole folds when given."""
    base = measured if train is None else measured & train
    res = np.full((y.size, len(alphas)), np.nan)
    for past, (a, b) in fl.forward_splits(folds, first) if splits is None else splits:
        tr = fl.rows_of(y.size, past, base)
        if tr.sum() < 2:
            continue
        g, c = ridge_path(x[tr], y[tr], alphas)
        rows = a + np.flatnonzero(measured[a:b])
        res[rows] = y[rows, None] - (x[rows] @ g + c)
    return res


def _pooled_mse(res: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Mean square per alpha over ``rows`` (inf where it is not finite); zero over no rows, so
    that it never outweighs another figure in a maximum."""
    if rows.size == 0:
        return np.zeros(res.shape[1])
    with np.errstate(over="ignore", invalid="ignore"):
        p = np.mean(res[rows] ** 2, axis=0)
    return np.where(np.isfinite(p), p, np.inf)


@dataclass(frozen=True)
class Config:
    """One configuration tried: a grid, the α values and the inputs."""

    grid: TauGrid
    alphas: tuple[float, ...]
    names: tuple[str, ...]


def select(
    bank: FilterBank,
    y: np.ndarray,
    measured: np.ndarray,
    configs: Sequence[Config],
    folds: Folds,
    train: np.ndarray | None = None,
    rule: str = "parsimony",
    forward: bool = True,
) -> tuple[int, float, list[dict[str, Any]]]:
    """(config index, alpha, table) chosen by free-run error on the measured rows of held-out
    folds: leave-one-fold-out and, with ``forward``, rolling origin (each fold predicted from
    the folds before it). A config is judged by the worse of the two mean squares, so one that
    does well backwards but badly forwards is not chosen.

    ``rule="parsimony"`` (the default): the simplest config (configs run from simple to rich),
    then its largest alpha, whose figure is within :data:`~calibration.metrics.PARSIMONY` of the
    best; ``rule="1se"``: whose mean square is within one standard error (over folds) of the
    best's; ``rule="min"``: the best itself."""
    scored = [a + np.flatnonzero(measured[a:b]) for a, b in folds]
    rows = np.concatenate(scored)
    later = np.concatenate(scored[FORWARD_FIRST:]) if len(scored) > FORWARD_FIRST else rows[:0]
    pooled, per_fold, loco, ahead = [], [], [], []
    for cfg in configs:
        x = bank.design(cfg.grid, cfg.names)
        res = cv_residuals(x, y, measured, folds, cfg.alphas, train)
        p = _pooled_mse(res, rows)
        if rule == "1se":  # the only rule that reads the figure per fold
            with np.errstate(over="ignore", invalid="ignore"):
                f = np.array([np.mean(res[r] ** 2, axis=0) for r in scored])  # (folds, alphas)
            per_fold.append(np.where(np.isfinite(f), f, np.inf))
        if forward and later.size:
            fres = forward_residuals(x, y, measured, folds, cfg.alphas, train)
            q = _pooled_mse(
                fres, later[~np.isnan(fres[later, 0])]
            )  # a fold with no past to fit on: not scored
        else:
            q = np.zeros_like(p)
        loco.append(p)
        ahead.append(q)
        pooled.append(np.maximum(p, q))
    k_best = int(np.argmin([p.min() for p in pooled]))
    i_best = int(np.argmin(pooled[k_best]))
    best = float(pooled[k_best][i_best])
    if rule == "min":
        limit = best
    elif rule == "1se":
        f = per_fold[k_best][:, i_best]
        limit = best + (float(np.std(f, ddof=1) / math.sqrt(f.size)) if f.size > 1 else 0.0)
    else:
        limit = best * (1 + PARSIMONY) ** 2
    choice, table = None, []
    for k, (cfg, p) in enumerate(zip(configs, pooled)):
        ok = np.flatnonzero(p <= limit)
        j = int(ok[np.argmax(np.asarray(cfg.alphas)[ok])]) if ok.size else int(np.argmin(p))
        if choice is None and ok.size:
            choice = (k, j)
        table.append(
            {
                "grid": cfg.grid.label,
                "alpha": cfg.alphas[j],
                "score_rms_um": math.sqrt(p[j]),
                "cv_rms_um": math.sqrt(loco[k][j]),
                "forward_rms_um": math.sqrt(ahead[k][j]) if forward and later.size else None,
                "best_alpha": cfg.alphas[int(np.argmin(p))],
                "best_score_rms_um": math.sqrt(p.min()),
            }
        )
    if choice is None:
        raise CalibrationError(
            "no configuration could be scored"
        )  # unreachable: best is one of them
    k, j = choice
    return k, configs[k].alphas[j], table


def select_chained(
    bank: FilterBank,
    y: np.ndarray,
    measured: np.ndarray,
    config: Config,
    blocks: Folds,
    train: np.ndarray | None = None,
) -> tuple[float, list[dict[str, Any]]] | None:
    """(alpha, table) chosen on forward-chained ``blocks`` (half cycles,
    :func:`calibration.folds.halves`): each from the third predicted in free run by gains fitted on
    the blocks before it (with two blocks, a heat-up and its cool-down, the second from the
    first); the largest alpha whose pooled mean square is within
    :data:`~calibration.metrics.PARSIMONY` of the best. Only the future judges the penalty, as a
    user fitting on the past and running on the next shift would. None when no block can be
    predicted (fewer than two blocks)."""
    if len(blocks) < 2:
        return None
    x = bank.design(config.grid, config.names)
    first = 1 if len(blocks) == 2 else 2
    res = forward_residuals(x, y, measured, blocks, config.alphas, train, first=first)
    rows = np.flatnonzero(~np.isnan(res[:, 0]))
    if rows.size == 0:
        return None
    p = _pooled_mse(res, rows)
    ok = np.flatnonzero(p <= float(p.min()) * (1 + PARSIMONY) ** 2)
    j = int(ok[np.argmax(np.asarray(config.alphas)[ok])])
    return config.alphas[j], [
        {
            "grid": config.grid.label,
            "alpha": config.alphas[j],
            "score_rms_um": math.sqrt(p[j]),
            "chained_blocks": len(blocks),
            "best_alpha": config.alphas[int(np.argmin(p))],
            "best_score_rms_um": math.sqrt(float(p.min())),
        }
    ]


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


@dataclass(frozen=True, eq=False)
class RidgeFit:
    """A fitted ridge bank and how it was judged. Gains are per krpm**p (speed) or per unit."""

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
    """Each fold's free-run residual from a model fitted without it (nested when done); NaN on
    the rows not scored."""
    forward_folds: tuple[FoldScore, ...] | None = None
    forward_rms_um: float | None = None
    forward_max_abs_um: float | None = None
    """Rolling origin, honest: each fold from the third predicted by a model whose gains, alpha
    and grid were chosen on the folds before it only (None with fewer than three folds)."""
    forward_residual_um: np.ndarray | None = None
    """The rolling-origin residual behind ``forward_rms_um``; NaN on the rows not predicted."""
    structure_detail: str = ""
    """How the inputs shared strength (:data:`STRUCTURES`), in words."""
    forward_clipped_residual_um: np.ndarray | None = None
    """The rolling-origin residual with each input held to the range its past saw (the
    ``clip`` extrapolation); None without inputs."""
    forward_distance: np.ndarray | None = None
    """On each row predicted forward, how far the inputs lay outside the range their past saw
    (:func:`compensator.expected.distance_outside`); None without inputs."""
    forward_rms_by_alpha_um: tuple[float, ...] = ()
    """The same rolling origin with the chosen grid at each alpha tried, held fixed: how much
    the penalty alone moves the forward error."""

    # -- prediction ---------------------------------------------------------------------

    def drives(
        self, t: np.ndarray, speed_rpm: Any, inputs: Mapping[str, Any] | None
    ) -> dict[str, np.ndarray]:
        sp = np.abs(as_series("speed_rpm", speed_rpm, t.size))
        np.minimum(sp, SPEED_CLIP * max(self.speed_max_rpm, 1.0), out=sp)
        out = speed_terms(sp)
        for nm in self.input_names:
            if inputs is None or nm not in inputs:
                raise CalibrationError(f"the model needs input {nm!r}")
            lo, hi = self.valid_ranges[nm]
            u = np.clip(as_series(nm, inputs[nm], t.size), lo, hi)
            out[f"in:{nm}"] = u - self.references[nm]
        return out

    def predict(
        self,
        time_s: Any,
        speed_rpm: Any,
        inputs: Mapping[str, Any] | None = None,
        segments: Sequence[tuple[int, int]] | None = None,
    ) -> np.ndarray:
        """Free-run elongation [um] over a log: no measured elongation is used. Every state starts
        at equilibrium with the first sample; inputs are deviations from the stored references,
        so after :meth:`settling_time_s` the prediction does not depend on where the log starts.
        |speed| is clipped to ``SPEED_CLIP`` times the calibrated maximum and inputs to their
        valid ranges, so any finite input gives a finite output."""
        t = as_times(time_s)
        x = FilterBank(t, self.drives(t, speed_rpm, inputs), segments).design(
            self.grid, self.input_names
        )
        return self.intercept_um + x @ self.gains

    def predict_dataset(self, ds: Dataset) -> np.ndarray:
        """:meth:`predict` over a dataset, each segment from its own start."""
        return self.predict(
            ds.time_s, ds.speed_rpm, ds.inputs if self.input_names else None, ds.segments
        )

    @property
    def gains(self) -> np.ndarray:
        """All gains in design-column order (speed n, speed n^2, then each input's bank)."""
        return np.concatenate([self.speed_gains_um.ravel(), self.input_gains_um.ravel()])

    @property
    def slowest_tau_s(self) -> float:
        return max((*self.grid.speed_taus_s, *self.grid.input_taus_s))

    def settling_time_s(self, fraction: float = 1e-3) -> float:
        """Time after which a wrong initial state has decayed to ``fraction`` of itself."""
        return self.slowest_tau_s * math.log(1 / fraction)

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
        return StateSpace(
            tuple(taus), drive, feed, self.intercept_um, self.input_names, dict(self.references)
        )

    def to_thermal_model(
        self, dt_s: float, **fields: Any
    ) -> tuple[ThermalModel, ModelState, float]:
        """The speed-only part as the runtime's :class:`ThermalModel`, its state at rest, and the
        constant it lacks: elongation = ``model`` output + ``offset_um``. Exact: state j has
        dissipation 1/tau_j and generation (g_n*n + g_n2*n^2)/tau_j; static terms are elastic."""
        if self.input_names:
            raise CalibrationError("a model with inputs has no ThermalModel form (see state_space)")
        ss = self.state_space()
        states = tuple(
            ThermalStateCoefficients(
                dissipation_per_s=(1 / tau, 0.0),
                generation_um_per_s=(0.0, float(b[0]) / tau, float(b[1]) / tau, 0.0),
            )
            for tau, b in zip(ss.taus_s, ss.drive)
        )
        model = ThermalModel(
            fitted_dt_s=dt_s,
            speed_range_rpm=(0.0, self.speed_max_rpm),
            states=states,
            elastic_um=(float(ss.feedthrough[0]), float(ss.feedthrough[1])),
            form="ident-ridge",
            **fields,
        )
        return model, ModelState((0.0,) * len(states), 0.0), self.intercept_um

    def to_model(
        self,
        form: str,
        units: Mapping[str, str] | None = None,
        fallback: Any = None,
        fit: Mapping[str, Any] | None = None,
        **fields: Any,
    ) -> StateSpaceModel:
        """The runtime's :class:`~compensator.statespace.StateSpaceModel`: exact (the same
        states, gains, references and ranges), so it free-runs a log to :meth:`predict`."""
        ss = self.state_space()
        inputs = []
        for nm in self.input_names:
            lo, hi = self.valid_ranges[nm]
            span = (hi - lo) / 3
            tlo, thi = self.trained_ranges.get(nm, (lo + span, hi - span))
            inputs.append(
                InputChannel(
                    name=nm,
                    unit=(units or {}).get(nm, "1"),
                    reference=float(self.references[nm]),
                    trained_range=(min(tlo, thi), max(tlo, thi)),
                    valid_range=(lo, hi),
                )
            )
        return StateSpaceModel(
            form=form,
            fitted_dt_s=self.fitted_dt_s,
            speed_range_rpm=(0.0, self.speed_max_rpm),
            taus_s=ss.taus_s,
            drive_um=tuple(tuple(float(v) for v in row) for row in ss.drive),
            feedthrough_um=tuple(float(v) for v in ss.feedthrough),
            offset_um=float(ss.offset_um),
            inputs=tuple(inputs),
            max_measured_um=max(self.max_measured_um, 1e-3),
            fallback=fallback,
            fit=FitRecord.of(dict(fit or {})),
            **fields,
        )

    # -- sanity -----------------------------------------------------------------------------

    def steady_range_um(self) -> float:
        """Largest |steady elongation change| the gains imply over the calibrated speed range and
        the inputs' measured ranges (:func:`compensator.statespace.steady_range_um`)."""
        gains = [*self.speed_gains_um.sum(axis=1), *self.input_gains_um.sum(axis=1)]
        inputs = []
        for nm in self.input_names:
            lo, hi = self.valid_ranges[nm]
            span = (hi - lo) / 3  # valid range = measured range widened by its span each side
            inputs.append(
                (self.references[nm], self.trained_ranges.get(nm, (lo + span, hi - span)))
            )
        return steady_range_um(gains, self.speed_max_rpm, inputs)

    def describe(self) -> list[str]:
        lines = [
            (
                f"grid {self.grid.label}, alpha {self.alpha:.3g}, "
                f"{'accepted' if self.accepted else 'REFUSED'}"
            ),
            f"  leave-one-fold-out free run: RMS {self.cv_rms_um:.2f} um, max {self.cv_max_abs_um:.2f} um",
        ]
        if self.nested_rms_um is not None:
            lines.append(
                f"  nested (held-out fold not used to choose): RMS {self.nested_rms_um:.2f} um, "
                f"max {self.nested_max_abs_um:.2f} um"
            )
        if self.baseline:
            lines.append(
                f"  exponential baseline: tau {self.baseline['tau_s'] / 60:.0f} min, "
                f"RMS {self.baseline['cv_rms_um']:.2f} um"
            )
        lines += [f"  refused: {r}" for r in self.refusals] + [f"  note: {n}" for n in self.notes]
        return lines


# -- fitting --------------------------------------------------------------------------------------


def _validate_grid(grid: TauGrid, dt_s: float, names: Sequence[str]) -> None:
    for tau in (*grid.speed_taus_s, *grid.input_taus_s):
        if tau != 0 and not (dt_s <= tau <= MAX_TAU_S):
            raise CalibrationError(
                f"time constant {tau:g} s is outside {dt_s:g} s (the sample "
                f"period) .. {MAX_TAU_S / 86400:g} days"
            )
    if not grid.speed_taus_s:
        raise CalibrationError("the speed bank needs at least one time constant")
    if names and not grid.input_taus_s:
        raise CalibrationError(f"grid {grid.label} has no input bank")


STRUCTURES = ("all", "pca", "few", "bounded")
"""How the inputs enter a ridge bank (:func:`fit`)."""
MAX_COMPONENTS = 4
"""Principal components tried, one to this many."""
MAX_FEW = 4
"""Inputs a greedy forward selection keeps at most."""
STEEL_EXPANSION_PER_K = 11.5e-6
"""Linear expansion of steel and cast iron, 10-13e-6 per K (ISO 1 and the thermal error
literature, docs/REFERENCES.md): the middle of that range."""
THERMAL_LOOP_MM = 1000.0
"""The longest structural path a spindle sensor can stand for: a metre of machine between the
tool and the table, more than a spindle housing and column of a machining centre."""
BOUND_UM_PER_K = STEEL_EXPANSION_PER_K * THERMAL_LOOP_MM * 1000.0
"""The largest steady sensitivity to one temperature that physics allows: a whole thermal loop
of steel warming with that sensor, 11.5 um/K. Two neighbouring sensors at +16 and -11 um/K are
gains trading off against each other, not expansion."""
TEMPERATURE_UNITS = ("degC", "K")
MIN_VALID_MARGIN_K = 10.0
"""A temperature's valid range reaches at least this far beyond what calibration saw (else one
span of it): a reading there is a warmer or cooler machine, for the extrapolation chosen by
data to handle; beyond, a sensor fault. On the real record, one cycle's 1-2 K span made the
next half cycle's readings "invalid" on five sensors, held at the range's end: 3.26 um RMS
where the readings taken as they were gave 2.45."""


def _components(
    drives: Mapping[str, np.ndarray], names: Sequence[str], rows: np.ndarray
) -> dict[str, tuple[np.ndarray, float]]:
    """The principal components of the inputs standardised on ``rows``: name -> (the weight of
    each input's deviation, in 1/unit, and the share of variance). Temperatures on one casting
    move together; a few components carry what 16 nearly collinear gains would trade off."""
    u = np.column_stack([drives[f"in:{nm}"][rows] for nm in names])
    sd = u.std(axis=0)
    sd = np.where(sd > 1e-12, sd, 1.0)
    _, sv, vt = np.linalg.svd((u - u.mean(axis=0)) / sd, full_matrices=False)
    share = sv**2 / max(float(np.sum(sv**2)), 1e-300)
    count = min(MAX_COMPONENTS, len(names))
    return {f"pc{j + 1}": (vt[j] / sd, float(share[j])) for j in range(count)}


def _bounded(
    bank: FilterBank, y: np.ndarray, rows: np.ndarray, configs: Sequence[Config], limits: np.ndarray
) -> list[Config]:
    """``configs`` with only the α whose steady sensitivities (the sum of an input's gains over
    its filters, each of unit steady gain) lie within ``limits``, fitted on ``rows``; a config
    with none left is dropped. :class:`CalibrationError` when none is left at all."""
    out = []
    for cfg in configs:
        x = bank.design(cfg.grid, cfg.names)
        g, _ = ridge_path(x[rows], y[rows], cfg.alphas)
        ns = 2 * len(cfg.grid.speed_taus_s)
        sens = (
            g[ns:].reshape(len(cfg.names), len(cfg.grid.input_taus_s), len(cfg.alphas)).sum(axis=1)
        )
        ok = np.all(np.abs(sens) <= limits[:, None], axis=0)
        if ok.any():
            out.append(replace(cfg, alphas=tuple(a for a, k in zip(cfg.alphas, ok) if k)))
    if not out:
        raise CalibrationError(
            f"no penalty brings every steady sensitivity within {BOUND_UM_PER_K:.1f} um/K"
        )
    return out


def _mix(
    drives: dict[str, np.ndarray],
    mixes: Mapping[str, tuple[np.ndarray, float]],
    names: Sequence[str],
) -> None:
    """Each principal component's drive, from the input drives of ``names``."""
    for pc, (w, _) in mixes.items():
        drives[f"in:{pc}"] = sum(wi * drives[f"in:{nm}"] for wi, nm in zip(w, names))


def _held_to_range(
    bank: FilterBank,
    ds: Dataset,
    train: np.ndarray,
    used: Sequence[str],
    mixes: Mapping[str, tuple[np.ndarray, float]],
    cfg: Config,
    end: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The design of ``cfg`` over rows ``..end`` with every input of ``used`` held to the range
    it had on ``train`` (clipped), and each row's distance outside that range."""
    lo = np.array([float(np.min(ds.inputs[nm][train])) for nm in used])
    hi = np.array([float(np.max(ds.inputs[nm][train])) for nm in used])
    u = np.column_stack([np.asarray(ds.inputs[nm], float) for nm in used])
    d = distance_outside(u, lo, hi)
    drives = dict(bank.drives)
    for j, nm in enumerate(used):  # a clip shifts the deviation by the same amount
        drives[f"in:{nm}"] = bank.drives[f"in:{nm}"] + (np.clip(u[:, j], lo[j], hi[j]) - u[:, j])
    _mix(drives, mixes, used)
    held = FilterBank(
        bank.time_s[:end],
        {k: v[:end] for k, v in drives.items()},
        [(a, min(b, end)) for a, b in bank.segments if a < end],
    )
    held.cache.update({k: v[:end] for k, v in bank.cache.items() if k[0] in ("n", "n2")})
    xe = held.design(cfg.grid, cfg.names)
    x = np.zeros((bank.time_s.size, xe.shape[1]))
    x[:end] = xe
    return x, d


def _greedy(
    bank: FilterBank,
    y: np.ndarray,
    measured: np.ndarray,
    grids: Sequence[TauGrid],
    alphas: tuple[float, ...],
    names: Sequence[str],
    folds: Folds,
    train: np.ndarray | None,
    rule: str,
    penalty_forward: bool,
) -> tuple[Config, float, list[dict[str, Any]]]:
    """Forward selection of inputs: add the one that lowers the held-out error most, while it
    lowers it by more than PARSIMONY, up to :data:`MAX_FEW`; then α and grid as :func:`select`."""
    kept: tuple[str, ...] = ()
    best = math.inf
    while len(kept) < MAX_FEW:
        trials = [tuple(sorted((*kept, nm))) for nm in names if nm not in kept]
        if not trials:
            break
        scores = []
        for trial in trials:
            configs = [Config(g, alphas, trial) for g in grids]
            _, _, tab = select(
                bank, y, measured, configs, folds, train, rule="min", forward=penalty_forward
            )
            scores.append(min(r["best_score_rms_um"] for r in tab))
        j = int(np.argmin(scores))
        if not scores[j] < best * (1 - PARSIMONY):
            break
        kept, best = trials[j], scores[j]
    configs = [Config(g, alphas, kept) for g in grids]
    k, al, tab = select(
        bank, y, measured, configs, folds, train, rule=rule, forward=penalty_forward
    )
    return configs[k], al, tab


def fit(
    ds: Dataset,
    rows: np.ndarray | None = None,
    *,
    grids: Sequence[TauGrid] | None = None,
    input_names: Sequence[str] = (),
    alphas: Sequence[float] = DEFAULT_ALPHAS,
    nested: bool = False,
    rule: str = "parsimony",
    forward: bool = True,
    penalty_forward: bool = False,
    structure: str = "all",
    units: Mapping[str, str] | None = None,
    alpha_by: str = "folds",
) -> RidgeFit:
    """Ridge banks fitted on the measured rows of ``rows`` (default: all), α and grid chosen by
    leave-one-fold-out free-run error on the measured rows of ``ds.folds``.

    ``grids`` are candidates ordered from simple to rich (default: :func:`auto_grid`). Inputs
    (``input_names``, columns of ``ds``) enter as deviations from their training mean. With
    ``nested`` every fold is also predicted by a model whose α and grid were chosen without it
    (the honest figure; three folds or more). With ``forward`` every fold from the third is also
    predicted by a model chosen and fitted on the folds before it only (the honest forward
    figure, which the identification's choice reads). ``penalty_forward`` also judges α and the
    grid by the worse of leave-one-fold-out and rolling-origin error (:func:`select`); it is off
    by default because on the real record it made the forward error worse (a larger α, more
    bias: docs/IDENTIFICATION.md). Refusals: the gain bound only (the exponential baseline is judged by
    the caller, :func:`fit_ridge_cv` or the identification).

    ``structure`` says how the inputs share strength (:data:`STRUCTURES`): ``all``, a bank per
    input; ``pca``, a bank per principal component of the standardised inputs, their number
    chosen by cross-validation (the model still reads every input: the gains map back exactly);
    ``few``, a bank per input for the few inputs a greedy forward selection keeps (up to
    :data:`MAX_FEW`, each kept only when it lowers the held-out error by more than PARSIMONY);
    the model then reads those inputs only; ``bounded``, a bank per input with α kept to those
    whose steady sensitivity to every temperature (``units`` says which inputs are, in degC or K)
    stays within :data:`BOUND_UM_PER_K`: shrunk until physically plausible.

    ``alpha_by="chained"`` chooses α (one grid only) on forward-chained half cycles
    (:func:`select_chained`) instead of leave-one-fold-out; where the past holds fewer than three
    half cycles it falls back to leave-one-fold-out.

    Forward splits are origins every half cycle (:func:`calibration.folds.forward_of`) when the
    folds are cycles, whole folds from the third when they are blocks of one cycle."""
    cpu0 = time.process_time()
    t = as_times(ds.time_s)
    sp = as_series("speed_rpm", ds.speed_rpm, t.size)
    y = np.asarray(ds.elongation_um, dtype=float)
    if y.shape != t.shape or np.isinf(y).any():
        raise CalibrationError("elongation_um: one value per row, a number or NaN (not measured)")
    measured = ds.measured if rows is None else ds.measured & rows
    folds = tuple(ds.folds)
    if len(folds) < 2:
        raise CalibrationError(
            "one cycle only: nothing to validate on; record a heat-up and a "
            "cool-down more (see CYCLE_RULE)"
        )
    if any(not measured[a:b].any() for a, b in folds):
        raise CalibrationError(
            "two folds or more, each with a measured row, are needed to validate"
        )
    names = tuple(sorted(input_names))
    if alpha_by not in ("folds", "chained"):
        raise CalibrationError(f"alpha_by must be 'folds' or 'chained', got {alpha_by!r}")
    dt_s = ds.dt_s
    cand = list(grids) if grids is not None else [auto_grid(t, sp, ds.cycles, bool(names))]
    for grid in cand:
        _validate_grid(grid, dt_s, names)
    drives = speed_terms(sp)
    refs: dict[str, float] = {}
    ranges: dict[str, tuple[float, float]] = {}
    trained: dict[str, tuple[float, float]] = {}
    for nm in names:
        u = as_series(nm, ds.inputs[nm], t.size)
        refs[nm] = float(u.mean())
        lo, hi = float(u.min()), float(u.max())
        margin = hi - lo
        if (units or {}).get(nm) in TEMPERATURE_UNITS:
            margin = max(margin, MIN_VALID_MARGIN_K)
        ranges[nm], trained[nm] = (lo - margin, hi + margin), (lo, hi)
        drives[f"in:{nm}"] = u - refs[nm]
    if structure not in STRUCTURES:
        raise CalibrationError(
            f"unknown input structure {structure!r}; known: {', '.join(STRUCTURES)}"
        )
    mixes = _components(drives, names, measured) if structure == "pca" and names else {}
    limits = np.array(
        [BOUND_UM_PER_K if (units or {}).get(nm) in TEMPERATURE_UNITS else math.inf for nm in names]
    )
    _mix(drives, mixes, names)
    bank = FilterBank(t, drives, ds.segments)
    y0 = np.where(measured, y, 0.0)  # never read off the measured rows; keeps the arithmetic finite

    def choose(
        over: Folds, train: np.ndarray | None = None
    ) -> tuple[Config, float, list[dict[str, Any]]]:
        if structure == "few" and names:
            return _greedy(
                bank, y0, measured, cand, tuple(alphas), names, over, train, rule, penalty_forward
            )
        if structure == "pca" and names:
            configs = [
                Config(g, tuple(alphas), tuple(list(mixes)[:m]))
                for m in range(1, len(mixes) + 1)
                for g in cand
            ]
        else:
            configs = [Config(g, tuple(alphas), names) for g in cand]
        if structure == "bounded" and names:
            configs = _bounded(
                bank, y0, measured if train is None else measured & train, configs, limits
            )
        if alpha_by == "chained" and len(configs) == 1:
            blocks = fl.halves(t, sp, over)
            if ds.unit != "cycle" and train is None and len(ds.cycles) == 1:
                # one cycle: its heat-up predicts its cool-down, as the next shift would see
                blocks = fl.halves(t, sp, ds.cycles)
            got = select_chained(bank, y0, measured, configs[0], blocks, train)
            if got is not None:
                return configs[0], got[0], got[1]
        ki, al, tab = select(
            bank, y0, measured, configs, over, train, rule=rule, forward=penalty_forward
        )
        return configs[ki], al, tab

    cfg, alpha, table = choose(folds)
    x = bank.design(cfg.grid, cfg.names)
    res = cv_residuals(x, y0, measured, folds, (alpha,))[:, 0]
    cv_rms, cv_max = measured_stats(res)
    nested_folds: tuple[FoldScore, ...] | None = None
    nested_rms: float | None = None
    nested_max: float | None = None
    outer: np.ndarray | None = None
    if nested and len(folds) >= 3:
        outer = np.full(t.size, np.nan)
        for i, fold in enumerate(folds):
            inner = [f for j, f in enumerate(folds) if j != i]
            train = fl.without(t.size, fold)
            ci, al, _ = choose(inner, train)
            xi = bank.design(ci.grid, ci.names)
            g, c = ridge_path(xi[measured & train], y0[measured & train], (al,))
            scored = fold[0] + np.flatnonzero(measured[fold[0] : fold[1]])
            outer[scored] = y0[scored] - (xi[scored] @ g[:, 0] + c[0])
        nested_folds = fold_scores(outer, folds)
        nested_rms, nested_max = measured_stats(outer)
    fwd_folds: tuple[FoldScore, ...] | None = None
    fwd_rms: float | None = None
    fwd_max: float | None = None
    ahead: np.ndarray | None = None
    clipped: np.ndarray | None = None
    distance: np.ndarray | None = None
    fwd_spread: tuple[float, ...] = ()
    splits = fl.forward_of(t, sp, folds, ds.unit == "cycle", measured)
    if forward and splits:
        ahead = np.full(t.size, np.nan)
        if names:
            clipped, distance = np.full(t.size, np.nan), np.full(t.size, np.nan)
        for past, (a, b) in splits:
            train = fl.rows_of(t.size, past)
            ci, al, _ = choose(past, train)
            xi = bank.design(ci.grid, ci.names)
            g, c = ridge_path(xi[measured & train], y0[measured & train], (al,))
            scored = a + np.flatnonzero(measured[a:b])
            ahead[scored] = y0[scored] - (xi[scored] @ g[:, 0] + c[0])
            # with inputs: the same gains with the inputs held to the past's range, and how far out
            if clipped is not None and distance is not None:
                used = names if structure == "pca" else ci.names
                xc, d = _held_to_range(bank, ds, train, used, mixes, ci, b)
                clipped[scored] = y0[scored] - (xc[scored] @ g[:, 0] + c[0])
                distance[scored] = d[scored]
        fwd_folds = fold_scores(ahead, [f for _, f in splits])
        fwd_rms, fwd_max = measured_stats(ahead)
        later = fl.rows_of(t.size, [f for _, f in splits], measured)
        by_alpha = _pooled_mse(
            forward_residuals(x, y0, measured, folds, alphas, splits=splits),
            np.flatnonzero(later),
        )
        fwd_spread = tuple(math.sqrt(v) if math.isfinite(v) else math.inf for v in by_alpha)
    g, c = ridge_path(x[measured], y0[measured], (alpha,))
    gains, intercept = g[:, 0], float(c[0])
    ns = len(cfg.grid.speed_taus_s)
    per_column = gains[2 * ns :].reshape(len(cfg.names), len(cfg.grid.input_taus_s))
    detail = ""
    if structure == "pca" and names:  # a component's gain, spread back over the inputs it mixes
        kept = names
        share = sum(mixes[pc][1] for pc in cfg.names)
        detail = f"{len(cfg.names)} principal component(s) ({share:.0%} of the variance)"
        input_gains = sum(
            (np.outer(mixes[pc][0], row) for pc, row in zip(cfg.names, per_column)),
            np.zeros((len(names), len(cfg.grid.input_taus_s))),
        )
    else:
        kept = cfg.names
        input_gains = per_column
        detail = f"kept {', '.join(kept)}" if structure == "few" and names else ""
    refs = {nm: refs[nm] for nm in kept}
    ranges = {nm: ranges[nm] for nm in kept}
    trained = {nm: trained[nm] for nm in kept}
    result = RidgeFit(
        grid=cfg.grid,
        input_names=kept,
        references=refs,
        intercept_um=intercept,
        speed_gains_um=gains[: 2 * ns].reshape(2, ns),
        input_gains_um=np.asarray(input_gains, float).reshape(
            len(kept), len(cfg.grid.input_taus_s)
        ),
        alpha=alpha,
        cycles=folds,
        folds=fold_scores(res, folds),
        cv_rms_um=cv_rms,
        cv_max_abs_um=cv_max,
        speed_max_rpm=float(np.abs(sp).max()),
        valid_ranges=ranges,
        max_measured_um=float(np.abs(y[measured]).max()),
        nested_folds=nested_folds,
        nested_rms_um=nested_rms,
        nested_max_abs_um=nested_max,
        selection=tuple(table),
        fitted_dt_s=dt_s,
        segments=tuple(ds.segments),
        trained_ranges=trained,
        held_out_residual_um=outer if outer is not None else res,
        forward_folds=fwd_folds,
        forward_rms_um=fwd_rms,
        forward_max_abs_um=fwd_max,
        forward_rms_by_alpha_um=fwd_spread,
        forward_residual_um=ahead,
        structure_detail=detail,
        forward_clipped_residual_um=clipped,
        forward_distance=distance,
    )
    refusals, notes = [], []
    steady = result.steady_range_um()
    if steady > GAIN_BOUND * result.max_measured_um:
        refusals.append(
            f"the gains imply a steady elongation of {steady:.0f} um, over {GAIN_BOUND:g} x "
            f"the largest measured ({result.max_measured_um:.1f} um)"
        )
    if alpha in (alphas[0], alphas[-1]) and len(alphas) > 1:
        notes.append(f"alpha {alpha:.3g} is at the end of the grid tried")
    if nested and len(folds) < 3:
        notes.append("nested cross-validation needs three folds or more: not done")
    if not any(b - a > 1 and (np.abs(sp[a:b]) <= fl.IDLE_RPM).any() for a, b in folds):
        notes.append("no fold has a rest: the cooling time constants are not identifiable")
    return replace(
        result,
        accepted=not refusals,
        refusals=tuple(refusals),
        notes=tuple(notes),
        fit_cpu_s=time.process_time() - cpu0,
    )


def fit_baseline(
    ds: Dataset, rows: np.ndarray | None = None, *, nested: bool = False, forward: bool = True
) -> RidgeFit:
    """The exponential baseline: one rung, no static term, no penalty; the time constant (at or
    above the sample period) with the lowest held-out free-run error (:func:`select`)."""
    grids = [TauGrid((tau,)) for tau in BASELINE_TAUS_S if tau >= ds.dt_s]
    return fit(ds, rows, grids=grids, alphas=(0.0,), rule="min", nested=nested, forward=forward)


def fit_ridge_cv(
    time_s: Any,
    speed_rpm: Any,
    elongation_um: Any,
    inputs: Mapping[str, Any] | None = None,
    *,
    cycles: Folds | None = None,
    grids: Sequence[TauGrid] | None = None,
    alphas: Sequence[float] = DEFAULT_ALPHAS,
    nested: bool = False,
    rule: str = "parsimony",
    segments: Folds | None = None,
) -> RidgeFit:
    """:func:`fit` on series (one log, or several joined with ``segments``), judged against the
    exponential baseline on the same folds (:func:`fit_baseline`): refused
    when its CV (or nested) RMS is worse.

    ``inputs`` maps a name to a column; ``cycles`` (the folds) default to
    :func:`calibration.folds.split_cycles` and must cover the log in order. The elongation is
    NaN where not measured.
    """
    cpu0 = time.process_time()
    t = as_times(time_s)
    sp = as_series("speed_rpm", speed_rpm, t.size)
    y = np.asarray(elongation_um, float)
    if y.shape != t.shape:
        raise CalibrationError(f"elongation_um has {y.size} values for {t.size} time stamps")
    ds = from_arrays(t, sp, y, inputs, folds=cycles, segments=segments)
    fl.check_cover(ds.folds, t.size)
    if len(ds.folds) < 2:
        raise CalibrationError(
            "one cycle only: nothing to validate on; record a heat-up and a "
            "cool-down more (see CYCLE_RULE)"
        )
    res = fit(
        ds, grids=grids, input_names=tuple(inputs or ()), alphas=alphas, nested=nested, rule=rule
    )
    base = fit_baseline(ds, nested=nested)
    baseline: dict[str, float | None] = {
        "tau_s": base.grid.speed_taus_s[0],
        "cv_rms_um": base.cv_rms_um,
        "cv_max_abs_um": base.cv_max_abs_um,
    }
    refusals = list(res.refusals)
    if res.cv_rms_um > base.cv_rms_um:
        refusals.insert(
            0,
            f"CV RMS {res.cv_rms_um:.2f} um is worse than the exponential baseline's "
            f"{base.cv_rms_um:.2f} um",
        )
    if base.nested_rms_um is not None:
        baseline |= {
            "nested_rms_um": base.nested_rms_um,
            "nested_max_abs_um": base.nested_max_abs_um,
        }
        if res.nested_rms_um is not None and res.nested_rms_um > base.nested_rms_um:
            refusals.insert(
                1,
                f"nested CV RMS {res.nested_rms_um:.2f} um is worse than the baseline's "
                f"{base.nested_rms_um:.2f} um",
            )
    return replace(
        res,
        baseline=baseline,
        refusals=tuple(refusals),
        accepted=not refusals,
        fit_cpu_s=time.process_time() - cpu0,
    )


# -- the candidate ----------------------------------------------------------------------------


def hac_covariance(
    result: RidgeFit,
    time_s: Any,
    speed_rpm: Any,
    elongation_um: Any,
    inputs: Mapping[str, Any] | None = None,
    maxlags: int | None = None,
) -> np.ndarray:
    """Newey-West (HAC) covariance of the gains, design-column order (NaN for a constant column).

    Sandwich of the ridge estimator, ``(Z'Z + a*m*I)^-1 S (Z'Z + a*m*I)^-1`` on the standardised
    design Z, ``S`` the HAC covariance of ``z_k * e_k`` (statsmodels' ``S_hac_simple``). Free-run
    residuals are correlated over hours: ``maxlags`` defaults to one hour of samples. It measures
    the variance of the regularised gains, not their bias. Gains of one bank trade off against
    each other, so report derived quantities (a steady elongation, ``w' C w``), not single gains.
    Needs the elongation on every row (its lags are rows one period apart).
    """
    from statsmodels.stats.sandwich_covariance import S_hac_simple

    t = as_times(time_s)
    y = as_series("elongation_um", elongation_um, t.size)
    segs = result.segments if result.segments and result.segments[-1][1] == t.size else None
    x = FilterBank(t, result.drives(t, speed_rpm, inputs), segs).design(
        result.grid, result.input_names
    )
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


def hac_stderr(
    result: RidgeFit,
    time_s: Any,
    speed_rpm: Any,
    elongation_um: Any,
    inputs: Mapping[str, Any] | None = None,
    maxlags: int | None = None,
) -> np.ndarray:
    """HAC standard errors of the gains (:func:`hac_covariance`), design-column order."""
    cov = hac_covariance(result, time_s, speed_rpm, elongation_um, inputs, maxlags)
    return np.sqrt(np.clip(np.diag(cov), 0, None))


def derived(res: RidgeFit, ds: Dataset) -> list[dict[str, Any]]:
    """HAC (Newey-West) standard errors of derived quantities: the steady rise at a few speeds and
    each input's total steady sensitivity. Single bank gains trade off against each other, so
    they are not reported. Empty for sparse targets."""
    if not ds.dense:
        return []
    try:
        cov = hac_covariance(
            res, ds.time_s, ds.speed_rpm, ds.elongation_um, ds.inputs if res.input_names else None
        )
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
        w[ns : 2 * ns] = n * n
        out.append(
            {
                "quantity": f"steady rise at {rpm:.0f} rpm",
                "unit": "um",
                "value": float(w @ res.gains),
                "hac_stderr": float(math.sqrt(max(w @ cov @ w, 0.0))),
            }
        )
    ni = len(res.grid.input_taus_s)
    for i, nm in enumerate(res.input_names):
        w = np.zeros(res.gains.size)
        w[2 * ns + i * ni : 2 * ns + (i + 1) * ni] = 1.0
        out.append(
            {
                "quantity": f"steady sensitivity to {nm}",
                "unit": "um per unit",
                "value": float(w @ res.gains),
                "hac_stderr": float(math.sqrt(max(w @ cov @ w, 0.0))),
            }
        )
    return out


def to_model_or_refuse(
    res: RidgeFit, name: str, **kwargs: Any
) -> tuple[StateSpaceModel | None, str | None]:
    """The runtime model, or None and why the model class refused it."""
    try:
        return res.to_model(name, **kwargs), None
    except ModelError as err:
        return None, f"model refused: {err}"
