"""Serial controller links (pyserial): a generic ASCII line protocol and Haas Q/E commands.

Every request is one line; every reply is one line, matched by a regular expression
whose named group ``value`` carries the number. Before each request the input buffer is
flushed, so a late reply to an earlier request can never be taken for the current one.

A device that vanishes (a USB adapter unplugged) raises :class:`UnreachableError`; the
adapter closes the port and reopens it on the next call, so it recovers when the device
returns. A silent or half-finished reply raises :class:`AdapterTimeoutError`; a reply that
does not match raises :class:`BadValueError`; a refused write raises
:class:`WriteRejectedError`.

Reading the offset back: the generic protocol has no standard query, so ``offset_query`` (e.g.
``?OFFSET``, answered ``OFFSET=<value>`` by default ``offset_query_reply``) turns it on; without
one the link cannot read back (``can_read_offset`` is false).

Haas (NGC "machine data collection" Q/E commands): ``?Q600 <var>`` reads a macro variable,
answered ``MACRO, <var>, <value>`` (a leading ``>`` is allowed); ``?E<var> <value>`` writes
one, answered ``!``. The spindle speed is macro #3027 by default; the offset goes to a
configurable macro variable, which the part program or a macro applies as a tool-length
offset (for example ``#2000 + T`` wear, via ``G10``), and is read back with ``?Q600`` too.

The sign of life: Haas writes the counter to ``life_var`` and the "compensation valid" flag
(1/0) to ``valid_var`` after the offset, one ``?E`` each (the ``haas`` profile: #10501 and
#10502); the generic protocol sends ``life_request`` (``{counter}`` and ``{valid}``, e.g.
``LIFE {counter} {valid}``) after the offset's line, answered like it.

The closed loop, Haas: a probe or tool-setter cycle leaves its measurement in macro
``measurement_var`` and then changes a counter in ``measurement_sequence_var`` (optional: a
sigma in ``measurement_sigma_var``), in the offset's unit (or ``measurement_scale``); all are
read with ``?Q600``, the counter before and after the value. Each value is used once, and the
counter found at the first read is stale.
"""

from __future__ import annotations

import re
from typing import Annotated, Any, ClassVar, Literal

from pydantic import AfterValidator, BaseModel, Field, model_validator

from .base import (
    SETTINGS_CONFIG,
    Adapter,
    AdapterError,
    AdapterSettings,
    AdapterTimeoutError,
    Allowed,
    BadValueError,
    Baud,
    ConfigError,
    Count,
    NonZero,
    Pattern,
    RawMeasurement,
    Seconds,
    Text,
    UnreachableError,
    ValuePattern,
    WriteRejectedError,
    checked_life,
    life_configured,
    read_handshake,
    serial_options,
)
from .reading import Life

try:
    import termios

    _PORT_ERRORS: tuple[type[BaseException], ...] = (OSError, termios.error)
except ImportError:  # not POSIX
    _PORT_ERRORS = (OSError,)

NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


class SerialSettings(BaseModel):
    """The options of a serial line (adapters and sensors alike)."""

    model_config = SETTINGS_CONFIG

    port: Annotated[str, Field(min_length=1), Allowed("a serial device such as /dev/ttyUSB0")]
    baudrate: Baud = 115200
    timeout_s: Seconds = Field(0.5, description="for one reply line")
    eol: Text = Field("\r\n", description="end of line, sent and expected")


def _offset_request(v: str) -> str:
    try:
        v.format(value=1.0)
    except (KeyError, IndexError, ValueError):
        raise ValueError("a request with {value} in it, e.g. 'OFFSET {value:.4f}'") from None
    if "{value" not in v:
        raise ValueError("a request with {value} in it, e.g. 'OFFSET {value:.4f}'")
    return v


OffsetRequest = Annotated[
    str,
    AfterValidator(_offset_request),
    Allowed("a request with {value} in it, e.g. 'OFFSET {value:.4f}'"),
]

_LIFE_REQUEST = "a request with {counter} and {valid} in it, e.g. 'LIFE {counter} {valid}', or ''"


