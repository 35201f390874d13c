"""The offset, one small state machine: tracking, ramping, holding.

It owns the shaper and knows what the controller holds (``held_um``), which is what the
journal records. Each cycle :meth:`OffsetTracker.plan` shapes the model's elongation; the runtime
then reports the outcome: :meth:`written`, or :meth:`kept` when nothing reached the controller.
:meth:`controller_holds` is for a controller whose value is known to differ (a deferred
write check, a machine that is off and applies 0), :meth:`rewrite` for a link that came back.

- ``TRACKING``: the controller holds the shaped offset, which follows the model;
- ``RAMPING``: the controller holds a value on its way to the model's, slowed by the slew limit
  or the transient policy;
- ``HOLDING``: the controller keeps an older value because a write was not possible; the
  shaper moves on from that value, so when writes resume the offset ramps, never jumps.

Where the link writes a sign of life (:class:`cnc_adapters.Life`), it goes with the offset in
the cycle's one write: a cycle that writes the offset sends both, one that has no new offset to
write (none due, or holding) confirms the held one with the sign of life alone. The counter
moves only when the controller took the sign, so a control that watches it sees thermocomp
stop, hang or lose the link; the "compensation valid" flag says whether the offset the
controller holds follows the estimate now. The offset never waits on the sign of life: an offset
the controller took counts as written even where the counter or the flag was refused or is
missing (``SIGN_OF_LIFE``, once in the log at the start of a run of failures).
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Callable

from cnc_adapters import Failure, FailureKind, Life, Reading, WriteResult
from compensator.shaping import Flag, OffsetShaper, ShapedOffset, ShaperConfig

from .alarms import Alarm
from .config import FaultPolicy
from .events import event
from .link import Heard, LinkWatch

log = logging.getLogger("thermocomp.runtime")

_SLOWED = Flag.SLEW_LIMITED | Flag.TRANSIENT | Flag.RELEASING
NOT_COMPENSATING = (
    Alarm.NOT_READY
    | Alarm.ESTIMATE_REFUSED
    | Alarm.IDLE_ASSUMED
    | Alarm.SPEED_READ_FAILED
    | Alarm.WRITE_BACKOFF
)
"""A cycle with any of these holds the offset: compensation is not valid (the status's
``holding`` or ``not writing``, :func:`.states.spindle_state`)."""


class OffsetMode(enum.Enum):
    TRACKING = "tracking"
    RAMPING = "ramping"
    HOLDING = "holding"


class OffsetTracker:
    def __init__(self, config: ShaperConfig, held_um: float = 0.0):
        self.shaper = OffsetShaper(config, held_um)
        self.held_um = self.shaper.output_um
        self.pending = False
        self.mode = OffsetMode.TRACKING

    def plan(
        self, elongation_um: float, speed_rpm: float, dt_s: float, cutting: bool | None = None
    ) -> ShapedOffset:
        """The shaped offset for this cycle (not yet written); ``cutting`` the controller's
        signal, or None for the shaper to infer it from the speed."""
        return self.shaper.update(elongation_um, speed_rpm, dt_s, cutting)

    def wants_write(self, shaped: ShapedOffset) -> bool:
        return shaped.write or self.pending

    def written(self, shaped: ShapedOffset) -> None:
        self.held_um = shaped.offset_um
        self.pending = False
        self.mode = OffsetMode.RAMPING if shaped.flags & _SLOWED else OffsetMode.TRACKING

    def kept(self, wanted: bool) -> None:
        """Nothing was written this cycle; ``wanted`` says whether a write was due."""
        if wanted:
            self.pending = True
        if self.shaper.output_um != self.held_um:
            self.shaper.hold(self.held_um)  # the controller still holds the old value
        if self.pending:
            self.mode = OffsetMode.HOLDING

    def controller_holds(self, offset_um: float) -> None:
        """The controller holds ``offset_um``: move on from there and write again. A value that
        is not a finite number is not moved on from: the offset is only written again. A value
        beyond the clamp is none of ours: the shaper steps from it straight to the clamp's edge,
        and that edge is what counts as held (and is journaled), never the foreign value."""
        self.pending = True
        if math.isfinite(offset_um):
            self.shaper.hold(float(offset_um))
            limit = self.shaper.config.max_offset_um
            self.held_um = min(max(float(offset_um), -limit), limit)
        self.mode = OffsetMode.HOLDING

    def observe(self, held_um: float, tolerance_um: float) -> float | None:
        """The controller was read back and holds ``held_um``. Within ``tolerance_um`` of what
        it should hold: None. Otherwise the difference (held - expected); the offset then
        moves on from the held value through the slew limit, and is written again."""
        expected = self.held_um
        if not math.isfinite(held_um) or abs(held_um - expected) <= tolerance_um:
            return None
        self.controller_holds(held_um)
        return held_um - expected

    def rewrite(self) -> None:
        """Write the offset again at the next chance (the controller may have lost it)."""
        self.pending = True


def mismatch_cause(held_um: float, tolerance_um: float) -> str:
    """Who probably changed the controller's offset."""
    if abs(held_um) <= tolerance_um:
        return "reset to zero (controller restart, NC reset or power cycle)"
    return "an outside write (operator, NC program or another client)"


