"""Run logs: the one format of calibration runs, replays, the journal and the simulator.

Format (shared by calibration, replay, the runtime journal and the
simulator)::

    # spindle_id: sp1            <- optional '# key: value' metadata lines
    time_s,speed_rpm,elongation_um,ambient_c
    0,0,0.00,22.0
    60,3000,1.52,22.0

``time_s`` and ``speed_rpm`` are required; ``elongation_um`` is optional; any
other column is kept. Time must strictly increase and be in seconds: a stamp beyond
:data:`MAX_ABS_TIME_S`, or a sample period and span no spindle's log has
(:func:`time_unit_refusal`: milliseconds counted from 0, say), is refused naming the likely unit;
speed and elongation must be physically possible
(:data:`MAX_SPEED_RPM`, :data:`MAX_ABS_ELONGATION_UM`). Gaps are allowed and
reported. Every error is one line naming the file and line.

Sparse measurements: a log whose metadata says ``# elongation_um: sparse`` (a journal export,
``thermocomp journal export``: probe measurements only) may leave ``elongation_um`` empty on the
rows that were not measured; they read as NaN (:attr:`RunLog.measured` is False there). Without
that line every row needs a number.

Whole files are written atomically (:mod:`compensator.io.atomic`); a recording appends a
row at a time (:class:`RunLogAppender`).
"""

from __future__ import annotations

import math
import os
import re
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import RunLogError
from .atomic import atomic_write

REQUIRED_COLUMNS = ("time_s", "speed_rpm")
ELONGATION_COLUMN = "elongation_um"
SPARSE = "sparse"
"""The value of the metadata key ``elongation_um`` that lets elongation cells be empty."""
GAP_FACTOR = 5.0
"""A step longer than this many median steps is reported as a gap."""

MAX_ABS_TIME_S = 1e11
"""Largest |time_s| read as seconds; a larger stamp is refused, not converted.

1e11 s after the epoch is the year 5138, so no time in seconds (relative, or epoch seconds,
~1.7e9 today) comes near it, while epoch milliseconds exceed it for any date after
1973-03-03 (~1.7e12 today): those are refused with "divide by 1000" (and microseconds and
nanoseconds with their factor). Milliseconds counted from 0 are told by the sample period and
span instead (:func:`time_unit_refusal`); a header that says so (a ``time_ms`` column) is
refused by name.
"""

TIME_UNIT_COLUMNS = {"time_ms": 1e3, "time_us": 1e6, "time_ns": 1e9}
"""Time columns in another unit, each with the factor that turns them into seconds."""

MIN_SAMPLE_PERIOD_S = 1e-4
"""Shortest median step read as seconds (10 kHz): loggers of a spindle's heating sample from
~10 ms to ~10 min; a shorter step is a clock in hours or minutes read as seconds."""
MAX_SAMPLE_PERIOD_S = 3600.0
"""Longest median step read as seconds: an hour, six times the slowest logger (~10 min), so a
log sampled every 1000 s stays legitimate; a longer step is milliseconds read as seconds."""
MAX_SPAN_S = 366 * 86400.0
"""Longest log read as seconds: a year (a calibration spans minutes to weeks, a journal export
months); 40 h in milliseconds spans 4.6 "years"."""
MIN_CALIBRATION_SPAN_S = 60.0
"""Shortest calibration log: a minute (a spindle's time constants are minutes to hours); 40 h
in hours spans 40 "s". Only where a log is to calibrate: replays and journals may be short."""
MIN_ROWS_TO_JUDGE = 10
"""A log with fewer rows has no sample period to tell its unit by: it is not judged."""
TIME_UNITS = (
    ("ms", "milliseconds", 1e-3),
    ("us", "microseconds", 1e-6),
    ("min", "minutes", 60.0),
    ("h", "hours", 3600.0),
)
"""The units a time column is taken in by mistake: (suffix, name, seconds per unit)."""

