"""What one cycle takes from a controller and gives it, as typed values.

The runtime asks a link once a cycle for what it wants (:class:`Wants`) and gets one frozen
:class:`Reading`: every field is a finite value in its unit, or a :class:`Failure` that says
why not, or None where it was not asked for or the link has no such value. Conversion and
validation happen in the link, where a value enters: no exception raised by a controller's
value ever reaches the runtime. A write gives a :class:`WriteResult`. What a link can read at
all is its :class:`Capabilities`.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from compensator.errors import (
    AdapterError,
    AdapterTimeoutError,
    BadValueError,
    UnreachableError,
    WriteRejectedError,
    clip,
)

__all__ = [
    "LIFE_MODULUS",
    "LIFE_OPTION_PAIRS",
    "Capabilities",
    "Failure",
    "FailureKind",
    "Life",
    "Measurement",
    "Reading",
    "Wants",
    "WriteResult",
]

REASON_CHARS = 400
"""A failure's reason is cut to this many characters: it goes into events and status lines.
Room for a long URL and node id, and the status code and hint that come after them."""


LIFE_OPTION_PAIRS: tuple[tuple[tuple[str, ...], tuple[str, ...]], ...] = (
    (("life_node", "life_path"), ("valid_node", "valid_path")),
    (("life_register",), ("valid_register",)),
    (("life_address",), ("valid_address",)),
    (("life_macro",), ("valid_macro",)),
    (("life_var",), ("valid_var",)),
)
"""Each backend's sign-of-life options: (the counter's keys, the flag's keys), either key of
a group naming it (an OPC UA node id or browse path)."""


class FailureKind(enum.Enum):
    """Why a value is missing: the runtime acts differently on each."""

    LINK = "link"
    """The controller cannot be reached (refused, lost): the link is down."""
    TIMEOUT = "timeout"
    """The controller did not answer in time: the link is down."""
    VALUE = "value"
    """The controller answered with a value of the wrong type, status, range or finiteness."""
    REFUSED = "refused"
    """The controller refused a write."""
    FAILED = "failed"
    """Any other failure of the request (a node that does not exist, an option not set)."""


@dataclass(frozen=True)
class Failure:
    """A value the link could not give, and why (one line, no secret)."""

    kind: FailureKind
    reason: str

    @classmethod
    def of(cls, err: BaseException) -> Failure:
        """The failure an exception of the link stands for."""
        if isinstance(err, AdapterTimeoutError):
            kind = FailureKind.TIMEOUT
        elif isinstance(err, UnreachableError):
            kind = FailureKind.LINK
        elif isinstance(err, BadValueError):
            kind = FailureKind.VALUE
        elif isinstance(err, WriteRejectedError):
            kind = FailureKind.REFUSED
        elif isinstance(err, AdapterError):
            kind = FailureKind.FAILED
        else:  # a conversion that raised on a value the controller gave
            kind = FailureKind.VALUE
        reason = str(err) or type(err).__name__
        return cls(kind, clip(reason, REASON_CHARS))

    @property
    def link_lost(self) -> bool:
        """The controller cannot be reached or does not answer: the link is down."""
        return self.kind in (FailureKind.LINK, FailureKind.TIMEOUT)

    def __str__(self) -> str:
        return self.reason


@dataclass(frozen=True)
class Measurement:
    """A new tool-setter or probe measurement of the elongation [um] (positive: the tool grew
    toward the workpiece), its sigma [um] when the controller states one, and its sequence."""

    elongation_um: float
    sigma_um: float | None
    sequence: int
    source: str


@dataclass(frozen=True)
class Wants:
    """What the runtime asks of the controller this cycle, beside the speed."""

    cutting: bool = False
    """The controller's cutting signal."""
    held_offset: bool = False
    """The offset the controller holds now (a read-back)."""
    inputs: bool = False
    """The input channels (temperatures, load)."""
    measurement: bool = False
    """A new measurement from the controller's probe cycle."""


