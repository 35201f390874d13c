"""Calibration data: checks and resampling of logged runs. No file I/O here."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from compensator.errors import CalibrationError
from compensator.io import RunLog
from compensator.io.runlog import MAX_ABS_TIME_S, MAX_SPEED_RPM
from compensator.units import SPEED_SCALE_RPM

from .folds import stretches

MIN_ROWS = 20
MIN_MEASURED_ROWS = 10
"""A sparse log (probe measurements only) needs at least this many measured rows."""
MAX_PLAUSIBLE_UM = 5000.0  # 5 mm: no spindle grows that much
IDLE_RPM = 1.0
TRANSIENT_WINDOW_S = 300.0
TRANSIENT_STEP_FRACTION = 0.1
GAP_MEDIAN_STEPS = 10.0
MIN_GAP_S = 600.0
"""A time step longer than max(GAP_MEDIAN_STEPS x median step, MIN_GAP_S) is a gap in the
log (:func:`bridge_gaps`), and a gap is integrated at the **last logged speed**: a gap that
begins at rest (a logger left off overnight, a machine switched off) is a cool-down, and a
recording that stalls while the spindle runs keeps it running. The run-log convention would
otherwise hold the speed of the sample *after* the gap over all of it, heating a machine that
was off. 600 s keeps a coarse log (a step of a minute or more) from calling a single late
sample a gap."""


@dataclass(frozen=True)
class Run:
    """One calibration run: time, speed and measured elongation, all finite (from
    ``run_from_log(..., sparse=True)``: the elongation NaN on the rows not measured)."""

    name: str
    time_s: np.ndarray
    speed_rpm: np.ndarray
    elongation_um: np.ndarray

    def __len__(self) -> int:
        return int(self.time_s.size)

    @property
    def n_krpm(self) -> np.ndarray:
        return np.abs(self.speed_rpm) / SPEED_SCALE_RPM

    @property
    def dt_s(self) -> np.ndarray:
        return np.diff(self.time_s)

    @property
    def median_dt_s(self) -> float:
        return float(np.median(self.dt_s))

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1] - self.time_s[0])


def gap_threshold_s(time_s: np.ndarray) -> float:
    """The shortest time step that is a gap: max(10 x median step, 600 s) (:data:`MIN_GAP_S`)."""
    dt = np.diff(np.asarray(time_s, dtype=float))
    return max(GAP_MEDIAN_STEPS * float(np.median(dt)), MIN_GAP_S) if dt.size else MIN_GAP_S


def bridge_gaps(
    time_s: np.ndarray, speed_rpm: np.ndarray, gap_s: float | None = None
) -> tuple[np.ndarray, list[tuple[int, float]]]:
    """The speed with every gap in the log integrated at the last logged speed.

    ``speed_rpm[k]`` is held over ``(time_s[k-1], time_s[k]]``, so a sample ending a step
    longer than ``gap_s`` (default :func:`gap_threshold_s`) gets the speed of the sample before
    the gap: at rest, the model cools across it; the logged speeds resume at the next sample. Returns the new speed (a
    copy) and the (row, gap length [s]) of each gap. Pure: no I/O, inputs untouched.
    """
    t = np.asarray(time_s, dtype=float)
    speed = np.array(speed_rpm, dtype=float)  # a copy: the caller keeps the logged speed
    if t.shape != speed.shape or t.ndim != 1:
        raise CalibrationError(f"time_s {t.shape} and speed_rpm {speed.shape} differ in shape")
    limit_s = gap_threshold_s(t) if gap_s is None else float(gap_s)
    if not limit_s > 0 or not np.isfinite(limit_s):
        raise CalibrationError(f"gap threshold {gap_s!r} s is not a positive number")
    dt = np.diff(t)
    rows = np.flatnonzero(dt > limit_s) + 1
    speed[rows] = speed[rows - 1]
    return speed, [(int(k), float(dt[k - 1])) for k in rows]


def _at(log: RunLog, src: str, row: int) -> str:
    line = log.line_of(row)
    return f"{src}:{line}" if line else f"{src} (row {row})"


def _check_values(log: RunLog, src: str, elongation_um: np.ndarray) -> None:
    """The reader's checks again, for a RunLog built in memory rather than read from a file."""
    cols = {"time_s": log.time_s, "speed_rpm": log.speed_rpm, "elongation_um": elongation_um}
    for col, values in cols.items():
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            row = int(bad[0])
            raise CalibrationError(
                f"{_at(log, src, row)}: column {col}: {values[row]} is not a finite number"
            )
    for col, values, limit in (
        ("time_s", log.time_s, MAX_ABS_TIME_S),
        ("speed_rpm", log.speed_rpm, MAX_SPEED_RPM),
    ):
        over = np.flatnonzero(np.abs(values) > limit)
        if over.size:
            row = int(over[0])
            raise CalibrationError(
                f"{_at(log, src, row)}: column {col}: {values[row]:g} is beyond "
                f"{limit:g} (wrong unit?)"
            )
    back = np.flatnonzero(np.diff(log.time_s) <= 0)
    if back.size:
        row = int(back[0]) + 1
        raise CalibrationError(
            f"{_at(log, src, row)}: time does not increase "
            f"({log.time_s[row]:g} s after {log.time_s[row - 1]:g} s)"
        )