class ControllerOffset(OffsetTracker):
    """The offset as the controller holds it: the tracker, plus the read-back that checks it,
    what a mismatch does, the back-off from a controller that keeps refusing, and when writes
    took effect. The controller's offset is the truth:

    - it is read back at start, after a reconnect and every ``faults.readback_every`` cycles; a
      value further than ``faults.offset_tolerance_um`` from the one written raises
      ``OFFSET_MISMATCH`` and the offset ramps from there through the slew limit;
    - a controller that refuses ``faults.max_mismatches`` times in a row is not fought: writes
      back off, doubling from the period up to ``faults.max_write_backoff_s``.
    """

    def __init__(
        self,
        name: str,
        config: ShaperConfig,
        faults: FaultPolicy,
        period_s: float,
        counters: dict[str, int],
        *,
        held_um: float = 0.0,
        can_read_back: bool = False,
        writes_life: bool = False,
    ):
        super().__init__(config, held_um)
        self.name = name
        self.faults = faults
        self.period_s = period_s
        self.counters = counters
        self.can_read_back = can_read_back
        self.writes = True  # False: `[cooling] mode = "cooling"`, the chiller only
        self.need_readback = True
        self.since_readback = 0
        self.mismatch_streak = 0
        self.wrote_since_check = False
        self.foreign_um: float | None = None  # a value beyond the clamp last read back
        # why this cycle cannot vouch for what the controller holds (no write, not in step), or
        # None: whether the machine is ready could not be read, or a reconnect not yet read back
        self.unsure: str | None = None
        self.paused_until_s = -math.inf
        self.last_readback_um: float | None = None  # what the controller held when last read back
        self.last_write_s: float | None = None  # clock time of the last offset written
        self.write_done_s: float | None = None  # clock time the last write returned
        # the last cycle the controller held the offset the shaper aimed at (a write went
        # through, or none was due): the spindle's state counts cycles from here
        self.last_in_step_s: float | None = None
        # the sign of life last taken by the controller (counter 0: none yet); None: this link
        # writes none
        self.life: Life | None = Life(0, False) if writes_life else None
        self.life_error: str | None = None  # why the sign of life fails, while it does

    def follow(self, old: ControllerOffset) -> None:
        """Go on from ``old`` (a reload): the shaper's settling and the timing of the writes.
        The new link reads the offset back first."""
        self.shaper.follow(old.shaper)
        self.last_write_s, self.write_done_s = old.last_write_s, old.write_done_s
        self.last_in_step_s = old.last_in_step_s
        if self.life is not None and old.life is not None:
            self.life = old.life  # the control's watcher sees the counter go on, never restart

    # -- the read-back ------------------------------------------------------------------

    def take(self, now: float, reading: Reading, heard: Heard, link: LinkWatch) -> Alarm:
        """What this cycle's reading says of the offset the controller holds: a deferred write
        check, a reconnect, the read-back when due."""
        alarms = Alarm.NONE
        if reading.write_refused_um is not None:
            alarms |= self.write_refused(now, reading.write_refused_um)
        if heard.came_back:
            self.reconnected()
        if heard.not_ready_um is None and self.writes:
            alarms |= self.read_back(now, reading.held_offset_um, link)
        # after a reconnect the controller may hold anything: where it can be read back and was
        # not in this reading, write nothing until it is (the next cycle asks for it)
        unread = self.need_readback and self.can_read_back and reading.held_offset_um is None
        self.unsure = None
        if heard.ready_unknown:
            self.unsure = "whether the machine is ready cannot be read"
        elif heard.came_back and unread:
            self.unsure = "the offset the controller holds is read back first after a reconnect"
        return alarms

    def wants_readback(self, link_up: bool) -> bool:
        """Whether this cycle's reading should hold the controller's offset: due, or the link
        is down (a reconnect in this cycle's read needs it)."""
        every = self.faults.readback_every
        due = self.need_readback or (every > 0 and self.since_readback + 1 >= every)
        return self.writes and self.can_read_back and (due or not link_up)

    def reconnected(self) -> None:
        """The controller may have lost the offset (a restart clears it): read it back, or,
        where it cannot be read, write it again."""
        self.need_readback = True
        if not self.can_read_back:
            self.rewrite()

    def read_back(self, now: float, held: float | Failure | None, link: LinkWatch) -> Alarm:
        """Compare the offset the controller holds with ours, when due."""
        every = self.faults.readback_every
        self.since_readback += 1
        due = self.need_readback or (every > 0 and self.since_readback >= every)
        if not (due and link.up and self.can_read_back) or held is None:
            return Alarm.NONE
        if isinstance(held, Failure):
            if held.kind is FailureKind.VALUE:
                # it holds something that is not a number: write ours again, from where we were
                log.warning("%s: offset read-back: %s; writing it again", self.name, held)
                self.need_readback = False
                self.since_readback = 0
                self.rewrite()
                return Alarm.OFFSET_MISMATCH
            if held.link_lost:
                return link.failed(now, held)
            log.warning("%s: offset read-back failed: %s", self.name, held)
            return Alarm.NONE
        when = (
            "at start"
            if self.counters["readbacks"] == 0
            else ("after a reconnect" if self.need_readback else "periodic check")
        )
        self.counters["readbacks"] += 1
        self.last_readback_um = held
        self.need_readback = False
        self.since_readback = 0
        return self.mismatch(now, held, when)

    def write_refused(self, now: float, held_um: float) -> Alarm:
        """A deferred check: the controller did not take our last write, and holds ``held_um``."""
        self.counters["write_rejected"] += 1
        return Alarm.WRITE_REJECTED | self.mismatch(now, held_um, "deferred write check")

    def mismatch(self, now: float, held_um: float, when: str) -> Alarm:
        """The controller holds ``held_um``; act on it if it is not what we wrote."""
        expected = self.held_um
        faults = self.faults
        wrote_since, self.wrote_since_check = self.wrote_since_check, False
        if held_um == self.foreign_um and not wrote_since:
            return Alarm.NONE  # the same foreign value, nothing written since: no news
        diff = self.observe(held_um, faults.offset_tolerance_um)
        limit = self.shaper.config.max_offset_um
        self.foreign_um = held_um if diff is not None and abs(held_um) > limit else None
        if diff is None:
            if wrote_since:  # it took a write of ours: not refusing
                self.mismatch_streak = 0
            return Alarm.NONE
        self.counters["mismatches"] += 1
        self.mismatch_streak += 1
        cause = mismatch_cause(held_um, faults.offset_tolerance_um)
        if self.mismatch_streak <= faults.max_mismatches:  # then write_backoff speaks for it
            event(
                "offset_mismatch",
                self.name,
                "%s: OFFSET_MISMATCH (%s): the controller holds %.3f um, expected %.3f um; "
                "probably %s; ramping from there",
                self.name,
                when,
                held_um,
                expected,
                cause,
                level=logging.ERROR,
                held_um=held_um,
                expected_um=expected,
                cause=cause,
                when=when,
                streak=self.mismatch_streak,
            )
        if self.mismatch_streak >= faults.max_mismatches:
            k = self.mismatch_streak - faults.max_mismatches
            pause = min(faults.max_write_backoff_s, self.period_s * 2 ** (k + 1))
            self.paused_until_s = now + pause
            event(
                "write_backoff",
                self.name,
                "%s: the controller keeps refusing the offset (%d mismatches in a row): no "
                "write for %.3g s",
                self.name,
                self.mismatch_streak,
                pause,
                level=logging.ERROR,
                pause_s=pause,
                streak=self.mismatch_streak,
            )
        return Alarm.OFFSET_MISMATCH

    # -- the write ----------------------------------------------------------------------

    def paused(self, now: float) -> bool:
        """Writes back off from a controller that keeps refusing."""
        return now < self.paused_until_s

    def shaper_dt(self, dt_s: float, clock_now: float) -> float:
        """The time the offset may move over this cycle: the slew limit holds in wall time at
        the controller, from the last write that took effect. A controller that hung inside a
        write took it late; the next cycle, almost at once, may move the offset only by the
        limit times the time since then, not times the cycle's own dt."""
        if self.write_done_s is not None:
            dt_s = min(dt_s, max(0.0, clock_now - self.write_done_s))
        return dt_s

    def apply(
        self,
        now: float,
        shaped: ShapedOffset,
        heard: Heard,
        link: LinkWatch,
        write: Callable[[float | None, Life | None], WriteResult],
        clock: Callable[[], float],
        cycle_alarms: Alarm = Alarm.NONE,
    ) -> tuple[bool, Alarm]:
        """Write ``shaped`` when due and the controller can take it, with the sign of life;
        where no offset is written and the link is up, the sign of life alone confirms the held
        one. Whether the offset was written and the alarms. ``cycle_alarms``: the cycle's so
        far, for the "compensation valid" flag. A controller that is not ready (machine off, in
        E-stop, not homed) applies its own offset; once it is ready the offset is re-seeded
        from there through the slew limit. A cycle that cannot vouch for what the controller
        holds (:attr:`unsure`) writes no offset and is not in step: compensation not valid."""
        wanted = self.wants_write(shaped)
        wrote, alarms = False, Alarm.NONE
        if heard.not_ready_um is not None:
            alarms |= Alarm.NOT_READY
            self.controller_holds(heard.not_ready_um)
            alarms |= self.confirm(now, write, link, valid=self.valid(False, alarms))
        elif link.up and wanted and self.writes and not self.paused(now) and not self.unsure:
            life = None if self.life is None else self.life.next(self.valid(True, cycle_alarms))
            result = write(shaped.offset_um, life)
            alarms |= self.took(now, result, clock(), link)
            wrote = result.taken
            if wrote and life is not None:  # the offset taken, whatever befell the sign
                alarms |= self.beat(now, life, result.life_failure, link)
        elif link.up:  # nothing due, or held: confirm
            in_step = not wanted and not self.paused(now) and not self.unsure
            alarms |= self.confirm(now, write, link, valid=self.valid(in_step, cycle_alarms))
        else:
            self.counters["link_down_cycles"] += 1
        self.settle(
            now,
            shaped,
            wanted=wanted,
            wrote=wrote,
            ready=heard.not_ready_um is None,
            link_up=link.up,
        )
        if self.paused(now):
            alarms |= Alarm.WRITE_BACKOFF
        return wrote, alarms

    def valid(self, in_step: bool, alarms: Alarm) -> bool:
        """Whether compensation is valid once this cycle's write is taken: the controller then
        holds the offset aimed at (``in_step``: a write of it, or none due) and nothing holds
        it (:data:`NOT_COMPENSATING`); the same rule as the spindle's state
        (:func:`.states.spindle_state`), which a test holds them to. The chiller alone
        compensates while it runs."""
        if not self.writes:
            return True
        return in_step and not alarms & NOT_COMPENSATING

    def confirm(
        self,
        now: float,
        write: Callable[[float | None, Life | None], WriteResult],
        link: LinkWatch,
        *,
        valid: bool,
    ) -> Alarm:
        """The sign of life alone (no offset): the counter moves on when the controller took
        it. A link without one is not asked at all."""
        if self.life is None or not link.up:
            return Alarm.NONE
        life = self.life.next(valid)
        result = write(None, life)
        # a confirmation's own failure is a lost link; a link that reports the sign's refusal
        # there instead is taken as the sign's failure
        return self.beat(now, life, result.failure or result.life_failure, link)

    def beat(self, now: float, life: Life, failure: Failure | None, link: LinkWatch) -> Alarm:
        """The sign of life's part of a write the controller took: the counter moves on, or,
        where the counter or the flag was not written, stays where the controller last took it
        and ``SIGN_OF_LIFE`` is raised (an event where a run of failures begins and where it
        ends, not every cycle). The offset's part stands either way."""
        if failure is None:
            if self.life_error is not None:
                event(
                    "sign_of_life_restored",
                    self.name,
                    "%s: sign of life written again (counter %d)",
                    self.name,
                    life.counter,
                    counter=life.counter,
                )
            self.life, self.life_error = life, None
            return Alarm.NONE
        if failure.link_lost:
            return link.failed(now, failure)
        self.counters["life_failed"] += 1
        if self.life_error is None:
            event(
                "sign_of_life_failed",
                self.name,
                "%s: SIGN_OF_LIFE: the sign of life is not written (%s); the offset is, but "
                "the control's watch sees the counter stop at %d",
                self.name,
                failure.reason,
                0 if self.life is None else self.life.counter,
                level=logging.ERROR,
                error=failure.reason,
            )
        self.life_error = failure.reason
        return Alarm.SIGN_OF_LIFE

    def last_beat(
        self, write: Callable[[float | None, Life | None], WriteResult], link_up: bool
    ) -> Life | None:
        """A clean stop: one last sign of life with compensation not valid, the offset left
        where it is (the control's watcher reacts as its integrator chose). The sign written,
        or None (no sign of life on this link, the link down or the write failed)."""
        if self.life is None or not link_up:
            return None
        life = self.life.next(False)
        result = write(None, life)
        failure = result.failure or result.life_failure
        if failure is not None:
            log.warning("%s: last sign of life not written: %s", self.name, failure)
            return None
        self.life = life
        return life

    def took(self, now: float, result: WriteResult, done_s: float, link: LinkWatch) -> Alarm:
        """The outcome of this cycle's write, returned at clock time ``done_s``."""
        failure = result.failure
        if failure is None:
            self.counters["writes"] += 1
            self.last_write_s = now
            self.write_done_s = done_s  # a write a hung controller held took effect only now
            self.wrote_since_check = True
            return Alarm.NONE
        if failure.kind is FailureKind.REFUSED:
            self.counters["write_rejected"] += 1
            self.need_readback = True  # what does it hold now?
            event(
                "write_rejected",
                self.name,
                "%s: write refused (%d so far): %s",
                self.name,
                self.counters["write_rejected"],
                failure.reason,
                level=logging.ERROR,
                error=failure.reason,
            )
            return Alarm.WRITE_REJECTED
        if failure.link_lost:
            return link.failed(now, failure)
        log.error("%s: write failed: %s", self.name, failure.reason)
        return Alarm.NONE

    def settle(
        self,
        now: float,
        shaped: ShapedOffset,
        *,
        wanted: bool,
        wrote: bool,
        ready: bool,
        link_up: bool,
    ) -> None:
        """The cycle's end: what the controller holds now, and whether it is what the shaper
        aims at."""
        if wrote or (not wanted and link_up and ready and self.writes and not self.unsure):
            self.last_in_step_s = now  # the controller holds what the shaper aims at
        if wrote:
            self.written(shaped)
        elif ready:
            self.kept(wanted)
