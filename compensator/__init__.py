"""thermocomp compensator: the pure thermal model, offset shaping and the runtime."""

from .errors import (
    CalibrationError,
    ConfigError,
    ModelError,
    ModelFileError,
    NonFiniteInputError,
    RunLogError,
    ThermocompError,
    UnstableModelError,
)
from .model import (
    MODEL_FORMAT,
    SPEED_SCALE_RPM,
    DiscreteModel,
    ModelState,
    Simulation,
    ThermalModel,
    ThermalStateCoefficients,
)
from .shaping import Flag, OffsetShaper, ShapedOffset, ShaperConfig, ShaperState, TransientPolicy

__version__ = "0.1.0"

__all__ = [
    "MODEL_FORMAT",
    "SPEED_SCALE_RPM",
    "CalibrationError",
    "ConfigError",
    "DiscreteModel",
    "Flag",
    "ModelError",
    "ModelFileError",
    "ModelState",
    "NonFiniteInputError",
    "OffsetShaper",
    "RunLogError",
    "ShapedOffset",
    "ShaperConfig",
    "ShaperState",
    "Simulation",
    "ThermalModel",
    "ThermalStateCoefficients",
    "ThermocompError",
    "TransientPolicy",
    "UnstableModelError",
]
