"""Emulated PLCs on loopback for the ``plc`` backend, bridged to an
:class:`~machine_sim.controls.EmulatedControl`: each is the protocol's own server library,
not a fake of the wire format.

- :class:`S7Plc`: python-snap7's ``snap7.server.Server`` with the DBs the addresses name;
- :class:`ModbusTcpPlc`: pymodbus's ``ModbusTcpServer`` (holding and input registers, coils,
  discrete inputs);
- :class:`AdsPlc`: pyads's ``AdsTestServer`` with the symbols the addresses name (unknown
  symbols and writes of the wrong size are refused with the ADS error a TwinCAT gives).

Each also holds the sign of life's words (``life`` and ``valid``: by default where the
controller profiles put them, S7 ``DB100.DBW14``/``DBW16``, ADS ``GVL_Thermo.nLifeCounter``/
``bCompValid``; none on Modbus TCP unless given), read with :meth:`EmulatedPlc.get`.

Each plays the machine builder's PLC program: :meth:`EmulatedPlc.sync` (once per lock-step
cycle, after ``machine.advance()`` and before ``control.sync()``) hands a newly written offset
to ``control.write_raw``, then publishes the value the control holds at the held address, the
spindle's actual speed at the speed address and the cutting state at the cutting address.
The PLC passes a value on when it changes, as a program that compares with the last one does.

Each is a context manager that runs its server in a background thread on 127.0.0.1 and a free
port; :meth:`~EmulatedPlc.stop` drops it (listener and connections: a PLC switched off) and
:meth:`~EmulatedPlc.start` brings it back on the same port with the same memory.

The addresses are parsed here on their own, not with :mod:`cnc_adapters.plc`: the emulator is
the other side, and a shared parser would hide a shared mistake.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import math
import re
import socket
import struct
import threading
from typing import Any, Self

from .controls import EmulatedControl
from .vcnc import free_port

__all__ = ["AdsPlc", "EmulatedPlc", "ModbusTcpPlc", "S7Plc"]

HOST = "127.0.0.1"
_TYPES = {"INT16": "INT", "INT32": "DINT", "REAL32": "REAL", "FLOAT32": "REAL", "BIT": "BOOL"}
"""The other spellings of the data types, as the adapter takes them."""


class EmulatedPlc:
    """What every emulated PLC shares (see the module docstring). ``addresses`` maps a role
    (``offset``, ``speed``, ``held``, ``cutting``) to (address, data type)."""

    protocol = ""

    def __init__(self, control: EmulatedControl, addresses: dict[str, tuple[str, str]]):
        if "offset" not in addresses or "speed" not in addresses:
            raise ValueError("an emulated PLC needs at least the offset and the speed addresses")
        self.control = control
        self.addresses = {
            role: (a, _TYPES.get(t.upper(), t.upper())) for role, (a, t) in addresses.items()
        }
        self.host = HOST
        self.port = free_port(HOST)
        self.running = False
        self.passed_on = 0  # new offsets handed to the control
        self._last: Any = 0  # the memory starts at zero

    # the protocol's part
    def _start(self) -> None: ...
    def _stop(self) -> None: ...
    def get(self, role: str) -> Any: ...
    def put(self, role: str, value: Any) -> None: ...

    def start(self) -> Self:
        if not self.running:
            self._start()
            self.running = True
        return self

    def stop(self) -> None:
        """Drop the listener and every connection; the memory stays."""
        if self.running:
            self.running = False
            self._stop()

    close = stop

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def dtype(self) -> dict[str, str]:
        return {role: t for role, (_, t) in self.addresses.items()}

    def sync(self) -> None:
        """One scan of the builder's PLC program: a new offset to the control, then the held
        value, the speed and the cutting state back into the PLC's memory; the sign of life
        to the control's watch."""
        raw = self.get("offset")
        if raw != self._last:
            self.control.write_raw(float(raw))
            self.passed_on += 1
        if "held" in self.addresses:
            self.put("held", self.control.held_raw)
        self.put("speed", self.control.speed_rpm)
        if "cutting" in self.addresses:
            self.put("cutting", self.control.machine.cutting)
        if "life" in self.addresses and "valid" in self.addresses:  # the program's watch
            self.control.life_beat(self.get("life"), self.get("valid"))
        self._last = self.get("offset")  # after the write-back: the held address may be the same

    def _number(self, role: str, value: Any) -> Any:
        """``value`` as the role's data type holds it (a PLC's MOVE into an INT rounds)."""
        t = self.dtype[role]
        if t == "BOOL":
            return bool(value)
        if t in ("INT", "DINT"):
            lo, hi = (-(2**15), 2**15 - 1) if t == "INT" else (-(2**31), 2**31 - 1)
            v = float(value)
            return min(max(round(v), lo), hi) if math.isfinite(v) else 0
        return float(value)


