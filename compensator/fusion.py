"""A model with probe measurements fused in: the observer behind the one Predictor interface.
Pure: no I/O.

:class:`FusedPredictor` wraps any :class:`~compensator.predictor.Predictor` (speed only, with
inputs) and a :class:`~compensator.observer.ObserverConfig`. Its state carries the model's own
state and the observer's; its elongation is the model's plus the estimated bias. Between
measurements it steps like the model (the observer's time update runs with it, exact at the
real Δt); :meth:`FusedPredictor.measure` fuses one measurement. The runtime and replay use it
like any model (through :class:`compensator.estimate.Estimate`), so a closed loop needs no
special case.

A fused model always bounds what measurements can do (:mod:`compensator.observer`): an observer
setting without ``max_correction_um`` gets :func:`default_max_correction_um` of the model.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .errors import ModelError
from .fitrecord import FitRecord
from .modelbase import saved_numbers
from .observer import (
    CORRECTION_LIMIT_UM,
    COV_LIMIT,
    ObserverConfig,
    ObserverState,
    Update,
    measurement_update,
    time_update,
)
from .plausibility import POINTS, speed_only, steady_growth_um
from .predictor import Predictor

MIN_CORRECTION_UM = 10.0
"""The smallest default bound of the correction [um]: the order of what a speed-only model
misses over a day (the paper's largest residuals are 4 um, a hall's day-long drift some more)."""

CORRECTION_SHARE = 0.5
"""The default bound of the correction as a share of the model's steady growth over its range."""

OBSERVER_KEY = "observer"
"""Where a model's fit keeps the observer settings fitted at calibration."""


def observer_config_of(
    model: Predictor, override: Mapping[str, Any] | None = None
) -> ObserverConfig:
    """The observer settings fitted with ``model`` (``fit["observer"]``), else the defaults;
    ``override`` (the runtime's configuration) wins key by key. ``ModelError`` if invalid."""
    fit = getattr(model, "fit", None)
    stored: Any = None
    if isinstance(fit, FitRecord):
        stored = None if fit.observer is None else fit.observer.model_dump(exclude_unset=True)
    elif isinstance(fit, Mapping):  # a record's JSON form (a model that is no ModelBase)
        stored = fit.get(OBSERVER_KEY)
    stored = stored if isinstance(stored, Mapping) else {}
    data = {k: v for k, v in stored.items() if k in ObserverConfig.model_fields}
    data.update(override or {})
    try:
        return ObserverConfig(**data)
    except ValueError as err:
        raise ModelError(f"observer settings: {str(err).splitlines()[-1].strip()}") from err


def default_max_correction_um(model: Predictor) -> float:
    """The bound of the correction when none is configured [um]: half the model's largest steady
    growth over its calibrated range (a speed-only model's, or a model with inputs' fallback),
    and at least :data:`MIN_CORRECTION_UM`. A correction that large means the model no longer
    describes the spindle: refit. And an estimate pulled that far from the model by a faulty or
    hostile source leaves at most half the error of no compensation at all."""
    judged = speed_only(model)
    try:
        with np.errstate(all="ignore"):
            growth = steady_growth_um(
                judged, np.linspace(0.0, float(judged.speed_range_rpm[1]), POINTS)
            )
        span = float(np.max(np.abs(growth)))
    except (AttributeError, ArithmeticError, ValueError, ModelError):
        span = 0.0  # a model without a steady state of its own: the floor
    if not math.isfinite(span):
        span = 0.0
    return max(MIN_CORRECTION_UM, CORRECTION_SHARE * span)


def with_bounds(config: ObserverConfig, model: Predictor) -> ObserverConfig:
    """``config`` with its correction bound filled in from ``model`` where it has none."""
    if config.max_correction_um is not None:
        return config
    bound = min(default_max_correction_um(model), CORRECTION_LIMIT_UM)
    return config.model_copy(update={"max_correction_um": bound})


