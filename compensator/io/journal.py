"""The runtime's journal: one run-log file per spindle and UTC day, a row per cycle.

The journal must never stop compensation. :meth:`Journal.write` does not raise: a row that
cannot be written (full disk, a file-size limit, a read-only directory) stays queued in
memory and is written, in order, once the disk takes it again, retried with back-off. A
partial row left by a failed write is cut off again, so the file stays a valid run log.

``time_s`` is the runtime's monotonic clock anchored to the wall clock once, at start: it
always increases, and its differences are exactly the ``dt_s`` the model and the shaper used.
``wall_s`` is the wall clock as read, so a clock step shows and is flagged by the runtime,
not fatal. A day file that already ends later than the first new row (the clock was set
back between two runs) is continued in a new part, ``<name>-<day>.p2.csv``; so is one written
with other columns (an older version).

Per cycle it also records how the offset was shaped: ``cutting`` (1 when the tool
was taken to be in the part), ``cutting_source`` (``controller``: the controller's signal;
``speed``: inferred from the speed; ``speed-fallback``: inferred because the signal failed),
``policy_state`` (dual-slew ``cutting`` or ``clear``; slow/hold ``tracking``, ``window`` or
``releasing``) and ``slew_limit_um_per_s`` (the limit in force). Replay reads the ``cutting``
column of a journal as the controller's signal.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, BinaryIO

from ..errors import ConfigError
from .atomic import NOT_FOLLOWED, open_regular
from .runlog import header_text

log = logging.getLogger("thermocomp.journal")

ALARM_COLD_START = 32
"""The bit of the ``alarms`` column that marks a cold start (no saved state): the estimate began
at the model's own equilibrium at rest."""
FAULT_ALARM_BITS = {
    "SPEED_READ_FAILED": 1,
    "IDLE_ASSUMED": 2,
    "LINK_DOWN": 8,
    "OUTAGE": 64,
    "NOT_READY": 128,
    "INPUT_FALLBACK": 256,
    "CLOCK_STEP": 32768,
    "ESTIMATE_REFUSED": 4194304,
}
"""The bits of the ``alarms`` column that mark a cycle whose speed, inputs or time cannot be
trusted: a measurement taken then judges no model (``calibration.learning``)."""
FAULT_ALARMS = sum(FAULT_ALARM_BITS.values())
SHADOW_COLUMN = "shadow_um"
"""The column a shadow candidate's estimate is journaled in, after the input channels: run
beside the live model, never written to the controller."""
MAX_PENDING_ROWS = 250_000
"""Rows kept in memory while the disk refuses them (about 3 days at one cycle a second)."""
KIND_SUFFIXES = (".measurements", ".cooling")
"""What a spindle's measurement and cooling journals add to its name (``NAME.cooling-DAY.csv``)."""


def spindle_name_problem(name: str) -> str | None:
    """Why ``name`` cannot name a spindle's journals, or None. A name ending in a kind's suffix
    would make its cycle journal read as another spindle's measurements or chiller commands
    (``a.cooling-DAY.csv`` is spindle ``a``'s cooling journal)."""
    for suffix in KIND_SUFFIXES:
        if name.endswith(suffix):
            return (
                f"may not end in {suffix}: its journal files would read as those of "
                f"spindle {name.removesuffix(suffix)!r}"
            )
    return None


