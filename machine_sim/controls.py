"""The control side of a controller profile, emulated on the virtual machine tool.

A real control does not simply apply the number a PC writes: it takes it in its own unit and
resolution, refuses what it will not take (a value past its limit, a step that would raise an
alarm, a write without the access right), and may move the axis to it at a limited rate.
:class:`EmulatedControl` does the same for any :class:`~cnc_adapters.control_profiles.ControllerProfile`
in front of a :class:`~machine_sim.vcnc.VirtualMachine`, so the virtual workpiece error
shows the offset as the control applies it. Every emulated server (OPC UA, S7, Modbus TCP, ADS,
FOCAS, Haas MDC) hands the written value to :meth:`EmulatedControl.write_raw` and serves the
read-back from :attr:`EmulatedControl.held_raw`, and thermocomp's sign of life (the counter and
the valid flag it writes) to :meth:`EmulatedControl.life_beat`.

Lock-step: call :meth:`EmulatedControl.sync` once the machine's clock has moved on (before or
after ``machine.advance()``); it moves the applied value toward the held one over the clock
time elapsed, at the control's rate, and hands it to the machine.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

from cnc_adapters.control_profiles import ControllerProfile

from .vcnc import OFFSET_LIMIT_UM, VirtualMachine


@dataclass(frozen=True)
class Write:
    """One write the control received: plant time, raw value, and whether it took it."""

    time_s: float
    raw: float
    taken: bool
    reason: str = ""


@dataclass
class EmulatedControl:
    """A profile's control semantics on ``machine`` (see the module docstring).

    ``rate_um_per_s`` overrides the profile's own control-side rate limit (None: the profile's;
    ``math.inf``: none). ``writes`` records every write, taken or refused, in the control's
    units: what a test checks the clamp and the slew limit against."""

    machine: VirtualMachine
    profile: ControllerProfile
    rate_um_per_s: float | None = None
    held_raw: float = 0.0
    applied_um: float = 0.0
    refused: int = 0
    last_refusal: str = ""
    writes: list[Write] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.rate_um_per_s is None:
            self.rate_um_per_s = self.profile.control_rate_um_per_s or math.inf
        self._lock = threading.Lock()
        self._synced_s = self.machine.clock()
        self.machine.apply_offset(self.applied_um)

    @property
    def speed_rpm(self) -> float:
        """The spindle's actual speed, as the control reports it."""
        return self.machine.speed_rpm

    @property
    def held_um(self) -> float:
        """The held value as thermocomp's offset A [um]."""
        return self.profile.units.to_um(self.held_raw)

    def check(self, raw: object) -> str:
        """Why the control would refuse ``raw`` ('' when it takes it)."""
        p = self.profile
        if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not math.isfinite(raw):
            return f"not a finite number: {raw!r}"
        if p.integer and float(raw) != round(float(raw)):
            return f"not a whole count: {raw!r}"
        if abs(raw) > p.limit:
            return f"|{raw:g}| is past the control's limit {p.limit:g}"
        if p.max_step is not None and abs(raw - self.held_raw) > p.max_step:
            return f"a step of {abs(raw - self.held_raw):g} raises the control's alarm (> {p.max_step:g})"
        if abs(raw) / p.scale > OFFSET_LIMIT_UM:
            return f"|{raw:g}| is past the virtual machine's {OFFSET_LIMIT_UM:g} um"
        return ""

    def reset(self) -> None:
        """The control restarts: it holds and applies 0, whatever it held before."""
        with self._lock:
            self.held_raw = 0.0
            self.applied_um = 0.0
            self._synced_s = self.machine.clock()
            self.machine.apply_offset(0.0)

    def write_raw(self, raw: object) -> bool:
        """The control receives ``raw`` in its unit: True when it takes it (it becomes the held
        value), False when it refuses it (the held value stays; :attr:`last_refusal` says why)."""
        with self._lock:
            reason = self.check(raw)
            t = self.machine.plant.time_s
            # a number as written; what check() takes always is one
            value = (
                float(raw)
                if isinstance(raw, (int, float)) and not isinstance(raw, bool)
                else math.nan
            )
            if reason:
                self.refused += 1
                self.last_refusal = reason
                self.writes.append(Write(t, value, False, reason))
                return False
            self.held_raw = value
            self.writes.append(Write(t, value, True))
            return True

    def life_beat(self, counter: object, valid: object) -> None:
        """thermocomp's sign of life as the control's program reads it (the emulated PLC's
        scan, a macro variable written): handed to the machine's watch, where it has one."""
        beat = getattr(self.machine, "life_beat", None)
        if beat is not None:
            beat(counter, valid)

    def sync(self) -> None:
        """Move the applied value toward the held one over the clock time since the last call, at
        the control's rate, and hand it to the machine."""
        with self._lock:
            now = self.machine.clock()
            dt = max(0.0, now - self._synced_s)
            self._synced_s = now
            target = self.held_um
            diff = target - self.applied_um
            rate = self.rate_um_per_s
            assert rate is not None  # resolved by __post_init__
            step = math.inf if rate == math.inf else rate * dt
            self.applied_um = (
                target if abs(diff) <= step else self.applied_um + math.copysign(step, diff)
            )
            if not self.machine.apply_offset(self.applied_um):  # never: check() keeps to its travel
                raise RuntimeError(f"the virtual machine refused {self.applied_um} um")
