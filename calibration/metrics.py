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


SPEED_BANDS = 3
"""The running speeds are cut into this many equal bands of the calibrated range (rest apart)."""


MIN_BAND_ROWS = 10


def expected_error(residuals: Sequence[tuple[str, np.ndarray | None]], speed_rpm: np.ndarray, top_rpm: float,
                   *, idle_rpm: float = 1.0) -> dict[str, object]:
    """The error a model can be expected to make, by operating region: RMS and the 95th
    percentile of |residual| [um] at rest and in :data:`SPEED_BANDS` bands of the calibrated
    speed range. ``residuals`` are held-out residuals by preference, (source, residual) with NaN
    on the rows not predicted: each band takes the first with enough rows there (the forward one
    first: the future is what the model will meet) and names it. A band no residual covers is
    left out. What the fit stores beside the model."""
    n = np.abs(np.asarray(speed_rpm, float))
    edges = np.linspace(0.0, max(top_rpm, idle_rpm), SPEED_BANDS + 1)
    bands = [(0.0, idle_rpm, n <= idle_rpm)]
    for lo, hi in zip(edges[:-1], edges[1:]):
        bands.append((max(lo, idle_rpm), float(hi), (n > max(lo, idle_rpm)) & (n <= hi)))
    out = []
    for lo, hi, inside in bands:
        for source, residual in residuals:
            if residual is None:
                continue
            r = np.asarray(residual, float)
            sel = r[np.isfinite(r) & inside]
            if sel.size >= MIN_BAND_ROWS:
                out.append({"speed_rpm": [round(float(lo), 1), round(float(hi), 1)], "source": source,
                            "samples": int(sel.size), "rms_um": round(float(np.sqrt(np.mean(sel * sel))), 4),
                            "p95_abs_um": round(float(np.quantile(np.abs(sel), 0.95)), 4)})
                break
    return {"bands": out}


def band_index(expected: dict[str, object], speed_rpm: np.ndarray) -> np.ndarray:
    """For each speed, the index of the band of ``expected`` (:func:`expected_error`) it falls
    in; the top band above the calibrated range or in a band left out; -1 without bands."""
    bands = list(expected.get("bands", ()))  # type: ignore[call-overload]
    n = np.abs(np.asarray(speed_rpm, float))
    if not bands:
        return np.full(n.shape, -1)
    lo = np.array([b["speed_rpm"][0] for b in bands], float)
    hi = np.array([b["speed_rpm"][1] for b in bands], float)
    i = np.minimum(np.searchsorted(hi, n, side="left"), len(bands) - 1)  # the first band reaching n
    inside = (n <= hi[i]) & ((n > lo[i]) | (lo[i] == 0.0))
    return np.where(inside, i, len(bands) - 1)


def band_of(expected: dict[str, object], speed_rpm: float) -> dict[str, object] | None:
    """The band of ``expected`` that ``speed_rpm`` falls in (:func:`band_index`); None without
    bands."""
    i = int(band_index(expected, np.array([speed_rpm]))[0])
    return list(expected["bands"])[i] if i >= 0 else None  # type: ignore[call-overload]


def against_expected(expected: dict[str, object], residual: np.ndarray, speed_rpm: np.ndarray,
                     min_rows: int = MIN_BAND_ROWS) -> list[dict[str, object]]:
    """A residual [um] measured after the fit, band by band against what the fit stated
    (:func:`expected_error`): the stated RMS and 95th percentile beside the measured RMS and the
    share of errors within the stated percentile (about 95 % when the statement holds)."""
    r = np.asarray(residual, float)
    n = np.asarray(speed_rpm, float)
    which = band_index(expected, n)
    out = []
    for k, b in enumerate(expected.get("bands", ())):  # type: ignore[attr-defined]
        sel = r[(which == k) & np.isfinite(r)]
        if sel.size < min_rows:
            continue
        out.append({"speed_rpm": b["speed_rpm"], "source": b["source"], "expected_rms_um": b["rms_um"],
                    "expected_p95_abs_um": b["p95_abs_um"], "samples": int(sel.size),
                    "rms_um": float(np.sqrt(np.mean(sel * sel))),
                    "within_p95": float(np.mean(np.abs(sel) <= b["p95_abs_um"]))})
    return out


def band_label(band: dict[str, object]) -> str:
    """``at rest`` or ``lo-hi rpm``, for a band of :func:`expected_error`."""
    lo, hi = band["speed_rpm"]  # type: ignore[misc]
    return "at rest" if hi <= 1.0 else f"{lo:.0f}-{hi:.0f} rpm"
