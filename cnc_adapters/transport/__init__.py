"""The transports the controller links share: one Modbus transport (pymodbus's synchronous
clients, TCP and RTU, a register codec and one error policy) and one raw TCP transport
(connect, send and receive against a deadline, peer-closed detection).

A transport maps every fault of its wire to one class of the exception tree, the same for
every backend that uses it:

- refused, unreachable, no such device, a connect that times out: :class:`UnreachableError`;
- a request that draws no (valid) reply in time: :class:`AdapterTimeoutError`;
- the peer closed the connection or the device vanished, mid-reply or between requests:
  :class:`UnreachableError`;
- a Modbus exception reply: :class:`AdapterError` for a read, :class:`WriteRejectedError`
  for a write.

Faults on an established connection drop it through the owning link's ``_link_lost`` (the
next call reconnects); faults while connecting just fail the connect (the link backs off).
"""

from .modbus import WIDTH, ModbusTransport, RegisterCodec
from .tcp import TcpTransport

__all__ = ["WIDTH", "ModbusTransport", "RegisterCodec", "TcpTransport"]
