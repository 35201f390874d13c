"""Active cooling: hold the thermal error at a set point by steering the chiller. Pure: no I/O.

Paper 000 (docs/REFERENCES.md) preheats the spindle at a constant coolant temperature; once
the estimated error Ê reaches the reference RITE, a PID sets the coolant-temperature instruction

    u_k = u_k0 + kp·e_k + ki·Σ e·Δt + kd·(e_k − e_{k−1})/Δt,   e = RITE − Ê,

with kp = 2 K/µm, ki = 0, kd = 50 K·s/µm at 1 s. A warmer coolant lets the spindle grow, so
the gains are positive. :class:`CoolingLaw` is that controller made safe to leave running:

- **limits**: the set point stays in ``[min_c, max_c]`` and above the dew point plus a margin
  (condensation in the spindle is worse than any thermal error); the limits win over the rate;
- **a set-point rate limit** (K/min), so the chiller and the spindle are never shocked;
- **whole counts**: the command moves in the chiller's resolution (0.1 °C), toward the
  continuous value, so over any interval it moves at most ``rate × time + one count``;
- **anti-windup** by back-calculation (Åström & Hägglund, *Advanced PID Control*, 2006, §3.5):
  while the output is limited, the integral is pulled back toward what was sent;
- **bumpless hand-over**: at the switch from preheat (or a hold), the bias is set so the first
  closed-loop command equals the one in force;
- **derivative filtering**: the derivative acts on the estimate (a step in RITE gives no kick)
  through a first-order filter of ``derivative_filter_s``;
- **the start rule**: ``start = "rite"`` preheats until Ê ≥ RITE (the paper); ``"immediate"``
  closes the loop at once; after ``idle_release_s`` at rest the loop goes back to preheat;
- **holding**: without an estimate (a failed sensor) or without a chiller, :meth:`CoolingLaw.hold`
  keeps the last command for ``hold_s``, then ramps to the constant ``preheat_c``.

Temperatures in °C, errors in µm, times in s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator

from .errors import ConfigError, NonFiniteInputError

_FROZEN = ConfigDict(frozen=True, extra="forbid")


def _finite(value: float) -> float:
    if not math.isfinite(value):
        raise ValueError(f"must be finite, got {value}")
    return value


Finite = Annotated[float, AfterValidator(_finite)]

# Alduchov & Eskridge (1996), the Magnus form over water, -40..50 degC: a, b [degC]
_MAGNUS_A = 17.625
_MAGNUS_B_C = 243.04


def dew_point_c(air_c: float, relative_humidity_pct: float) -> float:
    """The dew point [°C] of air at ``air_c`` [°C] and ``relative_humidity_pct`` [%], by the
    Magnus formula with Alduchov & Eskridge's constants (error < 0.4 K from −40 to 50 °C)."""
    if (
        not (math.isfinite(air_c) and math.isfinite(relative_humidity_pct))
        or not 0 < relative_humidity_pct <= 100
    ):
        raise NonFiniteInputError(
            f"no dew point from air {air_c} degC, humidity {relative_humidity_pct} %"
        )
    g = math.log(relative_humidity_pct / 100.0) + _MAGNUS_A * air_c / (_MAGNUS_B_C + air_c)
    return _MAGNUS_B_C * g / (_MAGNUS_A - g)


class PidGains(BaseModel):
    """Ideal parallel PID gains on e = RITE − Ê [µm]: u = kp·e + ki·∫e dt + kd·de/dt [K]."""

    model_config = _FROZEN
    kp: Finite = Field(ge=0, description="K/um")
    ki_per_s: Finite = Field(default=0.0, ge=0, description="K/(um s)")
    kd_s: Finite = Field(default=0.0, ge=0, description="K s/um")
    source: str = ""

    @classmethod
    def paper(cls) -> PidGains:
        """Paper 000's gains, kp = 2, ki = 0, kd = 50 at a 1 s sample."""
        return cls(kp=2.0, ki_per_s=0.0, kd_s=50.0, source="paper 000 (kp=2, ki=0, kd=50 at 1 s)")

    def describe(self) -> str:
        return (
            f"kp {self.kp:.3g} K/um, ki {self.ki_per_s:.3g} K/(um s), kd {self.kd_s:.3g} K s/um"
            + (f" ({self.source})" if self.source else "")
        )