def _life_request(v: str) -> str:
    if v == "":
        return v
    try:
        v.format(counter=1, valid=1)
    except (KeyError, IndexError, ValueError):
        raise ValueError(_LIFE_REQUEST) from None
    if "{counter" not in v or "{valid" not in v:
        raise ValueError(_LIFE_REQUEST)
    return v


LifeRequest = Annotated[str, AfterValidator(_life_request), Allowed(_LIFE_REQUEST)]


class LineSettings(SerialSettings, AdapterSettings):
    """The options of :class:`LineAdapter`."""

    speed_request: Text = "?SPEED"
    speed_reply: ValuePattern = rf"^SPEED\s*=?\s*(?P<value>{NUMBER})$"
    offset_request: OffsetRequest = "OFFSET {value:.4f}"
    offset_reply: Pattern = r"^OK$"
    reject_reply: Pattern = r"^(ERR|ERROR|NAK|\?).*"
    offset_query: str = Field(
        "",
        description="reads the offset back (e.g. '?OFFSET'); empty: the device has no such query",
    )
    offset_query_reply: ValuePattern = rf"^OFFSET\s*=?\s*(?P<value>{NUMBER})$"
    life_request: LifeRequest = Field(
        "",
        description="the sign of life, one line after the offset's: {counter} (1..32767) and "
        "{valid} (1/0), answered like the offset; empty: none",
    )


