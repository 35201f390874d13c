"""How often to stop for the tool setter when it is the only measurement of a calibration run.

Pure: numbers in, a :class:`ProbePlan` out; the wizard prints :meth:`ProbePlan.lines`.

The rule, in this order:

1. **at least 3 measurements per staircase step**: a step's heat-up is a curve, and three points
   are the fewest that show its bend (interval <= step / 3);
2. **no longer than half the fastest thermal time constant**: the fastest state must be seen
   while it moves, not only settled (interval <= tau_fastest / 2). The time constant comes from a
   former model of the spindle when there is one; without one it is assumed, ``ASSUMED_TAU_S``
   (10 min: motorized spindles' fastest states are minutes), and the plan says so;
3. rounded **down** to whole minutes (so both bounds hold), at least one minute;
4. **a laser at speed** (the spindle keeps turning through the cycle) loses no growth at a stop,
   so it stops more often: every whole minute at which the cycles add at most
   :data:`AT_SPEED_OVERHEAD` to the program, when that is shorter. Its measurements are as noisy
   as a contact setter's, and more of them is what brings its model to the eddy-current
   sensor's (the benchmarks page has the figures);
5. **touches averaged per stop**: a laser at speed repeats its slow touch as often as the stop
   still fits that share at the planned interval (at most :data:`MAX_TOUCHES`): the mean of N
   independent touches has 1/sqrt(N) of one touch's noise (GUM, JCGM 100:2008, 4.2.3). At rest
   the cycle touches once unless asked: each further touch keeps the spindle stopped longer and
   lets more of the growth decay.

Each stop costs the cycle's time (``cycle_s``: the spindle at rest, the program waiting) and the
growth that decays meanwhile: the fastest state loses 1 - exp(-dwell / tau) of itself per stop,
a bias of the measurement toward cooler that the model sees too, since the log shows the spindle
at rest. Over the run the stops keep the spindle at rest for stops x dwell, the share of the run
reported as ``stopped_share``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from compensator.speed_programs import paper_calibration

from .nc_programs import probe_stops
from .probeprog import MAX_TOUCHES

ASSUMED_TAU_S = 600.0
"""The fastest thermal time constant assumed without a former model [s]."""
PER_STEP = 3
"""Measurements per staircase step, at least."""
AT_SPEED_OVERHEAD = 0.2
"""A laser at speed stops as often as its cycles add at most this share to the program."""


@dataclass(frozen=True)
class ProbePlan:
    """A probe interval and what it costs."""

    interval_s: float
    stops: int
    """Stops in the program, the one at its end included."""
    added_s: float
    """Time the stops add to the program: stops x cycle."""
    loss_per_stop: float
    """Share of the fastest state's growth that decays during one stop: 1 - exp(-cycle / tau)."""
    stopped_share: float
    """Share of the whole run (program plus stops) spent at rest in the cycles."""
    fastest_tau_s: float
    tau_assumed: bool
    step_s: float
    dwell_s: float
    """One cycle with one touch [s]."""
    program_s: float
    bound: str
    """Which bound set the interval: "step", "tau", "minimum" or "overhead" (a laser at speed)."""
    touches: int = 1
    """Slow touches averaged per stop."""
    touch_s: float = 0.0
    """What each touch after the first adds to the cycle [s]."""
    touches_planned: bool = False
    """The plan chose ``touches`` (a laser at speed), rather than the caller."""

    @property
    def cycle_s(self) -> float:
        """One stop, every touch included [s]."""
        return self.dwell_s + (self.touches - 1) * self.touch_s

    def lines(self) -> list[str]:
        """What the wizard prints, one line each."""
        tau = (
            f"{self.fastest_tau_s / 60:.1f} min, assumed (no former model)"
            if self.tau_assumed
            else f"{self.fastest_tau_s / 60:.1f} min, from the former model"
        )
        why = {
            "step": f"at least {PER_STEP} measurements per {self.step_s / 60:g}-min step",
            "tau": "half the fastest time constant",
            "minimum": "one minute, the shortest interval planned",
            "overhead": (
                f"a laser at speed loses no growth at a stop: as often as the cycles add at most "
                f"{AT_SPEED_OVERHEAD:.0%} to the program"
            ),
        }[self.bound]
        lines = [
            f"tool-setter stop every {self.interval_s / 60:.0f} min ({why}; fastest time constant {tau})",
            f"{self.stops} stops of about {self.cycle_s:.0f} s: the program takes {self.added_s / 60:.1f} min "
            f"longer ({(self.program_s + self.added_s) / 3600:.2f} h in all)",
            (
                f"each stop lets {100 * self.loss_per_stop:.1f} % of the fastest growth decay; "
                f"{100 * self.stopped_share:.1f} % of the run is spent at rest measuring"
            )
            if self.stopped_share > 0
            else "the spindle keeps turning through each cycle: no growth decays while it measures",
        ]
        if self.touches > 1:
            why = (
                f"as many as keep the cycles within {AT_SPEED_OVERHEAD:.0%} of the program"
                if self.touches_planned
                else "as asked"
            )
            lines.append(
                f"{self.touches} touches averaged per stop ({why}; {self.touch_s:.1f} s each after the "
                f"first): the mean has {1 / math.sqrt(self.touches):.2f} of one touch's noise, where "
                f"the touches are independent"
            )
        return lines