class CoolingLaw(BaseModel):
    """The controller's immutable settings; :class:`CoolingState` is kept apart."""

    model_config = _FROZEN
    rite_um: Finite = Field(description="the thermal error to hold [um]")
    preheat_c: Finite = Field(
        description="constant coolant set point in preheat and after a fault [degC]"
    )
    gains: PidGains = Field(default_factory=PidGains.paper)
    min_c: Finite = 10.0
    max_c: Finite = 30.0
    dew_point_c: Finite | None = Field(
        default=None, description="fixed dew point; None: none given"
    )
    dew_margin_k: Finite = Field(default=2.0, ge=0)
    rate_k_per_min: Finite = Field(default=1.0, gt=0, description="set-point rate limit")
    resolution_c: Finite = Field(
        default=0.1, ge=0, description="the chiller's count; 0: continuous"
    )
    derivative_filter_s: Finite = Field(default=10.0, ge=0)
    tracking_s: Finite | None = Field(
        default=None, gt=0, description="anti-windup tracking time; None: Ti"
    )
    start: Literal["rite", "immediate"] = "rite"
    idle_release_s: Finite = Field(default=1800.0, gt=0)
    hold_s: Finite = Field(default=300.0, ge=0)

    @model_validator(mode="after")
    def _consistent(self) -> CoolingLaw:
        if not self.min_c < self.max_c:
            raise ValueError(f"min_c ({self.min_c}) must be below max_c ({self.max_c})")
        low = self.floor_c()
        if not low <= self.preheat_c <= self.max_c:
            raise ValueError(
                f"preheat_c {self.preheat_c} degC is outside the limits {low:.2f}..{self.max_c} degC"
                + (" (dew point + margin)" if low > self.min_c else "")
            )
        return self

    def floor_c(self, dew_point_c: float | None = None) -> float:
        """The lowest set point allowed: ``min_c``, or the dew point plus the margin if higher.
        ``dew_point_c`` (measured) replaces the configured one."""
        dew = self.dew_point_c if dew_point_c is None else dew_point_c
        return self.min_c if dew is None else max(self.min_c, dew + self.dew_margin_k)

    def limits_c(self, dew_point_c: float | None = None) -> tuple[float, float]:
        """(low, high) for the command, in whole counts inside the limits. A dew point so high
        that no set point is safe gives (max, max): the warmest the chiller may go."""
        low, high = self.floor_c(dew_point_c), self.max_c
        r = self.resolution_c
        if r > 0:
            low, high = math.ceil(low / r - 1e-9) * r, math.floor(high / r + 1e-9) * r
        return (min(low, high), high)

    def initial(self, setpoint_c: float | None = None) -> CoolingState:
        """The state at start: preheat, the command at ``setpoint_c`` (what the chiller holds)
        or the preheat constant."""
        value = (
            self.preheat_c if setpoint_c is None or not math.isfinite(setpoint_c) else setpoint_c
        )
        low, high = self.limits_c()
        value = min(max(value, low), high)
        return CoolingState(
            phase="preheat",
            setpoint_c=self._count(value, low, high),
            ramp_c=value,
            bias_c=value,
            derivative_um_per_s=0.0,
            estimate_um=math.nan,
        )

    def _count(self, value: float, low: float, high: float) -> float:
        r = self.resolution_c
        out = round(value / r) * r if r > 0 else value
        return min(max(out, low), high)

    def _move(
        self, state: CoolingState, want_c: float, dt_s: float, dew: float | None
    ) -> tuple[float, float]:
        """The continuous command after the rate limit and the limits, and the count sent."""
        low, high = self.limits_c(dew)
        step = self.rate_k_per_min / 60.0 * dt_s
        ramp = min(max(want_c, state.ramp_c - step), state.ramp_c + step)
        ramp = min(max(ramp, low), high)  # the limits win over the rate
        return ramp, self._count(ramp, low, high)

    def step(
        self,
        state: CoolingState,
        estimate_um: float | None,
        dt_s: float,
        *,
        running: bool = True,
        dew_point_c: float | None = None,
    ) -> CoolingState:
        """Advance by ``dt_s`` with the error estimate ``estimate_um`` (None or non-finite: no
        estimate, so :meth:`hold`); ``running``: the spindle turns; ``dew_point_c``: measured."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise NonFiniteInputError(f"cooling step needs a finite dt > 0, got {dt_s}")
        if estimate_um is None or not math.isfinite(estimate_um):
            return self.hold(state, dt_s, dew_point_c=dew_point_c)
        idle_s = 0.0 if running else state.idle_s + dt_s
        phase = state.phase
        if phase == "closed" and idle_s >= self.idle_release_s:
            phase = "preheat"  # a long rest: back to the constant, and the start rule again
        if phase in ("preheat", "hold") and (
            self.start == "immediate"
            or estimate_um >= self.rite_um
            or (phase == "hold" and state.was_closed)
        ):
            return self._close(state, estimate_um, dt_s, idle_s, dew_point_c)
        if phase != "closed":
            ramp, out = self._move(state, self.preheat_c, dt_s, dew_point_c)
            return replace(
                state,
                phase="preheat",
                setpoint_c=out,
                ramp_c=ramp,
                bias_c=ramp,
                derivative_um_per_s=0.0,
                estimate_um=estimate_um,
                idle_s=idle_s,
                held_s=0.0,
                was_closed=False,
            )
        g = self.gains
        # derivative of the estimate, filtered (backward Euler of tau*dD/dt + D = dE/dt)
        raw = (estimate_um - state.estimate_um) / dt_s if math.isfinite(state.estimate_um) else 0.0
        tf = self.derivative_filter_s
        d = (tf * state.derivative_um_per_s + dt_s * raw) / (tf + dt_s)
        e = self.rite_um - estimate_um
        bias = state.bias_c + g.ki_per_s * e * dt_s
        want = bias + g.kp * e - g.kd_s * d
        ramp, out = self._move(state, want, dt_s, dew_point_c)
        if g.ki_per_s > 0:
            # back-calculation: what the limits took off is fed back into the integral
            tt = self.tracking_s or (g.kp / g.ki_per_s if g.kp > 0 else 60.0)
            # a tracking time at or below one step (kp/ki can underflow to 0) takes it all back
            bias += (ramp - want) * (1.0 if tt <= dt_s else dt_s / tt)
        return replace(
            state,
            phase="closed",
            setpoint_c=out,
            ramp_c=ramp,
            bias_c=bias,
            derivative_um_per_s=d,
            estimate_um=estimate_um,
            idle_s=idle_s,
            held_s=0.0,
            was_closed=True,
        )

    def _close(
        self, state: CoolingState, estimate_um: float, dt_s: float, idle_s: float, dew: float | None
    ) -> CoolingState:
        """Bumpless hand-over: the bias makes the first closed-loop command the one in force."""
        e = self.rite_um - estimate_um
        bias = state.ramp_c - self.gains.kp * e
        ramp, out = self._move(state, bias + self.gains.kp * e, dt_s, dew)
        return replace(
            state,
            phase="closed",
            setpoint_c=out,
            ramp_c=ramp,
            bias_c=bias,
            derivative_um_per_s=0.0,
            estimate_um=estimate_um,
            idle_s=idle_s,
            held_s=0.0,
            was_closed=True,
        )

    def hold(
        self, state: CoolingState, dt_s: float, *, dew_point_c: float | None = None
    ) -> CoolingState:
        """No estimate or no chiller: keep the last command for ``hold_s``, then ramp to the
        preheat constant. The limits still apply (a dew point may have risen)."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise NonFiniteInputError(f"cooling hold needs a finite dt > 0, got {dt_s}")
        held = state.held_s + dt_s
        want = state.ramp_c if held < self.hold_s else self.preheat_c
        ramp, out = self._move(state, want, dt_s, dew_point_c)
        return replace(
            state,
            phase="hold",
            setpoint_c=out,
            ramp_c=ramp,
            held_s=held,
            estimate_um=math.nan,
            derivative_um_per_s=0.0,
            was_closed=state.was_closed and held < self.hold_s,
        )

    def describe(self) -> list[str]:
        low, high = self.limits_c()
        lines = [
            f"hold the thermal error at RITE {self.rite_um:.2f} um; "
            + ("preheat at" if self.start == "rite" else "start at")
            + f" {self.preheat_c:.1f} degC",
            f"PID {self.gains.describe()}; derivative filter {self.derivative_filter_s:g} s",
            f"set point {low:.1f}..{high:.1f} degC"
            + (
                f" (dew point {self.dew_point_c:.1f} + {self.dew_margin_k:g} K)"
                if self.dew_point_c is not None
                else ""
            )
            + f", at most {self.rate_k_per_min:g} K/min, in {self.resolution_c:g} degC counts",
            f"no estimate or no chiller: hold {self.hold_s:g} s, then {self.preheat_c:.1f} degC",
        ]
        return lines


