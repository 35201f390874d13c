"""FANUC FOCAS/Ethernet controller link: macro variables over TCP (port 8193), pure socket.

The offset goes to a common macro variable (``offset_macro``, #500 by default) with the
FOCAS "write macro (double)" call; the machine builder's ladder (or a macro) hands it to the
control's "thermal growth compensation along tool vector" through the THD00-15 / THSTB /
THREND handshake (``docs/controls/fanuc.md``). The speed is the control's actual spindle speed
(``cnc_acts``), or a macro variable the ladder fills (``speed_source = "macro"``). The held
value is read back from the offset macro, or from ``ack_macro``, a variable the ladder or macro
sets to the value the control took (after THREND): then a value written but not applied shows
as a read-back mismatch.

The wire format is the one public reverse engineering documents (the README and code of PyPI
``pyfocas``, built on ``diohpix/pyfanuc``): big-endian packets ``A0 A0 A0 A0 | origin |
type | length``, an open (0x0101) and a close (0x0201) request around generic requests
(0x2101) of subpackets ``length | 0001 (CNC) | 0001 function | 5 x int32 [| payload]``; each
reply subpacket echoes the command, then a 16-bit FOCAS return code, 4 bytes, a 16-bit payload
length and the payload. Numbers come back as 8-byte "scaled integers" (int32 mantissa, 16-bit
base 10 or 2, 16-bit decimal exponent; exponent -1 (FF FF): a vacant variable).

Why not ``pyfocas`` itself: its write does not look at the reply (a refused write is silent),
it reads each reply with one ``recv(1500)`` (no framing: a reply split across TCP segments,
or a late one after a timeout, desynchronises the session), it never sends the close request
(the control's FOCAS session stays taken), its timeouts are fixed, a read of a vacant variable
raises a decoding error, a refused read loses its return code, and it has no ``cnc_acts``.
This client sends the same bytes (the tests compare them), frames replies by their length
field and checks every return code.

The sign of life: ``life_macro`` takes the counter the ladder or a macro watches and
``valid_macro`` the "compensation valid" flag (1/0), common variables both (the ``fanuc``
profile: #502 and #503). They go after the offset's own request was taken, both in ONE generic
request of two "write macro" subpackets; a refusal names its variable. The CNC takes each
subpacket on its own: in the offset's request, the beat would reach the control even with the
offset refused. A refused counter or flag leaves the offset taken (the write's ``life_failure``).

Errors, the socket's mapped by the TCP transport (:mod:`cnc_adapters.transport.tcp`): a
refused or unanswered connect, a closed or dropped session is :class:`UnreachableError`, no
reply within ``timeout_s`` (the open request's too) :class:`AdapterTimeoutError` (the session
is dropped: a late reply must not be taken for the next request's), a reply that breaks the
format :class:`AdapterError` (dropped too); a FOCAS return code other than 0 is
:class:`WriteRejectedError` for a write and :class:`BadValueError` for a read. Nothing here
was run against a real FANUC control.
"""

from __future__ import annotations

import math
import struct
from typing import Annotated, Any, ClassVar, Literal

from pydantic import AfterValidator, Field, model_validator

from .base import (
    Adapter,
    AdapterError,
    AdapterSettings,
    Allowed,
    BadValueError,
    ConfigError,
    Seconds,
    UnreachableError,
    WriteRejectedError,
    checked_life,
    host_options,
    life_configured,
    one_of,
)
from .reading import Life
from .transport.tcp import TcpTransport

__all__ = ["FocasAdapter", "FocasSettings", "decode_scaled", "focas_error", "request_packet"]

SYNC = b"\xa0\xa0\xa0\xa0"
CLIENT = 0x0001  # the origin of a request; replies carry another (0x0002 or 0x0004 seen)
OPEN_REQUEST, OPEN_RESPONSE = 0x0101, 0x0102
CLOSE_REQUEST, CLOSE_RESPONSE = 0x0201, 0x0202
REQUEST, RESPONSE = 0x2101, 0x2102
CNC = 0x0001  # the control device of a subpacket (0x0002: the PMC)
READ_MACRO = 0x15  # cnc_rdmacro: first, last -> 8 bytes per variable
WRITE_MACRO_DOUBLE = 0xA8  # pyfocas's "write macro (double)": number, 0, 0, 0, 8 + a double
READ_ACTS = 0x25  # cnc_acts: the actual spindle speed [rpm]
DEFAULT_PORT = 8193

