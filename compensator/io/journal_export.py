"""The journal export: one run log from the runtime's journal, for replay and fit
(``thermocomp journal export``, :mod:`thermocomp.commands.journal`).

The journal directory holds, per spindle and UTC day, the cycle journal (``NAME-DAY[.pN].csv``,
:class:`compensator.io.journal.Journal`, the input channels after its own columns), the probe
measurements (``NAME.measurements-DAY[.pN].csv``) and the chiller commands
(``NAME.cooling-DAY[.pN].csv``). The export is the cycle journal's rows with ``from <= time_s <
to``, every column kept as written (text: no number is reformatted), sorted by time with repeated
instants dropped (the first part's row kept), and after them:

- ``elongation_um``, ``measurement_sigma_um``: the probe measurement (outcome ``accepted`` or
  ``restarted``) taken in the row's cycle, time in (previous row's time, row's time]; the first
  row of the journal read takes [time - dt_s, time]. Several in one cycle: the last. Empty on
  the rows without one; the log then says ``# elongation_um: sparse`` (see
  :mod:`compensator.io.runlog`). Both columns are left out when no measurement falls in range.
- ``chiller_setpoint_c``, ``supply_c``: the last chiller command at or before the row (empty
  before the first); left out when the spindle has no cooling journal.

The metadata names the spindle, the source, the range, the files read and the input columns
(``# inputs:``, which ``fit --inputs all`` takes). Edge installs have numpy, pydantic and the
standard library only: this module reads the CSV files with :mod:`csv`, never pandas or scipy.
"""

from __future__ import annotations

import bisect
import csv
import io
import math
import os
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from ..errors import ConfigError, RunLogError
from .atomic import atomic_write
from .journal import SHADOW_COLUMN, Journal, is_row
from .retention import DAY_S, JournalFile, journal_files, utc_day
from .runlog import ELONGATION_COLUMN, REQUIRED_COLUMNS, SPARSE, header_text

SOURCE = "thermocomp journal export"
MAX_LINE_CHARS = 64 * 1024
"""A journal line longer than this is damaged: skipped and counted, like a torn row."""
PROBE_OUTCOMES = ("accepted", "restarted")
"""Measurements the export takes as the measured elongation (not ``rejected``, ``refused``)."""
SIGMA_COLUMN = "measurement_sigma_um"
SETPOINT_COLUMN = "chiller_setpoint_c"
SUPPLY_COLUMN = "supply_c"
ADDED_COLUMNS = (ELONGATION_COLUMN, SIGMA_COLUMN, SETPOINT_COLUMN, SUPPLY_COLUMN)
"""The columns an export adds after the cycle journal's."""
NOT_INPUTS = frozenset(Journal.COLUMNS) | frozenset(ADDED_COLUMNS) | {SHADOW_COLUMN}
"""The columns of an export that are no input channel (the journal's own, the export's)."""


def iso(epoch_s: float) -> str:
    """An instant [epoch s] as ISO 8601 in UTC, ``...Z``; milliseconds when it has them."""
    when = datetime.fromtimestamp(epoch_s, tz=UTC)
    text = when.isoformat(timespec="milliseconds" if when.microsecond else "seconds")
    return text.replace("+00:00", "Z")


@dataclass
class _Table:
    """One kind of journal file, read: the columns (first-seen order) and the rows as
    (time [s], cells by column, file name)."""

    columns: list[str] = field(default_factory=list)
    rows: list[tuple[float, dict[str, str], str]] = field(default_factory=list)
    skipped: int = 0

    def read(self, path: Path) -> None:
        try:
            text = path.read_text(encoding="utf-8", errors="replace")
        except OSError as err:
            raise RunLogError(f"cannot read: {err.strerror or err}", str(path)) from err
        lines = text.splitlines(keepends=True)
        if lines and not lines[-1].endswith("\n"):
            lines.pop()  # a row being written right now
        body = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
        long = [len(ln) > MAX_LINE_CHARS for ln in body]
        self.skipped += sum(long[1:])  # no row of a journal is this long: a damaged line
        # the journal never quotes (its cells are numbers and words): a stray '"' is a damaged
        # cell of its own row, never the start of a field that swallows the rows after it
        reader = csv.reader((ln for ln, too in zip(body, long) if not too), quoting=csv.QUOTE_NONE)
        header = [c.strip() for c in next(reader, [])]
        if not header or header[0] != "time_s":
            if header:  # not a journal this module can read: say so rather than guess
                raise RunLogError(
                    f"header {','.join(header)[:80]!r} does not start with time_s", str(path)
                )
            return
        for c in header:
            if c not in self.columns:
                self.columns.append(c)
        for cells in reader:
            if not is_row(header, cells):
                self.skipped += 1  # a torn or damaged row: the rest of the day is still good
                continue
            self.rows.append((float(cells[0]), dict(zip(header, cells)), path.name))

    def sort(self) -> None:
        """By time; a repeated instant keeps its first row (the earlier part's)."""
        self.rows.sort(key=lambda r: r[0])  # stable: files were read day by day, part by part
        out: list[tuple[float, dict[str, str], str]] = []
        for r in self.rows:
            if not out or r[0] > out[-1][0]:
                out.append(r)
        self.rows = out


