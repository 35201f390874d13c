"""Offset shaping: from a predicted elongation S to the offset A = -S written to the CNC.

Kept apart from the model: the model says where the tool tip is, the shaper
decides what the controller may be told and when. :func:`shape` is the pure
transition over an immutable :class:`ShaperState`; :class:`OffsetShaper` owns
that state and is the one shaping path of the runtime and of replay
(:func:`shape_series`). No clock, no I/O.

Order of operations each sample:

1. ``desired = clamp(-S, +-max_offset_um)``;
2. is the tool cutting? The controller's signal where the caller has one (``cutting``), else
   inferred from the speed (:class:`CuttingSignal`): the tool is taken to be cutting once the
   spindle turns and has held its speed, within a tolerance, for ``settle_s``; while the speed
   changes, and at rest, it is not. Before the first sample the spindle counts as settled, so
   a start with the spindle turning is taken as cutting;
3. the transient policy (``transient.mode``):

   - ``dual-slew`` (the default): the output follows ``desired`` at ``max_rate_um_per_s``
     while cutting and at ``not_cutting_rate_um_per_s`` while not, so the elastic step of a
     speed change (centrifugal growth, preload) lands while the spindle accelerates, when the
     tool is clear of the part, and the surface never sees a fast move;
   - ``slow`` and ``hold`` (paper 001's open idea, "lengthen the update cycle"): when |dn/dt|
     or a single speed step crosses its threshold, a window opens for ``window_s``. In
     ``hold`` the target is frozen at the current output for the window; in ``slow`` it is
     refreshed only every ``slow_period_s``. While the window is open, and afterwards until
     the output has caught up, the output moves at ``release_rate_um_per_s``;
   - ``enabled = false``: one slew limit, ``max_rate_um_per_s``, whatever the tool does;

4. deadband: no change while |target - output| < ``deadband_um``;
5. slew: |change| <= rate * dt, the rate of step 3.

Invariants (checked by property tests): the output is finite, within the clamp, never
changes faster than :attr:`ShaperConfig.rate_limit_um_per_s`, and never faster than
``max_rate_um_per_s`` on a sample taken as cutting. The one exception is a controller that
holds a value beyond the clamp (an outside write, a clamp lowered by a reload): no offset
beyond the clamp is ever written, so the first output steps straight to the clamp (flag
``CLAMPED``) and the slew limit applies from there.
"""

from __future__ import annotations

import enum
import functools
import math
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from .errors import NonFiniteInputError
from .units import require_dt, require_finite, speed_magnitude_rpm


class Flag(enum.IntFlag):
    """Why the written offset differs from -S. Journaled as an integer."""

    NONE = 0
    CLAMPED = 1
    SLEW_LIMITED = 2
    DEADBAND = 4
    TRANSIENT = 8
    RELEASING = 16


NOT_CUTTING_RATE_UM_PER_S = 50.0
"""The default slew limit while the tool is not cutting: a 12 um elastic step within 0.3 s."""

POLICIES = ("dual-slew", "longer-cycle", "hold", "slow-slew")
"""The transient policies by name, as reports call them: ``transient.mode`` dual-slew, slow
(the longer update cycle), hold, and ``transient.enabled = false`` (one slow slew limit)."""