FOCAS_ERRORS = {
    1: "EW_FUNC: function not executed or not available",
    2: "EW_LENGTH: data block length error",
    3: "EW_NUMBER: data number error (no such variable)",
    4: "EW_ATTRIB: data attribute error",
    5: "EW_DATA: data error (value out of range)",
    6: "EW_NOOPT: no option",
    7: "EW_PROT: write protection",
    8: "EW_OVRFLOW: memory overflow",
    9: "EW_PARAM: CNC parameter error",
    10: "EW_BUFFER: buffer empty or full",
    11: "EW_PATH: path number error",
    12: "EW_MODE: CNC mode error",
    13: "EW_REJECT: execution rejected",
    15: "EW_ALARM: the CNC is in alarm",
    16: "EW_STOP: the CNC is stopped or in emergency stop",
    17: "EW_PASSWD: data protected by the CNC's password",
    -1: "EW_BUSY: the CNC is busy",
}
"""The FOCAS library's return codes by the names its documentation gives them. On the wire the
reply carries the same number (public captures show 1 for a function a control lacks and 6 for
a missing option); which codes a given control sends for which refusal is not verified here."""

COMMON_VARIABLES = (range(100, 200), range(500, 1000))
"""Common macro variables: #100-#199 (cleared at power-off on most controls) and #500-#999
(kept). How many exist depends on the control and its macro option."""


def focas_error(code: int) -> str:
    """A FOCAS return code in words."""
    return f"FOCAS error {code} ({FOCAS_ERRORS.get(code, 'unknown code')})"


def _common_variable(v: int) -> int:
    if not any(v in r for r in COMMON_VARIABLES):
        raise ValueError("a common macro variable: 100..199 or 500..999")
    return v


CommonVariable = Annotated[
    int, AfterValidator(_common_variable), Allowed("a common macro variable: 100..199 or 500..999")
]
LifeVariable = Annotated[
    Annotated[int, AfterValidator(_common_variable)] | Literal[""],
    Allowed("a common macro variable: 100..199 or 500..999, or '' for none"),
]


def packet(ptype: int, body: bytes, origin: int = CLIENT) -> bytes:
    """One packet: the sync bytes, origin, type, the length of ``body``, and ``body``."""
    return SYNC + struct.pack(">HHH", origin, ptype, len(body)) + body


def command(function: int, *args: int, payload: bytes = b"") -> bytes:
    """One request subpacket without its length: the CNC device, the function, five int32
    arguments (missing ones 0) and an optional payload."""
    a = (list(args) + [0] * 5)[:5]
    return struct.pack(">HHH5i", CNC, 1, function, *a) + payload


def request_packet(*commands: bytes) -> bytes:
    """A generic request carrying ``commands`` (each prefixed with its length)."""
    body = struct.pack(">H", len(commands)) + b"".join(
        struct.pack(">H", len(c) + 2) + c for c in commands
    )
    return packet(REQUEST, body)


def decode_scaled(raw: bytes) -> float | None:
    """An 8-byte scaled integer: int32 mantissa, 16-bit base (10 or 2), 16-bit decimal
    exponent; None for a vacant variable (exponent bytes FF FF). ValueError for any other
    layout."""
    if len(raw) != 8:
        raise ValueError(f"a scaled integer is 8 bytes, not {len(raw)}")
    mantissa, base, exponent = struct.unpack(">iHh", raw)
    if exponent == -1:
        return None
    if base not in (2, 10) or exponent < 0:
        raise ValueError(f"scaled integer {raw.hex(' ')}: base {base}, exponent {exponent}")
    return mantissa / base**exponent


class _Malformed(Exception):
    """The reply breaks the packet format (the session is out of step)."""