def _life_roles(
    addresses: dict[str, tuple[str, str]],
    life_address: str | None,
    life_type: str,
    valid_address: str | None,
    valid_type: str,
) -> None:
    """The sign of life's words in the PLC's memory (the controller profiles' defaults, where
    they name one): thermocomp writes them, the builder's program watches them."""
    if life_address:
        addresses["life"] = (life_address, life_type)
    if valid_address:
        addresses["valid"] = (valid_address, valid_type)


# -- S7 -----------------------------------------------------------------------------------

_S7 = re.compile(r"DB(\d+)\.DB([XWD])(\d+)(?:\.([0-7]))?", re.IGNORECASE)


def _s7(address: str) -> tuple[int, str, int, int]:
    m = _S7.fullmatch(address.strip())
    if m is None:
        raise ValueError(f"not an S7 address: {address!r}")
    return int(m.group(1)), m.group(2).upper(), int(m.group(3)), int(m.group(4) or 0)


class S7Plc(EmulatedPlc):
    """An S7 PLC (python-snap7's server) with the DBs the addresses name, each large enough for
    them (``db_size`` bytes at least). Its ``rack`` and ``slot`` are whatever a client asks."""

    protocol = "s7"

    def __init__(
        self,
        control: EmulatedControl,
        *,
        offset_address: str = "DB100.DBD0",
        offset_type: str = "REAL",
        speed_address: str = "DB100.DBD4",
        speed_type: str = "REAL",
        held_address: str | None = "DB100.DBD8",
        held_type: str | None = None,
        cutting_address: str | None = "DB100.DBX12.0",
        cutting_type: str = "BOOL",
        life_address: str | None = "DB100.DBW14",
        life_type: str = "INT",
        valid_address: str | None = "DB100.DBW16",
        valid_type: str = "INT",
        db_size: int = 64,
    ):
        addresses = {"offset": (offset_address, offset_type), "speed": (speed_address, speed_type)}
        if held_address:
            addresses["held"] = (held_address, held_type or offset_type)
        if cutting_address:
            addresses["cutting"] = (cutting_address, cutting_type)
        _life_roles(addresses, life_address, life_type, valid_address, valid_type)
        super().__init__(control, addresses)
        self._where = {role: _s7(a) for role, (a, _) in self.addresses.items()}
        sizes: dict[int, int] = {}
        for db, width, start, _bit in self._where.values():
            end = start + {"X": 1, "W": 2, "D": 4}[width]
            sizes[db] = max(sizes.get(db, db_size), end)
        self.dbs = {db: bytearray(size) for db, size in sizes.items()}
        self.server: Any = None

    def _start(self) -> None:
        from snap7.type import SrvArea

        server = _tracking_s7_server()(log=False)
        for db, data in self.dbs.items():
            server.register_area(SrvArea.DB, db, data)  # the server writes into these
        server.start_to(self.host, tcp_port=self.port)
        self.server = server

    def _stop(self) -> None:
        server, self.server = self.server, None
        if server is not None:
            server.drop_clients()
            server.stop()

    @contextlib.contextmanager
    def _locked(self, db: int):
        """The DB's own lock, the one the server holds while a client writes into it."""
        from snap7.type import SrvArea

        server = self.server
        if server is not None:
            server.lock_area(SrvArea.DB, db)
        try:
            yield
        finally:
            if server is not None:
                server.unlock_area(SrvArea.DB, db)

    def get(self, role: str) -> Any:
        from snap7.util import get_bool, get_dint, get_int, get_real

        db, width, start, bit = self._where[role]
        t = self.dtype[role]
        with self._locked(db):
            data = self.dbs[db]
            if width == "X":
                return get_bool(data, start, bit)
            if width == "W":
                return get_int(data, start)
            return get_dint(data, start) if t == "DINT" else get_real(data, start)

    def put(self, role: str, value: Any) -> None:
        from snap7.util import set_bool, set_dint, set_int, set_real

        db, width, start, bit = self._where[role]
        t = self.dtype[role]
        v = self._number(role, value)
        with self._locked(db):
            data = self.dbs[db]
            if width == "X":
                set_bool(data, start, bit, bool(v))
            elif width == "W":
                set_int(data, start, int(v))
            elif t == "DINT":
                set_dint(data, start, int(v))
            else:
                set_real(data, start, float(v))


