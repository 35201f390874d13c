"""The journal of one spindle's cycles: one row a cycle; a disk that refuses it is an alarm and
the rows wait in memory. Every input channel the link reads is journaled, used by the model or
not, so that a journal can be refitted with inputs."""

from __future__ import annotations

import logging
import math
from pathlib import Path

from compensator.io import Journal
from compensator.io.journal import SHADOW_COLUMN

from .alarms import Alarm
from .config import SpindleConfig
from .events import event
from .outcome import CycleOutcome

log = logging.getLogger("thermocomp.runtime")

JOURNAL_INPUTS_RETRY_S = 60.0
"""After a failed read of the input channels for the journal alone, wait this long [s]."""


class Recorder:
    """The cycle journal, its failures, and when a speed-only model's inputs are read for it."""

    def __init__(
        self,
        cfg: SpindleConfig,
        journal_dir: Path,
        *,
        channels: tuple[str, ...],
        shadow: bool,
        anchor_s: float,
        fsync_s: float,
        counters: dict[str, int],
    ):
        self.name = cfg.name
        self.anchor_s = anchor_s
        self.counters = counters
        self.journal = Journal(
            journal_dir,
            cfg.name,
            {"spindle": cfg.name, "model": cfg.model, "source": "thermocomp run"},
            fsync_every_s=fsync_s,
            input_columns=tuple(channels) + ((SHADOW_COLUMN,) if shadow else ()),
        )
        self.error: str | None = None
        self.inputs_after_s = -math.inf  # a failed journal-only read of the inputs waits till then

    def follow(self, old: Recorder) -> None:
        """Write on through ``old``'s journal (a reload): the rows it still holds in memory are
        not lost; a new set of columns starts a new part."""
        self.error = old.error
        if old.journal.directory == self.journal.directory and (
            old.journal.input_columns == self.journal.input_columns
        ):
            self.journal.close()  # never opened: nothing written yet
            self.journal, old.journal = old.journal, self.journal

    def wants_inputs(self, now: float) -> bool:
        """A speed-only model's inputs, read for the journal alone, are due."""
        return bool(self.journal.input_columns) and now >= self.inputs_after_s

    def inputs_failed(self, now: float, why: str) -> None:
        """A failure costs blank cells, and the next try waits ``JOURNAL_INPUTS_RETRY_S`` (a
        channel that times out must not slow every cycle)."""
        self.inputs_after_s = now + JOURNAL_INPUTS_RETRY_S
        log.info(
            "%s: input channels not read for the journal (next try in %g s): %s",
            self.name,
            JOURNAL_INPUTS_RETRY_S,
            why,
        )

    def write(self, out: CycleOutcome, wall_now: float, shadow_um: float | None) -> Alarm:
        """One journal row; a disk that refuses it is an alarm, the row waits in memory."""
        j = self.journal
        alarms = out.alarms
        if self.error is not None:
            alarms |= Alarm.JOURNAL_FAILED  # the row says so itself once it lands
        inputs = dict(out.inputs)
        if shadow_um is not None:
            inputs[SHADOW_COLUMN] = shadow_um
        ok = j.write(
            self.anchor_s + out.time_s,
            out.speed_rpm,
            out.predicted_um,
            out.offset_um,
            out.written,
            int(out.flags),
            int(alarms),
            dt_s=out.dt_s,
            wall_s=wall_now,
            now_s=out.time_s,
            cutting=out.cutting,
            cutting_source=out.cutting_source,
            policy_state=out.policy_state,
            slew_limit_um_per_s=out.slew_limit_um_per_s,
            inputs=inputs,
        )
        if ok:
            if self.error is not None:
                event(
                    "journal_restored",
                    self.name,
                    "%s: journal writing again (%s)",
                    self.name,
                    j.path,
                    path=str(j.path),
                    dropped_rows=j.dropped_rows,
                )
                self.error = None
            return Alarm.NONE
        if j.error is not None and j.error != self.error:
            self.counters["journal_failed"] += 1
            event(
                "journal_failed",
                self.name,
                "%s: cannot write the journal: %s; rows kept in memory (%d), compensation goes on",
                self.name,
                j.error,
                j.pending_rows,
                level=logging.ERROR,
                error=j.error,
                pending_rows=j.pending_rows,
            )
            self.error = j.error
        return Alarm.JOURNAL_FAILED if self.error is not None else Alarm.NONE

    def close(self, now: float) -> None:
        self.journal.close(now)
        lost = self.journal.pending_rows + self.journal.dropped_rows
        if lost:
            event(
                "journal_failed",
                self.name,
                "%s: stopping with %d journal row(s) not written (%s)",
                self.name,
                lost,
                self.journal.error,
                level=logging.ERROR,
                lost_rows=lost,
                error=self.journal.error,
            )