class SerialLine:
    """Mixin for :class:`~cnc_adapters.base.Link` subclasses: one ASCII line per request
    and per reply on a serial port. Call :meth:`_init_serial` from ``__init__``."""

    name: ClassVar[str]

    def _init_serial(self, port: str, baudrate: int, timeout_s: float, eol: str) -> None:
        self.port = port
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s)
        self.eol = eol
        self._ser: Any = None  # a serial.Serial while open

    def _connect(self) -> None:
        import serial

        try:
            self._ser = serial.Serial(
                self.port, self.baudrate, timeout=self.timeout_s, write_timeout=self.timeout_s
            )
        except (serial.SerialException, OSError) as err:
            raise UnreachableError(
                f"{self.name} open at {self.port}: cannot open the port: {err}"
            ) from err

    def _disconnect(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001 - the device may already be gone
                pass

    def exchange(self, request: str | None, op: str = "read") -> str:
        """Send one line and return the reply line (without its end of line); a failure says
        ``op`` (``read speed``), the request and the port.

        With ``request=None`` the device talks on its own (a streaming amplifier): the
        input buffer is dropped and the first whole line after it is returned.
        """
        import serial

        self.open()  # type: ignore[attr-defined]
        ser = self._ser
        end = self.eol[-1].encode("ascii")
        head = self._head(op, request)
        vanished: tuple[type[BaseException], ...] = (serial.SerialException, *_PORT_ERRORS)
        try:
            ser.reset_input_buffer()
            if request is not None:
                ser.write((request + self.eol).encode("ascii"))
            else:
                ser.read_until(end)  # most likely the tail of a line: dropped
            raw = ser.read_until(end)
        except vanished as err:
            raise self._link_lost(f"{head}: the port vanished: {err}") from err  # type: ignore[attr-defined]
        if not raw:
            raise AdapterTimeoutError(f"{head}: no reply within {self.timeout_s:g} s")
        if not raw.endswith(end):
            raise AdapterTimeoutError(f"{head}: partial reply {raw!r}")
        try:
            return raw.decode("ascii").strip()
        except UnicodeDecodeError as err:
            raise BadValueError(f"{head}: garbage reply {raw!r}") from err

    def _head(self, op: str, request: str | None) -> str:
        """``<link> <operation> <request> at <port>``: the start of an exchange's message."""
        sent = repr(request) if request is not None else "(the stream)"
        return f"{self.name} {op} {sent} at {self.port}"


class LineAdapter(SerialLine, Adapter):
    """A generic request/response ASCII protocol on a serial line."""

    name = "line"
    Settings: ClassVar[type[AdapterSettings]] = LineSettings
    can_read_offset: ClassVar[bool] = False  # an instance with an offset_query can

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 115200,
        timeout_s: float = 0.5,
        speed_request: str = "?SPEED",
        speed_reply: str = rf"^SPEED\s*=?\s*(?P<value>{NUMBER})$",
        offset_request: str = "OFFSET {value:.4f}",
        offset_reply: str = r"^OK$",
        reject_reply: str = r"^(ERR|ERROR|NAK|\?).*",
        eol: str = "\r\n",
        offset_query: str = "",
        offset_query_reply: str = rf"^OFFSET\s*=?\s*(?P<value>{NUMBER})$",
        life_request: str = "",
        **scaling: Any,
    ):
        super().__init__(**scaling)
        self._init_serial(port, baudrate, timeout_s, eol)
        try:
            self.life_request = _life_request(life_request) or None
        except ValueError as err:
            raise AdapterError(f"{self.name}: life_request: expected {err}") from None
        self.writes_life = self.life_request is not None
        self.speed_request = speed_request
        self.offset_request = offset_request
        self.offset_query = offset_query or None
        self.can_read_offset = self.offset_query is not None  # type: ignore[misc]
        try:
            self.speed_reply = re.compile(speed_reply)
            self.offset_reply = re.compile(offset_reply)
            self.reject_reply = re.compile(reject_reply)
            self.offset_query_reply = re.compile(offset_query_reply)
        except re.error as err:
            raise AdapterError(f"{self.name}: bad reply pattern: {err}") from err
        if "value" not in self.speed_reply.groupindex:
            raise AdapterError(f"{self.name}: speed_reply needs a (?P<value>...) group")
        if "value" not in self.offset_query_reply.groupindex:
            raise AdapterError(f"{self.name}: offset_query_reply needs a (?P<value>...) group")

    @classmethod
    def url_options(cls, url: str) -> dict[str, Any]:
        """``serial:///dev/ttyUSB0?protocol=haas&baudrate=9600&offset_var=10500``."""
        return serial_options(url)

    def _read_speed_raw(self) -> float:
        reply = self.exchange(self.speed_request, "read speed")
        m = self.speed_reply.match(reply)
        if m is None:
            raise BadValueError(
                f"{self._head('read speed', self.speed_request)}: unexpected reply {reply!r}"
            )
        return self._number(m.group("value"), "read speed", self.speed_request)

    def _number(self, text: str, op: str, request: str) -> float:
        """The reply's value group as a float (a configured pattern may match a word)."""
        try:
            return float(text)
        except ValueError as err:
            raise BadValueError(f"{self._head(op, request)}: {text!r} is not a number") from err

    def _read_offset_raw(self) -> float:
        if self.offset_query is None:  # read_offset_um checks can_read_offset first
            return super()._read_offset_raw()
        return self._query(self.offset_query, self.offset_query_reply, "read offset")

    def _query(self, request: str, reply_pattern: re.Pattern[str], op: str = "read") -> float:
        """The number in the reply to ``request``: :class:`AdapterError` when the controller
        refuses it, :class:`BadValueError` for a reply that does not match."""
        reply = self.exchange(request, op)
        m = reply_pattern.match(reply)
        if m is not None:
            return self._number(m.group("value"), op, request)
        if self.reject_reply.match(reply):
            raise AdapterError(f"{self._head(op, request)}: controller refused it: {reply!r}")
        raise BadValueError(f"{self._head(op, request)}: unexpected reply {reply!r}")

    def _write_offset_raw(self, value: float) -> None:
        request = self.offset_request.format(value=value)
        reply = self.exchange(request, "write offset")
        if self.reject_reply.match(reply):
            raise WriteRejectedError(
                f"{self._head('write offset', request)}: controller refused it: {reply!r}"
            )
        if not self.offset_reply.match(reply):
            raise BadValueError(
                f"{self._head('write offset', request)}: unexpected reply {reply!r}"
            )

    def _write_life_raw(self, life: Life) -> None:
        life = checked_life(self.name, life)
        assert self.life_request is not None  # writes_life
        self._write_line(
            self.life_request.format(counter=life.counter, valid=int(life.valid)),
            "write sign of life",
        )

    def _write_line(self, request: str, op: str) -> None:
        """One write request, answered like the offset's: refused (``reject_reply``) is
        :class:`WriteRejectedError`, anything but ``offset_reply`` :class:`BadValueError`."""
        reply = self.exchange(request, op)
        if self.reject_reply.match(reply):
            raise WriteRejectedError(f"{self._head(op, request)}: controller refused it: {reply!r}")
        if not self.offset_reply.match(reply):
            raise BadValueError(f"{self._head(op, request)}: unexpected reply {reply!r}")


