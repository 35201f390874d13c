"""The adapter family: one abstract base with a small template method (python-can style).

Public :meth:`Adapter.read_speed`, :meth:`Adapter.read_offset_um` and
:meth:`Adapter.write_offset_um` validate values (finite, sign), convert units and sign
(:class:`compensator.units.ControllerUnits`, the only place um meet controller units) and log;
backends override only the raw calls ``_connect``, ``_read_speed_raw``, ``_read_offset_raw``,
``_write_offset_raw`` and ``_disconnect``. :class:`Link` is the reconnecting connection that
adapters and sensors share.

Every backend declares its options as a pydantic model, ``Settings`` (:class:`AdapterSettings`
and the helpers here); :func:`build` checks a configuration against it before the backend is
constructed, so a misspelt key or a bad value is one :class:`ConfigError` line that names the
key, the value and what is allowed.

Backends are registered by name in :mod:`cnc_adapters.registry`.
"""

from __future__ import annotations

import inspect
import logging
import math
import numbers
import random
import re
import struct
import time
import typing
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Self
from urllib.parse import parse_qsl, urlsplit

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    model_validator,
)

from compensator.errors import (
    MAX_MESSAGE_CHARS,
    AdapterError,
    AdapterTimeoutError,
    BadValueError,
    ConfigError,
    UnreachableError,
    WriteRejectedError,
    clip,
    did_you_mean,
    unknown,
)
from compensator.units import ControllerUnits

from .reading import (
    LIFE_MODULUS,
    LIFE_OPTION_PAIRS,
    Capabilities,
    Failure,
    Life,
    Measurement,
    Reading,
    Wants,
    WriteResult,
)

__all__ = [
    "RUNTIME_ONLY",
    "Adapter",
    "AdapterError",
    "AdapterSettings",
    "AdapterTimeoutError",
    "Allowed",
    "BadValueError",
    "Capabilities",
    "ConfigError",
    "Failure",
    "Life",
    "Link",
    "LinkSettings",
    "Measurement",
    "Problem",
    "Reading",
    "SettingsError",
    "UnreachableError",
    "Wants",
    "WriteRejectedError",
    "WriteResult",
    "build",
    "check_settings",
    "checked_life",
    "did_you_mean",
    "host_options",
    "life_configured",
    "life_pair_refusal",
    "option_names",
    "query_params",
    "redact_url",
    "serial_options",
    "typed_params",
    "unknown",
]

log = logging.getLogger("thermocomp.adapters")


def redact_url(text: str) -> str:
    """``text`` with the user information of a URL in it replaced by ``***``: a URL that goes
    into a log line or an error message never carries a user name or password."""
    # greedy up to the last '@': a password with a raw '/' or '@' in it is hidden all the same
    return re.sub(r"(?s)://.*@", "://***@", text)


def url_has_password(url: str) -> bool:
    """Whether ``url`` carries a password (``opc.tcp://user:secret@host``), as asyncua would
    read it."""
    userinfo, at, _ = urlsplit(url).netloc.rpartition("@")
    return bool(at) and ":" in userinfo


def short(value: Any, limit: int = 60) -> str:
    """``repr(value)``, cut to ``limit`` characters, any URL user information hidden."""
    text = redact_url(repr(value))
    return text if len(text) <= limit else text[: limit - 3] + "..."


class Link(ABC):
    """A connection to one device that reopens itself after a failure.

    A lost link is reopened on the next call, with exponential back-off and jitter
    between failed attempts (``backoff_s`` doubling up to ``max_backoff_s``, +-``jitter``);
    during the back-off calls fail at once with :class:`UnreachableError`.
    ``on_link_change(up, reason)`` tells the owner when the link goes down or comes back.
    ``clock`` is injectable for tests. Subclasses implement ``_connect`` and ``_disconnect``,
    and ``_abort`` where a dead link can be dropped faster than it can be closed.
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

    def open(self) -> Self:
        if self._closed:
            raise AdapterError(f"{self.name} link is closed")
        if self._open:
            return self
        now = self._clock()
        if now < self._next_attempt:
            raise UnreachableError(
                f"{self.name}: link down, next attempt in {self._next_attempt - now:.1f} s "
                f"({self._failures} failed)"
            )
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
            except Exception:
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

    def _link_lost(
        self, message: str, error: type[AdapterError] = UnreachableError
    ) -> AdapterError:
        """Drop a dead link so that the next call reconnects; the error to raise (``error``:
        :class:`UnreachableError`, or :class:`AdapterTimeoutError` for a peer that hangs)."""
        try:
            self._abort()
        except Exception:  # noqa: BLE001 - it is already dead
            pass
        self._open = False
        log.warning("%s", message)
        self._set_down(message)
        return error(message)

    def _abort(self) -> None:
        """Drop a link that is dead or hung; by default the same as closing it."""
        self._disconnect()

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @abstractmethod
    def _connect(self) -> None: ...

    @abstractmethod
    def _disconnect(self) -> None: ...


# -- settings -----------------------------------------------------------------------------


class Allowed:
    """Field metadata: what a value must be, for the one-line error (``timeout_s must be a
    number > 0, not 'abc'``)."""

    __slots__ = ("text",)

    def __init__(self, text: str):
        self.text = text

    def __repr__(self) -> str:
        return f"Allowed({self.text!r})"


SETTINGS_CONFIG = ConfigDict(
    extra="forbid", frozen=True, allow_inf_nan=False, hide_input_in_errors=True
)
"""Every settings model: no unknown key, immutable, no NaN or infinity; and the input is kept
out of pydantic's own message, which is chained to ours and might hold a secret."""


def _nonzero(v: float) -> float:
    if v == 0:
        raise ValueError("a finite number other than 0")
    return v


def _sign(v: Any) -> Any:
    if isinstance(v, bool):
        raise ValueError("+1 or -1")
    if isinstance(v, str):
        try:
            v = float(v)
        except ValueError:
            raise ValueError("+1 or -1") from None
    if isinstance(v, (int, float)) and v in (1, -1):
        return int(v)
    raise ValueError("+1 or -1")