class FocasSettings(AdapterSettings):
    """The options of :class:`FocasAdapter`."""

    host: Annotated[str, Field(min_length=1), Allowed("the CNC's host name or IP address")]
    port: Annotated[int, Field(ge=1, le=65535), Allowed("a TCP port 1..65535")] = DEFAULT_PORT
    timeout_s: Seconds = Field(2.0, description="connect and reply timeout")
    offset_macro: CommonVariable = Field(500, description="the common variable the offset goes to")
    ack_macro: CommonVariable = Field(  # type: ignore[assignment]
        None,
        description="a variable the ladder/macro sets to the value the control took; "
        "read back instead of offset_macro",
    )
    speed_source: one_of("acts", "macro") = Field(  # type: ignore[valid-type]
        "acts", description="acts: cnc_acts; macro: speed_macro, filled by the ladder or a macro"
    )
    speed_macro: CommonVariable = Field(  # type: ignore[assignment]
        None, description="with speed_source = 'macro': the variable holding the actual speed"
    )
    life_macro: LifeVariable = Field(
        None,  # type: ignore[arg-type]  # not validated: None is "none"
        description="the sign of life: the variable of the counter the control watches",
    )
    valid_macro: LifeVariable = Field(
        None,  # type: ignore[arg-type]  # not validated: None is "none"
        description="the sign of life: the variable of the valid flag (1/0)",
    )

    @model_validator(mode="after")
    def _variables(self) -> FocasSettings:
        check_variables(
            self.offset_macro,
            self.ack_macro,
            self.speed_source,
            self.speed_macro,
            ValueError,
            self.life_macro,
            self.valid_macro,
        )
        return self


def check_variables(
    offset: int,
    ack: int | None,
    source: str,
    speed: int | None,
    error: type[Exception] = ConfigError,
    life: int | str | None = None,
    valid: int | str | None = None,
) -> bool:
    """The macro variables: a speed variable exactly with ``speed_source = "macro"``, the sign
    of life's two or neither, and no two of them the same. Whether a sign of life is
    configured."""
    if source not in ("acts", "macro"):
        raise error(f"speed_source is 'acts' or 'macro', not {source!r}")
    if (source == "macro") != (speed is not None):
        raise error("speed_macro goes with speed_source = 'macro' (and is needed there)")
    try:
        configured = life_configured(life, valid, "life_macro", "valid_macro")
    except ValueError as err:
        raise error(str(err)) from None
    used = [("offset_macro", offset), ("ack_macro", ack), ("speed_macro", speed)]
    if configured:
        used += [("life_macro", int(life)), ("valid_macro", int(valid))]  # type: ignore[arg-type]
    used = [(k, v) for k, v in used if v is not None]
    for k, v in used:
        if not any(v in r for r in COMMON_VARIABLES):
            raise error(f"{k} #{v} is not a common macro variable (100..199, 500..999)")
    for i, (ka, va) in enumerate(used):
        for kb, vb in used[i + 1 :]:
            if va == vb:
                raise error(f"{ka} and {kb} are both #{va}")
    return configured


