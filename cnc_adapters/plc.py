"""Generic PLC-register link: the offset goes into a PLC variable, the machine builder's PLC
program applies it. Three protocols behind one backend, ``plc``:

- ``s7``: Siemens S7 (S7-300/400/1200/1500, the PLC of a SINUMERIK 840D sl) through
  python-snap7 (pure Python from 3.0). Addresses in Siemens syntax: ``DB100.DBD0`` (a double
  word: ``REAL`` by default, or ``DINT``), ``DB100.DBW4`` (``INT``), ``DB100.DBX8.0`` (a bit).
  Big-endian, as the S7 stores it. An S7-1200/1500 answers only with PUT/GET access allowed
  and the DB's optimized block access switched off.
- ``modbus-tcp``: Modbus TCP through pymodbus. ``hr:40`` (or just ``40``) is holding register
  40 (the wire address, from 0), ``ir:40`` an input register, ``coil:5`` and ``di:5`` a coil and
  a discrete input. A register value is ``real32`` (two registers), ``int32`` (two) or
  ``int16``; ``word_order`` (``big``: high word first) and ``byte_order`` (inside a register;
  ``big`` is the Modbus standard) say how two registers make one value.
- ``ads``: Beckhoff ADS through pyads (optional; imported only when used). Addresses are
  symbol names (``GVL_Thermo.nTempComp``, ``MAIN.fSpeed``) of PLC type ``REAL``, ``LREAL``,
  ``DINT``, ``INT`` or ``BOOL``, or ``<index group>:<index offset>`` (``0x4020:0x10``) for an
  object without a symbol. The AMS Net ID of the target (``ams_net_id``; default: the
  host's IPv4 address and ``.1.1``) and its AMS port (``ams_port``, 851: the first TwinCAT 3
  PLC runtime) address it; the TwinCAT side needs a route to this PC's AMS Net ID
  (``local_ams_net_id`` sets it, for the whole process).

Each address has a type option (``offset_type``, ``speed_type``, ``held_type``,
``cutting_type``): ``REAL``/``real32``, ``LREAL`` (ADS), ``DINT``/``int32``, ``INT``/``int16``,
``BOOL``/``bit``; by default the address's own (an S7 DBW is an ``INT``) or ``REAL``. An
integer type takes ``int(round(raw))``, and a value outside its range is refused with
:class:`BadValueError` before anything is sent.

``offset_address`` takes the offset, ``speed_address`` holds the actual speed. The read-back
comes from ``held_address``, where the PLC reports the value it applies (a value it refused,
or has not taken yet, shows there); without one, the offset's own address is read back, which
proves only that the value arrived. ``cutting_address`` (optional) is a bit (or a state
register, with ``cutting_values``) that says the tool is in the part.

The sign of life: ``life_address`` takes the counter the PLC watches (an ``INT`` by default; an
S7 DBD a ``DINT``) and ``valid_address`` the "compensation valid" flag (``BOOL`` for an ADS
symbol or a coil, else a word holding 1/0; an S7 bit is refused: a byte write would overwrite
its neighbours). Both, or neither (``""`` turns a profile's off). They go with the offset in as
few requests as the protocol allows, the offset's request first, so that a refused offset sends
no beat: S7 and Modbus TCP one request per run of adjacent words (python-snap7's
multi-variable write sends one request per variable), each taken or refused whole (one that
carried the offset and the sign of life and was refused is followed by the offset alone); ADS
the offset's write, then one sum-write of the counter and the flag (a sum-write takes each
symbol on its own: with the offset in it, the beat would go even with the offset refused). A
refused counter or flag leaves the offset taken (the write's ``life_failure``).

A connection that fails or drops is :class:`UnreachableError`, a request that goes unanswered
:class:`AdapterTimeoutError` (both drop the link; the next call reconnects), a write the PLC
refuses (an address outside the DB, access denied, a symbol it does not have)
:class:`WriteRejectedError`.

URL forms: ``s7://host[:port]?rack=0&slot=2&offset_address=DB100.DBD0&speed_address=...``,
``modbustcp://host[:502]?device_id=1&offset_address=hr:0&...``,
``ads://host[:48898]?ams_net_id=5.12.34.56.1.1&offset_address=GVL.nTempComp&...``.
"""

from __future__ import annotations

import ipaddress
import math
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any, ClassVar
from urllib.parse import urlsplit

from pydantic import AfterValidator, Field, model_validator

from .base import (
    Adapter,
    AdapterError,
    AdapterSettings,
    AdapterTimeoutError,
    Allowed,
    BadValueError,
    ConfigError,
    CuttingValues,
    Seconds,
    Text,
    UnreachableError,
    WriteRejectedError,
    checked_life,
    host_options,
    life_configured,
    one_of,
    short,
)
from .reading import Failure, Life
from .transport.modbus import ModbusTransport, RegisterCodec

__all__ = ["PlcAdapter", "PlcSettings", "parse_address", "plc_type"]

PROTOCOLS = ("s7", "modbus-tcp", "ads")
DEFAULT_PORT = {"s7": 102, "modbus-tcp": 502, "ads": 48898}
SCHEME_PROTOCOL = {"s7": "s7", "modbustcp": "modbus-tcp", "ads": "ads"}

# -- data types ---------------------------------------------------------------------------