def run_from_log(log: RunLog, name: str | None = None, *, sparse: bool = False) -> Run:
    """Check that a log can calibrate: elongation present, enough rows, plausible units.

    With ``sparse`` the elongation may be NaN on the rows that were not measured (a journal
    export: probe measurements only; the cycles method fits on the measured rows); at least
    :data:`MIN_MEASURED_ROWS` must be. Without, every row needs a finite one."""
    src = log.source or name or "run"
    if log.elongation_um is None:
        raise CalibrationError(
            f"{src}: no elongation_um column: a calibration run needs the measured growth"
        )
    if len(log) < MIN_ROWS:
        raise CalibrationError(
            f"{src}: {len(log)} rows; a calibration run needs at least {MIN_ROWS}"
        )
    elong = np.asarray(log.elongation_um, dtype=float)
    measured = np.isfinite(elong)
    if sparse and not measured.all():
        if measured.sum() < MIN_MEASURED_ROWS:
            raise CalibrationError(
                f"{src}: the elongation is measured on {int(measured.sum())} rows; a "
                f"calibration needs at least {MIN_MEASURED_ROWS}"
            )
        _check_values(log, src, np.where(np.isnan(elong), 0.0, elong))  # NaN: not measured
    else:
        _check_values(log, src, elong)
    speed = np.abs(log.speed_rpm)
    top = float(speed.max())
    if top <= 0:
        raise CalibrationError(f"{src}: the spindle never turns (speed is 0 throughout)")
    if top < 100:
        raise CalibrationError(
            f"{src}: highest speed is {top:g} rpm; is speed_rpm in krpm? (multiply by 1000)"
        )
    if np.ptp(speed) == 0:
        raise CalibrationError(
            f"{src}: constant speed only ({top:g} rpm): speed must vary to identify the model"
        )
    peak = float(np.nanmax(np.abs(elong)))
    if peak > MAX_PLAUSIBLE_UM:
        row = int(np.nanargmax(np.abs(elong)))
        raise CalibrationError(
            f"{_at(log, src, row)}: elongation {log.elongation_um[row]:g} um is over 5 mm; "
            "is elongation_um in nm, or the sensor off range?"
        )
    return Run(name or src, log.time_s.copy(), log.speed_rpm.copy(), log.elongation_um.copy())


def resample(run: Run, dt_s: float) -> Run:
    """A run on a uniform grid of period ``dt_s``.

    Speed is the time average of |n| over each interval (the logged speed is
    taken as held over the interval that ends at its sample); elongation is
    interpolated at the grid instants. Sub-sampling a finer log is exact for
    speed changes on interval edges. A sparse run's measurements (NaN between them) go to the
    grid instant at or before them: the speed of the interval that ends there is the one held
    through the measuring cycle, where the nearest instant after it may average in the next
    speed, and with it a growth at speed the measurement never saw.
    """
    t0, t1 = run.time_s[0], run.time_s[-1]
    k = int(np.floor((t1 - t0) / dt_s + 1e-9))
    if k < 2:
        raise CalibrationError(f"{run.name}: shorter than two periods of {dt_s:g} s")
    grid = t0 + np.arange(k + 1) * dt_s
    if np.allclose(np.diff(run.time_s), dt_s, rtol=1e-9, atol=1e-9) and len(run) == grid.size:
        return run
    # integral of the held speed: speed[k] holds over (t[k-1], t[k]]
    n = np.abs(run.speed_rpm)
    cum = np.concatenate([[0.0], np.cumsum(n[1:] * np.diff(run.time_s))])

    def integral(t: np.ndarray) -> np.ndarray:
        idx = np.clip(np.searchsorted(run.time_s, t, side="left"), 1, len(run) - 1)
        return cum[idx - 1] + n[idx] * (t - run.time_s[idx - 1])

    speed = np.empty_like(grid)
    speed[0] = n[0]
    speed[1:] = np.diff(integral(grid)) / dt_s
    y = run.elongation_um
    ok = np.isfinite(y)
    if ok.all():
        elong = np.interp(grid, run.time_s, y)
    else:  # sparse: each measurement on its nearest grid instant, the rest stays unmeasured
        elong = np.full(grid.size, np.nan)
        at = np.clip(np.floor((run.time_s[ok] - t0) / dt_s + 1e-9).astype(int), 0, grid.size - 1)
        elong[at] = y[ok]
    return Run(run.name, grid, speed, elong)


def transient_mask(
    time_s: np.ndarray, speed_rpm: np.ndarray, max_rpm: float, window_s: float = TRANSIENT_WINDOW_S
) -> np.ndarray:
    """True within ``window_s`` after a speed step of more than 10 % of ``max_rpm``."""
    n = np.abs(speed_rpm)
    steps = np.flatnonzero(np.abs(np.diff(n)) > TRANSIENT_STEP_FRACTION * max(max_rpm, 1.0)) + 1
    mask = np.zeros(n.size, dtype=bool)
    if steps.size == 0:
        return mask
    starts = time_s[steps]
    idx = np.searchsorted(starts, time_s, side="right") - 1
    ok = idx >= 0
    mask[ok] = time_s[ok] - starts[idx[ok]] < window_s
    return mask


def has_cooldown(run: Run, min_s: float = 600.0) -> bool:
    """A stretch at rest of ``min_s`` or longer after the spindle has run."""
    idle = np.abs(run.speed_rpm) < IDLE_RPM
    ran = np.cumsum(~idle) > 0
    seg = idle & ran
    if not seg.any():
        return False
    spans = np.array(stretches(seg))
    starts, ends = spans[:, 0], spans[:, 1] - 1
    t = run.time_s
    # a stretch at rest begins when the previous sample ended the last step at speed
    begin = t[np.maximum(starts - 1, 0)]
    return bool(np.max(t[ends] - begin) >= min_s)
