"""thermocomp's pure core: the thermal models, the predictor interface, offset shaping, units,
speed programs and the clock protocol. No I/O here; files live in :mod:`compensator.io`."""

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
    DiscreteModel,
    ModelState,
    Simulation,
    ThermalModel,
    ThermalStateCoefficients,
)
from .predictor import Predictor
from .shaping import (
    CuttingSignal,
    Flag,
    OffsetShaper,
    ShapedOffset,
    ShaperConfig,
    ShaperState,
    TransientPolicy,
)
from .units import SPEED_SCALE_RPM, ControllerUnits

__all__ = [
    "MODEL_FORMAT",
    "SPEED_SCALE_RPM",
    "CalibrationError",
    "ConfigError",
    "ControllerUnits",
    "CuttingSignal",
    "DiscreteModel",
    "Flag",
    "ModelError",
    "ModelFileError",
    "ModelState",
    "NonFiniteInputError",
    "OffsetShaper",
    "Predictor",
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