def one_of(*choices: str) -> Any:
    """A string field that takes one of ``choices``."""
    text = ", ".join(repr(c) for c in choices)

    def check(v: str) -> str:
        if v not in choices:
            raise ValueError(f"one of {text}")
        return v

    return Annotated[str, AfterValidator(check), Allowed(f"one of {text}")]


def _pattern(v: str) -> str:
    try:
        re.compile(v)
    except re.error as err:
        raise ValueError(f"a regular expression ({err})") from None
    return v


def _value_pattern(v: str) -> str:
    if "value" not in re.compile(_pattern(v)).groupindex:
        raise ValueError("a regular expression with a (?P<value>...) group")
    return v


Seconds = Annotated[float, Field(gt=0), Allowed("a number > 0 (seconds)")]
Positive = Annotated[float, Field(gt=0), Allowed("a number > 0")]
NonZero = Annotated[float, AfterValidator(_nonzero), Allowed("a finite number other than 0")]
Finite = Annotated[float, Allowed("a finite number")]
Fraction = Annotated[float, Field(ge=0, lt=1), Allowed("a number from 0 up to (not including) 1")]
Sign = Annotated[int, BeforeValidator(_sign), Allowed("+1 or -1")]
Count = Annotated[int, Field(ge=0), Allowed("a whole number >= 0")]
Baud = Annotated[int, Field(gt=0), Allowed("a whole number > 0 (bits per second)")]
Text = Annotated[str, Field(min_length=1), Allowed("a non-empty string")]
Pattern = Annotated[str, AfterValidator(_pattern), Allowed("a regular expression")]
ValuePattern = Annotated[
    str, AfterValidator(_value_pattern), Allowed("a regular expression with a (?P<value>...) group")
]


class LinkSettings(BaseModel):
    """Options of every link: reconnection back-off."""

    model_config = SETTINGS_CONFIG

    backoff_s: Seconds = Field(0.5, description="first wait after a failed connect; doubles")
    max_backoff_s: Seconds = Field(30.0, description="longest wait between connect attempts")
    jitter: Fraction = Field(0.2, description="the wait varies by +-this fraction")


class AdapterSettings(LinkSettings):
    """Options of every controller adapter: units and sign, and the link's back-off. A default
    of None means the backend's own (a preset's, or one derived from another option); None
    cannot be given."""

    # the defaults are not validated, so None stands for "the backend's own" here only
    offset_scale: NonZero = Field(  # type: ignore[assignment]
        None, description="controller unit per um (0.001: mm); default 1, or the preset's"
    )
    offset_sign: Sign = Field(  # type: ignore[assignment]
        None, description="-1 for a controller whose offset points the other way; default +1"
    )
    speed_scale: NonZero = Field(  # type: ignore[assignment]
        None, description="rpm per controller speed unit; default 1"
    )
    offset_resolution: Annotated[
        float, Field(ge=0), Allowed("a number >= 0 (controller units)")
    ] = Field(  # type: ignore[assignment]
        None,
        description="one count of the controller's offset, in its unit; the written value "
        "is rounded to it (a controller profile sets it); default 0: continuous",
    )

    @model_validator(mode="before")
    @classmethod
    def _life_pairs(cls, data: Any) -> Any:
        """The sign of life's counter and flag given together, or neither: one alone would
        silently pair with a preset's or profile's default for the other."""
        if isinstance(data, Mapping):
            for counters, flags in LIFE_OPTION_PAIRS:
                if counters[0] not in cls.model_fields:
                    continue
                if any(data.get(k) is not None for k in counters) != any(
                    data.get(k) is not None for k in flags
                ):
                    raise ValueError(life_pair_refusal(_either(counters), _either(flags)))
        return data


RUNTIME_ONLY = frozenset({"clock", "rng", "on_link_change", "machine"})
"""Constructor keywords that are objects of the running program, never configuration: passed
through, not validated."""


def _allowed_of(field: Any) -> str | None:
    return next((m.text for m in field.metadata if isinstance(m, Allowed)), None)


def _nested_model(annotation: Any) -> Any:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _nested_model(arg)
        if found is not None:
            return found
    return None


def option_names(model: type[BaseModel]) -> list[str]:
    """The options of ``model``, its own first, then those it inherits (the common ones last)."""
    names: list[str] = []
    for klass in model.__mro__:
        for name in inspect.get_annotations(klass):
            if name in model.model_fields and name not in names:
                names.append(name)
    return names


_SECRET_WORDS = ("password", "passwd", "secret", "token", "credential", "private")


def names_a_secret(key: str) -> bool:
    """The key's name (or its table's) says that its value is secret: never echoed."""
    return any(w in key.lower() for w in _SECRET_WORDS)


_ABSENT: Any = object()


@dataclass(frozen=True)
class Problem:
    """One configuration problem, in the product's one dialect: the key as written (dotted,
    from the mapping that was checked), the value given, and what is wrong: ``unknown key (did
    you mean 'x'?)``, ``expected <what is allowed>``, or a check's own sentence."""

    key: str
    text: str
    given: Any = _ABSENT

    def under(self, prefix: str) -> Problem:
        """The same problem, its key inside the table ``prefix``."""
        return Problem(
            f"{prefix}.{self.key}" if prefix and self.key else prefix or self.key,
            self.text,
            self.given,
        )

    def line(self, scope: str = "") -> str:
        """``scope: key = value: text``; a section's value (a table) and a secret's are not echoed."""
        head = f"{scope}: " if scope else ""
        if not self.key:
            return f"{head}{self.text}"
        table = isinstance(self.given, Mapping) or (
            isinstance(self.given, (list, tuple))
            and any(isinstance(v, Mapping) for v in self.given)
        )
        shown = not (self.given is _ABSENT or table or names_a_secret(self.key))
        given = self.given
        if isinstance(given, str) and "://" not in given:  # user:password@host, no scheme
            given = re.sub(r"(?s)\A[^@/]*:.*@", "***@", given)
        return f"{head}{self.key}{' = ' + short(given) if shown else ''}: {self.text}"


MAX_PROBLEM_LINES = 20


