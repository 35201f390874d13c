"""Adapter backends by name, and :func:`open_adapter` (python-can's ``interface`` module).

Built-in backends are named here as ``"module:Class"`` and imported only when used, so a
backend's library (asyncua, pyserial, pymodbus, LinuxCNC's ``hal``) loads only where it is
configured. Third parties register theirs through the entry-point group
``thermocomp.adapters``.

Every built-in backend declares its options as a pydantic model (:func:`settings_model`);
:func:`check_adapter` validates a configuration against it without constructing anything, and
:func:`open_adapter` does the same before it constructs, so a misspelt key or a bad value is
one :class:`~compensator.errors.ConfigError` line.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from importlib.metadata import entry_points
from typing import Any
from urllib.parse import urlsplit

from pydantic import BaseModel

from .base import (
    Adapter,
    ConfigError,
    Problem,
    SettingsError,
    build,
    check_settings,
    construct,
    query_params,
    redact_url,
    unknown,
    url_has_password,
)
from .control_profiles import adapter_settings

BACKENDS: dict[str, str] = {
    "sim": "machine_sim.adapter:SimAdapter",
    "opcua": "cnc_adapters.opcua:OpcUaAdapter",
    "line": "cnc_adapters.serial_link:LineAdapter",
    "haas": "cnc_adapters.serial_link:HaasAdapter",
    "modbus": "cnc_adapters.modbus:ModbusRtuAdapter",
    "linuxcnc": "cnc_adapters.linuxcnc:LinuxCncAdapter",
    "plc": "cnc_adapters.plc:PlcAdapter",
    "focas": "cnc_adapters.focas:FocasAdapter",
    "haas-mdc": "cnc_adapters.haas_mdc:HaasMdcAdapter",
}
SCHEMES = {
    "opc.tcp": "opcua",
    "sim": "sim",
    "linuxcnc": "linuxcnc",
    "s7": "plc",
    "modbustcp": "plc",
    "ads": "plc",
    "focas": "focas",
    "haas": "haas-mdc",
}
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
    raise ConfigError(unknown("adapter", name, known))


def settings_model(kind: str) -> type[BaseModel] | None:
    """The pydantic model of the options of backend ``kind`` (``"opcua"``, ``"sim"``, ...);
    None for a third-party backend that declares none. Imports the backend's module, not its
    library."""
    return getattr(backend(kind), "Settings", None)


def _url_kind(url: str) -> str:
    try:
        scheme = urlsplit(url).scheme
    except ValueError as err:
        raise ConfigError(f"adapter URL {redact_url(url)!r}: {err}") from err
    if scheme == "serial":
        protocol = query_params(url).get("protocol", "line")
        kind = SERIAL_PROTOCOLS.get(protocol)
        if kind is None:
            raise ConfigError(
                f"unknown serial protocol {protocol!r}; known: {', '.join(SERIAL_PROTOCOLS)}"
            )
        return kind
    kind = SCHEMES.get(scheme)
    if kind is None:
        raise ConfigError(f"no adapter for URL scheme {scheme!r} in {redact_url(url)!r}")
    return kind


def _refuse_password(kind: str, url: str, options: Mapping[str, Any]) -> None:
    """A password in a URL ends up in logs and process lists: refused, and never repeated."""
    if not url_has_password(url):
        return
    if kind == "opcua":
        from .opcua import url_password_refusal  # only where OPC UA is configured

        env = options.get("password_env") or "THERMOCOMP_OPCUA_PASSWORD"
        raise ConfigError(f"opcua adapter: {url_password_refusal(str(env))}")
    raise ConfigError(
        f"{kind} adapter: the URL carries a password, which this backend never uses: refused"
    )


def _resolve(
    target: str | Mapping[str, Any], overrides: Mapping[str, Any]
) -> tuple[str, type[Adapter], dict[str, Any] | None]:
    """The backend name, its class and its options (None: a third-party backend that parses
    its URL itself)."""
    if isinstance(target, str):
        kind = _url_kind(target)
        _refuse_password(kind, target, {**query_params(target), **overrides})
        cls = backend(kind)
        if getattr(cls, "Settings", None) is None:
            return kind, cls, None
        return kind, cls, {**cls.url_options(target), **overrides}
    cfg = adapter_settings(target)  # a controller profile's route and units, under the user's keys
    kind = cfg.pop("type", None)
    if not kind and "url" in cfg:
        url = cfg.pop("url")
        if not isinstance(url, str):
            raise SettingsError("adapter", [Problem("url", "expected a string (a URL)", url)])
        return _resolve(url, {**cfg, **overrides})
    if not kind:
        raise ConfigError("adapter configuration needs a 'type' or a 'url'")
    try:
        cls = backend(str(kind))
    except ConfigError as err:  # the key as written: the configuration names it under adapter
        raise SettingsError("adapter", [Problem("type", str(err), kind)]) from err
    return str(kind), cls, {**cfg, **overrides}


def check_adapter(target: str | Mapping[str, Any], **overrides: Any) -> BaseModel | None:
    """Validate an adapter configuration (a URL, or a mapping with a ``type`` or a ``url``)
    against its backend's settings model, constructing nothing and connecting nowhere: the
    validated settings (only the options given are set), or None for a third-party backend
    without a model. One :class:`ConfigError` line naming the key, the value and what is
    allowed when they do not validate; runtime-only keywords (clock, rng, ...) are ignored."""
    kind, cls, options = _resolve(target, overrides)
    if options is None:
        return None
    return check_settings(f"{kind} adapter", cls.Settings, options)  # type: ignore[arg-type]


def open_adapter(target: str | Mapping[str, Any], **overrides: Any) -> Adapter:
    """An adapter from a URL or a mapping with a ``type`` key (not yet connected), its options
    validated first (:func:`check_adapter`)."""
    kind, cls, options = _resolve(target, overrides)
    if options is None:
        return construct(f"{kind} adapter", cls.from_url, target, **overrides)
    return build(f"{kind} adapter", cls, options)