LifeVar = Annotated[
    Annotated[int, Field(ge=0)] | Literal[""],
    Allowed("a macro variable number >= 0, or '' for none"),
]


class HaasMacros(BaseModel):
    """The Haas macro-variable options, shared by the serial and the MDC (TCP) link."""

    model_config = SETTINGS_CONFIG

    speed_var: Count = Field(3027, description="macro variable of the actual speed")
    offset_var: Count = Field(10500, description="macro variable the offset goes to")
    offset_decimals: Annotated[int, Field(ge=0, le=8), Allowed("a whole number 0..8")] = 4
    # the closed loop; None: no measurement (the defaults are not validated)
    measurement_var: Count = Field(  # type: ignore[assignment]
        None,
        description="closed loop: the macro variable the probe cycle leaves its measurement in",
    )
    measurement_sequence_var: Count = Field(  # type: ignore[assignment]
        None, description="the macro variable the probe cycle changes after writing the measurement"
    )
    measurement_sigma_var: Count = Field(  # type: ignore[assignment]
        None, description="optional: the macro variable of the measurement's sigma"
    )
    measurement_scale: NonZero = Field(  # type: ignore[assignment]
        None, description="macro unit per um of the measurement; default offset_scale"
    )
    life_var: LifeVar = Field(
        None,  # type: ignore[arg-type]  # not validated: None is "none"
        description="the sign of life: the macro variable of the counter the program checks",
    )
    valid_var: LifeVar = Field(
        None,  # type: ignore[arg-type]  # not validated: None is "none"
        description="the sign of life: the macro variable of the valid flag (1/0)",
    )

    @model_validator(mode="after")
    def _measurement(self) -> HaasMacros:
        check_macros(
            "",
            self.offset_var,
            self.measurement_var,
            self.measurement_sequence_var,
            self.measurement_sigma_var,
            ValueError,
            self.life_var,
            self.valid_var,
        )
        return self


class HaasSettings(HaasMacros, LineSettings):
    """The options of :class:`HaasAdapter`; the requests and replies (line options) default to
    the Q/E commands for ``speed_var`` and ``offset_var``."""

    # None: the Haas commands' own (the line options' defaults are another protocol's)
    speed_request: Text | None = None  # type: ignore[assignment]
    speed_reply: ValuePattern | None = None  # type: ignore[assignment]
    offset_request: OffsetRequest | None = None  # type: ignore[assignment]
    offset_reply: Pattern | None = None  # type: ignore[assignment]
    reject_reply: Pattern | None = None  # type: ignore[assignment]
    offset_query: str | None = Field(  # type: ignore[assignment]
        None, description="default '?Q600 <offset_var>'; empty: no read-back"
    )
    offset_query_reply: ValuePattern | None = None  # type: ignore[assignment]

    @model_validator(mode="after")
    def _life(self) -> HaasSettings:
        if self.life_request:
            raise ValueError(
                "haas: the sign of life goes to life_var and valid_var, not life_request"
            )
        return self


def check_macros(
    prefix: str,
    offset_var: int,
    value: int | None,
    sequence: int | None,
    sigma: int | None,
    error: type[Exception] = AdapterError,
    life: int | str | None = None,
    valid: int | str | None = None,
) -> bool:
    """The measurement's macro variables: the value and its counter together, the sigma only
    with them; the sign of life's two or neither; all different and none the offset's. Whether
    a sign of life is configured."""
    if (value is None) != (sequence is None) or (sigma is not None and value is None):
        raise error(
            f"{prefix}a measurement needs both measurement_var and measurement_sequence_var "
            "(the handshake), measurement_sigma_var only with them"
        )
    given = [v for v in (offset_var, value, sequence, sigma) if v is not None]
    if len(set(given)) < len(given):
        raise error(
            f"{prefix}offset_var, measurement_var, measurement_sequence_var and "
            f"measurement_sigma_var must be different macro variables, not {given}"
        )
    try:
        configured = life_configured(life, valid, "life_var", "valid_var")
    except ValueError as err:
        raise error(f"{prefix}{err}") from None
    if configured:
        mine = [int(life), int(valid)]  # type: ignore[arg-type]
        if len(set(mine)) < 2 or set(mine) & set(given):
            raise error(
                f"{prefix}life_var and valid_var must be two macro variables of their own, "
                f"not {mine} (offset_var and the measurement's: {given})"
            )
    return configured


