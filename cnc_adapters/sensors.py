"""Displacement sensors for calibration: the eddy-current probe at the spindle nose.

One base class, :class:`Sensor`, with the template method :meth:`Sensor.read_um`: it reads a
raw value from the backend, converts it (``um = raw * scale + offset_um``), refuses
non-finite values and reports a reading beyond the sensor's measuring range
(``range_um``) as :class:`SensorOverRangeError`. Backends, registered by name:

- ``ascii``: an amplifier on a serial line that sends one ASCII reading per line, polled
  with ``request`` or streaming on its own (``request`` empty). Typical reply
  ``+0123.45``; ``over_range`` matches the amplifier's out-of-range token (``OVER``,
  ``----``, ...).
- ``modbus``: a Modbus RTU input (or holding) register of a DAQ module or amplifier.
- ``opcua``: a node on an OPC UA server (a DAQ gateway, or the virtual machine tool's
  ``Displacement`` with ``preset=virtual-cnc``).

:func:`open_sensor` builds one from a URL (``serial:///dev/ttyUSB1?baudrate=9600&scale=-1``,
``serial:///dev/ttyUSB1?protocol=modbus&register=2&type=int16&scale=0.1``,
``opc.tcp://host:4840/?preset=virtual-cnc``) or a mapping with a ``type``, its options checked
first against the sensor's settings model (:func:`settings_model`): one
:class:`~compensator.errors.ConfigError` line for a misspelt key or a bad value. Sign: positive
elongation moves the tool tip toward the workpiece; a probe facing the nose reads a smaller
gap as the spindle grows, so such a probe needs a negative ``scale``.
"""

from __future__ import annotations

import math
import re
import warnings
from abc import abstractmethod
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, BeforeValidator, Field, model_validator

from compensator.errors import SensorOverRangeError

from .base import (
    AdapterError,
    Allowed,
    BadValueError,
    ConfigError,
    Finite,
    Link,
    LinkSettings,
    NonZero,
    Pattern,
    Seconds,
    ValuePattern,
    build,
    one_of,
    query_params,
    redact_url,
    serial_options,
)
from .modbus import DataType, ModbusLink, ModbusLinkSettings, Register, Table, check_types
from .opcua import OpcUaLink, OpcUaLinkSettings, url_has_password, url_password_refusal
from .serial_link import NUMBER, SerialLine, SerialSettings

ABSOLUTE_LIMIT_UM = 1e6  # 1 m: anything beyond is a unit or wiring fault, not a reading


def _range(value: Any) -> tuple[float, float] | None:
    if value is None or value == "":
        return None
    if isinstance(value, str):
        value = value.split(",")
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError) as err:
        raise AdapterError(f"sensor range_um {value!r}: give two numbers 'low,high'") from err
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise AdapterError(f"sensor range_um {value!r}: need finite low < high")
    return lo, hi


def _range_option(v: Any) -> Any:
    try:
        return _range(v)
    except AdapterError:
        raise ValueError("two finite numbers 'low,high' with low < high") from None


def _codes(v: Any) -> Any:
    # a URL gives the codes as one comma-separated string
    return tuple(float(c) for c in v.split(",") if c.strip()) if isinstance(v, str) else v


RangeUm = Annotated[
    tuple[float, float] | None,
    BeforeValidator(_range_option),
    Allowed("two finite numbers 'low,high' with low < high"),
]


class SensorSettings(LinkSettings):
    """Options of every displacement sensor."""

    scale: NonZero = Field(1.0, description="um per raw unit; negative for a probe facing the nose")
    offset_um: Finite = Field(0.0, description="added after scaling")
    range_um: RangeUm = Field(None, description="the measuring range: beyond it, over-range")


class AsciiSettings(SerialSettings, SensorSettings):
    """The options of :class:`AsciiSensor`."""

    baudrate: Annotated[int, Field(gt=0), Allowed("a whole number > 0 (bits per second)")] = 9600
    timeout_s: Seconds = 1.0
    request: str | None = Field(None, description="sent to poll a reading; none: it streams")
    reply: ValuePattern = rf"(?P<value>{NUMBER})"
    over_range: Pattern = r"(?i)(OVER|UNDER|OUT\s*OF\s*RANGE|OVR|OOR|-{3,}|\+{3,})"


with warnings.catch_warnings():
    # the option is called "register"; it shadows ABCMeta.register, which nothing calls here
    warnings.filterwarnings("ignore", message='Field name "register"', category=UserWarning)

    class ModbusSensorSettings(ModbusLinkSettings, SensorSettings):
        """The options of :class:`ModbusSensor`."""

        table: Table = "input"
        register: Register = 0
        type: DataType = "int16"
        saturated_raw: Annotated[
            tuple[Finite, ...] | None,
            BeforeValidator(_codes),
            Allowed("raw codes 'a,b' the module sends when over range"),
        ] = None


if TYPE_CHECKING:  # a plain string to the type checker; pydantic checks the choice
    SensorPreset = str
