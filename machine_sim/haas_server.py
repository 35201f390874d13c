"""A loopback Haas MDC server (Machine Data Collection, Setting 143) in front of an emulated
control, for tests and the demo.

The wire, as public sources report it (``docs/controls/haas.md`` names them):

- ``?Q600 <var>`` reads a macro variable: ``MACRO, <value>`` (``style="ngc"``, reported from an
  NGC over TCP) or ``MACRO, <var>, <value>`` inside STX (0x02) ... ETB (0x17) after an echo of
  the request (``style="framed"``, reported over RS-232); each reply is followed by a ``>``
  prompt;
- ``?E<var> <value>`` writes one: ``!`` when taken, ``?`` when refused;
- ``?Q100``: ``SERIAL NUMBER, 1234567``; anything else: ``?``;
- two connections at most (a third is told "Too many connections" and closed), and every reply
  goes to all of them (``broadcast``).

What it serves: #``speed_var`` (3027) is the spindle's speed (:attr:`EmulatedControl.speed_rpm`);
#``offset_var`` is the macro variable thermocomp writes: a write goes through
:meth:`EmulatedControl.write_raw` (``?`` when the control refuses it) and a read returns
:attr:`EmulatedControl.held_raw`. Other variables are those :meth:`HaasMdcServer.set_macro` set
(a probe cycle's measurement); a ``?E`` outside ``writable`` is refused. A ``?E`` of ``life_vars``
(the sign of life's counter and flag, the ``haas`` profile's #10501 and #10502) goes to
:meth:`EmulatedControl.life_beat` too.

The Haas semantics the route depends on: the written macro value is not the applied wear. The
control applies a tool-length wear only when a G43 takes the offset again, so the macro template
re-applies it at safe points, and between them the axis keeps the wear of the last one. Here a
safe point is (1) every change of the programmed spindle speed (a new operation: the tool change
and its ``G43 H..``, where the template runs), and (2) every ``safe_point_every_s`` of plant time
when given (the template's re-application before each roughing or finishing pass). Only at a
safe point does :meth:`HaasMdcServer.sync` hand the held value to the axis
(:meth:`EmulatedControl.sync`); :attr:`HaasMdcServer.safe_points` records when and what.

Lock-step: ``clock.advance(...)``, ``machine.advance()``, ``server.sync()``, then the client's
cycle. The server runs in background threads on 127.0.0.1 and a free port; use it as a context
manager.
"""

from __future__ import annotations

import math
import re
import socket
import socketserver
import threading
from collections.abc import Iterable
from dataclasses import dataclass

from .controls import EmulatedControl

__all__ = ["HaasMdcServer", "SafePoint"]

_Q600 = re.compile(r"^\?Q600\s+(\d+)$")
_E = re.compile(r"^\?E(\d+)\s+(\S+)$")
_MAX_CONNECTIONS = 2
MODES = ("ok", "silent", "partial", "garbage", "ignore-first")
"""Fault injection: answer normally; not at all; half a line; bytes that are no ASCII; and
leave the first request on each new connection unanswered."""


@dataclass(frozen=True)
class SafePoint:
    """A safe point the emulated macro reached: plant time, why, and the raw wear it applied."""

    time_s: float
    reason: str
    raw: float


class _Handler(socketserver.BaseRequestHandler):
    server: _TcpServer

    def handle(self) -> None:
        owner = self.server.owner
        conn = self.request
        if not owner._admit(conn):
            conn.sendall(b"Too many connections. Disconnecting.\r\n")
            return
        answered = False
        buf = b""
        try:
            while True:
                try:
                    chunk = conn.recv(4096)
                except OSError:
                    return
                if not chunk:
                    return
                buf += chunk
                while b"\n" in buf or b"\r" in buf:
                    cut = min(i for i in (buf.find(b"\n"), buf.find(b"\r")) if i >= 0)
                    line, buf = buf[:cut], buf[cut + 1 :]
                    text = line.decode("ascii", "replace").strip()
                    if not text:
                        continue
                    if owner.mode == "ignore-first" and not answered:
                        answered = True
                        continue
                    answered = True
                    owner._reply(conn, text)
        finally:
            owner._leave(conn)


class _TcpServer(socketserver.ThreadingTCPServer):
    allow_reuse_address = True
    daemon_threads = True
    owner: HaasMdcServer


