"""The one interface every model offers the runtime and replay. Pure: no I/O.

A model (speed only, with temperatures, a future observer fusing probe measurements, the
cooling controller's estimate) is an immutable value with the methods below; its runtime state
is a separate immutable value with an ``elongation_um``. The runtime and replay call only
these, so a new model plugs in by implementing them and registering its file format in
:data:`compensator.io.modelfile.MODEL_TYPES`; nothing else branches on model classes.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol, runtime_checkable

import numpy as np


class PredictorState(Protocol):
    @property
    def elongation_um(self) -> float: ...


@runtime_checkable
class Predictor(Protocol):
    """A thermal-elongation model. Speeds in rpm (sign ignored), time in s, elongation in um."""

    # read-only, as every model value is immutable
    @property
    def spindle_id(self) -> str: ...

    @property
    def machine_id(self) -> str: ...

    @property
    def format(self) -> str:
        """The file format's name (read-only: each model class fixes its own literal)."""
        ...

    @property
    def form(self) -> str: ...

    @property
    def speed_range_rpm(self) -> tuple[float, float]:
        """(min, max) |speed| seen in calibration."""
        ...

    @property
    def input_names(self) -> tuple[str, ...]:
        """Extra channels the model reads besides speed (temperatures, load); empty if none."""
        ...

    @property
    def fallback(self) -> Predictor | None:
        """The speed-only model that stands in when an input fails; None for speed-only models."""
        ...

    def above_range(self, speed_rpm: float) -> bool:
        """True above the calibrated speed range: the prediction is an extrapolation."""
        ...

    def check_inputs(self, values: Mapping[str, float]) -> str | None:
        """Why these input values cannot be used (missing, not a finite number, out of range),
        or None. Every model judges alike (:func:`compensator.modelbase.check_inputs`): a bool
        is not a number."""
        ...

    def start(
        self,
        elongation_um: float | None,
        speed_rpm: float,
        inputs: Mapping[str, float] | None = None,
        references: Mapping[str, float] | None = None,
    ) -> Any:
        """A state whose elongation is ``elongation_um`` (None: none measured, the model's own
        equilibrium); input terms at their equilibrium, relative to ``references`` (default: the
        model's own, or these values for a cold start)."""
        ...

    def step(
        self, state: Any, speed_rpm: float, dt_s: float, inputs: Mapping[str, float] | None = None
    ) -> Any:
        """Advance ``state`` by ``dt_s`` with the speed (and inputs) held over the step."""
        ...

    def simulate_um(
        self,
        speed_rpm: np.ndarray,
        time_s: np.ndarray,
        inputs: Mapping[str, np.ndarray] | None = None,
        initial_um: float | None = None,
    ) -> np.ndarray:
        """Free run over a whole log; ``speed_rpm[k]`` held over ``(time_s[k-1], time_s[k]]``;
        ``initial_um`` as ``elongation_um`` in :meth:`start`."""
        ...

    def state_dict(self, state: Any) -> dict[str, Any]:
        """``state`` as JSON-able data, for the runtime's state file."""
        ...

    def state_from_dict(self, data: Mapping[str, Any]) -> Any:
        """A state saved by :meth:`state_dict`; ``ModelError`` if it does not fit this model."""
        ...

    def describe(self) -> list[str]:
        """Human-readable lines: form, inputs, time constants and equilibria."""
        ...

    def model_dump(self, *, mode: str = ...) -> dict[str, Any]:
        """The immutable coefficients as a mapping (pydantic's; ``mode="json"``: JSON-able)."""
        ...
