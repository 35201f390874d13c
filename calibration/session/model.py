"""The wizard's session: what ``<workdir>/<machine>/<spindle>/session.json`` holds, typed.

A session fills in step by step, so every field but the format may be missing: a session cut
short after its first answers is still a session. The file is private (``0600``): it keeps the
controller and sensor links as typed, which may carry credentials.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any, Final, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from compensator.errors import ConfigError, clip
from compensator.io import atomic_write, read_text

from ..nc_programs import DIALECTS, EXTENSIONS

SESSION_FORMAT: Final = "thermocomp.wizard/1"
SCHEMA_VERSION: Final = 1
"""The session's layout; files written before it was recorded are version 1."""
RUNS = ("calibration", "validation")
SOURCES = ("sensor", "tool-setter", "import")
"""Where the displacement comes from: an eddy-current sensor read live, the machine's tool setter
(the program stops for it every few minutes; the controller link reads its measurement), or a
DAQ file recorded beside the controller."""
LIVE = ("sensor", "tool-setter")
"""The sources the wizard records itself."""

Source = Literal["sensor", "tool-setter", "import"]

ID_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
"""A machine or spindle id (and no ``..`` in it): it names a directory and files, so nothing
that could leave the work directory or trouble a shell (``/``, ``\\``, NUL, spaces, ...)."""

_FROZEN = ConfigDict(frozen=True, extra="forbid")

FLAGGED = frozenset(
    {"max_rpm", "rate_s", "dialect", "step_min", "cooldown_min", "time_scale", "source"}
)
"""Answers given as the wizard's flag of the same name (``step_min``: ``--step-min``)."""


class RunRecord(BaseModel):
    """One run of the session: its log, and what its recording or import found."""

    model_config = _FROZEN

    log: str
    complete: bool = False
    rows: int | None = Field(default=None, ge=0)
    flagged: dict[str, int] | None = None
    """Samples flagged by the recorder, by problem name."""
    events: list[str] | None = None
    inputs: list[str] | None = None
    """The controller's own channels logged beside."""
    measurements: int | None = Field(default=None, ge=0)
    """Tool-setter measurements in the log (the tool-setter route)."""
    imported_from: str | None = None


class ProbePlanRecord(BaseModel):
    """The tool-setter route's probe interval as planned (``calibration.toolsetter_plan``)."""

    model_config = _FROZEN

    interval_s: float
    planned_interval_s: float
    dwell_s: float
    touches: int = 1
    bound: str
    fastest_tau_s: float | None = None
    tau_assumed: bool


class Saved(BaseModel):
    """What the last save wrote."""

    model_config = _FROZEN

    model: str
    report: str
    config: str
    version: str
    at_utc: str


class WizardSession(BaseModel):
    """Every answer and every result of one spindle's calibration session."""

    model_config = _FROZEN

    format: Literal["thermocomp.wizard/1"] = SESSION_FORMAT
    schema_version: Literal[1] = SCHEMA_VERSION
    updated_utc: str | None = None
    # 1 identify
    machine_id: str | None = None
    spindle_id: str | None = None
    time_anchor_s: float | None = None
    """The session's start on the wall clock: a faster (virtual) clock reads the same in a
    resumed process."""
    time_scale: float | None = Field(default=None, gt=0)
    max_rpm: float | None = Field(default=None, ge=100, le=200_000)
    source: Source | None = None
    controller: str | None = None
    sensor: str | None = None
    rate_s: float | None = Field(default=None, gt=0)
    # 2 program
    dialect: str | None = None
    step_min: float | None = Field(default=None, gt=0)
    cooldown_min: float | None = Field(default=None, ge=0)
    validation: bool | None = None
    validation_seed: int | None = None
    probe_spindle: Literal["stop", "keep"] | None = None
    probe_touches: int | None = Field(default=None, ge=1)
    probe_dwell_s: float | None = Field(default=None, ge=0, le=3600)
    probe_touch_s: float | None = Field(default=None, ge=0)
    probe_every_min: float | None = Field(default=None, ge=1, le=240)
    probe_every_s: float | None = Field(default=None, gt=0)
    probe_plan: ProbePlanRecord | None = None
    rest_h: float | None = Field(default=None, ge=0)
    programs: dict[str, str] | None = None
    # 3 record, 5 save
    runs: dict[str, RunRecord] | None = None
    saved: Saved | None = None

    @field_validator(
        "time_anchor_s",
        "time_scale",
        "max_rpm",
        "rate_s",
        "step_min",
        "cooldown_min",
        "probe_dwell_s",
        "probe_touch_s",
        "probe_every_min",
        "probe_every_s",
        "rest_h",
    )
    @classmethod
    def _finite(cls, v: float | None) -> float | None:
        if v is not None and not math.isfinite(v):
            raise ValueError("not a finite number")
        return v

    @field_validator("dialect")
    @classmethod
    def _dialect(cls, v: str | None) -> str | None:
        if v is not None and v not in DIALECTS:
            raise ValueError(f"{v!r}: choose from {', '.join(DIALECTS)}")
        return v

    @field_validator("machine_id", "spindle_id")
    @classmethod
    def _id(cls, v: str | None) -> str | None:
        if v is not None and (not ID_PATTERN.fullmatch(v) or ".." in v):
            raise ValueError(f"{clip(repr(v), 80)}: not an id")
        return v

    def get(self, key: str) -> Any:
        """The answer for ``key`` (None: not given yet)."""
        return getattr(self, key, None)

    def updated(self, **changes: Any) -> WizardSession:
        """A new session with ``changes``, checked as a loaded file is: a ConfigError in one line
        naming the flag of a value it refuses."""
        data = self.model_dump(exclude_none=True)
        data.update(changes)
        return _checked(data, None)

    def with_run(self, name: str, **changes: Any) -> WizardSession:
        """A new session with run ``name``'s record changed (the run must exist)."""
        runs = dict(self.runs or {})
        runs[name] = runs[name].model_copy(update=changes)
        return self.updated(runs={k: r.model_dump(exclude_none=True) for k, r in runs.items()})

    def run(self, name: str) -> RunRecord | None:
        return (self.runs or {}).get(name)

    def as_dict(self) -> dict[str, Any]:
        """The session as its file holds it (what the report and the configuration writer read)."""
        data = self.model_dump(mode="json", exclude_none=True)
        # the keys in the order a session file has always had them
        return {"format": data.pop("format"), **data}