Phase = Literal["preheat", "closed", "hold"]
_PHASES: dict[str, Phase] = {"preheat": "preheat", "closed": "closed", "hold": "hold"}


def _saved_float(value: object) -> float:
    """A number read back from a saved state, as ``float()`` takes it; TypeError otherwise."""
    if isinstance(value, (int, float, str)):
        return float(value)
    raise TypeError(f"{type(value).__name__} is not a number")


@dataclass(frozen=True)
class CoolingState:
    """The controller's runtime state: ``setpoint_c`` is the command to send."""

    phase: Phase
    setpoint_c: float
    ramp_c: float
    """The continuous command behind the whole counts [degC]."""
    bias_c: float
    """u_k0 plus the integral [degC]."""
    derivative_um_per_s: float
    estimate_um: float
    idle_s: float = 0.0
    held_s: float = 0.0
    was_closed: bool = False
    """A hold that started in closed loop returns to it, bumplessly, within ``hold_s``."""

    def to_dict(self) -> dict[str, float | str | bool]:
        return {
            "phase": self.phase,
            "setpoint_c": self.setpoint_c,
            "ramp_c": self.ramp_c,
            "bias_c": self.bias_c,
            "derivative_um_per_s": self.derivative_um_per_s,
            "idle_s": self.idle_s,
            "held_s": self.held_s,
            "was_closed": self.was_closed,
        }

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> CoolingState:
        try:
            phase = str(data["phase"])
            state = cls(
                phase="preheat",  # checked below, with the numbers
                setpoint_c=_saved_float(data["setpoint_c"]),
                ramp_c=_saved_float(data["ramp_c"]),
                bias_c=_saved_float(data["bias_c"]),
                derivative_um_per_s=_saved_float(data["derivative_um_per_s"]),
                estimate_um=math.nan,
                idle_s=_saved_float(data.get("idle_s", 0.0)),
                held_s=_saved_float(data.get("held_s", 0.0)),
                was_closed=bool(data.get("was_closed", False)),
            )
        except (KeyError, TypeError, ValueError) as err:
            raise ConfigError(f"cooling state: {err}") from err
        if phase not in _PHASES or not all(
            math.isfinite(v) for v in (state.setpoint_c, state.ramp_c, state.bias_c)
        ):
            raise ConfigError("cooling state: not a state this version wrote")
        return replace(state, phase=_PHASES[phase])
