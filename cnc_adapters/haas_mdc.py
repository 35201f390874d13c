"""Haas NGC Machine Data Collection (MDC) over TCP: the Haas Q/E commands of
:class:`~cnc_adapters.serial_link.HaasAdapter` on the control's MDC port instead of RS-232.

Setting 143 enables MDC and is the TCP port (5051 in Haas's example). The requests and the reply
parsing are :class:`~cnc_adapters.serial_link.HaasAdapter`'s own, composed here (an inner
instance whose line exchange is this link's socket): ``?Q600 <var>`` reads a macro variable
(speed #3027 by default, the offset's ``offset_var`` read back), ``?E<var> <value>`` writes one,
answered ``!`` (taken) or ``?`` (refused: :class:`WriteRejectedError`), and the probe cycle's
measurement handshake reads ``measurement_sequence_var``, ``measurement_var`` (and
``measurement_sigma_var``) the same way.

The sign of life (``life_var``, ``valid_var``) goes as the serial link's, one ``?E`` each after
the offset, and is not read back.

One request line and one reply line, over the TCP transport (:mod:`cnc_adapters.transport.tcp`,
which maps the socket's faults):

- before each request the input left on the socket is dropped (a late reply, the ``>`` prompt,
  output another MDC client asked for: the control sends every reply to all its connections);
- a reply line ends at a line feed or at ETB (0x17); what is outside the STX (0x02) ... ETB
  frame, the ``>`` prompts and an echo of the request are taken off; an empty line is skipped;
- ``MACRO, <value>`` (the form reported from an NGC over TCP) is read as ``MACRO, <var>,
  <value>`` (the form reported over RS-232) for the variable asked for;
- output that cannot answer the request is skipped, not taken: every request's echo, a
  ``MACRO`` reply naming another variable, anything but ``!`` or a refusal after a ``?E`` (the
  control sends every reply to all its connections, so another MDC client's can arrive while
  this one waits; a bare ``MACRO, <value>`` of another client's ``?Q600`` cannot be told apart:
  ``docs/controls/haas.md``, pitfalls);
- no reply within ``timeout_s``, or half a line: :class:`AdapterTimeoutError`, and the
  connection is dropped (a peer that went silent is often a half-open connection; the next call
  connects again); the first request on a new connection is sent once more when it draws no
  reply (Haas: the first ``?Q100`` "may have to be entered twice");
- a refused or lost connection, and the control's "too many connections" (MDC takes two):
  :class:`UnreachableError`; the next call reconnects, with the back-off of
  :class:`~cnc_adapters.base.Link`.

URL form: ``haas://host:5051?offset_var=10500``.
"""

from __future__ import annotations

import re
from typing import Annotated, Any, ClassVar
from urllib.parse import urlsplit

from pydantic import Field

from .base import (
    Adapter,
    AdapterSettings,
    AdapterTimeoutError,
    Allowed,
    BadValueError,
    RawMeasurement,
    Seconds,
    WriteRejectedError,
    query_params,
)
from .reading import Life
from .serial_link import HaasAdapter, HaasMacros
from .transport.tcp import TcpTransport

__all__ = ["HaasMdcAdapter", "HaasMdcSettings"]

STX, ETB = "\x02", "\x17"
REJECT_REPLY = r"^>?\s*(\?|INVALID|ERROR|NOT ALLOWED|UNKNOWN).*"
"""The Haas refusals of :class:`HaasAdapter`, and ``UNKNOWN`` (reported for an unsupported
command)."""

_Q600 = re.compile(r"^\?Q600\s+(\d+)$")
_BARE_MACRO = re.compile(r"^MACRO\s*,\s*([^,]*)$")
_NAMED_MACRO = re.compile(r"^MACRO\s*,\s*(\d+)\s*,")
_ECHO = re.compile(r"^\?[QE]\d")
_TOO_MANY = re.compile(r"too many connections", re.IGNORECASE)


