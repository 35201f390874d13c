"""The local control channel: ``thermocomp measure`` hands a measurement to the running service.

A Unix-domain stream socket, ``<state_dir>/control.sock``, mode 0600: only the service's own
user (and root) can talk to it. One JSON object per line each way::

    -> {"elongation_um": 12.3, "sigma_um": 0.5, "spindle": "s1"}     (sigma_um, spindle optional)
    <- {"ok": true, "spindle": "s1", "outcome": "accepted", "innovation_um": 0.4, ...}
    <- {"ok": false, "error": "..."}

The service polls the socket without blocking once per tick (:meth:`ControlChannel.poll`);
a request is answered once the spindle's next cycle has fused the measurement. A connection
that has not sent its line within ``request_timeout_s`` of the service's (injected) clock is
answered with an error and closed. The socket is bound and chmod-ed before it listens, so no
client can connect while it is still open to others.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import socket
import stat
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from compensator.errors import ConfigError, ControlError, clip
from compensator.observer import SIGMA_LIMIT_UM

SOCKET_NAME = "control.sock"
MAX_LINE_BYTES = 4096
MAX_CLIENTS = 16
_SUN_PATH_BYTES = 100  # sockaddr_un holds 108 bytes; longer paths go through /proc/self/fd
REQUEST_KEYS = frozenset({"elongation_um", "sigma_um", "spindle"})


def socket_path(state_dir: str | os.PathLike[str]) -> Path:
    return Path(state_dir) / SOCKET_NAME


@contextlib.contextmanager
def _addressable(path: Path) -> Iterator[str]:
    """``path`` as a socket address: itself, or, when too long for ``sockaddr_un``, the same
    file reached through an open descriptor of its directory."""
    if len(os.fsencode(path)) <= _SUN_PATH_BYTES:
        yield str(path)
        return
    fd = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
    try:
        yield f"/proc/self/fd/{fd}/{path.name}"
    finally:
        os.close(fd)


@dataclass(frozen=True)
class MeasureRequest:
    """One measurement sent to the service: the elongation [um], its sigma [um] (None: the
    spindle's configured one) and the spindle (None: the only one with an observer)."""

    elongation_um: float
    sigma_um: float | None
    spindle: str | None


def parse_request(line: bytes) -> MeasureRequest:
    """One request line; :class:`ConfigError` with a short reason when it is not one."""
    try:
        data = json.loads(line.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as err:
        raise ConfigError("the request is not a JSON object on one line") from err
    if not isinstance(data, dict):
        raise ConfigError("the request is not a JSON object")
    unknown = sorted(set(data) - REQUEST_KEYS)
    if unknown:
        raise ConfigError(
            f"unknown key {clip(unknown[0], 60)!r}; allowed: {', '.join(sorted(REQUEST_KEYS))}"
        )
    value = data.get("elongation_um")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"elongation_um must be a finite number, not {clip(repr(value), 60)}")
    sigma = data.get("sigma_um")
    if sigma is not None and (
        isinstance(sigma, bool)
        or not isinstance(sigma, (int, float))
        or not math.isfinite(sigma)
        or not 0 < sigma <= SIGMA_LIMIT_UM
    ):
        raise ConfigError(
            f"sigma_um must be a number > 0 and at most {SIGMA_LIMIT_UM:g} um, "
            f"not {clip(repr(sigma), 60)}"
        )
    spindle = data.get("spindle")
    if spindle is not None and not isinstance(spindle, str):
        raise ConfigError("spindle must be a name")
    return MeasureRequest(float(value), None if sigma is None else float(sigma), spindle)


class Pending:
    """A connection whose request is read or being read; answered once."""

    def __init__(self, conn: socket.socket, accepted_s: float):
        self.conn = conn
        self.accepted_s = accepted_s
        self.buffer = b""
        self.request: MeasureRequest | None = None
        self.answered = False

    def reply(self, answer: dict[str, Any]) -> None:
        """Send the answer line and close; a client that went away is no error of ours."""
        if self.answered:
            return
        self.answered = True
        try:
            self.conn.send((json.dumps(answer, allow_nan=False, default=str) + "\n").encode())
        except (OSError, ValueError):
            pass
        finally:
            self.conn.close()

    def fail(self, message: str) -> None:
        self.reply({"ok": False, "error": clip(message, 300)})


class ControlChannel:
    """The service's end of the control socket in ``state_dir``."""

    def __init__(
        self,
        state_dir: str | os.PathLike[str],
        clock: Callable[[], float],
        *,
        request_timeout_s: float = 10.0,
    ):
        self.path = socket_path(state_dir)
        self.clock = clock
        self.request_timeout_s = request_timeout_s
        self._sock: socket.socket | None = None
        self._reading: list[Pending] = []

    def open(self) -> ControlChannel:
        """Bind and listen; ``OSError`` when it cannot (the caller logs and goes on without)."""
        with contextlib.suppress(FileNotFoundError):
            # the state directory's lock is ours: a socket left there is a dead instance's
            if not stat.S_ISSOCK(os.lstat(self.path).st_mode):
                raise FileExistsError(f"{self.path} exists and is not a socket; not removing it")
            os.unlink(self.path)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            with _addressable(self.path) as address:
                sock.bind(address)
            os.chmod(self.path, 0o600)  # before listen(): nobody else can connect in between
            sock.listen(MAX_CLIENTS)
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        self._sock = sock
        return self

    def poll(self) -> list[Pending]:
        """Accept and read what is there, without blocking: the complete, well-formed requests
        (malformed ones and those too slow to arrive are answered here)."""
        if self._sock is None:
            return []
        now = self.clock()
        for _ in range(4 * MAX_CLIENTS):  # bounded: a flood cannot hold the cycle here
            try:
                conn, _ = self._sock.accept()
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break
            conn.setblocking(False)
            if len(self._reading) >= MAX_CLIENTS:
                # full: the connection that has sent nothing for longest makes room, so that idle
                # clients cannot keep a measurement waiting for the request timeout
                idle = [p for p in self._reading if not p.buffer]
                if not idle:
                    Pending(conn, now).fail("too many requests at once; try again")
                    continue
                oldest = min(idle, key=lambda p: p.accepted_s)
                self._reading.remove(oldest)
                oldest.fail("closed to make room: no request was sent")
            self._reading.append(Pending(conn, now))
        done: list[Pending] = []
        for p in list(self._reading):
            line = self._read_line(p)
            if line is None:
                if p.answered:
                    self._reading.remove(p)
                elif now - p.accepted_s > self.request_timeout_s:
                    self._reading.remove(p)
                    p.fail(f"no complete request line within {self.request_timeout_s:g} s")
                continue
            self._reading.remove(p)
            try:
                p.request = parse_request(line)
            except ConfigError as err:
                p.fail(str(err))
                continue
            done.append(p)
        return done

    @staticmethod
    def _read_line(p: Pending) -> bytes | None:
        """The request line once it is complete (a newline, or the client's end of writing)."""
        while True:
            try:
                chunk = p.conn.recv(MAX_LINE_BYTES)
            except (BlockingIOError, InterruptedError):
                return None
            except OSError:
                p.answered = True  # nobody left to answer
                p.conn.close()
                return None
            if not chunk:  # the client shut its side: what came is the request
                if p.buffer:
                    return p.buffer
                p.fail("empty request")
                return None
            p.buffer += chunk
            line = p.buffer.split(b"\n", 1)[0]
            if len(line) > MAX_LINE_BYTES:
                p.fail(f"request longer than {MAX_LINE_BYTES} bytes")
                return None
            if len(line) < len(p.buffer):
                return line

    def close(self) -> None:
        for p in self._reading:
            p.fail("the service is stopping")
        self._reading = []
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()
            with contextlib.suppress(OSError):
                os.unlink(self.path)


def send_measurement(
    state_dir: str | os.PathLike[str],
    elongation_um: float,
    sigma_um: float | None,
    spindle: str | None,
    timeout_s: float = 60.0,
) -> dict[str, Any]:
    """Send one measurement to the service running on ``state_dir`` and wait for its answer
    (the spindle's next cycle). :class:`ControlError` when no service answers."""
    path = socket_path(state_dir)
    request: dict[str, Any] = {"elongation_um": elongation_um}
    if sigma_um is not None:
        request["sigma_um"] = sigma_um
    if spindle is not None:
        request["spindle"] = spindle
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        try:
            with _addressable(path) as address:
                sock.connect(address)
        except (FileNotFoundError, ConnectionRefusedError, NotADirectoryError) as err:
            raise ControlError(
                f"no thermocomp service is running on {Path(state_dir)} (no one listens on {path})"
            ) from err
        except PermissionError as err:
            raise ControlError(
                f"{path}: permission denied (the socket is the service user's "
                "only: run as that user)"
            ) from err
        except OSError as err:
            raise ControlError(f"{path}: {err.strerror or err}") from err
        try:
            sock.sendall((json.dumps(request, allow_nan=False) + "\n").encode())
            reply = b""
            while b"\n" not in reply:
                chunk = sock.recv(MAX_LINE_BYTES)
                if not chunk:
                    break
                reply += chunk
        except TimeoutError as err:
            raise ControlError(f"the service did not answer within {timeout_s:g} s") from err
        except OSError as err:
            raise ControlError(f"{path}: {err.strerror or err}") from err
    try:
        answer = json.loads(reply.split(b"\n", 1)[0].decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as err:
        raise ControlError("the service's answer is not JSON (closed without answering?)") from err
    if not isinstance(answer, dict):
        raise ControlError("the service's answer is not a JSON object")
    return answer