class TransientPolicy(BaseModel):
    """What the offset does at speed transients. ``mode``: ``dual-slew`` (fast while the tool
    is not cutting, slow while it is), or paper 001's longer update cycle (``slow``, ``hold``),
    whose window opens when the speed changes fast. ``enabled = false``: one slew limit."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    enabled: bool = True
    mode: Literal["dual-slew", "slow", "hold"] = "dual-slew"
    speed_rate_rpm_per_s: float = Field(
        default=500.0, gt=0, description="slow/hold: |dn/dt| threshold"
    )
    speed_step_rpm: float = Field(
        default=3000.0, gt=0, description="slow/hold: |n_k - n_{k-1}| threshold"
    )
    window_s: float = Field(
        default=60.0, ge=0, description="slow/hold: window length after the last trigger"
    )
    slow_period_s: float = Field(default=15.0, gt=0, description="slow: target refresh period")
    release_rate_um_per_s: float | None = Field(
        default=None,
        gt=0,
        description="slow/hold: rate inside and after a window; default max_rate/4",
    )


class CuttingSignal(BaseModel):
    """Whether the tool is cutting: the controller's signal, or inferred from the speed.

    ``signal``: ``auto`` takes the controller's signal where the adapter has one configured
    (and a log's ``cutting`` column in replay), else infers it; ``controller`` requires one;
    ``speed`` always infers. Inferred: the spindle turns (|n| above ``speed_tolerance_rpm``) and
    has stayed within the tolerance (the larger of ``speed_tolerance_rpm`` and
    ``speed_tolerance_pct`` of the speed) of one speed for ``settle_s``. That is safe only when
    the machine approaches the part later than the first cycle that sees the new speed: keep
    the cycle period well below the time from at-speed to the first cut."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    signal: Literal["auto", "controller", "speed"] = "auto"
    settle_s: float = Field(default=2.0, gt=0, le=3600, description="speed held this long: cutting")
    speed_tolerance_rpm: float = Field(default=30.0, gt=0, le=10000, description="speed band [rpm]")
    speed_tolerance_pct: float = Field(
        default=1.0, ge=0, le=50, description="speed band [% of the speed]"
    )


class ShaperConfig(BaseModel):
    """Limits of the written offset. Units: um and um/s."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    max_offset_um: float = Field(default=100.0, gt=0, description="clamp: |A| <= max_offset_um")
    max_rate_um_per_s: float = Field(
        default=1.0,
        gt=0,
        description="slew limit while cutting (and always, unless the policy is dual-slew)",
    )
    not_cutting_rate_um_per_s: float | None = Field(
        default=None,
        gt=0,
        description="dual-slew: slew limit while the tool is not cutting; default "
        f"{NOT_CUTTING_RATE_UM_PER_S:g} um/s, or max_rate_um_per_s if that is higher",
    )
    deadband_um: float = Field(default=0.1, ge=0, description="no write for smaller changes")
    resolution_um: float = Field(
        default=0.0,
        ge=0,
        description="one count of the controller's value [um] (0: continuous): the "
        "output moves in whole counts, a count only once the slew limit allows a whole one since "
        "the last move (a controller profile sets it)",
    )
    transient: TransientPolicy = TransientPolicy()
    cutting: CuttingSignal = CuttingSignal()

    @model_validator(mode="after")
    def _consistent(self) -> ShaperConfig:
        if not all(
            math.isfinite(v) for v in (self.max_offset_um, self.max_rate_um_per_s, self.deadband_um)
        ):
            raise ValueError("shaping limits must be finite")
        if self.deadband_um >= self.max_offset_um:
            raise ValueError("deadband_um must be smaller than max_offset_um")
        if not math.isfinite(self.resolution_um) or self.resolution_um >= self.max_offset_um:
            raise ValueError("resolution_um must be smaller than max_offset_um")
        rr = self.transient.release_rate_um_per_s
        if rr is not None and rr > self.max_rate_um_per_s:
            raise ValueError("transient.release_rate_um_per_s must not exceed max_rate_um_per_s")
        nc = self.not_cutting_rate_um_per_s
        if nc is not None and nc < self.max_rate_um_per_s:
            raise ValueError(
                "not_cutting_rate_um_per_s must not be below max_rate_um_per_s "
                "(the slew limit while cutting)"
            )
        return self

    @property
    def fast_rate_um_per_s(self) -> float:
        """The slew limit while the tool is not cutting (dual-slew)."""
        nc = self.not_cutting_rate_um_per_s
        return max(NOT_CUTTING_RATE_UM_PER_S, self.max_rate_um_per_s) if nc is None else nc

    @property
    def release_rate_um_per_s(self) -> float:
        rr = self.transient.release_rate_um_per_s
        return self.max_rate_um_per_s / 4 if rr is None else rr

    @property
    def policy(self) -> str:
        """The transient policy by name (one of :data:`POLICIES`)."""
        t = self.transient
        if not t.enabled:
            return "slow-slew"
        return {"dual-slew": "dual-slew", "slow": "longer-cycle", "hold": "hold"}[t.mode]

    @property
    def rate_limit_um_per_s(self) -> float:
        """The fastest the output ever moves."""
        return self.fast_rate_um_per_s if self.policy == "dual-slew" else self.max_rate_um_per_s

    def with_policy(self, policy: str) -> ShaperConfig:
        """The same limits under another transient policy (:data:`POLICIES`), for comparisons."""
        if policy not in POLICIES:
            raise ValueError(f"unknown policy {policy!r}; one of {', '.join(POLICIES)}")
        changes: dict[str, dict[str, Any]] = {
            "slow-slew": {"enabled": False},
            "dual-slew": {"enabled": True, "mode": "dual-slew"},
            "longer-cycle": {"enabled": True, "mode": "slow"},
            "hold": {"enabled": True, "mode": "hold"},
        }
        change = changes[policy]
        return self.model_copy(update={"transient": self.transient.model_copy(update=change)})


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
    settle_speed_rpm: float | None = None
    """The speed the spindle is holding (cutting inference); None before the first sample."""
    settled_s: float = 0.0
    """How long it has held it."""
    slew_credit_um: float = 0.0
    """With a resolution: the slew allowance gathered since the last move, up to one count."""


@dataclass(frozen=True, slots=True)
class ShapedOffset:
    offset_um: float
    write: bool
    flags: Flag
    desired_um: float
    cutting: bool = False
    """Whether the sample was taken as cutting (the controller's signal, or inferred)."""
    rate_um_per_s: float = 0.0
    """The slew limit in force for this sample."""
    state: str = "tracking"
    """The policy's state: dual-slew ``cutting`` or ``clear`` (not cutting: the fast limit);
    slow/hold ``tracking``, ``window`` or ``releasing``; slow slew only ``tracking``."""


def _clamp(config: ShaperConfig, offset_um: float) -> float:
    m = config.max_offset_um
    return min(max(offset_um, -m), m)


def initial_state(config: ShaperConfig, offset_um: float = 0.0) -> ShaperState:
    """State for a controller that currently holds ``offset_um``. A value beyond the clamp (an
    outside write, a clamp lowered by a reload) is kept as what it holds; the next output is
    within the clamp (see the module's invariants)."""
    require_finite("initial offset", offset_um)
    return ShaperState(output_um=offset_um, target_um=_clamp(config, offset_um))


_DUAL, _WINDOWED, _ONE = 0, 1, 2  # how the policy moves the offset: by the cutting state,
# in windows opened by speed changes (slow, hold), or at one rate
_NO_FLAGS, _CLAMPED, _SLEWED, _DEADBAND = (
    int(Flag.NONE),
    int(Flag.CLAMPED),
    int(Flag.SLEW_LIMITED),
    int(Flag.DEADBAND),
)
_TRANSIENT, _RELEASING = int(Flag.TRANSIENT), int(Flag.RELEASING)


@dataclass(frozen=True, slots=True)
class _Limits:
    """A :class:`ShaperConfig` as plain numbers, read once rather than at every sample."""

    clamp: float
    rate: float
    fast_rate: float
    release_rate: float
    deadband: float
    kind: int
    hold: bool
    speed_rate: float
    speed_step: float
    window_s: float
    slow_period_s: float
    settle_s: float
    tolerance_rpm: float
    tolerance_frac: float
    resolution: float


@functools.lru_cache(maxsize=64)  # a frozen config: read once, not at every runtime cycle
def _limits(config: ShaperConfig) -> _Limits:
    t, c = config.transient, config.cutting
    kind = _ONE if not t.enabled else _DUAL if t.mode == "dual-slew" else _WINDOWED
    return _Limits(
        config.max_offset_um,
        config.max_rate_um_per_s,
        config.fast_rate_um_per_s,
        config.release_rate_um_per_s,
        config.deadband_um,
        kind,
        t.mode == "hold",
        t.speed_rate_rpm_per_s,
        t.speed_step_rpm,
        t.window_s,
        t.slow_period_s,
        c.settle_s,
        c.speed_tolerance_rpm,
        c.speed_tolerance_pct / 100.0,
        config.resolution_um,
    )


_WORDS = ("cutting", "clear", "window", "releasing", "tracking")

_State = tuple[float, float, float | None, float, float, bool, float | None, float, float]
"""ShaperState's fields, in order."""


def _advance(
    lim: _Limits, st: _State, elongation_um: float, n: float, dt: float, cutting: bool | None
) -> tuple[_State, int, bool, float, int, float]:
    """One sample over checked numbers (``n`` the speed's magnitude): the new state and the
    flags, the cutting state, the slew limit, the index of the policy's word and the desired
    (clamped) offset. The one transition of the shaper: :func:`shape` and :func:`shape_series`
    both run it."""
    y, held_target, last_n, window_left, latch_age, releasing, ref, settled, credit = st
    m = lim.clamp
    flags = _NO_FLAGS
    desired = -elongation_um
    if desired > m:
        desired, flags = m, _CLAMPED
    elif desired < -m:
        desired, flags = -m, _CLAMPED

    # the cutting state inferred from the speed: held within the band for settle_s, and turning
    tol = (
        lim.tolerance_rpm if lim.tolerance_rpm > lim.tolerance_frac * n else lim.tolerance_frac * n
    )
    if ref is None:
        ref, settled = n, lim.settle_s  # before any sample: settled (it may be cutting)
    elif abs(n - ref) > tol:
        ref, settled = n, 0.0
    else:
        settled += dt
    is_cutting = (
        (n > lim.tolerance_rpm and settled >= lim.settle_s) if cutting is None else bool(cutting)
    )

    window = 0.0
    in_transient = False
    if lim.kind == _DUAL:
        target, latch_age, releasing = desired, 0.0, False
        rate, word = (lim.rate, 0) if is_cutting else (lim.fast_rate, 1)
    else:
        triggered = False
        if lim.kind == _WINDOWED and last_n is not None:
            dn = abs(n - last_n)
            triggered = dn > lim.speed_step or (dt > 0 and dn / dt > lim.speed_rate)
        was_open = window_left > 0
        window = lim.window_s if triggered else max(window_left - dt, 0.0)
        in_transient = triggered or window > 0
        latch_age += dt
        if not in_transient:
            target, latch_age = desired, 0.0
        elif triggered and not was_open:
            # entering a window: stop where we are (inside the clamp), whatever the mode
            target, latch_age = min(max(y, -m), m), 0.0
        elif not lim.hold and latch_age >= lim.slow_period_s:
            target, latch_age = desired, 0.0
        else:
            target = held_target
        if in_transient:
            flags |= _TRANSIENT
        releasing = in_transient or releasing
        rate = lim.release_rate if releasing else lim.rate
        if releasing and not in_transient:
            flags |= _RELEASING
        word = 2 if in_transient else 3 if releasing else 4

    diff = target - y
    inside = -m <= y <= m
    q = lim.resolution
    if (
        diff == 0.0
        or (abs(diff) < lim.deadband and inside)
        or (q and abs(diff) < q * 0.5 and inside)
    ):
        new_y = y
        credit = 0.0
        if diff != 0.0:
            flags |= _DEADBAND
    else:
        limit = rate * dt + credit
        step = diff if -limit <= diff <= limit else (limit if diff > 0 else -limit)
        if step != diff:
            flags |= _SLEWED
        new_y = min(max(y + step, -m), m)
        if not inside:
            # a value beyond the clamp is none we wrote (an outside write, a lowered clamp): the
            # write goes straight to the clamp, on the grid toward zero, and on at the slew limit
            flags |= _CLAMPED
            if q:
                new_y, credit = math.trunc(new_y / q) * q, 0.0
        elif q:
            new_y, credit = _on_grid(y, new_y, q, limit, m)
    if releasing and not in_transient and abs(desired - new_y) <= max(lim.deadband, 0.5 * q, 1e-9):
        releasing = False
    return (
        (new_y, target, n, window, latch_age, releasing, ref, settled, credit),
        flags,
        is_cutting,
        rate,
        word,
        desired,
    )


def _on_grid(y: float, new_y: float, q: float, limit: float, m: float) -> tuple[float, float]:
    """A move from ``y`` toward ``new_y`` in whole counts of ``q``: the count nearest ``new_y``
    where the slew ``limit`` and the clamp ``m`` allow it, else the nearest on ``y``'s side (never
    past ``new_y``); and the slew credit left (the allowance gathered while no whole count fitted,
    up to one count; 0 after a move, so each move is within the rate times the time since the
    last one)."""
    eps = 1e-9 * q
    g = round(new_y / q) * q
    if abs(g - y) > eps and abs(g - y) <= limit + eps and abs(g) <= m + eps:
        return min(max(g, y - limit, -m), y + limit, m), 0.0  # float noise never lands past a limit
    if new_y > y:
        g = math.floor(new_y / q + 1e-9) * q
        if g > y + eps:
            return min(g, new_y), 0.0
    elif new_y < y:
        g = math.ceil(new_y / q - 1e-9) * q
        if g < y - eps:
            return max(g, new_y), 0.0
    return y, min(limit, q)


def _as_tuple(state: ShaperState) -> _State:
    return (
        state.output_um,
        state.target_um,
        state.speed_rpm,
        state.window_left_s,
        state.latch_age_s,
        state.releasing,
        state.settle_speed_rpm,
        state.settled_s,
        state.slew_credit_um,
    )


def shape(
    config: ShaperConfig,
    state: ShaperState,
    elongation_um: float,
    speed_rpm: float,
    dt_s: float,
    cutting: bool | None = None,
) -> tuple[ShaperState, ShapedOffset]:
    """One sample, ``dt_s`` seconds after the previous one: the new state and what to write.
    ``cutting``: the controller's signal, or None to infer it from the speed."""
    s = require_finite("elongation_um", elongation_um)
    n = speed_magnitude_rpm(speed_rpm)
    dt_s = require_dt(dt_s)
    new, flags, is_cutting, rate, word, desired = _advance(
        _limits(config), _as_tuple(state), s, n, dt_s, cutting
    )
    y = state.output_um
    return ShaperState(*new), ShapedOffset(
        new[0], new[0] != y, Flag(flags), desired, is_cutting, rate, _WORDS[word]
    )


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

    def update(
        self, elongation_um: float, speed_rpm: float, dt_s: float, cutting: bool | None = None
    ) -> ShapedOffset:
        """One sample: ``dt_s`` seconds after the previous call; ``cutting`` the controller's
        signal, or None to infer it from the speed."""
        self._state, shaped = shape(
            self.config, self._state, elongation_um, speed_rpm, dt_s, cutting
        )
        return shaped

    def follow(self, other: OffsetShaper) -> None:
        """Go on with ``other``'s view of the speed (a reload): the speed it was settling at and
        for how long, and the last speed, so that the cutting state does not restart."""
        o = other.state
        self._state = replace(
            self._state,
            speed_rpm=o.speed_rpm,
            settle_speed_rpm=o.settle_speed_rpm,
            settled_s=o.settled_s,
        )

    def hold(self, offset_um: float) -> None:
        """The controller holds ``offset_um``, not what the shaper last produced (a write failed
        or was refused, the machine applies its own value): move on from there, through the
        slew limit. The transient window, latched target and cutting inference are kept."""
        held = initial_state(self.config, offset_um).output_um
        if held != self._state.output_um:
            self._state = replace(self._state, output_um=held)


@dataclass(frozen=True)
class ShapedSeries:
    """What the runtime's shaper does over a whole log, sample by sample."""

    offset_um: np.ndarray
    flags: np.ndarray
    cutting: np.ndarray
    """bool: taken as cutting (the log's signal, or inferred)."""
    rate_um_per_s: np.ndarray
    """The slew limit in force."""


def shape_series(
    config: ShaperConfig,
    time_s: np.ndarray,
    speed_rpm: np.ndarray,
    elongation_um: np.ndarray,
    initial_offset_um: float | None = None,
    cutting: np.ndarray | None = None,
) -> ShapedSeries:
    """The offsets a controller would hold over a whole log, with their flags, cutting state
    and slew limit.

    The runtime's own shaper run sample by sample on the log's time stamps (each sample a
    write that succeeds). ``initial_offset_um`` defaults to the first ideal offset ``-S[0]``,
    a compensator already running when the log starts. ``cutting`` is the controller's signal
    per sample (1 or 0; NaN: none at that sample, inferred from the speed); None infers it from
    the speed throughout, as the runtime does without a signal.
    """
    t = np.asarray(time_s, dtype=float)
    n = np.abs(np.asarray(speed_rpm, dtype=float))
    s = np.asarray(elongation_um, dtype=float)
    sizes = {t.size, n.size, s.size} | (set() if cutting is None else {np.size(cutting)})
    if len(sizes) != 1:
        raise NonFiniteInputError(f"shape_series: the series differ in length ({sorted(sizes)})")
    dt = np.diff(t, prepend=t[0])
    for name, values in (("time_s", t), ("speed_rpm", n), ("elongation_um", s)):
        if not np.isfinite(values).all():
            raise NonFiniteInputError(
                f"{name} is not finite at sample {int(np.argmin(np.isfinite(values)))}"
            )
    if (dt < 0).any():
        raise NonFiniteInputError(f"time goes back at sample {int(np.argmax(dt < 0))}")
    if cutting is None:
        cut: list[bool | None] = [None] * s.size
    else:
        raw = np.asarray(cutting, dtype=float)
        bad = ~(np.isnan(raw) | (raw == 0) | (raw == 1))
        if bad.any():
            raise NonFiniteInputError(
                f"shape_series: cutting is {raw[bad][0]!r} at sample "
                f"{int(np.argmax(bad))}: 1, 0, or NaN (infer it from the speed)"
            )
        cut = [None if v != v else v == 1.0 for v in raw.tolist()]
    start = -float(s[0]) if initial_offset_um is None else initial_offset_um
    lim = _limits(config)
    st = _as_tuple(initial_state(config, start))
    out = np.empty_like(s)
    flags = np.zeros(s.size, dtype=np.int64)
    taken = np.zeros(s.size, dtype=bool)
    rate = np.empty_like(s)
    for k, (sk, nk, dk, ck) in enumerate(zip(s.tolist(), n.tolist(), dt.tolist(), cut)):
        st, flags[k], taken[k], rate[k], _, _ = _advance(lim, st, sk, nk, dk, ck)
        out[k] = st[0]
    return ShapedSeries(out, flags, taken, rate)