else:
    SensorPreset = one_of("virtual-cnc")


class OpcUaSensorSettings(OpcUaLinkSettings, SensorSettings):
    """The options of :class:`OpcUaSensor`."""

    preset: SensorPreset | None = None
    node: str | None = Field(None, description="node id of the displacement ({ns} allowed)")
    path: str | None = Field(None, description="browse path of the displacement")

    @model_validator(mode="after")
    def _where(self) -> OpcUaSensorSettings:
        if not (self.node or self.path or self.preset):
            raise ValueError("give node (a node id), path (a browse path) or a preset")
        return self


class Sensor(Link):
    """A displacement reading in um: ``raw * scale + offset_um``, within ``range_um``."""

    Settings: ClassVar[type[BaseModel] | None] = None

    def __init__(
        self,
        *,
        scale: float = 1.0,
        offset_um: float = 0.0,
        range_um: tuple[float, float] | str | None = None,
        **link: Any,
    ):
        scale, offset_um = float(scale), float(offset_um)
        if not (math.isfinite(scale) and scale != 0 and math.isfinite(offset_um)):
            raise AdapterError(
                f"{self.name} sensor: scale must be finite and non-zero, offset finite"
            )
        super().__init__(**link)
        self.scale = scale
        self.offset_um = offset_um
        self.range_um = _range(range_um)

    def read_um(self) -> float:
        """One reading [um]. :class:`SensorOverRangeError` when out of range,
        :class:`BadValueError` when not a finite number."""
        self.open()
        raw = self._read_raw()
        try:
            value = float(raw) * self.scale + self.offset_um
        except (TypeError, ValueError) as err:
            raise BadValueError(f"{self.name} sensor: reading {raw!r} is not a number") from err
        if not math.isfinite(value) or abs(value) > ABSOLUTE_LIMIT_UM:
            raise BadValueError(f"{self.name} sensor: reading is {value}")
        if self.range_um is not None and not self.range_um[0] <= value <= self.range_um[1]:
            lo, hi = self.range_um
            raise SensorOverRangeError(
                f"{self.name} sensor: {value:.2f} um is outside its range {lo:g}..{hi:g} um"
            )
        return value

    @abstractmethod
    def _read_raw(self) -> Any: ...


class AsciiSensor(SerialLine, Sensor):
    """An amplifier that gives one ASCII reading per line on a serial port."""

    name = "ascii"
    Settings = AsciiSettings

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 9600,
        timeout_s: float = 1.0,
        request: str | None = None,
        reply: str = rf"(?P<value>{NUMBER})",
        over_range: str = r"(?i)(OVER|UNDER|OUT\s*OF\s*RANGE|OVR|OOR|-{3,}|\+{3,})",
        eol: str = "\r\n",
        **kw: Any,
    ):
        super().__init__(**kw)
        self._init_serial(port, baudrate, timeout_s, eol)
        self.request = request or None
        try:
            self.reply = re.compile(reply)
            self.over_range = re.compile(over_range)
        except re.error as err:
            raise AdapterError(f"ascii sensor: bad pattern: {err}") from err
        if "value" not in self.reply.groupindex:
            raise AdapterError("ascii sensor: reply needs a (?P<value>...) group")

    def _read_raw(self) -> float:
        line = self.exchange(self.request)
        if self.over_range.search(line):
            raise SensorOverRangeError(f"ascii sensor: amplifier reports out of range ({line!r})")
        m = self.reply.search(line)
        if m is None:
            raise BadValueError(f"ascii sensor: no reading in {line!r}")
        return float(m.group("value"))


class ModbusSensor(ModbusLink, Sensor):
    """A Modbus RTU register holding the displacement (raw counts times ``scale``)."""

    name = "modbus"
    Settings = ModbusSensorSettings

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 19200,
        parity: Literal["N", "E", "O"] = "N",
        device_id: int = 1,
        table: Literal["input", "holding"] = "input",
        register: int = 0,
        type: str = "int16",
        word_order: Literal["big", "little"] = "big",
        byte_order: Literal["big", "little"] = "big",
        timeout_s: float = 0.5,
        saturated_raw: tuple[float, ...] | str | None = None,
        **kw: Any,
    ):
        super().__init__(**kw)
        check_types("modbus sensor", type)
        if table not in ("input", "holding"):
            raise AdapterError("modbus sensor: table is 'input' or 'holding'")
        self._init_modbus(port, baudrate, parity, device_id, word_order, byte_order, timeout_s)
        self.table, self.register, self.dtype = table, int(register), type
        if isinstance(saturated_raw, str):
            saturated_raw = tuple(float(v) for v in saturated_raw.split(",") if v)
        # raw codes a module sends for over/under range (e.g. 32767 / -32768 on many AI modules)
        self.saturated_raw = tuple(saturated_raw or ())

    def _read_raw(self) -> float:
        value = self._read_value("read displacement", self.table, self.register, self.dtype)
        if value in self.saturated_raw:
            raise SensorOverRangeError(
                f"modbus sensor: register {self.register} holds the over-range code {value:g}"
            )
        return value