MAX_SPEED_RPM = 1e6
"""Largest |speed_rpm| accepted: the fastest spindles turn ~3e5 rpm; beyond is a unit or
column mix-up (or a garbage reading), and would overflow the model's arithmetic."""

MAX_ABS_ELONGATION_UM = 1e6
"""Largest |elongation_um| the reader accepts (1 m): beyond, no sensor reads micrometres.
Calibration holds runs to a much tighter bound (``calibration.runs.MAX_PLAUSIBLE_UM``)."""

_YEAR_S = 365.2425 * 86400.0


@dataclass(frozen=True)
class Gap:
    line: int
    start_s: float
    duration_s: float


@dataclass(frozen=True)
class RunLog:
    """A parsed run log. Arrays are float64 and share one length."""

    time_s: np.ndarray
    speed_rpm: np.ndarray
    elongation_um: np.ndarray | None = None
    extras: Mapping[str, np.ndarray] = field(default_factory=dict)
    metadata: Mapping[str, str] = field(default_factory=dict)
    gaps: tuple[Gap, ...] = ()
    source: str | None = None

    def __len__(self) -> int:
        return int(self.time_s.size)

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1] - self.time_s[0]) if len(self) else 0.0

    @property
    def measured(self) -> np.ndarray:
        """bool per row: the row has a measured elongation (all False without the column; False
        on the empty cells of a sparse log)."""
        if self.elongation_um is None:
            return np.zeros(len(self), dtype=bool)
        measured: np.ndarray = np.isfinite(np.asarray(self.elongation_um, dtype=float))
        return measured

    @property
    def sparse(self) -> bool:
        """The elongation is measured on some rows but not all (see the module's docstring)."""
        m = self.measured
        return self.elongation_um is not None and not bool(m.all())

    @property
    def median_dt_s(self) -> float:
        return float(np.median(np.diff(self.time_s))) if len(self) > 1 else 0.0

    def line_of(self, row: int) -> int | None:
        """File line of data row ``row``, when the log came from a file."""
        if self.source is None:
            return None
        return _line_of_row(self.source, row)


def cell_format(column: int, kind: str) -> str:
    """printf format of one cell by column position and numpy dtype kind: 9 significant
    digits (sub-nanometre for um); time gets 15, so that epoch seconds keep their milliseconds."""
    if kind == "f":
        return "%.15g" if column == 0 else "%.9g"
    return "%d" if kind in "iub" else "%s"


def row_format(kinds: Sequence[str]) -> str:
    return ",".join(cell_format(i, k) for i, k in enumerate(kinds))


def header_text(columns: Sequence[str], metadata: Mapping[str, Any] | None) -> str:
    """The ``# key: value`` metadata lines and the header line of a run log."""
    return "".join(f"# {k}: {v}\n" for k, v in (metadata or {}).items()) + ",".join(columns) + "\n"


def _is_skipped(line: str) -> bool:
    s = line.strip()
    return not s or s.startswith("#")


def _lines_of_rows(path: str, rows: list[int]) -> dict[int, int]:
    """1-based file lines of data rows (0-based), skipping comments and blanks."""
    wanted = set(rows)
    found: dict[int, int] = {}
    last = max(wanted, default=-1)
    seen = -1  # the header is row -1
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, start=1):
            if _is_skipped(line):
                continue
            if seen in wanted:
                found[seen] = lineno
            if seen >= last:
                break
            seen += 1
    return found


def _line_of_row(path: str, row: int) -> int | None:
    return _lines_of_rows(path, [row]).get(row)


def _first_ragged_line(path: str) -> tuple[int | None, int, int]:
    """(line, fields, header fields) of the first row whose width differs from the header."""
    width = None
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, start=1):
            if _is_skipped(line):
                continue
            fields = len(line.split("#", 1)[0].rstrip("\r\n").split(","))
            if width is None:
                width = fields
            elif fields != width:
                return lineno, fields, width
    return None, 0, width or 0


