"""Real device peers for the adapter tests: pseudo-terminal pairs (socat), a Haas-protocol
responder, a generic line responder, pymodbus's own RTU server, and a node-opcua server."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest

JS = Path(__file__).parent / "js"


class PtyPair:
    """Two linked pseudo-terminals: ``ctl`` for the adapter, ``dev`` for the simulated device.

    :meth:`unplug` kills socat (both ends vanish, like a pulled USB adapter) and
    :meth:`plug` brings them back under the same names.
    """

    def __init__(self, directory: Path):
        if shutil.which("socat") is None:
            pytest.skip("socat is not installed (scripts/system-deps.sh installs it)")
        self.ctl = str(directory / "ctl")
        self.dev = str(directory / "dev")
        self.proc: subprocess.Popen | None = None
        self.plug()

    def plug(self) -> None:
        for p in (self.ctl, self.dev):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(p)
        self.proc = subprocess.Popen(
            ["socat", f"pty,raw,echo=0,link={self.ctl}", f"pty,raw,echo=0,link={self.dev}"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        end = time.monotonic() + 10
        while not (os.path.exists(self.ctl) and os.path.exists(self.dev)):
            if time.monotonic() > end:
                raise RuntimeError("socat did not create the pty pair")
            time.sleep(0.01)

    def unplug(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(10)
            self.proc = None
        end = time.monotonic() + 10
        while os.path.exists(self.ctl) and time.monotonic() < end:
            time.sleep(0.01)

    def close(self) -> None:
        self.unplug()


class LineDevice(threading.Thread):
    """Answers one request line with one reply line on the ``dev`` end of a pty pair.

    ``handler(line) -> str | None`` builds the reply. ``mode`` injects faults:
    ``ok``, ``silent`` (no reply), ``garbage`` (bytes that are no reply), ``partial``
    (a reply without its end of line), ``reject`` (the controller refuses writes).
    """

    def __init__(self, port: str, handler, eol: bytes = b"\r\n"):
        super().__init__(daemon=True)
        self.port = port
        self.handler = handler
        self.eol = eol
        self.mode = "ok"
        self.requests: list[str] = []
        self._halt = threading.Event()
        self.ready = threading.Event()
        self.start()
        if not self.ready.wait(10):
            raise RuntimeError(f"device could not open {port}")

    def run(self) -> None:
        import serial

        while not self._halt.is_set():
            try:
                with serial.Serial(self.port, 115200, timeout=0.05) as ser:
                    self.ready.set()
                    buf = b""
                    while not self._halt.is_set():
                        chunk = ser.read(ser.in_waiting or 1)  # return as soon as bytes arrive
                        if not chunk:
                            continue
                        buf += chunk
                        while b"\n" in buf:
                            line, buf = buf.split(b"\n", 1)
                            text = line.decode("ascii", "replace").strip()
                            self.requests.append(text)
                            reply = self._reply(text)
                            if reply is not None:
                                ser.write(reply)
            except (OSError, serial.SerialException):
                time.sleep(0.05)  # the pty is gone (unplugged): wait for it to come back

    def _reply(self, text: str) -> bytes | None:
        if self.mode == "silent":
            return None
        if self.mode == "garbage":
            return b"\xff\xfe#@!\r\n"
        reply = self.handler(text, self.mode)
        if reply is None:
            return None
        if self.mode == "partial":
            return reply.encode()[: max(1, len(reply) // 2)]
        return reply.encode() + self.eol

    def stop(self) -> None:
        self._halt.set()
        self.join(5)


class Registers:
    """What a simulated controller holds: speed, the last accepted offset and other macro
    variables (a probe cycle's measurement and counter)."""

    def __init__(self, speed_rpm: float = 0.0):
        self.speed_rpm = speed_rpm
        self.offset: float | None = None
        self.macros: dict[int, float] = {}


def haas_handler(regs: Registers, speed_var: int = 3027, offset_var: int = 10500):
    def handle(text: str, mode: str) -> str | None:
        m = re.match(r"^\?Q600 (\d+)$", text)
        if m:
            var = int(m.group(1))
            value = (
                regs.speed_rpm
                if var == speed_var
                else (regs.offset or 0.0)
                if var == offset_var
                else regs.macros.get(var, 0.0)
            )
            return f">MACRO, {var}, {value:.6f}"
        m = re.match(r"^\?E(\d+) (\S+)$", text)
        if m:
            if mode == "reject" or int(m.group(1)) != offset_var:
                return "?, INVALID"
            regs.offset = float(m.group(2))
            return ">!"
        return "?, UNKNOWN COMMAND"

    return handle


def line_handler(regs: Registers):
    def handle(text: str, mode: str) -> str | None:
        if text == "?SPEED":
            return f"SPEED={regs.speed_rpm:.1f}"
        m = re.match(r"^OFFSET (\S+)$", text)
        if m:
            if mode == "reject":
                return "ERR locked"
            regs.offset = float(m.group(1))
            return "OK"
        return "ERR unknown"

    return handle


class ModbusDevice:
    """pymodbus's own RTU server on the ``dev`` end: speed as float32 in input registers
    0-1, offset as float32 in holding registers 0-1."""

    def __init__(self, port: str):
        from pymodbus.datastore import (
            ModbusDeviceContext,
            ModbusSequentialDataBlock,
            ModbusServerContext,
        )

        self.port = port
        # Modbus data blocks count from 1: wire address 0 is block address 1
        self.ir = ModbusSequentialDataBlock(1, [0] * 16)
        self.hr = ModbusSequentialDataBlock(1, [0] * 16)
        self.context = ModbusServerContext(
            devices={1: ModbusDeviceContext(ir=self.ir, hr=self.hr)}, single=False
        )
        self.loop = asyncio.new_event_loop()
        self.server = None
        self.retained: list[tuple[int, int, list[int]]] = []  # set_registers: (fc, address, regs)
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.start()

    def start(self) -> None:
        from pymodbus.server import ModbusSerialServer

        async def go():
            self.server = ModbusSerialServer(self.context, port=self.port, baudrate=115200)
            for fc, address, regs in self.retained:
                await self.server.context.async_setValues(1, fc, address, regs)
            asyncio.ensure_future(self.server.serve_forever())
            await asyncio.sleep(0.2)

        asyncio.run_coroutine_threadsafe(go(), self.loop).result(10)

    def stop_server(self) -> None:
        if self.server is not None:
            asyncio.run_coroutine_threadsafe(self.server.shutdown(), self.loop).result(10)
            self.server = None

    def _run(self, coro):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(10)

    def set_speed(self, rpm: float) -> None:
        from pymodbus.client import ModbusSerialClient as C

        regs = C.convert_to_registers(float(rpm), C.DATATYPE.FLOAT32)
        self._run(self.server.context.async_setValues(1, 4, 0, regs))  # input registers 0-1

    def set_input(self, address: int, regs: list[int]) -> None:
        self._run(self.server.context.async_setValues(1, 4, address, [r & 0xFFFF for r in regs]))

    def set_registers(self, table: str, address: int, regs: list[int]) -> None:
        """What the PLC's program writes, also while the server is down (the server keeps its
        registers in a store of its own, made at each start: they are written again then)."""
        self.retained.append((4 if table == "input" else 3, address, [r & 0xFFFF for r in regs]))
        if self.server is not None:
            self._run(self.server.context.async_setValues(1, *self.retained[-1]))

    def offset(self) -> float:
        from pymodbus.client import ModbusSerialClient as C

        regs = self._run(self.server.context.async_getValues(1, 3, 0, 2))  # holding registers 0-1
        return float(C.convert_from_registers(list(regs), C.DATATYPE.FLOAT32))

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.stop_server()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)


