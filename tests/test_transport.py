"""The transports' contract: the same fault gives the same error class through every backend
that uses a transport (one test body a fault, parametrised over the backends).

Real peers, no mocks: a loopback TCP port nothing listens on (RTU: a serial device that does
not exist), a peer that takes the request and never answers, one that closes mid-reply (RTU:
the line is unplugged mid-reply), and for Modbus an exception reply. The Modbus RTU peers sit
on one end of a pseudo-terminal pair (socat)."""

from __future__ import annotations

import contextlib
import os
import select
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from devices import PtyPair

from cnc_adapters.base import (
    Adapter,
    AdapterError,
    AdapterTimeoutError,
    Failure,
    UnreachableError,
    Wants,
    WriteRejectedError,
)
from cnc_adapters.chiller import ModbusChiller
from cnc_adapters.focas import OPEN_RESPONSE, SYNC, FocasAdapter, packet
from cnc_adapters.haas_mdc import HaasMdcAdapter
from cnc_adapters.modbus import ModbusRtuAdapter
from cnc_adapters.plc import PlcAdapter
from cnc_adapters.sensors import ModbusSensor

HOST = "127.0.0.1"
SHORT_S = 0.3  # the timeout of a link whose peer never answers: the test waits it out
LONG_S = 10.0  # the timeout where the peer's fault must come first


@dataclass(frozen=True)
class Backend:
    """A link that uses a transport: how to make it for a peer (``(host, port)`` for TCP, a
    device path for RTU), a request that reads, one that writes (None: it writes nothing),
    and what its peer says: a handshake reply, and the first bytes of a reply."""

    name: str
    wire: str  # "tcp" or "rtu"
    make: Callable[[Any, float], Any]
    read: Callable[[Any], Any]
    write: Callable[[Any], Any] | None = None
    modbus: bool = False
    handshake: bytes | None = None
    half_reply: Callable[[bytes], bytes] = lambda request: b""


def _modbus_tcp_half(request: bytes) -> bytes:
    # the MBAP header of a 4-register reply and its byte count; the registers never come
    return request[:2] + b"\x00\x00\x00\x0b" + request[6:8] + b"\x08"


def _modbus_tcp_exception(request: bytes) -> bytes:
    # code 2: illegal data address
    return request[:2] + b"\x00\x00\x00\x03" + request[6:7] + bytes([request[7] | 0x80, 2])


def _crc16(frame: bytes) -> bytes:
    crc = 0xFFFF
    for byte in frame:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return struct.pack("<H", crc)


BACKENDS = [
    Backend(
        "focas",
        "tcp",
        lambda at, t: FocasAdapter(at[0], port=at[1], timeout_s=t),
        read=lambda link: link.read_speed(),
        write=lambda link: link.write_offset_um(1.0),
        handshake=packet(OPEN_RESPONSE, b"", origin=0x0002),
        half_reply=lambda request: SYNC + b"\x00\x02",
    ),
    Backend(
        "haas-mdc",
        "tcp",
        lambda at, t: HaasMdcAdapter(at[0], at[1], timeout_s=t, connect_timeout_s=t),
        read=lambda link: link.read_speed(),
        write=lambda link: link.write_offset_um(1.0),
        half_reply=lambda request: b"MACRO, 80",
    ),
    Backend(
        "plc modbus-tcp",
        "tcp",
        lambda at, t: PlcAdapter(
            protocol="modbus-tcp",
            host=at[0],
            port=at[1],
            timeout_s=t,
            offset_address="hr:0",
            speed_address="ir:0",
        ),
        read=lambda link: link.read_speed(),
        write=lambda link: link.write_offset_um(1.0),
        modbus=True,
        half_reply=_modbus_tcp_half,
    ),
    Backend(
        "chiller modbus-tcp",
        "tcp",
        lambda at, t: ModbusChiller(host=at[0], port=at[1], timeout_s=t),
        read=lambda link: link.read_supply_c(),
        write=lambda link: link.write_setpoint_c(20.0),
        modbus=True,
        half_reply=_modbus_tcp_half,
    ),
    Backend(
        "modbus rtu",
        "rtu",
        lambda dev, t: ModbusRtuAdapter(dev, timeout_s=t),
        read=lambda link: link.read_speed(),
        write=lambda link: link.write_offset_um(1.0),
        modbus=True,
    ),
    Backend(
        "chiller modbus-rtu",
        "rtu",
        lambda dev, t: ModbusChiller(transport="rtu", port=dev, timeout_s=t),
        read=lambda link: link.read_supply_c(),
        write=lambda link: link.write_setpoint_c(20.0),
        modbus=True,
    ),
    Backend(
        "modbus sensor",
        "rtu",
        lambda dev, t: ModbusSensor(dev, timeout_s=t),
        read=lambda link: link.read_um(),
        modbus=True,
    ),
]


