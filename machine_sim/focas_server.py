"""A loopback FOCAS/Ethernet server: the PC side of a FANUC control, for tests and the demo.

Built from the publicly documented packet format (the README and code of PyPI ``pyfocas``,
after ``diohpix/pyfanuc``), independently of :mod:`cnc_adapters.focas`, so that a test of that
client against this server checks two readings of the format against each other (and ``pyfocas``
itself can talk to it). It answers what thermocomp's FOCAS link uses:

- the open (0x0101) and close (0x0201) requests;
- generic requests (0x2101), any number of subpackets, each answered in order:
  read macro (function 0x15: first, last; 8-byte scaled integers, vacant ``FF FF``),
  write macro as doubles (0xA8: number, 0, 0, 0, byte count; then the doubles) and
  ``cnc_acts`` (0x25: the actual spindle speed); any other function answers return code 1
  (EW_FUNC), as a control does for a function it lacks.

Behind it stands a control (:class:`~machine_sim.controls.EmulatedControl`, or anything
with ``write_raw``, ``held_raw`` and ``speed_rpm``). A write to ``offset_macro`` goes to
``control.write_raw``. Where the control refuses it, ``refuse_in`` decides what the PC sees:

- ``"focas"``: the write answers return code 5 (EW_DATA) and the variable keeps its value
  (reads of ``offset_macro`` return ``control.held_raw``);
- ``"ladder"``: what a real control does: the macro variable takes any number (FOCAS answers
  0) and the builder's ladder, standing in here for the THD handshake, refuses it; the
  variable then holds the refused value while ``ack_macro`` (the value the control took, what
  the ladder reports after THREND) keeps ``control.held_raw``.

``ack_macro`` reads ``control.held_raw``; ``speed_macro`` reads ``control.speed_rpm`` (a ladder
copying the actual speed); the other common variables (#100-#199, #500-#999) start vacant and
hold what is written (the sign of life's counter and flag among them); any other number answers
return code 3 (EW_NUMBER), and a write to one of ``protected`` return code 7 (EW_PROT). A write
to ``life_macros`` (the sign of life's counter and flag, the ``fanuc`` profile's #502 and #503)
goes to ``control.life_beat`` too, where the control has one.

Faults for tests: :meth:`stop` (the control is gone: connections reset, nothing listens) and
:meth:`start` again on the same port; ``fault = "hang"`` (requests are read and never answered)
or ``"drop"`` (the connection is closed on the next request).

It runs in background threads on 127.0.0.1 and a free port (``port=0``); a context manager.
The open reply's 360-byte body is undocumented; it is sent zero-filled after its count.
"""

from __future__ import annotations

import math
import socket
import socketserver
import struct
import threading
from collections import Counter
from typing import Any, Protocol

SYNC = b"\xa0\xa0\xa0\xa0"
SERVER = 0x0002  # the origin of a reply (captures show 0x0002 and 0x0004)
OPEN, OPEN_REPLY, CLOSE, CLOSE_REPLY, GENERIC, GENERIC_REPLY = (
    0x0101,
    0x0102,
    0x0201,
    0x0202,
    0x2101,
    0x2102,
)
READ_MACRO, WRITE_MACRO_DOUBLE, ACTS = 0x15, 0xA8, 0x25
EW_OK, EW_FUNC, EW_LENGTH, EW_NUMBER, EW_DATA, EW_PROT = 0, 1, 2, 3, 5, 7
COMMON = (range(100, 200), range(500, 1000))

__all__ = ["FocasServer", "PlainControl", "encode_scaled"]


class Control(Protocol):
    held_raw: float

    def write_raw(self, raw: object) -> bool: ...

    @property
    def speed_rpm(self) -> float: ...


class PlainControl:
    """A control that takes any finite value at once, with a settable speed (for link tests
    that need no profile)."""

    def __init__(self, speed_rpm: float = 0.0):
        self.held_raw = 0.0
        self.speed_rpm = speed_rpm
        self.refused = 0

    def write_raw(self, raw: object) -> bool:
        if isinstance(raw, (int, float)) and not isinstance(raw, bool) and math.isfinite(raw):
            self.held_raw = float(raw)
            return True
        self.refused += 1
        return False


