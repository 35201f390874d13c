"""Spindle chiller links: thermocomp drives the coolant-temperature set point.

One base class, :class:`Chiller` (a :class:`~cnc_adapters.base.Link`: reconnection, back-off,
a context manager), with the template methods :meth:`Chiller.write_setpoint_c`,
:meth:`Chiller.read_setpoint_c` and :meth:`Chiller.read_supply_c`. They check values (finite,
within the configured device range ``min_c``..``max_c`` before anything is sent, a reading
within -50..150 degC) and convert degC to the device's raw unit (``scale_c`` degC per raw unit,
whole counts for an integer register); backends override only the raw calls. After a write
the set point is read back (``setpoint_readback``, on by default): a device that clamps or
ignores the value is a :class:`WriteRejectedError`, as is an exception reply to the write.

Backends, registered by name in :data:`CHILLERS` and built by :func:`open_chiller` (not yet
connected; options checked first, one :class:`ConfigError` line for a bad one):

- ``modbus``: Modbus TCP (``host``, ``port``) or RTU (``port`` a serial device, ``baudrate``,
  ``parity``, ``stopbits``) through pymodbus, as chiller controllers (Regloplas, Tool-Temp,
  Technotrans, Riedel, HYFRA) speak it: the set point in a holding register, the supply
  temperature in an input (or holding) register, each a signed ``int16`` in 0.1 degC
  (``scale_c``) or a ``float32`` in degC (``word_order``);
- ``opcua``: a set-point node and a supply node on an OPC UA server (a chiller reached through
  the CNC's or PLC's server); the session, security and credentials are the OPC UA adapter's
  (never a password in the configuration); an integer node is written in whole counts;
- ``virtual``: the chiller of a simulated plant (``plant=``, a
  :class:`~machine_sim.plant.SpindlePlant`), in process; ``reachable = False`` makes it
  unreachable, for tests.

Objects of the running program (``plant``, ``lock``, ``clock``, ``on_link_change``) are passed
to :func:`open_chiller` as keywords, never in the settings.
"""

from __future__ import annotations

import contextlib
import logging
import math
import numbers
from abc import abstractmethod
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Any, ClassVar

from pydantic import BaseModel, Field, model_validator

from .base import (
    AdapterError,
    Allowed,
    BadValueError,
    Baud,
    ConfigError,
    Finite,
    Link,
    LinkSettings,
    NonZero,
    Seconds,
    Text,
    UnreachableError,
    WriteRejectedError,
    check_settings,
    construct,
    key_error,
    one_of,
    short,
    unknown,
)
from .modbus import Order, Parity, Register, Table
from .opcua import OpcUaLink, OpcUaLinkSettings
from .transport.modbus import WIDTH, ModbusTransport, RegisterCodec

__all__ = [
    "CHILLERS",
    "PLAUSIBLE_C",
    "Chiller",
    "ChillerSettings",
    "ModbusChiller",
    "ModbusChillerSettings",
    "OpcUaChiller",
    "OpcUaChillerSettings",
    "VirtualChiller",
    "check_chiller",
    "open_chiller",
]

log = logging.getLogger("thermocomp.adapters.chiller")

PLAUSIBLE_C = (-50.0, 150.0)
"""A temperature read outside this is a wrong register, scale or sensor, never a coolant."""

INT16 = (-(2**15), 2**15 - 1)


class ChillerSettings(LinkSettings):
    """Options of every chiller: the device range guard, the read-back and the link's back-off."""

    min_c: Finite = Field(
        5.0, description="lowest set point sent [degC]; below: refused, nothing sent"
    )
    max_c: Finite = Field(
        35.0, description="highest set point sent [degC]; above: refused, nothing sent"
    )
    setpoint_readback: bool = Field(
        True,
        description="read the set point back after each write; a device that holds another "
        "value (clamped, ignored) is a refused write",
    )

    @model_validator(mode="after")
    def _range(self) -> ChillerSettings:
        lo, hi = PLAUSIBLE_C
        if not lo <= self.min_c < self.max_c <= hi:
            raise ValueError(
                f"min_c < max_c, both within {lo:g}..{hi:g} degC, "
                f"not {self.min_c:g}..{self.max_c:g}"
            )
        return self


