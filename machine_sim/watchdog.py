"""The control's watch on thermocomp's sign of life, as the virtual CNC runs it.

thermocomp writes a life counter (1 .. 32767, wrapping to 1; 0 = never written) and a
"compensation valid" flag with the offset. The control judges them on its own clock (here the
virtual machine's simulated time, never the wall clock):

- **waiting**: the counter has never been written (0). thermocomp has never run on this control,
  so there is nothing to watch and nothing happens: the virtual CNC works without thermocomp.
  The watch arms at the first beat (a counter that moves to a value other than 0) and stays
  armed until the control restarts.
- **ok**: the counter moved within ``timeout_s`` and the flag is true.
- **stale**: the counter has not moved for ``timeout_s`` (thermocomp died, hangs or lost the link).
  ``timeout_s`` is machine time; a machine that runs faster than the wall clock takes 3 s of
  wall time by default (:func:`default_timeout_s`), as a real control would.
- **invalid**: the flag is false (thermocomp stopped cleanly, holds, or knows its offset is
  wrong): the control reacts at once, whatever the counter does.

Leaving ok (for stale or invalid) is a *trip*; the reaction the integrator chose starts then:

- ``none``: today's behaviour: the offset stays as it is; the state is shown, nothing else.
- ``alarm``: an alarm text is set and the next cycle start is refused; the running program goes
  on to its end. The alarm is latched: the operator's reset clears it, and only once the sign of
  life is back (ok); a reset while it is still missing leaves it standing.
- ``feed-hold``: the running program pauses where it is (its time stops, the axes stand, the
  tool does not cut). The spindle keeps its speed, as on most controls, where a feed hold stops
  the feed and not the spindle: the spindle's growth stays where the offset was right.
  Latched: the operator's cycle start resumes the program, and only once the sign of life is
  back; the machine never moves on by itself.
- ``fade``: the applied offset goes to zero first-order, with time constant ``fade_tau_s`` (a
  spindle's cooling constant: the growth it compensated decays about as fast once the spindle
  stops), never faster than ``fade_max_rate_um_per_s``. The fade stops by itself when the sign
  of life is back (thermocomp writes its offset again); the offset stays where the fade left it
  until then.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Literal

from cnc_adapters.reading import LIFE_MODULUS

Reaction = Literal["none", "alarm", "feed-hold", "fade"]
REACTIONS: tuple[Reaction, ...] = ("none", "alarm", "feed-hold", "fade")
WatchState = Literal["waiting", "ok", "stale", "invalid"]

FADE_TAU_S = 1200.0
"""The default fade: the virtual motorized spindle's cooling time constant at rest (its growth
falls by 1/e in 18 to 22 min once the elastic part has gone), typical of motorized spindles."""
FADE_RATE_UM_PER_S = 1.0
"""The default cap on the fade's rate: the slow slew limit the service itself keeps while cutting."""
FADE_ZERO_UM = 0.001
"""A fading offset below this is zero: a first-order decay would never end."""
CHANGES_KEPT = 1000
ALARM_STALE = "7001 THERMAL COMPENSATION: no sign of life from thermocomp for {timeout:g} s"
ALARM_INVALID = "7002 THERMAL COMPENSATION: thermocomp says its offset is not valid"
WALL_TIMEOUT_S = 3.0
"""The watch's default timeout in wall seconds: a real control's, whatever the time scale."""
WALL_TIMEOUT_MIN_S = 1.0
"""A timeout shorter than this in wall time trips on a late cycle of a healthy service."""


def default_timeout_s(time_scale: float) -> float:
    """The default timeout in machine (simulated) seconds for a control running ``time_scale``
    times faster than the wall clock: :data:`WALL_TIMEOUT_S` of wall time. A watch judged on
    simulated time with a fixed 3 s would give a service at 60x 50 ms of wall time per beat, and
    trip over and over while it runs normally. Never under 3 s of machine time (a slower
    machine than real time keeps a real control's 3 s)."""
    return WALL_TIMEOUT_S * max(1.0, float(time_scale))


def timeout_warning(timeout_s: float, time_scale: float) -> str:
    """One line when ``timeout_s`` (machine seconds) is under :data:`WALL_TIMEOUT_MIN_S` of wall
    time at ``time_scale``; '' when it is not."""
    wall_s = timeout_s / time_scale
    if wall_s >= WALL_TIMEOUT_MIN_S:
        return ""
    return (
        f"--watch-timeout-s {timeout_s:g} is {wall_s * 1000:.0f} ms of wall time at "
        f"--time-scale {time_scale:g}: a late cycle of a healthy service will trip the watch; "
        f"give at least {WALL_TIMEOUT_MIN_S * time_scale:g} (the default is "
        f"{default_timeout_s(time_scale):g})"
    )


