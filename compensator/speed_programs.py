"""Speed programs: piecewise-constant spindle speed over time.

A :class:`Program` is a list of (duration_s, speed_rpm) segments. Sampling it
at ``dt_s`` gives ``speeds[k]``, the speed held over ``(t[k-1], t[k]]``, the
convention of :meth:`compensator.model.ThermalModel.simulate`. ``probe_at_s``, when given,
are the program times at which a tool-setter cycle runs: the machine stops the spindle for the
cycle's own duration and then resumes the program where it stopped, so the segments never
count that time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Program:
    name: str
    segments: tuple[tuple[float, float], ...]  # (duration_s, speed_rpm)
    probe_at_s: tuple[float, ...] = ()  # program times of the tool-setter stops, ascending

    @property
    def duration_s(self) -> float:
        return float(sum(d for d, _ in self.segments))

    def speed_at(self, t_s: float) -> float:
        """Speed held just before ``t_s`` (the segment containing ``t_s - 0``)."""
        edges = np.cumsum([d for d, _ in self.segments])
        k = int(np.searchsorted(edges, t_s, side="left"))
        return (
            float(self.segments[min(k, len(self.segments) - 1)][1])
            if t_s > 0
            else float(self.segments[0][1])
        )

    def sample(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Times 0, dt, 2dt, ... to the end, and the speed held up to each."""
        n = int(round(self.duration_s / dt_s))
        t = np.arange(n + 1) * dt_s
        edges = np.cumsum([d for d, _ in self.segments])
        speeds = np.array([s for _, s in self.segments], dtype=float)
        # speed over (t-dt, t]: the segment that contains t - dt/2
        idx = np.searchsorted(edges, t - dt_s / 2, side="right")
        idx = np.clip(idx, 0, len(speeds) - 1)
        out = speeds[idx]
        out[0] = 0.0  # the log starts with the spindle at rest
        return t, out


MIN = 60.0


def paper_calibration(
    max_rpm: float = 27000.0, cooldown_min: float = 60.0, step_min: float = 20.0
) -> Program:
    """Paper 001, Fig. 3, scaled to ``max_rpm`` (27 000 rpm in the paper) and in time to
    ``step_min`` per staircase step (20 min in the paper).

    Phase 1 (0-180 min): 3000 rpm, +3000 every 20 min up to 27 000.
    Phase 2 (180-240 min): abrupt drop to 12 000, then 18 000, then 0.
    Phase 3 (240-300 min): accelerate, decelerate, accelerate, stop.
    Then a cool-down at 0 rpm, which pins the dissipation (the decay at rest identifies it).
    """
    k = max_rpm / 27000.0
    c = step_min / 20.0
    segs = [(20 * MIN, 3000.0 * i) for i in range(1, 10)]
    segs += [(20 * MIN, 12000.0), (20 * MIN, 18000.0), (20 * MIN, 0.0)]
    segs += [(10 * MIN, 6000.0), (15 * MIN, 21000.0), (10 * MIN, 9000.0), (15 * MIN, 24000.0)]
    if cooldown_min > 0:
        segs.append((cooldown_min * MIN, 0.0))
    return Program(
        "paper-calibration", tuple((d * c if i < 16 else d, s * k) for i, (d, s) in enumerate(segs))
    )


def random_validation(
    max_rpm: float = 27000.0,
    seed: int = 1,
    duration_min: float = 240.0,
    min_rpm_frac: float = 0.11,
    hold_min: tuple[float, float] = (2.0, 15.0),
) -> Program:
    """Random speeds between ~3000 and ``max_rpm`` (paper 001 validated on
    3000-15 000-10 000 rpm), held 2-15 min, with a few stops."""
    rng = np.random.default_rng(seed)
    segs: list[tuple[float, float]] = []
    total = 0.0
    while total < duration_min * MIN:
        d = float(rng.uniform(*hold_min)) * MIN
        if rng.uniform() < 0.12:
            s = 0.0
        else:
            s = float(np.round(rng.uniform(min_rpm_frac, 1.0) * max_rpm, -2))
        segs.append((d, s))
        total += d
    segs.append((30 * MIN, 0.0))
    return Program(f"random-validation-{seed}", tuple(segs))


def job_shop_day(max_rpm: float = 27000.0, seed: int = 7, hours: float = 8.0) -> Program:
    """A shift: operations of 1-20 min at mixed speeds, tool-change stops of
    5-30 s, setups of a few minutes, a 45-min lunch break mid-shift."""
    rng = np.random.default_rng(seed)
    segs: list[tuple[float, float]] = []
    total = 0.0
    lunch_at = hours * 3600.0 / 2
    had_lunch = False
    while total < hours * 3600.0:
        if not had_lunch and total >= lunch_at:
            segs.append((45 * MIN, 0.0))
            total += 45 * MIN
            had_lunch = True
            continue
        d = float(rng.uniform(1.0, 20.0)) * MIN
        s = float(
            np.round(
                rng.choice([0.25, 0.4, 0.55, 0.7, 0.85, 1.0]) * max_rpm * rng.uniform(0.9, 1.0), -2
            )
        )
        segs.append((d, s))
        segs.append((float(rng.uniform(5, 30)), 0.0))  # tool change
        total += d
        if rng.uniform() < 0.15:
            segs.append((float(rng.uniform(3, 12)) * MIN, 0.0))  # setup, measuring
    return Program(f"job-shop-day-{seed}", tuple(segs))


PROGRAMS: dict[str, Callable[..., Program]] = {
    "paper-calibration": paper_calibration,
    "random-validation": random_validation,
    "job-shop-day": job_shop_day,
}


def program(name: str, max_rpm: float, seed: int | None = None) -> Program:
    try:
        factory = PROGRAMS[name]
    except KeyError as err:
        raise KeyError(f"unknown program {name!r}; choose from {', '.join(PROGRAMS)}") from err
    if seed is None or name == "paper-calibration":
        return factory(max_rpm)
    return factory(max_rpm, seed=seed)