def _read_metadata(path: str) -> tuple[dict[str, str], int | None]:
    """Leading '# key: value' lines, and the line number of the header."""
    meta: dict[str, str] = {}
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, start=1):
            s = line.strip()
            if not s:
                continue
            if s.startswith("#"):
                key, sep, value = s.lstrip("#").partition(":")
                if sep and key.strip():
                    meta[key.strip()] = value.strip()
                continue
            return meta, lineno
    return meta, None


def _raw_cell(path: str, line: int | None, column: int) -> str:
    """The text of one cell, stripped; '' when it cannot be found."""
    if line is None:
        return ""
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, text in enumerate(fh, start=1):
            if lineno == line:
                cells = text.split("#", 1)[0].rstrip("\r\n").split(",")
                return cells[column].strip() if column < len(cells) else ""
    return ""


def _factor_text(factor: float) -> str:
    return "1000" if factor == 1e3 else f"1e{round(math.log10(factor))}"


def _check_time_unit(time_s: np.ndarray, src: str) -> None:
    """Refuse time stamps that cannot be seconds (:data:`MAX_ABS_TIME_S`), naming the first."""
    beyond = np.flatnonzero(np.abs(time_s) > MAX_ABS_TIME_S)
    if not beyond.size:
        return
    row = int(beyond[0])
    t = float(time_s[row])
    line = _line_of_row(src, row)
    for factor, unit in ((1e3, "milliseconds"), (1e6, "microseconds"), (1e9, "nanoseconds")):
        if 0 < t / factor <= MAX_ABS_TIME_S:
            raise RunLogError(
                f"time_s looks like {unit} ({t:.15g} s would be the year "
                f"{1970 + t / _YEAR_S:,.0f}); divide by {_factor_text(factor)}",
                src,
                line,
            )
    raise RunLogError(
        f"time_s {t:g} s is beyond {MAX_ABS_TIME_S:g} s (the year 5138): not seconds", src, line
    )


def _duration_text(seconds: float) -> str:
    """A duration in the unit a person reads it in."""
    s = abs(seconds)
    if s >= 2 * _YEAR_S:
        return f"{seconds / _YEAR_S:.1f} years"
    if s >= 3 * 86400:
        return f"{seconds / 86400:.1f} days"
    if s >= 2 * 3600:
        return f"{seconds / 3600:.3g} h"
    if s >= 120:
        return f"{seconds / 60:.3g} min"
    if s >= 0.1:
        return f"{seconds:.3g} s"
    return f"{seconds * 1e3:.3g} ms"


def _plausible_s(step_s: float, span_s: float, min_span_s: float) -> bool:
    return (
        MIN_SAMPLE_PERIOD_S <= step_s <= MAX_SAMPLE_PERIOD_S and min_span_s <= span_s <= MAX_SPAN_S
    )


def time_unit_refusal(
    time_s: Any, column: str = "time_s", *, min_span_s: float = 0.0, also: str = ""
) -> str | None:
    """Why ``time_s`` cannot be seconds, in one line naming the likely unit and the fix, or None.

    Judged by the median step (the sample period) and the span (the time covered, gaps left
    out: :data:`GAP_FACTOR`), against what a spindle's logs have (:data:`MIN_SAMPLE_PERIOD_S` .. :data:`MAX_SAMPLE_PERIOD_S`, up to :data:`MAX_SPAN_S`,
    from ``min_span_s``: :data:`MIN_CALIBRATION_SPAN_S` where a log is to calibrate). A log of
    fewer than :data:`MIN_ROWS_TO_JUDGE` rows is not judged. The numbers cannot tell every
    mistake: minutes read as seconds look like a short, fast log, and are caught (if at all) by
    the fitted time constants (:func:`compensator.plausibility.time_constant_refusal`).
    ``also``: another way out, said after the conversion (``{unit}``: the likely unit's suffix).
    """
    t = np.asarray(time_s, dtype=float)
    if t.size < MIN_ROWS_TO_JUDGE or not np.isfinite(t).all():
        return None
    steps_s = np.diff(t)
    step_s = float(np.median(steps_s))
    if step_s <= 0:
        return None
    # the time the log covers, its gaps left out: a journal may pause for a year
    span_s = float(steps_s[steps_s <= GAP_FACTOR * step_s].sum())
    if _plausible_s(step_s, span_s, min_span_s):
        return None
    seen = f"steps of {_duration_text(step_s)} over {_duration_text(span_s)}"
    fits = [
        (abs(math.log10(step_s * f / 10.0)) + abs(math.log10(span_s * f / 86400.0)), u, name, f)
        for u, name, f in TIME_UNITS
        if _plausible_s(step_s * f, span_s * f, max(min_span_s, MIN_CALIBRATION_SPAN_S))
    ]
    if not fits:
        return f"{column} is not seconds: {seen} are no spindle log's; convert it to seconds{also}"
    _, unit, name, factor = min(fits)
    how = f"divide it by {_factor_text(1 / factor)}" if factor < 1 else f"multiply it by {factor:g}"
    return (
        f"{column} looks like {name}: {seen} are no spindle log's (in {unit}: "
        f"{_duration_text(step_s * factor)} steps over {_duration_text(span_s * factor)}); "
        f"{how} to make it seconds{also.format(unit=unit)}"
    )