def problem_lines(lines: list[str]) -> str:
    """Problems one a line, as many as fit one error message (the rest counted)."""
    out: list[str] = []
    size = 0
    for i, line in enumerate(lines):
        line = clip(line, 300)
        if i >= MAX_PROBLEM_LINES or size + len(line) > MAX_MESSAGE_CHARS - 60:
            out.append(f"({len(lines) - i} more problem(s) not shown)")
            break
        out.append(line)
        size += len(line) + 1
    return "\n".join(out)


class SettingsError(ConfigError):
    """Settings that do not validate: one :class:`Problem` a line, each ``label: key = value:
    what is wrong``. A configuration that holds these settings (a spindle's ``adapter``, the
    chiller) re-reads :attr:`problems` under its own key."""

    def __init__(self, label: str, problems: list[Problem]):
        self.label = label
        self.problems = tuple(problems)
        super().__init__(problem_lines([p.line(label) for p in self.problems]))

    def under(self, prefix: str) -> SettingsError:
        return SettingsError(self.label, [p.under(prefix) for p in self.problems])


def key_error(key: str, text: str, given: Any = _ABSENT) -> SettingsError:
    """For a check across keys (a model validator) that can say which key is wrong: the
    settings' error then names that key and its value (``port = 0: expected ...``)."""
    return SettingsError("", [Problem(key, text, given)])


def _number(v: Any) -> str:
    """A bound as a user writes it: 31536000, not 3.1536e+07; 0.01 as 0.01."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    return str(int(f)) if f.is_integer() and abs(f) < 1e15 else f"{f:g}"


def _range(field: Any) -> str | None:
    """A number field's type and bounds in words (``a number > 0 and <= 3600``), or None."""
    ann = field.annotation
    kinds = {a for a in (ann, *typing.get_args(ann)) if a in (int, float)}
    if not kinds:
        return None
    words = {"gt": ">", "ge": ">=", "lt": "<", "le": "<="}
    bounds = [
        f"{words[k]} {_number(getattr(m, k))}"
        for m in field.metadata
        for k in words
        if getattr(m, k, None) is not None
    ]
    kind = "a whole number" if kinds == {int} else "a number"
    return " and ".join([f"{kind} {bounds[0]}", *bounds[1:]]) if bounds else kind


_PLAIN = {
    "bool_parsing": "true or false",
    "bool_type": "true or false",
    "int_parsing": "a whole number",
    "int_type": "a whole number",
    "int_from_float": "a whole number",
    "float_parsing": "a number",
    "float_type": "a number",
    "finite_number": "a finite number",
    "string_type": "a string",
    "path_type": "a path (a string)",
    "list_type": "an array",
    "tuple_type": "an array",
    "dict_type": "a table",
    "model_type": "a table",
    "model_attributes_type": "a table",
    "missing": "a value",
}
_NUMERIC = {
    "greater_than",
    "greater_than_equal",
    "less_than",
    "less_than_equal",
    "finite_number",
    "int_parsing",
    "int_type",
    "int_from_float",
    "float_parsing",
    "float_type",
    "multiple_of",
}


def expected(e: Mapping[str, Any], field: Any = None) -> str:
    """What the value must be, in words, from pydantic's error type and context and the
    field's declaration (its :class:`Allowed` text first): never pydantic's own sentence."""
    if field is not None:
        allowed = _allowed_of(field)
        if allowed is not None:
            return allowed
    t, ctx = e["type"], e.get("ctx") or {}
    if t in _NUMERIC and field is not None and (words := _range(field)) is not None:
        return words
    if t in _PLAIN:
        return _PLAIN[t]
    if t in ("literal_error", "enum"):
        return f"one of {ctx.get('expected')}"
    bound = {
        "greater_than": ("gt", ">"),
        "greater_than_equal": ("ge", ">="),
        "less_than": ("lt", "<"),
        "less_than_equal": ("le", "<="),
        "multiple_of": ("multiple_of", "a multiple of"),
    }.get(t)
    if bound is not None:
        return f"a number {bound[1]} {_number(ctx.get(bound[0]))}"
    if t == "string_too_short":
        return f"a string of at least {ctx.get('min_length')} character(s)"
    if t == "string_too_long":
        return f"a string of at most {ctx.get('max_length')} characters"
    if t == "string_pattern_mismatch":
        return f"a string matching {ctx.get('pattern')}"
    if t == "too_short":
        return f"at least {ctx.get('min_length')} entr(y/ies)"
    if t == "too_long":
        return f"at most {ctx.get('max_length')} entries"
    # a type this table does not know: pydantic's words without their "Input should be"
    return re.sub(r"^(Input should be |Value error, |Assertion failed, )", "", str(e.get("msg", t)))


def key_names(model: type[BaseModel]) -> list[str]:
    """The keys ``model`` takes: its options (:func:`option_names` order), then their aliases."""
    names = option_names(model)
    for f in model.model_fields.values():
        for alias in (f.alias, f.validation_alias):
            if isinstance(alias, str) and alias not in names:
                names.append(alias)
    return names


def _field(model: Any, key: str) -> Any:
    if model is None:
        return None
    found = model.model_fields.get(key)
    if found is not None:
        return found
    return next(
        (f for f in model.model_fields.values() if key in (f.alias, f.validation_alias)), None
    )


def _is_table_of(annotation: Any) -> bool:
    """A free-form table (``dict[str, ...]``), possibly optional: its keys are the user's names."""
    if typing.get_origin(annotation) in (dict, Mapping):
        return True
    return any(_is_table_of(a) for a in typing.get_args(annotation) if a is not type(None))


def walk(
    model: type[BaseModel], data: Any, loc: tuple[Any, ...]
) -> tuple[list[str | int], Any, Any]:
    """The key path of a pydantic error as written in ``data`` (pydantic's union and function
    tags left out), the model that holds its last key and that key's field (None when unknown)."""
    path: list[str | int] = []
    holder: Any = model
    field: Any = None
    current: Any = model  # the model the next key belongs to (None inside a free-form table)
    named = False  # the next key is a name of the user's (a free-form table's), not a field
    for i, part in enumerate(loc):
        last = i == len(loc) - 1
        if isinstance(part, int) and isinstance(data, (list, tuple)):
            path.append(part)
            data = data[part] if -len(data) <= part < len(data) else None
            continue
        if (
            isinstance(part, str)
            and isinstance(data, Mapping)
            and (part in data or last or _field(current, part))
        ):
            path.append(part)
            data = data.get(part)
            if named:  # the value under the user's name is of the model found before
                named = False
                continue
            holder, field = current, _field(current, part)
            current = _nested_model(field.annotation) if field is not None else None
            named = field is not None and _is_table_of(field.annotation)
            continue
        # a union member's or a validator's tag: not a key of the file
    return path, holder, field


