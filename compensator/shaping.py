"""Offset shaping: from a predicted elongation S to the offset A = -S written to the CNC.

Kept apart from the model: the model says where the tool tip is, the shaper
decides what the controller may be told and when. :func:`shape` is the pure
transition over an immutable :class:`ShaperState`; :class:`OffsetShaper` owns
that state and is the one shaping path of the runtime and of replay
(:func:`shape_series`). No clock, no I/O.

Order of operations each sample:

1. ``desired = clamp(-S, +-max_offset_um)``;
2. transient policy (paper 001's open idea): when |dn/dt| or a single speed
   step crosses its threshold, a window opens for ``window_s``. In ``hold``
   mode the target is frozen at the current output for the window; in
   ``slow`` mode the target is refreshed only every ``slow_period_s`` (a
   lengthened update cycle). While the window is open, and afterwards until
   the output has caught up, the output moves at ``release_rate_um_per_s``;
3. deadband: no change while |target - output| < ``deadband_um``;
4. slew: |change| <= rate * dt.

Invariants (checked by property tests): the output is finite, within the clamp,
and never changes faster than ``max_rate_um_per_s``, whatever the input. A controller that
holds a value beyond the clamp (an outside write, a lowered clamp) is led into it at the
slew limit: every output is then closer to the clamp than the one before.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from .units import require_dt, require_finite, speed_magnitude_rpm


class Flag(enum.IntFlag):
    """Why the written offset differs from -S. Journaled as an integer."""

    NONE = 0
    CLAMPED = 1
    SLEW_LIMITED = 2
    DEADBAND = 4
    TRANSIENT = 8
    RELEASING = 16


class TransientPolicy(BaseModel):
    """Lengthen the update cycle while the spindle speed changes fast."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    enabled: bool = True
    speed_rate_rpm_per_s: float = Field(500.0, gt=0, description="|dn/dt| threshold")
    speed_step_rpm: float = Field(3000.0, gt=0, description="|n_k - n_{k-1}| threshold")
    mode: Literal["hold", "slow"] = "slow"
    window_s: float = Field(60.0, ge=0, description="window length after the last trigger")
    slow_period_s: float = Field(15.0, gt=0, description="target refresh period in 'slow'")
    release_rate_um_per_s: float | None = Field(
        None, gt=0, description="rate inside and after a window; default max_rate/4"
    )


