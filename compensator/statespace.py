"""A linear state-space model of the elongation, driven by speed and measured inputs. Pure: no I/O.

The form the identification (``calibration.estimators.ridge_bank``, ``docs/IDENTIFICATION.md``) fits::

    S      = c + D.v + sum_j x_j + r                      [um]
    dx_j/dt = (B_j.v - x_j) / tau_j                        one first-order state per time constant
    dr/dt   = -r / max(tau)                                what the inputs do not explain at a start
    v       = [n, n^2, u_1 - ref_1, ..., u_m - ref_m]      n = |speed| in krpm, u in its own unit

``c`` is a constant (``offset_um``), ``D`` a static (instantaneous) feed-through and ``B`` the
drive of each state. Stepping is the exact zero-order hold with v held over the step, so the
model steps at any Δt. The references ``ref_i`` are absolute, fixed at the fit and stored here:
a prediction never depends on where a log starts, once the states have settled.

Starting (:meth:`StateSpaceModel.start`) puts every state at its equilibrium with the current
speed and inputs. A measured elongation, when given, goes to ``r`` only: the part of the state
that the speed and inputs do not explain, which decays with the model's slowest time constant.
It never goes into the speed states.

Checked at construction (and so at load): finite coefficients with matching shapes; every time
constant between the sample period of the fit and :data:`MAX_TAU_S`; the steady elongation the
gains imply over the trained speed and input ranges at most :data:`GAIN_BOUND` times the largest
measured. A model that fails is a one-line :class:`~compensator.errors.ModelError`.

Outside the range an input had in calibration the model does what the fit chose by data on
forward splits (``extrapolation``): ``linear``, the gains carried on up to the valid range;
``clip``, each input held at the end of its trained range; ``blend``, the prediction moved
toward the speed-only fallback's as the inputs leave the range, all of it at ``blend_span``
spans out (:func:`compensator.expected.distance_outside`). Past the valid range every policy
holds the input at that range's end (a sensor fault, which the runtime catches first).

It implements :class:`~compensator.predictor.Predictor`; ``fallback`` is the speed-only model the
runtime uses when an input fails.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any, Final, Literal, Union

import numpy as np
from pydantic import Field, field_validator, model_validator

from .errors import ModelError
from .expected import distance_outside
from .filters import Steps, decay, lag, lag_step, series
from .model import MODEL_FORMAT, ThermalModel
from .modelbase import Channel, ModelBase, saved_numbers, speed_range
from .units import SPEED_SCALE_RPM, require_dt, require_finite, speed_magnitude_rpm

STATE_SPACE_FORMAT: Final = "thermocomp.state-space-model/1"

MAX_TAU_S = 10 * 86400.0
"""Longest time constant a model may hold: ten days. Slower cannot be told from drift."""
GAIN_BOUND = 10.0
"""The steady elongation the gains imply over the trained ranges: at most this many times the
largest elongation measured in calibration."""
SPEED_CLIP = 2.0
"""|speed| is clipped to this many times the calibrated maximum inside the model, so any finite
input gives a finite output (above the range the runtime raises an extrapolation alarm anyway)."""


def _finite(values: Any) -> bool:
    return all(math.isfinite(v) for v in values)


def steady_range_um(
    gains: Any, speed_max_rpm: float, inputs: list[tuple[float, tuple[float, float]]]
) -> float:
    """Largest |steady elongation change| that steady gains on [n, n^2, inputs...] imply over
    0..``speed_max_rpm``, each input (reference, (min, max)) at the worse end of its range [um]:
    the bound the fit and the model file are both held to."""
    g = np.asarray(gains, dtype=float)
    n = np.linspace(0.0, speed_max_rpm / SPEED_SCALE_RPM, 201)
    total = float(np.max(np.abs(g[0] * n + g[1] * n * n)))
    for gi, (ref, (lo, hi)) in zip(g[2:], inputs):
        total += abs(float(gi)) * max(abs(lo - ref), abs(hi - ref))
    return total


class InputChannel(Channel):
    """A measured input (a temperature...) as the model uses it."""

    reference: float = Field(description="absolute reference, fixed at the fit: the training mean")
    trained_range: tuple[float, float] = Field(description="(min, max) seen in calibration")

    @model_validator(mode="after")
    def _ranges(self) -> InputChannel:
        values = (self.reference, *self.trained_range, *self.valid_range)
        if not _finite(values):
            raise ValueError(f"input {self.name}: reference and ranges must be finite")
        (tlo, thi), (vlo, vhi) = self.trained_range, self.valid_range
        if not (vlo <= tlo <= thi <= vhi):
            raise ValueError(
                f"input {self.name}: need valid min <= trained min <= trained max <= valid max"
            )
        return self


Extrapolation = Literal["linear", "clip", "blend"]
EXTRAPOLATIONS: tuple[Extrapolation, ...] = ("linear", "clip", "blend")

Fallback = Annotated[Union["StateSpaceModel", ThermalModel], Field(discriminator="format")]


class StateSpaceModel(ModelBase):
    """Immutable coefficients; the module docstring gives the equations. Gains per krpm (n),
    per krpm² (n²) and per input unit."""

    format: Literal["thermocomp.state-space-model/1"] = STATE_SPACE_FORMAT
    form: str = Field("ridge", description="how it was fitted: ridge, exp-baseline, ...")
    fitted_dt_s: float = Field(gt=0, description="median sample period of the calibration data [s]")
    speed_range_rpm: tuple[float, float] = Field(
        description="(min, max) |speed| seen in calibration [rpm]"
    )
    taus_s: tuple[float, ...] = Field(min_length=1, description="time constant of each state [s]")
    drive_um: tuple[tuple[float, ...], ...] = Field(
        description="B: per state, the gains on [n, n^2, inputs...] [um per krpm**p or per unit]"
    )
    feedthrough_um: tuple[float, ...] = Field(description="D: static gains on [n, n^2, inputs...]")
    offset_um: float = Field(0.0, description="c: constant elongation [um]")
    inputs: tuple[InputChannel, ...] = ()
    max_measured_um: float = Field(
        gt=0, description="largest |elongation| measured in calibration [um]"
    )
    fallback: Fallback | None = Field(None, description="speed-only model used when an input fails")
    extrapolation: Extrapolation = Field(
        "linear",
        description="outside the trained input range: "
        "linear, clip (hold at the trained end) or blend (toward the fallback)",
    )
    blend_span: float = Field(
        1.0,
        gt=0,
        le=1,
        description="blend: spans outside the trained range at which the fallback alone is used",
    )

    @field_validator("speed_range_rpm")
    @classmethod
    def _range(cls, value: tuple[float, float]) -> tuple[float, float]:
        return speed_range(value, positive_max=True)

    @model_validator(mode="after")
    def _sane(self) -> StateSpaceModel:
        width = 2 + len(self.inputs)
        if len(self.drive_um) != len(self.taus_s):
            raise ModelError(
                f"{len(self.drive_um)} drive rows for {len(self.taus_s)} time constants"
            )
        for row in (*self.drive_um, self.feedthrough_um):
            if len(row) != width:
                raise ModelError(
                    f"a gain row has {len(row)} entries; speed n, n^2 and "
                    f"{len(self.inputs)} input(s) need {width}"
                )
        gains = (
            [v for row in self.drive_um for v in row] + list(self.feedthrough_um) + [self.offset_um]
        )
        if not _finite(gains) or not math.isfinite(self.max_measured_um):
            raise ModelError("gains must be finite")
        for tau in self.taus_s:
            if not (math.isfinite(tau) and self.fitted_dt_s <= tau <= MAX_TAU_S):
                raise ModelError(
                    f"time constant {tau:g} s is outside {self.fitted_dt_s:g} s (the "
                    f"sample period) .. {MAX_TAU_S / 86400:g} days"
                )
        steady = self.steady_range_um()
        if not steady <= GAIN_BOUND * self.max_measured_um:
            raise ModelError(
                f"the gains imply a steady elongation of {steady:.4g} um, over "
                f"{GAIN_BOUND:g} x the largest measured ({self.max_measured_um:.4g} um)"
            )
        if self.fallback is not None and self.fallback.input_names:
            raise ModelError("the fallback must be a speed-only model")
        if self.fallback is not None and not self.inputs:
            raise ModelError("a speed-only model has no fallback")
        if self.inputs and self.fallback is None:
            raise ModelError("a model with inputs needs a speed-only fallback")
        if self.extrapolation != "linear" and not self.inputs:
            raise ModelError(f"extrapolation {self.extrapolation!r} is for a model with inputs")
        return self

    # -- derived quantities -----------------------------------------------------------

    @property
    def order(self) -> int:
        return len(self.taus_s)

    @property
    def channels(self) -> tuple[InputChannel, ...]:
        return self.inputs

    @property
    def _b(self) -> np.ndarray:
        return np.array(self.drive_um, dtype=float).reshape(len(self.taus_s), 2 + len(self.inputs))

    @property
    def _d(self) -> np.ndarray:
        return np.array(self.feedthrough_um, dtype=float)

    @property
    def _slowest_s(self) -> float:
        return max(self.taus_s)

    def total_gains(self) -> np.ndarray:
        """Steady gains on [n, n^2, inputs...]: the feed-through plus every state's drive."""
        gains: np.ndarray = self._d + self._b.sum(axis=0)
        return gains

    def steady_range_um(self) -> float:
        """Largest |steady elongation change| the gains imply over the trained ranges."""
        return steady_range_um(
            self.total_gains(),
            self.speed_range_rpm[1],
            [(c.reference, c.trained_range) for c in self.inputs],
        )

    def steady_state_um(self, speed_rpm: float, inputs: Mapping[str, float] | None = None) -> float:
        """Equilibrium elongation with ``speed_rpm`` held, inputs at ``inputs`` (default: at
        their references) [um]."""
        v = self._signals(speed_rpm, inputs or {c.name: c.reference for c in self.inputs})
        return float(self.offset_um + self.total_gains() @ v)

    def time_constants_s(self, speed_rpm: float = 0.0) -> tuple[float, ...]:
        return tuple(self.taus_s)

    def outside_trained(self, values: Mapping[str, float]) -> str | None:
        """Which input lies outside the range seen in calibration (valid, but extrapolated)."""
        for c in self.inputs:
            v = values.get(c.name)
            lo, hi = c.trained_range
            if v is not None and math.isfinite(v) and not lo <= v <= hi:
                return f"{c.name}: {v:g} {c.unit} is outside the trained {lo:g}..{hi:g}"
        return None

    def _held_range(self, c: InputChannel) -> tuple[float, float]:
        """Where an input is held: its trained range under ``clip``, else its valid range."""
        return c.trained_range if self.extrapolation == "clip" else c.valid_range

    def _limits(self) -> np.ndarray:
        """(inputs, 2): where each input is held, by the extrapolation policy."""
        ranges = [self._held_range(c) for c in self.inputs]
        return np.array(ranges, dtype=float).reshape(-1, 2)

    def distance_outside(self, values: Mapping[str, Any]) -> np.ndarray | float:
        """How far ``values`` (one value or one series per input) lie outside the trained range,
        in spans (:func:`compensator.expected.distance_outside`); 0 for a speed-only model."""
        if not self.inputs:
            return 0.0
        u = np.column_stack([np.atleast_1d(np.asarray(values[c.name], float)) for c in self.inputs])
        d = distance_outside(
            u,
            np.array([c.trained_range[0] for c in self.inputs]),
            np.array([c.trained_range[1] for c in self.inputs]),
        )
        return float(d[0]) if np.ndim(values[self.inputs[0].name]) == 0 else d

    def _weight(self, inputs: Mapping[str, float] | None) -> float:
        """The fallback's share of a blended prediction."""
        if self.extrapolation != "blend" or inputs is None:
            return 0.0
        return min(1.0, float(self.distance_outside(inputs)) / self.blend_span)

    def _signals(self, speed_rpm: float, inputs: Mapping[str, float] | None) -> np.ndarray:
        n = (
            min(speed_magnitude_rpm(speed_rpm), SPEED_CLIP * self.speed_range_rpm[1])
            / SPEED_SCALE_RPM
        )
        v = [n, n * n]
        for c in self.inputs:
            if inputs is None or c.name not in inputs:
                raise ModelError(f"the model needs input {c.name!r}")
            u = require_finite(c.name, float(inputs[c.name]))
            lo, hi = self._held_range(c)
            v.append(min(max(u, lo), hi) - c.reference)
        return np.array(v)

    # -- the Predictor interface -----------------------------------------------------------

    def start(
        self,
        elongation_um: float | None,
        speed_rpm: float,
        inputs: Mapping[str, float] | None = None,
        references: Mapping[str, float] | None = None,
    ) -> StateSpaceState:
        """Every state at equilibrium with ``speed_rpm`` and ``inputs``; ``elongation_um`` (None:
        none measured) minus that equilibrium goes to the unexplained part, which decays with the
        slowest time constant. ``references`` is ignored: this model's are absolute and stored."""
        v = self._signals(speed_rpm, inputs)
        x = self._b @ v
        static = float(self.offset_um + self._d @ v)
        residual = 0.0
        if elongation_um is not None:
            residual = require_finite("elongation_um", elongation_um) - (math.fsum(x) + static)
        if self.extrapolation != "blend" or self.fallback is None:
            return StateSpaceState(tuple(float(e) for e in x), residual, static)
        # both start at a measured elongation, so the blend starts there too
        return StateSpaceState(
            tuple(float(e) for e in x),
            residual,
            static,
            self.fallback.start(elongation_um, speed_rpm),
            self._weight(inputs),
        )

    def step(
        self,
        state: StateSpaceState,
        speed_rpm: float,
        dt_s: float,
        inputs: Mapping[str, float] | None = None,
    ) -> StateSpaceState:
        """Advance by ``dt_s`` with the speed and inputs held (exact zero-order hold)."""
        dt_s = require_dt(dt_s)
        if len(state.states_um) != self.order:
            raise ModelError(f"state has {len(state.states_um)} states, the model {self.order}")
        v = self._signals(speed_rpm, inputs)
        x = tuple(
            lag_step(x, float(u), dt_s, tau)
            for x, u, tau in zip(state.states_um, self._b @ v, self.taus_s)
        )
        r = lag_step(state.residual_um, 0.0, dt_s, self._slowest_s)
        if self.extrapolation != "blend" or self.fallback is None:
            return StateSpaceState(x, r, float(self.offset_um + self._d @ v))
        # the fallback's own state, of the fallback's type (a start of it, or what it stepped to)
        fb: Any = (
            state.fallback if state.fallback is not None else self.fallback.start(state.own_um, 0.0)
        )
        return StateSpaceState(
            x,
            r,
            float(self.offset_um + self._d @ v),
            self.fallback.step(fb, speed_rpm, dt_s),
            self._weight(inputs),
        )

    def simulate_um(
        self,
        speed_rpm: np.ndarray,
        time_s: np.ndarray,
        inputs: Mapping[str, np.ndarray] | None = None,
        initial_um: float | None = None,
    ) -> np.ndarray:
        """Free run over a whole log, ``speed_rpm[k]`` held over ``(time_s[k-1], time_s[k]]``;
        states at equilibrium with the first sample, ``initial_um`` as in :meth:`start`.

        The same exact zero-order-hold step as :meth:`step` at every sample, whatever its Δt,
        computed a block of samples at a time so that everything stays in cache: one matrix
        product gives the static part and every state's drive, then every state's recursion
        in closed form (:class:`_Recursion`)."""
        t = series("time_s", time_s)
        size = t.size
        if size == 0:
            raise ModelError("cannot simulate an empty log")
        sp = series("speed_rpm", speed_rpm, size)
        logged = []
        for c in self.inputs:
            if inputs is None or c.name not in inputs:
                raise ModelError(f"the model needs input {c.name!r}, which the log lacks")
            u = np.asarray(inputs[c.name], dtype=float)
            if u.shape != (size,):
                series(c.name, u, size)  # says what is wrong with it
            logged.append(u)
        # rows: the static part, then each state's drive; the references, constant, go into
        # the constant (a filter passes a constant unchanged)
        gains = np.vstack([self._d, self._b])
        refs = np.array([c.reference for c in self.inputs])
        constant = self.offset_um - float((gains[:, 2:] @ refs).sum())
        valid = self._limits()
        lo, hi = valid[:, :1], valid[:, 1:]
        cap = SPEED_CLIP * self.speed_range_rpm[1]
        rec = _Recursion(self.taus_s, t)
        out = np.empty(size)
        v = np.empty((gains.shape[1], min(_BLOCK, size)))
        y = np.empty((gains.shape[0], v.shape[1]))
        with np.errstate(over="ignore", invalid="ignore"):  # the states' overflow is redone
            for s in range(0, size, _BLOCK):  # the signals [n, n^2, inputs...] a block at a time
                e = min(s + _BLOCK, size)
                vb, yb = v[:, : e - s], y[:, : e - s]
                np.abs(sp[s:e], out=vb[0])
                np.minimum(vb[0], cap, out=vb[0])
                vb[0] /= SPEED_SCALE_RPM
                np.multiply(vb[0], vb[0], out=vb[1])
                if logged:
                    w = vb[2:]
                    if e - s == _BLOCK:  # one call: the block's rows are contiguous
                        np.concatenate([u[s:e] for u in logged], out=w.reshape(-1))
                    else:
                        np.stack([u[s:e] for u in logged], out=w)
                    # the extremes say both whether to clip (rarely: a sensor fault) and whether a
                    # value is not finite (NaN fails every comparison; the clip would hide an inf)
                    low, high = np.minimum.reduce(w, axis=1), np.maximum.reduce(w, axis=1)
                    if not ((low >= lo[:, 0]).all() and (high <= hi[:, 0]).all()):
                        if not (np.isfinite(low).all() and np.isfinite(high).all()):
                            self._refuse_non_finite(logged)
                        np.clip(w, lo, hi, out=w)
                np.matmul(gains, vb, out=yb)
                ob = out[s:e]
                np.add(yb[0], constant, out=ob)
                rec.block(s, yb[1:], ob)
        rec.finish(out)
        if initial_um is not None:
            out += (require_finite("initial_um", initial_um) - out[0]) * decay(t, self._slowest_s)
        if self.extrapolation == "blend" and self.fallback is not None:
            w = np.minimum(
                self.distance_outside(dict(zip(self.input_names, logged))) / self.blend_span, 1.0
            )
            out += w * (self.fallback.simulate_um(sp, t, None, initial_um) - out)
        return out

    def _refuse_non_finite(self, logged: list[np.ndarray]) -> None:
        for c, u in zip(self.inputs, logged):
            series(c.name, u, u.size)  # raises, naming the sample

    def state_dict(self, state: StateSpaceState) -> dict[str, Any]:
        out = {
            "states_um": list(state.states_um),
            "residual_um": state.residual_um,
            "static_um": state.static_um,
        }
        if state.fallback is not None and self.fallback is not None:
            out.update(
                fallback_state=self.fallback.state_dict(state.fallback), blend_weight=state.weight
            )
        return out

    def state_from_dict(self, data: Mapping[str, Any]) -> StateSpaceState:
        """A state saved by :meth:`state_dict`; :class:`ModelError` if it does not fit this model."""
        try:
            x = saved_numbers("states_um", data["states_um"])
            r, s = saved_numbers("residual_um/static_um", [data["residual_um"], data["static_um"]])
        except (KeyError, TypeError, ValueError) as err:
            raise ModelError(f"saved state is not a state of this model ({err})") from err
        if len(x) != self.order:
            raise ModelError(f"saved state has {len(x)} states, the model {self.order}")
        if self.extrapolation != "blend" or self.fallback is None or "fallback_state" not in data:
            return StateSpaceState(x, r, s)  # a blend's fallback restarts at this state's estimate
        fb = self.fallback.state_from_dict(data["fallback_state"])
        (w,) = saved_numbers("blend_weight", [data.get("blend_weight", 0.0)], 1.0)
        return StateSpaceState(x, r, s, fb, min(max(w, 0.0), 1.0))

    def describe(self) -> list[str]:
        lo, hi = self.speed_range_rpm
        taus = ", ".join(f"{t / 60:.1f}" for t in self.taus_s)
        lines = [
            f"{self.format}, form {self.form}, spindle {self.spindle_id!r}, machine {self.machine_id!r}",
            f"  fitted at {self.fitted_dt_s:g} s over {lo:.0f}..{hi:.0f} rpm; {self.order} state(s), "
            f"tau = {taus} min; constant {self.offset_um:.2f} um",
            f"  steady elongation range {self.steady_range_um():.1f} um (bound {GAIN_BOUND:g} x "
            f"{self.max_measured_um:.1f} um measured)",
        ]
        for n in (0.0, hi / 2, hi):
            lines.append(
                f"  at {n:7.0f} rpm, inputs at their references: equilibrium "
                f"{self.steady_state_um(n):7.2f} um"
            )
        g = self.total_gains()
        for gi, c in zip(g[2:], self.inputs):
            lines.append(
                f"  {c.name}: {gi:+.3g} um/{c.unit} in steady state, reference {c.reference:.3f} "
                f"{c.unit}, trained {c.trained_range[0]:.3g}..{c.trained_range[1]:.3g}, "
                f"valid {c.valid_range[0]:.3g}..{c.valid_range[1]:.3g}"
            )
        lines += self.fit_lines()
        if self.fallback is not None:
            lines.append(f"  fallback when an input fails: {self.fallback.form} (speed only)")
        if self.inputs:
            how = {
                "linear": "the gains carried on to the valid range",
                "clip": "each input held at its trained end",
                "blend": f"moved toward the fallback, all of it {self.blend_span:g} span(s) out",
            }
            lines.append(
                f"  outside the trained range: {self.extrapolation} ({how[self.extrapolation]})"
            )
        return lines