class OpcUaSensor(OpcUaLink, Sensor):
    """A displacement node on an OPC UA server (the OPC UA adapter's session and security)."""

    name = "opcua"
    Settings = OpcUaSensorSettings
    PRESETS: ClassVar[dict[str, dict[str, str]]] = {
        "virtual-cnc": {
            "namespace_uri": "urn:thermocomp:virtual-cnc",
            "node": "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/Displacement",
        }
    }

    def __init__(
        self,
        url: str,
        *,
        preset: str | None = None,
        node: str | None = None,
        path: str | None = None,
        namespace_uri: str | None = None,
        timeout_s: float = 4.0,
        security: str = "None",
        certificate: str | None = None,
        private_key: str | None = None,
        trust_dir: str | None = None,
        username_env: str = "THERMOCOMP_OPCUA_USER",
        password_env: str = "THERMOCOMP_OPCUA_PASSWORD",
        password_file: str | None = None,
        password_credential: str | None = None,
        application_uri: str = "urn:thermocomp:client",
        **kw: Any,
    ):
        super().__init__(**kw)
        p = self.PRESETS.get(preset or "", {})
        if preset and not p:
            raise AdapterError(
                f"opcua sensor: unknown preset {preset!r}; known: {', '.join(self.PRESETS)}"
            )
        self.node_id = node or (None if path else p.get("node"))
        self.path = None if self.node_id else path
        if not (self.node_id or self.path):
            raise AdapterError("opcua sensor: give node (node id), path (browse path) or a preset")
        self._init_opcua(
            url,
            namespace_uri=namespace_uri or p.get("namespace_uri"),
            timeout_s=timeout_s,
            security=security,
            certificate=certificate,
            private_key=private_key,
            trust_dir=trust_dir,
            username_env=username_env,
            password_env=password_env,
            password_file=password_file,
            application_uri=application_uri,
            password_credential=password_credential,
        )
        self._node: Any = None  # its asyncua Node, once connected

    def _on_connected(self, client: Any, ns: str) -> None:
        self._node = self._resolve(client, self.node_id, self.path, ns)
        self._call("read displacement node", self._node.read_value, node=self._node)

    def _read_raw(self) -> Any:
        value = self._call("read displacement node", self._node.read_value, node=self._node)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise BadValueError(
                f"{self._where('read displacement node', self._node)}: holds "
                f"{type(value).__name__}, not a number"
            )
        return value

    def _forget(self) -> None:
        self._node = None


SENSORS: dict[str, type[Sensor]] = {
    "ascii": AsciiSensor,
    "modbus": ModbusSensor,
    "opcua": OpcUaSensor,
}


def settings_model(kind: str) -> type[BaseModel]:
    """The pydantic model of the options of sensor ``kind`` (``ascii``, ``modbus``, ``opcua``)."""
    cls = SENSORS.get(kind)
    if cls is None:
        raise ConfigError(f"unknown sensor type {kind!r}; known: {', '.join(SENSORS)}")
    return cls.Settings  # type: ignore[return-value]


def _resolve(
    target: str | Mapping[str, Any], overrides: Mapping[str, Any]
) -> tuple[str, dict[str, Any]]:
    """The sensor type and its options, from a URL or a mapping."""
    if isinstance(target, str):
        parts = urlsplit(target)
        if parts.scheme == "serial":
            kind = query_params(target).get("protocol", "ascii")
            if kind not in ("ascii", "modbus"):
                raise ConfigError(f"unknown serial sensor protocol {kind!r}; known: ascii, modbus")
            return kind, {**serial_options(target), **overrides}
        if parts.scheme == "opc.tcp":
            if url_has_password(target):
                env = {**query_params(target), **overrides}.get(
                    "password_env"
                ) or "THERMOCOMP_OPCUA_PASSWORD"
                raise ConfigError(f"opcua sensor: {url_password_refusal(str(env))}")
            return "opcua", {"url": target.split("?", 1)[0], **query_params(target), **overrides}
        raise ConfigError(f"no sensor for URL scheme {parts.scheme!r} in {redact_url(target)!r}")
    cfg = dict(target)
    kind = cfg.pop("type", None)
    if kind is None and "url" in cfg:
        url = cfg.pop("url")
        if not isinstance(url, str):
            raise ConfigError(f"sensor url must be a string, not {type(url).__name__}")
        return _resolve(url, {**cfg, **overrides})
    settings_model(str(kind))  # an unknown type, said as such
    return str(kind), {**cfg, **overrides}


def open_sensor(target: str | Mapping[str, Any], **overrides: Any) -> Sensor:
    """A sensor from a URL or a mapping with a ``type`` (not yet connected), its options
    validated first."""
    kind, options = _resolve(target, overrides)
    return build(f"{kind} sensor", SENSORS[kind], options)
