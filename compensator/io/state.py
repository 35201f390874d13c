"""The runtime's state file: one JSON object with a checksum, written atomically."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from typing import Any

from ..errors import ModelFileError
from .atomic import atomic_write, read_regular
from .checksum import digest

STATE_FORMAT = "thermocomp.state/1"


def save_state(path: str | os.PathLike[str], payload: Mapping[str, Any]) -> None:
    """Atomically write a runtime state file with its checksum."""
    body = {"format": STATE_FORMAT, **payload}
    body["sha256"] = digest(body)
    text = json.dumps(body, allow_nan=False)
    with atomic_write(path) as fh:
        fh.write(text)


MAX_STATE_BYTES = 1 << 20
"""A state file is a few hundred bytes; anything this large is not one."""


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number a state file may hold")


def load_state(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The saved state, or None when missing; :class:`ModelFileError` when unreadable, not
    JSON, not finite (``NaN``), absurdly nested or large, or its checksum does not match."""
    src = os.fspath(path)
    try:
        raw = read_regular(src, MAX_STATE_BYTES)  # a FIFO or a device is refused, never waited on
    except FileNotFoundError:
        return None
    except OSError as err:
        raise ModelFileError(f"{src}: unreadable state file ({err.strerror or err})") from err
    if len(raw) > MAX_STATE_BYTES:
        raise ModelFileError(f"{src}: not a state file (larger than {MAX_STATE_BYTES} bytes)")
    try:
        body = json.loads(raw.decode("utf-8"), parse_constant=_no_constant)
    except (ValueError, UnicodeError, RecursionError) as err:
        reason = "nested too deeply" if isinstance(err, RecursionError) else str(err)[:120]
        raise ModelFileError(f"{src}: unreadable state file ({reason})") from err
    if not isinstance(body, dict) or body.get("format") != STATE_FORMAT:
        raise ModelFileError(f"{src}: not a {STATE_FORMAT} file")
    expected = body.pop("sha256", None)
    try:
        actual = digest(body)
    except (ValueError, TypeError, RecursionError) as err:
        raise ModelFileError(f"{src}: unreadable state file ({type(err).__name__})") from err
    if expected != actual:
        raise ModelFileError(f"{src}: state file checksum mismatch")
    return body


def quarantine(path: str | os.PathLike[str], stamp: str) -> str | None:
    """Move a bad state file aside as ``<path>.corrupt-<stamp>``; the new name, or None when
    it could not be moved (then it is left where it is and simply not used)."""
    src = os.fspath(path)
    dst = f"{src}.corrupt-{stamp}"
    try:
        os.replace(src, dst)
    except OSError:
        return None
    return dst