StateSpaceModel.model_rebuild()


@dataclass(frozen=True, slots=True)
class StateSpaceState:
    """Runtime state, kept apart from the coefficients: each state, the unexplained part, and
    the static part (constant and feed-through) at the last step."""

    states_um: tuple[float, ...]
    residual_um: float
    static_um: float
    fallback: Any = None
    """A blend's fallback state (``extrapolation = "blend"``); None otherwise."""
    weight: float = 0.0
    """The fallback's share of the elongation at the last step."""

    @property
    def own_um(self) -> float:
        """The model's own elongation, before any blend."""
        return math.fsum(self.states_um) + self.residual_um + self.static_um

    @property
    def elongation_um(self) -> float:
        if self.fallback is None or self.weight == 0.0:
            return self.own_um
        return (1.0 - self.weight) * self.own_um + self.weight * float(self.fallback.elongation_um)


_BLOCK = 4096
"""Samples per block of a free run: a block's signals, drives and states stay in cache."""
_SUB = 16
"""Samples per sub-block: a running sum or a state's response inside one is a product with a
small matrix, which a BLAS does faster than numpy's running sum."""
_SPAN = 200.0
"""Largest decay exponent inside one closed-form stretch of a free run: exp(200) ~ 7e86, far
from overflow for any drive the checked gains give (an overflow is redone scaled, exactly)."""
_FEW_ODD = 8
"""Steps off the usual one in a block up to which the block's usual runs still go by
sub-blocks; beyond, the clock is irregular and the whole block goes by stretches."""
_LD_MAX = 1e4  # dt/tau beyond this is a full reset (exp(-1e4) == 0)
_UPPER = np.triu(np.ones((_SUB, _SUB)))
"""[j, k] = 1 where j <= k: a running sum over a sub-block as a product."""