class HaasMdcServer:
    """A Haas MDC server on 127.0.0.1 bridged to ``control`` (see the module docstring).

    ``offset_var`` and ``speed_var`` as on the client; ``writable`` the (first, last) ranges of
    macro variables a ``?E`` may write (default: the NGC general-purpose #10000-#10999);
    ``style`` the reply form ("ngc" or "framed"); ``safe_point_every_s`` the plant seconds
    between the macro's re-applications within an operation (None: only at operation changes);
    ``wear_var``: a read-only macro variable that reports the wear the axis applies (the tool's
    #2201.., raw), for tests."""

    def __init__(
        self,
        control: EmulatedControl,
        *,
        offset_var: int = 10500,
        speed_var: int = 3027,
        writable: Iterable[tuple[int, int]] = ((10000, 10999),),
        style: str = "ngc",
        broadcast: bool = True,
        safe_point_every_s: float | None = None,
        wear_var: int = 2201,
        life_vars: tuple[int, int] | None = (10501, 10502),
        port: int = 0,
    ):
        if style not in ("ngc", "framed"):
            raise ValueError(f"style must be 'ngc' or 'framed', not {style!r}")
        if safe_point_every_s is not None and not (
            math.isfinite(safe_point_every_s) and safe_point_every_s > 0
        ):
            raise ValueError(f"safe_point_every_s must be a number > 0, not {safe_point_every_s!r}")
        self.control = control
        self.offset_var = int(offset_var)
        self.speed_var = int(speed_var)
        self.writable = tuple((int(a), int(b)) for a, b in writable)
        self.style = style
        self.broadcast = broadcast
        self.safe_point_every_s = safe_point_every_s
        self.wear_var = int(wear_var)
        self.life_vars = life_vars
        self.mode = "ok"
        self.crosstalk: str | None = None
        """A request of another MDC client, answered (to every connection) just before each
        reply: its output arrives while a client waits for its own."""
        self.macros: dict[int, float] = {}
        self.requests: list[str] = []
        self.safe_points: list[SafePoint] = []
        self.connections_refused = 0
        self._port = int(port)
        self._lock = threading.Lock()
        self._left = threading.Condition(self._lock)
        self._conns: list[socket.socket] = []
        self._server: _TcpServer | None = None
        self._thread: threading.Thread | None = None
        machine = control.machine
        self._synced_s = machine.plant.time_s
        self._rpm = machine.commanded_rpm(self._synced_s)
        self.applied_raw = self._raw_of(control.applied_um)

    # -- the server ------------------------------------------------------------------------

    @property
    def port(self) -> int:
        return self._port

    @property
    def url(self) -> str:
        return f"haas://127.0.0.1:{self._port}?offset_var={self.offset_var}"

    def start(self) -> HaasMdcServer:
        """Listen (again: on the same port once it has one)."""
        if self._server is not None:
            return self
        server = _TcpServer(("127.0.0.1", self._port), _Handler)
        server.owner = self
        self._port = int(server.server_address[1])
        self._server = server
        self._thread = threading.Thread(
            target=server.serve_forever,
            name="haas-mdc",
            kwargs={"poll_interval": 0.05},
            daemon=True,
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop listening and drop every connection: the control is gone."""
        server, self._server = self._server, None
        if server is not None:
            server.shutdown()
            server.server_close()
        if self._thread is not None:
            self._thread.join(5)
            self._thread = None
        self.drop_connections()

    def drop_connections(self) -> None:
        """Close every client connection, the server still listening."""
        with self._lock:
            conns, self._conns = self._conns, []
        for c in conns:
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            c.close()

    def __enter__(self) -> HaasMdcServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _admit(self, conn: socket.socket) -> bool:
        with self._lock:
            if len(self._conns) >= _MAX_CONNECTIONS:
                self.connections_refused += 1
                return False
            self._conns.append(conn)
            return True

    def _leave(self, conn: socket.socket) -> None:
        with self._lock:
            if conn in self._conns:
                self._conns.remove(conn)
            self._left.notify_all()

    def wait_connections(self, at_most: int, timeout_s: float = 5.0) -> bool:
        """Wait until at most ``at_most`` clients are connected (a client's close reaches the
        server on its own thread); False when that did not happen within ``timeout_s``."""
        with self._lock:
            return self._left.wait_for(lambda: len(self._conns) <= at_most, timeout_s)

    @property
    def connections(self) -> int:
        with self._lock:
            return len(self._conns)

    # -- the control -----------------------------------------------------------------------

    def set_macro(self, var: int, value: float) -> None:
        """What the control's own program writes into macro ``var`` (a probe cycle)."""
        with self._lock:
            self.macros[int(var)] = float(value)

    def _raw_of(self, offset_um: float) -> float:
        p = self.control.profile
        return offset_um * p.scale * p.sign + 0.0  # no -0.0 on the wire

    def sync(self) -> None:
        """After ``machine.advance()``: at a safe point since the last call, the macro re-applies
        the held value as the tool's wear (:meth:`EmulatedControl.sync`); otherwise the axis
        keeps the wear of the last safe point."""
        machine = self.control.machine
        now = machine.plant.time_s
        reasons = []
        rpm = machine.commanded_rpm(now)
        if rpm != self._rpm:
            reasons.append("operation")
        every = self.safe_point_every_s
        if every is not None and math.floor(now / every + 1e-9) > math.floor(
            self._synced_s / every + 1e-9
        ):
            reasons.append("interval")
        self._rpm, self._synced_s = rpm, now
        if not reasons:
            return
        self.control.sync()
        self.applied_raw = self._raw_of(self.control.applied_um)
        self.safe_points.append(SafePoint(now, "+".join(reasons), self.applied_raw))

    def apply_now(self, reason: str = "manual") -> None:
        """A safe point now (the operator runs the macro, a tool change outside the program)."""
        self.control.sync()
        self.applied_raw = self._raw_of(self.control.applied_um)
        self.safe_points.append(
            SafePoint(self.control.machine.plant.time_s, reason, self.applied_raw)
        )

    # -- the protocol ------------------------------------------------------------------------

    def _answer(self, text: str) -> str:
        """The payload that answers request ``text``."""
        self.requests.append(text)
        if text == "?Q100":
            return "SERIAL NUMBER, 1234567"
        m = _Q600.match(text)
        if m:
            var = int(m.group(1))
            if var == self.speed_var:
                value = self.control.speed_rpm
            elif var == self.offset_var:
                value = self.control.held_raw
            elif var == self.wear_var:
                value = self.applied_raw
            else:
                with self._lock:
                    if var not in self.macros:
                        return "?"
                    value = self.macros[var]
            number = f"{value:.6f}"
            if self.style == "framed":
                return f"MACRO, {var}, {number:>15}"
            return f"MACRO, {number}"
        m = _E.match(text)
        if m:
            var = int(m.group(1))
            try:
                value = float(m.group(2))
            except ValueError:
                return "?"
            if not any(a <= var <= b for a, b in self.writable):
                return "?"
            if var == self.offset_var:
                return "!" if self.control.write_raw(value) else "?"
            if var in (self.speed_var, self.wear_var):
                return "?"
            with self._lock:
                self.macros[var] = value
                life = (
                    tuple(self.macros.get(v) for v in self.life_vars)
                    if self.life_vars is not None and var in self.life_vars
                    else None
                )
            if life is not None:  # the program's macro watches the sign of life
                self.control.life_beat(*life)
            return "!"
        return "?"

    def _frame(self, request: str, payload: str, whole: bool = True) -> bytes:
        """The bytes of a reply; ``whole=False``: cut before its end (a half-sent reply)."""
        if self.style == "framed":
            head = f"{request}\r\r\n\x02{payload}"
            return (head + "\x17\r\n>" if whole else head).encode("ascii")
        return (f">{payload}\r\n>" if whole else f">{payload}").encode("ascii")

    def _reply(self, conn: socket.socket, text: str) -> None:
        payload = self._answer(text)
        mode = self.mode
        if mode == "silent":
            return
        other = self.crosstalk
        if other is not None and other != text:
            self._send(conn, self._frame(other, self._answer(other)))
        if mode == "garbage":
            data = b"\xff\xfe MACRO \xff\r\n"
        elif mode == "partial":
            data = self._frame(text, payload, whole=False)
        else:
            data = self._frame(text, payload)
        self._send(conn, data)

    def _send(self, conn: socket.socket, data: bytes) -> None:
        with self._lock:
            targets = list(self._conns) if self.broadcast else [conn]
        for c in targets:
            try:
                c.sendall(data)
            except OSError:
                pass