class FocasAdapter(Adapter):
    """A FANUC control over FOCAS/Ethernet: the offset in a common macro variable (see the
    module docstring).

    ``offset_macro`` receives the raw offset (a controller profile's unit: detection units for
    ``profile = "fanuc"``), written as a double; ``ack_macro``, when given, is what the held
    value is read back from. ``speed_source`` ``"acts"`` reads ``cnc_acts``; ``"macro"`` reads
    ``speed_macro``. One TCP session (one FOCAS handle) is kept open and closed with the close
    request."""

    name = "focas"
    Settings: ClassVar[type[AdapterSettings]] = FocasSettings
    can_read_offset: ClassVar[bool] = True

    def __init__(
        self,
        host: str,
        *,
        port: int = DEFAULT_PORT,
        timeout_s: float = 2.0,
        offset_macro: int = 500,
        ack_macro: int | None = None,
        speed_source: str = "acts",
        speed_macro: int | None = None,
        life_macro: int | str | None = None,
        valid_macro: int | str | None = None,
        **scaling: Any,
    ):
        super().__init__(**scaling)
        configured = check_variables(
            offset_macro, ack_macro, speed_source, speed_macro, ConfigError, life_macro, valid_macro
        )
        # the sign of life: the counter's and the flag's variables
        self.life_macros: tuple[int, int] | None = (
            (int(life_macro), int(valid_macro))  # type: ignore[arg-type]
            if configured
            else None
        )
        self.writes_life = self.life_macros is not None
        if not (isinstance(timeout_s, (int, float)) and math.isfinite(timeout_s) and timeout_s > 0):
            raise ConfigError(f"focas: timeout_s must be a number > 0, not {timeout_s!r}")
        self.host = str(host)
        self.port = int(port)
        self.timeout_s = float(timeout_s)
        self.offset_macro = int(offset_macro)
        self.ack_macro = None if ack_macro is None else int(ack_macro)
        self.speed_source = speed_source
        self.speed_macro = None if speed_macro is None else int(speed_macro)
        self._tcp = TcpTransport(
            self.name, self.host, self.port, timeout_s=self.timeout_s, lost=self._link_lost
        )

    @classmethod
    def url_options(cls, url: str) -> dict[str, Any]:
        """``focas://10.0.0.7:8193?offset_macro=500&ack_macro=501``: the host, the port (8193
        when left out) and the query."""
        return host_options("focas adapter", url)

    # -- the session -------------------------------------------------------------------

    def _connect(self) -> None:
        self._tcp.connect(handshake=self._open_session)

    def _open_session(self) -> None:
        where = self._tcp.address
        deadline = self._tcp.deadline()
        self._tcp.send("open request", packet(OPEN_REQUEST, struct.pack(">H", 2)))
        try:
            ptype, _ = self._read_packet("open request", deadline)
        except _Malformed as err:
            raise UnreachableError(f"{self.name} open session at {where}: refused: {err}") from err
        if ptype != OPEN_RESPONSE:
            raise UnreachableError(
                f"{self.name} open session at {where}: answered with packet "
                f"type {ptype:#06x}, not {OPEN_RESPONSE:#06x}"
            )

    def _disconnect(self) -> None:
        self._tcp.close(goodbye=self._close_session)

    def _close_session(self) -> None:
        """Free the control's FOCAS session (it may be gone already: faults are ignored)."""
        deadline = self._tcp.deadline(min(self.timeout_s, 1.0))
        self._tcp.send("close request", packet(CLOSE_REQUEST, b""))
        self._read_packet("close request", deadline)

    def _abort(self) -> None:
        self._tcp.abort()

    def _read_packet(self, what: str, deadline: float) -> tuple[int, bytes]:
        """One packet off the stream, framed by its length field: its type and body."""
        head = self._tcp.recv_exact(what, 10, deadline)
        if head[:4] != SYNC:
            raise _Malformed(f"no sync bytes: {head[:4].hex(' ')}")
        origin, ptype, length = struct.unpack(">HHH", head[4:])
        if origin == CLIENT:
            raise _Malformed("a request where a reply was due")
        return ptype, self._tcp.recv_exact(what, length, deadline)

    def _exchange(self, what: str, cmd: bytes, refused: type[AdapterError]) -> bytes:
        """Send one command, return the payload of its reply; a FOCAS return code other than 0
        raises ``refused``. The socket's faults are the TCP transport's."""
        return self._exchange_many([(what, cmd)], refused)[0]

    def _exchange_many(
        self, commands: list[tuple[str, bytes]], refused: type[AdapterError]
    ) -> list[bytes]:
        """Send ``commands`` (what each is, and its bytes) in ONE generic request, return the
        payloads of their replies, in order; the first return code other than 0 raises
        ``refused``, naming its command."""
        what = " + ".join(w for w, _ in commands)
        deadline = self._tcp.deadline()
        self._tcp.send(what, request_packet(*(c for _, c in commands)))
        try:
            ptype, body = self._read_packet(what, deadline)
            if ptype != RESPONSE:
                raise _Malformed(f"packet type {ptype:#06x}, not {RESPONSE:#06x}")
            replies = _replies(body, [c[:6] for _, c in commands])
        except _Malformed as err:
            raise self._link_lost(
                f"{self.name} {what} at {self._tcp.address}: malformed reply ({err}); session dropped",
                AdapterError,
            ) from err
        for (one, _), (code, _) in zip(commands, replies, strict=True):
            if code != 0:
                raise refused(
                    f"{self.name} {one} at {self._tcp.address}: the CNC answered {focas_error(code)}"
                )
        return [payload for _, payload in replies]

    # -- macro variables -----------------------------------------------------------------

    def read_macro(self, number: int) -> float | None:
        """Common macro variable ``number`` (None: vacant). Opens the link if needed."""
        self.open()
        return self._read_macro(number, f"read #{number}")

    def _read_macro(self, number: int, what: str) -> float | None:
        payload = self._exchange(what, command(READ_MACRO, number, number), BadValueError)
        # 8 bytes per variable (pyfanuc, pyfocas's code); pyfocas's README shows one read of a
        # single variable answered with 16: the value is the first 8 either way
        if len(payload) < 8 or len(payload) % 8:
            raise BadValueError(
                f"{self.name} {what} at {self._tcp.address}: {len(payload)} bytes, not 8-byte values"
            )
        try:
            return decode_scaled(payload[:8])
        except ValueError as err:
            raise BadValueError(f"{self.name} {what} at {self._tcp.address}: {err}") from err

    def _value(self, number: int, what: str) -> float:
        value = self._read_macro(number, what)
        if value is None:
            raise BadValueError(
                f"{self.name} {what} at {self._tcp.address}: #{number} is vacant (nothing written yet, "
                "or cleared)"
            )
        return value

    def write_macro(self, number: int, value: float) -> None:
        """Write ``value`` (a double) to common macro variable ``number``; WriteRejectedError
        when the CNC refuses it."""
        self.open()
        self._write_macro(number, value)

    def _write_macro(self, number: int, value: float) -> None:
        cmd = command(WRITE_MACRO_DOUBLE, number, 0, 0, 0, 8, payload=struct.pack(">d", value))
        self._exchange(f"write #{number} = {value:g}", cmd, WriteRejectedError)

    # -- the adapter's raw calls ---------------------------------------------------------

    def _read_speed_raw(self) -> float:
        if self.speed_source == "macro":
            return self._value(self.speed_macro, f"read speed #{self.speed_macro}")  # type: ignore[arg-type]
        try:
            payload = self._exchange("read speed (cnc_acts)", command(READ_ACTS), BadValueError)
        except BadValueError as err:
            raise BadValueError(
                f"{err}; a control without it can hand the speed over in a macro "
                "variable (speed_source = 'macro')"
            ) from err
        if len(payload) < 8:
            raise BadValueError(
                f"{self.name} read speed (cnc_acts) at {self._tcp.address}: {len(payload)} bytes"
            )
        try:
            rpm = decode_scaled(payload[:8])
        except ValueError as err:
            raise BadValueError(
                f"{self.name} read speed (cnc_acts) at {self._tcp.address}: {err}"
            ) from err
        if rpm is None:
            raise BadValueError(
                f"{self.name} read speed (cnc_acts) at {self._tcp.address}: no value"
            )
        return rpm

    def _read_offset_raw(self) -> float:
        number = self.ack_macro if self.ack_macro is not None else self.offset_macro
        return self._value(number, f"read back #{number}")

    def _write_offset_raw(self, value: float) -> None:
        self._write_macro(self.offset_macro, float(value))

    def _write_life_raw(self, life: Life) -> None:
        """The counter and the flag (1/0) in ONE FOCAS request of two "write macro"
        subpackets, after the offset's own request was taken: the CNC takes each subpacket on
        its own, so a beat in the offset's request would reach the control even when the
        offset is refused. The first subpacket the CNC refuses is the failure, naming its
        variable."""
        life = checked_life(self.name, life)
        assert self.life_macros is not None  # writes_life
        counter_var, flag_var = self.life_macros
        values = [(counter_var, float(life.counter)), (flag_var, float(life.valid))]
        self._exchange_many(
            [
                (
                    f"write #{number} = {value:g}",
                    command(
                        WRITE_MACRO_DOUBLE, number, 0, 0, 0, 8, payload=struct.pack(">d", value)
                    ),
                )
                for number, value in values
            ],
            WriteRejectedError,
        )


