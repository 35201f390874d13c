"""A cold start on a turning spindle: ``COLD_START_TURNING``.

A cold start (no usable saved state) whose first speed read shows the spindle turning (at least
``TURNING_MIN_RPM``, or 1 % of the calibrated top) means the machine is probably warm while the
estimate starts from rest. The alarm stands until ``cold_start_settle_taus`` x the model's
slowest time constant have passed, or until the observer takes a measurement; a restart does
not clear it.
"""

from __future__ import annotations

import logging
import math
from typing import Any

from compensator.estimate import Estimate
from compensator.io.journal_export import iso

from .alarms import Alarm
from .events import event

TURNING_MIN_RPM = 10.0
"""Below this |speed| [rpm] (or 1 % of the calibrated top, whichever is larger) a spindle is not
taken as turning at a cold start: a reading's noise, not a machine at work."""


def slowest_tau_s(model: Any) -> float | None:
    """The slowest time constant [s] of ``model`` anywhere in its speed range, its input lags
    and its fallback included; None where the model states none. A wrong initial state decays
    with the model's own dynamics, so after k of these it has fallen to exp(-k) of itself."""
    parts = [model, getattr(model, "model", None)]  # a fused model wraps its own
    parts += [
        getattr(m, k, None)
        for m in list(parts)
        if m is not None
        for k in ("speed_model", "fallback")
    ]
    taus: list[float] = []
    for m in parts:
        if m is None:
            continue
        lo, hi = getattr(m, "speed_range_rpm", (0.0, 0.0))
        if callable(getattr(m, "time_constants_s", None)):
            for n in (0.0, lo, (lo + hi) / 2, hi):
                taus += [float(t) for t in m.time_constants_s(n)]
        taus += [float(t.tau_s) for t in getattr(m, "inputs", None) or () if hasattr(t, "tau_s")]
    taus = [t for t in taus if math.isfinite(t) and t > 0]
    return max(taus) if taus else None


class ColdStart:
    """Whether the estimate still rests on a cold start's guess."""

    def __init__(self, name: str, settle_taus: float, anchor_s: float):
        self.name = name
        self.settle_taus = settle_taus
        self.anchor_s = anchor_s
        # the clock time the estimate counts as settled while raised (inf: only a measurement
        # settles it); unjudged from a cold start until a speed is read
        self.settle_s: float | None = None
        self.unjudged = False
        # until then the model alone still carries the cold start's error (a measurement
        # corrects the estimate through the bias, not the model): its misses are no drift
        self.model_until_s = -math.inf

    def follow(self, old: ColdStart) -> None:
        """A reload or another model: a new configuration does not settle an estimate."""
        self.settle_s, self.unjudged = old.settle_s, old.unjudged
        self.model_until_s = old.model_until_s

    def started(self) -> None:
        self.unjudged = True  # turning or not: judged at the first speed read

    def carried(self, now: float, until_wall_s: float, wall_now: float) -> None:
        """A restart does not settle an estimate: the rest of the wait carries over."""
        self.settle_s = now + min(until_wall_s - wall_now, 1e9)
        self.model_until_s = self.settle_s
        event(
            "cold_start_turning",
            self.name,
            "%s: COLD_START_TURNING carried over a restart: the estimate of the last cold start "
            "settles at %s, or at a measurement accepted",
            self.name,
            iso(until_wall_s),
            level=logging.WARNING,
            settles_wall_s=until_wall_s,
            carried=True,
        )

    def judge(self, now: float, speed_rpm: float, estimate: Estimate) -> None:
        """The first speed read after a cold start: turning, the machine is probably warm while
        the estimate starts from rest, so COLD_START_TURNING is raised until it has settled."""
        self.unjudged = False
        turning = max(TURNING_MIN_RPM, 0.01 * estimate.core.speed_range_rpm[1])
        if abs(speed_rpm) < turning:
            return
        tau = slowest_tau_s(estimate.model)
        k = self.settle_taus
        self.settle_s = now + k * tau if tau is not None else math.inf
        if tau is not None:
            self.model_until_s = self.settle_s
        until = (
            f"until {iso(self.anchor_s + self.settle_s)} ({k:g} x the model's slowest time "
            f"constant, {tau / 60:.0f} min) or"
            if tau is not None
            else "(the model states no time constant) until"
        )
        event(
            "cold_start_turning",
            self.name,
            "%s: COLD_START_TURNING: cold start with the spindle at %.0f rpm: the machine is "
            "probably warm while the estimate starts from rest; expect a large error %s a "
            "measurement is accepted",
            self.name,
            speed_rpm,
            until,
            level=logging.WARNING,
            speed_rpm=speed_rpm,
            tau_s=tau,
            settle_taus=k,
            settles_s=None if tau is None else self.anchor_s + self.settle_s,
        )

    def alarm(self, now: float) -> Alarm:
        """COLD_START_TURNING while raised: it clears once the settling time has passed since
        it was raised (the cold start's error has decayed to exp(-k) of itself, running or
        not), or at a measurement the observer takes (:meth:`measured`)."""
        if self.settle_s is None:
            return Alarm.NONE
        if now < self.settle_s:
            return Alarm.COLD_START_TURNING
        self.settle_s = None
        event(
            "cold_start_settled",
            self.name,
            "%s: COLD_START_TURNING cleared: the estimate has settled (%g x the model's slowest "
            "time constant since the cold start)",
            self.name,
            self.settle_taus,
            reason="settled",
        )
        return Alarm.NONE

    def measured(self, measured_um: float, outcome: str) -> None:
        """The observer took a measurement: the estimate no longer rests on the start's guess."""
        if self.settle_s is None:
            return
        self.settle_s = None
        event(
            "cold_start_settled",
            self.name,
            "%s: COLD_START_TURNING cleared: measurement %.3f um %s by the observer",
            self.name,
            measured_um,
            outcome,
            reason="measurement",
            outcome=outcome,
            measured_um=measured_um,
        )

    def saved_fields(self, now: float, wall_now: float) -> dict[str, float]:
        """What the state file keeps of an unsettled start (its end in wall time)."""
        if self.settle_s is None:
            return {}
        return {"cold_start_unsettled_until_wall_s": wall_now + min(self.settle_s - now, 1e9)}
