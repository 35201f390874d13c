"""``thermocomp journal export [--config RUNTIME.toml | --journal-dir DIR] [--spindle NAME]
[--from WHEN] [--to WHEN] --output RUN.csv``: one run log of a spindle's journal rows in [from,
to), with its probe measurements and chiller commands beside them
(:func:`compensator.io.journal_export.export_journal` says how). WHEN is an ISO date (00:00 UTC)
or date-time (UTC unless it names a zone).

Edge installs have numpy, pydantic and the standard library only: nothing here imports pandas
or scipy.
"""

from __future__ import annotations

import argparse
from datetime import UTC, datetime
from pathlib import Path
from typing import overload

from compensator.errors import ConfigError
from compensator.io.journal_export import export_journal, iso

WHEN_FORMS = "2024-05-01, 2024-05-01T13:30, 2024-05-01T13:30:00+02:00"


@overload
def parse_when(text: str, flag: str) -> float: ...
@overload
def parse_when(text: None, flag: str) -> None: ...
@overload
def parse_when(text: str | None, flag: str) -> float | None: ...
def parse_when(text: str | None, flag: str) -> float | None:
    """Epoch seconds [s] of an ISO date (00:00 UTC) or date-time (UTC without a zone); None for
    None. A one-line :class:`ConfigError` for anything else."""
    if text is None:
        return None
    try:
        when = datetime.fromisoformat(text.strip())
    except ValueError as err:
        raise ConfigError(
            f"{flag} {text[:60]!r}: not an ISO date or date-time ({WHEN_FORMS})"
        ) from err
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return when.timestamp()


def journal_dir_of(args: argparse.Namespace) -> Path:
    """``--journal-dir``, or the ``journal_path`` of the runtime configuration ``--config``."""
    directory, config = getattr(args, "journal_dir", None), getattr(args, "config", None)
    if directory is not None and config is not None:
        raise ConfigError("give --journal-dir or --config, not both")
    if directory is not None:
        return Path(directory)
    if config is not None:
        from ..runtime.config import load_config

        return load_config(config).journal_path
    raise ConfigError(
        "give the journal directory (--journal-dir) or the runtime configuration (--config)"
    )


def export(args: argparse.Namespace) -> int:
    """``thermocomp journal export``: write the run log and say what it holds on one line."""
    start = parse_when(getattr(args, "from_", None), "--from")
    end = parse_when(getattr(args, "to", None), "--to")
    if getattr(args, "output", None) is None:
        raise ConfigError("give the run log to write (--output)")
    done = export_journal(
        journal_dir_of(args),
        args.output,
        spindle=getattr(args, "spindle", None),
        start_s=start,
        end_s=end,
    )
    notes = []
    if done.measurements_unplaced:
        notes.append(
            f"{done.measurements_unplaced} measurement(s) in range on no row of their own "
            "(several in one cycle: the last kept)"
        )
    if done.filled_cells:
        notes.append(f"{done.filled_cells} blank input cell(s) (not read) hold the last value read")
    if done.skipped_rows:
        notes.append(f"{done.skipped_rows} unreadable journal row(s) skipped")
    print(
        f"{done.path}: {done.rows} rows of spindle {done.spindle}, {iso(done.first_s)} .. "
        f"{iso(done.last_s)}, {done.measured_rows} with a measured elongation, "
        f"{len(done.input_columns)} input column(s), from {len(done.files)} journal file(s)"
        + "".join(f"; {n}" for n in notes)
    )
    return 0
