"""Models that use more than speed: temperatures, spindle load, ambient. Pure: no I/O.

``S = S_speed(n) + sum_j x_j`` where ``S_speed`` is a :class:`~compensator.model.ThermalModel`
fitted jointly with the input terms, and each input term ``j`` is

- static (``tau_s = 0``): ``x_j = g_j * (u_j - ref_j)``;
- dynamic: ``dx_j/dt = (g_j * (u_j - ref_j) - x_j) / tau_j``, stepped exactly with ``u_j`` held
  over each interval (the run-log convention, as for speed).

``u_j`` is the input in its own unit (degC, %), ``ref_j`` its stated reference (the mean value at
the start of the calibration runs: a spindle at rest overnight), ``g_j`` in um per unit.

The same value also carries ``fallback``: the best speed-only model, which the runtime uses when a
sensor fails (stale, out of range, NaN), so it never writes an offset built on garbage.
:class:`AugmentedModel` implements :class:`~compensator.predictor.Predictor`; its state carries the
references of the cold start, so the runtime keeps them across restarts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final, Literal

import numpy as np
from pydantic import Field, field_validator

from .errors import ModelError, NonFiniteInputError
from .filters import first_order, lag_step
from .model import ModelState, ThermalModel
from .modelbase import Channel, ModelBase, saved_numbers
from .units import require_dt

AUGMENTED_FORMAT: Final = "thermocomp.augmented-model/1"


class InputTerm(Channel):
    """One extra input and how it enters the elongation."""

    reference_mode: Literal["start", "fixed"] = Field(
        "start",
        description="start: relative to the value at a cold start (each calibration run's "
        "first sample; the runtime's first reading after a cold start); fixed: to `reference`",
    )
    reference: float = Field(
        description="the fixed reference; in start mode the calibration runs' mean start"
    )
    gain_um_per_unit: float
    tau_s: float = Field(ge=0, description="first-order time constant; 0 = static term")

    @field_validator("reference", "gain_um_per_unit", "tau_s")
    @classmethod
    def _finite(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError("must be finite")
        return v


class AugmentedModel(ModelBase):
    """A speed model plus input terms, and the speed-only model to fall back on."""

    format: Literal["thermocomp.augmented-model/1"] = AUGMENTED_FORMAT
    speed_model: ThermalModel
    inputs: tuple[InputTerm, ...] = Field(min_length=1)
    fallback: ThermalModel
    selection: list[dict[str, Any]] = Field(
        default_factory=list, description="how the inputs were chosen"
    )

    @property
    def form(self) -> str:
        return f"{self.speed_model.form}+" + "+".join(t.name for t in self.inputs)

    @property
    def channels(self) -> tuple[InputTerm, ...]:
        return self.inputs

    @property
    def speed_range_rpm(self) -> tuple[float, float]:
        return self.speed_model.speed_range_rpm

    # -- free run over a log ------------------------------------------------------

    def references(self, first: Mapping[str, float]) -> dict[str, float]:
        """The reference of each input, given the values at a cold start."""
        return {
            t.name: float(first[t.name]) if t.reference_mode == "start" else t.reference
            for t in self.inputs
        }

    def input_response(self, time_s: np.ndarray, inputs: Mapping[str, np.ndarray]) -> np.ndarray:
        """Sum of the input terms over ``time_s`` (inputs held over each interval), each term at
        its equilibrium at the first sample, the log's first sample taken as the cold start."""
        t = np.asarray(time_s, dtype=float)
        total = np.zeros_like(t)
        for term in self.inputs:
            if term.name not in inputs:
                raise ModelError(f"the model needs input {term.name!r}, which the log lacks")
            u = np.asarray(inputs[term.name], dtype=float)
            if u.shape != t.shape:
                raise ModelError(f"input {term.name}: {u.size} values for {t.size} times")
            if not np.isfinite(u).all():
                raise NonFiniteInputError(f"input {term.name} has non-finite values")
            ref = u[0] if term.reference_mode == "start" else term.reference
            drive = term.gain_um_per_unit * (u - ref)
            total += first_order(drive, np.diff(t, prepend=t[0]), term.tau_s, float(drive[0]))
        return total

    def simulate_um(
        self,
        speed_rpm: np.ndarray,
        time_s: np.ndarray,
        inputs: Mapping[str, np.ndarray] | None = None,
        initial_um: float | None = None,
    ) -> np.ndarray:
        """Free-run elongation; the speed part starts from ``initial_um`` (None: 0) less the input terms'
        share at the first sample (each input term starts at its equilibrium)."""
        response = self.input_response(time_s, inputs or {})
        state = self.speed_model.state_at(
            (initial_um or 0.0) - float(response[0]), float(np.abs(speed_rpm[0]))
        )
        base = self.speed_model.simulate(
            np.asarray(speed_rpm, float), np.asarray(time_s, float), state
        ).elongation_um
        elongation_um: np.ndarray = base + response
        return elongation_um

    # -- the runtime's step ---------------------------------------------------------

    def start(
        self,
        elongation_um: float | None,
        speed_rpm: float,
        inputs: Mapping[str, float] | None = None,
        references: Mapping[str, float] | None = None,
    ) -> AugmentedState:
        """Input terms at their equilibrium for ``inputs``, the speed part at ``elongation_um`` less
        their share. Without ``references`` these inputs are the cold start's (:meth:`references`)."""
        if inputs is None:
            raise ModelError(f"the model needs inputs {', '.join(self.input_names)} to start")
        elongation_um = 0.0 if elongation_um is None else elongation_um
        refs = dict(references) if references is not None else self.references(inputs)
        x = tuple(t.gain_um_per_unit * (float(inputs[t.name]) - refs[t.name]) for t in self.inputs)
        speed = self.speed_model.state_at(elongation_um - float(sum(x)), speed_rpm)
        return AugmentedState(speed, x, refs)

    def step(
        self,
        state: AugmentedState,
        speed_rpm: float,
        dt_s: float,
        inputs: Mapping[str, float] | None = None,
    ) -> AugmentedState:
        if inputs is None:
            raise ModelError(f"the model needs inputs {', '.join(self.input_names)} to step")
        dt_s = require_dt(dt_s)
        speed_state = self.speed_model.step(state.speed, speed_rpm, dt_s)
        refs = state.references
        x = []
        for term, xj in zip(self.inputs, state.inputs):
            drive = term.gain_um_per_unit * (float(inputs[term.name]) - refs[term.name])
            x.append(lag_step(xj, drive, dt_s, term.tau_s))
        return AugmentedState(speed_state, tuple(x), refs)

    def state_dict(self, state: AugmentedState) -> dict[str, Any]:
        return {
            "speed": self.speed_model.state_dict(state.speed),
            "inputs_um": list(state.inputs),
            "references": dict(state.references),
        }

    def state_from_dict(self, data: Mapping[str, Any]) -> AugmentedState:
        try:
            x = saved_numbers("inputs_um", data["inputs_um"])
            refs = {
                t.name: saved_numbers("references", [data["references"][t.name]], 1e9)[0]
                for t in self.inputs
            }
            speed = self.speed_model.state_from_dict(data["speed"])
        except (KeyError, TypeError, ValueError) as err:
            raise ModelError(f"saved state is not a state of this model ({err})") from err
        if len(x) != len(self.inputs) or not all(math.isfinite(v) for v in (*x, *refs.values())):
            raise ModelError("saved state does not fit the model's inputs")
        return AugmentedState(speed, x, refs)

    def describe(self) -> list[str]:
        lines = [
            f"{self.format}, inputs {', '.join(self.input_names)}, spindle {self.spindle_id!r}"
        ]
        for t in self.inputs:
            dyn = "static" if t.tau_s == 0 else f"lag {t.tau_s:g} s"
            ref = (
                "its value at a cold start"
                if t.reference_mode == "start"
                else f"{t.reference:g} {t.unit}"
            )
            lines.append(
                f"  {t.name}: {t.gain_um_per_unit:.4g} um/{t.unit}, {dyn}, relative to {ref}, "
                f"valid {t.valid_range[0]:.3g}..{t.valid_range[1]:.3g} {t.unit}"
            )
        lines += self.fit_lines()
        lines.append("  speed part (fitted with the inputs):")
        lines.append(f"  fallback when a sensor fails: {self.fallback.form} (speed only)")
        return lines + self.speed_model.describe()


@dataclass(frozen=True)
class AugmentedState:
    speed: ModelState
    inputs: tuple[float, ...]
    references: Mapping[str, float]

    @property
    def elongation_um(self) -> float:
        return self.speed.elongation_um + float(sum(self.inputs))


__all__ = ["AUGMENTED_FORMAT", "AugmentedModel", "AugmentedState", "InputTerm", "first_order"]
