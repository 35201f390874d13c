"""Link health, one small state machine: connected, retrying, outage; the link and the cutting
signal as one spindle's cycle sees them.

The adapter reconnects by itself (back-off and jitter in :class:`cnc_adapters.base.Link`); this
machine only tracks what the runtime must do about it: no write while the link is down, an
``OUTAGE`` alarm once it has been down longer than ``max_outage_s``, and a fresh write of the
offset once it is back (the controller may have lost the value).
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass

from cnc_adapters import Failure, FailureKind, Reading

from .alarms import UNREAD, Alarm
from .config import FaultPolicy
from .events import event

log = logging.getLogger("thermocomp.runtime")


class LinkState(enum.Enum):
    CONNECTED = "connected"
    RETRYING = "retrying"
    OUTAGE = "outage"


class LinkHealth:
    """Events: :meth:`failed` (the controller cannot be reached) and :meth:`succeeded`."""

    def __init__(self, max_outage_s: float):
        self.max_outage_s = max_outage_s
        self.state = LinkState.CONNECTED
        self.down_since: float | None = None

    @property
    def up(self) -> bool:
        return self.state is LinkState.CONNECTED

    def failed(self, now: float) -> LinkState:
        """The link is down at ``now``: retrying, and an outage once down long enough."""
        if self.down_since is None:
            self.down_since = now
            self.state = LinkState.RETRYING
        elif now - self.down_since > self.max_outage_s:
            self.state = LinkState.OUTAGE
        return self.state

    def succeeded(self, now: float) -> float | None:
        """The link answered at ``now``; how long it had been down, or None if it was up."""
        if self.down_since is None:
            return None
        down = now - self.down_since
        self.down_since = None
        self.state = LinkState.CONNECTED
        return down


@dataclass(frozen=True)
class Heard:
    """What the cycle takes from this cycle's reading before it steps the model."""

    read_rpm: float
    """The speed to step the model with: read, held, or 0 (idle assumed)."""
    alarms: Alarm
    came_back: bool
    """The link came back, or the adapter reconnected by itself: the controller may have lost
    the offset."""
    cutting: bool | None
    cutting_source: str
    shaper_rpm: float | None
    """The speed the shaper infers from when the speed was not read (the last one read)."""
    not_ready_um: float | None
    """A controller not ready to take our offset applies this one."""
    ready_unknown: bool = False
    """Whether the controller is ready could not be read: no write this cycle."""

    @property
    def unread(self) -> bool:
        return bool(self.alarms & UNREAD)