def encode_scaled(value: float | None) -> bytes:
    """``value`` as an 8-byte scaled integer: int32 mantissa, base 10, the largest decimal
    exponent up to 8 whose mantissa fits (1.0 goes as 100000000 e8, as in the captures);
    None as a vacant variable (exponent FF FF)."""
    if value is None:
        return struct.pack(">iHh", 0, 10, -1)
    if not math.isfinite(value):
        raise ValueError(f"{value!r} has no scaled-integer form")
    for exponent in range(8, -1, -1):
        mantissa = round(value * 10**exponent)
        if -(2**31) <= mantissa < 2**31:
            return struct.pack(">iHh", mantissa, 10, exponent)
    raise OverflowError(f"{value!r} does not fit a scaled integer")


def _packet(ptype: int, body: bytes) -> bytes:
    return SYNC + struct.pack(">HHH", SERVER, ptype, len(body)) + body


def _reply(cmd: bytes, code: int, payload: bytes = b"") -> bytes:
    """One reply subpacket (without its length): the command echoed, the return code, four
    zero bytes, the payload's length and the payload."""
    return cmd + struct.pack(">h4xH", code, len(payload)) + payload


class FocasServer:
    """A FOCAS/Ethernet server in front of ``control`` (see the module docstring).

    ``received`` lists every value written to ``offset_macro``, in the control's unit, taken or
    not; ``calls`` counts the subpackets by function, ``requests`` the generic requests;
    ``sessions`` and ``closes`` count the open and close requests."""

    def __init__(
        self,
        control: Control,
        *,
        offset_macro: int = 500,
        ack_macro: int | None = None,
        speed_macro: int | None = None,
        refuse_in: str = "focas",
        acts: bool = True,
        protected: tuple[int, ...] = (),
        life_macros: tuple[int, int] | None = (502, 503),
        host: str = "127.0.0.1",
        port: int = 0,
    ):
        if refuse_in not in ("focas", "ladder"):
            raise ValueError(f"refuse_in is 'focas' or 'ladder', not {refuse_in!r}")
        self.control = control
        self.offset_macro = offset_macro
        self.ack_macro = ack_macro
        self.speed_macro = speed_macro
        self.refuse_in = refuse_in
        self.acts = acts
        self.protected = frozenset(protected)
        self.life_macros = life_macros
        self._life_written = 0
        self.host = host
        self.port = port
        self.fault = ""
        self.variables: dict[int, float | None] = {}
        self.received: list[float] = []
        self.calls: Counter[int] = Counter()
        self.sessions = 0
        self.closes = 0
        self.requests = 0  # generic requests, whatever their number of subpackets
        self.lock = threading.RLock()  # one request at a time touches the control
        self._server: socketserver.ThreadingTCPServer | None = None
        self._thread: threading.Thread | None = None
        self._conns: set[socket.socket] = set()
        self._released = threading.Event()

    @property
    def url(self) -> str:
        return f"focas://{self.host}:{self.port}?offset_macro={self.offset_macro}"

    # -- life cycle -------------------------------------------------------------------

    def start(self) -> FocasServer:
        """Listen (again: on the port of the last start) and serve in a background thread."""
        owner = self

        class Handler(socketserver.BaseRequestHandler):
            def handle(self) -> None:
                owner._serve(self.request)

        class Server(socketserver.ThreadingTCPServer):
            allow_reuse_address = True
            daemon_threads = True

        self._released.clear()
        self._server = Server((self.host, self.port), Handler)
        self.port = self._server.server_address[1]
        self._thread = threading.Thread(
            target=self._server.serve_forever,
            name="focas-server",
            kwargs={"poll_interval": 0.05},
            daemon=True,
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        """The control goes away: nothing listens, open sessions are reset."""
        server, self._server = self._server, None
        self._released.set()
        if server is not None:
            server.shutdown()
            server.server_close()
        if self._thread is not None:
            self._thread.join(5)
            self._thread = None
        with self.lock:
            conns, self._conns = self._conns, set()
        for conn in conns:
            try:  # a reset, not an orderly close: the client sees the session die
                conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                conn.close()
            except OSError:
                pass

    def __enter__(self) -> FocasServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- one connection -------------------------------------------------------------------

    def _serve(self, conn: socket.socket) -> None:
        with self.lock:
            self._conns.add(conn)
        try:
            while True:
                got = self._read_packet(conn)
                if got is None:
                    return
                ptype, body = got
                if self.fault == "drop":
                    return
                if self.fault == "hang":
                    self._released.wait()
                    return
                if ptype == OPEN:
                    self.sessions += 1
                    conn.sendall(_packet(OPEN_REPLY, struct.pack(">H", 8) + bytes(358)))
                elif ptype == CLOSE:
                    self.closes += 1
                    conn.sendall(_packet(CLOSE_REPLY, b""))
                    return
                elif ptype == GENERIC:
                    self.requests += 1
                    conn.sendall(_packet(GENERIC_REPLY, self._generic(body)))
                else:
                    return  # an unknown packet: the control drops the session
        except OSError:
            return
        finally:
            with self.lock:
                self._conns.discard(conn)
            try:
                conn.close()
            except OSError:
                pass

    @staticmethod
    def _read_packet(conn: socket.socket) -> tuple[int, bytes] | None:
        head = _recv(conn, 10)
        if head is None or head[:4] != SYNC:
            return None
        _origin, ptype, length = struct.unpack(">HHH", head[4:])
        body = _recv(conn, length) if length else b""
        return None if body is None else (ptype, body)

    def _generic(self, body: bytes) -> bytes:
        count = struct.unpack(">H", body[:2])[0]
        replies, n = [], 2
        life_before = self._life_written
        for _ in range(count):
            size = struct.unpack(">H", body[n : n + 2])[0]
            replies.append(self._command(body[n + 2 : n + size]))
            n += size
        if self._life_written != life_before:  # one beat a request: the macro's watch
            beat = getattr(self.control, "life_beat", None)
            if beat is not None and self.life_macros is not None:
                with self.lock:
                    beat(*(self.variables.get(v) for v in self.life_macros))
        return struct.pack(">H", len(replies)) + b"".join(
            struct.pack(">H", len(r) + 2) + r for r in replies
        )

    def _command(self, sub: bytes) -> bytes:
        cmd = sub[:6]
        if len(sub) < 26:
            return _reply(cmd.ljust(6, b"\0"), EW_LENGTH)
        device, _one, function = struct.unpack(">HHH", cmd)
        args = struct.unpack(">5i", sub[6:26])
        extra = sub[26:]
        with self.lock:
            self.calls[function] += 1
            if device != 1:
                return _reply(cmd, EW_FUNC)
            if function == READ_MACRO:
                return self._read(cmd, args[0], args[1])
            if function == WRITE_MACRO_DOUBLE:
                return self._write(cmd, args[0], args[4], extra)
            if function == ACTS and self.acts:
                return _reply(cmd, EW_OK, encode_scaled(float(round(self.control.speed_rpm))))
            return _reply(cmd, EW_FUNC)

    # -- macro variables ------------------------------------------------------------------

    def _value(self, number: int) -> float | None:
        if number == self.ack_macro:
            return self.control.held_raw
        if number == self.speed_macro:
            return float(self.control.speed_rpm)
        if number == self.offset_macro and self.refuse_in == "focas":
            return self.control.held_raw
        if number == self.offset_macro and number not in self.variables:
            return self.control.held_raw
        return self.variables.get(number)

    def _read(self, cmd: bytes, first: int, last: int) -> bytes:
        numbers = range(first, last + 1)
        if (
            not numbers
            or len(numbers) > 100
            or not all(any(n in r for r in COMMON) for n in numbers)
        ):
            return _reply(cmd, EW_NUMBER)
        return _reply(cmd, EW_OK, b"".join(encode_scaled(self._value(n)) for n in numbers))

    def _write(self, cmd: bytes, number: int, size: int, extra: bytes) -> bytes:
        if size <= 0 or size % 8 or len(extra) != size:
            return _reply(cmd, EW_LENGTH)
        values = struct.unpack(f">{size // 8}d", extra)
        numbers = range(number, number + len(values))
        if not all(any(n in r for r in COMMON) for n in numbers):
            return _reply(cmd, EW_NUMBER)
        if not all(math.isfinite(v) for v in values):
            return _reply(cmd, EW_DATA)
        if any(n in self.protected for n in numbers):
            return _reply(cmd, EW_PROT)
        for n, v in zip(numbers, values):
            if n == self.offset_macro:
                self.received.append(v)
                taken = self.control.write_raw(v)
                if self.refuse_in == "focas":
                    if not taken:
                        return _reply(cmd, EW_DATA)
                    continue
            self.variables[n] = v
        if self.life_macros is not None and any(n in self.life_macros for n in numbers):
            self._life_written += 1
        return _reply(cmd, EW_OK)


def _recv(conn: socket.socket, n: int) -> bytes | None:
    buf = bytearray()
    while len(buf) < n:
        chunk = conn.recv(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


def serve(control: Any = None, **kw: Any) -> FocasServer:
    """A started server in front of ``control`` (default: a :class:`PlainControl`)."""
    return FocasServer(control if control is not None else PlainControl(), **kw).start()