class HaasMdcSettings(HaasMacros, AdapterSettings):
    """The options of :class:`HaasMdcAdapter`: the TCP endpoint, and the Haas options of
    :class:`~cnc_adapters.serial_link.HaasSettings` (:class:`~cnc_adapters.serial_link.HaasMacros`)."""

    host: Annotated[str, Field(min_length=1), Allowed("a host name or IP address of the control")]
    port: Annotated[
        int, Field(ge=1, le=65535), Allowed("a TCP port 1..65535 (the control's Setting 143)")
    ] = 5051
    timeout_s: Seconds = Field(1.0, description="for one reply line")
    connect_timeout_s: Seconds = Field(3.0, description="for the TCP connection")
    eol: Annotated[
        str, Field(min_length=1, pattern=r"^[\x00-\x7f]+$"), Allowed("a non-empty ASCII string")
    ] = Field("\r\n", description="end of line, sent and expected")


class _MdcProtocol(HaasAdapter):
    """:class:`HaasAdapter`'s requests and replies, each line exchanged by the MDC link."""

    name = "haas-mdc"

    def __init__(self, link: HaasMdcAdapter, **haas: Any):
        super().__init__(
            link.address, eol=link.eol, timeout_s=link.timeout_s, reject_reply=REJECT_REPLY, **haas
        )
        self._link = link

    def exchange(self, request: str | None, op: str = "read") -> str:
        assert request is not None  # the Haas commands are all requests
        return self._link.exchange(request, op)