class Chiller(Link):
    """A chiller whose coolant set point [degC] thermocomp writes.

    ``scale_c`` is degC per raw unit of the set point (``supply_scale_c`` of the supply
    temperature, where it differs); ``raw_range`` (a backend's integer type) makes the raw set
    point a whole count within it. Subclasses implement ``_connect``,
    ``_disconnect``, ``_write_setpoint_raw``, ``_read_supply_raw`` and, with
    ``can_read_setpoint``, ``_read_setpoint_raw``.
    """

    name: ClassVar[str] = "chiller"
    Settings: ClassVar[type[ChillerSettings]] = ChillerSettings
    can_read_setpoint: ClassVar[bool] = False

    scale_c: float = 1.0
    supply_scale_c: float | None = None  # None: scale_c
    raw_range: tuple[int, int] | None = None

    def __init__(
        self,
        *,
        min_c: float = 5.0,
        max_c: float = 35.0,
        setpoint_readback: bool = True,
        **link: Any,
    ):
        super().__init__(**link)
        self.min_c = float(min_c)
        self.max_c = float(max_c)
        if not (
            math.isfinite(self.min_c) and math.isfinite(self.max_c) and self.min_c < self.max_c
        ):
            raise AdapterError(
                f"{self.name} chiller: need finite min_c < max_c, not {min_c!r}..{max_c!r}"
            )
        self.setpoint_readback = bool(setpoint_readback)
        self.setpoint_c_requested: float | None = None

    # -- template methods ------------------------------------------------------

    def write_setpoint_c(self, value_c: float) -> float:
        """Command the coolant set point [degC]; the value sent, as the device's unit rounds it.

        :class:`BadValueError` (nothing sent) for a value that is not a finite number, is outside
        ``min_c``..``max_c`` or does not fit the device's register; :class:`WriteRejectedError`
        when the device refuses it or, read back, holds another value."""
        if (
            isinstance(value_c, bool)
            or not isinstance(value_c, numbers.Real)
            or not math.isfinite(float(value_c))
        ):
            raise BadValueError(
                f"{self.name} chiller: refusing to write set point {short(value_c)}"
            )
        value_c = float(value_c)
        if not self.min_c <= value_c <= self.max_c:
            raise BadValueError(
                f"{self.name} chiller: set point {value_c:g} degC is outside the "
                f"device range {self.min_c:g}..{self.max_c:g} degC; nothing written"
            )
        self.open()
        raw = self._raw_of(value_c)  # after open: an OPC UA node says its type at connect
        log.debug("%s chiller: write set point %.3f degC (raw %r)", self.name, value_c, raw)
        self.setpoint_c_requested = value_c
        self._write_setpoint_raw(raw)
        if self.setpoint_readback and self.can_read_setpoint:
            held = self._number("set point read back", self._read_setpoint_raw())
            if not self._same_raw(held, raw):
                raise WriteRejectedError(
                    f"{self.name} chiller: wrote set point {self._c_of(raw):g} degC, the device "
                    f"holds {self._c_of(held):g} degC (outside its own range, or ignored)"
                )
        return self._c_of(raw)

    def read_setpoint_c(self) -> float | None:
        """The set point [degC] the device holds now, read from it; None where it cannot say
        (:attr:`can_read_setpoint` False). :class:`BadValueError` for an implausible value."""
        if not self.can_read_setpoint:
            return None
        self.open()
        return self._plausible("set point", self._read_setpoint_raw())

    def read_supply_c(self) -> float:
        """The actual coolant supply temperature [degC]; :class:`BadValueError` when it is not
        a finite number within -50..150 degC."""
        self.open()
        return self._plausible("supply temperature", self._read_supply_raw(), self.supply_scale_c)

    # -- conversions -----------------------------------------------------------

    def _raw_of(self, value_c: float) -> float | int:
        raw = value_c * (1.0 / self.scale_c)  # 1/0.1 is 10.0 exactly: 21.3 degC -> 213
        if self.raw_range is None:
            return raw
        whole = round(raw)
        lo, hi = self.raw_range
        if not lo <= whole <= hi:
            raise BadValueError(
                f"{self.name} chiller: set point {value_c:g} degC is {whole} counts "
                f"of {self.scale_c:g} degC, outside {lo}..{hi}; nothing written"
            )
        return whole

    def _c_of(self, raw: float, scale_c: float | None = None) -> float:
        return raw / (1.0 / (scale_c or self.scale_c))  # 213 / 10.0 is 21.3; 213 * 0.1 is not

    def _same_raw(self, held: float, sent: float) -> bool:
        if self.raw_range is not None:
            return held == sent
        # a float32 register holds ~7 digits of what was sent
        return math.isclose(held, sent, rel_tol=1e-6, abs_tol=1e-9)

    def _number(self, what: str, raw: Any) -> float:
        if (
            isinstance(raw, bool)
            or not isinstance(raw, numbers.Real)
            or not math.isfinite(float(raw))
        ):
            raise BadValueError(f"{self.name} chiller: {what} {short(raw)} is not a finite number")
        return float(raw)

    def _plausible(self, what: str, raw: Any, scale_c: float | None = None) -> float:
        value = self._c_of(self._number(what, raw), scale_c)
        lo, hi = PLAUSIBLE_C
        if not lo <= value <= hi:
            raise BadValueError(
                f"{self.name} chiller: {what} {value:g} degC is outside {lo:g}..{hi:g} "
                "degC (a wrong register, scale or sensor)"
            )
        return value

    # -- backend hooks ---------------------------------------------------------

    @abstractmethod
    def _write_setpoint_raw(self, raw: float) -> None: ...

    @abstractmethod
    def _read_supply_raw(self) -> Any: ...

    def _read_setpoint_raw(self) -> Any:
        raise AdapterError(f"{self.name} chiller: this link cannot read the set point back")


