"""The raw TCP transport of the socket links (FANUC FOCAS, Haas MDC): connect with a timeout,
send, receive against a deadline, and one mapping of the socket's faults.

- a refused, unreachable or unresolvable peer, and a connect that times out (nothing answered
  the SYN: a control switched off or unplugged): :class:`UnreachableError`;
- a connected peer that sends nothing (or not all of a reply) before the deadline:
  :class:`AdapterTimeoutError`;
- the peer closed the connection (before or mid-reply), or the socket failed:
  :class:`UnreachableError`.

On an established connection each of these drops it through the owning link's
``_link_lost`` (a late reply must never be taken for the next request's; the next call
reconnects). During :meth:`TcpTransport.connect`, its handshake included, they only close
the socket: the link's own back-off follows.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable

from ..base import AdapterError, AdapterTimeoutError, UnreachableError

__all__ = ["TcpTransport"]

Lost = Callable[[str, type[AdapterError]], AdapterError]
"""The owning link's ``_link_lost``: drops the link, returns the error to raise."""

_TAIL = 256  # bytes of the latest input kept, for what a peer said before it closed


class TcpTransport:
    """One TCP connection to ``host``:``port`` for the link whose ``_link_lost`` is ``lost``.

    ``timeout_s`` bounds each reply (:meth:`deadline`), ``connect_timeout_s`` (default
    ``timeout_s``) the connect. ``closed_reason(last)`` may say why the peer closed, from the
    last bytes it sent (a "too many connections" line), as the message of the error raised.
    Bytes received and not yet taken stay in :attr:`pending`."""

    def __init__(
        self,
        label: str,
        host: str,
        port: int,
        *,
        timeout_s: float,
        lost: Lost,
        connect_timeout_s: float | None = None,
        keepalive: bool = False,
        closed_reason: Callable[[bytes], str | None] | None = None,
    ):
        self.label = label
        self.host = host
        self.port = int(port)
        self.timeout_s = float(timeout_s)
        self.connect_timeout_s = float(
            timeout_s if connect_timeout_s is None else connect_timeout_s
        )
        self.keepalive = keepalive
        self._lost = lost
        self._closed_reason = closed_reason
        self.sock: socket.socket | None = None
        self.pending = b""
        self._tail = b""
        self._live = False  # connected and handed over: faults now drop the owner's link

    @property
    def address(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"

    # -- the connection -----------------------------------------------------------------

    def connect(self, handshake: Callable[[], None] | None = None) -> None:
        """Connect, then run ``handshake`` (a session's open request, through :meth:`send`
        and the reads); any error closes the socket again."""
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        except TimeoutError as err:
            raise UnreachableError(
                f"{self.label} connect at {self.address}: no answer "
                f"within {self.connect_timeout_s:g} s"
            ) from err
        except OSError as err:
            raise UnreachableError(
                f"{self.label} connect at {self.address}: cannot connect: {err}"
            ) from err
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self.keepalive:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        except OSError:
            pass
        self.sock, self.pending, self._tail = sock, b"", b""
        if handshake is not None:
            try:
                handshake()
            except BaseException:
                self.abort()
                raise
        self._live = True

    def close(self, goodbye: Callable[[], None] | None = None) -> None:
        """Close the connection, after ``goodbye`` (a session's close request; its faults are
        ignored: the peer may be gone). Idempotent."""
        self._live = False  # a fault now only ends the goodbye
        if self.sock is not None and goodbye is not None:
            try:
                goodbye()
            except Exception:  # noqa: BLE001 - closing goes on
                pass
        self.abort()

    def abort(self) -> None:
        """Drop the connection at once, without waiting for a hung peer."""
        self._live = False
        sock, self.sock = self.sock, None
        self.pending = b""
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()

    def _fail(self, message: str, error: type[AdapterError]) -> AdapterError:
        if self._live:
            return self._lost(message, error)
        self.abort()
        return error(message)

    def _socket(self, what: str) -> socket.socket:
        if self.sock is None:
            raise UnreachableError(f"{self.label} {what} at {self.address}: not connected")
        return self.sock

    # -- sending and receiving ------------------------------------------------------------

    def deadline(self, timeout_s: float | None = None) -> float:
        """The monotonic time by which a reply is due (``timeout_s`` from now, by default the
        transport's)."""
        return time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)

    def send(self, what: str, data: bytes) -> None:
        sock = self._socket(what)
        try:
            sock.settimeout(self.timeout_s)
            sock.sendall(data)
        except TimeoutError as err:  # the peer takes nothing in: hung, as one that never answers
            raise self._fail(
                f"{self.label} {what} at {self.address}: took no data within {self.timeout_s:g} s",
                AdapterTimeoutError,
            ) from err
        except OSError as err:
            raise self._fail(
                f"{self.label} {what} at {self.address}: link lost: {err}", UnreachableError
            ) from err

    def drain(self, what: str) -> None:
        """Drop what arrived unasked (a late reply, a prompt, another client's output): a stale
        reply must never answer the next request."""
        sock = self._socket(what)
        self.pending = b""
        sock.settimeout(0.0)
        while True:
            try:
                chunk = sock.recv(4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as err:
                raise self._fail(
                    f"{self.label} {what} at {self.address}: link lost: {err}", UnreachableError
                ) from err
            if not chunk:
                raise self._closed(what)
            self._tail = (self._tail + chunk)[-_TAIL:]

    def recv_exact(self, what: str, n: int, deadline: float) -> bytes:
        """Exactly ``n`` bytes, by ``deadline``."""
        while len(self.pending) < n:
            self._receive(what, deadline)
        out, self.pending = self.pending[:n], self.pending[n:]
        return out

    def recv_until(
        self, what: str, ends: tuple[bytes, ...], deadline: float, *, drop_on_timeout: bool = True
    ) -> bytes:
        """The input up to and including the first of ``ends``, by ``deadline``.
        ``drop_on_timeout`` False keeps the connection on a timeout (for a caller that asks
        once more on it); the error is :class:`AdapterTimeoutError` all the same."""
        while True:
            cuts = [i + len(e) for e in ends if (i := self.pending.find(e)) >= 0]
            if cuts:
                cut = min(cuts)
                out, self.pending = self.pending[:cut], self.pending[cut:]
                return out
            self._receive(what, deadline, drop_on_timeout=drop_on_timeout)

    def _receive(self, what: str, deadline: float, *, drop_on_timeout: bool = True) -> None:
        sock = self._socket(what)
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                got = f"partial reply {self.pending[:80]!r}" if self.pending else "no reply"
                message = (
                    f"{self.label} {what} at {self.address}: {got} within {self.timeout_s:g} s"
                )
                if drop_on_timeout:
                    raise self._fail(message, AdapterTimeoutError)
                raise AdapterTimeoutError(message)
            try:
                sock.settimeout(left)
                chunk = sock.recv(4096)
            except TimeoutError:
                continue  # the deadline decides
            except OSError as err:
                raise self._fail(
                    f"{self.label} {what} at {self.address}: link lost: {err}", UnreachableError
                ) from err
            if not chunk:
                raise self._closed(what)
            self.pending += chunk
            self._tail = (self._tail + chunk)[-_TAIL:]
            return

    def _closed(self, what: str) -> AdapterError:
        reason = self._closed_reason(self._tail) if self._closed_reason is not None else None
        return self._fail(
            reason or f"{self.label} {what} at {self.address}: the peer closed the connection",
            UnreachableError,
        )
