"""The Modbus transport of every Modbus link (the ``modbus`` adapter and sensor, the ``plc``
adapter's Modbus TCP, the ``modbus`` chiller): pymodbus's synchronous client for TCP or RTU,
the register codec, and one error policy.

The policy (see :mod:`cnc_adapters.transport`): a connect that fails is
:class:`UnreachableError`; no valid reply within ``timeout_s`` (pymodbus's
``ModbusIOException``; on RTU a bad CRC too, which the framer drops) is
:class:`AdapterTimeoutError`; a connection the peer closed or a serial device that vanished
(``ConnectionException``, ``OSError``) is :class:`UnreachableError`; any other pymodbus error
(a reply that breaks the frame) is :class:`AdapterError`. On TCP each of these drops the
connection (a late reply must not be taken for the next request's); on RTU only a vanished
device does, as a serial line has no session and the framer resynchronises on silence. An
exception reply is the ``refused`` class of the request: :class:`AdapterError` for a read,
:class:`WriteRejectedError` for a write; the link stays up.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from ..base import (
    AdapterError,
    AdapterTimeoutError,
    BadValueError,
    UnreachableError,
    WriteRejectedError,
)

__all__ = ["RANGE", "WIDTH", "ModbusTransport", "RegisterCodec"]

WIDTH = {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2}
"""Registers each data type spans."""
RANGE = {
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
}
FLOAT32_MAX = 3.4028234663852886e38
_STRUCT = {"int16": ">h", "uint16": ">H", "int32": ">i", "uint32": ">I", "float32": ">f"}

Lost = Callable[[str, type[AdapterError]], AdapterError]
"""The owning link's ``_link_lost``: drops the link, returns the error to raise."""


def _swap(regs: list[int]) -> list[int]:
    return [((r & 0xFF) << 8) | (r >> 8) for r in regs]


@dataclass(frozen=True)
class RegisterCodec:
    """Numbers to and from 16-bit registers: ``word_order`` ``big`` puts the high word first,
    ``byte_order`` ``big`` (the Modbus standard) the high byte first inside each register."""

    word_order: str = "big"
    byte_order: str = "big"

    def decode(self, regs: Sequence[int], dtype: str) -> int | float:
        """The value of ``regs`` (exactly ``WIDTH[dtype]`` registers) as ``dtype``: an int for
        an integer type, a float for ``float32``."""
        regs = [int(r) & 0xFFFF for r in regs]
        if self.byte_order == "little":
            regs = _swap(regs)
        if self.word_order == "little":
            regs.reverse()
        raw = b"".join(r.to_bytes(2, "big") for r in regs)
        return struct.unpack(_STRUCT[dtype], raw)[0]

    def encode(self, value: float, dtype: str, label: str = "modbus") -> list[int]:
        """``value`` as the registers of ``dtype``: an integer type takes it rounded;
        :class:`BadValueError` (``label`` names the link) when it does not fit, before anything
        is sent."""
        if dtype in RANGE:
            lo, hi = RANGE[dtype]
            whole = round(value)
            if not lo <= whole <= hi:
                raise BadValueError(f"{label}: {value} does not fit {dtype}")
            raw = struct.pack(_STRUCT[dtype], int(whole))
        else:
            if math.isfinite(value) and abs(value) > FLOAT32_MAX:
                raise BadValueError(f"{label}: {value} does not fit {dtype}")
            raw = struct.pack(_STRUCT[dtype], value)
        regs = [int.from_bytes(raw[i : i + 2], "big") for i in range(0, len(raw), 2)]
        if self.word_order == "little":
            regs.reverse()
        return _swap(regs) if self.byte_order == "little" else regs