TYPES = ("REAL", "LREAL", "DINT", "INT", "BOOL")
_ALIASES = {
    "REAL32": "REAL",
    "FLOAT32": "REAL",
    "FLOAT": "REAL",
    "LREAL": "LREAL",
    "REAL64": "LREAL",
    "FLOAT64": "LREAL",
    "INT32": "DINT",
    "INT16": "INT",
    "BIT": "BOOL",
}
INT_RANGE = {"INT": (-(2**15), 2**15 - 1), "DINT": (-(2**31), 2**31 - 1)}
REAL_MAX = 3.4028234663852886e38  # the largest finite IEEE 754 single
_TYPE_TEXT = "one of REAL (real32), LREAL, DINT (int32), INT (int16), BOOL (bit)"


def plc_type(v: Any) -> str:
    """A data type's canonical IEC name (``REAL``, ``LREAL``, ``DINT``, ``INT``, ``BOOL``) from
    any accepted spelling (``real32``, ``int16``, ``bit``, any case)."""
    if not isinstance(v, str):
        raise ValueError(_TYPE_TEXT)
    word = v.strip().upper()
    word = _ALIASES.get(word, word)
    if word not in TYPES:
        raise ValueError(_TYPE_TEXT)
    return word


PlcType = Annotated[str, AfterValidator(plc_type), Allowed(_TYPE_TEXT)]


def encode_number(name: str, value: float, dtype: str) -> float | int | bool:
    """``value`` as ``dtype`` takes it: an integer type rounded (``int(round(value))``) and
    checked against its range, a REAL checked against the single's range;
    :class:`BadValueError` before anything is sent when it does not fit."""
    if not math.isfinite(value):
        raise BadValueError(f"{name}: refusing to write {value!r}")
    if dtype in INT_RANGE:
        lo, hi = INT_RANGE[dtype]
        whole = round(value)
        if not lo <= whole <= hi:
            raise BadValueError(
                f"{name}: {value:g} rounds to {whole}, outside {dtype} "
                f"({lo}..{hi}); nothing written"
            )
        return whole
    if dtype == "REAL" and abs(value) > REAL_MAX:
        raise BadValueError(
            f"{name}: {value:g} does not fit a REAL (32-bit float); nothing written"
        )
    if dtype == "BOOL":
        raise BadValueError(f"{name}: a number cannot go into a BOOL")
    return float(value)


# -- addresses ----------------------------------------------------------------------------

ROLES = ("offset", "speed", "held", "cutting", "life", "valid")


@dataclass(frozen=True)
class Address:
    """One parsed address: where (protocol-specific), and the data type it holds.

    S7: ``area`` ``"DB"``, ``number`` the DB, ``start`` the byte, ``bit`` for a DBX.
    Modbus: ``area`` ``hr``/``ir``/``coil``/``di``, ``start`` the wire address.
    ADS: ``area`` ``"symbol"``, ``symbol`` the name."""

    text: str
    dtype: str
    area: str
    number: int = 0
    start: int = 0
    bit: int | None = None
    symbol: str = ""

    @property
    def size(self) -> int:
        """Bytes (S7) or registers (Modbus) the value spans."""
        return {"REAL": 4, "DINT": 4, "INT": 2, "BOOL": 1, "LREAL": 8}[self.dtype]

    @property
    def registers(self) -> int:
        return {"REAL": 2, "DINT": 2, "INT": 1, "BOOL": 1, "LREAL": 4}[self.dtype]


_S7_RE = re.compile(r"DB(\d{1,5})\.DB([XWD])(\d{1,5})(?:\.(\d+))?", re.IGNORECASE)
S7_SYNTAX = (
    "an S7 address DB<n>.DBD<byte> (REAL or DINT), DB<n>.DBW<byte> (INT) or "
    "DB<n>.DBX<byte>.<bit 0-7> (BOOL), e.g. DB100.DBD0"
)
_MODBUS_RE = re.compile(r"(?:(hr|ir|coil|di):)?(\d{1,5})", re.IGNORECASE)
MODBUS_SYNTAX = (
    "a Modbus address hr:<n> (or <n>: a holding register), ir:<n> (input register), "
    "coil:<n> or di:<n> (discrete input), n 0..65535, e.g. hr:0"
)
_IDENT = r"[A-Za-z_][A-Za-z0-9_]*(?:\[\d+(?:,\d+)*\])*"
_ADS_RE = re.compile(rf"\.?{_IDENT}(?:\.{_IDENT})*")
_ADS_INDEX_RE = re.compile(r"(0x[0-9a-f]{1,8}|\d{1,10}):(0x[0-9a-f]{1,8}|\d{1,10})", re.IGNORECASE)
ADS_SYNTAX = (
    "an ADS symbol name such as GVL_Thermo.nTempComp or MAIN.fSpeed[1], or "
    "<index group>:<index offset> such as 0x4020:0x10"
)
SYNTAX = {"s7": S7_SYNTAX, "modbus-tcp": MODBUS_SYNTAX, "ads": ADS_SYNTAX}

# what each role may hold: the offset, its read-back and the speed are numbers
_NUMBERS = ("REAL", "LREAL", "DINT", "INT")
_NOUN = {
    "offset": "offset",
    "speed": "speed",
    "held": "held value",
    "cutting": "cutting signal",
    "life": "life counter",
    "valid": "valid flag",
}
_WRITTEN = ("offset", "life", "valid")
"""The roles thermocomp writes: a table a client can write, and no bit inside a byte."""


