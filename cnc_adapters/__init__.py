"""Controller and sensor links: OPC UA, serial (line, Haas, Modbus RTU), LinuxCNC, and the
virtual machine tool (``sim``), all behind one :class:`~cnc_adapters.base.Adapter` base.

This package imports only the pure core (:mod:`compensator`, never its files) and nothing of
calibration or the runtime.
"""

from .base import (
    Adapter,
    AdapterError,
    AdapterSettings,
    AdapterTimeoutError,
    BadValueError,
    ConfigError,
    Link,
    UnreachableError,
    WriteRejectedError,
    redact_url,
)
from .reading import (
    LIFE_MODULUS,
    Capabilities,
    Failure,
    FailureKind,
    Life,
    Measurement,
    Reading,
    Wants,
    WriteResult,
)
from .registry import BACKENDS, backend, check_adapter, open_adapter, settings_model

__all__ = [
    "BACKENDS",
    "LIFE_MODULUS",
    "Adapter",
    "AdapterError",
    "AdapterSettings",
    "AdapterTimeoutError",
    "BadValueError",
    "Capabilities",
    "ConfigError",
    "Failure",
    "FailureKind",
    "Life",
    "Link",
    "Measurement",
    "Reading",
    "UnreachableError",
    "Wants",
    "WriteRejectedError",
    "WriteResult",
    "backend",
    "check_adapter",
    "open_adapter",
    "redact_url",
    "settings_model",
]