class ModbusTransport:
    """One pymodbus client, Modbus TCP (``host``, ``port`` a number) or RTU (``port`` a serial
    device; ``baudrate``, ``parity``, ``stopbits``), for the link whose ``_link_lost`` is
    ``lost``. ``label`` starts every message. Not connected until :meth:`connect`."""

    def __init__(
        self,
        label: str,
        *,
        lost: Lost,
        port: int | str,
        host: str | None = None,
        device_id: int = 1,
        timeout_s: float = 0.5,
        codec: RegisterCodec | None = None,
        baudrate: int = 19200,
        parity: str = "N",
        stopbits: int = 1,
    ):
        self.label = label
        self.tcp = host is not None
        self.host = host
        self.port = port
        self.device_id = int(device_id)
        self.timeout_s = float(timeout_s)
        self.codec = codec or RegisterCodec()
        self.baudrate = int(baudrate)
        self.parity = parity
        self.stopbits = int(stopbits)
        # every message names the device: the endpoint and its address on the bus
        self.where = f"{host}:{port}" if self.tcp else str(port)
        self.where += f" (device {self.device_id})"
        self._lost = lost
        self.client: Any = None

    # -- the connection -----------------------------------------------------------------

    def connect(self) -> None:
        from pymodbus.client import ModbusSerialClient, ModbusTcpClient

        # retries=0: a retry would answer a late reply with the next request's
        client: ModbusTcpClient | ModbusSerialClient
        if self.tcp:
            client = ModbusTcpClient(
                str(self.host), port=int(self.port), timeout=self.timeout_s, retries=0
            )
        else:
            client = ModbusSerialClient(
                str(self.port),
                baudrate=self.baudrate,
                parity=self.parity,
                stopbits=self.stopbits,
                timeout=self.timeout_s,
                retries=0,
            )
        cause: Exception | None = None
        try:
            up = client.connect()
        except OSError as err:  # pyserial's errors are OSErrors too
            up, cause = False, err
        if not up:
            _quietly(client.close)
            raise UnreachableError(
                f"{self.label} connect at {self.where}: cannot reach it"
                + (f": {cause}" if cause else "")
            ) from cause
        self.client = client

    def close(self) -> None:
        """Idempotent; the device may already be gone."""
        client, self.client = self.client, None
        if client is not None:
            _quietly(client.close)

    # -- requests -----------------------------------------------------------------------

    def request(
        self,
        what: str,
        method: str,
        *args: Any,
        refused: type[AdapterError] = AdapterError,
        **kw: Any,
    ) -> Any:
        """The reply of the client's ``method`` (``read_holding_registers``, ...) to this
        device, its faults mapped as the module docstring says; an exception reply raises
        ``refused``."""
        from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

        head = f"{self.label} {what} at {self.where}"  # the operation, the register, the device
        if self.client is None:
            raise UnreachableError(f"{head}: not connected")
        try:
            rr = getattr(self.client, method)(*args, device_id=self.device_id, **kw)
        except ModbusIOException as err:
            raise self._fault(
                f"{head}: no valid reply within {self.timeout_s:g} s", AdapterTimeoutError
            ) from err
        except (ConnectionException, OSError) as err:
            raise self._lost(f"{head}: link lost: {err}", UnreachableError) from err
        except ModbusException as err:
            raise self._fault(f"{head}: bad reply: {err}", AdapterError) from err
        if rr.isError():
            raise refused(f"{head}: exception reply: {rr}")
        return rr

    def _fault(self, message: str, error: type[AdapterError]) -> AdapterError:
        # a TCP stream out of step is not trusted again; a serial line has no session to drop
        return self._lost(message, error) if self.tcp else error(message)

    def read_registers(self, what: str, table: str, address: int, count: int) -> list[int]:
        """``count`` registers from ``address`` of ``table`` (``input`` or ``holding``)."""
        method = "read_input_registers" if table == "input" else "read_holding_registers"
        what = f"{what} {table} register {address}" + (f" (+{count - 1})" if count > 1 else "")
        rr = self.request(what, method, address, count=count)
        regs = list(rr.registers)
        if len(regs) < count:
            raise BadValueError(
                f"{self.label} {what} at {self.where}: {len(regs)} registers, not {count}"
            )
        return regs[:count]

    def read_bit(self, what: str, table: str, address: int) -> bool:
        """One bit: a ``coil`` or a discrete input (``di``)."""
        method = "read_coils" if table == "coil" else "read_discrete_inputs"
        rr = self.request(f"{what} {table} {address}", method, address, count=1)
        if not rr.bits:
            raise BadValueError(f"{self.label} {what} {table} {address} at {self.where}: no bit")
        return bool(rr.bits[0])

    def read_value(self, what: str, table: str, address: int, dtype: str) -> int | float:
        """The ``dtype`` value at ``address`` of ``table``, decoded by :attr:`codec`."""
        return self.codec.decode(self.read_registers(what, table, address, WIDTH[dtype]), dtype)

    def write_registers(self, what: str, address: int, regs: list[int]) -> None:
        """Holding registers from ``address``; an exception reply is :class:`WriteRejectedError`."""
        what = f"{what} holding register {address}" + (
            f" (+{len(regs) - 1})" if len(regs) > 1 else ""
        )
        self.request(what, "write_registers", address, regs, refused=WriteRejectedError)

    def write_value(self, what: str, address: int, value: float, dtype: str) -> None:
        """``value`` as ``dtype`` into the holding registers at ``address``
        (:class:`BadValueError`, nothing sent, when it does not fit)."""
        regs = self.codec.encode(
            value, dtype, f"{self.label} {what} holding register {address} at {self.where}"
        )
        self.write_registers(what, address, regs)


def _quietly(fn: Callable[[], Any]) -> None:
    try:
        fn()
    except Exception:  # noqa: BLE001 - closing what may already be dead
        pass