def parse_address(protocol: str, role: str, text: Any, dtype: str | None = None) -> Address:
    """The address ``text`` of ``role`` (offset, speed, held, cutting, life, valid) for
    ``protocol``, with its data type (``dtype``, or the address's own, or ``REAL``; a cutting
    signal and an ADS or coil valid flag: ``BOOL``; a life counter and a register's valid flag:
    ``INT``, a DBD's ``DINT``). ValueError with one line that names the option, the value and
    the syntax allowed."""
    key = f"{role}_address"
    if not isinstance(text, str):  # a ValueError: the settings' one-line message
        raise ValueError(f"{key} = {short(text)}: expected {SYNTAX[protocol]}")
    addr = text.strip()
    if protocol == "s7":
        m = _S7_RE.fullmatch(addr)
        width = m.group(2).upper() if m else ""
        bad = (
            m is None
            or not 1 <= int(m.group(1)) <= 65535
            or int(m.group(3)) > 65535
            or (width == "X") != (m.group(4) is not None)
            or (m.group(4) is not None and int(m.group(4)) > 7)
        )
        if bad:
            raise ValueError(f"{key} = {short(text)}: expected {S7_SYNTAX}")
        own = {"D": ("REAL", "DINT"), "W": ("INT",), "X": ("BOOL",)}[width]
        if width == "X" and role == "valid":
            raise ValueError(
                f"{key} {addr} is a bit: writing it would write its whole byte over the PLC's "
                "other bits; give a word (a DBW, INT 1/0)"
            )
        if width == "X" and role != "cutting":
            raise ValueError(
                f"{key} {addr} is a bit; the {_NOUN[role]} needs a number (a DBD or a DBW)"
            )
        if role in ("life", "valid") and width == "D":
            own = ("DINT", "REAL")
        dtype = dtype or own[0]
        if dtype not in own:
            raise ValueError(
                f"{role}_type {dtype} does not fit {key} {addr} (a DB{width} holds "
                f"{' or '.join(own)})"
            )
        assert m is not None  # checked with the syntax above
        found = Address(
            addr.upper(),
            dtype,
            "DB",
            int(m.group(1)),
            int(m.group(3)),
            None if m.group(4) is None else int(m.group(4)),
        )
    elif protocol == "modbus-tcp":
        m = _MODBUS_RE.fullmatch(addr)
        if m is None or int(m.group(2)) > 65535:
            raise ValueError(f"{key} = {short(text)}: expected {MODBUS_SYNTAX}")
        area = (m.group(1) or "hr").lower()
        bits = area in ("coil", "di")
        if role in ("life", "valid") and area not in ("hr", "coil" if role == "valid" else "hr"):
            raise ValueError(
                f"{key} = {short(text)}: expected a holding register (hr:<n>)"
                + (" or a coil (coil:<n>)" if role == "valid" else "")
                + ", the tables a client writes"
            )
        if bits and role not in ("cutting", "valid"):
            raise ValueError(
                f"{key} {addr} is a bit; the {_NOUN[role]} needs a number (hr:<n> or ir:<n>)"
            )
        dtype = dtype or (
            "BOOL" if bits else "INT" if role in ("cutting", "life", "valid") else "REAL"
        )
        if bits != (dtype == "BOOL") or dtype == "LREAL":
            allowed = "BOOL" if bits else "REAL (real32), DINT (int32) or INT (int16)"
            raise ValueError(
                f"{role}_type {dtype} does not fit {key} {addr} (a {area} holds {allowed})"
            )
        found = Address(f"{area}:{int(m.group(2))}", dtype, area, start=int(m.group(2)))
        if found.start + found.registers > 65536:
            raise ValueError(f"{key} {addr}: a {dtype} runs past register 65535")
        if role == "offset" and area != "hr":
            raise ValueError(
                f"{key} = {short(text)}: expected a holding register (hr:<n>), the one "
                "table a client writes"
            )
    else:
        index = _ADS_INDEX_RE.fullmatch(addr)
        if index is None and _ADS_RE.fullmatch(addr) is None:
            raise ValueError(f"{key} = {short(text)}: expected {ADS_SYNTAX}")
        dtype = dtype or (
            "BOOL" if role in ("cutting", "valid") else "INT" if role == "life" else "REAL"
        )
        if index is not None:  # an object by its index (a CNC object, %MB of a PLC), no symbol
            group, offset = (int(x, 0) for x in index.groups())
            if group > 0xFFFFFFFF or offset > 0xFFFFFFFF:
                raise ValueError(f"{key} = {short(text)}: expected {ADS_SYNTAX} (32-bit numbers)")
            found = Address(addr, dtype, "index", number=group, start=offset)
        else:
            found = Address(addr, dtype, "symbol", symbol=addr)
    if role not in ("cutting", "valid") and found.dtype not in _NUMBERS:
        raise ValueError(
            f"{role}_type = {found.dtype!r}: expected a number type (REAL, LREAL, DINT, INT)"
        )
    if role == "cutting" and found.dtype in ("REAL", "LREAL"):
        raise ValueError(
            f"cutting_type = {found.dtype!r}: expected BOOL or an integer type (a state)"
        )
    return found


# -- settings -----------------------------------------------------------------------------


def _net_id(v: str) -> str:
    parts = v.split(".") if isinstance(v, str) else []
    if len(parts) != 6 or not all(p.isdigit() and int(p) <= 255 for p in parts):
        raise ValueError("an AMS Net ID: six numbers 0..255 joined by dots, e.g. 5.12.34.56.1.1")
    return v


NetId = Annotated[
    str,
    AfterValidator(_net_id),
    Allowed("an AMS Net ID: six numbers 0..255 joined by dots, e.g. 5.12.34.56.1.1"),
]
Port = Annotated[int, Field(ge=1, le=65535), Allowed("a TCP port 1..65535")]
if TYPE_CHECKING:  # a plain string to the type checker; pydantic checks the choice
    Order = str
    Protocol = str
