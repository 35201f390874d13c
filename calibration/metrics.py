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

from compensator.expected import Band, ExpectedError, Figure

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


def _figure(source: str, r: np.ndarray) -> Figure | None:
    r = r[np.isfinite(r)]
    if r.size < MIN_BAND_ROWS:
        return None
    return Figure(
        source=source,
        samples=int(r.size),
        rms_um=round(float(np.sqrt(np.mean(r * r))), 4),
        p95_abs_um=round(float(np.quantile(np.abs(r), 0.95)), 4),
    )


def expected_error(
    forward: np.ndarray | None,
    held_out: np.ndarray | None,
    speed_rpm: np.ndarray,
    top_rpm: float,
    distance: np.ndarray | None = None,
    *,
    forward_folds: int = 0,
    idle_rpm: float = 1.0,
) -> ExpectedError | None:
    """The error a model can be expected to make, by operating region
    (:class:`compensator.expected.ExpectedError`): RMS and the 95th percentile of |residual|
    [um] at rest and in :data:`SPEED_BANDS` bands of the calibrated speed range, inside the
    trained input range and outside it. ``forward`` (rolling origin) and ``held_out`` residuals
    took no part in the fit that made them (NaN on the rows not predicted); ``distance`` is how
    far the inputs of each forward row lay outside the range its past saw.

    Inside, a band states the larger of the two figures that have :data:`MIN_BAND_ROWS` there:
    the forward one holds what the future brings, the held-out one covers the bands the
    forward splits never reached. Outside, the forward rows that left their range state it,
    the band's own where it has enough, else all speeds pooled. None when no band is covered."""
    n = np.abs(np.asarray(speed_rpm, float))
    nan = np.full(n.shape, np.nan)
    fwd = nan if forward is None else np.asarray(forward, float)
    held = nan if held_out is None else np.asarray(held_out, float)
    dist = (
        np.zeros(n.shape)
        if distance is None
        else np.nan_to_num(np.asarray(distance, float), nan=0.0)
    )
    out_rows = dist > 0
    pooled = _figure("forward, outside, all speeds", np.where(out_rows, fwd, np.nan))
    edges = np.linspace(0.0, max(top_rpm, idle_rpm), SPEED_BANDS + 1)
    regions = [(0.0, idle_rpm, n <= idle_rpm)]
    for lo, hi in itertools.pairwise(edges):
        regions.append((max(lo, idle_rpm), float(hi), (n > max(lo, idle_rpm)) & (n <= hi)))
    bands = []
    for lo, hi, inside in regions:
        figs = [
            f
            for f in (
                _figure("forward", np.where(inside & ~out_rows, fwd, np.nan)),
                _figure("held out", np.where(inside, held, np.nan)),
            )
            if f is not None
        ]
        if not figs:
            continue
        worst = max(figs, key=lambda f: f.p95_abs_um)
        outside = _figure("forward, outside", np.where(inside & out_rows, fwd, np.nan)) or pooled
        bands.append(
            Band(
                speed_rpm=(round(float(lo), 1), round(float(hi), 1)),
                source=worst.source,
                samples=worst.samples,
                rms_um=worst.rms_um,
                p95_abs_um=worst.p95_abs_um,
                outside=outside,
            )
        )
    if not bands:
        return None
    seen = dist[np.isfinite(fwd)]
    return ExpectedError(
        bands=tuple(bands),
        outside_validated=round(float(seen.max()), 4) if seen.size else 0.0,
        forward_folds=forward_folds,
    )


def against_expected(
    expected: ExpectedError,
    residual: np.ndarray,
    speed_rpm: np.ndarray,
    distance: np.ndarray | None = None,
    min_rows: int = MIN_BAND_ROWS,
) -> list[dict[str, object]]:
    """A residual [um] measured after the fit, band by band against what the fit stated: the
    stated RMS and 95th percentile beside the measured RMS and the share of errors within the
    stated bound (about 95 % when the statement holds; outside the trained range the bound is
    the outside one, :meth:`ExpectedError.p95_at`)."""
    r = np.asarray(residual, float)
    n = np.asarray(speed_rpm, float)
    which = expected.band_index(n)
    bound = expected.p95_at(n, distance)
    out_rows = (
        np.zeros(n.shape, bool)
        if distance is None
        else np.nan_to_num(np.asarray(distance, float)) > 0
    )
    valid = expected.validated(n, distance)
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
            }
        )
    return out
