"""The cumulative thermal-elongation model: a pure, immutable value.

The model follows eq. 10 of paper 001 (``docs/REFERENCES.md``), generalised to
one or more parallel first-order thermal states plus an instantaneous (elastic)
speed-dependent term. For state *j*, with the speed held at n over a step::

    dx_j/dt = -lambda_j(n) * x_j + u_j(n)
    lambda_j(n) = d0 + d1*n                      [1/s]      dissipation
    u_j(n)      = g0 + g1*n + g2*n**2 + g3*n**3  [um/s]     heat generation
    S           = sum_j x_j + e1*n + e2*n**2     [um]       elongation

n is |speed| in krpm (the internal scale keeps n**3 well conditioned). ``d1``
is the paper's speed x state term, extra entries in ``states`` are extra
thermal states, and ``e1``/``e2`` are the elastic (centrifugal or preload) part,
which is not a state and therefore never filtered.

Stepping uses the exact zero-order-hold solution of that linear system::

    a = exp(-lambda*dt),   x' = a*x + (1 - a)/lambda * u

so a model fitted at 60 s steps correctly at 0.1 s, 1 s or irregular
intervals: ``a' = a**(dt'/dt)`` and the input gain scales by
``(1 - a')/(1 - a)``.

Convention: ``speed_rpm`` passed to :meth:`ThermalModel.step` is held over the
whole step; in :meth:`ThermalModel.simulate` ``speeds[k]`` is held over
``(times[k-1], times[k]]``, which is the paper's ``S_k = a*S_{k-1} + f(n_k)``.

This module does no I/O; reading and writing model files lives in
:mod:`compensator.io.modelfile`. :class:`ThermalModel` implements
:class:`~compensator.predictor.Predictor`.

References
----------
Paper 001, the cumulative thermal-error model, eqs. 10-13 (``docs/REFERENCES.md``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from .errors import ModelError, NonFiniteInputError, UnstableModelError
from .filters import constant_decay, decaying_sum, one_minus_exp, rate_gains, rate_step
from .modelbase import (  # noqa: F401 (SAVED_LIMIT_UM, saved_numbers: their old home)
    MAX_FITTED_DT_S,
    MAX_MODEL_UM,
    MIN_FITTED_DT_S,
    SAVED_LIMIT_UM,
    ModelBase,
    saved_numbers,
    speed_range,
)
from .units import SPEED_SCALE_RPM, require_dt, require_finite, speed_krpm

MODEL_FORMAT: Final = "thermocomp.model/1"

_CHUNK = 16384  # samples per block: keeps the per-block temporaries in cache
_MAX_LOG_SPAN = 500.0  # exp(500) is far from overflow; bounds the rescaling
_BOUND_POINTS = 33  # speeds at which the equilibrium is held to MAX_MODEL_UM, rest to top


class ThermalStateCoefficients(BaseModel):
    """Coefficients of one first-order thermal state (n in krpm)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    dissipation_per_s: tuple[float, float] = Field(
        description="(d0 [1/s], d1 [1/(s*krpm)]): lambda(n) = d0 + d1*n"
    )
    generation_um_per_s: tuple[float, float, float, float] = Field(
        description="(g0, g1, g2, g3) [um/s per krpm**i]: u(n) = sum g_i*n**i"
    )

    @field_validator("dissipation_per_s", "generation_um_per_s")
    @classmethod
    def _finite(cls, value: tuple[float, ...]) -> tuple[float, ...]:
        if not all(math.isfinite(v) for v in value):
            raise ValueError("coefficients must be finite")
        return value

    def rate_per_s(self, n_krpm: float) -> float:
        d0, d1 = self.dissipation_per_s
        return d0 + d1 * n_krpm

    def generation(self, n_krpm: float) -> float:
        g0, g1, g2, g3 = self.generation_um_per_s
        return ((g3 * n_krpm + g2) * n_krpm + g1) * n_krpm + g0


