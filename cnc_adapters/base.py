"""The adapter family: one abstract base with a small template method (python-can style).

Public :meth:`Adapter.read_speed` and :meth:`Adapter.write_offset_um` validate values
(finite, sign), convert units and sign (:class:`compensator.units.ControllerUnits`, the only
place um meet controller units) and log; backends override only the raw calls ``_connect``,
``_read_speed_raw``, ``_write_offset_raw`` and ``_disconnect``. :class:`Link` is the
reconnecting connection that adapters and sensors share.

Backends are registered by name in :mod:`cnc_adapters.registry`.
"""

from __future__ import annotations

import logging
import math
import random
import re
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any, ClassVar
from urllib.parse import parse_qsl, urlsplit

from compensator.errors import (
    AdapterError,
    AdapterTimeoutError,
    BadValueError,
    UnreachableError,
    WriteRejectedError,
)
from compensator.units import ControllerUnits

__all__ = ["Adapter", "AdapterError", "AdapterTimeoutError", "BadValueError", "Link",
           "UnreachableError", "WriteRejectedError", "query_params", "typed_params"]

log = logging.getLogger("thermocomp.adapters")


class Link(ABC):
    """A connection to one device that reopens itself after a failure.

    A lost link is reopened on the next call, with exponential back-off and jitter
    between failed attempts (``backoff_s`` doubling up to ``max_backoff_s``, +-``jitter``);
    during the back-off calls fail at once with :class:`UnreachableError`.
    ``on_link_change(up, reason)`` tells the owner when the link goes down or comes back.
    ``clock`` is injectable for tests. Subclasses implement ``_connect`` and ``_disconnect``.
    """

    name: ClassVar[str] = "abstract"

    def __init__(
        self,
        *,
        backoff_s: float = 0.5,
        max_backoff_s: float = 30.0,
        jitter: float = 0.2,
        on_link_change: Callable[[bool, str], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        rng: random.Random | None = None,
    ):
        self.backoff_s = backoff_s
        self.max_backoff_s = max_backoff_s
        self.jitter = jitter
        self.on_link_change = on_link_change
        self._clock = clock
        self._rng = rng or random.Random()
        self._open = False
        self._closed = False
        self._failures = 0
        self._next_attempt = -math.inf
        self._down = False
        self.reconnects = 0

    def open(self) -> Link:
        if self._closed:
            raise AdapterError(f"{self.name} link is closed")
        if self._open:
            return self
        now = self._clock()
        if now < self._next_attempt:
            raise UnreachableError(
                f"{self.name}: link down, next attempt in {self._next_attempt - now:.1f} s "
                f"({self._failures} failed)")
        try:
            self._connect()
        except AdapterError as err:
            self._failures += 1
            delay = min(self.max_backoff_s, self.backoff_s * 2 ** (self._failures - 1))
            delay *= 1 + self.jitter * self._rng.uniform(-1, 1)
            self._next_attempt = now + delay
            self._set_down(str(err))
            raise
        self._open = True
        if self._down:
            self.reconnects += 1
            self._down = False
            self._notify(True, "link restored")
        self._failures = 0
        self._next_attempt = -math.inf
        return self

    def _notify(self, up: bool, reason: str) -> None:
        if self.on_link_change is not None:
            try:
                self.on_link_change(up, reason)
            except Exception:  # noqa: BLE001 - a faulty listener must not break the link
                log.exception("%s: on_link_change failed", self.name)

    def _set_down(self, reason: str) -> None:
        if not self._down:
            self._down = True
            self._notify(False, reason)

    def close(self) -> None:
        """Idempotent."""
        if self._open:
            try:
                self._disconnect()
            finally:
                self._open = False
        self._closed = True

    def _link_lost(self, message: str) -> UnreachableError:
        """Drop a dead link so that the next call reconnects; the error to raise."""
        try:
            self._disconnect()
        except Exception:  # noqa: BLE001 - it is already dead
            pass
        self._open = False
        log.warning("%s", message)
        self._set_down(message)
        return UnreachableError(message)

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @abstractmethod
    def _connect(self) -> None: ...

    @abstractmethod
    def _disconnect(self) -> None: ...


class Adapter(Link):
    """A link to one spindle on one controller.

    ``offset_scale`` converts um to the controller's unit (0.001 for mm) and
    ``offset_sign`` flips the sign for controllers whose thermal offset points
    the other way (:attr:`units`). ``speed_scale`` converts the controller's speed unit to
    rpm. Reconnection, back-off and ``on_link_change`` are those of :class:`Link`.
    """

    def __init__(
        self,
        *,
        offset_scale: float = 1.0,
        offset_sign: int = 1,
        speed_scale: float = 1.0,
        **link: Any,
    ):
        self.units = ControllerUnits(float(offset_scale), offset_sign)
        super().__init__(**link)
        self.speed_scale = speed_scale
        self.offset_um_requested: float | None = None

    @property
    def offset_scale(self) -> float:
        return self.units.scale

    @property
    def offset_sign(self) -> int:
        return self.units.sign

    # -- template methods ------------------------------------------------------

    def read_speed(self) -> float:
        """Actual spindle speed [rpm], as a magnitude (reverse rotation heats alike);
        :class:`BadValueError` when not a finite number. The one check of every backend's speed."""
        self.open()
        raw = self._read_speed_raw()
        if isinstance(raw, bool):
            raise BadValueError(f"{self.name}: speed {raw!r} is not a number")
        try:
            rpm = abs(float(raw) * self.speed_scale)
        except (TypeError, ValueError) as err:
            raise BadValueError(f"{self.name}: speed {raw!r} is not a number") from err
        if not math.isfinite(rpm):
            raise BadValueError(f"{self.name}: speed is {rpm}")
        return rpm

    def write_offset_um(self, offset_um: float) -> None:
        """Write the thermal offset [um]; a non-finite value never leaves this method."""
        if isinstance(offset_um, bool) or not isinstance(offset_um, (int, float)) \
                or not math.isfinite(offset_um):
            raise BadValueError(f"{self.name}: refusing to write offset {offset_um!r}")
        self.open()
        raw = self.units.to_controller(offset_um)
        log.debug("%s: write offset %.4f um (raw %r)", self.name, offset_um, raw)
        self.offset_um_requested = float(offset_um)
        self._write_offset_raw(raw)

    def take_write_mismatch(self) -> float | None:
        """For backends that check writes later: the offset [um] the controller holds when it
        did not take the last write, reported once; None when all is well."""
        raw = self._take_mismatch_raw()
        if raw is None or isinstance(raw, bool) or not isinstance(raw, (int, float)):
            return None
        return self.units.to_um(raw)

    def _take_mismatch_raw(self) -> Any:
        """Backend hook: the raw value the controller holds after a failed deferred check."""
        return None

    def input_channels(self) -> tuple[str, ...]:
        """Names of the extra input channels this link is configured to read (temperatures,
        load, ambient), for models that use them."""
        return ()

    def read_inputs(self) -> dict[str, float]:
        """The extra channels, by name; a value that is not a number comes back as NaN (the
        runtime treats it as a sensor fault)."""
        if not self.input_channels():
            return {}
        self.open()
        out = {}
        for name, raw in self._read_inputs_raw().items():
            try:
                out[name] = float(raw)
            except (TypeError, ValueError):
                out[name] = math.nan
        return out

    def _read_inputs_raw(self) -> dict[str, Any]:
        raise AdapterError(f"{self.name}: this adapter reads no input channels")

    def not_ready_offset_um(self) -> float | None:
        """For controllers whose offset depends on the machine state (LinuxCNC zeroes external
        offsets at machine-on and ignores them until homed): the offset [um] it applies while
        not ready to take ours; None when it is ready."""
        return None

    # -- backend hooks ----------------------------------------------------------

    @abstractmethod
    def _read_speed_raw(self) -> Any: ...

    @abstractmethod
    def _write_offset_raw(self, value: float) -> None: ...


def construct(label: str, factory: Any, *args: Any, **kw: Any) -> Any:
    """``factory(*args, **kw)``, an option the backend does not know reported as an
    :class:`AdapterError` that names it (a URL or configuration typo), not a ``TypeError``."""
    try:
        return factory(*args, **kw)
    except TypeError as err:
        m = re.search(r"unexpected keyword argument '(\w+)'", str(err))
        if m is None:
            raise
        raise AdapterError(f"{label}: unknown option {m.group(1)!r}") from err


def query_params(url: str) -> dict[str, str]:
    return dict(parse_qsl(urlsplit(url).query))


INT_PARAMS = frozenset({"baudrate", "device_id", "speed_register", "offset_register", "offset_sign",
                        "speed_var", "offset_var", "r_parameter"})
FLOAT_PARAMS = frozenset({"timeout_s", "offset_scale", "speed_scale", "time_scale"})


def typed_params(url: str, drop: tuple[str, ...] = ("protocol",), ints: frozenset[str] = INT_PARAMS,
                 floats: frozenset[str] = FLOAT_PARAMS) -> dict[str, Any]:
    """URL query parameters as constructor keywords, the ``ints`` and ``floats`` converted."""
    out: dict[str, Any] = {}
    for k, v in query_params(url).items():
        if k in drop:
            continue
        try:
            out[k] = int(v) if k in ints else float(v) if k in floats else v
        except ValueError as err:
            raise AdapterError(f"URL parameter {k}={v!r} is not a number") from err
    return out
