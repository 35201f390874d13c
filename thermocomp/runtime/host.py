"""The box the service runs on: systemd's notify protocol and watchdog, the kernel's word on the
wall clock, the JSON log, and the wait between cycles that a stop ends at once."""

from __future__ import annotations

import logging
import math
import os
import select
import socket
import time

from .config import RuntimeConfig
from .events import JsonLines

log = logging.getLogger("thermocomp.runtime")

TIME_ERROR = 5
"""adjtimex's answer for a clock that is not synchronised."""


def kernel_clock_synchronized() -> bool | None:
    """Whether the kernel holds the wall clock synchronised (NTP, chrony or timesyncd keep it
    so: ``adjtimex`` answers other than ``TIME_ERROR``); None where it cannot be asked."""
    try:
        import ctypes

        buf = ctypes.create_string_buffer(512)  # a struct timex with modes 0: read only
        return int(ctypes.CDLL(None, use_errno=True).adjtimex(buf)) != TIME_ERROR
    except (OSError, AttributeError):
        return None


def setup_logging(cfg: RuntimeConfig) -> None:
    handler: logging.Handler = (
        logging.FileHandler(cfg.log_file) if cfg.log_file else logging.StreamHandler()
    )
    handler.setFormatter(JsonLines())
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(cfg.log_level.upper())
    logging.getLogger("asyncua").setLevel(logging.ERROR)
    logging.raiseExceptions = False  # a log that cannot be written must not stop compensation


def sd_notify(message: str) -> None:
    """systemd's notify protocol (Type=notify, WatchdogSec=); a no-op outside systemd."""
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return
    if addr.startswith("@"):
        addr = "\0" + addr[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
            s.connect(addr)
            s.send(message.encode(), socket.MSG_DONTWAIT)  # never block the control loop
    except OSError as err:
        log.debug("sd_notify %s failed: %s", message, err)


class Systemd:
    """What the service last told systemd: the watchdog's beat and the status line."""

    def __init__(self) -> None:
        self._last_beat = -math.inf
        self._status = ""

    def beat(self) -> None:
        """Feed the watchdog at most once a real second (systemd counts real seconds)."""
        beat = time.monotonic()
        if beat - self._last_beat >= 1.0:
            self._last_beat = beat
            sd_notify("WATCHDOG=1")

    def status(self, text: str) -> None:
        """The line `systemctl status` shows, sent when it changes."""
        if text != self._status:
            self._status = text
            sd_notify(f"STATUS={text}")


class Wake:
    """The wait between cycles, which :meth:`set` (SIGTERM's and SIGINT's handler) ends at once.

    ``time.sleep`` goes on sleeping after a signal's handler returns (PEP 475), so a spindle with
    a long ``period_s`` would write its last beat only when the period ends, or never: systemd
    kills it first. Nor may the handler set a ``threading.Event``: it runs between two bytecodes
    of the main thread, which may hold the event's lock at that moment (a deadlock). The handler
    writes one byte to a pipe instead (no lock), and the wait is a ``select`` on it: a signal
    that came before the wait began ends it as well. Until :meth:`open` (and after
    :meth:`close`) the wait is a plain sleep."""

    def __init__(self) -> None:
        self._fds: tuple[int, int] | None = None

    def open(self) -> None:
        if self._fds is None:
            r, w = os.pipe()
            os.set_blocking(r, False)
            os.set_blocking(w, False)  # a handler never blocks on a full pipe
            self._fds = (r, w)

    def set(self) -> None:
        """End the wait now, or the next one at once (safe in a signal handler)."""
        if self._fds is not None:
            try:
                os.write(self._fds[1], b"\0")
            except OSError:  # full: a wake is already pending
                pass

    def wait(self, seconds: float) -> bool:
        """Wait up to ``seconds``; True where :meth:`set` ended it."""
        if self._fds is None:
            time.sleep(max(0.0, seconds))
            return False
        r = self._fds[0]
        ready, _, _ = select.select([r], [], [], max(0.0, seconds))
        if not ready:
            return False
        try:
            while os.read(r, 512):
                pass
        except BlockingIOError:
            pass
        return True

    def close(self) -> None:
        fds, self._fds = self._fds, None
        for fd in fds or ():
            os.close(fd)