class LinkWatch:
    """The link as one spindle's cycle sees it: its health (:class:`LinkHealth`), why it went
    down, the speed to step with while a read fails (held up to ``speed_hold_s``, then idle
    assumed), and reconnects the adapter made by itself. Its own events."""

    def __init__(
        self,
        name: str,
        faults: FaultPolicy,
        counters: dict[str, int],
        *,
        cutting_from_controller: bool,
        reconnects: int,
    ):
        self.name = name
        self.faults = faults
        self.counters = counters
        self.health = LinkHealth(faults.max_outage_s)
        self.error: str | None = None  # why the link went down, while it is
        self.last_good_read_s: float | None = None
        self.last_speed_rpm = 0.0
        self.idle_assumed = False
        self.reconnects = reconnects  # the adapter's count, as last seen
        self.cutting = CuttingSignal(name, cutting_from_controller)

    def follow(self, old: LinkWatch) -> None:
        """Go on from ``old`` (a reload): the last speed read, and a failing cutting signal
        (said once). The new link's health starts afresh."""
        self.last_good_read_s, self.last_speed_rpm = old.last_good_read_s, old.last_speed_rpm
        self.cutting.error = old.cutting.error

    @property
    def up(self) -> bool:
        return self.health.up

    @property
    def state(self) -> LinkState:
        return self.health.state

    @property
    def down_since(self) -> float | None:
        return self.health.down_since

    def take(self, now: float, reading: Reading, limit_rpm: float | None) -> Heard:
        """The speed, the cutting signal, reconnects and readiness of this cycle's reading."""
        read_rpm, alarms, restored = self.speed(now, reading.speed_rpm, limit_rpm)
        came_back = self.reconnected_by_itself(reading.reconnects) or restored
        # the speed, the read-back and the write judge the link; the cutting signal, the inputs
        # and a probe source that fail are their own alarms, never a link down
        cutting, source, cutting_alarms = self.cutting.take(reading.cutting, self.up)
        shaper_rpm = None
        # a speed not read (held, or idle assumed) says nothing of the tool: it is taken to cut
        # (slow), and the shaper's inference goes on from the last speed read
        if alarms & UNREAD and cutting is None:
            cutting, source, shaper_rpm = True, "unread", self.last_speed_rpm
        not_ready = reading.not_ready_offset_um if self.up else None
        unknown = isinstance(not_ready, Failure)
        if isinstance(not_ready, Failure):
            log.warning(
                "%s: whether the controller is ready is not known (%s): no write this cycle",
                self.name,
                not_ready,
            )
            not_ready = None
        return Heard(
            read_rpm,
            alarms | cutting_alarms,
            came_back,
            cutting,
            source,
            shaper_rpm,
            not_ready,
            unknown,
        )

    def speed(
        self, now: float, value: float | Failure, limit_rpm: float | None
    ) -> tuple[float, Alarm, bool]:
        """The speed to step the model with, the alarms of reading it, and whether the link came
        back this cycle (the controller may have lost the offset). ``limit_rpm``: a speed above
        it is no spindle's (a register read as 0xFFFFFFFF, a unit slip): a failed read."""
        if not isinstance(value, Failure) and limit_rpm is not None and value > limit_rpm:
            value = Failure(
                FailureKind.VALUE,
                f"speed {value:g} rpm is no spindle's (above {limit_rpm:g} rpm): taken as a "
                "failed read",
            )
        if not isinstance(value, Failure):
            self.last_good_read_s = now
            self.last_speed_rpm = value
            if self.idle_assumed:
                self.idle_assumed = False
                event("speed_restored", self.name, "%s: speed read again", self.name)
            down_s = self.health.succeeded(now)
            self.error = None
            if down_s is not None:
                event(
                    "link_restored",
                    self.name,
                    "%s: link restored after %.1f s",
                    self.name,
                    down_s,
                    down_s=round(down_s, 3),
                )
            return value, Alarm.NONE, down_s is not None
        self.counters["read_failed"] += 1
        alarms = Alarm.SPEED_READ_FAILED
        if value.link_lost:
            alarms |= self.failed(now, value)
        else:
            log.warning("%s: speed read failed: %s", self.name, value)
        since = now - (self.last_good_read_s if self.last_good_read_s is not None else now)
        if self.last_good_read_s is not None and since <= self.faults.speed_hold_s:
            return self.last_speed_rpm, alarms, False
        alarms |= Alarm.IDLE_ASSUMED
        if not self.idle_assumed:
            self.idle_assumed = True
            event(
                "idle_assumed",
                self.name,
                "%s: no speed for %.0f s: assuming idle",
                self.name,
                since,
                level=logging.WARNING,
                since_s=round(since, 3),
            )
        return 0.0, alarms, False

    def failed(self, now: float, failure: Failure) -> Alarm:
        """The controller cannot be reached or does not answer: LINK_DOWN, and OUTAGE once down
        longer than ``max_outage_s``; an event when it goes down and when the outage begins."""
        before = self.health.state
        state = self.health.failed(now)
        if before is LinkState.CONNECTED:
            self.error = failure.reason  # the cause; later attempts only say they failed again
            name = "timeout" if failure.kind is FailureKind.TIMEOUT else "link_down"
            event(
                name,
                self.name,
                "%s: link down: %s",
                self.name,
                failure.reason,
                level=logging.ERROR,
                error=failure.reason,
            )
        if state is LinkState.OUTAGE and before is not LinkState.OUTAGE:
            down_s = now - (self.health.down_since or now)
            event(
                "outage",
                self.name,
                "%s: OUTAGE: the controller has not answered for %.0f s; no offset is written",
                self.name,
                down_s,
                level=logging.CRITICAL,
                down_s=round(down_s, 3),
            )
        return Alarm.LINK_DOWN | (Alarm.OUTAGE if state is LinkState.OUTAGE else Alarm.NONE)

    def reconnected_by_itself(self, reconnects: int) -> bool:
        """Whether the adapter reconnected on its own since the last reading."""
        seen, self.reconnects = self.reconnects, reconnects
        return seen != reconnects


class CuttingSignal:
    """The controller's cutting signal, where the spindle takes it from the controller:
    ``CUTTING_SIGNAL_FAILED`` while it cannot be read (the shaper then infers it from the
    speed), an event when that begins and one when it ends."""

    def __init__(self, name: str, from_controller: bool):
        self.name = name
        self.from_controller = from_controller
        self.error: str | None = None  # why the controller's signal failed, while it does

    def take(self, value: bool | Failure | None, link_up: bool) -> tuple[bool | None, str, Alarm]:
        """The cutting state and its source; None (the shaper infers it from the speed) without
        a signal, with the link down, or when it failed."""
        if not (self.from_controller and link_up) or value is None:
            return None, "speed", Alarm.NONE
        if isinstance(value, Failure):
            if value.reason != self.error:
                event(
                    "cutting_signal_failed",
                    self.name,
                    "%s: CUTTING_SIGNAL_FAILED: %s; the cutting state is inferred from the speed",
                    self.name,
                    value.reason,
                    level=logging.WARNING,
                    error=value.reason,
                )
            self.error = value.reason
            return None, "speed-fallback", Alarm.CUTTING_SIGNAL_FAILED
        if self.error is not None:
            event(
                "cutting_signal_restored",
                self.name,
                "%s: the controller's cutting signal reads again",
                self.name,
            )
            self.error = None
        return value, "controller", Alarm.NONE
