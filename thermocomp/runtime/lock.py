"""One instance per state directory: an exclusive ``flock`` on the state directory itself.

Two services on one spindle would fight over the offset (twice the slew rate) and interleave
their journals. The lock is the kernel's: it goes with the process, however it dies, so a
crashed instance never blocks the next start. It is held on the directory, not on a file in
it, so that no stray ``rm`` can break it (a removed lock file would let a second instance
lock a new one). The holder's pid is written into ``<state_dir>/thermocomp.lock`` for the
message a second instance prints; that file is information only.
"""

from __future__ import annotations

import errno
import fcntl
import os
from pathlib import Path

from compensator.errors import ThermocompError
from compensator.io.atomic import write_text

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
        fd = os.open(self.path.parent, os.O_RDONLY | os.O_DIRECTORY | getattr(os, "O_CLOEXEC", 0))
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as err:
            os.close(fd)
            holder = _read_pid(self.path)
            who = f"pid {holder}" if holder else "another process"
            raise AlreadyRunningError(
                f"state directory {self.path.parent} is in use by {who}; "
                "one instance per state directory"
            ) from err
        try:
            # a link planted there is replaced, never written through
            write_text(self.path, f"{os.getpid()}\n")
        except OSError as err:  # a read-only state directory: the lock holds all the same
            self.read_only = err.errno in (errno.EROFS, errno.EACCES, errno.EPERM)
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


def holder(state_dir: str | os.PathLike[str]) -> tuple[bool, int | None]:
    """Whether a service holds ``state_dir``, and its pid when the lock file names it. The lock
    is tried and given back at once, so no service is missed or blocked for long."""
    directory = Path(state_dir)
    try:
        fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return False, None  # no state directory: no service has run there
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True, _read_pid(directory / LOCK_NAME)
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False, None
    finally:
        os.close(fd)


def _read_pid(path: Path) -> int | None:
    try:
        text = path.read_bytes()[:32].decode("ascii", "replace").strip()
        return int(text) if text.isdigit() else None
    except OSError:
        return None
