"""The runtime's state file: one JSON object with a checksum, written atomically."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from typing import Any

from ..errors import ModelFileError
from .atomic import atomic_write
from .checksum import digest

STATE_FORMAT = "thermocomp.state/1"


def save_state(path: str | os.PathLike[str], payload: Mapping[str, Any]) -> None:
    """Atomically write a runtime state file with its checksum."""
    body = {"format": STATE_FORMAT, **payload}
    body["sha256"] = digest(body)
    text = json.dumps(body, allow_nan=False)
    with atomic_write(path) as fh:
        fh.write(text)


def load_state(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The saved state, or None when missing; :class:`ModelFileError` when unreadable."""
    src = os.fspath(path)
    try:
        with open(src, encoding="utf-8") as fh:
            body = json.load(fh)
    except FileNotFoundError:
        return None
    except (OSError, json.JSONDecodeError, UnicodeError) as err:
        raise ModelFileError(f"{src}: unreadable state file ({err})") from err
    if not isinstance(body, dict) or body.get("format") != STATE_FORMAT:
        raise ModelFileError(f"{src}: not a {STATE_FORMAT} file")
    expected = body.pop("sha256", None)
    if expected != digest(body):
        raise ModelFileError(f"{src}: state file checksum mismatch")
    return body