@functools.cache
def _tracking_s7_server() -> type:
    from snap7.server import Server

    class TrackingServer(Server):
        """snap7's server, keeping its client sockets so that a stop drops them at once (its own
        stop leaves a connected client served until that client goes quiet for 5 s)."""

        def __init__(self, **kw: Any) -> None:
            super().__init__(**kw)
            self._sockets: set[socket.socket] = set()
            self._sockets_lock = threading.Lock()

        def _handle_client(self, client_socket: socket.socket, address: Any) -> None:
            with self._sockets_lock:
                self._sockets.add(client_socket)
            try:
                super()._handle_client(client_socket, address)
            finally:
                with self._sockets_lock:
                    self._sockets.discard(client_socket)

        def drop_clients(self) -> None:
            with self._sockets_lock:
                sockets = list(self._sockets)
            for s in sockets:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    return TrackingServer


# -- Modbus TCP ---------------------------------------------------------------------------

_MB = re.compile(r"(?:(hr|ir|coil|di):)?(\d+)", re.IGNORECASE)
_MB_READ_FC = {"coil": 1, "di": 2, "hr": 3, "ir": 4}
_MB_WRITE_FC = {"coil": 5, "di": 2, "hr": 16, "ir": 4}
_MB_FMT = {"REAL": ">f", "DINT": ">i", "INT": ">h"}