# -- modbus -------------------------------------------------------------------------------

if TYPE_CHECKING:  # a plain string to the type checker; pydantic checks the choice
    ChillerDataType = str
    Transport = str
else:
    ChillerDataType = one_of("int16", "float32")
    Transport = one_of("tcp", "rtu")
DEFAULT_TCP_PORT = 502


class ModbusChillerSettings(ChillerSettings):
    """The options of :class:`ModbusChiller`."""

    transport: Transport = Field("tcp", description="tcp: host and port; rtu: a serial port")
    host: Text | None = Field(None, description="tcp: the chiller's (or gateway's) address")
    port: Annotated[int | str | None, Allowed("tcp: a TCP port 1..65535; rtu: a serial device")] = (
        Field(
            None,
            description="tcp: the TCP port (default 502); rtu: the serial device, /dev/ttyUSB0",
        )
    )
    baudrate: Baud = Field(19200, description="rtu")
    parity: Parity = Field("N", description="rtu")
    stopbits: Annotated[int, Field(ge=1, le=2), Allowed("1 or 2")] = Field(1, description="rtu")
    device_id: Annotated[int, Field(ge=0, le=247), Allowed("a Modbus device address 0..247")] = 1
    setpoint_register: Register = Field(0, description="the holding register(s) of the set point")
    supply_register: Register = Field(0, description="the register(s) of the supply temperature")
    supply_table: Table = "input"
    data_type: ChillerDataType = Field("int16", description="of both registers")
    scale_c: NonZero = Field(  # type: ignore[assignment]
        None, description="degC per register unit; default 0.1 for int16, 1 for float32"
    )
    word_order: Order = Field("big", description="float32: big: the high word first")
    timeout_s: Seconds = 0.5

    @model_validator(mode="after")
    def _link(self) -> ModbusChillerSettings:
        if self.transport == "tcp":
            if not self.host:
                raise ValueError("transport tcp needs host")
            if self.port is not None and (
                not isinstance(self.port, int) or not 1 <= self.port <= 65535
            ):
                raise key_error("port", "expected a TCP port 1..65535 (transport tcp)", self.port)
        else:
            if not (isinstance(self.port, str) and self.port):
                raise ValueError("transport rtu needs port, a serial device such as /dev/ttyUSB0")
            if self.host is not None:
                raise ValueError("transport rtu takes no host (port is the serial device)")
        width = WIDTH[self.data_type]
        if (
            self.supply_table == "holding"
            and abs(self.setpoint_register - self.supply_register) < width
        ):
            raise ValueError(
                f"setpoint_register {self.setpoint_register} and supply_register "
                f"{self.supply_register} ({self.data_type}, holding) overlap"
            )
        return self


