"""One instance per state directory: an exclusive ``flock`` on ``<state_dir>/thermocomp.lock``.

Two services on one spindle would fight over the offset (twice the slew rate) and interleave
their journals. The lock is the kernel's: it goes with the process, however it dies, so a
crashed instance never blocks the next start. The holder's pid is written into the file for
the message a second instance prints.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from pathlib import Path

from compensator.errors import ThermocompError

LOCK_NAME = "thermocomp.lock"


class AlreadyRunningError(ThermocompError, BlockingIOError):
    """Another thermocomp instance holds the state directory."""


class StateDirLock:
    """Held from :meth:`acquire` until :meth:`release` (or the process ends)."""

    def __init__(self, state_dir: str | os.PathLike[str]):
        self.path = Path(state_dir) / LOCK_NAME
        self._fd: int | None = None
        self.read_only = False

    def acquire(self) -> StateDirLock:
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            if err.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
                raise
            # a read-only state directory: lock the file that is there (flock needs no write)
            fd = os.open(self.path, os.O_RDONLY)
            self.read_only = True
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as err:
            holder = _read_pid(fd)
            os.close(fd)
            who = f"pid {holder}" if holder else "another process"
            raise AlreadyRunningError(f"state directory {self.path.parent} is in use by {who} "
                                      f"(lock {self.path}); one instance per state directory") from err
        if not self.read_only:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)  # closing drops the flock

    def __enter__(self) -> StateDirLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        return int(text) if text.isdigit() else None
    except OSError:
        return None