def plan_probe_interval(
    step_s: float,
    cooldown_s: float,
    dwell_s: float,
    fastest_tau_s: float | None = None,
    *,
    program_s: float | None = None,
    at_speed: bool = False,
    touches: int | None = None,
    touch_s: float = 0.0,
) -> ProbePlan:
    """The probe interval for a calibration run with the tool setter alone (the rule is the
    module's): ``step_s``, the staircase step; ``cooldown_s``, the cool-down at rest;
    ``dwell_s``, one probe cycle's time with one touch (spindle stopped to program resumed);
    ``fastest_tau_s``, the fastest thermal time constant of a former model (None: assumed,
    ``ASSUMED_TAU_S``). ``program_s``: the program's duration without its stops (default: the
    calibration profile's at this step and cool-down). ``touches``: slow touches per stop (None:
    planned for a laser at speed, one at rest); ``touch_s``, what each after the first adds."""
    for name, v in (
        ("step_s", step_s),
        ("cooldown_s", cooldown_s),
        ("dwell_s", dwell_s),
        ("touch_s", touch_s),
    ):
        if not (math.isfinite(v) and v >= 0) or (name == "step_s" and v <= 0):
            least = "> 0" if name == "step_s" else ">= 0"
            raise ValueError(f"{name} {v!r}: give a finite number of seconds {least}")
    assumed = fastest_tau_s is None
    tau = ASSUMED_TAU_S if fastest_tau_s is None else float(fastest_tau_s)
    if not (math.isfinite(tau) and tau > 0):
        raise ValueError(f"fastest_tau_s {fastest_tau_s!r}: give a time constant > 0 s")
    by_step, by_tau = step_s / PER_STEP, tau / 2
    minutes = math.floor(min(by_step, by_tau) / 60.0)
    if touches is not None and not (isinstance(touches, int) and 1 <= touches <= MAX_TOUCHES):
        raise ValueError(f"touches {touches!r}: give a whole number from 1 to {MAX_TOUCHES}")
    bound = "minimum" if minutes < 1 else ("step" if by_step <= by_tau else "tau")
    interval = 60.0 * max(minutes, 1)
    first = dwell_s + ((touches or 1) - 1) * touch_s  # the cycle that sets the interval
    if at_speed:
        often = 60.0 * max(math.ceil(first / AT_SPEED_OVERHEAD / 60.0), 1)
        if often < interval:
            interval, bound = often, "overhead"
    planned = touches is None and at_speed and touch_s > 0
    if planned:  # rule 5: fill the stop's share at this interval with touches
        room = AT_SPEED_OVERHEAD * interval - dwell_s
        touches = max(1, min(MAX_TOUCHES, 1 + math.floor(room / touch_s + 1e-9)))
    touches = touches or 1
    cycle = dwell_s + (touches - 1) * touch_s
    if program_s is None:
        program_s = paper_calibration(
            27000.0, cooldown_min=cooldown_s / 60.0, step_min=step_s / 60.0
        ).duration_s
    n = len(probe_stops(program_s, interval))
    added = n * cycle
    # a laser at speed keeps the spindle turning through the cycle: no growth decays, none at rest
    return ProbePlan(
        interval_s=interval,
        stops=n,
        added_s=added,
        loss_per_stop=0.0 if at_speed else 1.0 - math.exp(-cycle / tau),
        stopped_share=0.0
        if at_speed
        else added / (program_s + added)
        if program_s + added > 0
        else 0.0,
        fastest_tau_s=tau,
        tau_assumed=assumed,
        step_s=float(step_s),
        dwell_s=float(dwell_s),
        program_s=float(program_s),
        bound=bound,
        touches=touches,
        touch_s=float(touch_s),
        touches_planned=planned,
    )
