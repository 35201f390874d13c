"""Controller and sensor links: OPC UA, serial (line, Haas, Modbus RTU), LinuxCNC, and the
virtual machine tool (``sim``), all behind one :class:`~cnc_adapters.base.Adapter` base.

This package imports only the pure core (:mod:`compensator`, never its files) and nothing of
calibration or the runtime.
"""

from .base import (
    Adapter,
    AdapterError,
    AdapterTimeoutError,
    BadValueError,
    Link,
    UnreachableError,
    WriteRejectedError,
)
from .registry import BACKENDS, backend, open_adapter

__all__ = [
    "BACKENDS",
    "Adapter",
    "AdapterError",
    "AdapterTimeoutError",
    "BadValueError",
    "Link",
    "UnreachableError",
    "WriteRejectedError",
    "backend",
    "open_adapter",
]