def dotted(path: list[str | int]) -> str:
    """``a.b[2].c``: a key path as written in TOML (an array's entries by index)."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else f".{part}" if out else str(part)
    return out


def problems_of(model: type[BaseModel], data: Any, err: ValidationError) -> list[Problem]:
    """``err`` in the product's dialect: one :class:`Problem` per key (a union fails once per
    member: the first said), misspelt keys first (a required key it was meant to be is missing
    only for that). Keys are paths as written in ``data``; a check that raised a
    :class:`SettingsError` (a nested adapter's or chiller's) gives its own problems, under
    its key."""
    out: list[Problem] = []
    seen: set[tuple[Any, ...]] = set()
    for e in sorted(err.errors(), key=lambda x: x["type"] != "extra_forbidden"):
        path, holder, field = walk(model, data, tuple(e["loc"]))
        if tuple(path) in seen:
            continue
        seen.add(tuple(path))
        key = dotted(path)
        given = e.get("input", _ABSENT)
        inner = (e.get("ctx") or {}).get("error")
        if isinstance(inner, SettingsError):
            out += [p.under(key) for p in inner.problems]
        elif isinstance(inner, ValidationError):  # a model a check builds (its keys are ours too)
            out += [
                Problem(
                    ".".join(filter(None, [key, dotted(list(x["loc"]))])),
                    f"expected {expected(x)}",
                    x.get("input", _ABSENT),
                )
                for x in inner.errors()
            ]
        elif e["type"] == "extra_forbidden":
            choices = key_names(holder) if holder is not None else []
            near = did_you_mean(str(path[-1]) if path else "", choices)
            text = (
                f"unknown key (did you mean {near!r}?)"
                if near
                else "unknown key; allowed: " + ", ".join(choices)
                if choices
                else "unknown key"
            )
            # a misspelt secret's value is as secret as the one it was meant to be
            out.append(Problem(key, text, _ABSENT if near and names_a_secret(near) else given))
        elif e["type"] == "missing":
            want = expected(e, field)
            out.append(
                Problem(
                    key,
                    "required key missing" + (f"; expected {want}" if want != "a value" else ""),
                )
            )
        elif e["type"] in ("value_error", "assertion_error"):  # our own checks say what is wrong
            text = str(inner) if inner is not None else expected(e)
            # a settings model's field check says what is allowed ("+1 or -1", as the old "must
            # be" messages did); the configuration's checks, and checks across keys, what is wrong
            allowed = field is not None and (
                _allowed_of(field) is not None
                or holder.model_config.get("hide_input_in_errors") is True
            )
            out.append(Problem(key, f"expected {text}" if allowed else text, given))
        else:
            out.append(Problem(key, f"expected {expected(e, field)}", given))
    return out


def describe(label: str, model: type[BaseModel], data: Any, err: ValidationError) -> SettingsError:
    """``err`` as a :class:`SettingsError`: one line per problem, each ``label: key = value:
    what is wrong``."""
    return SettingsError(label, problems_of(model, data, err))


def check_settings(label: str, model: type[BaseModel], options: Mapping[str, Any]) -> BaseModel:
    """``options`` (runtime-only keywords left out) validated by ``model``; one
    :class:`ConfigError` line naming the key, the value and what is allowed when they do not.
    A runtime-only keyword given as plain data (``clock = 1`` in a file) is refused too."""
    for key in sorted(RUNTIME_ONLY & options.keys()):
        # plain data under such a key came from a file or a URL, where it means nothing
        if isinstance(options[key], (str, bytes, int, float, list, tuple, dict)):
            raise SettingsError(
                label,
                [
                    Problem(
                        key,
                        "no configuration option (the running program passes its own)",
                        options[key],
                    )
                ],
            )
    data = {k: v for k, v in options.items() if k not in RUNTIME_ONLY}
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise describe(label, model, data, err) from err


def build(label: str, cls: Any, options: Mapping[str, Any]) -> Any:
    """``cls`` built from ``options``, checked first against ``cls.Settings`` (when the class
    has one). Only the options given reach the constructor, so the backend's and a preset's
    defaults stay in force; runtime-only keywords (clock, rng, ...) pass through unchecked."""
    model = getattr(cls, "Settings", None)
    if model is None:  # a third-party backend without a settings model
        return construct(label, cls, **options)
    checked = check_settings(label, model, options).model_dump(exclude_unset=True)
    runtime = {k: v for k, v in options.items() if k in RUNTIME_ONLY}
    return construct(label, cls, **checked, **runtime)


def construct(label: str, factory: Any, *args: Any, **kw: Any) -> Any:
    """``factory(*args, **kw)``, an option the backend does not know reported as a
    :class:`ConfigError` that names it (a URL or configuration typo), not a ``TypeError``."""
    try:
        return factory(*args, **kw)
    except TypeError as err:
        m = re.search(r"unexpected keyword argument '(\w+)'", str(err))
        if m is None:
            raise
        raise SettingsError(label, [Problem(m.group(1), "unknown key")]) from err


# -- the adapter --------------------------------------------------------------------------


@dataclass(frozen=True)
class RawMeasurement:
    """What a controller's probe cycle left: its sequence counter and value, in its unit."""

    sequence: int
    value: Any
    sigma: Any = None


_NOTHING_MORE = Wants()


