"""One exception tree for all of thermocomp.

Every error also subclasses the builtin it refines (python-control style), so
callers that only know ``ValueError`` or ``OSError`` still catch them.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable
from typing import Any

MAX_MESSAGE_CHARS = 2000
"""An error's message is clipped to this on construction: a huge bad value echoed back
(one was 50 MB) must not travel whole through logs and terminals. Printers clip further."""

_LINE_BREAK = re.compile(r"\r\n|[\n\r\v\f\x1c-\x1e\x85\u2028\u2029]")
_CUT = re.compile(r"\.\.\. \((\d+) characters cut\)\Z")
_WIDEST = 10  # characters of the line one character of the text may become: \U0010ffff


def _escape(char: str) -> str:
    code = ord(char)
    return (
        f"\\x{code:02x}"
        if code < 0x100
        else f"\\u{code:04x}"
        if code < 0x10000
        else f"\\U{code:08x}"
    )


def _one_line(text: str) -> str:
    text = _LINE_BREAK.sub(" | ", text).replace("\t", " ")
    if text.isprintable():
        return text
    # the other controls, and invisible or unassigned characters: an echoed value must not
    # move the cursor, recolour the terminal or reorder the line (bidi overrides)
    return "".join(c if c.isprintable() else _escape(c) for c in text)


def clip(text: str, limit: int = 300) -> str:
    """``text`` on one line of at most ``limit`` characters (for a ``limit`` of 40 or more).

    Line breaks become `` | ``, tabs spaces, other unprintable characters escapes as in
    ``repr`` (``\\x1b``, ``\\u202e``). A longer text keeps its start and ends
    ``... (N characters cut)``; N counts characters of ``text``, plus those an earlier clip
    cut (an error's message is clipped once when it is made). Only the start of ``text`` is
    examined: a 50 MB text costs no more than a short one.
    """
    flat = _one_line(text[: limit + 1])
    if len(text) <= limit and len(flat) <= limit:
        return flat
    earlier = _CUT.search(text, max(0, len(text) - 64))
    cut_before = int(earlier.group(1)) if earlier else 0
    body = text[: earlier.start()] if earlier else text
    # the longest suffix this text can need: the count has at most this many digits
    room = max(limit - len(f"... ({len(body) + cut_before} characters cut)"), 0)
    keep = min(room, len(body))  # a character of text gives 1 to _WIDEST of the line
    head = _one_line(body[:keep])
    while len(head) > room:  # escapes or line breaks widened the kept start
        keep -= max(1, (len(head) - room) // _WIDEST)
        head = _one_line(body[:keep])
    return f"{head}... ({len(body) - keep + cut_before} characters cut)"


def did_you_mean(word: str, choices: Iterable[str]) -> str | None:
    """The one "did you mean" of the product: the nearest of ``choices`` to a misspelt ``word``
    (an adapter, sensor or chiller option, a configuration key, a backend), or None."""
    near = difflib.get_close_matches(word, list(choices), n=1)
    return near[0] if near else None


def unknown(what: str, name: Any, known: Iterable[str]) -> str:
    """``unknown <what> 'x' (did you mean 'y'?); known: ...``: a name that is not one of ``known``."""
    names = list(known)
    near = did_you_mean(name, names) if isinstance(name, str) else None
    return (
        f"unknown {what} {name!r}"
        + (f" (did you mean {near!r}?)" if near else "")
        + f"; known: {', '.join(names)}"
    )


class ThermocompError(Exception):
    """Root of every error raised on purpose by thermocomp.

    A message longer than :data:`MAX_MESSAGE_CHARS` is clipped (:func:`clip`) when the error
    is made.
    """

    def __init__(self, *args: object) -> None:
        if len(args) == 1 and isinstance(args[0], str) and len(args[0]) > MAX_MESSAGE_CHARS:
            args = (clip(args[0], MAX_MESSAGE_CHARS),)
        super().__init__(*args)


class ModelError(ThermocompError, ValueError):
    """A thermal model is invalid."""


class UnstableModelError(ModelError):
    """A state's pole |a(n)| >= 1 somewhere in the calibrated speed range."""


class ModelFileError(ModelError):
    """A model file is unreadable, of an unknown schema, or tampered with."""


class NonFiniteInputError(ThermocompError, ValueError):
    """A speed, time step or elongation is NaN or infinite."""


class RunLogError(ThermocompError, ValueError):
    """A run log is malformed. ``path`` and ``line`` locate the fault."""

    def __init__(self, message: str, path: str | None = None, line: int | None = None):
        self.path = path
        self.line = line
        where = ""
        if path is not None:
            where = f"{path}:{line}: " if line is not None else f"{path}: "
        super().__init__(f"{where}{message}")


class ConfigError(ThermocompError, ValueError):
    """A configuration value is invalid."""


class CalibrationError(ThermocompError, ValueError):
    """Calibration data cannot produce a trustworthy model."""


class AcquisitionError(ThermocompError, RuntimeError):
    """A recording stopped on a fault (sensor lost, saturated, frozen). What was recorded is kept."""


# -- controller and sensor links (raised by cnc_adapters) ---------------------------------


class AdapterError(ThermocompError, OSError):
    """A controller or sensor link failed."""


class UnreachableError(AdapterError, ConnectionError):
    """The controller cannot be reached (refused, unplugged, lost)."""


class AdapterTimeoutError(AdapterError, TimeoutError):
    """The controller did not answer in time."""


class WriteRejectedError(AdapterError, PermissionError):
    """The controller refused a write (access denied, type mismatch, out of range)."""


class BadValueError(AdapterError, ValueError):
    """A value read from the controller, or about to be written, is not usable."""


class SensorOverRangeError(BadValueError):
    """The sensor reports its measuring range exceeded (the probe is saturated)."""


class ControlError(ThermocompError, ConnectionError):
    """The running service cannot be reached through its control channel (not running, another
    user's), or it did not answer."""