class ModbusTcpPlc(EmulatedPlc):
    """A Modbus TCP PLC (pymodbus's server, unit ``device_id``): ``size`` holding registers,
    input registers, coils and discrete inputs from address 0. ``word_order`` as the adapter's
    (``big``: high word first)."""

    protocol = "modbus-tcp"

    def __init__(
        self,
        control: EmulatedControl,
        *,
        offset_address: str = "hr:0",
        offset_type: str = "REAL",
        speed_address: str = "ir:0",
        speed_type: str = "REAL",
        held_address: str | None = "ir:2",
        held_type: str | None = None,
        cutting_address: str | None = "di:0",
        cutting_type: str = "BOOL",
        life_address: str | None = None,
        life_type: str = "INT",
        valid_address: str | None = None,
        valid_type: str = "INT",
        device_id: int = 1,
        word_order: str = "big",
        size: int = 64,
    ):
        addresses = {"offset": (offset_address, offset_type), "speed": (speed_address, speed_type)}
        if held_address:
            addresses["held"] = (held_address, held_type or offset_type)
        if cutting_address:
            addresses["cutting"] = (cutting_address, cutting_type)
        _life_roles(addresses, life_address, life_type, valid_address, valid_type)
        super().__init__(control, addresses)
        self.device_id = device_id
        self.word_order = word_order
        self.size = size
        self._where = {}
        for role, (a, _) in self.addresses.items():
            m = _MB.fullmatch(a.strip())
            if m is None:
                raise ValueError(f"not a Modbus address: {a!r}")
            self._where[role] = ((m.group(1) or "hr").lower(), int(m.group(2)))
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self.server: Any = None
        self._device: Any = None

    def _make_device(self) -> Any:
        from pymodbus.simulator import DataType, SimData, SimDevice

        def block(bits: bool) -> list[Any]:
            if bits:
                return [SimData(0, count=self.size, values=False, datatype=DataType.BITS)]
            return [SimData(0, count=self.size, values=0, datatype=DataType.REGISTERS)]

        # (coils, discrete inputs, holding registers, input registers): four tables
        return SimDevice(
            self.device_id, simdata=(block(True), block(True), block(False), block(False))
        )

    def _run(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(10)  # type: ignore[arg-type]

    def _start(self) -> None:
        from pymodbus.server import ModbusTcpServer

        if self._loop is None:
            self._loop = asyncio.new_event_loop()
            self._thread = threading.Thread(
                target=self._loop.run_forever, daemon=True, name="modbus-tcp-plc"
            )
            self._thread.start()
        memory = self._snapshot()

        async def go() -> Any:
            server = ModbusTcpServer(self._make_device(), address=(self.host, self.port))
            await server.serve_forever(background=True)
            return server

        self.server = self._run(go())
        for (table, start), regs in memory.items():  # the memory outlives a power cycle
            self._run(self.server.async_setValues(self.device_id, _MB_WRITE_FC[table], start, regs))

    def _snapshot(self) -> dict[tuple[str, int], list[Any]]:
        if self.server is None:
            return getattr(self, "_memory", {})
        out = {}
        for table, start in set(self._where.values()):
            count = 1 if table in ("coil", "di") else 4
            out[table, start] = self._run(
                self.server.async_getValues(self.device_id, _MB_READ_FC[table], start, count)
            )
        return out

    def _stop(self) -> None:
        if self.server is not None:
            self._memory = self._snapshot()
            self._run(self.server.shutdown())
            self.server = None

    def close(self) -> None:
        self.stop()
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._loop.stop)
            if self._thread is not None:
                self._thread.join(5)
            self._loop.close()
            self._loop = None

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _width(self, role: str) -> int:
        return {"REAL": 2, "DINT": 2, "INT": 1, "BOOL": 1}[self.dtype[role]]

    def get(self, role: str) -> Any:
        table, start = self._where[role]
        values = list(
            self._run(
                self.server.async_getValues(
                    self.device_id, _MB_READ_FC[table], start, self._width(role)
                )
            )
        )
        if table in ("coil", "di"):
            return bool(values[0])
        if self.word_order == "little":
            values.reverse()
        raw = b"".join(int(v).to_bytes(2, "big") for v in values)
        return struct.unpack(_MB_FMT[self.dtype[role]], raw)[0]

    def put(self, role: str, value: Any) -> None:
        table, start = self._where[role]
        v = self._number(role, value)
        if table in ("coil", "di"):
            regs: list[Any] = [bool(v)]
        else:
            raw = struct.pack(_MB_FMT[self.dtype[role]], v)
            regs = [int.from_bytes(raw[i : i + 2], "big") for i in range(0, len(raw), 2)]
            if self.word_order == "little":
                regs.reverse()
        self._run(self.server.async_setValues(self.device_id, _MB_WRITE_FC[table], start, regs))


# -- ADS ----------------------------------------------------------------------------------

_ADS_INDEX = re.compile(r"(0x[0-9a-f]+|\d+):(0x[0-9a-f]+|\d+)", re.IGNORECASE)
_ADS_FMT = {"REAL": "<f", "LREAL": "<d", "DINT": "<i", "INT": "<h", "BOOL": "<?"}
ADSERR_DEVICE_INVALIDSIZE = 0x705
ADSERR_DEVICE_SYMBOLNOTFOUND = 0x710


@functools.cache
def _ads_handler_class() -> type:
    from pyads import constants
    from pyads.testserver import AdvancedHandler
    from pyads.testserver.handler import AmsResponseData

    class Refused(Exception):
        def __init__(self, code: int):
            super().__init__(code)
            self.code = code

    class StrictHandler(AdvancedHandler):
        """pyads's handler, answering an unknown symbol or a write of the wrong size with the
        ADS error a TwinCAT gives (its own raises in the connection thread, and the client
        waits for its timeout)."""

        def handle_request(self, request: Any) -> Any:
            command = struct.unpack("<H", request.ams_header.command_id)[0]
            if command == constants.ADSCOMMAND_WRITE:
                data = request.ams_header.data
                group, offset, length = struct.unpack("<III", data[:12])
                if group != constants.ADSIGRP_SYM_RELEASEHND:
                    try:
                        var = (
                            self.get_variable_by_handle(offset)
                            if group == constants.ADSIGRP_SYM_VALBYHND
                            else self.get_variable_by_indices(group, offset)
                        )
                    except KeyError:
                        return self._refuse(request, ADSERR_DEVICE_SYMBOLNOTFOUND)
                    if length != var.size:
                        return self._refuse(request, ADSERR_DEVICE_INVALIDSIZE)
            try:
                return super().handle_request(request)
            except KeyError:
                return self._refuse(request, ADSERR_DEVICE_SYMBOLNOTFOUND)

        @staticmethod
        def _refuse(request: Any, code: int) -> Any:
            state = struct.unpack("<H", request.ams_header.state_flags)[0] | 0x0001
            command = struct.unpack("<H", request.ams_header.command_id)[0]
            data = struct.pack("<I", code)
            if command in (constants.ADSCOMMAND_READ, constants.ADSCOMMAND_READWRITE):
                data += struct.pack("<I", 0)  # the read length: nothing follows
            return AmsResponseData(struct.pack("<H", state), request.ams_header.error_code, data)

    return StrictHandler


