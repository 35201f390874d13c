"""Modbus RTU controller link (pymodbus): a PLC or gateway that holds speed and offset in registers.

Speed comes from an input or holding register block, the offset goes to holding registers.
Each value has a data type (``int16``, ``uint16``, ``int32``, ``uint32``, ``float32``), a word
order (``big``: high word first) and a byte order inside each register (``big`` is the Modbus
standard; ``little`` swaps the two bytes). Integer types take ``speed_scale`` and
``offset_scale`` to reach rpm and the register's unit.

A reply with a bad CRC is dropped by the framer, so it surfaces as a timeout; a Modbus
exception reply (illegal address, device failure) is an :class:`AdapterError`, or a
:class:`WriteRejectedError` for a write. The offset is read back from the holding registers
it is written to (an integer type holds it rounded to its unit).

The closed loop: a probe or tool-setter cycle leaves its measurement in
``measurement_register`` and then changes a counter in ``measurement_sequence_register``
(optional: a sigma in ``measurement_sigma_register``), all in one table
(``measurement_table``). The value is encoded like the offset (``measurement_type``, the word
and byte order; an integer type in units of ``measurement_scale``, by default
``offset_scale``); each value is used once, and the counter found at the first read is stale.

The sign of life: ``life_register`` (the counter the PLC watches, ``life_type`` default
``int16``) and ``valid_register`` (the "compensation valid" flag, 1/0, ``valid_type``), holding
registers both, or neither. The offset's, the counter's and the flag's registers go in one
``write_registers`` per run of adjacent registers: one request when all three are adjacent;
the offset's run first, so that a refused offset sends no beat. A request is taken whole or
refused whole; one that carried the offset and the sign of life and was refused is followed by
the offset alone: a refused counter or flag leaves the offset taken (``life_failure``).

The cutting signal: ``cutting_register`` (in ``cutting_table``, an integer of
``cutting_type``) holds a state the PLC sets; ``cutting_values`` are the values that mean
"cutting" (default 1). Without one, the runtime infers it from the speed.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, Field, model_validator

from .base import (
    SETTINGS_CONFIG,
    Adapter,
    AdapterError,
    AdapterSettings,
    Allowed,
    Baud,
    CuttingValues,
    Finite,
    NonZero,
    RawMeasurement,
    Seconds,
    checked_life,
    life_configured,
    one_of,
    read_handshake,
    serial_options,
)
from .reading import Failure, Life
from .transport.modbus import WIDTH, ModbusTransport, RegisterCodec

if TYPE_CHECKING:  # a plain string to the type checker; pydantic checks the choice
    DataType = str
    Table = str
    Order = str
    Parity = str
else:
    DataType = one_of(*WIDTH)
    Table = one_of("input", "holding")
    Order = one_of("big", "little")
    Parity = one_of("N", "E", "O")
Register = Annotated[int, Field(ge=0, le=65535), Allowed("a register address 0..65535")]
LifeRegister = Annotated[
    Annotated[int, Field(ge=0, le=65535)] | Literal[""],
    Allowed("a holding register address 0..65535, or '' for none"),
]


class ModbusLinkSettings(BaseModel):
    """The options of a Modbus RTU line (adapters and sensors alike)."""

    model_config = SETTINGS_CONFIG

    port: Annotated[str, Field(min_length=1), Allowed("a serial device such as /dev/ttyUSB0")]
    baudrate: Baud = 19200
    parity: Parity = "N"
    device_id: Annotated[int, Field(ge=0, le=247), Allowed("a Modbus device address 0..247")] = 1
    word_order: Order = Field("big", description="big: high word first")
    byte_order: Order = Field("big", description="inside each register; big is the standard")
    timeout_s: Seconds = 0.5


with warnings.catch_warnings():
    # the option is called "register"; it shadows ABCMeta.register, which nothing calls here
    warnings.filterwarnings("ignore", message='Field name "register"', category=UserWarning)

    class InputRegister(BaseModel):
        """One extra channel of :class:`ModbusRtuAdapter`."""

        model_config = SETTINGS_CONFIG

        # a Field, not a bare annotation: else pydantic takes ABCMeta.register for its default
        register: Register = Field(description="the register's address")
        type: DataType = "int16"
        table: Table = "input"
        scale: Finite = 1.0


class ModbusSettings(ModbusLinkSettings, AdapterSettings):
    """The options of :class:`ModbusRtuAdapter`."""

    speed_table: Table = "input"
    speed_register: Register = 0
    speed_type: DataType = "float32"
    offset_register: Register = Field(0, description="holding register(s) written and read back")
    offset_type: DataType = "float32"
    input_registers: dict[str, InputRegister] | None = None
    # the closed loop; None: no measurement (the defaults are not validated)
    measurement_register: Register = Field(  # type: ignore[assignment]
        None, description="closed loop: the register(s) the probe cycle leaves its measurement in"
    )
    measurement_sequence_register: Register = Field(  # type: ignore[assignment]
        None, description="the counter the probe cycle changes after writing the measurement"
    )
    measurement_sigma_register: Register = Field(  # type: ignore[assignment]
        None, description="optional: the measurement's sigma, encoded as the measurement"
    )
    measurement_table: Table = "holding"
    measurement_type: DataType = "float32"
    measurement_sequence_type: DataType = "uint16"
    measurement_scale: NonZero = Field(  # type: ignore[assignment]
        None, description="register unit per um of the measurement; default offset_scale"
    )
    cutting_register: Register = Field(  # type: ignore[assignment]
        None,
        description="the register the PLC's cutting state is in; none: inferred from the speed",
    )
    cutting_table: Table = "holding"
    cutting_type: DataType = "uint16"
    cutting_values: CuttingValues = Field(
        [1],  # type: ignore[arg-type]  # a list, as documented
        description="the values that mean cutting",
    )
    life_register: LifeRegister = Field(
        None,  # type: ignore[arg-type]  # not validated: None is "none"
        description="the sign of life: the holding register(s) of the counter the PLC watches",
    )
    life_type: DataType = Field("int16", description="the counter's data type")
    valid_register: LifeRegister = Field(
        None,  # type: ignore[arg-type]  # not validated: None is "none"
        description="the sign of life: the holding register(s) of the valid flag (1/0)",
    )
    valid_type: DataType = Field("int16", description="the valid flag's data type")

    @model_validator(mode="after")
    def _measurement(self) -> ModbusSettings:
        check_measurement(
            "",
            self.measurement_register,
            self.measurement_sequence_register,
            self.measurement_sigma_register,
            self.measurement_type,
            self.measurement_sequence_type,
            ValueError,
        )
        check_life(
            self.offset_register,
            self.offset_type,
            self.life_register,
            self.life_type,
            self.valid_register,
            self.valid_type,
            ValueError,
        )
        return self


class ModbusLink:
    """Mixin for :class:`~cnc_adapters.base.Link` subclasses: a Modbus RTU client on a serial
    port (:class:`~cnc_adapters.transport.ModbusTransport`). Call :meth:`_init_modbus` from
    ``__init__``."""

    name: ClassVar[str]

    def _init_modbus(
        self,
        port: str,
        baudrate: int,
        parity: str,
        device_id: int,
        word_order: str,
        byte_order: str,
        timeout_s: float,
    ) -> None:
        self.port = port
        self.baudrate = int(baudrate)
        self.parity = parity
        self.device_id = int(device_id)
        self.word_order = word_order
        self.byte_order = byte_order
        self.timeout_s = float(timeout_s)
        lost = self._link_lost  # type: ignore[attr-defined]
        self._modbus = ModbusTransport(
            self.name,
            lost=lost,
            port=port,
            device_id=device_id,
            timeout_s=timeout_s,
            codec=RegisterCodec(word_order, byte_order),
            baudrate=baudrate,
            parity=parity,
        )

    def _connect(self) -> None:
        self._modbus.connect()

    def _disconnect(self) -> None:
        self._modbus.close()

    def _read_value(self, what: str, table: str, register: int, dtype: str) -> float:
        return float(self._modbus.read_value(what, table, register, dtype))


def check_measurement(
    prefix: str,
    value: int | None,
    sequence: int | None,
    sigma: int | None,
    dtype: str,
    sequence_type: str,
    error: type[Exception] = AdapterError,
) -> None:
    """The measurement's registers: the value and its counter together, the sigma only with
    them, no two overlapping."""
    if (value is None) != (sequence is None) or (sigma is not None and value is None):
        raise error(
            f"{prefix}a measurement needs both measurement_register and measurement_sequence_register "
            "(the handshake), measurement_sigma_register only with them"
        )
    if value is None or sequence is None:
        return
    spans = [
        (value, dtype, "measurement_register"),
        (sequence, sequence_type, "measurement_sequence_register"),
    ]
    if sigma is not None:
        spans.append((sigma, dtype, "measurement_sigma_register"))
    for i, (a, ta, na) in enumerate(spans):
        for b, tb, nb in spans[i + 1 :]:
            if a < b + WIDTH[tb] and b < a + WIDTH[ta]:
                raise error(f"{prefix}{na} {a} ({ta}) and {nb} {b} ({tb}) overlap")


def check_life(
    offset: int,
    offset_type: str,
    life: int | str | None,
    life_type: str,
    valid: int | str | None,
    valid_type: str,
    error: type[Exception] = AdapterError,
) -> bool:
    """Whether a sign of life is configured: both registers or neither (``""``: none); none
    of the offset's, the counter's and the flag's registers overlapping."""
    try:
        configured = life_configured(life, valid, "life_register", "valid_register")
    except ValueError as err:
        raise error(str(err)) from None
    if not configured:
        return False
    spans = [
        (offset, offset_type, "offset_register"),
        (int(life), life_type, "life_register"),  # type: ignore[arg-type]
        (int(valid), valid_type, "valid_register"),  # type: ignore[arg-type]
    ]
    for i, (a, ta, na) in enumerate(spans):
        if a + WIDTH[ta] > 65536:
            raise error(f"{na} {a}: a {ta} runs past register 65535")
        for b, tb, nb in spans[i + 1 :]:
            if a < b + WIDTH[tb] and b < a + WIDTH[ta]:
                raise error(f"{na} {a} ({ta}) and {nb} {b} ({tb}) overlap")
    return True


