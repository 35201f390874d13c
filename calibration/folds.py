"""How a log is cut for validation: whole heat-up/cool-down cycles (:func:`split_cycles`, rule in
:data:`CYCLE_RULE`), contiguous blocks of a log that holds one cycle only (:func:`blocks`), and
the training rows of a fold held out (:func:`without`). Every score in the identification is a
free run scored on a held-out fold; one-step error is never used to choose anything. Pure.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import numpy as np

from .checks import as_series, as_times

Fold = tuple[int, int]
"""Half-open row range ``(start, stop)``."""

H = 3600.0
IDLE_RPM = 1.0
"""At or below this |speed| the spindle is at rest."""
MIN_REST_S = 1800.0
"""A rest shorter than this (a tool change, a pause) does not end a heat-up."""
MIN_RUN_S = 600.0
"""A run shorter than this (a blip during a cool-down) does not start a heat-up."""
BLOCKS = 4
"""Folds of a log that holds one cycle only: this many contiguous blocks of equal duration."""
MIN_FOLD_ROWS = 20
"""A block (or a stretch refitted by the output-error form) needs at least this many rows."""

CYCLE_RULE = (
    "a cycle is a heat-up and the cool-down that follows: the spindle runs when |speed| > "
    f"{IDLE_RPM:g} rpm; rests shorter than {MIN_REST_S / 60:g} min are bridged (they belong to the "
    f"run), then runs shorter than {MIN_RUN_S / 60:g} min are ignored (they belong to the rest); "
    "each remaining run starts a cycle, which ends where the next one starts; samples before the "
    "first run join the first cycle, and the last cycle ends with the log (it may have no "
    "cool-down). Durations are measured on the time stamps, a logged value held over the interval "
    "that ends at its sample."
)


def stretches(mask: np.ndarray) -> list[Fold]:
    """The runs of True in ``mask``, as half-open ranges."""
    edges = np.diff(np.concatenate([[0], np.asarray(mask).astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def duration_s(t: np.ndarray, a: int, b: int) -> float:
    """Time covered by samples a..b-1, each held over the interval ending at it."""
    return float(t[b - 1] - t[max(a - 1, 0)])


def split_cycles(
    time_s: Any,
    speed_rpm: Any,
    *,
    idle_rpm: float = IDLE_RPM,
    min_rest_s: float = MIN_REST_S,
    min_run_s: float = MIN_RUN_S,
) -> list[Fold]:
    """Cut a log into cycles: half-open index ranges ``(start, stop)`` that cover it in order.

    The rule (:data:`CYCLE_RULE`): the spindle runs when |speed| > ``idle_rpm``; rests shorter
    than ``min_rest_s`` are bridged, then runs shorter than ``min_run_s`` are ignored; each run
    left starts a cycle that ends where the next starts. Samples before the first run join the
    first cycle; the last cycle ends with the log. A log with no run is one cycle.
    """
    t = as_times(time_s)
    n = np.abs(as_series("speed_rpm", speed_rpm, t.size))
    if t.size == 0:
        return []
    running = n > idle_rpm
    for a, b in stretches(~running):
        if a > 0 and b < t.size and duration_s(t, a, b) < min_rest_s:
            running[a:b] = True  # a pause between two runs
    for a, b in stretches(running):
        if duration_s(t, a, b) < min_run_s:
            running[a:b] = False
    starts = [a for a, _ in stretches(running)]
    if not starts:
        return [(0, int(t.size))]
    bounds = [0, *starts[1:], int(t.size)]
    return [(int(a), int(b)) for a, b in itertools.pairwise(bounds)]


def describe_cycles(
    time_s: Any, speed_rpm: Any, cycles: Sequence[Fold], idle_rpm: float = IDLE_RPM
) -> list[str]:
    """One line per cycle: when, how long it ran and at what speed, how long it rested."""
    t = np.asarray(time_s, float)
    n = np.abs(np.asarray(speed_rpm, float))
    held = np.diff(t, prepend=t[:1])  # the interval each sample is held over
    lines = []
    for i, (a, b) in enumerate(cycles, start=1):
        run = n[a:b] > idle_rpm
        run_s = float(np.sum(held[a:b][run]))
        top = float(n[a:b].max()) if b > a else 0.0
        lines.append(
            f"cycle {i}: samples {a}..{b - 1}, {t[a] / H:.2f}-{t[b - 1] / H:.2f} h, "
            f"running {run_s / H:.2f} h up to {top:.0f} rpm, "
            f"at rest {(duration_s(t, a, b) - run_s) / H:.2f} h"
        )
    return lines


def longest_stretch_s(
    time_s: Any, speed_rpm: Any, cycles: Sequence[Fold], idle_rpm: float = IDLE_RPM
) -> float:
    """The median over cycles of the longer of its run and its rest [s]: the longest time
    constant the log can pin down (a slow heat-up looks like a long time constant otherwise)."""
    t = np.asarray(time_s, float)
    n = np.abs(np.asarray(speed_rpm, float))
    held = np.diff(t, prepend=t[:1])
    out = []
    for a, b in cycles:
        run = float(np.sum(held[a:b][n[a:b] > idle_rpm]))
        out.append(max(run, duration_s(t, a, b) - run))
    return float(np.median(out)) if out else 0.0


def blocks(time_s: np.ndarray, count: int = BLOCKS) -> tuple[Fold, ...]:
    """``count`` contiguous blocks of equal duration (the folds of a one-cycle log)."""
    edges = np.searchsorted(time_s, np.linspace(time_s[0], time_s[-1], count + 1)[1:-1])
    bounds = [0, *sorted({int(e) for e in edges}), int(time_s.size)]
    return tuple((a, b) for a, b in itertools.pairwise(bounds) if b > a)


def forward_splits(folds: Sequence[Fold], first: int = 1) -> list[tuple[tuple[Fold, ...], Fold]]:
    """Rolling origin: (the folds before, the next fold) for every fold from index ``first``. A
    model fitted on the past predicts the future, which leave-one-out (where later folds inform
    an earlier one) does not test."""
    return [(tuple(folds[:k]), folds[k]) for k in range(max(first, 1), len(folds))]


def run_end(time_s: Any, speed_rpm: Any, fold: Fold, idle_rpm: float = IDLE_RPM) -> int | None:
    """Where a cycle's cool-down begins: the row after its last running sample (rests shorter
    than :data:`MIN_REST_S` bridged, as :func:`split_cycles` does). None when the cycle has no
    run or no rest after it (the log's last cycle may end running)."""
    a, b = fold
    t = np.asarray(time_s, float)
    running = np.abs(np.asarray(speed_rpm, float)[a:b]) > idle_rpm
    if not running.any():
        return None
    end = a + int(np.flatnonzero(running)[-1]) + 1
    return end if end < b and duration_s(t, end, b) >= MIN_RUN_S else None


def halves(time_s: Any, speed_rpm: Any, folds: Sequence[Fold]) -> tuple[Fold, ...]:
    """The folds cut where each cycle's cool-down begins (:func:`run_end`): a heat-up and its
    cool-down, in order; a cycle without both stays whole."""
    out: list[Fold] = []
    for a, b in folds:
        mid = run_end(time_s, speed_rpm, (a, b))
        out += (
            [(a, b)]
            if mid is None or mid - a < MIN_FOLD_ROWS or b - mid < MIN_FOLD_ROWS
            else [
                (a, mid),
                (mid, b),
            ]
        )
    return tuple(out)


Split = tuple[tuple[Fold, ...], Fold]
"""(the past as folds, the stretch predicted)."""

FORWARD_ORIGIN_RULE = (
    "forward origins every half cycle: at each cycle's start and where its cool-down begins, "
    "once the past holds a whole cycle and the heat-up of the next; each predicts the stretch to "
    "the next origin in free run from the log's start, with a model chosen and fitted on the rows "
    "before the origin only"
)


def forward_origins(time_s: Any, speed_rpm: Any, folds: Sequence[Fold]) -> list[Split]:
    """Rolling origin inside cycles as well as at their boundaries (:data:`FORWARD_ORIGIN_RULE`).
    The past of each split is its whole cycles plus, for an origin where a cool-down begins, the
    heat-up before it as a fold of its own (a model choosing its penalty by leave-one-fold-out
    on the past has two folds or more). Four cycles give five splits, five give seven (whole
    cycles alone: two and three); two cycles give one, the cool-down of the second."""
    out: list[Split] = []
    for k, (a, b) in enumerate(folds):
        if k == 0:
            continue
        past = tuple(folds[:k])
        mid = run_end(time_s, speed_rpm, (a, b))
        if mid is not None and (mid - a < MIN_FOLD_ROWS or b - mid < MIN_FOLD_ROWS):
            mid = None
        if k >= 2:
            out.append((past, (a, mid if mid is not None else b)))
        if mid is not None:
            out.append(((*past, (a, mid)), (mid, b)))
    return out


def forward_of(
    time_s: Any,
    speed_rpm: Any,
    folds: Sequence[Fold],
    by_cycle: bool,
    measured: np.ndarray | None = None,
) -> list[Split]:
    """The forward splits the identification scores every candidate on: origins every half
    cycle (:func:`forward_origins`) when the folds are cycles; rolling origin over whole folds
    from the third (:func:`forward_splits`) when they are blocks of one cycle. With ``measured``
    (sparse targets), a split whose stretch has no measured row is left out."""
    out = forward_origins(time_s, speed_rpm, folds) if by_cycle else forward_splits(folds, first=2)
    if measured is None:
        return out
    return [(p, (a, b)) for p, (a, b) in out if np.asarray(measured[a:b]).any()]


def rows_of(size: int, folds: Sequence[Fold], rows: np.ndarray | None = None) -> np.ndarray:
    """The rows of ``folds`` (within ``rows`` when given)."""
    out = np.zeros(size, bool)
    for a, b in folds:
        out[a:b] = True
    return out if rows is None else out & rows


def without(size: int, fold: Fold, rows: np.ndarray | None = None) -> np.ndarray:
    """The training rows when ``fold`` is held out: ``rows`` (default every row) less the fold."""
    out = np.ones(size, bool) if rows is None else np.array(rows, dtype=bool)
    out[fold[0] : fold[1]] = False
    return out


def check_cover(folds: Sequence[Fold], size: int) -> None:
    """Folds must be non-empty and cover the rows in order."""
    from compensator.errors import CalibrationError

    if (
        not folds
        or folds[0][0] != 0
        or folds[-1][1] != size
        or any(b <= a for a, b in folds)
        or any(x[1] != y[0] for x, y in itertools.pairwise(folds))
    ):
        raise CalibrationError("cycles must be non-empty and cover the log in order")