class Journal:
    """The runtime's journal: the common run-log format, one file per UTC day."""

    COLUMNS: tuple[str, ...] = (
        "time_s",
        "speed_rpm",
        "predicted_um",
        "offset_um",
        "written",
        "flags",
        "alarms",
        "dt_s",
        "wall_s",
        "cutting",
        "cutting_source",
        "policy_state",
        "slew_limit_um_per_s",
    )

    KIND = ""
    """What this kind of journal adds to the spindle's name in its files' names."""

    def __init__(
        self,
        directory: str | os.PathLike[str],
        name: str,
        metadata: Mapping[str, Any],
        *,
        fsync_every_s: float = 10.0,
        retry_s: float = 1.0,
        max_retry_s: float = 60.0,
        max_pending_rows: int = MAX_PENDING_ROWS,
        input_columns: tuple[str, ...] = (),
    ):
        self.directory = Path(directory)
        spindle = name.removesuffix(self.KIND)
        problem = spindle_name_problem(spindle)
        if problem is not None:
            raise ConfigError(f"spindle name {spindle!r} {problem}")
        bad = sorted(
            {c for c in input_columns if _word(c) != c or not c}
            | (set(input_columns) & set(type(self).COLUMNS))
        )
        if bad or len(set(input_columns)) != len(input_columns):
            raise ConfigError(
                f"{name}: input channel names must be letters, digits, - and _ (40 at "
                f"most), unique, and not a journal column: {', '.join(bad) or 'duplicates'}"
            )
        self.input_columns = tuple(input_columns)
        self._inputs = tuple(input_columns)
        self.name = name
        self.metadata = dict(metadata)
        self.fsync_every_s = fsync_every_s
        self.retry_s = retry_s
        self.max_retry_s = max_retry_s
        self._pending: collections.deque[tuple[float, str]] = collections.deque(
            maxlen=max_pending_rows
        )
        self.dropped_rows = 0
        self._fd: int | None = None
        self._day: str | None = None
        self._path: Path | None = None
        self._last_t = -math.inf
        self._last_sync: float | None = None
        self._failures = 0
        self._next_try = -math.inf
        self.error: str | None = None
        """Why the last write failed (file and OS error); None while the journal is writing."""

    @property
    def path(self) -> Path | None:
        """The file being written."""
        return self._path

    @property
    def pending_rows(self) -> int:
        return len(self._pending)

    def path_for(self, day: str, part: int = 1) -> Path:
        return self.directory / (
            f"{self.name}-{day}.csv" if part == 1 else f"{self.name}-{day}.p{part}.csv"
        )

    def write(
        self,
        time_s: float,
        speed_rpm: float,
        predicted_um: float,
        offset_um: float,
        written: bool,
        flags: int,
        alarms: int,
        *,
        dt_s: float = 0.0,
        wall_s: float | None = None,
        now_s: float | None = None,
        cutting: bool = False,
        cutting_source: str = "speed",
        policy_state: str = "tracking",
        slew_limit_um_per_s: float | None = None,
        inputs: Mapping[str, float] | None = None,
    ) -> bool:
        """Queue one row and write what the disk takes; True when nothing is left queued.

        ``now_s`` (monotonic seconds, default ``time_s``) paces the retries and the fsync.
        ``inputs``: this cycle's values of the input channels (a missing or non-finite one is
        a blank cell).
        """
        t = self._next_time(time_s)
        wall = t if wall_s is None else wall_s
        row = (
            f"{t:.3f},{speed_rpm:.9g},{predicted_um:.12g},{offset_um:.12g},{int(written)},"
            f"{int(flags)},{int(alarms)},{dt_s:.9f},{wall:.3f},{int(cutting)},{_word(cutting_source)},"
            f"{_word(policy_state)},{_cell(slew_limit_um_per_s)}"
        )
        if self._inputs:
            got = inputs or {}
            row += "," + ",".join(_cell(got.get(name), ".9g") for name in self._inputs)
        return self._enqueue(t, row + "\n", now_s)

    @property
    def columns(self) -> tuple[str, ...]:
        """The header of this journal's files: the fixed columns, then the input channels."""
        return tuple(type(self).COLUMNS) + self.input_columns

    def _next_time(self, time_s: float) -> float:
        t = max(time_s, self._last_t + 1e-3)  # the run-log format needs increasing time
        self._last_t = t
        return t

    def _enqueue(self, t: float, row: str, now_s: float | None) -> bool:
        if len(self._pending) == self._pending.maxlen:
            self.dropped_rows += 1
        self._pending.append((t, row))
        now = t if now_s is None else now_s
        if now < self._next_try:
            return False
        return self.flush(now)

    def flush(self, now_s: float) -> bool:
        """Write the queued rows; on failure keep them and set :attr:`error`."""
        try:
            while self._pending:
                day = time.strftime("%Y-%m-%d", time.gmtime(self._pending[0][0]))
                if day != self._day:
                    self._open(day, self._pending[0][0])
                batch = []
                for t, row in self._pending:
                    if time.strftime("%Y-%m-%d", time.gmtime(t)) != day:
                        break
                    batch.append(row)
                self._append("".join(batch))
                for _ in batch:
                    self._pending.popleft()
            if self.fsync_every_s >= 0 and (
                self._last_sync is None or now_s - self._last_sync >= self.fsync_every_s
            ):
                self._sync(now_s)
        except OSError as err:
            self._failures += 1
            self._next_try = now_s + min(self.max_retry_s, self.retry_s * 2 ** (self._failures - 1))
            where = err.filename or self._path or self.directory
            self.error = f"{where}: {err.strerror or err}"
            return False
        self._failures = 0
        self._next_try = -math.inf
        self.error = None
        return True

    def _open(self, day: str, first_t: float) -> None:
        self._close_fd()
        self.directory.mkdir(parents=True, exist_ok=True)
        part = 1
        header = ",".join(self.columns)
        while True:
            path = self.path_for(day, part)
            cut_torn_tail(path)  # a power loss's partial row is never glued to a new one
            last = _last_time(path)
            # a new part: the clock was set back (every file keeps increasing time), or the file
            # has other columns (written by another version)
            if (last is None or last < first_t) and _header(path) in (None, header):
                break
            part += 1
        fd = open_regular(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT)
        try:
            if os.fstat(fd).st_size == 0:
                self._write_all(fd, header_text(self.columns, self.metadata))
        except OSError:
            os.close(fd)
            raise
        self._fd, self._day, self._path = fd, day, path

    def _append(self, text: str) -> None:
        assert self._fd is not None
        self._write_all(self._fd, text)

    @staticmethod
    def _write_all(fd: int, text: str) -> None:
        """Write all of ``text`` or none of it: a partial write is cut off again."""
        data = text.encode("utf-8")
        size = os.fstat(fd).st_size
        try:
            done = 0
            while done < len(data):
                done += os.write(fd, data[done:])
        except OSError:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, size)
            raise

    def _sync(self, now_s: float) -> None:
        if self._fd is not None:
            os.fsync(self._fd)
        self._last_sync = now_s

    def _close_fd(self) -> None:
        fd, self._fd, self._day = self._fd, None, None
        if fd is not None:
            try:
                os.fsync(fd)  # on rotation and close
            except OSError:
                pass
            finally:
                os.close(fd)

    def close(self, now_s: float | None = None) -> None:
        """Write what is queued (one last try) and close."""
        if self._pending:
            self.flush(now_s if now_s is not None else self._last_t)
        self._close_fd()


