"""Adapter backends by name, and :func:`open_adapter` (python-can's ``interface`` module).

Built-in backends are named here as ``"module:Class"`` and imported only when used, so a
backend's library (asyncua, pyserial, pymodbus, LinuxCNC's ``hal``) loads only where it is
configured. Third parties register theirs through the entry-point group
``thermocomp.adapters``.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from importlib.metadata import entry_points
from typing import Any
from urllib.parse import urlsplit

from .base import Adapter, AdapterError, construct, query_params

BACKENDS: dict[str, str] = {
    "sim": "cnc_adapters.sim.adapter:SimAdapter",
    "opcua": "cnc_adapters.opcua:OpcUaAdapter",
    "line": "cnc_adapters.serial_link:LineAdapter",
    "haas": "cnc_adapters.serial_link:HaasAdapter",
    "modbus": "cnc_adapters.modbus:ModbusRtuAdapter",
    "linuxcnc": "cnc_adapters.linuxcnc:LinuxCncAdapter",
}
SCHEMES = {"opc.tcp": "opcua", "sim": "sim", "linuxcnc": "linuxcnc"}
"""URL scheme -> backend; ``serial://`` picks its backend by ``?protocol=``."""
SERIAL_PROTOCOLS = {"line": "line", "haas": "haas", "modbus": "modbus"}
ENTRY_POINT_GROUP = "thermocomp.adapters"


def _load(spec: str) -> Any:
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


def backend(name: str) -> type[Adapter]:
    """The adapter class registered as ``name`` (built in, or by entry point)."""
    spec = BACKENDS.get(name)
    if spec is not None:
        return _load(spec)
    plugins = entry_points(group=ENTRY_POINT_GROUP)
    for ep in plugins:
        if ep.name == name:
            return ep.load()
    known = sorted(set(BACKENDS) | {ep.name for ep in plugins})
    raise AdapterError(f"unknown adapter {name!r}; known: {', '.join(known)}")


def open_adapter(target: str | Mapping[str, Any], **overrides: Any) -> Adapter:
    """An adapter from a URL or a mapping with a ``type`` key (not yet connected)."""
    if isinstance(target, str):
        scheme = urlsplit(target).scheme
        if scheme == "serial":
            protocol = query_params(target).get("protocol", "line")
            kind = SERIAL_PROTOCOLS.get(protocol)
            if kind is None:
                raise AdapterError(f"unknown serial protocol {protocol!r}; known: "
                                   f"{', '.join(SERIAL_PROTOCOLS)}")
        else:
            kind = SCHEMES.get(scheme)
            if kind is None:
                raise AdapterError(f"no adapter for URL scheme {scheme!r} in {target!r}")
        return construct(f"{kind} adapter", backend(kind).from_url,  # type: ignore[attr-defined]
                         target, **overrides)
    cfg = dict(target)
    kind = cfg.pop("type", None)
    if not kind and "url" in cfg:
        return open_adapter(cfg.pop("url"), **cfg, **overrides)
    if not kind:
        raise AdapterError("adapter configuration needs a 'type' or a 'url'")
    cfg.update(overrides)
    return construct(f"{kind} adapter", backend(kind), **cfg)
