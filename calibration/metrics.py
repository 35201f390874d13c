"""The figures every candidate is judged by, in one place: free-run residual statistics on the
scored rows, per fold and pooled, and the parsimony rule that compares them. A residual is NaN on
a row that was not measured (it is not scored); a non-finite residual on a scored row (a free
run that diverged) counts as 1e9 um, so that it loses. Pure."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from compensator.expected import (
    COVERAGE,
    MIN_FORWARD_FOLDS,
    Band,
    ExpectedError,
    Figure,
    recent_rpm,
)

PARSIMONY = 0.02
"""A simpler grid (or a larger α), or a simpler candidate, wins when its CV RMS is within 2 % of
the best."""
DIVERGED_UM = 1e9
"""What a non-finite residual on a scored row counts as."""


@dataclass(frozen=True)
class FoldScore:
    """Free-run error on one held-out fold."""

    cycle: int
    start: int
    stop: int
    rms_um: float
    max_abs_um: float


def finite(residual: np.ndarray) -> np.ndarray:
    """A diverging free run scores huge, not NaN."""
    return np.where(np.isfinite(residual), residual, DIVERGED_UM)


def pooled_stats(residual: np.ndarray, scored: np.ndarray | None = None) -> tuple[float, float]:
    """RMS and max |residual| [um] over the ``scored`` rows (default: every row); inf for none."""
    r = np.asarray(residual, float)
    if scored is not None:
        r = r[scored]
    if r.size == 0:
        return math.inf, math.inf
    r = finite(r)
    return float(np.sqrt(np.mean(r * r))), float(np.max(np.abs(r)))


def measured_stats(residual: np.ndarray) -> tuple[float, float]:
    """:func:`pooled_stats` over the rows that have a residual (NaN: not measured)."""
    r = np.asarray(residual, float)
    return pooled_stats(r, ~np.isnan(r))


def fold_scores(residual: np.ndarray, folds: Sequence[tuple[int, int]]) -> tuple[FoldScore, ...]:
    """RMS and max |residual| on the measured rows of each fold."""
    return tuple(
        FoldScore(i, a, b, *measured_stats(residual[a:b]))
        for i, (a, b) in enumerate(folds, start=1)
    )


def residual_stats(residual: np.ndarray) -> dict[str, float | int | None]:
    """Samples, RMS, max |r|, mean |r|, mean and standard deviation of a residual [um]; None
    for each figure of an empty one."""
    r = np.asarray(residual, dtype=float)
    if r.size == 0:
        return {
            "samples": 0,
            "rms_um": None,
            "max_abs_um": None,
            "mean_abs_um": None,
            "mean_um": None,
            "std_um": None,
        }
    return {
        "samples": int(r.size),
        "rms_um": float(np.sqrt(np.mean(r**2))),
        "max_abs_um": float(np.max(np.abs(r))),
        "mean_abs_um": float(np.mean(np.abs(r))),
        "mean_um": float(np.mean(r)),
        "std_um": float(np.std(r)),
    }


SPEED_BANDS = 3
"""The running speeds are cut into this many equal bands of the calibrated range (rest apart)."""


MIN_BAND_ROWS = 10
"""A region with fewer residuals than this states nothing of its own."""

MIN_FOLD_ROWS = math.ceil(COVERAGE / (1 - COVERAGE))
"""The fewest residuals whose finite-sample quantile (:func:`conformal_quantile`) is finite at
:data:`~compensator.expected.COVERAGE`: 19 at 95 %. A fold with fewer in a region is pooled."""


def conformal_quantile(abs_residual: np.ndarray, coverage: float = COVERAGE) -> float:
    """The split-conformal half-width of ``n`` exchangeable |residuals| [um]: the
    ``ceil((n + 1) * coverage)``-th smallest, so that a new residual exchangeable with them lies
    within it with probability at least ``coverage`` (Vovk et al. 2005; Lei et al. 2018). inf
    when ``n`` is too small for the level (fewer than :data:`MIN_FOLD_ROWS` at 95 %)."""
    r = np.sort(np.abs(np.asarray(abs_residual, float)))
    r = r[np.isfinite(r)]
    k = math.ceil((r.size + 1) * coverage)
    return float(r[k - 1]) if 0 < k <= r.size else math.inf


def fold_quantile(
    groups: Sequence[np.ndarray], coverage: float = COVERAGE
) -> tuple[float, int] | None:
    """The 95 % half-width [um] of residuals grouped by fold, and the folds behind it; None when
    fewer than :data:`~compensator.expected.MIN_FORWARD_FOLDS` folds hold
    :data:`MIN_FOLD_ROWS` residuals each.

    The rows of one fold follow one another and err together: pooled, they would count as many
    independent draws, and the quantile of the pool holds on average over folds but not on the
    next one. So each fold gives its own conformal half-width (:func:`conformal_quantile`), and
    the folds are taken as the exchangeable units: the ``ceil((m + 1) * coverage)``-th smallest
    of the ``m`` fold half-widths, which is the worst fold below 19 folds. The next fold's own
    95 % half-width exceeds it with probability at most ``1 / (m + 1)``."""
    qs = sorted(
        conformal_quantile(g, coverage) for g in groups if np.isfinite(g).sum() >= MIN_FOLD_ROWS
    )
    m = len(qs)
    if m < MIN_FORWARD_FOLDS:
        return None
    return qs[min(m, math.ceil((m + 1) * coverage)) - 1], m


def _groups(r: np.ndarray, keys: np.ndarray) -> list[np.ndarray]:
    fin = np.isfinite(r)
    return [r[fin & (keys == k)] for k in np.unique(keys[fin])]


def _forward_figure(
    source: str,
    r: np.ndarray,
    keys: np.ndarray | None,
    widen: Figure | None = None,
    folds: int = 0,
) -> Figure | None:
    """The region's figure from the forward residuals ``r`` (NaN: not in it) grouped by fold
    ``keys``: per fold (:func:`fold_quantile`); where too few folds hold enough residuals, the
    pooled figure ``widen`` (all speeds) widened to the region's own largest |residual|, with
    the region's folds; None below :data:`MIN_BAND_ROWS` residuals or without either. Without
    ``keys`` (the folds unknown) the pooled conformal quantile, said to rest on ``folds``."""
    fin = np.isfinite(r)
    if fin.sum() < MIN_BAND_ROWS:
        return None
    rf = r[fin]
    rms = round(float(np.sqrt(np.mean(rf * rf))), 4)
    if keys is None:
        q = conformal_quantile(rf)
        return Figure(
            source=f"{source}, pooled",
            samples=int(rf.size),
            rms_um=rms,
            p95_abs_um=round(q if math.isfinite(q) else float(np.max(np.abs(rf))), 4),
            folds=folds,
        )
    got = fold_quantile(_groups(r, keys))
    if got is not None:
        q, m = got
        return Figure(
            source=f"{source}, per fold",
            samples=int(rf.size),
            rms_um=rms,
            p95_abs_um=round(q, 4),
            folds=m,
        )
    if widen is None:
        return None
    return Figure(
        source=f"{source}, all speeds widened",
        samples=int(rf.size),
        rms_um=rms,
        p95_abs_um=round(max(widen.p95_abs_um, float(np.max(np.abs(rf)))), 4),
        folds=min(len(np.unique(keys[fin])), widen.folds or 0),
    )


def _held_figure(r: np.ndarray) -> Figure | None:
    r = r[np.isfinite(r)]
    if r.size < MIN_BAND_ROWS:
        return None
    q = conformal_quantile(r)
    return Figure(
        source="held out",
        samples=int(r.size),
        rms_um=round(float(np.sqrt(np.mean(r * r))), 4),
        p95_abs_um=round(float(np.max(np.abs(r))) if not math.isfinite(q) else q, 4),
        folds=0,
    )


def _held_floor(fig: Figure, held: np.ndarray, keys: np.ndarray | None) -> Figure:
    """``fig`` widened, where they reach further, to the held-out residuals of its region taken
    the same way (per fold, :func:`fold_quantile`; pooled without folds): each held-out cycle
    was predicted by a model fitted without it, one more draw of an unseen cycle's error, as in
    the jackknife+ (Barber et al. 2021). It never narrows the forward figure, nor adds folds to
    what the statement calls validated."""
    h = held[np.isfinite(held)]
    if h.size < MIN_FOLD_ROWS:
        return fig
    if keys is None:
        q = conformal_quantile(h)
    else:
        got = fold_quantile(_groups(held, keys))
        q = got[0] if got is not None else math.inf
    if not math.isfinite(q) or q <= fig.p95_abs_um:
        return fig
    return fig.model_copy(
        update={"p95_abs_um": round(q, 4), "source": f"{fig.source}, widened to held out"}
    )


def fold_keys(size: int, folds: Sequence[tuple[int, int]]) -> np.ndarray:
    """Per row, the index of the fold (half-open row range) that holds it; -1 outside every
    fold (one group of its own)."""
    keys = np.full(size, -1, int)
    for i, (a, b) in enumerate(folds):
        keys[a:b] = i
    return keys


def expected_error(
    forward: np.ndarray | None,
    held_out: np.ndarray | None,
    speed_rpm: np.ndarray,
    top_rpm: float,
    distance: np.ndarray | None = None,
    *,
    forward_folds: int = 0,
    idle_rpm: float = 1.0,
    folds: Sequence[tuple[int, int]] | None = None,
    time_s: np.ndarray | None = None,
    memory_s: float | None = None,
) -> ExpectedError | None:
    """The error a model can be expected to make, by operating region
    (:class:`compensator.expected.ExpectedError`): RMS and the 95 % half-width of |residual|
    [um] at rest and in :data:`SPEED_BANDS` bands of the calibrated speed range, inside the
    trained input range and outside it. ``forward`` residuals (rolling origin: each predicted by
    a model fitted on the rows before it, NaN on the rows not predicted) state it; ``folds``
    (half-open row ranges, the cycles) group them, since one fold's rows err together;
    ``distance`` is how far the inputs of each forward row lay outside the range its past saw.
    Without ``folds`` the residuals are pooled (each region's conformal quantile, said to rest
    on ``forward_folds``). With ``time_s`` and ``memory_s`` (how long a speed stays in the
    thermal state, :func:`compensator.expected.memory_s_of`) the statement also records the
    fastest speed within ``memory_s`` before any forward residual (``history_rpm``): after
    running faster, at rest too, the spindle is where validation never measured.

    A region's half-width is the split-conformal quantile per fold, the worst fold when folds
    are few (:func:`fold_quantile`). A speed band whose folds hold too few residuals each takes
    the figure pooled over all speeds, widened to its own largest residual; one with fewer than
    :data:`MIN_BAND_ROWS` forward residuals states no validated figure. Speeds above the fastest
    a forward residual was measured at are not validated (``measured_rpm``). ``held_out``
    residuals (past cycles predicted from the others) widen a forward band where they reach
    further, taken the same way (the jackknife+ draws), and state a band alone only where no
    forward one does, never as validated (a floor): held out, past cycles understated the next
    cycle's error many-fold. None when no band has residuals."""
    n = np.abs(np.asarray(speed_rpm, float))
    nan = np.full(n.shape, np.nan)
    fwd = nan if forward is None else np.asarray(forward, float)
    held = nan if held_out is None else np.asarray(held_out, float)
    dist = (
        np.zeros(n.shape)
        if distance is None
        else np.nan_to_num(np.asarray(distance, float), nan=0.0)
    )
    keys = None if folds is None else fold_keys(n.size, folds)
    out_rows = dist > 0
    f = forward_folds
    pooled_in = _forward_figure("forward", np.where(~out_rows, fwd, np.nan), keys, None, f)
    pooled_out = _forward_figure("forward, outside", np.where(out_rows, fwd, np.nan), keys, None, f)
    edges = np.linspace(0.0, max(top_rpm, idle_rpm), SPEED_BANDS + 1)
    regions = [(0.0, idle_rpm, n <= idle_rpm)]
    for lo, hi in itertools.pairwise(edges):
        regions.append((max(lo, idle_rpm), float(hi), (n > max(lo, idle_rpm)) & (n <= hi)))
    bands = []
    for lo, hi, inside in regions:
        held_here = np.where(inside, held, np.nan)
        fig = _forward_figure(
            "forward", np.where(inside & ~out_rows, fwd, np.nan), keys, pooled_in, f
        )
        fig = _held_floor(fig, held_here, keys) if fig is not None else _held_figure(held_here)
        if fig is None:
            continue
        outside = _forward_figure(
            "forward, outside", np.where(inside & out_rows, fwd, np.nan), keys, pooled_out, f
        )
        bands.append(
            Band(
                speed_rpm=(round(float(lo), 1), round(float(hi), 1)),
                source=fig.source,
                samples=fig.samples,
                rms_um=fig.rms_um,
                p95_abs_um=fig.p95_abs_um,
                outside=outside,
                folds=fig.folds,
            )
        )
    if not bands:
        return None
    seen = np.isfinite(fwd)
    history = None
    if time_s is not None and memory_s is not None and memory_s > 0 and seen.any():
        history = round(float(recent_rpm(np.asarray(time_s, float), n, memory_s)[seen].max()), 1)
    return ExpectedError(
        bands=tuple(bands),
        outside_validated=round(float(dist[seen].max()), 4) if seen.any() else 0.0,
        forward_folds=forward_folds,
        measured_rpm=round(float(n[seen].max()), 1) if seen.any() else 0.0,
        history_rpm=history,
        memory_s=round(float(memory_s), 1) if history is not None and memory_s else None,
    )