def _word(text: str, also: str = "-_") -> str:
    """A text cell: letters, digits and the characters in ``also`` only (no separator can slip
    in), 40 at most."""
    return "".join(c for c in text if c.isalnum() or c in also)[:40]


def _header(path: Path) -> str | None:
    """The column line of an existing run log, or None (missing, empty or not a regular file)."""
    try:
        fd = open_regular(path, os.O_RDONLY)
    except OSError:
        return None
    with os.fdopen(fd, "rb") as fh:
        return _header_of(fh)


def _header_of(fh: BinaryIO) -> str | None:
    """The column line of a run log open for binary reading from its start, or None."""
    for raw in fh:
        line = raw.decode("utf-8", "replace")
        if line.strip() and not line.startswith("#"):
            return line.strip()
    return None


def _cell(value: float | None, fmt: str = ".9g") -> str:
    return "" if value is None or not math.isfinite(value) else format(value, fmt)


class MeasurementJournal(Journal):
    """Every tool-setter or probe measurement the runtime was given, one row each: what it
    measured, against what estimate, and what the observer made of it. One file per spindle
    and UTC day, ``<spindle>.measurements-YYYY-MM-DD.csv`` beside the journal, on the journal's
    time base (``time_s``); it never raises either. ``outcome``: ``accepted``, ``rejected``
    (beyond the gate), ``restarted`` (the bias restarted from agreeing refusals) or ``refused``
    (not a usable value: its cells are empty). Its ``time_s,elongation_um,sigma_um`` columns
    are a measurements file as replay reads one."""

    KIND = ".measurements"

    COLUMNS = (
        "time_s",
        "elongation_um",
        "sigma_um",
        "source",
        "sequence",
        "outcome",
        "predicted_um",
        "innovation_um",
        "innovation_sd_um",
        "bias_um",
        "bias_sd_um",
        "wall_s",
    )

    def __init__(
        self, directory: str | os.PathLike[str], name: str, metadata: Mapping[str, Any], **kw: Any
    ):
        super().__init__(directory, name + self.KIND, metadata, **kw)

    def record(
        self,
        time_s: float,
        *,
        elongation_um: float | None,
        sigma_um: float | None,
        source: str,
        sequence: int | None,
        outcome: str,
        predicted_um: float | None = None,
        innovation_um: float | None = None,
        innovation_sd_um: float | None = None,
        bias_um: float | None = None,
        bias_sd_um: float | None = None,
        wall_s: float | None = None,
        now_s: float | None = None,
    ) -> bool:
        """Queue one measurement's row and write what the disk takes (never raises)."""
        t = self._next_time(time_s)
        src = _word(source, "-_.:") or "unknown"
        row = (
            ",".join(
                (
                    f"{t:.3f}",
                    _cell(elongation_um, ".12g"),
                    _cell(sigma_um),
                    src,
                    "" if sequence is None else str(int(sequence)),
                    outcome,
                    _cell(predicted_um, ".12g"),
                    _cell(innovation_um),
                    _cell(innovation_sd_um),
                    _cell(bias_um, ".12g"),
                    _cell(bias_sd_um),
                    f"{t if wall_s is None else wall_s:.3f}",
                )
            )
            + "\n"
        )
        return self._enqueue(t, row, now_s)