@dataclass(frozen=True)
class WatchSettings:
    """How the control watches the sign of life and how it reacts (see the module)."""

    timeout_s: float = 3.0
    reaction: Reaction = "none"
    fade_tau_s: float = FADE_TAU_S
    fade_max_rate_um_per_s: float = FADE_RATE_UM_PER_S

    def __post_init__(self) -> None:
        if self.reaction not in REACTIONS:
            raise ValueError(
                f"watch reaction {self.reaction!r} is not one of {', '.join(REACTIONS)}"
            )
        for name in ("timeout_s", "fade_tau_s", "fade_max_rate_um_per_s"):
            v = getattr(self, name)
            if (
                isinstance(v, bool)
                or not isinstance(v, (int, float))
                or not (math.isfinite(v) and v > 0)
            ):
                raise ValueError(f"watch {name} must be a finite number > 0, got {v!r}")


def _whole(value: object) -> int | None:
    """``value`` as a whole number (an int, or a finite float with no fraction); None else."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        return int(value)
    return None


class Watch:
    """The watcher: fed the counter and the flag as the control reads them (:meth:`beat`) and
    judged on the machine's clock (:meth:`update`). Pure: it owns no clock and moves nothing; the
    machine asks it what is in force (:attr:`alarm`, :attr:`held`, :attr:`fading`).

    ``say``: called with (machine time, one line) for each trip and its reaction, the sign of
    life coming back, a reset and what the machine adds (:meth:`note`: a refused cycle start),
    as a control's message line; None: silent."""

    def __init__(
        self,
        settings: WatchSettings | None = None,
        say: Callable[[float, str], None] | None = None,
    ) -> None:
        self.settings = settings or WatchSettings()
        self.say = say
        self.restart()

    def note(self, now_s: float, text: str) -> None:
        """One line for the control's message log (nothing without ``say``)."""
        if self.say is not None:
            self.say(float(now_s), text)

    def restart(self) -> None:
        """The control (re)starts: the nodes read 0 and false, nothing is armed or latched."""
        self.counter = 0
        self.valid = False
        self.last_beat_s: float | None = None
        """Machine time the counter last moved; None: never (the watch waits)."""
        self.state: WatchState = "waiting"
        self.trips = 0
        self.tripped_at_s: float | None = None
        """Machine time of the last trip; None: never."""
        self.alarm = ""
        """The latched alarm text ('' when none): the next cycle start is refused."""
        self.held = False
        """The latched feed hold: the program pauses until the operator resumes it."""
        self.fading = False
        """The offset is fading to zero."""
        self.changes: deque[tuple[float, WatchState]] = deque(maxlen=CHANGES_KEPT)
        """The last changes of state: (machine time, the new state)."""

    @property
    def armed(self) -> bool:
        return self.last_beat_s is not None

    @property
    def ok(self) -> bool:
        """Nothing to react to: the sign of life is there, or it has never been."""
        return self.state in ("waiting", "ok")

    def with_reaction(self, reaction: Reaction) -> None:
        """Change the reaction. A watch that has tripped acts as if it had been set so at the trip
        (a what-if from a copy of the machine: the reaction follows from the trip alone)."""
        self.settings = replace(self.settings, reaction=reaction)
        self.alarm, self.held, self.fading = "", False, False
        if not self.ok:
            self._react()

    def beat(self, counter: object, valid: object, now_s: float) -> WatchState:
        """The counter and the flag as the control reads them at ``now_s``. A beat is a counter
        that moved to another whole number in 1 .. 32767 (an integer, or a whole floating-point
        number where the variable is one, a SINUMERIK R parameter); 0 (never written), a value
        out of range or not a whole number moves nothing. The flag is true as a Boolean true or
        the number 1; anything else is false."""
        n = _whole(counter)
        if n is not None and 0 < n <= LIFE_MODULUS:
            if n != self.counter:
                self.last_beat_s = float(now_s)
            self.counter = n
        elif n == 0:
            self.counter = 0
        self.valid = valid is True or _whole(valid) == 1
        return self.update(now_s)

    def update(self, now_s: float) -> WatchState:
        """Judge at ``now_s`` (machine time): the state, tripping (the reaction starts) when it
        leaves ok, and ending a fade when the sign of life is back."""
        new: WatchState
        if self.last_beat_s is None:
            new = "waiting"
        elif not self.valid:
            new = "invalid"
        elif now_s - self.last_beat_s >= self.settings.timeout_s - 1e-9:
            new = "stale"
        else:
            new = "ok"
        if new in ("stale", "invalid") and self.state in ("waiting", "ok"):
            self.state = new
            self.trips += 1
            self.tripped_at_s = float(now_s)
            self._react()
            self.note(now_s, self._trip_text())
        elif new == "ok":
            if self.state in ("stale", "invalid"):
                self.note(now_s, self._back_text())
            self.fading = False  # thermocomp writes its offset again
        if new != (self.changes[-1][1] if self.changes else "waiting"):
            self.changes.append((float(now_s), new))
        self.state = new
        return new

    def _react(self) -> None:
        r = self.settings.reaction
        if r == "alarm":
            self.alarm = (
                ALARM_INVALID
                if self.state == "invalid"
                else ALARM_STALE.format(timeout=self.settings.timeout_s)
            )
        elif r == "feed-hold":
            self.held = True
        elif r == "fade":
            self.fading = True

    def _trip_text(self) -> str:
        if self.state == "invalid":
            why = "invalid: the valid flag is false"
        else:
            last = "" if self.last_beat_s is None else f" (last beat at {self.last_beat_s:.1f} s)"
            why = f"stale: the life counter still for {self.settings.timeout_s:g} s{last}"
        r = self.settings.reaction
        did = {
            "none": "the offset kept",
            "alarm": f"alarm {self.alarm}; the next cycle start is refused until a reset",
            "feed-hold": "feed hold, the program paused (the spindle turns)",
            "fade": (
                f"the offset fades to zero (tau {self.settings.fade_tau_s:g} s, at most "
                f"{self.settings.fade_max_rate_um_per_s:g} um/s)"
            ),
        }[r]
        return f"watch tripped ({self.trips}): {why}; reaction {r}: {did}"

    def _back_text(self) -> str:
        then = ""
        if self.alarm:
            then = "; the alarm stands until a reset"
        elif self.held:
            then = "; the feed hold waits for cycle start"
        return f"watch ok: the sign of life is back (counter {self.counter}){then}"

    @property
    def refusal(self) -> str:
        """Why the next cycle start is refused ('' when it is not)."""
        if self.alarm:
            return self.alarm
        if self.held and not self.ok:
            return "feed hold: the sign of life from thermocomp is missing"
        return ""

    def reset(self, now_s: float | None = None) -> bool:
        """The operator's reset: the alarm clears if the sign of life is back (True when
        nothing is latched after it). ``now_s``: the machine time, for its message line."""
        had = self.alarm
        if self.ok:
            self.alarm = ""
        if now_s is not None:
            if had and not self.alarm:
                self.note(now_s, f"reset: alarm cleared ({had.split(' ', 1)[0]})")
            elif self.alarm:
                self.note(
                    now_s,
                    f"reset: alarm {self.alarm.split(' ', 1)[0]} stands, the sign of life is "
                    f"still missing ({self.state})",
                )
            else:
                self.note(now_s, "reset: no alarm to clear")
        return not self.alarm

    def resume(self) -> bool:
        """The operator's cycle start during a feed hold: the program resumes if the sign of
        life is back (True when it does)."""
        if self.held and self.ok and not self.alarm:
            self.held = False
            return True
        return False

    def fade(self, offset_um: float, dt_s: float) -> float:
        """The offset ``dt_s`` later while fading: first-order toward 0 with ``fade_tau_s``,
        never faster than ``fade_max_rate_um_per_s``; 0 once below :data:`FADE_ZERO_UM`."""
        s = self.settings
        target = offset_um * math.exp(-dt_s / s.fade_tau_s)
        cap = s.fade_max_rate_um_per_s * dt_s
        step = max(-cap, min(cap, target - offset_um))
        out = offset_um + step
        return 0.0 if abs(out) < FADE_ZERO_UM else out

    def summary(self) -> str:
        """One line for a report: the state, the counter and flag, the trips, the reaction."""
        if not self.armed:
            return "never written: thermocomp did not run here, nothing to watch"
        return (
            f"{self.state} (counter {self.counter}, valid {str(self.valid).lower()}), tripped "
            f"{self.trips} times; {self.reaction_text() or f'reaction {self.settings.reaction}'}"
        )

    def reaction_text(self) -> str:
        """What the control does now, for its status node: '' when nothing is in force."""
        if self.ok and not (self.alarm or self.held):
            return ""
        parts = []
        if self.alarm:
            parts.append("alarm: cycle start refused")
        if self.held:
            parts.append("feed hold: program paused")
        if self.fading:
            parts.append("fade: offset to zero")
        return "; ".join(parts) or "none: offset kept"