def _check_magnitude(
    values: np.ndarray, limit: float, col: str, unit: str, why: str, src: str
) -> None:
    """Refuse the first |value| over ``limit``: a unit mix-up or garbage, not a measurement."""
    over = np.flatnonzero(np.abs(values) > limit)
    if over.size:
        row = int(over[0])
        raise RunLogError(
            f"column {col}: {values[row]:g} {unit} is beyond {limit:g} {unit} ({why})",
            src,
            _line_of_row(src, row),
        )


def read_run_log(path: str | os.PathLike[str]) -> RunLog:
    """Read a run log; raise :class:`RunLogError` naming file and line on any fault."""
    import pandas as pd  # heavy; only the reader needs it

    src = os.fspath(path)
    try:
        meta, header_line = _read_metadata(src)
    except OSError as err:
        raise RunLogError(f"cannot read: {err.strerror or err}", src) from err
    except UnicodeError as err:
        raise RunLogError("not a text file", src) from err
    if header_line is None:
        raise RunLogError("no header line (expected time_s,speed_rpm[,elongation_um,...])", src)
    try:
        with warnings.catch_warnings():
            # a row longer than the header must not silently become an index
            warnings.simplefilter("error", pd.errors.ParserWarning)
            df = pd.read_csv(
                src,
                comment="#",
                skip_blank_lines=True,
                skipinitialspace=True,
                index_col=False,
                engine="c",
                low_memory=False,
            )
    except pd.errors.EmptyDataError as err:
        raise RunLogError("empty file", src) from err
    except (pd.errors.ParserError, pd.errors.ParserWarning, ValueError, UnicodeError) as err:
        line, fields, width = _first_ragged_line(src)
        if line is not None:
            raise RunLogError(
                f"malformed CSV: {fields} fields where the header has {width}", src, line
            ) from err
        msg = str(err).strip().splitlines()[-1]
        raise RunLogError(f"malformed CSV: {msg}", src) from err
    df.columns = [str(c).strip() for c in df.columns]
    dupes = sorted({c for c in df.columns if list(df.columns).count(c) > 1})
    if dupes:
        raise RunLogError(f"duplicate column(s) {', '.join(dupes)}", src, header_line)
    missing = [c for c in REQUIRED_COLUMNS if c not in df.columns]
    other_unit = [c for c in TIME_UNIT_COLUMNS if c in df.columns]
    if "time_s" in missing and other_unit:
        col = other_unit[0]
        raise RunLogError(
            f"column {col}: time must be in seconds, in a column time_s; divide by "
            f"{_factor_text(TIME_UNIT_COLUMNS[col])} and rename",
            src,
            header_line,
        )
    slow_unit = [u for u in TIME_UNITS if f"time_{u[0]}" in df.columns and u[2] > 1]
    if "time_s" in missing and slow_unit:
        raise RunLogError(
            f"column time_{slow_unit[0][0]}: time must be in seconds, in a column time_s; "
            f"multiply by {slow_unit[0][2]:g} and rename",
            src,
            header_line,
        )
    if missing:
        raise RunLogError(
            f"missing column(s) {', '.join(missing)} in header {','.join(df.columns)}",
            src,
            header_line,
        )
    if len(df) == 0:
        raise RunLogError("no data rows", src)

    def numeric(col: str, allow_nan: bool = False) -> np.ndarray:
        raw = df[col]
        values = pd.to_numeric(raw, errors="coerce").to_numpy(dtype=float)
        # allowed: cells empty (or nan, NA...): no value; text that is not a number never is
        bad = (
            np.isinf(values) | (np.isnan(values) & raw.notna().to_numpy())
            if allow_nan
            else ~np.isfinite(values)
        )
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            line = _line_of_row(src, row)
            cell = raw.iloc[row]
            if cell is None or (isinstance(cell, float) and math.isnan(cell)):
                # pandas reads 'nan', 'NA', 'null' and an empty cell alike: show the text
                text = _raw_cell(src, line, list(df.columns).index(col))
                what = f"'{text}'" if text else "empty cell"
            else:
                what = f"'{cell}'"
            raise RunLogError(f"column {col}: {what} is not a finite number", src, line)
        return values

    time_s = numeric("time_s")
    speed = numeric("speed_rpm")
    sparse = meta.get(ELONGATION_COLUMN, "").strip().lower() == SPARSE
    elong = numeric(ELONGATION_COLUMN, sparse) if ELONGATION_COLUMN in df.columns else None
    _check_time_unit(time_s, src)
    dt = np.diff(time_s)
    back = np.flatnonzero(dt <= 0)
    if back.size:
        row = int(back[0]) + 1
        raise RunLogError(
            f"time does not increase ({time_s[row]:g} s after {time_s[row - 1]:g} s)",
            src,
            _line_of_row(src, row),
        )
    why = time_unit_refusal(time_s)
    if why is not None:
        raise RunLogError(why, src)
    _check_magnitude(speed, MAX_SPEED_RPM, "speed_rpm", "rpm", "no spindle turns that fast", src)
    if elong is not None:
        _check_magnitude(
            elong,
            MAX_ABS_ELONGATION_UM,
            ELONGATION_COLUMN,
            "um",
            "over 1 m: wrong unit or a sensor fault?",
            src,
        )
    extras: dict[str, np.ndarray] = {}
    for col in df.columns:
        if col in REQUIRED_COLUMNS or col == ELONGATION_COLUMN:
            continue
        conv = pd.to_numeric(df[col], errors="coerce")
        extras[col] = (
            conv.to_numpy(dtype=float)
            if conv.notna().sum() == df[col].notna().sum()
            else df[col].to_numpy(dtype=object)
        )
    gaps: tuple[Gap, ...] = ()
    if dt.size:
        idx = np.flatnonzero(dt > GAP_FACTOR * float(np.median(dt)))
        lines = _lines_of_rows(src, [int(k) + 1 for k in idx[:100]])
        gaps = tuple(Gap(lines.get(int(k) + 1, -1), float(time_s[k]), float(dt[k])) for k in idx)
    return RunLog(
        time_s=time_s,
        speed_rpm=speed,
        elongation_um=elong,
        extras=extras,
        metadata=meta,
        gaps=gaps,
        source=src,
    )