class Adapter(Link):
    """A link to one spindle on one controller.

    ``offset_scale`` converts um to the controller's unit (0.001 for mm) and
    ``offset_sign`` flips the sign for controllers whose thermal offset points
    the other way (:attr:`units`). ``speed_scale`` converts the controller's speed unit to
    rpm. Reconnection, back-off and ``on_link_change`` are those of :class:`Link`.

    A backend declares ``Settings`` (its options, an :class:`AdapterSettings`), ``url_options``
    (the options a URL carries) and whether it ``can_read_offset``.
    """

    Settings: ClassVar[type[AdapterSettings] | None] = None
    """The backend's options as a pydantic model (None: a backend that declares none)."""

    can_read_offset: ClassVar[bool] = False
    """Whether :meth:`read_offset_um` reads the offset the controller holds. An instance whose
    configuration names no way to read it (a line protocol without a query) says False."""

    def __init__(
        self,
        *,
        offset_scale: float = 1.0,
        offset_sign: int = 1,
        speed_scale: float = 1.0,
        offset_resolution: float = 0.0,
        **link: Any,
    ):
        self.units = ControllerUnits(float(offset_scale), offset_sign, float(offset_resolution))
        super().__init__(**link)
        self.speed_scale = speed_scale
        self.offset_um_requested: float | None = None
        self._measurement_seq: int | None = None  # the counter last seen; kept across reconnects

    @classmethod
    def url_options(cls, url: str) -> dict[str, Any]:
        """The options ``url`` carries, values as given (query values are strings; ``Settings``
        converts them)."""
        raise NotImplementedError(f"{cls.name} adapter: no URL form")

    @classmethod
    def from_url(cls, url: str, **overrides: Any) -> Adapter:
        """An adapter from its URL (``overrides`` win), checked against ``Settings``."""
        adapter: Adapter = build(f"{cls.name} adapter", cls, {**cls.url_options(url), **overrides})
        return adapter

    @property
    def offset_scale(self) -> float:
        return self.units.scale

    @property
    def offset_sign(self) -> int:
        return self.units.sign

    # -- one cycle: one read, one write ----------------------------------------

    @property
    def capabilities(self) -> Capabilities:
        """What this configured link can read, beside the speed."""
        return Capabilities(
            held_offset=bool(self.can_read_offset),
            cutting=bool(self.can_read_cutting),
            measurement=bool(self.can_read_measurement),
            inputs=tuple(self.input_channels()),
            life_sign=bool(self.writes_life),
        )

    def read(self, wants: Wants = _NOTHING_MORE) -> Reading:
        """This cycle's values, the speed first, then what ``wants`` asks for and the link can
        read. Never raises for a controller's value or a failed request: each becomes a
        :class:`Failure` in its field. Once a request finds the link lost, nothing more is
        asked this cycle (those fields stay None).

        The default calls the per-value methods one after the other, each converting and
        checking its value; a backend that can ask for all in one request overrides it."""
        speed = _guarded(self.read_speed)
        if isinstance(speed, Failure) and speed.link_lost:
            return Reading(speed, reconnects=self.reconnects)
        fields: dict[str, Any] = {}
        if not isinstance(speed, Failure):  # a backend that checks its writes later says so here
            refused = _guarded(self.take_write_mismatch)
            if refused is not None and not isinstance(refused, Failure) and math.isfinite(refused):
                fields["write_refused_um"] = float(refused)
        caps = self.capabilities
        steps: list[tuple[str, bool, Callable[[], Any]]] = [
            ("cutting", wants.cutting and caps.cutting, self.read_cutting),
            ("not_ready_offset_um", True, self._not_ready_checked),
            ("held_offset_um", wants.held_offset and caps.held_offset, self.read_offset_um),
            ("inputs", wants.inputs and bool(caps.inputs), self._read_inputs_checked),
            ("measurement", wants.measurement and caps.measurement, self.read_measurement),
        ]
        for name, wanted, call in steps:
            if not wanted or (
                name == "held_offset_um" and fields.get("not_ready_offset_um") is not None
            ):
                continue  # a controller that is not ready applies its own offset
            value = _guarded(call)
            fields[name] = value
            if isinstance(value, Failure) and value.link_lost:
                break
        return Reading(speed, reconnects=self.reconnects, **fields)

    def write(self, offset_um: float | None, life: Life | None = None) -> WriteResult:
        """Write the thermal offset [um] and the sign of life: taken, or the failure (refused by
        the controller, the link lost, a value that is not finite). ``offset_um`` None confirms
        the offset the controller holds: only the sign of life is written. A link configured
        without a sign of life (:attr:`writes_life` False) ignores ``life``. Never raises for a
        failure of the link.

        The offset goes whatever happens to the sign of life: a counter or flag the controller
        refuses or does not have is :attr:`WriteResult.life_failure`, the offset taken. A lost
        link is :attr:`WriteResult.failure`, whatever the write carried."""
        life = life if self.writes_life else None
        if offset_um is None and life is None:
            return WriteResult()
        life_failure: list[Failure | None] = []
        done = _guarded(lambda: life_failure.append(self._write_checked(offset_um, life)))
        if isinstance(done, Failure):
            if offset_um is None and not done.link_lost and self._sending:
                return WriteResult(life_failure=done)  # a confirmation: only the life was sent
            return WriteResult(done)
        return WriteResult(
            pending=offset_um is not None and self._write_pending(), life_failure=life_failure[0]
        )

    _sending = False
    """Whether the write under way got past its checks (a value refused before anything is
    sent is the write's failure, not the sign of life's)."""

    _offset_sent_alone = False
    """Whether the write under way sent the offset in a request of its own (a backend sets it
    before that request): its failure is the offset's, and the offset is not sent again."""

    def _write_checked(self, offset_um: float | None, life: Life | None) -> Failure | None:
        """The one path of every write: the offset checked and converted, then the backend's
        :meth:`_write_raw`; the sign of life's failure, the offset taken. A request that carried
        both and failed (not a lost link) is followed by the offset alone: one more request,
        only then, so that a refused counter or flag never keeps the offset from the control."""
        raw = None
        self._sending = False
        if life is not None:
            life = checked_life(self.name, life)
        if offset_um is not None:
            if (
                isinstance(offset_um, bool)
                or not isinstance(offset_um, (int, float))
                or not math.isfinite(offset_um)
            ):
                raise BadValueError(f"{self.name}: refusing to write offset {offset_um!r}")
            raw = self.units.to_controller(offset_um)
            log.debug("%s: write offset %.4f um (raw %r)", self.name, offset_um, raw)
        self.open()
        if offset_um is not None:
            self.offset_um_requested = float(offset_um)
        self._sending = True
        self._offset_sent_alone = False
        if raw is None or life is None:
            return self._write_raw(raw, life)
        try:
            return self._write_raw(raw, life)
        except _LINK_FAILURES as err:
            failure = Failure.of(err)
            if failure.link_lost or self._offset_sent_alone:
                raise  # the offset's own failure: no other request would tell more
        log.info("%s: %s; writing the offset alone", self.name, failure.reason)
        self._write_raw(raw, None)  # its failure is the offset's own
        return failure

    writes_life: bool = False
    """Whether this configured link writes a sign of life (a life counter and a "compensation
    valid" flag) with the offset. A backend sets it from its settings; default False."""

    def _write_raw(self, raw: float | None, life: Life | None) -> Failure | None:
        """Backend hook: write the offset (in the controller's unit; None: leave it) and the
        sign of life (None: none this time). The offset goes first, and a refused offset sends
        no sign of life: it raises. Returns the sign of life's failure when the offset was
        taken (:meth:`_life_part`); a request that carried both may also raise, and the offset
        is then written alone. A backend that can put both into one request whose values are
        taken all or none overrides this; the default writes the offset, then the life sign."""
        if raw is not None:
            self._offset_sent_alone = True
            self._write_offset_raw(raw)
        if life is None:
            return None
        return self._life_part(lambda: self._write_life_raw(life))

    def _life_part(self, call: Callable[[], Any]) -> Failure | None:
        """Send the sign of life's part of a write (the offset's is done): its failure, or
        None. A lost link is raised: the write's failure."""
        try:
            call()
        except _LINK_FAILURES as err:
            failure = Failure.of(err)
            if failure.link_lost:
                raise
            return failure
        return None

    def life_problems(self) -> list[str]:
        """The sign of life's variables looked up where the link can do so without writing
        (``thermocomp run --check``): one line per problem, naming the variable and the option
        to change. Empty: found, or a link that cannot look them up (they are seen at the
        first write). A lost link raises."""
        return []

    def _write_life_raw(self, life: Life) -> None:
        """Backend hook: write the life counter and the valid flag."""
        raise AdapterError(f"{self.name}: this link writes no sign of life")

    def _write_pending(self) -> bool:
        """Whether the last write is checked with the next reading (a deferred check)."""
        return False

    def _not_ready_checked(self) -> float | None:
        """:meth:`not_ready_offset_um`, a value that is not a finite number refused."""
        um = self.not_ready_offset_um()
        if um is None:
            return None
        value = _finite(um)
        if value is None:
            raise BadValueError(
                f"{self.name}: the offset applied while not ready {short(um)} is not a number"
            )
        return value

    def _read_inputs_checked(self) -> dict[str, float | Failure]:
        """The input channels by name, each a finite number or the failure of its value."""
        self.open()
        return self._inputs_of(self._read_inputs_raw())

    def _inputs_of(self, raw: Mapping[Any, Any]) -> dict[str, float | Failure]:
        """Raw input values by name, each as a finite number or the failure of its value (an
        exception in a value's place is that value's failure)."""
        out: dict[str, float | Failure] = {}
        for name, value in raw.items():
            if isinstance(value, BaseException):
                out[str(name)] = Failure.of(value)
                continue
            number = _finite(value)
            out[str(name)] = (
                number
                if number is not None
                else Failure.of(
                    BadValueError(
                        f"{self.name}: input {name} is {short(value)}, not a finite number"
                    )
                )
            )
        return out

    # -- template methods ------------------------------------------------------

    def read_speed(self) -> float:
        """Actual spindle speed [rpm], as a magnitude (reverse rotation heats alike);
        :class:`BadValueError` when not a finite number. The one check of every backend's speed."""
        self.open()
        return self._speed_of(self._read_speed_raw())

    def _speed_of(self, raw: Any) -> float:
        """A raw speed in rpm, as a magnitude; :class:`BadValueError` for anything that is not
        a finite number (a boolean, a string that is no number, an overflow, NaN)."""
        if isinstance(raw, bool):
            raise BadValueError(f"{self.name}: speed {short(raw)} is not a number")
        try:
            rpm = abs(float(raw) * self.speed_scale)
        except (TypeError, ValueError, OverflowError) as err:
            raise BadValueError(f"{self.name}: speed {short(raw)} is not a number") from err
        if not math.isfinite(rpm):
            raise BadValueError(f"{self.name}: speed is {rpm}")
        return rpm

    def read_offset_um(self) -> float:
        """The offset [um] the controller holds now, read back from it (not what was last
        written): :class:`BadValueError` when it is not a finite number, :class:`AdapterError`
        from a link that cannot read it (:attr:`can_read_offset` False)."""
        if not self.can_read_offset:
            raise AdapterError(
                f"{self.name}: this link cannot read back the offset the "
                "controller holds (can_read_offset is false)"
            )
        self.open()
        return self._offset_of(self._read_offset_raw())

    def _offset_of(self, raw: Any) -> float:
        """A raw offset the controller holds, in um; :class:`BadValueError` for anything that
        is not a finite number."""
        if isinstance(raw, bool) or not isinstance(raw, numbers.Real):
            raise BadValueError(
                f"{self.name}: the controller's offset {short(raw)} is not a number"
            )
        value = _finite(raw)
        if value is None:
            raise BadValueError(f"{self.name}: the controller's offset is {short(raw)}")
        um = self.units.to_um(value)
        if not math.isfinite(um):  # a huge value in a small unit
            raise BadValueError(
                f"{self.name}: the controller's offset {short(raw)} is out of range"
            )
        return um

    def write_offset_um(self, offset_um: float) -> None:
        """Write the thermal offset [um] alone; a non-finite value never leaves this method."""
        if offset_um is None:
            raise BadValueError(f"{self.name}: refusing to write offset None")
        self._write_checked(offset_um, None)

    def take_write_mismatch(self) -> float | None:
        """For a third-party backend that checks writes later through ``_take_mismatch_raw``:
        the offset [um] the controller holds when it did not take the last write, reported once;
        None when all is well. The built-in backends report a deferred check in
        :attr:`Reading.write_refused_um` instead (:meth:`read`)."""
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
            except (TypeError, ValueError, OverflowError):
                out[name] = math.nan
        return out

    def _read_inputs_raw(self) -> dict[str, Any]:
        raise AdapterError(f"{self.name}: this adapter reads no input channels")

    can_read_measurement: ClassVar[bool] = False
    """Whether this backend can take tool-setter or probe measurements from the controller
    (:meth:`read_measurement`). An instance configured without a measurement source says False."""

    measurement_scale: float | None = None
    """Controller unit per um of a measurement when it is not the offset's (a probe cycle that
    hands over um while the offset is in mm); None: the offset's ``offset_scale``."""

    def read_measurement(self) -> Measurement | None:
        """A new measurement of the elongation written by the controller's probe cycle, or None.

        The handshake: the cycle writes the value, then changes a sequence counter; a value is
        returned once, when the counter differs from the one seen before. The counter found at
        the adapter's first read is taken as seen: a value left from before is stale; a counter
        that changed while the link was down is new. The value is in the controller's length
        unit (the offset's ``offset_scale``, or ``measurement_scale``), positive when the tool
        grew toward the workpiece. :class:`BadValueError` for a value that is not
        a finite number (the counter is then taken as seen, so it is refused once)."""
        if not self.can_read_measurement:
            return None
        self.open()
        return self._measurement_of(self._read_measurement_raw())

    def _measurement_of(self, raw: RawMeasurement | None) -> Measurement | None:
        """The handshake of :meth:`read_measurement` on what the controller holds now: a new
        counter gives its value (in um) once; :class:`BadValueError` for a value or sigma that
        is not a finite number (the counter is then taken as seen, so it is refused once)."""
        if raw is None:
            return None
        seq = whole_sequence(self.name, raw.sequence)
        last = self._measurement_seq
        self._measurement_seq = seq
        if last is None or seq == last:
            return None
        scale = self.measurement_scale or self.units.scale
        value = _finite(raw.value)
        elongation_um = None if value is None else value / scale
        if elongation_um is None or not math.isfinite(elongation_um):
            raise BadValueError(
                f"{self.name}: measurement {short(raw.value)} (sequence {seq}) is "
                "not a finite number"
            )
        sigma_um = None
        if raw.sigma is not None:
            spread = _finite(raw.sigma)  # a string, a boolean, an array: no sigma, refused
            sigma_um = math.nan if spread is None else abs(spread / scale)
            if not (math.isfinite(sigma_um) and sigma_um > 0):
                raise BadValueError(
                    f"{self.name}: measurement sigma {short(raw.sigma)} (sequence "
                    f"{seq}) is not a positive number"
                )
        return Measurement(elongation_um, sigma_um, seq, self.name)

    def _read_measurement_raw(self) -> RawMeasurement | None:
        """Backend hook: the controller's (sequence, value[, sigma]) as they stand now, in its
        unit, or None when it holds none."""
        raise AdapterError(f"{self.name}: this adapter takes no measurements")

    can_read_cutting: ClassVar[bool] = False
    """Whether this link reads the controller's own cutting signal (:meth:`read_cutting`). An
    instance configured without one says False: the runtime then infers it from the speed."""

    cutting_values: tuple[Any, ...] = (True,)
    """The raw values of the cutting signal that mean "cutting": ``True`` for a bit (an at-speed
    bit, a feed-active flag, or a 0/1 number), ``(False,)`` for an inverted one (feed hold), the
    codes of an enumeration (a program or motion state) otherwise."""

    def read_cutting(self) -> bool | None:
        """Whether the controller says the tool may be in the part now (the spindle at speed and
        feeding), or None where this link has no such signal. :class:`BadValueError` for a value
        that is neither a boolean nor a whole number."""
        if not self.can_read_cutting:
            return None
        self.open()
        return cutting_of(self.name, self._read_cutting_raw(), self.cutting_values)

    def _read_cutting_raw(self) -> Any:
        """Backend hook: the controller's cutting signal as it stands now (raw)."""
        raise AdapterError(f"{self.name}: this adapter reads no cutting signal")

    def not_ready_offset_um(self) -> float | None:
        """For controllers whose offset depends on the machine state (LinuxCNC zeroes external
        offsets at machine-on and ignores them until homed): the offset [um] it applies while
        not ready to take ours; None when it is ready."""
        return None

    # -- backend hooks ----------------------------------------------------------

    @abstractmethod
    def _read_speed_raw(self) -> Any: ...

    def _read_offset_raw(self) -> Any:
        """The offset the controller holds, in its unit; backends that can read it override
        this and set ``can_read_offset``."""
        raise AdapterError(f"{self.name}: this link cannot read back the offset")

    @abstractmethod
    def _write_offset_raw(self, value: float) -> None: ...


