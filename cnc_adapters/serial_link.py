"""Serial controller links (pyserial): a generic ASCII line protocol and Haas Q/E commands.

Every request is one line; every reply is one line, matched by a regular expression
whose named group ``value`` carries the number. Before each request the input buffer is
flushed, so a late reply to an earlier request can never be taken for the current one.

A device that vanishes (a USB adapter unplugged) raises :class:`UnreachableError`; the
adapter closes the port and reopens it on the next call, so it recovers when the device
returns. A silent or half-finished reply raises :class:`AdapterTimeoutError`; a reply that
does not match raises :class:`BadValueError`; a refused write raises
:class:`WriteRejectedError`.

Haas (NGC "machine data collection" Q/E commands): ``?Q600 <var>`` reads a macro variable,
answered ``MACRO, <var>, <value>`` (a leading ``>`` is allowed); ``?E<var> <value>`` writes
one, answered ``!``. The spindle speed is macro #3027 by default; the offset goes to a
configurable macro variable, which the part program or a macro applies as a tool-length
offset (for example ``#2000 + T`` wear, via ``G10``).
"""

from __future__ import annotations

import re
from typing import Any
from urllib.parse import urlsplit

from .base import (
    Adapter,
    AdapterError,
    AdapterTimeoutError,
    BadValueError,
    UnreachableError,
    WriteRejectedError,
    typed_params,
)

try:
    import termios

    _PORT_ERRORS: tuple[type[BaseException], ...] = (OSError, termios.error)
except ImportError:  # not POSIX
    _PORT_ERRORS = (OSError,)

NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


class SerialLine:
    """Mixin for :class:`~cnc_adapters.base.Link` subclasses: one ASCII line per request
    and per reply on a serial port. Call :meth:`_init_serial` from ``__init__``."""

    name: str

    def _init_serial(self, port: str, baudrate: int, timeout_s: float, eol: str) -> None:
        self.port = port
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s)
        self.eol = eol
        self._ser = None

    def _connect(self) -> None:
        import serial

        try:
            self._ser = serial.Serial(self.port, self.baudrate, timeout=self.timeout_s,
                                      write_timeout=self.timeout_s)
        except (serial.SerialException, OSError) as err:
            raise UnreachableError(f"{self.name}: cannot open {self.port}: {err}") from err

    def _disconnect(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001 - the device may already be gone
                pass

    def exchange(self, request: str | None) -> str:
        """Send one line and return the reply line (without its end of line).

        With ``request=None`` the device talks on its own (a streaming amplifier): the
        input buffer is dropped and the first whole line after it is returned.
        """
        import serial

        self.open()  # type: ignore[attr-defined]
        ser = self._ser
        end = self.eol[-1].encode("ascii")
        what = repr(request) if request is not None else "the stream"
        try:
            ser.reset_input_buffer()
            if request is not None:
                ser.write((request + self.eol).encode("ascii"))
            else:
                ser.read_until(end)  # most likely the tail of a line: dropped
            raw = ser.read_until(end)
        except (serial.SerialException, *_PORT_ERRORS) as err:
            raise self._link_lost(f"{self.name}: {self.port} vanished: {err}") from err  # type: ignore[attr-defined]
        if not raw:
            raise AdapterTimeoutError(f"{self.name}: no reply to {what} within {self.timeout_s:g} s")
        if not raw.endswith(end):
            raise AdapterTimeoutError(f"{self.name}: partial reply {raw!r} to {what}")
        try:
            return raw.decode("ascii").strip()
        except UnicodeDecodeError as err:
            raise BadValueError(f"{self.name}: garbage reply {raw!r} to {what}") from err


class LineAdapter(SerialLine, Adapter):
    """A generic request/response ASCII protocol on a serial line."""

    name = "line"

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
        **scaling: Any,
    ):
        super().__init__(**scaling)
        self._init_serial(port, baudrate, timeout_s, eol)
        self.speed_request = speed_request
        self.offset_request = offset_request
        try:
            self.speed_reply = re.compile(speed_reply)
            self.offset_reply = re.compile(offset_reply)
            self.reject_reply = re.compile(reject_reply)
        except re.error as err:
            raise AdapterError(f"{self.name}: bad reply pattern: {err}") from err
        if "value" not in self.speed_reply.groupindex:
            raise AdapterError(f"{self.name}: speed_reply needs a (?P<value>...) group")

    @classmethod
    def from_url(cls, url: str, **overrides: Any) -> LineAdapter:
        """``serial:///dev/ttyUSB0?protocol=haas&baudrate=9600&offset_var=10500``."""
        parts = urlsplit(url)
        kw = {**typed_params(url), **overrides}
        return cls(parts.path, **kw)

    def _read_speed_raw(self) -> float:
        reply = self.exchange(self.speed_request)
        m = self.speed_reply.match(reply)
        if m is None:
            raise BadValueError(f"{self.name}: unexpected reply {reply!r} to {self.speed_request!r}")
        return float(m.group("value"))

    def _write_offset_raw(self, value: float) -> None:
        request = self.offset_request.format(value=value)
        reply = self.exchange(request)
        if self.reject_reply.match(reply):
            raise WriteRejectedError(f"{self.name}: controller refused {request!r}: {reply!r}")
        if not self.offset_reply.match(reply):
            raise BadValueError(f"{self.name}: unexpected reply {reply!r} to {request!r}")


class HaasAdapter(LineAdapter):
    """Haas Q/E commands: speed from macro #3027, offset to a configurable macro variable."""

    name = "haas"

    def __init__(self, port: str, *, speed_var: int = 3027, offset_var: int = 10500,
                 offset_decimals: int = 4, **kw: Any):
        self.speed_var = int(speed_var)
        self.offset_var = int(offset_var)
        kw.setdefault("speed_request", f"?Q600 {self.speed_var}")
        kw.setdefault("speed_reply", rf"^>?\s*MACRO,\s*{self.speed_var},\s*(?P<value>{NUMBER})$")
        kw.setdefault("offset_request", f"?E{self.offset_var} {{value:.{int(offset_decimals)}f}}")
        kw.setdefault("offset_reply", r"^>?\s*!$")
        kw.setdefault("reject_reply", r"^>?\s*(\?|INVALID|ERROR|NOT ALLOWED).*")
        kw.setdefault("eol", "\r\n")
        super().__init__(port, **kw)
