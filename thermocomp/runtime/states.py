"""Each spindle's **state**, derived in one place: :func:`spindle_state`, a pure function of its
runtime facts (:class:`SpindleFacts`): ``compensating``, ``holding`` or ``not writing``, with one
reason. The snapshot carries it, and the page, ``thermocomp status``, ``/metrics``, MQTT and the
service's status line all show that one; none derives its own. The alarm names and JSON-safe
numbers every view shares live here too."""

from __future__ import annotations

import math
import time
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from .spindle import Alarm, SpindleRuntime

ALARM_NAMES = {int(a): a.name for a in Alarm if a.name and a != Alarm.NONE}
"""Alarm bit -> name, as the page and the metrics show them."""


def alarm_names(bits: int) -> list[str]:
    return [name for bit, name in ALARM_NAMES.items() if bits & bit]


def finite(value: Any) -> float | None:
    """A JSON-safe number: None for a missing or non-finite one."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


# -- the spindle's state: one derivation ------------------------------------------------------

STATES = ("compensating", "holding", "not writing")
"""Every state a running spindle can be in, best first. A clean stop leaves a fourth,
``stopped`` (:func:`stopped_state`), in the last status the service publishes."""

StateWord = Literal["compensating", "holding", "not writing", "stopped"]


class SpindleFacts(BaseModel):
    """What a spindle's state is judged on, at one instant; times are journal times [s]."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    now_s: float
    period_s: float = Field(gt=0)
    not_writing_cycles: int = Field(ge=1)
    cycles: int = Field(ge=0, description="cycles run since the runtime was built")
    writes_offset: bool = True
    link_up: bool
    link_state: str = "connected"
    link_down_since_s: float | None = None
    link_error: str | None = None
    last_in_step_s: float | None = Field(
        None,
        description="the last cycle the controller held the offset "
        "aimed at: a write went through, or none was due",
    )
    last_write_s: float | None = None
    since_s: float = Field(
        description="when the runtime began: a spindle never in step counts from here"
    )
    alarm_bits: int = 0
    offset_mode: str = "tracking"
    cold_settle_s: float | None = Field(
        None,
        description="COLD_START_TURNING: when the estimate settles (inf: only at a measurement)",
    )
    unsure: str | None = Field(
        None,
        description="why the last cycle could not vouch for the offset the controller holds "
        "(whether the machine is ready could not be read, a reconnect not yet read back)",
    )