def checked_life(name: str, life: Any) -> Life:
    """``life`` as it may leave for the controller: a :class:`Life` whose counter is a whole
    number 0 .. :data:`~cnc_adapters.reading.LIFE_MODULUS` (it fits a signed 16-bit word) and
    whose flag is a bool; :class:`BadValueError` otherwise, before anything is sent."""
    counter = getattr(life, "counter", None)
    valid = getattr(life, "valid", None)
    if (
        not isinstance(life, Life)
        or type(counter) is not int
        or not 0 <= counter <= LIFE_MODULUS
        or type(valid) is not bool
    ):
        raise BadValueError(f"{name}: refusing to write the sign of life {short(life)}")
    return life


def _either(keys: tuple[str, ...]) -> str:
    """``life_node (or life_path)``: the keys that name one variable."""
    return keys[0] + "".join(f" (or {k})" for k in keys[1:])


def life_pair_refusal(counter_key: str, flag_key: str) -> str:
    """The one line for a sign of life given by half."""
    return (
        f"the sign of life needs both {counter_key} and {flag_key}, or neither "
        f'({counter_key.split()[0]} = "" and {flag_key.split()[0]} = "" turn a profile\'s or '
        "preset's default off)"
    )


def life_configured(counter: Any, flag: Any, counter_key: str, flag_key: str) -> bool:
    """Whether a link's settings name a sign of life: both the counter's and the flag's address
    (True), or neither (False; None or ``""``, which turns a preset's or profile's default off).
    One alone is a ValueError naming both keys."""
    has_counter = counter is not None and counter != ""
    has_flag = flag is not None and flag != ""
    if has_counter != has_flag:
        raise ValueError(life_pair_refusal(counter_key, flag_key))
    return has_counter