def write_run_log(
    path: str | os.PathLike[str],
    columns: Mapping[str, np.ndarray],
    metadata: Mapping[str, Any] | None = None,
) -> None:
    """Atomically write a run log. ``columns`` must start with time_s, speed_rpm."""
    names = list(columns)
    if names[:2] != list(REQUIRED_COLUMNS):
        raise RunLogError(f"a run log starts with columns {REQUIRED_COLUMNS}, got {names[:2]}")
    arrays = [np.asarray(columns[name]) for name in names]
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1:
        raise RunLogError(f"columns differ in length: {sorted(shapes)}")
    fmt = row_format([a.dtype.kind for a in arrays])
    rows = arrays[0].shape[0]
    with atomic_write(path) as fh:
        fh.write(header_text(names, metadata))
        for s in range(0, rows, 100_000):  # bounded memory on month-long logs
            block = zip(*(a[s : s + 100_000].tolist() for a in arrays))
            fh.write("\n".join(map(fmt.__mod__, block)) + "\n")


class RunLogAppender:
    """Append rows to a run log as they are measured, so an interruption loses nothing.

    A new file gets the metadata and header; an existing one must have the same header, and
    a half-written last line (a crash mid-write) is cut off before appending. Each row is
    flushed; the file is fsynced every ``fsync_every_s`` of ``clock`` and on close.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        columns: tuple[str, ...],
        metadata: Mapping[str, Any] | None = None,
        *,
        fsync_every_s: float = 5.0,
        clock: Any = None,
    ):
        if tuple(columns[:2]) != REQUIRED_COLUMNS:
            raise RunLogError(f"a run log starts with columns {REQUIRED_COLUMNS}")
        self.path = Path(path)
        self.columns = tuple(columns)
        self._fmt = row_format("f" * len(self.columns))
        self._clock = clock or time.monotonic
        self.fsync_every_s = fsync_every_s
        self.rows_before = 0
        self.last_row: tuple[float, ...] | None = None
        self.first_row: tuple[float, ...] | None = None
        self.metadata: dict[str, str] = {}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists() and self.path.stat().st_size > 0:
            self._adopt()
            self._fh = open(self.path, "a", encoding="utf-8")
        else:
            self._fh = open(self.path, "w", encoding="utf-8")
            self.metadata = {k: str(v) for k, v in (metadata or {}).items()}
            self._fh.write(header_text(self.columns, self.metadata))
            self._sync()
        self._last_sync = self._clock()

    def _adopt(self) -> None:
        src = str(self.path)
        data = self.path.read_bytes()
        if not data.endswith(b"\n"):
            cut = data.rfind(b"\n") + 1
            with open(self.path, "r+b") as fh:
                fh.truncate(cut)
        meta, header_line = _read_metadata(src)
        self.metadata = meta
        if header_line is None:
            raise RunLogError("no header line", src)
        with open(self.path, encoding="utf-8") as fh:
            lines = fh.read().splitlines()
        header = tuple(c.strip() for c in lines[header_line - 1].split(","))
        if header != self.columns:
            raise RunLogError(
                f"header {','.join(header)} differs from {','.join(self.columns)}: "
                "not a log of this recording",
                src,
                header_line,
            )
        rows = [ln for ln in lines[header_line:] if not _is_skipped(ln)]
        self.rows_before = len(rows)
        if rows:
            try:
                self.first_row = tuple(float(v) for v in rows[0].split(","))
                self.last_row = tuple(float(v) for v in rows[-1].split(","))
            except ValueError as err:
                raise RunLogError(f"unreadable row: {err}", src, header_line + len(rows)) from err

    def append(self, values: tuple[float, ...] | list[float]) -> None:
        if len(values) != len(self.columns):
            raise RunLogError(
                f"{len(values)} values for {len(self.columns)} columns", str(self.path)
            )
        if self.last_row is not None and not values[0] > self.last_row[0]:
            return  # the format needs increasing time; a repeated instant adds nothing
        self._fh.write(self._fmt % tuple(values) + "\n")
        self._fh.flush()
        self.last_row = tuple(float(v) for v in values)
        if self.first_row is None:
            self.first_row = self.last_row
        if self._clock() - self._last_sync >= self.fsync_every_s:
            self._sync()

    def _sync(self) -> None:
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._last_sync = self._clock()

    def close(self) -> None:
        if not self._fh.closed:
            self._sync()
            self._fh.close()

    def __enter__(self) -> RunLogAppender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def time_unit_of(column: str) -> tuple[str, str, float] | None:
    """(suffix, name, seconds per unit) when a column's name says its time unit other than
    seconds: ``time_ms``, ``t_min``, ``Time [ms]``, ``time (h)``; None when it says seconds or
    nothing."""
    m = _UNIT_IN_NAME.search(column.strip().lower())
    if m is None:
        return None
    said = m.group(1).replace("µ", "u")
    return next((u for u in TIME_UNITS if u[0] == said), None)


_UNIT_IN_NAME = re.compile(r"(?:^|[_\s\[(])(ms|us|µs|min|h|s)[\])]?$")


def read_daq_csv(
    path: str | os.PathLike[str],
    time_column: str,
    columns: Mapping[str, str],
    *,
    seconds_per_unit: float = 1.0,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Time [s] and named columns from a CSV a data-acquisition system wrote.

    ``columns`` maps the names wanted to the file's column names. The time column may hold
    seconds (or numbers in another unit, ``seconds_per_unit`` each) or date-times (ISO 8601);
    date-times become seconds since the epoch. Rows are sorted by time; an unreadable cell is
    reported with its line; time that cannot be seconds (:func:`time_unit_refusal`) is refused.
    """
    import pandas as pd

    src = os.fspath(path)
    try:
        df = pd.read_csv(src, comment="#", skipinitialspace=True, sep=None, engine="python")
    except OSError as err:
        raise RunLogError(f"cannot read: {err.strerror or err}", src) from err
    except (pd.errors.ParserError, pd.errors.EmptyDataError, ValueError, UnicodeError) as err:
        raise RunLogError(f"not a readable CSV: {str(err).strip().splitlines()[-1]}", src) from err
    df.columns = [str(c).strip() for c in df.columns]
    want = {"time": time_column, **columns}
    missing = [c for c in want.values() if c not in df.columns]
    if missing:
        raise RunLogError(
            f"no column(s) {', '.join(missing)}; the file has {', '.join(df.columns)}", src
        )
    header_line = _read_metadata(src)[1] or 1

    def bad(row: int, col: str, cell: Any) -> RunLogError:
        return RunLogError(
            f"column {col}: {cell!r} is not a finite number", src, header_line + 1 + row
        )

    raw_t = df[time_column]
    t = pd.to_numeric(raw_t, errors="coerce").to_numpy(dtype=float)
    if np.isnan(t).all():
        stamps = pd.to_datetime(raw_t, errors="coerce", utc=True, format="ISO8601")
        if stamps.isna().any():
            row = int(np.flatnonzero(stamps.isna().to_numpy())[0])
            raise RunLogError(
                f"column {time_column}: {raw_t.iloc[row]!r} is neither seconds nor a date-time",
                src,
                header_line + 1 + row,
            )
        t = (stamps - pd.Timestamp("1970-01-01", tz="UTC")).dt.total_seconds().to_numpy(dtype=float)
    elif not np.isfinite(t).all():
        row = int(np.flatnonzero(~np.isfinite(t))[0])
        raise bad(row, time_column, raw_t.iloc[row])
    else:
        t = t * seconds_per_unit
    out: dict[str, np.ndarray] = {}
    for name, col in columns.items():
        v = pd.to_numeric(df[col], errors="coerce").to_numpy(dtype=float)
        if not np.isfinite(v).all():
            row = int(np.flatnonzero(~np.isfinite(v))[0])
            raise bad(row, col, df[col].iloc[row])
        out[name] = v
    order = np.argsort(t, kind="stable")
    t = t[order]
    keep = np.r_[True, np.diff(t) > 0]  # repeated instants: the first reading is kept
    why = time_unit_refusal(
        t[keep],
        time_column,
        also=", or call the column time_{unit}: the import converts it",
    )
    if why is not None:
        raise RunLogError(why, src)
    return t[keep], {k: v[order][keep] for k, v in out.items()}