def check_types(name: str, *types: str) -> None:
    for t in types:
        if t not in WIDTH:
            raise AdapterError(f"{name}: unknown data type {t!r}; known: {', '.join(WIDTH)}")


class ModbusRtuAdapter(ModbusLink, Adapter):
    name = "modbus"
    Settings: ClassVar[type[AdapterSettings]] = ModbusSettings
    can_read_offset: ClassVar[bool] = True
    can_read_measurement: ClassVar[bool] = True  # an instance without measurement_register cannot

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 19200,
        parity: Literal["N", "E", "O"] = "N",
        device_id: int = 1,
        speed_table: Literal["input", "holding"] = "input",
        speed_register: int = 0,
        speed_type: str = "float32",
        offset_register: int = 0,
        offset_type: str = "float32",
        word_order: Literal["big", "little"] = "big",
        byte_order: Literal["big", "little"] = "big",
        timeout_s: float = 0.5,
        input_registers: dict[str, dict[str, Any]] | None = None,
        measurement_register: int | None = None,
        measurement_sequence_register: int | None = None,
        measurement_sigma_register: int | None = None,
        measurement_table: Literal["input", "holding"] = "holding",
        measurement_type: str = "float32",
        measurement_sequence_type: str = "uint16",
        measurement_scale: float | None = None,
        cutting_register: int | None = None,
        cutting_table: Literal["input", "holding"] = "holding",
        cutting_type: str = "uint16",
        cutting_values: tuple[Any, ...] = (1,),
        life_register: int | str | None = None,
        life_type: str = "int16",
        valid_register: int | str | None = None,
        valid_type: str = "int16",
        **scaling: Any,
    ):
        super().__init__(**scaling)
        check_types(
            "modbus",
            speed_type,
            offset_type,
            measurement_type,
            measurement_sequence_type,
            cutting_type,
            life_type,
            valid_type,
        )
        # the sign of life: (register, type) of the counter and of the flag
        self.life: tuple[tuple[int, str], tuple[int, str]] | None = None
        if check_life(
            int(offset_register),
            offset_type,
            life_register,
            life_type,
            valid_register,
            valid_type,
        ):
            self.life = ((int(life_register), life_type), (int(valid_register), valid_type))  # type: ignore[arg-type]
        self.writes_life = self.life is not None
        if cutting_type == "float32":
            raise AdapterError(
                "modbus: cutting_type is an integer type (a state, not a measurement)"
            )
        self.cutting = (
            None
            if cutting_register is None
            else (cutting_table, int(cutting_register), cutting_type)
        )
        self.can_read_cutting = self.cutting is not None  # type: ignore[misc]
        self.cutting_values = tuple(cutting_values)
        check_measurement(
            "modbus: ",
            measurement_register,
            measurement_sequence_register,
            measurement_sigma_register,
            measurement_type,
            measurement_sequence_type,
        )
        if measurement_table not in ("input", "holding"):
            raise AdapterError("modbus: measurement_table is 'input' or 'holding'")
        # (table, type, sequence type, value, sequence[, sigma]) registers of the probe cycle
        self.measurement = (
            (
                measurement_table,
                measurement_type,
                measurement_sequence_type,
                measurement_register,
                measurement_sequence_register,
                measurement_sigma_register,
            )
            if measurement_register is not None and measurement_sequence_register is not None
            else None
        )
        self.can_read_measurement = self.measurement is not None  # type: ignore[misc]
        self.measurement_scale = measurement_scale
        # extra channels: name -> {register, type (int16...), table (input/holding), scale}
        self.input_registers = {}
        for name, spec in (input_registers or {}).items():
            spec = dict(spec)
            bad = set(spec) - {"register", "type", "table", "scale"}
            if bad or "register" not in spec:
                raise AdapterError(
                    f"modbus input {name}: give register [type, table, scale], not {sorted(bad)}"
                )
            spec.setdefault("type", "int16")
            spec.setdefault("table", "input")
            spec.setdefault("scale", 1.0)
            check_types(f"modbus input {name}", spec["type"])
            self.input_registers[name] = spec
        if speed_table not in ("input", "holding"):
            raise AdapterError("modbus: speed_table is 'input' or 'holding'")
        self._init_modbus(port, baudrate, parity, device_id, word_order, byte_order, timeout_s)
        self.speed_table = speed_table
        self.speed_register = int(speed_register)
        self.speed_type = speed_type
        self.offset_register = int(offset_register)
        self.offset_type = offset_type

    @classmethod
    def url_options(cls, url: str) -> dict[str, Any]:
        return serial_options(url)

    def _read_speed_raw(self) -> float:
        return self._read_value(
            "read speed", self.speed_table, self.speed_register, self.speed_type
        )

    def input_channels(self) -> tuple[str, ...]:
        return tuple(self.input_registers)

    def _read_inputs_raw(self) -> dict[str, float]:
        return {
            name: self._read_value(
                f"read {name}", spec["table"], int(spec["register"]), spec["type"]
            )
            * float(spec["scale"])
            for name, spec in self.input_registers.items()
        }

    def _read_offset_raw(self) -> float:
        return self._read_value("read offset", "holding", self.offset_register, self.offset_type)

    def _read_measurement_raw(self) -> RawMeasurement | None:
        assert self.measurement is not None  # can_read_measurement
        table, dtype, seq_type, value, seq, sigma = self.measurement
        # one request each: the counter is read twice, around the value
        return read_handshake(
            self.name,
            lambda: self._read_value("read measurement sequence", table, seq, seq_type),
            lambda: self._read_value("read measurement", table, value, dtype),
            None
            if sigma is None
            else lambda: self._read_value("read measurement sigma", table, sigma, dtype),
        )

    def _read_cutting_raw(self) -> int:
        table, register, dtype = self.cutting  # type: ignore[misc]
        return int(self._read_value("read cutting state", table, register, dtype))

    def _write_offset_raw(self, value: float) -> None:
        self._modbus.write_value("write offset", self.offset_register, value, self.offset_type)

    def _write_raw(self, raw: float | None, life: Life | None) -> Failure | None:
        """The offset, the counter and the flag: one ``write_registers`` per run of adjacent
        registers (all three adjacent: one request), the offset's run first, so that a refused
        offset sends no beat. Every value encoded first, so that one that does not fit sends
        nothing. A later run (the sign of life's alone) that fails is the sign of life's
        failure, the offset taken."""
        if life is None:
            if raw is not None:
                self._write_offset_raw(raw)
            return None
        life = checked_life(self.name, life)
        assert self.life is not None  # writes_life
        (counter_at, counter_type), (flag_at, flag_type) = self.life
        values: list[tuple[str, int, str, float]] = [
            ("life counter", counter_at, counter_type, life.counter)
        ]
        values.append(("valid flag", flag_at, flag_type, int(life.valid)))
        if raw is not None:
            values.append(("offset", self.offset_register, self.offset_type, raw))
        encoded = []
        for name, at, dtype, value in sorted(values, key=lambda v: v[1]):
            where = f"{self.name} write {name} holding register {at} at {self._modbus.where}"
            encoded.append((name, at, self._modbus.codec.encode(value, dtype, where)))
        runs: list[list[tuple[str, int, list[int]]]] = []
        for item in encoded:
            if runs and item[1] == runs[-1][-1][1] + len(runs[-1][-1][2]):
                runs[-1].append(item)
            else:
                runs.append([item])
        runs.sort(key=lambda run: all(name != "offset" for name, _, _ in run))  # offset first
        for run in runs:
            what = "write " + ", ".join(name for name, _, _ in run)

            def send(run: list[tuple[str, int, list[int]]] = run, what: str = what) -> None:
                self._modbus.write_registers(
                    what, run[0][1], [r for _, _, regs in run for r in regs]
                )

            if raw is not None and any(name == "offset" for name, _, _ in run):
                self._offset_sent_alone = len(run) == 1
                send()  # the offset's failure (with the life in it: the offset is sent alone)
            else:
                failure = self._life_part(send)
                if failure is not None:
                    return failure
        return None