else:
    Order = one_of("big", "little")
    Protocol = one_of(*PROTOCOLS)

LifeAddress = Annotated[
    str, Allowed("an address of the protocol (as offset_address), or '' for none")
]

# options of one protocol only: given for another, they are a mistake
_OWN = {
    "s7": ("rack", "slot"),
    "modbus-tcp": ("device_id", "word_order", "byte_order"),
    "ads": ("ams_net_id", "ams_port", "local_ams_net_id"),
}


class PlcSettings(AdapterSettings):
    """The options of :class:`PlcAdapter`."""

    protocol: Protocol = Field(
        description="s7 (python-snap7), modbus-tcp (pymodbus) or ads (pyads)"
    )
    host: Text = Field(description="the PLC's address (IP or name)")
    port: Port = Field(  # type: ignore[assignment]
        None,
        description="TCP port; default 102 (s7), 502 (modbus-tcp), 48898 (ads: the AMS router)",
    )
    timeout_s: Seconds = Field(2.0, description="per request")
    rack: Annotated[int, Field(ge=0, le=7), Allowed("a rack number 0..7")] = Field(
        0, description="s7: the CPU's rack"
    )
    slot: Annotated[int, Field(ge=0, le=31), Allowed("a slot number 0..31")] = Field(
        1, description="s7: the CPU's slot (S7-1200/1500: 1, or 0; S7-300 and SINUMERIK 840D sl: 2)"
    )
    device_id: Annotated[int, Field(ge=0, le=255), Allowed("a Modbus unit id 0..255")] = Field(
        1, description="modbus-tcp: the unit id"
    )
    word_order: Order = Field("big", description="modbus-tcp: big: the high word first")
    byte_order: Order = Field(
        "big", description="modbus-tcp: inside a register; big is the standard"
    )
    ams_net_id: NetId = Field(  # type: ignore[assignment]
        None, description="ads: the target's AMS Net ID; default the host's IPv4 address + .1.1"
    )
    ams_port: Port = Field(
        851, description="ads: the AMS port (851: TwinCAT 3 PLC 1; 801: TwinCAT 2)"
    )
    local_ams_net_id: NetId = Field(  # type: ignore[assignment]
        None, description="ads: this PC's AMS Net ID, as the target's route knows it (process-wide)"
    )
    offset_address: Text = Field(description="where the offset goes")
    offset_type: PlcType = Field(  # type: ignore[assignment]
        None, description="default: the address's own, or REAL"
    )
    speed_address: Text = Field(description="where the actual speed is")
    speed_type: PlcType = Field(  # type: ignore[assignment]
        None, description="default: the address's own, or REAL"
    )
    held_address: Text = Field(  # type: ignore[assignment]
        None,
        description="where the PLC reports the value it applies; default: read the offset back",
    )
    held_type: PlcType = Field(None, description="default: offset_type")  # type: ignore[assignment]
    cutting_address: Text = Field(  # type: ignore[assignment]
        None, description="a bit (or state) that says the tool cuts; none: inferred from the speed"
    )
    cutting_type: PlcType = Field(  # type: ignore[assignment]
        None, description="default: BOOL (a Modbus register: INT)"
    )
    cutting_values: CuttingValues = Field(
        [True],  # type: ignore[arg-type]  # a list, as documented
        description="the values that mean cutting (a bit: true; false for an inverted one)",
    )
    life_address: LifeAddress = Field(  # type: ignore[assignment]
        None,
        description="the sign of life: the counter the PLC watches (a word: S7 DBW, hr:<n>, an "
        "INT symbol); '' for none, where a profile names one",
    )
    life_type: PlcType = Field(  # type: ignore[assignment]
        None, description="default: INT (an S7 DBD: DINT)"
    )
    valid_address: LifeAddress = Field(  # type: ignore[assignment]
        None,
        description="the sign of life: the 'compensation valid' flag (S7 DBW 1/0, hr:<n> 1/0 or "
        "coil:<n>, a BOOL symbol); '' for none, where a profile names one",
    )
    valid_type: PlcType = Field(  # type: ignore[assignment]
        None, description="default: BOOL (ADS, a coil), INT (a register or DBW)"
    )

    @model_validator(mode="after")
    def _check(self) -> PlcSettings:
        check_plc(
            self.protocol,
            self.model_fields_set,
            self.host,
            self.ams_net_id,
            {r: (getattr(self, f"{r}_address"), getattr(self, f"{r}_type")) for r in ROLES},
            ValueError,
        )
        return self