class ThermalModel(ModelBase):
    """Immutable model value; see the module docstring for the equations.

    Construction validates stability over ``speed_range_rpm``: a state with
    lambda(n) <= 0, i.e. a discrete pole |a(n)| >= 1, anywhere in the range
    raises :class:`~compensator.errors.UnstableModelError`; any other invalid
    field raises :class:`~compensator.errors.ModelError`.
    """

    format: Literal["thermocomp.model/1"] = MODEL_FORMAT
    form: str = Field("paper", description="name of the model form chosen by calibration")
    fitted_dt_s: float = Field(
        gt=0,
        description="sample period of the calibration data [s]",
        # held to these by ModelBase's validator, which says why in its own words
        json_schema_extra={"minimum": MIN_FITTED_DT_S, "maximum": MAX_FITTED_DT_S},
    )
    speed_range_rpm: tuple[float, float] = Field(
        description="(min, max) |speed| seen in calibration [rpm]; max 10 .. 1e6 rpm"
    )
    states: tuple[ThermalStateCoefficients, ...] = Field(min_length=1)
    elastic_um: tuple[float, float] = Field(
        (0.0, 0.0), description="(e1 [um/krpm], e2 [um/krpm**2]): instantaneous e(n)"
    )

    @field_validator("speed_range_rpm")
    @classmethod
    def _range(cls, value: tuple[float, float]) -> tuple[float, float]:
        return speed_range(value)

    @field_validator("elastic_um")
    @classmethod
    def _elastic_finite(cls, value: tuple[float, float]) -> tuple[float, float]:
        if not all(math.isfinite(v) for v in value):
            raise ValueError("elastic coefficients must be finite")
        return value

    @model_validator(mode="after")
    def _stable(self) -> ThermalModel:
        lo, hi = (v / SPEED_SCALE_RPM for v in self.speed_range_rpm)
        for j, st in enumerate(self.states, start=1):
            # lambda is linear in n, so its minimum over the range is at an end
            for n in (lo, hi):
                lam = st.rate_per_s(n)
                if not lam > 0:
                    a = math.exp(-lam * self.fitted_dt_s) if lam > -50 else math.inf
                    raise UnstableModelError(
                        f"state {j} is unstable at {n * SPEED_SCALE_RPM:.0f} rpm: "
                        f"a(n) = {a:.6g} >= 1 at dt = {self.fitted_dt_s:g} s "
                        f"(dissipation {lam:.3g} 1/s)"
                    )
        return self

    @model_validator(mode="after")
    def _bounded(self) -> ThermalModel:
        # finite coefficients can still hold an equilibrium no calibration measured (a gain
        # x 1e300): refused here, at load, before any arithmetic overflows on it
        lo, hi = self.speed_range_rpm
        for i in range(_BOUND_POINTS):
            rpm = lo + (hi - lo) * i / (_BOUND_POINTS - 1)
            n = rpm / SPEED_SCALE_RPM
            parts = [
                (f"state {j}", st.generation(n) / st.rate_per_s(n))
                for j, st in enumerate(self.states, start=1)
            ]
            parts.append(("the elastic part", self.elastic(rpm)))
            parts.append(
                (
                    "the model",
                    math.fsum(v for _, v in parts)
                    if all(math.isfinite(v) for _, v in parts)
                    else math.inf,
                )
            )
            for what, um in parts:
                if not abs(um) <= MAX_MODEL_UM:
                    raise ModelError(
                        f"{what} holds {um:.4g} um at equilibrium at {rpm:.0f} rpm: beyond "
                        f"{MAX_MODEL_UM:g} um, more than any calibration measures"
                    )
        return self

    # -- construction -------------------------------------------------------

    @classmethod
    def from_discrete(
        cls,
        a: float,
        beta_um: tuple[float, float, float, float],
        dt_s: float,
        *,
        speed_range_rpm: tuple[float, float],
        elastic_um: tuple[float, float] = (0.0, 0.0),
        **fields: Any,
    ) -> ThermalModel:
        """Exact continuous equivalent of the paper's discrete form (eqs. 11-12).

        ``S_k = a*S_{k-1} + b0 + b1*n + b2*n**2 + b3*n**3`` at period ``dt_s``,
        with ``beta_um = (b0, b1, b2, b3)`` per krpm**i.
        """
        if not (math.isfinite(a) and all(math.isfinite(b) for b in beta_um)):
            raise NonFiniteInputError("discrete coefficients must be finite")
        if a >= 1.0:
            raise UnstableModelError(f"pole a = {a:.6g} >= 1: the model is unstable")
        if a <= 0.0:
            raise ModelError(f"pole a = {a:.6g} <= 0 has no continuous-time equivalent")
        lam = -math.log(a) / dt_s
        gain = lam / (1.0 - a)  # u = beta * lambda / (1 - a)
        state = ThermalStateCoefficients(
            dissipation_per_s=(lam, 0.0),
            generation_um_per_s=tuple(b * gain for b in beta_um),  # type: ignore[arg-type]
        )
        return cls(
            fitted_dt_s=dt_s,
            speed_range_rpm=speed_range_rpm,
            states=(state,),
            elastic_um=elastic_um,
            **fields,
        )

    # -- derived quantities -----------------------------------------------

    @property
    def _speed_state(self) -> bool:
        return any(st.dissipation_per_s[1] != 0.0 for st in self.states)

    @property
    def order(self) -> int:
        return len(self.states)

    def elastic(self, speed_rpm: float) -> float:
        n = speed_krpm(speed_rpm)
        e1, e2 = self.elastic_um
        return (e2 * n + e1) * n

    def time_constants_s(self, speed_rpm: float = 0.0) -> tuple[float, ...]:
        n = speed_krpm(speed_rpm)
        return tuple(1.0 / st.rate_per_s(n) for st in self.states)

    def steady_state_um(self, speed_rpm: float) -> float:
        """Equilibrium elongation when ``speed_rpm`` is held forever [um]."""
        n = speed_krpm(speed_rpm)
        return sum(st.generation(n) / st.rate_per_s(n) for st in self.states) + self.elastic(
            speed_rpm
        )

    def discretize(self, dt_s: float) -> DiscreteModel:
        """The exact zero-order-hold model at a fixed period: a new value."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ModelError(f"dt_s must be finite and > 0, got {dt_s}")
        return DiscreteModel(self, float(dt_s))

    # -- the Predictor interface (speed only: no inputs, no fallback) -----------

    @property
    def fallback(self) -> None:
        return None

    def start(
        self,
        elongation_um: float | None,
        speed_rpm: float,
        inputs: Mapping[str, float] | None = None,
        references: Mapping[str, float] | None = None,
    ) -> ModelState:
        return self.state_at(0.0 if elongation_um is None else elongation_um, speed_rpm)

    def simulate_um(
        self,
        speed_rpm: np.ndarray,
        time_s: np.ndarray,
        inputs: Mapping[str, np.ndarray] | None = None,
        initial_um: float | None = None,
    ) -> np.ndarray:
        state = self.state_at(
            0.0 if initial_um is None else initial_um, float(np.asarray(speed_rpm, dtype=float)[0])
        )
        return self.simulate(speed_rpm, time_s, state).elongation_um

    def state_dict(self, state: ModelState) -> dict[str, Any]:
        return {"thermal_um": list(state.thermal_um)}

    def state_from_dict(self, data: Mapping[str, Any]) -> ModelState:
        """A state saved by :meth:`state_dict`; :class:`ModelError` if it does not fit this model."""
        try:
            thermal = saved_numbers("thermal_um", data["thermal_um"])
        except (KeyError, TypeError, ValueError) as err:
            raise ModelError(f"saved state is not a state of this model ({err})") from err
        if len(thermal) != self.order:
            raise ModelError(
                f"saved state has {len(thermal)} thermal states, the model {self.order}"
            )
        return ModelState(thermal, 0.0)

    def describe(self) -> list[str]:
        lo, hi = self.speed_range_rpm
        lines = [
            f"{self.format}, form {self.form}, spindle {self.spindle_id!r}, machine {self.machine_id!r}",
            f"  fitted at {self.fitted_dt_s:g} s over {lo:.0f}..{hi:.0f} rpm; stable over that range",
        ]
        for n in (0.0, hi / 2, hi):
            taus = ", ".join(f"{t / 60:.1f}" for t in self.time_constants_s(n))
            lines.append(
                f"  at {n:7.0f} rpm: tau = {taus} min, equilibrium {self.steady_state_um(n):7.2f} um"
            )
        lines += self.fit_lines()
        return lines

    # -- state --------------------------------------------------------------

    def cold_state(self, speed_rpm: float = 0.0) -> ModelState:
        """All thermal states at zero: the spindle at ambient."""
        return ModelState((0.0,) * self.order, self.elastic(speed_rpm))

    def state_at(self, elongation_um: float, speed_rpm: float = 0.0) -> ModelState:
        """A state whose elongation equals ``elongation_um``.

        The thermal part is split across states in proportion to their
        equilibrium shares at ``speed_rpm`` (the spindle is assumed near
        equilibrium); where those shares are not all of one sign it is split
        evenly.
        """
        require_finite("elongation_um", elongation_um)
        elastic = self.elastic(speed_rpm)
        thermal = elongation_um - elastic
        n = speed_krpm(speed_rpm)
        shares = [st.generation(n) / st.rate_per_s(n) for st in self.states]
        total = sum(shares)
        if total != 0 and (all(s >= 0 for s in shares) or all(s <= 0 for s in shares)):
            weights = [s / total for s in shares]
        else:
            weights = [1.0 / self.order] * self.order
        return ModelState(tuple(thermal * w for w in weights), elastic)

    # -- stepping -----------------------------------------------------------

    def step(
        self,
        state: ModelState,
        speed_rpm: float,
        dt_s: float,
        inputs: Mapping[str, float] | None = None,
    ) -> ModelState:
        """Advance ``state`` by ``dt_s`` seconds with ``speed_rpm`` held.

        Negative speed is reverse rotation (|n| is used); NaN or inf raises
        :class:`NonFiniteInputError`, as does a negative ``dt_s``. ``inputs`` is ignored:
        this model uses speed only.
        """
        n = speed_krpm(speed_rpm)
        dt_s = require_dt(dt_s)
        if len(state.thermal_um) != self.order:
            raise ModelError(
                f"state has {len(state.thermal_um)} thermal states, model has {self.order}"
            )
        new = tuple(
            rate_step(x, st.rate_per_s(n), st.generation(n), dt_s)
            for x, st in zip(state.thermal_um, self.states)
        )
        return ModelState(new, self.elastic(speed_rpm))

    def simulate(
        self,
        speeds_rpm: np.ndarray,
        times_s: np.ndarray,
        state: ModelState | None = None,
    ) -> Simulation:
        """Free-run the model over a whole log (vectorised).

        ``elongation_um[0]`` is the initial state's elongation at
        ``speeds_rpm[0]``; ``speeds_rpm[k]`` drives the step that ends at
        ``times_s[k]``. ``state`` defaults to :meth:`cold_state`.
        """
        speeds = np.asarray(speeds_rpm, dtype=float)
        times = np.asarray(times_s, dtype=float)
        if speeds.ndim != 1 or speeds.shape != times.shape:
            raise ModelError("speeds_rpm and times_s must be 1-D arrays of one length")
        if speeds.size == 0:
            raise ModelError("cannot simulate an empty log")
        if not math.isfinite(float(times[0])):
            raise NonFiniteInputError(f"time at sample 0 is {times[0]}")
        if state is None:
            state = self.cold_state(float(speeds[0]))
        elif len(state.thermal_um) != self.order:
            raise ModelError(
                f"state has {len(state.thermal_um)} thermal states, model has {self.order}"
            )
        if not math.isfinite(float(speeds[0])):
            raise NonFiniteInputError(f"speed at sample 0 is {speeds[0]}")

        out = np.empty_like(speeds)
        out[0] = math.fsum(state.thermal_um) + self.elastic(float(speeds[0]))
        x = list(state.thermal_um)
        k = 1.0 / SPEED_SCALE_RPM
        e1, e2 = self.elastic_um[0] * k, self.elastic_um[1] * k * k
        nbuf = np.empty(min(_CHUNK, speeds.size))
        dbuf = np.empty(min(_CHUNK, speeds.size))
        # one pass over the log in cache-sized blocks: checks, then every state
        for s in range(1, speeds.size, _CHUNK):
            e = min(s + _CHUNK, speeds.size)
            sp = speeds[s:e]
            # a sum is finite only if every term is: a cheap check without a mask
            if not math.isfinite(float(np.add.reduce(sp))):
                i = s + int(np.flatnonzero(~np.isfinite(sp))[0])
                raise NonFiniteInputError(f"speed at sample {i} is {speeds[i]}")
            dtb = np.subtract(times[s:e], times[s - 1 : e - 1], out=dbuf[: e - s])
            dmin, dmax = float(dtb.min()), float(dtb.max())
            if not (math.isfinite(dmin) and math.isfinite(dmax)):
                i = s + int(np.flatnonzero(~np.isfinite(times[s:e]))[0])
                raise NonFiniteInputError(f"time at sample {i} is {times[i]}")
            if dmin < 0:
                i = s + int(np.flatnonzero(dtb < 0)[0])
                raise NonFiniteInputError(f"time goes backwards at sample {i}")
            uniform = dmax - dmin <= 1e-12 * max(dmax, 1e-300)
            # the closed form needs the time since the block start; lfilter does not
            elapsed = None if uniform and not self._speed_state else times[s:e] - times[s - 1]
            nb = np.abs(sp, out=nbuf[: e - s])  # |rpm|; coefficients are scaled instead
            ob = out[s:e]
            for j, st in enumerate(self.states):
                xb = _advance_block(st, nb, dtb, x[j], elapsed, uniform, k)
                if j == 0:
                    ob[:] = xb
                else:
                    ob += xb
                x[j] = float(xb[-1])
            if e1 or e2:
                el = nb * e2
                el += e1
                el *= nb
                ob += el
        finals = x
        final = ModelState(tuple(finals), self.elastic(float(speeds[-1])))
        return Simulation(out, final)


def _generation(
    st: ThermalStateCoefficients, n: np.ndarray, out: np.ndarray, scale: float = 1.0
) -> np.ndarray:
    """u(n) by Horner; ``scale`` converts ``n`` to krpm inside the coefficients."""
    g0, g1, g2, g3 = st.generation_um_per_s
    g1, g2, g3 = g1 * scale, g2 * scale * scale, g3 * scale**3
    np.multiply(n, g3, out=out)
    out += g2
    out *= n
    out += g1
    out *= n
    if g0:
        out += g0
    return out


def filter_state(
    st: ThermalStateCoefficients, n_krpm: np.ndarray, dt_s: np.ndarray, x0: float = 0.0
) -> np.ndarray:
    """Free response of one thermal state to a speed sequence (n in krpm).

    ``dt_s[k-1]`` is the step ending at sample k (``len(dt_s) == len(n) - 1``);
    ``n_krpm[k]`` is held over that step. Returns x at every sample, x[0] = x0.
    The building block of output-error fitting: x is linear in the gains.
    """
    return _filter(st, np.abs(np.asarray(n_krpm, dtype=float)), np.asarray(dt_s, dtype=float), x0)


def _filter(st: ThermalStateCoefficients, n: np.ndarray, dt: np.ndarray, x0: float) -> np.ndarray:
    x = np.empty_like(n)
    x[0] = x0
    for s in range(1, n.size, _CHUNK):
        e = min(s + _CHUNK, n.size)
        dtb = dt[s - 1 : e - 1]
        uniform = float(dtb.max() - dtb.min()) <= 1e-12 * max(float(dtb.max()), 1e-300)
        x[s:e] = _advance_block(st, n[s:e], dtb, x0, np.cumsum(dtb), uniform, 1.0)
        x0 = float(x[e - 1])
    return x


def _advance_block(
    st: ThermalStateCoefficients,
    n: np.ndarray,
    dt: np.ndarray,
    x0: float,
    elapsed: np.ndarray | None,
    uniform: bool,
    scale: float,
) -> np.ndarray:
    """States after each step of a block: speed n[k] >= 0 held for dt[k], from x0.

    ``n * scale`` is in krpm; ``elapsed[k]`` is the time from the block start
    to the end of step k; ``uniform`` says every dt is the same.
    """
    d0, d1 = st.dissipation_per_s
    if d1 == 0.0 and uniform:
        # constant pole: one lfilter pass
        a, gain = rate_gains(d0, float(dt[0]))
        return constant_decay(a, _generation(st, n, np.empty_like(n), scale), x0, gain)
    return _advance_general(st, n, dt, x0, elapsed, scale)


def _advance_general(
    st: ThermalStateCoefficients,
    n: np.ndarray,
    dt: np.ndarray,
    x0: float,
    elapsed: np.ndarray | None,
    scale: float,
) -> np.ndarray:
    """Time-varying pole a_k = exp(-lambda(n_k)*dt_k), in closed form
    (:func:`compensator.filters.decaying_sum`); the cumulative decay is ``d0 * elapsed`` where
    lambda does not depend on speed. Blocks span at most ``_MAX_LOG_SPAN``."""
    d0, d1 = st.dissipation_per_s
    if d1 == 0.0:
        lam = None
        ld = dt * d0
    else:
        lam = n * (d1 * scale)
        lam += d0
        ld = lam * dt
    gain = one_minus_exp(ld)
    if lam is None:
        gain *= 1.0 / d0
    else:
        zero = lam == 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            gain /= lam
        if zero.any():
            gain[zero] = dt[zero]
    inc = _generation(st, n, np.empty_like(n), scale)
    inc *= gain
    if lam is None:
        # elapsed is left out only for uniform steps of speed-independent poles: lfilter's
        assert elapsed is not None
        return decaying_sum(inc, x0, cum=elapsed * d0, span=_MAX_LOG_SPAN)
    return decaying_sum(inc, x0, ld=ld, span=_MAX_LOG_SPAN)


@dataclass(frozen=True, slots=True)
class ModelState:
    """Runtime state, kept apart from the coefficients.

    ``thermal_um`` holds each thermal state; ``elastic_um`` the instantaneous
    part at the last speed.
    """

    thermal_um: tuple[float, ...]
    elastic_um: float = 0.0

    @property
    def elongation_um(self) -> float:
        return math.fsum(self.thermal_um) + self.elastic_um


@dataclass(frozen=True, slots=True)
class Simulation:
    """Result of :meth:`ThermalModel.simulate`."""

    elongation_um: np.ndarray
    final: ModelState


@dataclass(frozen=True, slots=True)
class DiscreteModel:
    """A model sampled at a fixed period ``dt_s`` (exact zero-order hold)."""

    continuous: ThermalModel
    dt_s: float

    def paper_coefficients(self) -> dict[str, float]:
        """(a, b0..b3 per krpm**i) of ``S_k = a*S_{k-1} + f(n_k)``.

        Only defined for the paper's form: one state, no speed x state term.
        """
        m = self.continuous
        if m.order != 1 or m.states[0].dissipation_per_s[1] != 0.0:
            raise ModelError("paper coefficients exist only for one state without n*S term")
        st = m.states[0]
        a, gain = rate_gains(st.dissipation_per_s[0], self.dt_s)
        g0, g1, g2, g3 = st.generation_um_per_s
        return {"a": a, "b0": gain * g0, "b1": gain * g1, "b2": gain * g2, "b3": gain * g3}

    def step(self, state: ModelState, speed_rpm: float) -> ModelState:
        return self.continuous.step(state, speed_rpm, self.dt_s)