class AdsPlc(EmulatedPlc):
    """A TwinCAT PLC runtime as pyads's ``AdsTestServer`` (on a free port: the AdsLib takes
    ``host:port``) with one symbol per address (an ``<index group>:<index offset>`` address: an
    object at those indices, as a CNC object of the GEO task). The client addresses it by any
    AMS Net ID and AMS port."""

    protocol = "ads"

    def __init__(
        self,
        control: EmulatedControl,
        *,
        offset_address: str = "GVL_Thermo.nTempComp",
        offset_type: str = "DINT",
        speed_address: str = "GVL_Thermo.fSpeed",
        speed_type: str = "REAL",
        held_address: str | None = "GVL_Thermo.nTempCompHeld",
        held_type: str | None = None,
        cutting_address: str | None = "GVL_Thermo.bCutting",
        cutting_type: str = "BOOL",
        life_address: str | None = "GVL_Thermo.nLifeCounter",
        life_type: str = "INT",
        valid_address: str | None = "GVL_Thermo.bCompValid",
        valid_type: str = "BOOL",
    ):
        addresses = {"offset": (offset_address, offset_type), "speed": (speed_address, speed_type)}
        if held_address:
            addresses["held"] = (held_address, held_type or offset_type)
        if cutting_address:
            addresses["cutting"] = (cutting_address, cutting_type)
        _life_roles(addresses, life_address, life_type, valid_address, valid_type)
        super().__init__(control, addresses)
        from pyads import constants
        from pyads.testserver import PLCVariable

        ads_type = {
            "REAL": constants.ADST_REAL32,
            "LREAL": constants.ADST_REAL64,
            "DINT": constants.ADST_INT32,
            "INT": constants.ADST_INT16,
            "BOOL": constants.ADST_BIT,
        }
        self.handler = _ads_handler_class()()
        self.variables: dict[str, Any] = {}
        for role, (name, t) in self.addresses.items():
            index = _ADS_INDEX.fullmatch(name)
            where = (
                {}
                if index is None
                else {"index_group": int(index.group(1), 0), "index_offset": int(index.group(2), 0)}
            )
            var = PLCVariable(name, struct.pack(_ADS_FMT[t], 0), ads_type[t], t, **where)
            self.handler.add_variable(var)
            self.variables[role] = var
        self.server: Any = None

    def _start(self) -> None:
        from pyads.testserver import AdsTestServer

        server = AdsTestServer(
            handler=self.handler, ip_address=self.host, port=self.port, logging=False
        )
        # it listens only once its thread runs: listen now, so that a client connecting at
        # once is not refused (a second listen() in the thread changes nothing)
        server.server.listen(5)
        server.start()
        self.server = server

    def _stop(self) -> None:
        server, self.server = self.server, None
        if server is not None:
            # end its accept loop before its socket closes (a select() on a closed socket
            # raises in that thread), then drop the connections and the socket
            server._run = False
            server.join(5)
            server.stop()

    def get(self, role: str) -> Any:
        return struct.unpack(_ADS_FMT[self.dtype[role]], self.variables[role].value)[0]

    def put(self, role: str, value: Any) -> None:
        self.variables[role].value = struct.pack(
            _ADS_FMT[self.dtype[role]], self._number(role, value)
        )
