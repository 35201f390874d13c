"""The figures every candidate is judged by, in one place: free-run residual statistics on the
scored rows, per fold and pooled, and the parsimony rule that compares them. A residual is NaN on
a row that was not measured (it is not scored); a non-finite residual on a scored row (a free
run that diverged) counts as 1e9 um, so that it loses. Pure."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

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
    return tuple(FoldScore(i, a, b, *measured_stats(residual[a:b]))
                 for i, (a, b) in enumerate(folds, start=1))


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