def check_plc(
    protocol: str,
    given: Any,
    host: str,
    ams_net_id: str | None,
    addresses: dict[str, tuple[str | None, str | None]],
    error: type[Exception] = ConfigError,
) -> dict[str, Address]:
    """Every address parsed for ``protocol`` (the held value's type by default the offset's,
    where the held address can hold it); an option of another protocol among ``given`` and an
    ADS target without an AMS Net ID to derive are refused."""
    for other, keys in _OWN.items():
        wrong = [k for k in keys if k in given and other != protocol]
        if wrong:
            raise error(f"{wrong[0]} is an option of protocol {other!r}, not of {protocol!r}")
    out: dict[str, Address] = {}
    life, valid = addresses.get("life", (None, None)), addresses.get("valid", (None, None))
    try:
        life_configured(life[0], valid[0], "life_address", "valid_address")
    except ValueError as err:
        raise error(str(err)) from None
    for role, (text, dtype) in addresses.items():
        if text is None or (text == "" and role in ("life", "valid")):
            if dtype is not None and role in ("held", "cutting", "life", "valid"):
                raise error(f"{role}_type needs {role}_address")
            continue
        try:
            out[role] = parse_address(protocol, role, text, dtype)
        except ValueError as err:
            raise error(str(err)) from None
    if "held" in out and addresses["held"][1] is None:  # the held value as the offset is written
        try:
            out["held"] = parse_address(protocol, "held", addresses["held"][0], out["offset"].dtype)
        except ValueError:
            pass  # an S7 DBW beside a DBD: its own type
    written = [(r, out[r]) for r in _WRITTEN if r in out]
    for i, (ra, a) in enumerate(written):
        for rb, b in written[i + 1 :]:
            if _overlap(a, b):
                raise error(f"{ra}_address {a.text} and {rb}_address {b.text} overlap")
    if protocol == "ads" and ams_net_id is None:
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            raise error(
                f"ams_net_id is required: host {short(host)} is no IPv4 address to "
                "derive it from (<ip>.1.1)"
            ) from None
    return out


def _overlap(a: Address, b: Address) -> bool:
    """Whether two addresses share a byte (S7), a register or coil (Modbus) or a symbol."""
    if a.area != b.area or a.number != b.number:
        return False
    if a.area == "symbol":
        return a.symbol.lower() == b.symbol.lower()
    width = (lambda x: x.size) if a.area in ("DB", "index") else (lambda x: x.registers)
    return a.start < b.start + width(b) and b.start < a.start + width(a)


def encode_flag(valid: bool, dtype: str) -> bool | int | float:
    """The valid flag as ``dtype`` holds it: a BOOL true/false, a number 1/0."""
    if dtype == "BOOL":
        return bool(valid)
    return float(valid) if dtype in ("REAL", "LREAL") else int(valid)


# -- the protocols ------------------------------------------------------------------------