def _buffer(store: np.ndarray, *shape: int) -> np.ndarray:
    """A contiguous view of ``shape`` at the start of ``store``: no allocation per block (a
    fresh array of this size is often fresh pages from the system, each a fault)."""
    return store[: math.prod(shape)].reshape(shape)


class _Recursion:
    """Every state's exact step ``x_k = a_k*x_{k-1} + (1 - a_k)*d_k``, ``a_k = exp(-dt_k/tau)``
    (:func:`compensator.filters.lag_step` at each sample) over a log, a block at a time, added
    into the output; no Python loop over samples.

    - Runs of the log's usual step (a whole block, or a block cut by a few odd steps such as a
      gap, each then taken alone): per sub-block of ``_SUB`` samples, the
      response from rest is a product with a fixed lower-triangular matrix of ``(1 - a)*a**i``,
      the state carried from one sub-block to the next is the same recursion with ``a**_SUB``
      (in closed form), and what it adds at each sample is its decay ``a**(i + 1)``.
    - Any other block: closed form over a stretch from its start s, with L the time since s
      over tau, ``x_k = (x_s + sum_{s<j<=k} (1 - a_j)*d_j*exp(L_j)) * exp(-L_k)``, each step
      with its own Δt; a step longer than ``_SPAN`` time constants alone.
    - A state whose time constant is within a few usual steps: over the whole log at the end
      (:func:`compensator.filters.lag`), where that pays.
    """

    def __init__(self, taus_s: tuple[float, ...], t: np.ndarray) -> None:
        self.t = t
        self.taus = np.asarray(taus_s, dtype=float)
        usual = 0.0
        if t.size > 1:  # the median of about a thousand steps: for the tables only
            stride = max(1, (t.size - 1) // 1024)
            usual = float(np.median(t[1::stride] - t[:-1:stride]))
        regular = math.isfinite(usual) and usual > 0
        fast = _BLOCK * usual > _SPAN * self.taus if regular else self.taus < 0
        self.slow, self.fast = np.flatnonzero(~fast), np.flatnonzero(fast)
        rows = self.slow.size
        self.tau = self.taus[self.slow][:, None]
        self.rate = 1.0 / self.tau
        self.ones = np.ones(rows)
        self.x = np.empty(rows)
        self.fast_drive = np.empty((self.fast.size, t.size if self.fast.size else 0))
        size = min(_BLOCK, t.size)
        self.dt = np.empty(size)
        self.work = [np.empty(rows * size) for _ in range(3)]
        self.sums = np.empty(size)
        self.usual = usual if regular and rows else math.nan
        if math.isnan(self.usual):
            return
        ld = usual * self.rate  # (states, 1)
        i = np.arange(_SUB)
        lower = np.subtract.outer(i, i).T  # [j, k] = k - j: sample j's weight at sample k
        self.rest = np.where(lower >= 0, np.exp(-np.maximum(lower, 0) * ld[:, :, None]), 0.0)
        self.rest *= -np.expm1(-ld)[:, :, None]  # (states, _SUB, _SUB)
        self.carry = np.exp(-(i + 1.0) * ld)  # (states, _SUB)
        b = np.arange(1.0, _BLOCK // _SUB + 1) * (_SUB * ld)  # the carry's own closed form
        self.grow, self.shrink = np.exp(b), np.exp(-b)

    def block(self, s: int, drives: np.ndarray, out: np.ndarray) -> None:
        """Samples s.. of every state, from their drives (a row each), added into ``out``.
        Call under ``numpy.errstate(over="ignore", invalid="ignore")``: an overflow of the
        closed form is found and redone scaled."""
        if self.fast.size:
            self.fast_drive[:, s : s + drives.shape[1]] = drives[self.fast]
        if not self.slow.size:
            return
        d = drives if self.slow.size == drives.shape[0] else drives[self.slow]
        first = 0
        if s == 0:  # at equilibrium with the first sample
            self.x[:] = d[:, 0]
            out[0] += math.fsum(self.x)
            first = 1
        m = d.shape[1] - first
        if m <= 0:
            return
        t, s1 = self.t, s + first
        dt = np.subtract(t[s1 : s1 + m], t[s1 - 1 : s1 + m - 1], out=self.dt[:m])
        lo, hi = float(dt.min()), float(dt.max())
        if not (lo >= 0 and math.isfinite(hi)):
            Steps.of(t)  # raises, naming the sample
            raise ModelError("time_s is not usable")
        if lo == hi == self.usual:
            odd = np.empty(0, dtype=np.intp)
        elif math.isnan(self.usual):
            odd = np.arange(m)
        else:
            odd = np.flatnonzero(dt != self.usual)
        if odd.size > _FEW_ODD:  # an irregular clock: closed-form stretches throughout
            self._stretches(s + first, d[:, first:], dt, out[first:])
            return
        # runs of the usual step by sub-blocks, each odd step (a gap, a jitter) on its own
        i = 0
        for end, with_odd in [*((k + 1, 1) for k in odd.tolist()), (m, 0)]:
            run = end - i - with_odd  # samples reached by the usual step
            whole = run - run % _SUB if run > 0 else 0
            a = first + i
            if whole and self._regular(d[:, a : a + whole], out[a : a + whole]):
                i += whole
            if i < end:
                a = first + i
                self._stretches(s + a, d[:, a : first + end], dt[i:end], out[a : first + end])
                i = end

    def _regular(self, d: np.ndarray, out: np.ndarray) -> bool:
        """Samples at the usual step, a whole number of sub-blocks; False (nothing changed) if
        the carry's closed form overflows (a drive near the float range)."""
        rows, nb = d.shape[0], d.shape[1] // _SUB
        local = _buffer(self.work[0], rows, nb, _SUB)
        np.matmul(d.reshape(rows, nb, _SUB), self.rest, out=local)
        ends = np.multiply(local[:, :, -1], self.grow[:, :nb], out=_buffer(self.work[1], rows, nb))
        np.cumsum(ends, axis=1, out=ends)  # the state at each sub-block's end
        ends += self.x[:, None]
        ends *= self.shrink[:, :nb]
        if not np.isfinite(ends[:, -1]).all():
            return False
        before = _buffer(self.work[2], nb, rows)  # the state before each sub-block
        before[0] = self.x
        before[1:] = ends[:, :-1].T
        sums = _buffer(self.sums, nb * _SUB)
        out += np.matmul(self.ones, local.reshape(rows, -1), out=sums)
        out += np.matmul(before, self.carry, out=sums.reshape(nb, _SUB)).reshape(-1)
        self.x[:] = ends[:, -1]
        return True

    def _stretches(self, s: int, d: np.ndarray, dt: np.ndarray, out: np.ndarray) -> None:
        """Samples s..s+len(dt)-1 from each step's own Δt, in stretches of at most _SPAN of the
        fastest state's time constant (one longer step alone)."""
        t, m, rows = self.t, dt.size, self.x.size
        reach = _SPAN * float(self.tau.min())
        p = 0
        while p < m:
            # within this block's samples only: they are checked to be in order
            q = p + int(np.searchsorted(t[s + p : s + m], t[s + p - 1] + reach, side="right"))
            if q <= p + 1:  # one step: directly
                ld = np.minimum(dt[p] / self.tau[:, 0], _LD_MAX)
                self.x *= np.exp(-ld)
                self.x -= np.expm1(-ld) * d[:, p]
                out[p] += math.fsum(self.x)
                p += 1
                continue
            if q - p >= _SUB:  # whole sub-blocks, for the running sum (the rest next)
                q -= (q - p) % _SUB
            n = q - p
            inc = np.multiply(dt[p:q], -self.rate, out=_buffer(self.work[0], rows, n))
            np.expm1(inc, out=inc)
            inc *= d[:, p:q]  # -(1 - a_k)*d_k
            g = _buffer(self.work[1], rows, n)
            np.multiply(t[s + p : s + q] - t[s + p - 1], self.rate, out=g)  # L
            np.exp(g, out=g)
            c = np.multiply(inc, g, out=_buffer(self.work[2], rows, n))
            if n < 2 * _SUB or n % _SUB:
                np.cumsum(c, axis=1, out=c)
            else:  # the running sum inside sub-blocks as a product, then each one's total on
                r = np.matmul(c.reshape(rows, -1, _SUB), _UPPER, out=inc.reshape(rows, -1, _SUB))
                before = np.cumsum(r[:, :-1, -1], axis=1)  # (a row of 16 per add is slow)
                r[:, 1:, :] += np.repeat(before, _SUB, axis=1).reshape(rows, -1, _SUB)
                c, inc = inc, c
            np.subtract(self.x[:, None], c, out=c)
            c /= g
            for i in np.flatnonzero(~np.isfinite(c[:, -1])):  # a drive near the float range
                c[i] = self._scaled(
                    float(self.x[i]), np.expm1(dt[p:q] * -self.rate[i]), d[i, p:q], g[i]
                )
            out[p:q] += np.matmul(self.ones, c, out=self.sums[:n])
            self.x[:] = c[:, -1]
            p = q

    @staticmethod
    def _scaled(x: float, gain: np.ndarray, d: np.ndarray, g: np.ndarray) -> np.ndarray:
        """One state's stretch, its values scaled by a power of two (exact) so that the sums
        stay far from overflow; ``gain`` is -(1 - a_k), ``g`` exp(L)."""
        inc = gain * d
        e = math.frexp(max(float(np.max(np.abs(inc))), abs(x)))[1]
        c = np.ldexp(inc, -e)
        c *= g
        np.cumsum(c, out=c)
        np.subtract(math.ldexp(x, -e), c, out=c)
        c /= g
        out: np.ndarray = np.ldexp(c, e)
        return out

    def finish(self, out: np.ndarray) -> None:
        """The fast states, over the whole log."""
        if self.fast.size:
            steps = Steps.of(self.t)
            for i, drive in zip(self.fast.tolist(), self.fast_drive):
                out += lag(steps, drive, float(self.taus[i]))


__all__ = [
    "GAIN_BOUND",
    "MAX_TAU_S",
    "MODEL_FORMAT",
    "STATE_SPACE_FORMAT",
    "InputChannel",
    "StateSpaceModel",
    "StateSpaceState",
]