@dataclass(frozen=True)
class Capabilities:
    """What a configured link can read, beside the speed, and write."""

    held_offset: bool = False
    """It reads back the offset the controller holds."""
    cutting: bool = False
    """It reads the controller's own cutting signal."""
    measurement: bool = False
    """It takes tool-setter or probe measurements from the controller."""
    inputs: tuple[str, ...] = ()
    """The names of the input channels it reads."""
    life_sign: bool = False
    """It writes a sign of life (:class:`Life`) with the offset: the control can watch it."""


def _frozen(values: Mapping[str, float | Failure] | None) -> Mapping[str, float | Failure] | None:
    return None if values is None else MappingProxyType(dict(values))


@dataclass(frozen=True)
class Reading:
    """One cycle's values from the controller, each checked where it entered.

    None in a field: not asked for, not read (the link was lost before it), or no such value on
    this link. A float is always finite.
    """

    speed_rpm: float | Failure
    """The spindle's speed [rpm], a magnitude."""
    cutting: bool | Failure | None = None
    """Whether the controller says the tool may be in the part now."""
    not_ready_offset_um: float | Failure | None = None
    """A controller that is not ready to take our offset (off, E-stop, not homed) applies this
    one [um]; None when it is ready."""
    held_offset_um: float | Failure | None = None
    """The offset the controller holds [um], read back."""
    inputs: Mapping[str, float | Failure] | Failure | None = None
    """The input channels by name, each a finite value or its own failure."""
    measurement: Measurement | Failure | None = None
    """A new measurement since the last one taken; None when there is none."""
    write_refused_um: float | None = None
    """A deferred check of the last write: the controller did not take it and holds this [um]."""
    reconnects: int = 0
    """How often the link has reconnected by itself: a change means the controller may have
    lost the offset."""

    def __post_init__(self) -> None:
        if isinstance(self.inputs, Mapping):
            object.__setattr__(self, "inputs", _frozen(self.inputs))

    @property
    def speed_read(self) -> bool:
        return not isinstance(self.speed_rpm, Failure)


LIFE_MODULUS = 32767
"""The life counter runs 1 .. 32767 and wraps to 1: it fits a signed 16-bit word of every
control, and 0 means "never written" (a control that finds 0 knows thermocomp never ran)."""


@dataclass(frozen=True)
class Life:
    """The sign of life written with the offset: a counter the control watches (it moves every
    cycle the service writes or confirms the offset; a counter that stops means thermocomp has
    stopped), and whether compensation is valid (false while the service holds, does not
    write, or stops cleanly)."""

    counter: int
    valid: bool

    def __post_init__(self) -> None:
        if isinstance(self.counter, bool) or not 0 <= self.counter <= LIFE_MODULUS:
            raise ValueError(f"life counter {self.counter!r} is not in 0..{LIFE_MODULUS}")

    def next(self, valid: bool) -> Life:
        """The next beat: the counter moved on (1 .. 32767, then 1 again), ``valid`` as given."""
        return Life(self.counter % LIFE_MODULUS + 1, bool(valid))


@dataclass(frozen=True)
class WriteResult:
    """The outcome of one write: the offset taken (``failure`` None), or the offset's failure;
    and, apart, the sign of life's."""

    failure: Failure | None = None
    """The offset's failure only (None for a confirmation, whose offset is not written, unless
    the link was lost: a lost link is this failure, whatever the write carried)."""
    pending: bool = False
    """Taken, to be checked with the next reading (:attr:`Reading.write_refused_um`)."""
    life_failure: Failure | None = None
    """The offset was taken (or confirmed) but the sign of life was not: a counter or flag
    refused, missing or of a type that cannot hold it. The control's watch sees a counter that
    does not move; the offset still reached the controller."""

    @property
    def taken(self) -> bool:
        return self.failure is None