def _reply(body: bytes, echo: bytes) -> tuple[int, bytes]:
    """The FOCAS return code and the payload of a one-subpacket reply whose command must be
    ``echo``."""
    return _replies(body, [echo])[0]


def _replies(body: bytes, echoes: list[bytes]) -> list[tuple[int, bytes]]:
    """The FOCAS return code and the payload of each subpacket of a reply, whose commands must
    be ``echoes``, in order."""
    if len(body) < 2 or struct.unpack(">H", body[:2])[0] != len(echoes):
        raise _Malformed(
            "not one subpacket" if len(echoes) == 1 else f"not {len(echoes)} subpackets"
        )
    out = []
    k = 2
    for echo in echoes:
        n = struct.unpack(">H", body[k : k + 2])[0] if len(body) >= k + 2 else 0
        sub = body[k + 2 : k + n]
        if n < 16 or len(body) < k + n:
            raise _Malformed(f"subpacket of {n} bytes in a body of {len(body)}")
        if sub[:6] != echo:
            raise _Malformed(f"reply to {sub[:6].hex(' ')}, not to {echo.hex(' ')}")
        code = struct.unpack(">h", sub[6:8])[0]
        length = struct.unpack(">H", sub[12:14])[0]
        payload = sub[14 : 14 + length]
        if len(payload) != length:
            raise _Malformed(f"payload of {len(payload)} bytes, not {length}")
        out.append((code, payload))
        k += n
    if k != len(body):
        raise _Malformed(f"subpackets of {k - 2} bytes in a body of {len(body)}")
    return out