class _Driver:
    """One protocol's client: connect, read, write, with its errors mapped to the tree."""

    def __init__(self, owner: PlcAdapter):
        self.owner = owner
        self.name = owner.name
        self.at = f"{owner.host}:{owner.port}"  # the endpoint every message names

    def head(self, what: str) -> str:
        """``plc <operation> (<address>) at <endpoint>``: the start of a request's message."""
        return f"{self.name} {what} at {self.at}"

    def lost(self, message: str, error: type[AdapterError] = UnreachableError) -> AdapterError:
        return self.owner._link_lost(message, error)

    def connect(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def read(self, what: str, a: Address) -> Any:
        raise NotImplementedError

    def write(self, what: str, a: Address, value: float) -> None:
        raise NotImplementedError

    atomic = False
    """Whether a request of several values is taken whole or refused whole: then the offset
    may share its request with the sign of life (a refused offset takes no beat along)."""

    def requests(self, items: list[Item]) -> list[list[Item]]:
        """``items`` (name, address, value) in as few requests as the protocol allows, the
        values of each; by default one each, in order."""
        return [[item] for item in items]

    def send(self, request: list[Item]) -> None:
        """Send one request of :meth:`requests`."""
        ((name, a, value),) = request
        self.write(f"write {name} ({a.text})", a, value)


Item = tuple[str, Address, Any]
"""One value to write: what it is (``offset``, ``life counter``, ``valid flag``), its address
and its value, encoded for the address's type."""


def runs(items: list[Item], width: Any) -> list[list[Item]]:
    """``items`` in runs of adjacent addresses (one request each): sorted by area, number and
    start, a run going on while the next starts where the last ends (``width(address)``)."""
    out: list[list[Item]] = []
    for item in sorted(items, key=lambda i: (i[1].area, i[1].number, i[1].start)):
        last = out[-1][-1][1] if out else None
        a = item[1]
        if (
            last is not None
            and last.area == a.area
            and last.number == a.number
            and a.start == last.start + width(last)
        ):
            out[-1].append(item)
        else:
            out.append([item])
    return out


def _what(run: list[Item]) -> str:
    """``write offset, life counter (DB100.DBD0, DB100.DBW4)``: a request's head."""
    return f"write {', '.join(n for n, _, _ in run)} ({', '.join(a.text for _, a, _ in run)})"


class _S7(_Driver):
    client: Any = None  # a snap7 Client while open

    def connect(self) -> None:
        from snap7.client import Client
        from snap7.error import S7Error

        o = self.owner
        self.at = f"{o.host}:{o.port} (rack {o.rack}, slot {o.slot})"
        client = Client()
        try:
            client.connect(o.host, o.rack, o.slot, tcp_port=o.port)
        except (S7Error, OSError) as err:
            _quietly(client.disconnect)
            raise UnreachableError(
                f"{self.name}: no S7 PLC at {o.host}:{o.port} (rack {o.rack}, slot {o.slot}): {err}"
            ) from err
        # python-snap7 waits 5 s by default; a request waits timeout_s
        connection: Any = client.connection  # set by connect()
        connection.timeout = o.timeout_s
        connection.socket.settimeout(o.timeout_s)
        self.client = client

    def close(self) -> None:
        client, self.client = self.client, None
        if client is not None:
            _quietly(client.disconnect)

    def _call(self, what: str, fn: Any, *args: Any, refused: type[AdapterError]) -> Any:
        from snap7 import error
        from snap7.error import S7ConnectionError, S7Error, S7TimeoutError

        # a reply out of step with its request: the stream is no longer trusted (newer releases)
        out_of_step = tuple(
            getattr(error, n)
            for n in ("S7StalePacketError", "S7PacketLostError")
            if hasattr(error, n)
        )
        try:
            return fn(*args)
        except S7TimeoutError as err:
            raise self.lost(
                f"{self.head(what)}: no answer within {self.owner.timeout_s:g} s: {err}",
                AdapterTimeoutError,
            ) from err
        except (S7ConnectionError, OSError, *out_of_step) as err:
            raise self.lost(f"{self.head(what)}: link lost: {err}") from err
        except S7Error as err:  # the PLC answered with an error: wrong DB, no PUT/GET access
            raise refused(f"{self.head(what)}: the PLC refused: {err}") from err

    def read(self, what: str, a: Address) -> Any:
        from snap7.util import get_bool, get_dint, get_int, get_real

        data = self._call(
            what, self.client.db_read, a.number, a.start, a.size, refused=AdapterError
        )
        if len(data) < a.size:
            raise BadValueError(f"{self.head(what)}: {len(data)} bytes, not {a.size}")
        if a.dtype == "BOOL":
            return get_bool(data, 0, a.bit or 0)
        return {"REAL": get_real, "DINT": get_dint, "INT": get_int}[a.dtype](data, 0)

    def write(self, what: str, a: Address, value: float) -> None:
        from snap7.util import set_dint, set_int, set_real

        data = bytearray(a.size)
        if a.dtype == "REAL":
            set_real(data, 0, value)
        else:  # a whole number (encode_number rounded it)
            {"DINT": set_dint, "INT": set_int}[a.dtype](data, 0, int(value))
        self._call(what, self.client.db_write, a.number, a.start, data, refused=WriteRejectedError)

    atomic = True  # one db_write: the PLC takes the bytes or refuses them

    def requests(self, items: list[Item]) -> list[list[Item]]:
        """One ``db_write`` per run of adjacent bytes in one DB (python-snap7's
        ``write_multi_vars`` sends one request per item: no fewer requests)."""
        return runs(items, lambda a: a.size)

    def send(self, request: list[Item]) -> None:
        from snap7.util import set_dint, set_int, set_real

        run = request
        first = run[0][1]
        data = bytearray(sum(a.size for _, a, _ in run))
        k = 0
        for _, a, value in run:
            if a.dtype == "REAL":
                set_real(data, k, float(value))
            else:
                {"DINT": set_dint, "INT": set_int}[a.dtype](data, k, int(value))
            k += a.size
        self._call(
            _what(run),
            self.client.db_write,
            first.number,
            first.start,
            data,
            refused=WriteRejectedError,
        )


class _ModbusTcp(_Driver):
    """Through the Modbus transport: its codec, and its error policy."""

    modbus: ModbusTransport | None = None

    @property
    def _modbus(self) -> ModbusTransport:
        assert self.modbus is not None  # the adapter reads and writes only while open
        return self.modbus

    def connect(self) -> None:
        o = self.owner
        modbus = ModbusTransport(
            self.name,
            lost=o._link_lost,
            host=o.host,
            port=o.port,
            device_id=o.device_id,
            timeout_s=o.timeout_s,
            codec=RegisterCodec(o.word_order, o.byte_order),
        )
        modbus.connect()
        self.modbus = modbus

    def close(self) -> None:
        modbus, self.modbus = self.modbus, None
        if modbus is not None:
            modbus.close()

    def read(self, what: str, a: Address) -> Any:
        if a.area in ("coil", "di"):
            return self._modbus.read_bit(what, a.area, a.start)
        table = "holding" if a.area == "hr" else "input"
        regs = self._modbus.read_registers(what, table, a.start, a.registers)
        return self._modbus.codec.decode(regs, _REGISTER_TYPE[a.dtype])

    def write(self, what: str, a: Address, value: float) -> None:
        self._modbus.write_value(what, a.start, value, _REGISTER_TYPE[a.dtype])

    atomic = True  # a Modbus exception reply: nothing of the request was written

    def requests(self, items: list[Item]) -> list[list[Item]]:
        """One ``write_registers`` per run of adjacent holding registers; a coil its own."""
        out: list[list[Item]] = []
        for run in runs(items, lambda a: a.registers):
            out += [[item] for item in run] if run[0][1].area == "coil" else [run]
        return out

    def send(self, request: list[Item]) -> None:
        run = request
        first = run[0][1]
        if first.area == "coil":
            ((name, a, value),) = run
            self._modbus.request(
                f"write {name} coil {a.start}",
                "write_coil",
                a.start,
                bool(value),
                refused=WriteRejectedError,
            )
            return
        regs: list[int] = []
        for _, a, value in run:
            regs += self._modbus.codec.encode(
                value, _REGISTER_TYPE[a.dtype], f"{self.name} {_what(run)}"
            )
        self._modbus.write_registers(_what(run), first.start, regs)


_REGISTER_TYPE = {"REAL": "float32", "DINT": "int32", "INT": "int16"}


# ADS return codes: 0x700-0x73F the target answered (device errors), 0x745 a request's timeout
_ADS_DEVICE = range(0x700, 0x740)
_ADS_TIMEOUT = 0x745


class _Ads(_Driver):
    conn: Any = None  # a pyads Connection while open

    def connect(self) -> None:
        try:
            import pyads
        except ImportError as err:  # an optional extra: say which
            raise AdapterError(
                f"{self.name}: protocol 'ads' needs pyads (pip install thermocomp[ads]): {err}"
            ) from err
        o = self.owner
        self.pyads = pyads
        self.types = {
            "REAL": pyads.PLCTYPE_REAL,
            "LREAL": pyads.PLCTYPE_LREAL,
            "DINT": pyads.PLCTYPE_DINT,
            "INT": pyads.PLCTYPE_INT,
            "BOOL": pyads.PLCTYPE_BOOL,
        }
        # the AdsLib takes host:port; the plain host reaches the router's own 48898
        where = o.host if o.port == DEFAULT_PORT["ads"] else f"{o.host}:{o.port}"
        self.at = f"{o.ams_net_id}:{o.ams_port} via {where}"
        conn = None
        try:
            if o.local_ams_net_id is not None:
                pyads.set_local_address(o.local_ams_net_id)
            conn = pyads.Connection(o.ams_net_id, o.ams_port, where)
            conn.open()
            conn.set_timeout(max(1, round(o.timeout_s * 1000)))
            conn.read_state()  # the AdsLib connects lazily: a first request proves the route
        except (pyads.ADSError, OSError) as err:
            if conn is not None:
                _quietly(conn.close)
            raise UnreachableError(
                f"{self.name}: no ADS target {o.ams_net_id}:{o.ams_port} at {where}: {err}"
            ) from err
        self.conn = conn

    def close(self) -> None:
        conn, self.conn = self.conn, None
        if conn is not None:
            _quietly(conn.close)

    def _call(self, what: str, fn: Any, *args: Any, refused: type[AdapterError]) -> Any:
        try:
            return fn(*args)
        except self.pyads.ADSError as err:
            code = getattr(err, "err_code", None)
            if code in _ADS_DEVICE:  # the target answered: no such symbol, wrong size, ...
                raise refused(f"{self.head(what)}: the target refused: {err}") from err
            if code == _ADS_TIMEOUT:
                raise self.lost(
                    f"{self.head(what)}: no answer within {self.owner.timeout_s:g} s: {err}",
                    AdapterTimeoutError,
                ) from err
            raise self.lost(f"{self.head(what)}: link lost: {err}") from err
        except OSError as err:
            raise self.lost(f"{self.head(what)}: link lost: {err}") from err

    def read(self, what: str, a: Address) -> Any:
        t = self.types[a.dtype]
        if a.area == "index":
            return self._call(what, self.conn.read, a.number, a.start, t, refused=AdapterError)
        return self._call(what, self.conn.read_by_name, a.symbol, t, refused=AdapterError)

    def requests(self, items: list[Item]) -> list[list[Item]]:
        """Symbols: ONE ADS sum-write (pyads's ``write_list_by_name``; each symbol's info is
        asked once a connection). Index-group addresses: one write each. (The PLC takes each
        symbol of a sum-write on its own: the adapter asks for the offset's and the sign of
        life's requests apart.)"""
        named = [i for i in items if i[1].area == "symbol"]
        return [[i] for i in items if i[1].area != "symbol"] + ([named] if named else [])

    def send(self, request: list[Item]) -> None:
        """An index-group write, or a sum-write of symbols whose every result is checked (one
        request, a single symbol's too, once its info is known)."""
        if request[0][1].area != "symbol":
            super().send(request)
            return
        named = request
        what = _what(named)
        results = self._call(
            what,
            self.conn.write_list_by_name,
            {a.symbol: value for _, a, value in named},
            refused=WriteRejectedError,
        )
        for name, a, _ in named:
            said = str(results.get(a.symbol, "no result")) if isinstance(results, dict) else ""
            if said != "no error":
                raise WriteRejectedError(
                    f"{self.head(f'write {name} ({a.text})')}: the target refused: {said}"
                )

    def write(self, what: str, a: Address, value: float) -> None:
        t = self.types[a.dtype]
        if a.area == "index":
            self._call(
                what, self.conn.write, a.number, a.start, value, t, refused=WriteRejectedError
            )
        else:
            self._call(
                what, self.conn.write_by_name, a.symbol, value, t, refused=WriteRejectedError
            )


_DRIVERS = {"s7": _S7, "modbus-tcp": _ModbusTcp, "ads": _Ads}


def _quietly(fn: Any) -> None:
    try:
        fn()
    except Exception:  # noqa: BLE001 - closing what is already dead
        pass


# -- the adapter --------------------------------------------------------------------------


class PlcAdapter(Adapter):
    """A PLC variable takes the offset; the builder's PLC program applies it (see the module
    docstring). Nothing connects before the first call."""

    name = "plc"
    Settings: ClassVar[type[AdapterSettings]] = PlcSettings
    can_read_offset: ClassVar[bool] = True  # the held address, or the offset's own

    def __init__(
        self,
        *,
        protocol: str,
        host: str,
        offset_address: str,
        speed_address: str,
        port: int | None = None,
        timeout_s: float = 2.0,
        rack: int = 0,
        slot: int = 1,
        device_id: int = 1,
        word_order: str = "big",
        byte_order: str = "big",
        ams_net_id: str | None = None,
        ams_port: int = 851,
        local_ams_net_id: str | None = None,
        offset_type: str | None = None,
        speed_type: str | None = None,
        held_address: str | None = None,
        held_type: str | None = None,
        cutting_address: str | None = None,
        cutting_type: str | None = None,
        cutting_values: tuple[Any, ...] = (True,),
        life_address: str | None = None,
        life_type: str | None = None,
        valid_address: str | None = None,
        valid_type: str | None = None,
        **scaling: Any,
    ):
        super().__init__(**scaling)
        if protocol not in PROTOCOLS:
            raise ConfigError(
                f"plc adapter: protocol must be one of {', '.join(PROTOCOLS)}, "
                f"not {short(protocol)}"
            )
        given = {
            k
            for k, v in (
                ("rack", rack != 0),
                ("slot", slot != 1),
                ("device_id", device_id != 1),
                ("word_order", word_order != "big"),
                ("byte_order", byte_order != "big"),
                ("ams_net_id", ams_net_id is not None),
                ("ams_port", ams_port != 851),
                ("local_ams_net_id", local_ams_net_id is not None),
            )
            if v
        }

        def typed(t: str | None) -> str | None:
            try:
                return None if t is None else plc_type(t)
            except ValueError as err:
                raise ConfigError(
                    f"plc adapter: a data type must be {err}, not {short(t)}"
                ) from None

        found = check_plc(
            protocol,
            given,
            host,
            ams_net_id,
            {
                "offset": (offset_address, typed(offset_type)),
                "speed": (speed_address, typed(speed_type)),
                "held": (held_address, typed(held_type)),
                "cutting": (cutting_address, typed(cutting_type)),
                "life": (life_address, typed(life_type)),
                "valid": (valid_address, typed(valid_type)),
            },
        )
        self.protocol = protocol
        self.host = host
        self.port = int(port) if port is not None else DEFAULT_PORT[protocol]
        self.timeout_s = float(timeout_s)
        self.rack, self.slot, self.device_id = int(rack), int(slot), int(device_id)
        self.word_order, self.byte_order = word_order, byte_order
        self.ams_net_id = ams_net_id or (f"{host}.1.1" if protocol == "ads" else None)
        self.ams_port = int(ams_port)
        self.local_ams_net_id = local_ams_net_id
        self.offset = found["offset"]
        self.speed = found["speed"]
        self.held = found.get("held", self.offset)
        self.cutting = found.get("cutting")
        self.can_read_cutting = self.cutting is not None  # type: ignore[misc]
        self.cutting_values = tuple(cutting_values)
        # the sign of life: both addresses, or neither ("" turns a profile's default off)
        self.life = found.get("life")
        self.valid = found.get("valid")
        self.writes_life = self.life is not None and self.valid is not None
        self._driver: _Driver | None = None

    @classmethod
    def url_options(cls, url: str) -> dict[str, Any]:
        """``s7://host[:port]?...``, ``modbustcp://host[:port]?...``, ``ads://host[:port]?...``:
        the scheme is the protocol, the query the other options."""
        parts = urlsplit(url)
        protocol = SCHEME_PROTOCOL.get(parts.scheme)
        if protocol is None:
            raise ConfigError(
                f"plc adapter: no protocol for URL scheme {parts.scheme!r}; "
                f"known: {', '.join(SCHEME_PROTOCOL)}"
            )
        return {"protocol": protocol, **host_options("plc adapter", url)}

    # -- the link -----------------------------------------------------------------------

    def _connect(self) -> None:
        driver = _DRIVERS[self.protocol](self)
        driver.connect()
        self._driver = driver

    def _disconnect(self) -> None:
        driver, self._driver = self._driver, None
        if driver is not None:
            driver.close()

    def _read(self, what: str, a: Address) -> Any:
        return self._driver.read(f"read {what} ({a.text})", a)  # type: ignore[union-attr]

    def _read_speed_raw(self) -> Any:
        return self._read("speed", self.speed)

    def _read_offset_raw(self) -> Any:
        return self._read("held offset", self.held)

    def _read_cutting_raw(self) -> Any:
        return self._read("cutting signal", self.cutting)  # type: ignore[arg-type]

    def _write_offset_raw(self, value: float) -> None:
        a = self.offset
        packed = encode_number(self.name, value, a.dtype)  # refused here: nothing is sent
        self._driver.write(f"write offset ({a.text})", a, packed)  # type: ignore[union-attr]

    def _write_raw(self, raw: float | None, life: Life | None) -> Failure | None:
        """The offset and the sign of life in as few requests as the protocol allows (see
        :meth:`_Driver.requests`), the offset's first: a refused offset sends no beat. Every
        value encoded first, so that a value that does not fit sends nothing. A request of the
        sign of life alone that fails is its failure, the offset taken."""
        if life is None:
            if raw is not None:
                self._write_offset_raw(raw)
            return None
        life = checked_life(self.name, life)
        assert self.life is not None and self.valid is not None  # writes_life
        driver = self._driver
        assert driver is not None  # open
        mine: list[Item] = []
        if raw is not None:
            mine.append(("offset", self.offset, encode_number(self.name, raw, self.offset.dtype)))
        beat: list[Item] = [
            ("life counter", self.life, encode_number(self.name, life.counter, self.life.dtype)),
            ("valid flag", self.valid, encode_flag(life.valid, self.valid.dtype)),
        ]
        if driver.atomic:
            requests = driver.requests(mine + beat)
        else:  # each value taken on its own: the offset in a request of its own
            requests = driver.requests(mine) + driver.requests(beat)
        requests.sort(key=lambda r: all(name != "offset" for name, _, _ in r))  # offset first
        for request in requests:
            if any(name == "offset" for name, _, _ in request):
                self._offset_sent_alone = len(request) == 1
                driver.send(request)  # the offset's failure (with the life in it: sent alone)
            else:
                failure = self._life_part(lambda r=request: driver.send(r))  # type: ignore[misc]
                if failure is not None:
                    return failure
        return None
