"""Units and the checks every value passes once, at the boundary. Pure: no I/O.

Conventions (all of thermocomp): speeds in rpm, positive or negative (reverse rotation);
the thermal model sees only |n|, in krpm. Elongation in um, positive toward the workpiece;
the offset written to the controller is ``A = -S`` in um until the adapter contract converts
it to the controller's own unit and sign with :class:`ControllerUnits`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .errors import ConfigError, NonFiniteInputError

SPEED_SCALE_RPM = 1000.0
"""Speeds are scaled to krpm inside the model: coefficients are per krpm**i."""

RANGE_TOLERANCE = 0.02
"""Speeds up to 2 % above the calibrated maximum still count as in range."""


def require_finite(name: str, value: float) -> float:
    """``value`` as a float; :class:`NonFiniteInputError` naming ``name`` if NaN or inf."""
    v = float(value)
    if not math.isfinite(v):
        raise NonFiniteInputError(f"{name} is {value}")
    return v


def require_dt(dt_s: float) -> float:
    """A finite, non-negative time step [s]."""
    dt = require_finite("dt_s", dt_s)
    if dt < 0:
        raise NonFiniteInputError(f"dt_s must be >= 0, got {dt_s}")
    return dt


def speed_magnitude_rpm(speed_rpm: float) -> float:
    """|n| [rpm]: heat does not depend on the direction of rotation."""
    return abs(require_finite("speed_rpm", speed_rpm))


def speed_krpm(speed_rpm: float) -> float:
    """|n| [krpm], the model's internal speed."""
    return speed_magnitude_rpm(speed_rpm) / SPEED_SCALE_RPM


@dataclass(frozen=True, slots=True)
class ControllerUnits:
    """The controller's offset unit and sign: ``raw = offset_um * scale * sign``.

    ``scale`` is the controller unit per um (0.001 for mm), ``sign`` -1 for a controller whose
    thermal offset points the other way, ``resolution`` one count of the controller's value in
    its unit (0: continuous); the raw value is rounded to it. The shaper already moves in whole
    counts (``ShaperConfig.resolution_um``), so the rounding only removes float noise there.
    The one place where um meet controller units.
    """

    scale: float = 1.0
    sign: int = 1
    resolution: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.sign, bool) or self.sign not in (1, -1):
            raise ConfigError(f"offset_sign must be +1 or -1, not {self.sign!r}")
        object.__setattr__(self, "sign", int(self.sign))  # 1.0 -> 1
        if not (math.isfinite(self.scale) and self.scale != 0):
            raise ConfigError("offset_scale must be finite and non-zero")
        if not (math.isfinite(self.resolution) and self.resolution >= 0):
            raise ConfigError("offset_resolution must be a finite number >= 0")

    @property
    def resolution_um(self) -> float:
        """One count as an offset [um] (0: continuous)."""
        return self.resolution / abs(self.scale)

    def to_controller(self, offset_um: float) -> float:
        raw = offset_um * self.scale * self.sign
        if self.resolution:
            raw = round(raw / self.resolution) * self.resolution
        return raw

    def to_um(self, raw: float) -> float:
        return raw / (self.scale * self.sign)