class ShaperConfig(BaseModel):
    """Limits of the written offset. Units: um and um/s."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    max_offset_um: float = Field(100.0, gt=0, description="clamp: |A| <= max_offset_um")
    max_rate_um_per_s: float = Field(1.0, gt=0, description="slew limit")
    deadband_um: float = Field(0.1, ge=0, description="no write for smaller changes")
    transient: TransientPolicy = TransientPolicy()

    @model_validator(mode="after")
    def _consistent(self) -> ShaperConfig:
        if not all(
            math.isfinite(v) for v in (self.max_offset_um, self.max_rate_um_per_s, self.deadband_um)
        ):
            raise ValueError("shaping limits must be finite")
        if self.deadband_um >= self.max_offset_um:
            raise ValueError("deadband_um must be smaller than max_offset_um")
        rr = self.transient.release_rate_um_per_s
        if rr is not None and rr > self.max_rate_um_per_s:
            raise ValueError("transient.release_rate_um_per_s must not exceed max_rate_um_per_s")
        return self

    @property
    def release_rate_um_per_s(self) -> float:
        rr = self.transient.release_rate_um_per_s
        return self.max_rate_um_per_s / 4 if rr is None else rr


@dataclass(frozen=True, slots=True)
class ShaperState:
    """What the shaper remembers between samples."""

    output_um: float = 0.0
    """Offset the controller holds now."""
    target_um: float = 0.0
    """Latched target the output moves toward."""
    speed_rpm: float | None = None
    window_left_s: float = 0.0
    latch_age_s: float = 0.0
    releasing: bool = False


@dataclass(frozen=True, slots=True)
class ShapedOffset:
    offset_um: float
    write: bool
    flags: Flag
    desired_um: float


def _clamp(config: ShaperConfig, offset_um: float) -> float:
    m = config.max_offset_um
    return min(max(offset_um, -m), m)


def initial_state(config: ShaperConfig, offset_um: float = 0.0) -> ShaperState:
    """State for a controller that currently holds ``offset_um``. A value beyond the clamp (an
    outside write, a clamp lowered by a reload) is kept: the output enters the clamp through
    the slew limit, it never jumps."""
    require_finite("initial offset", offset_um)
    return ShaperState(output_um=offset_um, target_um=_clamp(config, offset_um))


def shape(config: ShaperConfig, state: ShaperState, elongation_um: float, speed_rpm: float,
          dt_s: float) -> tuple[ShaperState, ShapedOffset]:
    """One sample, ``dt_s`` seconds after the previous one: the new state and what to write."""
    require_finite("elongation_um", elongation_um)
    n = speed_magnitude_rpm(speed_rpm)
    dt_s = require_dt(dt_s)
    cfg = config
    pol = cfg.transient
    m = cfg.max_offset_um
    flags = Flag.NONE

    desired = -elongation_um
    if abs(desired) > m:
        desired = math.copysign(m, desired)
        flags |= Flag.CLAMPED

    triggered = False
    if pol.enabled and state.speed_rpm is not None:
        dn = abs(n - state.speed_rpm)
        triggered = dn > pol.speed_step_rpm or (dt_s > 0 and dn / dt_s > pol.speed_rate_rpm_per_s)
    was_open = state.window_left_s > 0
    window = pol.window_s if triggered else max(state.window_left_s - dt_s, 0.0)
    in_transient = triggered or window > 0

    latch_age = state.latch_age_s + dt_s
    if not in_transient:
        target, latch_age = desired, 0.0
    elif triggered and not was_open:
        # entering a window: stop where we are (inside the clamp), whatever the mode
        target, latch_age = _clamp(cfg, state.output_um), 0.0
    elif pol.mode == "slow" and latch_age >= pol.slow_period_s:
        target, latch_age = desired, 0.0
    else:
        target = state.target_um
    if in_transient:
        flags |= Flag.TRANSIENT

    releasing = in_transient or state.releasing
    rate = cfg.release_rate_um_per_s if releasing else cfg.max_rate_um_per_s
    if releasing and not in_transient:
        flags |= Flag.RELEASING

    y = state.output_um
    diff = target - y
    if diff == 0.0 or (abs(diff) < cfg.deadband_um and abs(y) <= m):
        new_y = y
        if diff != 0.0:
            flags |= Flag.DEADBAND
    else:
        limit = rate * dt_s
        step = min(max(diff, -limit), limit)
        if step != diff:
            flags |= Flag.SLEW_LIMITED
        # from beyond the clamp the step itself leads in (the target is inside): no jump
        new_y = min(max(y + step, -m), m) if abs(y) <= m else y + step
    if releasing and not in_transient and abs(desired - new_y) <= max(cfg.deadband_um, 1e-9):
        releasing = False

    new_state = ShaperState(
        output_um=new_y,
        target_um=target,
        speed_rpm=n,
        window_left_s=window,
        latch_age_s=latch_age,
        releasing=releasing,
    )
    return new_state, ShapedOffset(new_y, new_y != y, flags, desired)


class OffsetShaper:
    """Applies a :class:`ShaperConfig` and owns the :class:`ShaperState` between samples."""

    def __init__(self, config: ShaperConfig | None = None, offset_um: float = 0.0):
        self.config = config or ShaperConfig()
        self._state = initial_state(self.config, offset_um)

    @property
    def state(self) -> ShaperState:
        return self._state

    @property
    def output_um(self) -> float:
        """The offset the controller holds now, as far as the shaper knows."""
        return self._state.output_um

    def update(self, elongation_um: float, speed_rpm: float, dt_s: float) -> ShapedOffset:
        """One sample: ``dt_s`` seconds after the previous call."""
        self._state, shaped = shape(self.config, self._state, elongation_um, speed_rpm, dt_s)
        return shaped

    def hold(self, offset_um: float) -> None:
        """The controller holds ``offset_um``, not what the shaper last produced (a write failed
        or was refused, the machine applies its own value): move on from there, through the
        slew limit. The transient window and latched target are kept."""
        held = initial_state(self.config, offset_um).output_um
        if held != self._state.output_um:
            self._state = replace(self._state, output_um=held)


def shape_series(config: ShaperConfig, time_s: np.ndarray, speed_rpm: np.ndarray,
                 elongation_um: np.ndarray, initial_offset_um: float | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The offsets a controller would hold over a whole log, and their flags.

    The runtime's own shaper run sample by sample on the log's time stamps (each sample a
    write that succeeds). ``initial_offset_um`` defaults to the first ideal offset ``-S[0]``,
    a compensator already running when the log starts.
    """
    t = np.asarray(time_s, dtype=float)
    n = np.asarray(speed_rpm, dtype=float)
    s = np.asarray(elongation_um, dtype=float)
    start = -float(s[0]) if initial_offset_um is None else initial_offset_um
    shaper = OffsetShaper(config, start)
    out = np.empty_like(s)
    flags = np.zeros(s.size, dtype=np.int64)
    prev = float(t[0])
    for k in range(s.size):
        res = shaper.update(float(s[k]), float(n[k]), float(t[k]) - prev)
        prev = float(t[k])
        out[k], flags[k] = res.offset_um, int(res.flags)
    return out, flags