class CoolingJournal(Journal):
    """Every chiller command and what came of it, one row per cooling cycle: the estimate the
    law saw, its phase, the set point commanded, whether it was sent, the chiller's supply
    temperature and the alarm. ``<spindle>.cooling-YYYY-MM-DD.csv`` beside the journal, on its
    time base; it never raises."""

    KIND = ".cooling"
    COLUMNS = (
        "time_s",
        "estimate_um",
        "rite_um",
        "phase",
        "setpoint_c",
        "sent",
        "supply_c",
        "alarm",
        "wall_s",
    )

    def __init__(
        self, directory: str | os.PathLike[str], name: str, metadata: Mapping[str, Any], **kw: Any
    ):
        super().__init__(directory, name + self.KIND, metadata, **kw)

    def record(
        self,
        time_s: float,
        *,
        estimate_um: float | None,
        rite_um: float,
        phase: str,
        setpoint_c: float,
        sent: bool,
        supply_c: float | None,
        alarm: str,
        wall_s: float | None = None,
        now_s: float | None = None,
    ) -> bool:
        """Queue one command's row and write what the disk takes (never raises)."""
        t = self._next_time(time_s)
        row = (
            ",".join(
                (
                    f"{t:.3f}",
                    _cell(estimate_um, ".6g"),
                    _cell(rite_um, ".6g"),
                    _word(phase, "-_") or "-",
                    _cell(setpoint_c, ".6g"),
                    "1" if sent else "0",
                    _cell(supply_c, ".6g"),
                    _word(alarm, "-_|") or "",
                    f"{t if wall_s is None else wall_s:.3f}",
                )
            )
            + "\n"
        )
        return self._enqueue(t, row, now_s)


TAIL_BYTES = 1 << 16
"""How far back from its end a file is checked for a torn tail (a row is far shorter)."""


