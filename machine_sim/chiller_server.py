"""A Modbus chiller controller on loopback, for the ``modbus`` chiller backend: pymodbus's own
server (Modbus TCP on 127.0.0.1 and a free port, or RTU on a serial device such as one end of
a pseudo-terminal pair), backed by a plant's chiller
(:class:`~machine_sim.plant.SpindlePlant`: ``set_chiller_setpoint_c``,
``chiller_setpoint_c``, ``supply_c``, ``coolant_c``).

Register map (wire addresses from 0, device ``device_id``; int16 is signed, in 0.1 degC;
float32 in degC, two registers, ``word_order`` ``big``: the high word first)::

    holding  0       int16    set point: a write commands the chiller, which clamps it to its
                              own range; the register then holds what it took (read: the
                              set point it holds now)
    holding  10-11   float32  the same set point, in degC
    input    0       int16    supply (outlet) temperature
    input    1       int16    coolant (jacket) temperature
    input    10-11   float32  supply temperature, in degC
    input    12-13   float32  coolant temperature, in degC

Any other register is an illegal address; there are no coils or discrete inputs to speak of
(16 of each, always off). A value the plant cannot take (a float32 NaN) is answered with
ILLEGAL_VALUE; with :attr:`ChillerServer.refuse_writes` set every write is answered with
DEVICE_FAILURE, as a chiller in local (panel) mode does. A value that is not a finite number
reads as int16 -32768 (the usual "no value") or a float32 NaN.

The plant is touched only under ``lock`` (the plant may be stepped by another thread), from
the server's own event-loop thread. :meth:`ChillerServer.stop` drops the listener and every
connection (a chiller switched off); :meth:`ChillerServer.start` brings it back on the same
port.
"""

from __future__ import annotations

import asyncio
import math
import struct
import threading
from typing import TYPE_CHECKING, Any, Self, cast

if TYPE_CHECKING:
    from pymodbus.constants import ExcCodes

__all__ = ["HOLDING", "INPUT", "SCALE_C", "ChillerServer"]

HOST = "127.0.0.1"
SCALE_C = 0.1
"""degC per count of the int16 registers."""
_PER_C = 1 / SCALE_C  # 10.0 exactly: 213 / 10.0 is 21.3, 213 * 0.1 is not
HOLDING = {"setpoint": 0, "setpoint_f32": 10}
INPUT = {"supply": 0, "coolant": 1, "supply_f32": 10, "coolant_f32": 12}
_READ_HOLDING = (3, 6, 16, 23)  # read, and the writes' own read of what was written
_WRITES = (6, 16, 23)


def _int16(value_c: float) -> int:
    if not math.isfinite(value_c):
        return 0x8000
    count = min(max(round(value_c * _PER_C), -(2**15)), 2**15 - 1)
    return count & 0xFFFF


def _signed(reg: int) -> int:
    return reg - 0x10000 if reg & 0x8000 else reg