class HaasMdcAdapter(Adapter):
    """Haas NGC MDC over TCP (see the module docstring): speed from macro #3027, the offset to
    a macro variable ``offset_var``, read back with ``?Q600``; a macro on the control applies it
    (``docs/controls/haas.md``)."""

    name = "haas-mdc"
    Settings: ClassVar[type[AdapterSettings]] = HaasMdcSettings
    can_read_offset: ClassVar[bool] = True
    can_read_measurement: ClassVar[bool] = True  # an instance without measurement_var cannot

    def __init__(
        self,
        host: str,
        port: int = 5051,
        *,
        timeout_s: float = 1.0,
        connect_timeout_s: float = 3.0,
        eol: str = "\r\n",
        speed_var: int = 3027,
        offset_var: int = 10500,
        offset_decimals: int = 4,
        measurement_var: int | None = None,
        measurement_sequence_var: int | None = None,
        measurement_sigma_var: int | None = None,
        measurement_scale: float | None = None,
        life_var: int | str | None = None,
        valid_var: int | str | None = None,
        **scaling: Any,
    ):
        super().__init__(**scaling)
        self.host = str(host)
        self.port = int(port)
        self.timeout_s = float(timeout_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self.eol = eol
        self._tcp = TcpTransport(
            self.name,
            self.host,
            self.port,
            timeout_s=self.timeout_s,
            connect_timeout_s=self.connect_timeout_s,
            keepalive=True,  # Haas: keep MDC open
            lost=self._link_lost,
            closed_reason=self._closed_reason,
        )
        self._fresh = False  # no request answered yet on this connection
        self._proto = _MdcProtocol(
            self,
            speed_var=speed_var,
            offset_var=offset_var,
            offset_decimals=offset_decimals,
            measurement_var=measurement_var,
            measurement_sequence_var=measurement_sequence_var,
            measurement_sigma_var=measurement_sigma_var,
            measurement_scale=measurement_scale,
            life_var=life_var,
            valid_var=valid_var,
        )
        self.writes_life = self._proto.writes_life
        self.speed_var = self._proto.speed_var
        self._proto_decimals = int(offset_decimals)
        self.offset_var = self._proto.offset_var
        self.can_read_measurement = self._proto.can_read_measurement  # type: ignore[misc]
        self.measurement_scale = measurement_scale

    @property
    def address(self) -> str:
        return self._tcp.address

    @classmethod
    def url_options(cls, url: str) -> dict[str, Any]:
        """``haas://host:5051?offset_var=10500`` (the port defaults to 5051)."""
        parts = urlsplit(url)
        out: dict[str, Any] = {"host": parts.hostname or ""}
        try:
            if parts.port is not None:
                out["port"] = parts.port
        except ValueError:  # not a port: the settings say what is allowed
            out["port"] = parts.netloc.rpartition(":")[2]
        return {**out, **query_params(url)}

    # -- the link ----------------------------------------------------------------------

    def _connect(self) -> None:
        self._tcp.connect()
        self._fresh = True

    def _disconnect(self) -> None:
        self._tcp.close()

    def _abort(self) -> None:
        self._tcp.abort()  # a hung peer: do not wait for it

    def exchange(self, request: str, op: str = "read") -> str:
        """Send one request line and return the reply line, cleaned (see the module docstring);
        a failure says ``op`` (``read speed``), the request and the control's address."""
        self.open()
        fresh, self._fresh = self._fresh, False
        try:
            return self._round_trip(request, op, drop_on_timeout=not fresh)
        except AdapterTimeoutError:
            if not fresh:
                raise
        # the first request on a new connection may go unanswered: once more, on it
        return self._round_trip(request, op)

    def _round_trip(self, request: str, op: str, *, drop_on_timeout: bool = True) -> str:
        what = f"{op} {request!r}"
        self._tcp.drain(what)  # a stale reply must never answer this request
        self._tcp.send(what, (request + self.eol).encode("ascii"))
        deadline = self._tcp.deadline()
        ends = (self.eol[-1].encode("ascii"), ETB.encode())
        while True:
            line = self._tcp.recv_until(what, ends, deadline, drop_on_timeout=drop_on_timeout)
            reply = self._clean(line, request)
            if reply:
                return reply
            # else a prompt, an echo, an empty line: read on

    def _closed_reason(self, last: bytes) -> str | None:
        """Why the control closed the connection, from what it sent last: MDC's refusal of a
        third connection."""
        lines = last.decode("ascii", "replace").splitlines()
        said = [line for line in lines if _TOO_MANY.search(line)]
        if not said:
            return None
        return (
            f"{self.name}: {self.address} refused the connection: "
            f"{said[-1].strip(' >' + chr(13) + chr(10))!r} (MDC takes two connections)"
        )

    def _clean(self, raw: bytes, request: str) -> str:
        """The reply text in ``raw`` ('' for none): the STX frame's content without prompts;
        the bare ``MACRO, <value>`` named for the variable asked; '' for an echo and for output
        that cannot answer ``request`` (another client's: the control sends to all)."""
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError as err:
            raise BadValueError(
                f"{self.name} {request!r} at {self.address}: garbage reply {raw!r}"
            ) from err
        if STX in text:
            text = text.rsplit(STX, 1)[1]  # an echo or a prompt may precede the frame
        text = text.replace(ETB, "").strip().lstrip(">").strip()
        if _TOO_MANY.search(text):
            raise self._link_lost(
                f"{self.name}: {self.address} refused the connection: {text!r} "
                "(MDC takes two connections)"
            )
        if not text or _ECHO.match(text):
            return ""  # a prompt, or a request echoed (Setting 187), ours or another client's
        refusal = self._proto.reject_reply.match(text) is not None
        if request.startswith("?E"):
            return text if refusal or text == "!" else ""
        q = _Q600.match(request)
        if q is None or refusal:
            return text
        bare = _BARE_MACRO.match(text)
        if bare:
            return f"MACRO, {q.group(1)}, {bare.group(1).strip()}"
        named = _NAMED_MACRO.match(text)
        if named and named.group(1) == q.group(1):
            return text
        return ""  # another variable, a write's '!', another query's reply

    # -- the Haas requests (serial_link.HaasAdapter's) ------------------------------------

    def _read_speed_raw(self) -> float:
        return self._proto._read_speed_raw()

    def _read_offset_raw(self) -> float:
        return self._proto._read_offset_raw()

    def _write_offset_raw(self, value: float) -> None:
        self._proto._write_offset_raw(value)
        # the control answers every client: another's '!' may have been taken for ours, so
        # the value is read back before the write counts as taken
        held = self._proto._read_offset_raw()
        step = 10.0**-self._proto_decimals
        if not (isinstance(held, (int, float)) and abs(held - value) <= step / 2 + 1e-12):
            raise WriteRejectedError(
                f"{self.name} write offset #{self._proto.offset_var} at {self.address}: "
                f"wrote {value!r}, the "
                f"control holds {held!r} (another client's reply taken for ours?)"
            )

    def _write_life_raw(self, life: Life) -> None:
        # one ?E a variable; not read back (a missed beat is one the control's watchdog
        # tolerates; a stop that is missed stops the counter, which the watchdog sees)
        self._proto._write_life_raw(life)

    def _read_measurement_raw(self) -> RawMeasurement | None:
        return self._proto._read_measurement_raw()