def against_expected(
    expected: ExpectedError,
    residual: np.ndarray,
    speed_rpm: np.ndarray,
    distance: np.ndarray | None = None,
    min_rows: int = MIN_BAND_ROWS,
    recent: np.ndarray | None = None,
) -> list[dict[str, object]]:
    """A residual [um] measured after the fit, band by band against what the fit stated: the
    stated RMS and 95th percentile beside the measured RMS and the share of errors within the
    stated bound (about 95 % when the statement holds; outside the trained range the bound is
    the outside one, :meth:`ExpectedError.p95_at`); ``within_p95_validated`` counts the rows
    the statement vouches for alone (``recent``: :meth:`ExpectedError.recent_rpm` of the log)."""
    r = np.asarray(residual, float)
    n = np.asarray(speed_rpm, float)
    which = expected.band_index(n)
    bound = expected.p95_at(n, distance)
    out_rows = (
        np.zeros(n.shape, bool)
        if distance is None
        else np.nan_to_num(np.asarray(distance, float)) > 0
    )
    valid = expected.validated(n, distance, recent)
    out = []
    for k, b in enumerate(expected.bands):
        sel = (which == k) & np.isfinite(r)
        if sel.sum() < min_rows:
            continue
        out.append(
            {
                "speed_rpm": list(b.speed_rpm),
                "label": b.label,
                "source": b.source,
                "expected_rms_um": b.rms_um,
                "expected_p95_abs_um": b.p95_abs_um,
                "samples": int(sel.sum()),
                "outside_samples": int((sel & out_rows).sum()),
                "validated_samples": int((sel & valid).sum()),
                "rms_um": float(np.sqrt(np.mean(r[sel] ** 2))),
                "within_p95": float(np.mean(np.abs(r[sel]) <= bound[sel])),
                # the promise is where validation measured: the rest is a floor
                "within_p95_validated": (
                    float(np.mean(np.abs(r[sel & valid]) <= bound[sel & valid]))
                    if (sel & valid).any()
                    else None
                ),
            }
        )
    return out
