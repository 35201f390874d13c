"""Journal retention, run by the service every ``[journal] sweep_every_s``."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from pathlib import Path

from .config import JournalRetention
from .events import event

log = logging.getLogger("thermocomp.runtime")


class JournalSweep:
    """Removes the oldest journal days past ``[journal]``'s age or size, never a file being
    written; by age only while the kernel says the wall clock is synchronised."""

    def __init__(self, clock_synchronized: Callable[[], bool | None]) -> None:
        self.clock_synchronized = clock_synchronized
        self._due = -math.inf
        self._age_paused_said = False

    def due(self, now: float, every_s: float) -> bool:
        """Whether a sweep is due at ``now``; the next one is then ``every_s`` later."""
        if now < self._due:
            return False
        self._due = now + every_s
        return True

    def sweep(
        self,
        journal_dir: Path,
        ret: JournalRetention,
        *,
        now_wall_s: float,
        keep: Iterable[Path | None],
    ) -> None:
        """One sweep of ``journal_dir``, sparing the files in ``keep``. A failure is logged;
        nothing here stops compensation."""
        from compensator.io.retention import sweep

        # by age only on a clock the kernel says is synchronised: a box that booted with its
        # clock months ahead must not age away the history (the size rule needs no clock)
        by_age = self.clock_synchronized() is not False
        if not by_age and not self._age_paused_said:
            self._age_paused_said = True
            log.warning(
                "journal retention: the wall clock is not synchronised: files are removed "
                "for the size limit only, not for their age, until it is"
            )
        try:
            res = sweep(
                journal_dir,
                now_wall_s=now_wall_s,
                max_age_days=ret.max_age_days,
                max_bytes=int(ret.max_size_mb * 2**20),
                keep=[p for p in keep if p],
                by_age=by_age,
            )
        except Exception as err:  # noqa: BLE001 - retention is housekeeping
            log.error("journal retention failed: %s", err)
            return
        if res.removed:
            event(
                "journal_swept",
                None,
                "journal: removed %d old file(s), %.1f MB freed; %.1f MB kept",
                len(res.removed),
                res.freed_bytes / 2**20,
                res.total_bytes / 2**20,
                removed=[p.name for p in res.removed][:50],
                freed_bytes=res.freed_bytes,
            )
        for problem in res.errors[:3]:
            log.warning("journal retention: %s", problem)