def _finite(raw: Any) -> float | None:
    """``raw`` as a finite float, or None (a boolean, a string, an array, an overflow, NaN)."""
    if isinstance(raw, bool) or not isinstance(raw, numbers.Real):
        return None
    try:
        value = float(raw)
    except (OverflowError, ValueError, TypeError):
        return None
    return value if math.isfinite(value) else None


_LINK_FAILURES = (
    AdapterError,
    TypeError,
    ValueError,
    ArithmeticError,
    IndexError,  # a reply shorter than its format
    struct.error,  # bytes that do not unpack
)
"""What a link's call may raise for a failure of the link or of a controller's value."""


def _guarded(call: Callable[[], Any]) -> Any:
    """``call()``, or the :class:`Failure` it raised: a link's error, or a conversion that a
    controller's value made fail (a TypeError, ValueError, OverflowError, a short reply's
    IndexError or struct.error ...). Anything else is a fault of this program and is raised."""
    try:
        return call()
    except _LINK_FAILURES as err:
        return Failure.of(err)


def cutting_of(name: str, raw: Any, values: tuple[Any, ...]) -> bool:
    """A raw cutting signal as a bool: True when it is one of ``values``. A configured boolean
    matches the signal's truth (a bit, or a 0/1 number), a configured number its whole value (a
    state code; a boolean signal counts as 0 or 1)."""
    number = _finite(raw)
    if isinstance(raw, bool) or (number is not None and number.is_integer()):
        code = int(raw)
        return any((v == (code != 0)) if isinstance(v, bool) else v == code for v in values)
    raise BadValueError(
        f"{name}: cutting signal {short(raw)} is neither a boolean nor a whole number"
    )


