"""Journal retention: how the runtime's journal directory is kept from filling the disk.

The journal (:mod:`.journal`) writes, per spindle ``NAME`` and UTC day ``YYYY-MM-DD``, three
kinds of file, each possibly continued in parts ``.p2``, ``.p3``, ...:

- ``NAME-YYYY-MM-DD[.pN].csv``: the cycle journal (:class:`~.journal.Journal`);
- ``NAME.measurements-YYYY-MM-DD[.pN].csv``: the probe measurements (:class:`~.journal.MeasurementJournal`);
- ``NAME.cooling-YYYY-MM-DD[.pN].csv``: the chiller commands (:class:`~.journal.CoolingJournal`).

:func:`sweep` removes the files older than a maximum age, then the oldest files while the journal
files together exceed a size. Only files whose name is one of those patterns (a real date, a
regular file, not a symbolic link) are ever considered: anything else in the directory is left
alone and does not count towards the size. The files of the current UTC day (or of a later one,
after the wall clock was set back) and the files named in ``keep`` (being written) are never
removed. :func:`sweep` never raises on an ``OSError``: it collects it, so a failing disk never
stops compensation. Deciding what to remove (:func:`plan`) is pure; :func:`sweep` lists, sizes
and removes.
"""

from __future__ import annotations

import datetime as _dt
import os
import re
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

DAY_S = 86400.0
"""Seconds in a UTC day."""

KINDS = ("cycles", "measurements", "cooling")
"""The journal's kinds of file: ``cycles`` (``NAME-DAY.csv``), ``measurements``
(``NAME.measurements-DAY.csv``), ``cooling`` (``NAME.cooling-DAY.csv``)."""

_NAME = re.compile(
    r"^(?P<spindle>[A-Za-z0-9][A-Za-z0-9_.-]*?)(?:\.(?P<kind>measurements|cooling))?"
    r"-(?P<day>\d{4}-\d{2}-\d{2})(?:\.p(?P<part>[1-9]\d{0,8}))?\.csv$"
)


@dataclass(frozen=True, order=True)
class JournalFile:
    """What a journal file's name says. Ordered oldest first: by day, then part, kind, spindle."""

    day: str
    """The UTC day of its rows, ``YYYY-MM-DD``."""
    part: int
    """1 for ``NAME-DAY.csv``, N for ``NAME-DAY.pN.csv``."""
    kind: str
    """One of :data:`KINDS`."""
    spindle: str
    name: str
    """The file name (no directory)."""

    @property
    def day_start_s(self) -> float:
        """Epoch seconds [s] of the day's first instant, 00:00 UTC."""
        return day_start_s(self.day)

    @property
    def day_end_s(self) -> float:
        """Epoch seconds [s] where the day ends (00:00 UTC of the next day): no row of the file
        is that late."""
        return self.day_start_s + DAY_S


def day_start_s(day: str) -> float:
    """Epoch seconds [s] of 00:00 UTC on ``day`` (``YYYY-MM-DD``); ValueError if no such day."""
    d = _dt.date.fromisoformat(day)
    return float((d - _dt.date(1970, 1, 1)).days) * DAY_S