class HaasAdapter(LineAdapter):
    """Haas Q/E commands: speed from macro #3027, offset to a configurable macro variable, read
    back with Q600 like any macro variable."""

    name = "haas"
    Settings: ClassVar[type[AdapterSettings]] = HaasSettings
    can_read_offset: ClassVar[bool] = True
    can_read_measurement: ClassVar[bool] = True  # an instance without measurement_var cannot

    def __init__(
        self,
        port: str,
        *,
        speed_var: int = 3027,
        offset_var: int = 10500,
        offset_decimals: int = 4,
        measurement_var: int | None = None,
        measurement_sequence_var: int | None = None,
        measurement_sigma_var: int | None = None,
        measurement_scale: float | None = None,
        life_var: int | str | None = None,
        valid_var: int | str | None = None,
        **kw: Any,
    ):
        self.speed_var = int(speed_var)
        self.offset_var = int(offset_var)
        configured = check_macros(
            "haas: ",
            self.offset_var,
            measurement_var,
            measurement_sequence_var,
            measurement_sigma_var,
            AdapterError,
            life_var,
            valid_var,
        )
        if kw.get("life_request"):
            raise ConfigError(
                "haas: the sign of life goes to life_var and valid_var, not life_request"
            )
        macro = rf"^>?\s*MACRO,\s*{{}},\s*(?P<value>{NUMBER})$"
        # (request, reply) per macro variable of the probe cycle: sequence, value[, sigma]; a
        # NaN is taken as read, so that it is refused once, like any value that is no number
        measured = rf"^>?\s*MACRO,\s*{{}},\s*(?P<value>{NUMBER}|(?i:[-+]?(?:nan|inf)))$"
        self.measurement_queries = tuple(
            (f"?Q600 {v}", re.compile(measured.format(v)))
            for v in (measurement_sequence_var, measurement_var, measurement_sigma_var)
            if v is not None
        )
        defaults = {
            "speed_request": f"?Q600 {self.speed_var}",
            "speed_reply": macro.format(self.speed_var),
            "offset_request": f"?E{self.offset_var} {{value:.{int(offset_decimals)}f}}",
            "offset_reply": r"^>?\s*!$",
            "reject_reply": r"^>?\s*(\?|INVALID|ERROR|NOT ALLOWED).*",
            "eol": "\r\n",
            "offset_query": f"?Q600 {self.offset_var}",
            "offset_query_reply": macro.format(self.offset_var),
        }
        for key, value in defaults.items():
            if kw.get(key) is None:
                kw[key] = value
        super().__init__(port, **kw)
        self.can_read_measurement = bool(self.measurement_queries)  # type: ignore[misc]
        self.measurement_scale = measurement_scale
        # the sign of life: the counter's and the flag's macro variables
        self.life_vars: tuple[int, int] | None = (
            (int(life_var), int(valid_var)) if configured else None  # type: ignore[arg-type]
        )
        self.writes_life = self.life_vars is not None

    def _write_life_raw(self, life: Life) -> None:
        """``?E<life_var> <counter>`` then ``?E<valid_var> 1`` (or 0): one line each, the Haas
        commands write one variable each."""
        life = checked_life(self.name, life)
        assert self.life_vars is not None  # writes_life
        counter_var, flag_var = self.life_vars
        self._write_line(f"?E{counter_var} {life.counter}", "write life counter")
        self._write_line(f"?E{flag_var} {int(life.valid)}", "write valid flag")

    def _read_measurement_raw(self) -> RawMeasurement | None:
        reads = [
            lambda q=q: self._query(q[0], q[1], "read measurement")
            for q in self.measurement_queries
        ]
        # one request each: the counter is read twice, around the value
        return read_handshake(self.name, reads[0], reads[1], reads[2] if len(reads) > 2 else None)