def wait_for(predicate: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


def free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


class TcpPeer:
    """A loopback server that answers the backend's handshake, then plays ``fault`` on every
    request: ``silent`` (reads, never answers), ``close`` (the first bytes of a reply, then
    closes), ``exception`` (a Modbus exception reply) or ``garbage`` (these bytes for a reply)."""

    def __init__(self, backend: Backend, fault: str, garbage: bytes = b""):
        self.backend, self.fault, self.garbage = backend, fault, garbage
        self.server = socket.create_server((HOST, 0))
        self.where = (HOST, self.server.getsockname()[1])
        self.accepted = 0
        self.conns: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            self.accepted += 1
            self.conns.append(conn)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        with contextlib.suppress(OSError):
            if self.backend.handshake is not None:
                conn.recv(4096)
                conn.sendall(self.backend.handshake)
            while request := conn.recv(4096):
                if self.fault == "close":
                    conn.sendall(self.backend.half_reply(request))
                    conn.close()
                    return
                if self.fault == "exception":
                    conn.sendall(_modbus_tcp_exception(request))
                if self.fault == "garbage":
                    conn.sendall(self.garbage)

    def close(self) -> None:
        self.server.close()
        for conn in self.conns:
            with contextlib.suppress(OSError):
                conn.close()


class RtuPeer:
    """A Modbus RTU device on the far end of a pty pair, playing ``fault`` on every request:
    ``silent``, ``close`` (the first bytes of a reply, then the line is unplugged),
    ``exception`` or ``garbage`` (these bytes for a reply)."""

    def __init__(self, tmp_path: Path, fault: str, garbage: bytes = b""):
        self.pty = PtyPair(tmp_path)
        self.fault, self.garbage = fault, garbage
        self.where = self.pty.ctl
        self._fd = os.open(self.pty.dev, os.O_RDWR | os.O_NOCTTY)
        self._halt = threading.Event()
        self.accepted = 1  # a serial line has no connections to count
        threading.Thread(target=self._serve, daemon=True).start()

    @staticmethod
    def _frame_length(buf: bytes) -> int | None:
        if len(buf) < 2:
            return None
        if buf[1] in (15, 16):  # address, function, start, quantity, byte count, data, CRC
            return None if len(buf) < 7 else 9 + buf[6]
        return 8

    def _serve(self) -> None:
        buf = b""
        while not self._halt.is_set():
            try:
                if not select.select([self._fd], [], [], 0.1)[0]:
                    continue
                buf += os.read(self._fd, 256)
            except OSError:
                return  # unplugged
            n = self._frame_length(buf)
            if n is None or len(buf) < n:
                continue
            request, buf = buf[:n], buf[n:]
            if self.fault == "close":
                os.write(self._fd, request[:2] + b"\x08")
                self.pty.unplug()
                return
            if self.fault == "exception":
                reply = bytes([request[0], request[1] | 0x80, 2])
                os.write(self._fd, reply + _crc16(reply))
            if self.fault == "garbage":
                os.write(self._fd, self.garbage)

    def close(self) -> None:
        self._halt.set()
        with contextlib.suppress(OSError):
            os.close(self._fd)
        self.pty.close()


@pytest.fixture(params=BACKENDS, ids=[b.name for b in BACKENDS])
def backend(request: pytest.FixtureRequest) -> Backend:
    return request.param


@pytest.fixture
def peer(backend: Backend, tmp_path: Path):
    """``peer(fault)``: a peer for ``backend`` playing ``fault``, closed after the test."""
    made: list[Any] = []

    def make(fault: str, garbage: bytes = b"") -> Any:
        p = (
            TcpPeer(backend, fault, garbage)
            if backend.wire == "tcp"
            else RtuPeer(tmp_path, fault, garbage)
        )
        made.append(p)
        return p

    yield make
    for p in made:
        p.close()


@contextlib.contextmanager
def link_to(backend: Backend, where: Any, timeout_s: float):
    link = backend.make(where, timeout_s)
    try:
        yield link
    finally:
        link.close()


def test_nothing_to_connect_to_is_unreachable(backend, tmp_path):
    where = (HOST, free_port()) if backend.wire == "tcp" else str(tmp_path / "no-such-device")
    with link_to(backend, where, LONG_S) as link:
        with pytest.raises(UnreachableError):
            backend.read(link)
        with pytest.raises(UnreachableError):  # in the back-off now
            backend.read(link)


def test_a_peer_that_never_answers_is_a_timeout(backend, peer):
    p = peer("silent")
    with link_to(backend, p.where, SHORT_S) as link:
        with pytest.raises(AdapterTimeoutError):
            backend.read(link)
        with pytest.raises(AdapterTimeoutError):
            backend.read(link)
        if backend.wire == "tcp":  # the connection was dropped: a late reply is never taken
            assert wait_for(lambda: p.accepted == 2)


def test_a_peer_that_closes_mid_reply_is_unreachable(backend, peer):
    p = peer("close")
    with link_to(backend, p.where, LONG_S) as link, pytest.raises(UnreachableError):
        backend.read(link)


def test_an_exception_reply_refuses_the_request_and_keeps_the_link(backend, peer):
    if not backend.modbus:
        pytest.skip("no exception replies in this protocol")
    p = peer("exception")
    with link_to(backend, p.where, LONG_S) as link:
        with pytest.raises(AdapterError) as err:
            backend.read(link)
        assert type(err.value) is AdapterError  # the device answered: no link fault
        if backend.write is not None:
            with pytest.raises(WriteRejectedError):
                backend.write(link)
        with pytest.raises(AdapterError) as again:
            backend.read(link)
        assert type(again.value) is AdapterError
        assert p.accepted == 1  # one connection throughout


# what a confused peer may send for a reply: bytes of no protocol, a FOCAS packet with a body
# that breaks its own length fields, a line of no ASCII, a Haas reply with no number in it,
# a Modbus TCP header that announces more than comes
GARBAGE = {
    "ff": b"\xff" * 40,
    "focas-lengths": SYNC + b"\x00\x02\x21\x02\x00\x08\x00\x01\xff\xff\x00\x00\x00\x00",
    "no-ascii": b"\x02\xfe\xfd\x17\r\n",
    "haas-word": b"\x02MACRO, 3027, abc\x17\r\n",
    "modbus-header": b"\x00\x01\x00\x00\xff\xff\x01\x04\xfe",
}
ADAPTERS = [b for b in BACKENDS if b.name in ("focas", "haas-mdc", "plc modbus-tcp", "modbus rtu")]


@pytest.mark.parametrize("garbage", list(GARBAGE.values()), ids=list(GARBAGE))
@pytest.mark.parametrize("backend", ADAPTERS, ids=[b.name for b in ADAPTERS], indirect=True)
def test_a_reply_of_garbage_is_a_failure_of_the_cycle_and_the_write(backend, peer, garbage):
    """Whatever bytes come back, a cycle's read and a write give Failures, never raise."""
    p = peer("garbage", garbage)
    with link_to(backend, p.where, SHORT_S) as link:
        assert isinstance(link, Adapter)
        for _ in range(2):  # the first on a new connection, the next after the fault
            r = link.read(Wants(cutting=True, held_offset=True, inputs=True, measurement=True))
            assert isinstance(r.speed_rpm, Failure), r.speed_rpm
            for value in (r.cutting, r.held_offset_um, r.inputs, r.measurement):
                assert value is None or isinstance(value, Failure), value
            assert link.write(1.0).failure is not None