class ModbusChiller(Chiller):
    """A chiller controller over Modbus TCP or RTU, through the Modbus transport
    (:mod:`cnc_adapters.transport.modbus`), whose error policy it has: a refused or lost
    connection is :class:`UnreachableError`; no valid reply within ``timeout_s`` is
    :class:`AdapterTimeoutError` (TCP: the connection is dropped, the next call reconnects;
    RTU: a bad CRC is dropped by the framer and surfaces so too); an exception reply to a write
    is :class:`WriteRejectedError`, to a read :class:`AdapterError`.
    """

    name = "modbus"
    Settings = ModbusChillerSettings
    can_read_setpoint: ClassVar[bool] = True

    def __init__(
        self,
        *,
        transport: str = "tcp",
        host: str | None = None,
        port: int | str | None = None,
        baudrate: int = 19200,
        parity: str = "N",
        stopbits: int = 1,
        device_id: int = 1,
        setpoint_register: int = 0,
        supply_register: int = 0,
        supply_table: str = "input",
        data_type: str = "int16",
        scale_c: float | None = None,
        word_order: str = "big",
        timeout_s: float = 0.5,
        **base: Any,
    ):
        super().__init__(**base)
        if transport not in ("tcp", "rtu") or data_type not in ("int16", "float32"):
            raise AdapterError(
                f"modbus chiller: transport is tcp or rtu, data_type int16 or "
                f"float32, not {transport!r}, {data_type!r}"
            )
        self.transport = transport
        self.host = host
        self.port = (
            (DEFAULT_TCP_PORT if port is None else int(port)) if transport == "tcp" else str(port)
        )
        self.where = f"{host}:{self.port}" if transport == "tcp" else str(port)
        self.baudrate = int(baudrate)
        self.parity = parity
        self.stopbits = int(stopbits)
        self.device_id = int(device_id)
        self.setpoint_register = int(setpoint_register)
        self.supply_register = int(supply_register)
        self.supply_table = supply_table
        self.data_type = data_type
        self.scale_c = float(
            scale_c if scale_c is not None else 0.1 if data_type == "int16" else 1.0
        )
        self.raw_range = INT16 if data_type == "int16" else None
        self.word_order = word_order
        self.timeout_s = float(timeout_s)
        self._modbus = ModbusTransport(
            "modbus chiller",
            lost=self._link_lost,
            host=host if transport == "tcp" else None,
            port=self.port,
            device_id=self.device_id,
            timeout_s=self.timeout_s,
            codec=RegisterCodec(word_order),
            baudrate=self.baudrate,
            parity=parity,
            stopbits=self.stopbits,
        )

    def _connect(self) -> None:
        self._modbus.connect()

    def _disconnect(self) -> None:
        self._modbus.close()

    def _read(self, what: str, table: str, register: int) -> float:
        return float(self._modbus.read_value(what, table, register, self.data_type))

    def _write_setpoint_raw(self, raw: float) -> None:
        self._modbus.write_value("write set point", self.setpoint_register, raw, self.data_type)

    def _read_setpoint_raw(self) -> float:
        return self._read("read set point", "holding", self.setpoint_register)

    def _read_supply_raw(self) -> float:
        return self._read("read supply temperature", self.supply_table, self.supply_register)


# -- OPC UA -------------------------------------------------------------------------------

_INTEGER_VARIANTS = {
    "SByte": (-(2**7), 2**7 - 1),
    "Byte": (0, 2**8 - 1),
    "Int16": INT16,
    "UInt16": (0, 2**16 - 1),
    "Int32": (-(2**31), 2**31 - 1),
    "UInt32": (0, 2**32 - 1),
    "Int64": (-(2**63), 2**63 - 1),
    "UInt64": (0, 2**64 - 1),
}
_FLOAT_VARIANTS = ("Float", "Double")


class OpcUaChillerSettings(OpcUaLinkSettings, ChillerSettings):
    """The options of :class:`OpcUaChiller`."""

    setpoint_node: Text = Field(description="the set point: node id ({ns} allowed) or browse path")
    supply_node: Text = Field(description="the supply temperature: node id or browse path")
    scale_c: NonZero = Field(
        1.0, description="degC per unit of the set-point node (0.1 for an integer node in 0.1 degC)"
    )
    supply_scale_c: NonZero = Field(  # type: ignore[assignment]
        None, description="degC per unit of the supply node; default scale_c"
    )


