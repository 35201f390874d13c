"""Atomic file writes and plain text files: the base of every thermocomp file format."""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from ..errors import ConfigError

_TMP_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)


@contextlib.contextmanager
def atomic_write(
    path: str | os.PathLike[str], open_mode: str = "w", *, mode: int = 0o666
) -> Iterator[IO[Any]]:
    """Write to a temporary file beside ``path``, fsync, then rename over it.

    A crash at any moment leaves either the old file or the new one, never a
    partial file. ``open_mode`` is ``"w"`` (UTF-8 text) or ``"wb"``. The file gets the
    permission bits ``mode`` less the process umask, as ``open()`` gives: by default
    readable by all under the usual umask 022; ``mode=0o600`` for a file that may hold a
    secret. An overwritten file's own mode is not kept.
    """
    if isinstance(mode, str):  # the open mode was once the keyword ``mode``
        raise TypeError(
            f"atomic_write: mode is the permission bits (e.g. 0o600), not {mode!r}; "
            "the open mode is open_mode"
        )
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    # os.open lets the kernel apply the umask (and any default ACL) at creation, where
    # mkstemp would force 0600 and reading the umask would race other threads
    for _ in range(100):
        tmp = target.parent / f".{target.name}.{secrets.token_hex(6)}.tmp"
        try:
            fd = os.open(tmp, _TMP_FLAGS, mode)
            break
        except FileExistsError:
            continue
    else:
        raise FileExistsError(f"{target.parent}: no free temporary name for {target.name}")
    try:
        try:
            fh = os.fdopen(fd, open_mode, encoding=None if "b" in open_mode else "utf-8")
        except BaseException:
            os.close(fd)  # fdopen took no ownership
            raise
        with fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):
        dfd = os.open(target.parent, os.O_DIRECTORY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def versioned_path(path: str | os.PathLike[str]) -> Path:
    """``path`` if free, else the first free ``stem.v2.suffix``, ``stem.v3.suffix``, ...:
    a model or report is never overwritten."""
    p = Path(path)
    if not p.exists():
        return p
    k = 2
    while True:
        q = p.with_name(f"{p.stem}.v{k}{p.suffix}")
        if not q.exists():
            return q
        k += 1


def write_text(path: str | os.PathLike[str], text: str, *, overwrite: bool = True) -> Path:
    """Atomically write a text file; with ``overwrite=False`` a taken name gets a version suffix."""
    target = Path(path) if overwrite else versioned_path(path)
    with atomic_write(target) as fh:
        fh.write(text)
    return target


NOT_FOLLOWED = getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
NOT_FOLLOWED |= getattr(os, "O_CLOEXEC", 0)
"""Flags of a file that is never followed nor waited on: a link is refused, a FIFO opens
without blocking."""


def open_regular(path: str | os.PathLike[str], flags: int, *, follow: bool = False) -> int:
    """A descriptor of the regular file ``path`` (``flags`` as for :func:`os.open`, created with
    mode 0666 less the umask). Anything planted in its place is an ``OSError`` naming it: a
    symbolic link unless ``follow`` (a journal would write, or cut, whatever it points to), a
    FIFO (opened without blocking, so none can hang a cycle) or a device."""
    extra = NOT_FOLLOWED if not follow else NOT_FOLLOWED & ~getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(path, flags | extra, 0o666)
    except OSError as err:
        if err.errno == errno.ELOOP or (err.errno == errno.ENXIO and Path(path).is_fifo()):
            raise _not_regular(path, follow) from err
        raise
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise _not_regular(path, follow)
        os.set_blocking(fd, True)
    except OSError:
        os.close(fd)
        raise
    return fd


def _not_regular(path: str | os.PathLike[str], follow: bool) -> OSError:
    what = "a FIFO, device or directory" if follow else "a symbolic link, FIFO or device"
    return OSError(errno.EINVAL, f"not a regular file ({what}): left alone", os.fspath(path))


def read_regular(path: str | os.PathLike[str], limit: int | None = None) -> bytes:
    """The bytes of a regular file, links followed (at most ``limit + 1`` of them, so that a
    caller can tell a file over its limit). Anything else (a FIFO, a device, a directory) is an
    ``OSError`` at once (:func:`open_regular`): a FIFO that no one writes cannot hang a start."""
    with os.fdopen(open_regular(path, os.O_RDONLY, follow=True), "rb") as fh:
        return fh.read(-1 if limit is None else limit + 1)


def read_text(path: str | os.PathLike[str], limit: int | None = None) -> str:
    """A regular file's UTF-8 text (its first ``limit`` bytes); one-line ConfigError otherwise,
    naming the file, never its content."""
    try:
        raw = read_regular(path, limit)
        return (raw if limit is None else raw[:limit]).decode("utf-8")
    except OSError as err:
        raise ConfigError(f"{path}: cannot read: {err.strerror or err}") from err
    except UnicodeError:
        raise ConfigError(f"{path}: not UTF-8 text") from None