@dataclass(frozen=True)
class FusedState:
    """The model's state, the observer's, and the age of the last accepted measurement."""

    model: Any
    observer: ObserverState
    since_measurement_s: float | None = None
    """Seconds since the last accepted measurement; None before the first."""

    @property
    def elongation_um(self) -> float:
        return float(self.model.elongation_um) + self.observer.bias_um

    @property
    def bias_um(self) -> float:
        return self.observer.bias_um


@dataclass(frozen=True)
class FusedPredictor:
    """``model`` with measurements fused in by the observer ``config``."""

    model: Predictor
    config: ObserverConfig

    def __post_init__(self) -> None:
        if isinstance(self.model, FusedPredictor):
            raise ModelError("a fused model cannot be fused again")
        # the bounds hold wherever a model is fused: the service, replay, a test
        object.__setattr__(self, "config", with_bounds(self.config, self.model))

    # -- what the wrapped model says --------------------------------------------------
    @property
    def format(self) -> str:
        return self.model.format

    @property
    def spindle_id(self) -> str:
        return self.model.spindle_id

    @property
    def machine_id(self) -> str:
        return self.model.machine_id

    @property
    def form(self) -> str:
        return f"{self.model.form}+observer"

    @property
    def speed_range_rpm(self) -> tuple[float, float]:
        return self.model.speed_range_rpm

    @property
    def input_names(self) -> tuple[str, ...]:
        return self.model.input_names

    @property
    def fallback(self) -> FusedPredictor | None:
        fb = self.model.fallback
        return None if fb is None else FusedPredictor(fb, self.config)

    def above_range(self, speed_rpm: float) -> bool:
        return self.model.above_range(speed_rpm)

    def check_inputs(self, values: Mapping[str, float]) -> str | None:
        return self.model.check_inputs(values)

    def outside_trained(self, values: Mapping[str, float]) -> str | None:
        outside = getattr(self.model, "outside_trained", None)
        return None if outside is None else outside(values)

    def model_dump(self, **kwargs: Any) -> dict[str, Any]:
        return self.model.model_dump(**kwargs)

    # -- the Predictor interface -----------------------------------------------------------
    def start(
        self,
        elongation_um: float | None,
        speed_rpm: float,
        inputs: Mapping[str, float] | None = None,
        references: Mapping[str, float] | None = None,
    ) -> FusedState:
        return FusedState(
            self.model.start(elongation_um, speed_rpm, inputs, references),
            ObserverState.prior(self.config),
        )

    def step(
        self,
        state: FusedState,
        speed_rpm: float,
        dt_s: float,
        inputs: Mapping[str, float] | None = None,
    ) -> FusedState:
        inner = self.model.step(state.model, speed_rpm, dt_s, inputs)
        age = None if state.since_measurement_s is None else state.since_measurement_s + dt_s
        return FusedState(inner, time_update(self.config, state.observer, dt_s), age)

    def simulate_um(
        self,
        speed_rpm: np.ndarray,
        time_s: np.ndarray,
        inputs: Mapping[str, np.ndarray] | None = None,
        initial_um: float | None = None,
    ) -> np.ndarray:
        """Without measurements the fused model is the model."""
        return self.model.simulate_um(speed_rpm, time_s, inputs, initial_um)

    def measure(
        self,
        state: FusedState,
        measured_um: float,
        sigma_um: float,
        model_at_probe_um: float | None = None,
        source: str = "measurement",
    ) -> tuple[FusedState, Update]:
        """Fuse one measurement of the elongation [um], with its sigma [um], from ``source`` (the
        bounds count each source's moves apart).

        ``model_at_probe_um``: the model's own elongation at the instant the measurement was
        taken, when that was not now (a tool setter measures with the spindle stopped, and the
        value is read after it has started again: the model's fast part has moved since). The
        bias is taken as unchanged over that short while. Default: the model's now."""
        at = float(state.model.elongation_um) if model_at_probe_um is None else model_at_probe_um
        first = state.since_measurement_s is None  # none taken yet: a start from nothing
        up = measurement_update(
            self.config, state.observer, measured_um, at, sigma_um, source, first
        )
        age = 0.0 if up.accepted or up.restarted else state.since_measurement_s
        return FusedState(state.model, up.state, age), up

    def rebase(self, state: FusedState, model_state: Any) -> FusedState:
        """``model_state`` in place of the model's (a switch between a model and its fallback),
        the bias shifted so that the fused elongation does not jump."""
        shift = float(state.model.elongation_um) - float(model_state.elongation_um)
        return replace(
            state,
            model=model_state,
            observer=replace(state.observer, bias_um=state.observer.bias_um + shift),
        )

    def is_stale(self, state: FusedState, max_age_s: float) -> bool:
        """No accepted measurement for longer than ``max_age_s`` (or none yet)."""
        return state.since_measurement_s is None or state.since_measurement_s > max_age_s

    def state_dict(self, state: FusedState) -> dict[str, Any]:
        z = state.observer
        return {
            **self.model.state_dict(state.model),
            OBSERVER_KEY: {
                "bias_um": z.bias_um,
                "drift_um_per_s": z.drift_um_per_s,
                "cov": [list(r) for r in z.cov],
                "since_measurement_s": state.since_measurement_s,
                "moved_um": dict(z.moved_um),
                "drift_by_um_per_s": dict(z.drift_by_um_per_s),
            },
        }

    def state_from_dict(self, data: Mapping[str, Any]) -> FusedState:
        """A state saved by :meth:`state_dict`, or the model's own (observer at its prior)."""
        inner = self.model.state_from_dict({k: v for k, v in data.items() if k != OBSERVER_KEY})
        saved = data.get(OBSERVER_KEY)
        if saved is None:
            return FusedState(inner, ObserverState.prior(self.config))
        try:
            b, r = saved_numbers("observer bias/drift", [saved["bias_um"], saved["drift_um_per_s"]])
            c = saved_numbers("observer cov", [v for row in saved["cov"] for v in row], COV_LIMIT)
            age = saved.get("since_measurement_s")
            if age is not None:
                (age,) = saved_numbers("observer age", [age])
            moved_in = saved.get("moved_um") or {}  # a state saved before the bounds: none
            if not isinstance(moved_in, Mapping):
                raise TypeError("moved_um is no mapping")
            moved = tuple(
                (str(k), v)
                for k, v in zip(moved_in, saved_numbers("observer moves", list(moved_in.values())))
                if v != 0.0
            )
            shares_in = saved.get("drift_by_um_per_s") or {}  # saved before: nobody's drift
            if not isinstance(shares_in, Mapping):
                raise TypeError("drift_by_um_per_s is no mapping")
            shares = tuple(
                (str(k), v)
                for k, v in zip(
                    shares_in, saved_numbers("observer drift", list(shares_in.values()))
                )
                if v != 0.0
            )
        except (KeyError, TypeError, ValueError) as err:
            raise ModelError(f"saved observer state is not valid ({err})") from err
        if len(c) != 4 or c[0] < 0 or c[3] < 0 or (age is not None and age < 0):
            raise ModelError("saved observer state is not valid (covariance or age)")
        cov = ((c[0], c[1]), (c[2], c[3]))
        return FusedState(inner, ObserverState(b, r, cov, (), moved, shares), age)

    def describe(self) -> list[str]:
        c = self.config
        return [
            *self.model.describe(),
            f"  observer: bias random walk {math.sqrt(c.bias_q_um2_per_s * 3600):.2f} um/sqrt(h), "
            f"drift {'on' if c.drift_q_um2_per_s3 > 0 else 'off'}, model sd {c.model_sd_um:.2f} um, "
            f"gate {c.gate_sigma:g} sd, restart after {c.reaccept_after} agreeing refusals",
            f"  observer bounds: |correction| <= {c.max_correction_um:g} um, one source moves it "
            f"<= {c.source_move_um:g} um net per {c.window_s:g} s",
        ]