class OpcUaChiller(OpcUaLink, Chiller):
    """A chiller's set point and supply temperature as nodes on an OPC UA server.

    The set point is written with the node's own data type (read at connect): an integer node
    takes whole counts of ``scale_c``. User and password as the OPC UA adapter takes them."""

    name = "opcua"
    Settings = OpcUaChillerSettings
    can_read_setpoint: ClassVar[bool] = True

    def __init__(
        self,
        url: str,
        *,
        setpoint_node: str,
        supply_node: str,
        scale_c: float = 1.0,
        supply_scale_c: float | None = None,
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
        **base: Any,
    ):
        super().__init__(**base)
        self._init_opcua(
            url,
            namespace_uri=namespace_uri,
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
        self.setpoint_ref = setpoint_node
        self.supply_ref = supply_node
        self.scale_c = float(scale_c)
        self.supply_scale_c = None if supply_scale_c is None else float(supply_scale_c)
        self._setpoint: Any = None
        self._supply: Any = None
        self._variant: Any = None

    def _on_connected(self, client: Any, ns: str) -> None:
        self._setpoint = self._resolve_ref(client, self.setpoint_ref, ns, "setpoint_node")
        self._supply = self._resolve_ref(client, self.supply_ref, ns, "supply_node")
        variant = self._call(
            "read set point node type",
            self._setpoint.read_data_type_as_variant_type,
            node=self._setpoint,
        )
        if variant.name not in _INTEGER_VARIANTS and variant.name not in _FLOAT_VARIANTS:
            raise AdapterError(
                f"opcua chiller: setpoint_node {self.setpoint_ref} holds "
                f"{variant.name}, not a number"
            )
        self._variant = variant
        self.raw_range = _INTEGER_VARIANTS.get(variant.name)
        self._call("read supply node", self._supply.read_value, node=self._supply)

    def _write_setpoint_raw(self, raw: float) -> None:
        from asyncua import ua

        value = int(raw) if self.raw_range is not None else float(raw)
        dv = ua.DataValue(ua.Variant(value, self._variant))
        self._call(
            "write set point node",
            self._setpoint.write_value,
            dv,
            node=self._setpoint,
            refused=WriteRejectedError,
        )

    def _read_setpoint_raw(self) -> Any:
        return self._call("read set point node", self._setpoint.read_value, node=self._setpoint)

    def _read_supply_raw(self) -> Any:
        return self._call("read supply node", self._supply.read_value, node=self._supply)

    def _forget(self) -> None:
        self._setpoint = None
        self._supply = None
        self._variant = None


# -- virtual ------------------------------------------------------------------------------


class VirtualChiller(Chiller):
    """The chiller of a simulated plant (``set_chiller_setpoint_c``, ``chiller_setpoint_c``,
    ``supply_c``), in process. ``lock`` guards the plant where another thread steps it.
    ``reachable = False`` makes every call fail as an unplugged chiller does."""

    name = "virtual"
    Settings = ChillerSettings
    can_read_setpoint: ClassVar[bool] = True

    def __init__(self, *, plant: Any = None, lock: Any = None, **base: Any):
        if plant is None:
            raise ConfigError(
                "virtual chiller: needs plant= (a SpindlePlant), passed by the program"
            )
        super().__init__(**base)
        self.plant = plant
        self.lock = lock if lock is not None else contextlib.nullcontext()
        self.reachable = True

    def _connect(self) -> None:
        if not self.reachable:
            raise UnreachableError("virtual chiller: unreachable (reachable is False)")

    def _disconnect(self) -> None:
        pass

    def _reach(self, what: str) -> None:
        if not self.reachable:
            raise self._link_lost(f"virtual chiller {what}: unreachable (reachable is False)")

    def _write_setpoint_raw(self, raw: float) -> None:
        self._reach("write set point")
        with self.lock:
            try:
                self.plant.set_chiller_setpoint_c(float(raw))
            except ValueError as err:
                raise WriteRejectedError(
                    f"virtual chiller: set point {raw!r} refused: {err}"
                ) from err

    def _read_setpoint_raw(self) -> Any:
        self._reach("read set point")
        with self.lock:
            return self.plant.chiller_setpoint_c

    def _read_supply_raw(self) -> Any:
        self._reach("read supply temperature")
        with self.lock:
            return self.plant.supply_c


# -- the registry -------------------------------------------------------------------------

CHILLERS: dict[str, type[Chiller]] = {
    "modbus": ModbusChiller,
    "opcua": OpcUaChiller,
    "virtual": VirtualChiller,
}


def check_chiller(backend: str, settings: Mapping[str, Any]) -> BaseModel:
    """``settings`` validated by backend ``backend``'s model; one :class:`ConfigError` line
    (the key, the value, what is allowed) for an unknown backend or a bad option."""
    cls = CHILLERS.get(backend)
    if cls is None:
        raise ConfigError(unknown("chiller backend", backend, CHILLERS))
    if not isinstance(settings, Mapping):
        raise ConfigError(
            f"{backend} chiller: settings must be a table of options, not {type(settings).__name__}"
        )
    return check_settings(f"{backend} chiller", cls.Settings, settings)


def open_chiller(backend: str, settings: Mapping[str, Any], **objects: Any) -> Chiller:
    """A chiller of ``backend`` (not yet connected), its ``settings`` checked first
    (:func:`check_chiller`). ``objects`` are the running program's (``plant``, ``lock``,
    ``clock``, ``rng``, ``on_link_change``), passed through unchecked."""
    checked = check_chiller(backend, settings).model_dump(exclude_unset=True)
    both = sorted(checked.keys() & objects.keys())
    if both:
        raise ConfigError(
            f"{backend} chiller: {', '.join(both)} given both as settings and as objects"
        )
    return construct(f"{backend} chiller", CHILLERS[backend], **checked, **objects)