def utc_day(epoch_s: float) -> str:
    """The UTC day ``YYYY-MM-DD`` of an instant in epoch seconds [s] (as the journal names files)."""
    return (_dt.date(1970, 1, 1) + _dt.timedelta(days=int(epoch_s // DAY_S))).isoformat()


def parse_name(name: str) -> JournalFile | None:
    """The journal file a name is, or None when it is not one (any other name, or a date that
    does not exist). A spindle name ending in ``.measurements`` or ``.cooling`` reads as that
    kind: the runtime's names are ``[A-Za-z0-9][A-Za-z0-9_.-]*``."""
    m = _NAME.match(name)
    if m is None:
        return None
    try:
        day_start_s(m["day"])
    except ValueError:
        return None
    kind = m["kind"] or "cycles"
    part = int(m["part"]) if m["part"] else 1
    if m["part"] == "1":  # the first part has no suffix: NAME-DAY.p1.csv is not the journal's
        return None
    return JournalFile(m["day"], part, kind, m["spindle"], name)


@dataclass(frozen=True)
class SweepResult:
    """What a sweep did."""

    removed: tuple[Path, ...] = ()
    """The files removed, in the order they were removed."""
    freed_bytes: int = 0
    """Their total size [bytes]."""
    total_bytes: int = 0
    """The size of the journal files left [bytes] (those it could size)."""
    errors: tuple[str, ...] = ()
    """One line per failure (``path: reason``); the sweep went on after each."""


def plan(
    files: Mapping[JournalFile, int],
    *,
    now_wall_s: float,
    max_age_days: float,
    max_bytes: int,
    protected: Collection[str] = (),
    by_age: bool = True,
) -> list[JournalFile]:
    """The files to remove, in order; pure.

    ``files`` maps each journal file to its size [bytes]; ``now_wall_s`` is the wall clock
    [epoch s]; ``protected`` are file names never to remove. First every file whose day ended
    more than ``max_age_days`` [days] before ``now_wall_s``, oldest first; then, while the files
    left exceed ``max_bytes`` [bytes] in all, the oldest left (by day, then part). The current
    UTC day's files (and any later day's) and the protected ones are never chosen, so the total
    may stay above ``max_bytes`` when only those are left. ``by_age`` False: no file is removed
    for its age (the wall clock is not known to be right), only for the size.
    """
    today = utc_day(now_wall_s)
    removable = sorted(f for f in files if f.day < today and f.name not in protected)
    cutoff_s = now_wall_s - max_age_days * DAY_S
    # by_age False: a wall clock that cannot be trusted (one set 91 days ahead would age away
    # the whole history); the size rule needs no clock
    chosen = [f for f in removable if f.day_end_s < cutoff_s] if by_age else []
    total = sum(files.values()) - sum(files[f] for f in chosen)
    gone = set(chosen)
    for f in removable:
        if total <= max_bytes:
            break
        if f not in gone:
            chosen.append(f)
            total -= files[f]
    return chosen


def journal_files(directory: str | os.PathLike[str]) -> tuple[dict[JournalFile, int], list[str]]:
    """The journal files in ``directory`` (regular files only, not recursing) with their sizes
    [bytes], and the errors met listing or sizing them (a missing directory is no error)."""
    found: dict[JournalFile, int] = {}
    errors: list[str] = []
    try:
        entries = list(os.scandir(directory))
    except FileNotFoundError:
        return found, errors
    except OSError as err:
        return found, [f"{directory}: {err.strerror or err}"]
    for entry in entries:
        jf = parse_name(entry.name)
        if jf is None:
            continue
        try:
            if not entry.is_file(follow_symlinks=False):
                continue
            found[jf] = entry.stat(follow_symlinks=False).st_size
        except FileNotFoundError:
            continue  # removed meanwhile
        except OSError as err:
            errors.append(f"{entry.path}: {err.strerror or err}")
    return found, errors


def _names_in(directory: Path, keep: Iterable[str | os.PathLike[str]]) -> set[str]:
    """The names of the ``keep`` paths that lie in ``directory`` (a relative path is taken from the
    working directory, as ``open`` takes it; None is skipped)."""
    base = os.path.realpath(directory)
    names = set()
    for k in keep:
        if k is None:
            continue
        p = os.fspath(k)
        if os.path.realpath(os.path.dirname(os.path.abspath(p))) == base:
            names.add(os.path.basename(p))
    return names


def sweep(
    directory: str | os.PathLike[str],
    *,
    now_wall_s: float,
    max_age_days: float = 90,
    max_bytes: int = 1 << 30,
    keep: Collection[str | os.PathLike[str]] = (),
    by_age: bool = True,
) -> SweepResult:
    """Remove old journal files from ``directory`` (:func:`plan`): those whose UTC day ended more
    than ``max_age_days`` [days] before ``now_wall_s`` [epoch s], then the oldest while the
    journal files exceed ``max_bytes`` [bytes]. Never a file of today (UTC), one in ``keep`` (the
    files being written) or a file that is not a journal file. Never raises on an ``OSError``:
    each is a line in :attr:`SweepResult.errors`, and the sweep goes on. ``by_age`` False: the
    size rule only (see :func:`plan`)."""
    d = Path(directory)
    sizes, errors = journal_files(d)
    chosen = plan(
        sizes,
        now_wall_s=now_wall_s,
        max_age_days=max_age_days,
        max_bytes=max_bytes,
        protected=_names_in(d, keep),
        by_age=by_age,
    )
    removed: list[Path] = []
    freed = 0
    for f in chosen:
        path = d / f.name
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass  # removed meanwhile: gone all the same
        except OSError as err:
            errors.append(f"{path}: {err.strerror or err}")
            continue
        else:
            removed.append(path)
            freed += sizes[f]
        del sizes[f]
    return SweepResult(tuple(removed), freed, sum(sizes.values()), tuple(errors))
