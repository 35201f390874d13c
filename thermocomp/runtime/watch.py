"""The tick's watch over each spindle's cycles: when each is due, how late it runs, and how
long every cycle has failed."""

from __future__ import annotations

import logging
from dataclasses import dataclass

from compensator.errors import ThermocompError

from .events import event

log = logging.getLogger("thermocomp.runtime")

FAILING_EXIT_S = 60.0
"""A spindle whose every cycle has failed this long [s] stops the service (non-zero status)."""
ON_TIME_CYCLES = 10
"""Cycles in a row on time after late ones before the service says they are on time again."""


@dataclass
class _Late:
    """A spindle whose cycles run late: the latest lateness [s], the cycles on time since."""

    late_s: float
    on_time: int = 0


class CycleWatch:
    """Per spindle: when its next cycle is due, the period its last cycle asked for, how late its
    cycles run (while they do) and since when every cycle has failed (while they do)."""

    def __init__(self) -> None:
        self._due: dict[str, float] = {}
        self._period: dict[str, float] = {}
        self._late: dict[str, _Late] = {}
        self._failing: dict[str, float] = {}  # spindle -> since when every cycle has failed

    def restart(self) -> None:
        """After a reload: every spindle is due at once."""
        self._due = {}

    def due(self, name: str, now: float) -> bool:
        """Whether spindle ``name``'s cycle is due at ``now``; a late one is said."""
        due = self._due.setdefault(name, now)
        if now < due:
            return False
        self._check_late(name, now - due)
        return True

    def ran(self, name: str, now: float, period_s: float) -> None:
        """The cycle ran (or failed); the next one is due ``period_s`` after this one was, never
        in the past: no catch-up burst."""
        self._period[name] = period_s
        due = self._due[name] + period_s
        self._due[name] = due if due > now else now + period_s

    def next_due(self) -> float:
        return min(self._due.values())

    def succeeded(self, name: str) -> None:
        self._failing.pop(name, None)

    def failed(self, name: str, now: float, err: ThermocompError, stopping: bool) -> bool:
        """A cycle that could not run is never silent: an event when the failures begin, and once
        every cycle has failed for ``FAILING_EXIT_S`` the service stops with one line and a
        non-zero status (it stops feeding the watchdog too), so that its supervisor restarts it
        from the last good state rather than leaving the controller's offset frozen. True: stop
        now (``stopping``: the service stops already)."""
        since = self._failing.setdefault(name, now)
        if since == now:
            event(
                "cycle_failed",
                name,
                "%s: CYCLE_FAILED: %s; the offset is not written until a cycle runs again",
                name,
                err,
                level=logging.ERROR,
                error=str(err)[:200],
            )
        if now - since >= FAILING_EXIT_S and not stopping:
            log.error(
                "%s: every cycle has failed for %.0f s (%s): stopping so that the service is "
                "restarted",
                name,
                now - since,
                str(err)[:200],
            )
            return True
        return False

    def notes(self) -> list[str]:
        """What the status line says of the cycles: failing ones, late ones."""
        notes = [f"{name}: cycles failing" for name in self._failing]
        notes += [f"{name}: cycles late ({late.late_s:.1f} s)" for name, late in self._late.items()]
        return notes

    def _check_late(self, name: str, late_s: float) -> None:
        """A cycle that runs a whole period or more after it was due is never silent: the offset
        then follows the growth that much later (an overloaded box, a slow controller link, a
        virtual machine run faster than the box can follow). An event when it begins, one when
        :data:`ON_TIME_CYCLES` cycles in a row ran on time again; the status says so meanwhile."""
        period = self._period.get(name)
        if period is None:
            return
        late = self._late.get(name)
        if late_s >= period:
            if late is None:
                event(
                    "cycles_late",
                    name,
                    "%s: cycles late: this one ran %.1f s after it was due (period "
                    "%g s): the offset follows the growth that much later; an overloaded box or a slow "
                    "controller link",
                    name,
                    late_s,
                    period,
                    level=logging.WARNING,
                    late_s=round(late_s, 3),
                    period_s=period,
                )
            self._late[name] = _Late(late_s)
        elif late is not None:
            late.on_time += 1
            if late.on_time >= ON_TIME_CYCLES:
                del self._late[name]
                event(
                    "cycles_on_time",
                    name,
                    "%s: cycles on time again (%d in a row)",
                    name,
                    ON_TIME_CYCLES,
                )