def cut_torn_tail(path: Path) -> Path | None:
    """Cut a run log back to its last complete row: a power loss can leave a partial last line,
    or a tail of NUL bytes (the size written, the data not). What is cut is kept beside it as
    ``<path>.torn-<offset>``; that path, or None when the file was whole (or missing). Only a
    regular file is ever cut: a symbolic link (or a FIFO, a device) is left alone, as is what
    it points to."""
    try:
        fd = open_regular(path, os.O_RDWR)
    except OSError:
        return None  # missing, or not ours to cut: the append fails and says so
    try:
        with os.fdopen(fd, "r+b") as fh:
            header = _header_of(fh)
            if header is None:
                return None
            size = fh.seek(0, os.SEEK_END)
            start = max(0, size - TAIL_BYTES)
            fh.seek(start)
            tail = fh.read()
            end = len(tail)
            while end > 0:
                if tail[end - 1] != 0x0A:  # no newline: a line cut short
                    end = tail.rfind(b"\n", 0, end) + 1
                    continue
                nl = tail.rfind(b"\n", 0, end - 1)
                if nl < 0 and start > 0:
                    break  # the line began before the window: it ended whole
                line = tail[nl + 1 : end - 1]
                if not _whole_line(line, header):
                    end = nl + 1
                    continue
                break
            if end == len(tail) or (start == 0 and header.encode() + b"\n" not in tail[:end]):
                return None  # whole; or the column line itself is torn: a new part follows
            aside = _keep_aside(path, start + end, tail[end:])
            fh.truncate(start + end)
    except OSError:
        return None  # not readable or not writable: the append fails and says so
    log.warning(
        "%s: cut back to its last complete row; the torn tail (%d bytes) is in %s",
        path,
        len(tail) - end,
        aside.name,
    )
    return aside


def _keep_aside(path: Path, offset: int, data: bytes) -> Path:
    """Write a torn tail to a new file beside ``path``: ``<path>.torn-<offset>`` (``.2``, ``.3``,
    ... when taken). Created exclusively, so nothing planted under that name is written through."""
    name = f"{path.name}.torn-{offset}"
    for k in range(1, 10):
        aside = path.with_name(name if k == 1 else f"{name}.{k}")
        try:
            fd = os.open(aside, os.O_WRONLY | os.O_CREAT | os.O_EXCL | NOT_FOLLOWED, 0o666)
        except FileExistsError:
            continue
        except OSError:
            break
        with contextlib.suppress(OSError), os.fdopen(fd, "wb") as out:
            out.write(data)
        return aside
    return path.with_name(name)  # not kept: the cut goes on, a power loss's bytes are no row


def _whole_line(line: bytes, header: str) -> bool:
    """A line a run log may end with: a comment in UTF-8, the column line, or a row (the journal
    writes no blank lines: one at the end is part of a torn tail)."""
    if b"\x00" in line or not line.strip():
        return False
    if line.strip() == header.encode():
        return True
    if line.startswith(b"#"):
        try:
            line.decode("utf-8")
        except UnicodeDecodeError:
            return False
        return True
    return _row(line, header)


NUMBER_COLUMNS = frozenset(("time_s", "speed_rpm", "predicted_um", "offset_um", "dt_s", "wall_s"))
"""The journals' columns that hold a number whenever they hold anything."""


def is_row(header: list[str], cells: list[str]) -> bool:
    """A whole row of a journal with the columns ``header``: as many cells, printable ASCII only
    (the journal writes numbers and words), a finite time first, and a number (or nothing) in
    every column of :data:`NUMBER_COLUMNS`. The tail repair and the export both judge by it."""
    if len(cells) != len(header) or not all(c.isascii() and c.isprintable() for c in cells):
        return False
    try:
        if not math.isfinite(float(cells[0])):
            return False
        for name, cell in zip(header, cells):
            if name in NUMBER_COLUMNS and cell.strip():
                float(cell)
    except ValueError:
        return False
    return True


def _row(line: bytes, header: str) -> bool:
    try:
        text = line.decode("ascii")
    except UnicodeDecodeError:
        return False
    return is_row(header.split(","), text.split(","))


def _last_time(path: Path) -> float | None:
    """``time_s`` of the last row of an existing run log, or None (missing, empty, no rows)."""
    try:
        with os.fdopen(open_regular(path, os.O_RDONLY), "rb") as fh:
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - 4096))
            tail = fh.read().decode("utf-8", "replace").splitlines()
    except OSError:
        return None
    for line in reversed(tail):
        cell = line.split(",", 1)[0].strip()
        if not cell or cell.startswith("#"):
            continue
        try:
            return float(cell)
        except ValueError:
            return None  # the header: no rows yet
    return None
