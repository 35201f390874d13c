"""Atomic file writes and plain text files: the base of every thermocomp file format."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from ..errors import ConfigError


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "w") -> Iterator[IO[Any]]:
    """Write to a temporary file beside ``path``, fsync, then rename over it.

    A crash at any moment leaves either the old file or the new one, never a
    partial file.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, mode) as fh:
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


def read_text(path: str | os.PathLike[str]) -> str:
    try:
        return Path(path).read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"{path}: cannot read: {err.strerror or err}") from err
    except UnicodeError as err:
        raise ConfigError(f"{path}: not a text file") from err
