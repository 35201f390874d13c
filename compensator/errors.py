"""One exception tree for all of thermocomp.

Every error also subclasses the builtin it refines (python-control style), so
callers that only know ``ValueError`` or ``OSError`` still catch them.
"""

from __future__ import annotations


class ThermocompError(Exception):
    """Root of every error raised on purpose by thermocomp."""


class ModelError(ThermocompError, ValueError):
    """A thermal model is invalid."""


class UnstableModelError(ModelError):
    """A state's pole |a(n)| >= 1 somewhere in the calibrated speed range."""


class ModelFileError(ModelError):
    """A model file is unreadable, of an unknown schema, or tampered with."""


class NonFiniteInputError(ThermocompError, ValueError):
    """A speed, time step or elongation is NaN or infinite."""


class RunLogError(ThermocompError, ValueError):
    """A run log is malformed. ``path`` and ``line`` locate the fault."""

    def __init__(self, message: str, path: str | None = None, line: int | None = None):
        self.path = path
        self.line = line
        where = ""
        if path is not None:
            where = f"{path}:{line}: " if line is not None else f"{path}: "
        super().__init__(f"{where}{message}")


class ConfigError(ThermocompError, ValueError):
    """A configuration value is invalid."""


class CalibrationError(ThermocompError, ValueError):
    """Calibration data cannot produce a trustworthy model."""


class AcquisitionError(ThermocompError, RuntimeError):
    """A recording stopped on a fault (sensor lost, saturated, frozen). What was recorded is kept."""


# -- controller and sensor links (raised by cnc_adapters) ---------------------------------


class AdapterError(ThermocompError, OSError):
    """A controller or sensor link failed."""


class UnreachableError(AdapterError, ConnectionError):
    """The controller cannot be reached (refused, unplugged, lost)."""


class AdapterTimeoutError(AdapterError, TimeoutError):
    """The controller did not answer in time."""


class WriteRejectedError(AdapterError, PermissionError):
    """The controller refused a write (access denied, type mismatch, out of range)."""


class BadValueError(AdapterError, ValueError):
    """A value read from the controller, or about to be written, is not usable."""


class SensorOverRangeError(BadValueError):
    """The sensor reports its measuring range exceeded (the probe is saturated)."""
