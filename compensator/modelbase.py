"""What every thermal model value shares. Pure: no I/O.

- :class:`ModelBase`: the identity and fit metadata every model file carries (format, spindle,
  machine, fit statistics, creation time), immutability, and one way to fail: any invalid
  field is a one-line :class:`~compensator.errors.ModelError` (:func:`model_error`).
- :class:`Channel`: a measured input (name, unit, plausible range), and :func:`check_inputs`,
  the one judge of the values a model is about to use: a bool is not a number.
- :func:`saved_numbers`: numbers read back from a saved runtime state.
- :func:`with_fit`: the model with entries of its fit record
  (:class:`~compensator.fitrecord.FitRecord`) changed.

:mod:`compensator.model` (speed only), :mod:`compensator.statespace` and
:mod:`compensator.inputs` build on it; their file formats are unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Self, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .errors import ModelError
from .fitrecord import FitRecord
from .units import RANGE_TOLERANCE, speed_magnitude_rpm

SAVED_LIMIT_UM = 1e4
"""No thermal state of a spindle is 10 mm: a saved value beyond this is a corrupt file."""

MIN_TOP_RPM = 10.0
"""The least top speed a calibration reaches [rpm]: a spindle turned slower heats too little to
calibrate (the largest vertical lathes still turn their table at tens of rpm). A lower top makes
every real speed read as impossible (above twice the calibrated top), compensation effectively
off."""
MIN_RANGE_SHARE = 0.05
"""The least share of a spindle's rated top speed (``faults.max_speed_rpm``) its model's calibrated
range must reach. The calibration programs step the spindle across its range (each step at 11 %
of the top or more, the highest near the top), so no calibration of that spindle tops below 5 %;
a model calibrated on part of the range (a shop that never runs the top) stays well above it.
Below it the model is another spindle's, or a test's: every speed the spindle turns is clamped
to a top at which it barely heats."""
MAX_TOP_RPM = 1e6
"""The most a calibrated top speed can be [rpm]: no run log holds a faster one
(``compensator.io.runlog.MAX_SPEED_RPM``)."""
MIN_FITTED_DT_S = 1e-3
"""The shortest sample period of a calibration [s]: a thermal log is sampled in seconds."""
MAX_FITTED_DT_S = 86400.0
"""The longest sample period of a calibration [s]: sampled more rarely than daily, a log sees
no thermal time constant."""
MAX_MODEL_UM = 1e6
"""The largest |elongation| a model may hold at equilibrium anywhere in its calibrated range, per
thermal state or in all [um]: no run log holds more (``compensator.io.runlog``'s 1 m), so no
calibration fits more, and beyond it a model's arithmetic nears a double's range (overflow)."""

CHANNEL_NAME = r"^[A-Za-z0-9_.-]+$"
"""An input's name: a run-log column and a runtime channel."""


def saved_numbers(name: str, values: Any, limit: float = SAVED_LIMIT_UM) -> tuple[float, ...]:
    """Numbers read back from a saved state: a list of real numbers (not bools, not strings),
    finite and within ``limit``; :class:`ModelError` naming ``name`` otherwise."""
    if not isinstance(values, (list, tuple)):
        raise ModelError(f"saved {name} is a {type(values).__name__}, not a list of numbers")
    out = []
    for v in values:
        if not is_number(v):
            raise ModelError(f"saved {name} holds a {type(v).__name__}, not a number")
        try:
            f = float(v)
        except OverflowError as err:
            raise ModelError(f"saved {name} holds a number too large") from err
        if not (math.isfinite(f) and abs(f) <= limit):
            raise ModelError(f"saved {name} holds {f:g}, beyond {limit:g}")
        out.append(f)
    return tuple(out)


def is_number(value: Any) -> bool:
    """A real number: int or float, not a bool (``True`` is an int in Python, not a reading)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def model_error(err: ValidationError) -> ModelError:
    """Our own error from pydantic's: the original if we raised one, else one line."""
    for item in err.errors():
        original = (item.get("ctx") or {}).get("error")
        if isinstance(original, ModelError):
            return original
    item = err.errors()[0]
    where = ".".join(str(p) for p in item["loc"]) or "model"
    more = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
    return ModelError(f"{where}: {item['msg']}{more}")


def speed_range(value: tuple[float, float], *, positive_max: bool = True) -> tuple[float, float]:
    """A calibrated |speed| range, one a calibration can produce: finite, 0 <= min <= max and
    :data:`MIN_TOP_RPM` <= max <= :data:`MAX_TOP_RPM`. (``positive_max`` is kept for callers:
    every form now needs a top speed a spindle turns at.)"""
    lo, hi = value
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo < 0 or hi < lo:
        raise ValueError(f"speed_range_rpm must satisfy 0 <= min <= max, got {value}")
    if not MIN_TOP_RPM <= hi <= MAX_TOP_RPM:
        raise ModelError(
            f"speed_range_rpm tops at {hi:g} rpm: a calibration tops between {MIN_TOP_RPM:g} and "
            f"{MAX_TOP_RPM:g} rpm (below, every real speed would count as impossible)"
        )
    return value


def range_share_refusal(top_rpm: float, max_speed_rpm: float | None) -> str | None:
    """Why a model whose calibrated range tops at ``top_rpm`` cannot be the model of a spindle
    rated ``max_speed_rpm``, or None (also where no rated speed is configured)."""
    if max_speed_rpm is None or top_rpm >= MIN_RANGE_SHARE * max_speed_rpm:
        return None
    return (
        f"the model's calibrated range tops at {top_rpm:g} rpm, under {100 * MIN_RANGE_SHARE:g} % "
        f"of the spindle's max_speed_rpm {max_speed_rpm:g} ({MIN_RANGE_SHARE * max_speed_rpm:g} "
        "rpm): no calibration of this spindle tops that low; calibrate it on this spindle, or "
        "correct faults.max_speed_rpm"
    )


def fitted_dt(value: float) -> float:
    """A calibration's sample period: :data:`MIN_FITTED_DT_S` .. :data:`MAX_FITTED_DT_S`."""
    if not MIN_FITTED_DT_S <= value <= MAX_FITTED_DT_S:
        raise ModelError(
            f"fitted_dt_s {value:g} s is no calibration's sample period "
            f"({MIN_FITTED_DT_S:g} .. {MAX_FITTED_DT_S:g} s)"
        )
    return value


class Channel(BaseModel):
    """A measured input (a temperature, the spindle load...) a model reads besides speed."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(pattern=CHANNEL_NAME, description="run-log column / runtime channel")
    unit: str = Field(description="unit of the input: degC, %, ...")
    valid_range: tuple[float, float] = Field(description="plausible values; outside: sensor fault")

    @model_validator(mode="after")
    def _valid_range(self) -> Channel:
        lo, hi = self.valid_range
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise ValueError(f"input {self.name}: valid_range must be finite with min <= max")
        return self


def check_inputs(channels: Sequence[Channel], values: Mapping[str, Any]) -> str | None:
    """Why ``values`` cannot be used for ``channels`` (missing, not a finite number, outside
    the valid range), or None. A bool is not a number."""
    for c in channels:
        v = values.get(c.name)
        if v is None:
            return f"{c.name}: no value"
        if not is_number(v) or not math.isfinite(v):
            return f"{c.name}: {v!r} is not a finite number"
        lo, hi = c.valid_range
        if not lo <= v <= hi:
            return f"{c.name}: {v:g} {c.unit} is outside {lo:g}..{hi:g}"
    return None


FIT_SUMMARY = (
    "method",
    "folds",
    "alpha",
    "cv_rms_um",
    "cv_max_abs_um",
    "nested_rms_um",
    "forward_rms_um",
)
"""The fit record's entries a model's description shows."""


class ModelBase(BaseModel):
    """Fields, checks and errors every model value shares; subclasses fix ``format`` to their
    own literal (the key :data:`compensator.io.modelfile.MODEL_TYPES` dispatches on) and keep
    their own coefficients. Invalid data raises :class:`ModelError`, never pydantic's error."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    format: str
    spindle_id: str = "unknown"
    machine_id: str = ""
    fit: FitRecord = Field(default_factory=FitRecord, description="fit statistics")
    created_utc: str | None = None

    def __init__(self, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as err:
            raise model_error(err) from err

    @classmethod
    def model_validate(cls, obj: Any, **kwargs: Any) -> Self:
        try:
            return super().model_validate(obj, **kwargs)
        except ValidationError as err:
            raise model_error(err) from err

    # every form's sample period (the field is each form's own)
    @field_validator("fitted_dt_s", check_fields=False)
    @classmethod
    def _fitted_dt(cls, value: float) -> float:
        return fitted_dt(value)

    # the largest growth a calibration measured (the state-space form's gains are held to ten
    # times it): no more than a run log can hold
    @field_validator("max_measured_um", check_fields=False)
    @classmethod
    def _measured(cls, value: float) -> float:
        if not value <= MAX_MODEL_UM:
            raise ModelError(
                f"max_measured_um {value:g} um is more than any calibration measures "
                f"({MAX_MODEL_UM:g} um)"
            )
        return value

    @field_validator("fit", mode="before")
    @classmethod
    def _fit_record(cls, value: Any) -> FitRecord:
        # None (no record) is the empty record: readers never check for it
        return FitRecord.of(value)

    def model_copy(self, *, update: Mapping[str, Any] | None = None, deep: bool = False) -> Self:
        """pydantic's copy, with a ``fit`` in ``update`` made a checked :class:`FitRecord`
        (a copy does not validate, and a dict there would reach the file and the runtime)."""
        if update is not None and "fit" in update:
            update = {**update, "fit": FitRecord.of(update["fit"])}
        return super().model_copy(update=update, deep=deep)

    @model_validator(mode="after")
    def _distinct_inputs(self) -> ModelBase:
        names = self.input_names
        if len(set(names)) != len(names):
            raise ModelError("an input appears twice")
        return self

    @model_validator(mode="after")
    def _inputs_bounded(self) -> ModelBase:
        # an input's own gain (the earlier with-inputs form) over its valid range: within what a
        # calibration measures, as the speed part's equilibrium is
        for c in self.channels:
            gain = getattr(c, "gain_um_per_unit", None)
            lo, hi = c.valid_range
            if gain is not None and not abs(gain) * (hi - lo) <= MAX_MODEL_UM:
                raise ModelError(
                    f"input {c.name}: its gain {gain:g} um per {c.unit} moves the elongation "
                    f"{abs(gain) * (hi - lo):.4g} um over its valid range: beyond "
                    f"{MAX_MODEL_UM:g} um, more than any calibration measures"
                )
        return self

    def replace(self, **changes: Any) -> Any:
        """A new, re-validated model with some fields changed."""
        return type(self).model_validate({**self.model_dump(), **changes})

    @property
    def channels(self) -> tuple[Channel, ...]:
        """The measured inputs the model reads besides speed; none for a speed-only model."""
        return ()

    @property
    def input_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.channels)

    def fit_lines(self) -> list[str]:
        """The fit record's headline figures for a description, one line; its nested records
        (the error to expect, the observer) have their own printouts."""
        shown = [f"{k}={v}" for k, v in self.fit.as_dict().items() if k in FIT_SUMMARY]
        return ["  fit: " + ", ".join(shown)] if shown else []

    def check_inputs(self, values: Mapping[str, Any]) -> str | None:
        """Why these input values cannot be used (missing, non-finite, out of range), or None."""
        return check_inputs(self.channels, values)

    def above_range(self, speed_rpm: float) -> bool:
        """True above the calibrated range (with ``RANGE_TOLERANCE``): extrapolation. Every
        model has a ``speed_range_rpm``, a field or its speed part's."""
        # each subclass has it (ModelBase declares no field a subclass could not narrow)
        top = float(self.speed_range_rpm[1])  # type: ignore[attr-defined]
        return speed_magnitude_rpm(speed_rpm) > top * (1 + RANGE_TOLERANCE)


M = TypeVar("M", bound=ModelBase)


def with_fit(model: M, **changes: Any) -> M:
    """``model`` with entries of its fit record changed (:meth:`FitRecord.with_changes`): the
    one way a step after the identification adds to the record (the observer, the growth
    direction...)."""
    return model.model_copy(update={"fit": model.fit.with_changes(**changes)})