class ChillerServer:
    """A chiller controller over Modbus (see the module docstring for the register map).

    TCP on 127.0.0.1 and a free port (:attr:`port`) by default; ``serial_port`` serves RTU on
    that device instead. ``lock`` guards the plant (a new lock by default). :attr:`writes`
    counts the write requests that reached the set point, refused ones included."""

    def __init__(
        self,
        plant: Any,
        *,
        lock: Any = None,
        device_id: int = 1,
        word_order: str = "big",
        refuse_writes: bool = False,
        serial_port: str | None = None,
        baudrate: int = 19200,
    ):
        if word_order not in ("big", "little"):
            raise ValueError("word_order is 'big' or 'little'")
        self.plant = plant
        self.lock = lock if lock is not None else threading.Lock()
        self.device_id = device_id
        self.word_order = word_order
        self.refuse_writes = refuse_writes
        self.serial_port = serial_port
        self.baudrate = baudrate
        self.host = HOST
        self.port = 0  # the free port the first start finds, kept for a restart
        self.writes = 0
        self.server: Any = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None

    # -- running -------------------------------------------------------------------------

    def _run(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(10)  # type: ignore[arg-type]

    def start(self) -> Self:
        if self.server is not None:
            return self
        if self._loop is None:
            self._loop = asyncio.new_event_loop()
            self._thread = threading.Thread(
                target=self._loop.run_forever, daemon=True, name="modbus-chiller"
            )
            self._thread.start()

        async def go() -> Any:
            from pymodbus.server import ModbusSerialServer, ModbusTcpServer

            server: ModbusSerialServer | ModbusTcpServer
            if self.serial_port is not None:
                server = ModbusSerialServer(
                    self._device(), port=self.serial_port, baudrate=self.baudrate
                )
            else:
                # port 0 the first time: the system picks a free one, with no race for it
                server = ModbusTcpServer(self._device(), address=(self.host, self.port))
            await server.serve_forever(background=True)  # returns once it listens
            return server

        self.server = self._run(go())
        if self.serial_port is None:
            self.port = int(self.server.transport.sockets[0].getsockname()[1])
        return self

    def stop(self) -> None:
        """Drop the listener and every connection; the plant keeps its set point."""
        server, self.server = self.server, None
        if server is not None:
            self._run(server.shutdown())

    def close(self) -> None:
        self.stop()
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._loop.stop)
            if self._thread is not None:
                self._thread.join(5)
            self._loop.close()
            self._loop = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the device ----------------------------------------------------------------------

    def _device(self) -> Any:
        from pymodbus.simulator import DataType, SimData, SimDevice

        def regs(address: int, count: int) -> SimData:
            return SimData(address, count=count, values=0, datatype=DataType.REGISTERS)

        bits = [SimData(0, count=16, values=False, datatype=DataType.BITS)]
        # (coils, discrete inputs, holding registers, input registers); the gaps between the
        # blocks are illegal addresses
        return SimDevice(
            self.device_id,
            action=self._action,
            simdata=(bits, list(bits), [regs(0, 1), regs(10, 2)], [regs(0, 2), regs(10, 4)]),
        )

    def _f32(self, value_c: float) -> list[int]:
        raw = struct.pack(">f", value_c)
        regs = [int.from_bytes(raw[:2], "big"), int.from_bytes(raw[2:], "big")]
        return regs[::-1] if self.word_order == "little" else regs

    def _from_f32(self, regs: list[int]) -> float:
        hi, lo = regs[::-1] if self.word_order == "little" else regs
        return struct.unpack(">f", hi.to_bytes(2, "big") + lo.to_bytes(2, "big"))[0]

    async def _action(
        self,
        fc: int,
        start: int,
        address: int,
        count: int,
        registers: list[int],
        values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """pymodbus's hook on every access (in its loop thread): a read shows the plant as it
        is now; a write goes to the plant, and the register keeps what it took."""
        from pymodbus.constants import ExcCodes

        def put(table: dict[str, int], name: str, regs: list[int]) -> None:
            registers[table[name] - start : table[name] - start + len(regs)] = regs

        if values is None:
            with self.lock:
                if fc == 4:
                    supply, coolant = float(self.plant.supply_c), float(self.plant.coolant_c)
                elif fc in _READ_HOLDING:
                    setpoint = float(self.plant.chiller_setpoint_c)
            if fc == 4:
                put(INPUT, "supply", [_int16(supply)])
                put(INPUT, "coolant", [_int16(coolant)])
                put(INPUT, "supply_f32", self._f32(supply))
                put(INPUT, "coolant_f32", self._f32(coolant))
            elif fc in _READ_HOLDING:
                put(HOLDING, "setpoint", [_int16(setpoint)])
                put(HOLDING, "setpoint_f32", self._f32(setpoint))
            return None
        if fc not in _WRITES:
            return None
        values = cast(list[int], values)  # the writes are of registers, never of bits
        self.writes += 1
        if self.refuse_writes:
            return ExcCodes.DEVICE_FAILURE
        end = address + len(values)
        f32 = HOLDING["setpoint_f32"]
        if address <= HOLDING["setpoint"] < end:
            wanted = _signed(values[HOLDING["setpoint"] - address]) / _PER_C
        elif address <= f32 and f32 + 1 < end:
            wanted = self._from_f32(list(values[f32 - address : f32 - address + 2]))
        else:  # half a float32
            return ExcCodes.ILLEGAL_ADDRESS
        try:
            with self.lock:
                taken = float(self.plant.set_chiller_setpoint_c(wanted))
        except ValueError:
            return ExcCodes.ILLEGAL_VALUE
        # what the chiller took, in every register of the write: pymodbus stores these
        for name, regs in (("setpoint", [_int16(taken)]), ("setpoint_f32", self._f32(taken))):
            for i, reg in enumerate(regs):
                if address <= HOLDING[name] + i < end:
                    values[HOLDING[name] + i - address] = reg
        return None