def _checked(data: Any, path: str | None) -> WizardSession:
    """``data`` as a session; a one-line ConfigError naming the file (``path``) or, for a value
    just given, its flag."""
    try:
        return WizardSession.model_validate(data)
    except ValidationError as err:
        first = err.errors()[0]
        at = ".".join(str(p) for p in first["loc"]) or "the session"
        why = clip(first["msg"], 200)
        if path is None:
            flag = "--" + at.replace("_", "-") if at in FLAGGED else at
            raise ConfigError(f"{flag} {clip(repr(first.get('input')), 80)}: {why}") from err
        raise ConfigError(
            f"{path}: not a wizard session: {at}: {why} ({err.error_count()} problem(s))"
        ) from err


def load_session(path: Path) -> WizardSession:
    """The session in ``path``; a ConfigError in one line for a file that is not one."""
    try:
        data = json.loads(read_text(path))
    except ValueError as err:
        raise ConfigError(f"{path}: not a wizard session: {err}") from err
    if not isinstance(data, dict) or data.get("format") != SESSION_FORMAT:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ConfigError(f"{path}: not a wizard session ({got!r})")
    return _checked(data, str(path))


def write_session(path: Path, session: WizardSession, now_utc: str) -> WizardSession:
    """Write ``session`` stamped ``now_utc`` to ``path`` (atomically, private); the stamped one."""
    stamped = session.model_copy(update={"updated_utc": now_utc})
    # private: it keeps the controller and sensor links as typed, which may carry credentials
    with atomic_write(path, mode=0o600) as fh:
        json.dump(stamped.as_dict(), fh, indent=2)
    return stamped


def check_id(value: Any, flag: str) -> str:
    """``value`` as an id (surrounding blanks dropped), or a one-line ConfigError naming it."""
    text = str(value).strip()
    if not ID_PATTERN.fullmatch(text) or ".." in text:
        raise ConfigError(
            f"{flag} {clip(repr(text), 80)}: an id names files, so 1 to 64 of A-Z a-z 0-9 "
            "'_' '.' '-', starting with a letter or digit, without '..'"
        )
    return text


def inside(root: Path, path: str | Path, what: str) -> Path:
    """``path`` resolved, if it stays inside ``root`` (a resolved directory); else a ConfigError.
    The session file is editable: every path read from it is checked before use."""
    try:
        resolved = Path(path).resolve()
    except (OSError, ValueError) as err:  # a NUL byte, a symlink loop
        raise ConfigError(
            f"{what} {clip(repr(str(path)), 200)}: not a usable path ({err})"
        ) from err
    if not resolved.is_relative_to(root):
        raise ConfigError(f"{what} {clip(str(resolved), 200)} is outside the work directory {root}")
    return resolved


def set_aside(directory: Path, session: WizardSession, now_utc: str) -> Path:
    """A new session in ``directory``: the earlier one's answers, run logs, programs and plot move
    to ``earlier/<when it was last updated>/`` (returned); models, reports and configurations
    stay."""
    import shutil

    stamp = re.sub(r"[^0-9A-Za-z]", "", str(session.updated_utc or now_utc))[:15] or "session"
    aside = directory / "earlier" / stamp
    k = 2
    while aside.exists():
        aside, k = directory / "earlier" / f"{stamp}-{k}", k + 1
    moved = [
        p
        for p in (
            directory / "session.json",
            directory / "runs",
            directory / "fit.png",
            *(directory / f"{r}{ext}" for r in RUNS for ext in set(EXTENSIONS.values())),
        )
        if p.exists()
    ]
    aside.mkdir(parents=True)
    for p in moved:
        shutil.move(str(p), str(aside / p.name))
    return aside
