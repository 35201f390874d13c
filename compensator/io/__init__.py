"""Every file thermocomp reads or writes, one module per format (pvlib's ``iotools`` idea).

- :mod:`.runlog`: run logs (calibration runs, replays, the simulator), DAQ CSV import;
- :mod:`.modelfile`: model files with their checksum;
- :mod:`.state`: the runtime's state file;
- :mod:`.journal`: the runtime's daily journal, and its measurements;
- :mod:`.retention`: removing old journal files (age, total size);
- :mod:`.journal_export`: one run log from a spindle's journal (``thermocomp journal export``);
- :mod:`.atomic`: atomic writes and plain text files;
- :mod:`.checksum`: the canonical JSON and digest that model files and state carry.

The pure model layer beside it never imports this package; the adapters below the
application do not either.
"""

from .atomic import atomic_write, read_text, versioned_path, write_text
from .journal import CoolingJournal, Journal, MeasurementJournal
from .journal_export import Exported, export_journal
from .modelfile import (
    MODEL_TYPES,
    load_any_model,
    load_model,
    model_digest,
    model_to_json,
    save_model,
)
from .retention import SweepResult, sweep
from .runlog import (
    ELONGATION_COLUMN,
    REQUIRED_COLUMNS,
    Gap,
    RunLog,
    RunLogAppender,
    read_daq_csv,
    read_run_log,
    write_run_log,
)
from .state import STATE_FORMAT, load_state, quarantine, save_state

__all__ = [
    "ELONGATION_COLUMN",
    "MODEL_TYPES",
    "REQUIRED_COLUMNS",
    "STATE_FORMAT",
    "CoolingJournal",
    "Exported",
    "Gap",
    "Journal",
    "MeasurementJournal",
    "RunLog",
    "RunLogAppender",
    "SweepResult",
    "atomic_write",
    "export_journal",
    "load_any_model",
    "load_model",
    "load_state",
    "model_digest",
    "model_to_json",
    "quarantine",
    "read_daq_csv",
    "read_run_log",
    "read_text",
    "save_model",
    "save_state",
    "sweep",
    "versioned_path",
    "write_run_log",
    "write_text",
]