def cutting_values_of(v: Any) -> tuple[Any, ...]:
    """Configured cutting values: a list of booleans or whole numbers (``"2,3"`` in a URL,
    ``"false"`` for an inverted bit)."""
    items = v.split(",") if isinstance(v, str) else v if isinstance(v, (list, tuple)) else [v]
    out: list[Any] = []
    for item in items:
        if isinstance(item, str):
            word = item.strip().lower()
            item = {"true": True, "false": False}.get(word, word)
            if isinstance(item, str):
                try:
                    item = int(item)
                except ValueError:
                    raise ValueError("booleans or whole numbers ('true', 'false', '2,3')") from None
        if not isinstance(item, (bool, int)):
            raise ValueError("booleans or whole numbers ('true', 'false', '2,3')")
        out.append(item)
    if not out:
        raise ValueError("at least one value")
    return tuple(out)


CuttingValues = Annotated[
    tuple[bool | int, ...],
    BeforeValidator(cutting_values_of),
    Allowed("booleans or whole numbers (true, false, [2, 3], '2,3' in a URL)"),
]


def whole_sequence(name: str, raw: Any) -> int:
    """A measurement's sequence counter as an int (an analog output or a register may hold it as
    a float); :class:`BadValueError` when it is not a whole number."""
    number = _finite(raw)
    if isinstance(raw, bool) or number is None or not number.is_integer():
        raise BadValueError(f"{name}: measurement sequence {short(raw)} is not a whole number")
    return int(raw)


def read_handshake(
    name: str,
    sequence: Callable[[], Any],
    value: Callable[[], Any],
    sigma: Callable[[], Any] | None = None,
) -> RawMeasurement | None:
    """The counter, the value (and sigma), then the counter again, for controllers where each
    is its own request. The cycle writes the value before it changes the counter, so the value
    read is never older than the counter; None when the counter moved in between (the cycle
    was writing: the next read takes that value with its own counter)."""
    first = sequence()
    got = value()
    spread = sigma() if sigma is not None else None
    if sequence() != first:
        return None
    return RawMeasurement(whole_sequence(name, first), got, spread)


def query_params(url: str) -> dict[str, str]:
    """A URL's query; an empty value is kept (``life_node=`` turns a preset's default off)."""
    return dict(parse_qsl(urlsplit(url).query, keep_blank_values=True))


def host_options(label: str, url: str) -> dict[str, Any]:
    """``scheme://host:port?key=value``: the host, the port (when the URL names one) and the
    query; ConfigError naming ``label`` for a port that is not a number 1..65535."""
    parts = urlsplit(url)
    try:
        port = parts.port
    except ValueError as err:
        raise ConfigError(f"{label}: the URL's port is no number 1..65535: {err}") from err
    out: dict[str, Any] = dict(query_params(url))
    if parts.hostname:
        out["host"] = parts.hostname
    if port is not None:
        out["port"] = port
    return out


def serial_options(url: str) -> dict[str, Any]:
    """``serial:///dev/ttyUSB0?protocol=haas&baudrate=9600``: the port and the query (the
    protocol picks the backend, so it is no option of it)."""
    return {
        "port": urlsplit(url).path,
        **{k: v for k, v in query_params(url).items() if k != "protocol"},
    }


INT_PARAMS = frozenset(
    {
        "baudrate",
        "device_id",
        "speed_register",
        "offset_register",
        "offset_sign",
        "speed_var",
        "offset_var",
        "r_parameter",
    }
)
FLOAT_PARAMS = frozenset({"timeout_s", "offset_scale", "speed_scale", "time_scale"})


def typed_params(
    url: str,
    drop: tuple[str, ...] = ("protocol",),
    ints: frozenset[str] = INT_PARAMS,
    floats: frozenset[str] = FLOAT_PARAMS,
) -> dict[str, Any]:
    """URL query parameters as constructor keywords, the ``ints`` and ``floats`` converted (for
    backends without a ``Settings`` model; built-in ones let it convert)."""
    out: dict[str, Any] = {}
    for k, v in query_params(url).items():
        if k in drop:
            continue
        try:
            out[k] = int(v) if k in ints else float(v) if k in floats else v
        except ValueError as err:
            raise AdapterError(f"URL parameter {k}={v!r} is not a number") from err
    return out
