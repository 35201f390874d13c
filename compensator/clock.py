"""Time as the layers share it: a clock is any callable that returns seconds. Pure.

The runtime, the recorder and the virtual machine tool take their clock as an argument, so a
test passes a fake one and never sleeps. :class:`ScaledClock` runs faster than the clock it is
given (the virtual machine tool's accelerated time); it reads no clock of its own.
:class:`SteppedClock` moves only when told to: a simulation in lock-step with its client.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol


class Clock(Protocol):
    def __call__(self) -> float: ...


class ScaledClock:
    """``scale`` simulated seconds per second of ``base``, from 0 at construction; the scale can
    change without a jump in simulated time."""

    def __init__(self, scale: float, base: Callable[[], float]):
        if not scale > 0:
            raise ValueError("time scale must be > 0")
        self.scale = float(scale)
        self._base = base
        self._b0 = base()
        self._s0 = 0.0

    def __call__(self) -> float:
        return self._s0 + (self._base() - self._b0) * self.scale

    def set_scale(self, scale: float) -> None:
        if not scale > 0:
            raise ValueError("time scale must be > 0")
        now = self()
        self._b0, self._s0, self.scale = self._base(), now, float(scale)


class SteppedClock:
    """Seconds that move only when :meth:`advance` is called: the virtual machine and the
    service in lock-step, so that no stall of the computer lets the machine run on unobserved."""

    scale = 1.0

    def __init__(self, start_s: float = 0.0):
        self._now = float(start_s)

    def __call__(self) -> float:
        return self._now

    def advance(self, dt_s: float) -> float:
        """Move on by ``dt_s`` (>= 0) seconds; the new time."""
        if not dt_s >= 0:
            raise ValueError(f"a stepped clock moves forward only, not by {dt_s}")
        self._now += float(dt_s)
        return self._now
