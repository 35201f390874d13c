"""The compensation cycle: read speed, step the model, shape, write, record.

This is the core the service (``thermocomp run``) wraps. It knows the controller only as
an object with ``read_speed()`` and ``write_offset_um()`` and time only through the injected
``clock`` (monotonic seconds; simulated seconds in tests and demos).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from .model import ModelState, ThermalModel
from .shaping import Flag, OffsetShaper, ShaperState


class Controller(Protocol):
    def read_speed(self) -> float: ...

    def write_offset_um(self, offset_um: float) -> None: ...


@dataclass(frozen=True, slots=True)
class Cycle:
    time_s: float
    dt_s: float
    speed_rpm: float
    predicted_um: float
    offset_um: float
    wrote: bool
    flags: Flag


class Compensator:
    """One spindle: model state, shaper state and the last cycle time."""

    def __init__(
        self,
        model: ThermalModel,
        shaper: OffsetShaper,
        controller: Controller,
        clock: Callable[[], float],
        state: ModelState | None = None,
        held_offset_um: float = 0.0,
    ):
        self.model = model
        self.shaper = shaper
        self.controller = controller
        self.clock = clock
        self.state = state or model.cold_state()
        self.shaper_state: ShaperState = shaper.initial(held_offset_um)
        self._last_t: float | None = None

    def cycle(self) -> Cycle:
        now = self.clock()
        dt = 0.0 if self._last_t is None else max(now - self._last_t, 0.0)
        self._last_t = now
        speed = self.controller.read_speed()
        self.state = self.model.step(self.state, speed, dt)
        s = self.state.elongation_um
        self.shaper_state, shaped = self.shaper.update(self.shaper_state, s, speed, dt)
        assert math.isfinite(shaped.offset_um)
        if shaped.write:
            self.controller.write_offset_um(shaped.offset_um)
        return Cycle(now, dt, speed, s, shaped.offset_um, shaped.write, shaped.flags)