class SpindleState(BaseModel):
    """One state word and one reason ("" for a plain ``compensating``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    state: StateWord
    reason: str = ""

    @property
    def compensating(self) -> bool:
        return self.state == "compensating"

    @property
    def line(self) -> str:
        return self.state + (f": {self.reason}" if self.reason else "")


def clock_time(t_s: float | None) -> str:
    """A journal time as a person reads it on the shop floor: ``12:03:10 UTC``."""
    if t_s is None or not math.isfinite(t_s):
        return "never"
    return time.strftime("%H:%M:%S UTC", time.gmtime(t_s))


def spindle_state(f: SpindleFacts) -> SpindleState:
    """The spindle's state: the one rule every view shows.

    - ``not writing``: no cycle has run yet (starting); the link is down (refused, lost, timing out); or the
      controller has not held the offset aimed at for more than ``not_writing_cycles`` cycles
      (no write went through while one was due: refused, backed off, cycles failing);
    - ``holding``: the link is up and writes reach the controller, but the offset does not follow
      the estimate now: the machine is not ready (the controller applies its own), whether it
      is ready or what the controller holds cannot be told this cycle, the estimate step was
      refused, the speed cannot be read (a sensor fault: last speed held, or idle
      assumed), or a write is pending (refused, backed off) for fewer cycles than that;
    - ``compensating``: otherwise; the reason then names what the estimate rests on when it is
      not the model as calibrated (an unsettled cold start, the speed-only fallback), or the
      chiller where it compensates instead of the offset.
    """
    bits = Alarm(f.alarm_bits)
    if f.cycles == 0 and f.now_s - f.since_s <= f.not_writing_cycles * f.period_s:
        return SpindleState(state="not writing", reason="starting: no cycle has run yet")
    if not f.link_up:
        word = "link down (outage)" if f.link_state == "outage" else "link down"
        since = "" if f.link_down_since_s is None else f" since {clock_time(f.link_down_since_s)}"
        why = f" ({f.link_error})" if f.link_error else ""
        return SpindleState(state="not writing", reason=f"{word}{since}{why}")
    if not f.writes_offset:
        return SpindleState(
            state="compensating",
            reason="by the chiller ([cooling] mode = cooling): no offset is written",
        )
    if bits & Alarm.NOT_READY:
        return SpindleState(
            state="holding",
            reason="machine not ready (off, E-stop or not homed): the "
            "controller applies its own offset",
        )
    ref = f.last_in_step_s if f.last_in_step_s is not None else f.since_s
    behind_s = f.now_s - ref
    if behind_s > f.not_writing_cycles * f.period_s:
        last = (
            "never written"
            if f.last_write_s is None
            else f"last write {clock_time(f.last_write_s)}"
        )
        if bits & Alarm.WRITE_BACKOFF:
            cause = "the controller keeps refusing the offset: writes paused"
        elif bits & Alarm.WRITE_REJECTED:
            cause = "the controller refuses the offset"
        elif f.unsure:
            cause = f"{f.unsure}: no offset written"
        else:
            # a time, not a duration: the line stays the same while nothing changes
            cause = f"no write has gone through since {clock_time(ref)}"
        return SpindleState(state="not writing", reason=f"{cause}; {last}")
    if f.unsure:
        return SpindleState(state="holding", reason=f"{f.unsure}: no offset written")
    if bits & Alarm.ESTIMATE_REFUSED:
        return SpindleState(
            state="holding", reason="estimate step refused: offset held at its last value"
        )
    if bits & Alarm.IDLE_ASSUMED:
        return SpindleState(state="holding", reason="sensor fault: speed not read, idle assumed")
    if bits & Alarm.SPEED_READ_FAILED:
        return SpindleState(state="holding", reason="sensor fault: speed not read, last speed held")
    if bits & Alarm.WRITE_BACKOFF:
        return SpindleState(
            state="holding",
            reason="the controller refused the offset: writes paused, "
            "offset held at its last value",
        )
    if f.offset_mode == "holding":
        return SpindleState(
            state="holding", reason="offset held at its last value: the write is pending"
        )
    notes = []
    if bits & Alarm.COLD_START_TURNING:
        until = (
            "a measurement is accepted"
            if f.cold_settle_s is None or not math.isfinite(f.cold_settle_s)
            else f"{clock_time(f.cold_settle_s)} or a measurement accepted"
        )
        notes.append(f"estimate unsettled after a cold start on a turning spindle (until {until})")
    if bits & Alarm.INPUT_FALLBACK:
        notes.append("on the speed-only fallback (input fault)")
    return SpindleState(state="compensating", reason="; ".join(notes))


def spindle_facts(rt: SpindleRuntime, now_s: float) -> SpindleFacts:
    """The facts of runtime ``rt`` at clock time ``now_s`` (the service's clock)."""
    a = rt.anchor_s

    def at(t: float | None) -> float | None:  # clock time -> journal time
        return None if t is None else a + t

    cfg = rt.cfg
    return SpindleFacts(
        now_s=a + now_s,
        period_s=cfg.period_s,
        not_writing_cycles=cfg.faults.not_writing_cycles,
        cycles=int(rt.counters.get("cycles", 0)),
        writes_offset=bool(rt.writes_offset),
        link_up=rt.link.up,
        link_state=rt.link.state.value,
        link_down_since_s=at(rt.link.down_since),
        link_error=rt.link.error,
        last_in_step_s=at(rt.offset.last_in_step_s),
        last_write_s=at(rt.offset.last_write_s),
        since_s=a + rt.pace.created_s,
        alarm_bits=int(rt.alarms),
        offset_mode=rt.offset.mode.value,
        cold_settle_s=at(rt.cold.settle_s),
        unsure=rt.offset.unsure,
    )


def state_of(rt: SpindleRuntime, now_s: float) -> SpindleState:
    """Runtime ``rt``'s state at clock time ``now_s``."""
    return spindle_state(spindle_facts(rt, now_s))


def stopped_state(rt: SpindleRuntime) -> SpindleState:
    """What a clean stop leaves: the offset the controller holds (last written or read back)
    stays there; the control's watcher reacts as its integrator chose."""
    if not rt.writes_offset:
        return SpindleState(state="stopped", reason="no offset was written (the chiller only)")
    held = rt.offset.held_um
    known = "" if rt.link.up else " (as last known: the link is down)"
    return SpindleState(state="stopped", reason=f"the control holds {held:.2f} µm{known}")
