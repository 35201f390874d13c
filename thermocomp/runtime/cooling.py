"""The chiller loop of ``[cooling]``: the spindle's estimate in, a coolant set point out.

Every ``period_s`` :meth:`CoolingRuntime.cycle` steps the pure :class:`~compensator.cooling_law.CoolingLaw`
on the estimate the spindle's runtime uses (its model with inputs, its fallback, or fused with
probes) and writes the set point to the chiller when it changed, or every ``refresh_s`` (a
chiller that restarted forgets it). Each command is journaled (``<spindle>.cooling-*.csv``).

Faults: a chiller that cannot be reached or refuses a write raises ``CHILLER_FAILED``; the law
then holds the last set point the chiller took for ``hold_s`` and moves to the constant
``preheat_c``, which is what is written when the chiller answers again; the loop then closes
again without a bump. The limits hold throughout: the law never commands outside them and the
chiller link refuses a value outside its own range before sending it. Nothing here can stop
the offset: every error is caught, logged and journaled.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from cnc_adapters.chiller import Chiller, open_chiller
from compensator.cooling_law import CoolingState
from compensator.errors import AdapterError, AdapterTimeoutError, ThermocompError, UnreachableError
from compensator.io import CoolingJournal

from .config import CoolingConfig
from .events import event

log = logging.getLogger("thermocomp.cooling")

CHILLER_FAILED = "CHILLER_FAILED"


class CoolingRuntime:
    """One chiller driven by one spindle's estimate."""

    def __init__(
        self,
        cfg: CoolingConfig,
        spindle: Any,
        journal_dir: Path,
        *,
        clock: Callable[[], float],
        wall: Callable[[], float],
        anchor_s: float,
        journal_fsync_s: float = 10.0,
        chiller: Chiller | None = None,
        previous: CoolingRuntime | None = None,
    ) -> None:
        self.cfg = cfg
        self.law = cfg.law()
        self.spindle = spindle
        self.clock, self.wall, self.anchor_s = clock, wall, anchor_s
        self.chiller = (
            chiller
            if chiller is not None
            else open_chiller(cfg.chiller["type"], cfg.chiller_options, clock=clock)
        )
        # a reload keeps the loop where it was; the limits of the new law apply from the next step
        self.state: CoolingState = previous.state if previous is not None else self.law.initial()
        self.last_sent_c: float | None = previous.last_sent_c if previous is not None else None
        self._sent_at = -math.inf
        self._last_t: float | None = None
        self.down_since: float | None = None
        self.error: str | None = None
        self.supply_c: float | None = None
        self.counters = {"cycles": 0, "writes": 0, "write_failed": 0}
        self.journal = CoolingJournal(
            journal_dir,
            spindle.cfg.name,
            {
                "spindle": spindle.cfg.name,
                "source": "thermocomp run",
                "mode": cfg.mode,
                "chiller": cfg.chiller["type"],
            },
            fsync_every_s=journal_fsync_s,
        )

    @property
    def alarm(self) -> str:
        return CHILLER_FAILED if self.down_since is not None else ""

    def cycle(self) -> dict[str, Any]:
        now = self.clock()
        dt = self.cfg.period_s if self._last_t is None else now - self._last_t
        self._last_t = now
        self.counters["cycles"] += 1
        estimate = self.spindle.estimate_um() if self.spindle.counters["cycles"] > 0 else None
        running = self.spindle.last_speed_rpm > 1.0
        if dt > 0:
            if self.down_since is not None:
                self.state = self.law.hold(self.state, dt)
            else:
                self.state = self.law.step(self.state, estimate, dt, running=running)
        sp = self.state.setpoint_c
        sent = False
        if (
            sp != self.last_sent_c
            or now - self._sent_at >= self.cfg.refresh_s
            or self.down_since is not None
        ):
            sent = self._send(now, sp)
        if sent or self.down_since is None:
            self._read_supply(now)
        self.journal.record(
            self.anchor_s + now,
            estimate_um=estimate,
            rite_um=self.law.rite_um,
            phase=self.state.phase,
            setpoint_c=sp,
            sent=sent,
            supply_c=self.supply_c,
            alarm=self.alarm,
            wall_s=self.wall(),
            now_s=now,
        )
        return {
            "time_s": now,
            "estimate_um": estimate,
            "phase": self.state.phase,
            "setpoint_c": sp,
            "sent": sent,
            "supply_c": self.supply_c,
            "alarm": self.alarm,
        }

    def _send(self, now: float, value_c: float) -> bool:
        try:
            self.chiller.write_setpoint_c(value_c)
        except (AdapterError, ThermocompError, OSError) as err:
            self.counters["write_failed"] += 1
            self._failed(now, err)
            return False
        if self.down_since is not None:
            event(
                "chiller_restored",
                self.spindle.cfg.name,
                "%s: the chiller takes the set point again (%.1f degC) after %.0f s",
                self.spindle.cfg.name,
                value_c,
                now - self.down_since,
                outage_s=round(now - self.down_since, 1),
            )
            self.down_since, self.error = None, None
        self.counters["writes"] += 1
        self.last_sent_c, self._sent_at = value_c, now
        return True

    def _failed(self, now: float, err: Exception) -> None:
        why = str(err)[:200]
        if self.down_since is None:
            self.down_since = now
            event(
                "chiller_failed",
                self.spindle.cfg.name,
                "%s: CHILLER_FAILED: %s; holding %s degC for %g s, then %.1f degC",
                self.spindle.cfg.name,
                why,
                "the last set point" if self.last_sent_c is None else f"{self.last_sent_c:.1f}",
                self.law.hold_s,
                self.law.preheat_c,
                level=logging.ERROR,
                error=why,
            )
            if self.last_sent_c is not None:  # the chiller holds what it took last
                self.state = replace(
                    self.state, setpoint_c=self.last_sent_c, ramp_c=self.last_sent_c
                )
        self.error = why

    def _read_supply(self, now: float) -> None:
        try:
            self.supply_c = self.chiller.read_supply_c()
        except (UnreachableError, AdapterTimeoutError) as err:  # gone: as a failed write
            self.supply_c = None
            self._failed(now, err)
        except (AdapterError, ThermocompError, OSError) as err:
            log.warning("%s: chiller supply temperature not read: %s", self.spindle.cfg.name, err)
            self.supply_c = None

    def status(self) -> dict[str, Any]:
        return {
            "mode": self.cfg.mode,
            "phase": self.state.phase,
            "setpoint_c": self.state.setpoint_c,
            "rite_um": self.law.rite_um,
            "supply_c": self.supply_c,
            "alarm": self.alarm,
            "error": self.error,
            **self.counters,
        }

    def close(self) -> None:
        try:
            self.journal.close(self.clock())
        finally:
            self.chiller.close()