class NodeOpcuaServer:
    """node-opcua's server (npm), started as a subprocess on a free loopback port."""

    def __init__(self, port: int):
        if shutil.which("node") is None:
            pytest.skip("Node.js is not installed (scripts/system-deps.sh installs it)")
        assert (JS / "node_modules" / "node-opcua-server").is_dir(), "run scripts/system-deps.sh"
        self.port = port
        self.url = f"opc.tcp://127.0.0.1:{port}/thermocomp/node"
        self.proc = subprocess.Popen(
            ["node", str(JS / "server.mjs"), str(port)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        self.lines: list[str] = []
        self._ready = threading.Event()
        threading.Thread(target=self._pump, daemon=True).start()
        if not self._ready.wait(60):
            self.close()
            raise RuntimeError("node-opcua server did not start")

    def _pump(self) -> None:
        for line in self.proc.stdout:  # type: ignore[union-attr]
            if line.startswith("@@ "):
                self.lines.append(line[3:].strip())
                if line.startswith("@@ ready"):
                    self._ready.set()

    def set_speed(self, rpm: float) -> None:
        self.proc.stdin.write(f"speed {rpm}\n")  # type: ignore[union-attr]
        self.proc.stdin.flush()  # type: ignore[union-attr]

    def reset(self) -> None:
        """Speed and offset back to 0 and no write reported yet (a server shared by tests)."""
        self._resets = getattr(self, "_resets", 0) + 1
        token = f"reset {self._resets}"
        self.proc.stdin.write(f"{token}\n")  # type: ignore[union-attr]
        self.proc.stdin.flush()  # type: ignore[union-attr]
        end = time.monotonic() + 30
        while token not in self.lines:  # the server's lines arrive in order: all before it are in
            if time.monotonic() > end or self.proc.poll() is not None:
                raise RuntimeError("node-opcua server did not answer a reset")
            time.sleep(0.01)
        self.lines.clear()

    def offset(self) -> float | None:
        vals = [float(x.split()[1]) for x in self.lines if x.startswith("offset ")]
        return vals[-1] if vals else None

    def close(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(Exception):
                self.proc.stdin.write("quit\n")  # type: ignore[union-attr]
                self.proc.stdin.flush()  # type: ignore[union-attr]
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