@dataclass(frozen=True)
class Exported:
    """What an export wrote."""

    path: Path
    spindle: str
    rows: int
    first_s: float
    last_s: float
    measured_rows: int
    measurements_unplaced: int
    """Measurements (accepted or restarted) in range that fell in no exported row's cycle or
    shared one with a later measurement."""
    files: tuple[str, ...]
    input_columns: tuple[str, ...]
    skipped_rows: int
    filled_cells: int = 0
    """Blank input cells (not read: link down, a failed read, a NaN) given the last value read
    before them, or the first one after at the start: fit and replay need every row."""


def _spindle_of(files: dict[JournalFile, int], spindle: str | None, directory: Path) -> str:
    names = sorted({f.spindle for f in files})
    if not names:
        raise ConfigError(f"{directory}: no journal files (NAME-YYYY-MM-DD.csv)")
    if spindle is None:
        if len(names) > 1:
            raise ConfigError(
                f"{directory} holds the journals of {len(names)} spindles "
                f"({', '.join(names)}): name one with --spindle"
            )
        return names[0]
    if spindle not in names:
        raise ConfigError(
            f"{directory}: no journal of spindle {spindle!r} (it has {', '.join(names)})"
        )
    return spindle


def export_journal(
    directory: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    spindle: str | None = None,
    start_s: float | None = None,
    end_s: float | None = None,
) -> Exported:
    """Write one run log of ``spindle``'s journal rows in [``start_s``, ``end_s``) [epoch s; None:
    unbounded] to ``output``, atomically (see the module's docstring). A one-line
    :class:`RunLogError` when no row is in range, :class:`ConfigError` for a bad range or spindle."""
    d = Path(directory)
    if start_s is not None and end_s is not None and not start_s < end_s:
        raise ConfigError(f"--from {iso(start_s)} is not before --to {iso(end_s)}")
    found, errors = journal_files(d)
    if errors and not found:
        raise RunLogError(errors[0])
    name = _spindle_of(found, spindle, d)
    mine = sorted(f for f in found if f.spindle == name)
    # the day before the range too: the first row's previous row, the last chiller command
    lo_day = utc_day(start_s - DAY_S) if start_s is not None else ""
    hi_day = utc_day(end_s) if end_s is not None else "9999-12-31"
    tables = {kind: _Table() for kind in ("cycles", "measurements", "cooling")}
    for f in mine:
        if lo_day <= f.day <= hi_day:
            tables[f.kind].read(d / f.name)
    cyc, meas, cool = tables["cycles"], tables["measurements"], tables["cooling"]
    for table in tables.values():
        table.sort()
    lo = -math.inf if start_s is None else start_s
    hi = math.inf if end_s is None else end_s
    first = bisect.bisect_left([r[0] for r in cyc.rows], lo)
    rows = [r for r in cyc.rows[first:] if r[0] < hi]
    if not rows:
        days = [f.day for f in mine if f.kind == "cycles"]
        held = (
            f"its journal has {days[0]} .. {days[-1]} (UTC)" if days else "it has no cycle journal"
        )
        raise RunLogError(
            f"no journal rows of spindle {name} in [{iso(lo) if start_s is not None else 'start'}, "
            f"{iso(hi) if end_s is not None else 'end'}): {held}",
            str(d),
        )
    if REQUIRED_COLUMNS[1] not in cyc.columns:
        raise RunLogError(
            f"the journal of spindle {name} has no {REQUIRED_COLUMNS[1]} column", str(d)
        )
    clash = [c for c in ADDED_COLUMNS if c in cyc.columns]
    if clash:
        raise RunLogError(
            f"the journal of spindle {name} has a column {clash[0]} already: the export "
            "adds its own",
            str(d),
        )

    # measurements: the last accepted (or restarted) one in each row's cycle
    probes = [
        (t, c, fn)
        for t, c, fn in meas.rows
        if c.get("outcome") in PROBE_OUTCOMES and _finite(c.get("elongation_um"))
    ]
    probe_t = [p[0] for p in probes]
    placed: dict[int, tuple[float, dict[str, str], str]] = {}
    taken: set[int] = set()
    prev = cyc.rows[first - 1][0] if first > 0 else None
    for i, (t, cells, _) in enumerate(rows):
        k = bisect.bisect_right(probe_t, t) - 1
        if prev is None:  # the first row read: its own cycle, closed at both ends
            begin = t - max(_float(cells.get("dt_s")), 0.0)
            inside = k >= 0 and probe_t[k] >= begin
        else:
            inside = k >= 0 and probe_t[k] > prev
        if inside:
            placed[i] = probes[k]
            taken.add(k)
        prev = t
    unplaced = sum(1 for k, p in enumerate(probe_t) if lo <= p < hi and k not in taken)

    # an input not read on a cycle holds its last value (the first one read, before any):
    # what a model stepping through that cycle would have been given
    inputs = tuple(c for c in cyc.columns if c not in NOT_INPUTS)
    filled = 0
    for c in inputs:
        have = [cells.get(c, "") for _, cells, _ in rows]
        good = [v for v in have if _finite(v)]
        if not good or len(good) == len(have):
            continue
        last = good[0]
        for i, v in enumerate(have):
            if _finite(v):
                last = v
            else:
                rows[i] = (rows[i][0], {**rows[i][1], c: last}, rows[i][2])
                filled += 1

    columns = list(cyc.columns)
    if placed:
        columns += [ELONGATION_COLUMN, SIGMA_COLUMN]
    if cool.rows:
        columns += [SETPOINT_COLUMN, SUPPLY_COLUMN]
    cool_t = [r[0] for r in cool.rows]
    used: set[str] = {fn for _, _, fn in rows} | {p[2] for p in placed.values()}
    buf = io.StringIO()
    out = csv.writer(buf, lineterminator="\n")
    for i, (t, cells, _) in enumerate(rows):
        line = [cells.get(c, "") for c in cyc.columns]
        if placed:
            p = placed.get(i)
            line += [p[1].get("elongation_um", ""), p[1].get("sigma_um", "")] if p else ["", ""]
        if cool.rows:
            k = bisect.bisect_right(cool_t, t) - 1
            if k >= 0:
                command = cool.rows[k]
                used.add(command[2])
                line += [command[1].get("setpoint_c", ""), command[1].get("supply_c", "")]
            else:
                line += ["", ""]
        out.writerow(line)

    files = tuple(sorted(used, key=lambda fn: next(f for f in mine if f.name == fn)))
    meta = {
        "spindle": name,
        "source": SOURCE,
        "from": iso(start_s) if start_s is not None else "-",
        "to": iso(end_s) if end_s is not None else "-",
        "files": ",".join(files),
        "inputs": ",".join(inputs),
        "measurements": str(len(placed)),
    }
    if placed and len(placed) < len(rows):
        meta[ELONGATION_COLUMN] = SPARSE
    if filled:
        meta["inputs_held"] = f"{filled} blank input cell(s) hold the last value read"
    with atomic_write(output) as fh:
        fh.write(header_text(columns, meta))
        fh.write(buf.getvalue())
    skipped = sum(t.skipped for t in tables.values())
    return Exported(
        Path(output),
        name,
        len(rows),
        rows[0][0],
        rows[-1][0],
        len(placed),
        unplaced,
        files,
        inputs,
        skipped,
        filled,
    )


def _float(text: str | None) -> float:
    try:
        return float(text) if text else 0.0
    except ValueError:
        return 0.0


def _finite(text: str | None) -> bool:
    try:
        return text is not None and math.isfinite(float(text))
    except ValueError:
        return False
