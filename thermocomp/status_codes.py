"""What ``thermocomp status`` answers with: its default endpoint and its exit statuses. Constants
only, so that the command line's help reads them without importing the command."""

from __future__ import annotations

DEFAULT_URL = "http://127.0.0.1:9740/"

EXIT_OK, EXIT_ATTENTION, EXIT_UNREACHABLE, EXIT_NOT_WRITING = 0, 1, 2, 3
EXIT_STOPPED = 4
"""The service is not running (its state directory is free): each spindle's saved state is
printed instead; with or without ``--exit-code``."""
EXIT_CODES = {
    EXIT_OK: "every spindle compensating, no alarm",
    EXIT_ATTENTION: "an alarm is raised (the chiller loop's too), or a spindle is holding",
    EXIT_UNREACHABLE: "the status could not be read (no service at the URL, "
    "one that does not answer, token refused, bad arguments)",
    EXIT_NOT_WRITING: "a spindle is not writing: its link is down, or no offset has gone through for "
    "faults.not_writing_cycles cycles",
    EXIT_STOPPED: "the service is not running (with --config: each spindle's saved state printed)",
}
"""``thermocomp status --exit-code``: the exit status, the worst that applies (3 over 1)."""
