"""Runtime configuration: TOML validated by pydantic (``extra="forbid"``).

See ``examples/machine.toml`` for an annotated example.
"""

from __future__ import annotations

import os
import re
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field, ValidationError, field_validator, model_validator

from cnc_adapters.base import Problem, SettingsError, problem_lines, problems_of
from cnc_adapters.chiller import check_chiller
from compensator.cooling_law import CoolingLaw, PidGains
from compensator.errors import ConfigError
from compensator.io.atomic import read_regular, read_text
from compensator.io.journal import spindle_name_problem

from .spindle_settings import (
    FROZEN,
    DriftSettings,
    FaultPolicy,
    LearningSettings,
    ObserverSettings,
    SpindleConfig,
    spindle_scope,
)

__all__ = [
    "DriftSettings",
    "FaultPolicy",
    "LearningSettings",
    "ObserverSettings",
    "SpindleConfig",
    "spindle_scope",
]


class CoolingConfig(BaseModel):
    """``[cooling]``: drive the chiller's set point to hold the thermal error at RITE (paper 000).

    ``mode``: ``off``; ``cooling`` (the chiller only: no offset is written); ``both`` (the offset
    cancels what the cooling leaves). The estimate is the spindle's own: its model, with its
    inputs or fused with probes, whatever the spindle runs."""

    model_config = FROZEN
    mode: Literal["off", "cooling", "both"] = "off"
    spindle: str | None = Field(
        None, description="whose estimate drives the chiller; default the only spindle"
    )
    chiller: dict[str, Any] = Field(
        default_factory=dict, description="a 'type' key (modbus, opcua, virtual) and its options"
    )
    rite_um: float | None = Field(
        None,
        description="the thermal error to hold [um]; "
        "`thermocomp cooling rite` suggests one from a journal",
    )
    preheat_c: float = Field(description="constant set point in preheat and after a fault [degC]")
    min_c: float = 10.0
    max_c: float = 30.0
    dew_point_c: float | None = Field(
        None,
        description="the shop's design dew point [degC]: the set point stays dew_margin_k above it",
    )
    dew_margin_k: float = Field(2.0, ge=0, le=20)
    rate_k_per_min: float = Field(1.0, gt=0, le=60)
    resolution_c: float = Field(0.1, ge=0, le=5)
    gains: PidGains = Field(default_factory=PidGains.paper)
    derivative_filter_s: float = Field(10.0, ge=0, le=3600)
    start: Literal["rite", "immediate"] = "rite"
    idle_release_s: float = Field(1800.0, gt=0, le=7 * 86400)
    hold_s: float = Field(
        300.0,
        ge=0,
        le=86400,
        description="chiller or estimate lost: hold the last "
        "set point this long, then go to preheat_c",
    )
    period_s: float = Field(1.0, ge=0.1, le=600)
    refresh_s: float = Field(
        60.0,
        gt=0,
        le=3600,
        description="write the set point again this often "
        "even unchanged (a chiller that restarted forgets it)",
    )

    @model_validator(mode="after")
    def _valid(self) -> CoolingConfig:
        if self.mode == "off":
            return self
        if self.rite_um is None:
            raise ValueError("cooling needs rite_um (thermocomp cooling rite suggests one)")
        if not isinstance(self.chiller.get("type"), str):
            raise ValueError("cooling.chiller needs a 'type' (modbus, opcua, virtual)")
        try:
            check_chiller(self.chiller["type"], self.chiller_options)
        except SettingsError as err:  # its keys, as written: under chiller
            raise err.under("chiller") from None
        self.law()  # the limits agree
        return self

    @property
    def chiller_options(self) -> dict[str, Any]:
        """The chiller's options without its ``type``."""
        return {k: v for k, v in self.chiller.items() if k != "type"}

    def law(self) -> CoolingLaw:
        """The law these settings describe (the fields both share, by name)."""
        shared = self.model_dump(include=set(CoolingLaw.model_fields))
        if shared.get("rite_um") is None:
            shared["rite_um"] = 0.0  # mode off: never stepped
        try:
            return CoolingLaw(**shared)
        except ValidationError as err:
            raise ValueError(
                str(err.errors()[0].get("ctx", {}).get("error", err.errors()[0]["msg"]))
            ) from err


MAX_HISTORY_POINTS = 20_000
"""Points of history per spindle at most (a week at 30 s): memory and /history stay small."""


class StatusConfig(BaseModel):
    """``[status]``: the read-only HTTP endpoint (``/``, ``/status``, ``/history``, ``/metrics``).

    Bound to loopback by default. ``access = "token"`` asks every request for the token
    (``Authorization: Bearer <token>`` or ``?token=``), read from ``token_file`` or the
    environment variable ``THERMOCOMP_STATUS_TOKEN``; never from this file."""

    model_config = FROZEN

    enabled: bool = True
    bind: str = Field(
        "127.0.0.1",
        min_length=1,
        max_length=255,
        description="address to listen on; 0.0.0.0 or :: for every interface",
    )
    port: int = Field(
        9740,
        ge=0,
        le=65535,
        description="TCP port; 0: any free one (the URL goes to <state_dir>/status.url)",
    )
    access: Literal["open", "token"] = "open"
    token_file: Path | None = Field(None, description="with access = token: the file holding it")
    history_h: float = Field(
        6.0,
        gt=0,
        le=168,
        description="hours of history kept for /history (the page plots up to 6 h of it)",
    )
    history_every_s: float = Field(
        10.0,
        ge=1,
        le=3600,
        description="one history point per this many "
        "seconds per spindle (the last values; alarms of the whole interval)",
    )

    @model_validator(mode="after")
    def _valid(self) -> StatusConfig:
        if self.history_h * 3600.0 / self.history_every_s > MAX_HISTORY_POINTS:
            raise ValueError(
                f"status: history_h / history_every_s keeps more than {MAX_HISTORY_POINTS} "
                "points per spindle; raise history_every_s"
            )
        if self.token_file is not None and self.access != "token":
            raise ValueError('status.token_file is set but status.access is not "token"')
        return self

    def token(self) -> str | None:
        """The token requests must carry, or None (open access); ConfigError if it is missing."""
        if self.access == "open":
            return None
        if self.token_file is not None:
            tok = read_secret_file(self.token_file, "status.token_file")
        else:
            tok = os.environ.get("THERMOCOMP_STATUS_TOKEN", "").strip()
        if len(tok) < 16:
            raise ConfigError(
                'status.access = "token": the token (token_file or '
                "THERMOCOMP_STATUS_TOKEN) must be at least 16 characters"
            )
        return tok


MAX_CONFIG_BYTES = 1 << 20
"""A configuration, token or password file larger than this is not one."""


def read_secret_file(path: Path, key: str) -> str:
    """A token or password kept in a file, stripped; ConfigError (naming the file, never its
    content) when it cannot be read, is not a regular file, or is not UTF-8 text."""
    try:
        return read_text(path, MAX_CONFIG_BYTES).strip()
    except ConfigError as err:
        raise ConfigError(f"{key} {err}") from None


class MqttConfig(BaseModel):
    """``[mqtt]``: publish the status to a broker (paho-mqtt). JSON payloads, retained: the
    service's on ``<topic>/status`` and each spindle's on ``<topic>/spindle/<name>``;
    ``<topic>/availability`` is ``online`` while the service runs and ``offline`` once it stops
    or is lost (the broker's last will). A broker that is down never stops compensation."""

    model_config = FROZEN

    enabled: bool = True
    host: str = Field(min_length=1, max_length=255)
    port: int = Field(1883, ge=1, le=65535)
    topic: str = Field(
        "thermocomp",
        min_length=1,
        max_length=200,
        pattern=r"^[^#+\x00]+$",
        description="topic prefix (no wildcards)",
    )
    client_id: str | None = Field(
        None, max_length=200, description="default: thermocomp-<host name>"
    )
    publish_every_s: float = Field(10.0, gt=0, le=3600)
    keepalive_s: int = Field(
        30,
        ge=5,
        le=3600,
        description="the broker declares the service lost "
        "(and publishes the last will) after 1.5 times this without a word",
    )
    qos: Literal[0, 1] = 1
    username: str | None = Field(None, max_length=200)
    password_file: Path | None = Field(None, description="or THERMOCOMP_MQTT_PASSWORD; never here")
    tls: bool = False
    ca_file: Path | None = Field(
        None, description="with tls: the broker's CA (default: the system's)"
    )

    @field_validator("host")
    @classmethod
    def _plain_host(cls, v: str) -> str:
        # "user:pw@host" or "mqtt://…" would put a password in every log line that names the broker
        if "@" in v or "/" in v or any(c.isspace() for c in v):
            raise ValueError(
                "mqtt.host takes a host name or address only (no scheme, user or "
                "password): the user goes in username, the password in password_file "
                "or THERMOCOMP_MQTT_PASSWORD"
            )
        return v

    def password(self) -> str | None:
        if self.password_file is not None:
            return read_secret_file(self.password_file, "mqtt.password_file")
        return os.environ.get("THERMOCOMP_MQTT_PASSWORD") or None


class JournalRetention(BaseModel):
    """``[journal]``: how long journal files are kept. The oldest days go first once they are
    older than ``max_age_days`` or the journal directory's journal files exceed ``max_size_mb``;
    the files being written are never removed."""

    model_config = FROZEN

    max_age_days: float = Field(90.0, gt=0, le=36500)
    max_size_mb: float = Field(1024.0, gt=0, le=1e7)
    sweep_every_s: float = Field(
        3600.0, gt=0, le=86400, description="look this often (and at start)"
    )


class RuntimeConfig(BaseModel):
    model_config = FROZEN

    state_dir: Path = Path("/var/lib/thermocomp")
    journal_dir: Path | None = Field(None, description="default: <state_dir>/journal")
    journal_fsync_s: float = Field(
        10.0,
        ge=0,
        le=3600,
        description="fsync the journal this often (0: every row); always on rotation and at stop",
    )
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    log_file: Path | None = Field(None, description="JSON-lines log; default stderr")
    watchdog: bool = True
    time_scale: float = Field(
        1.0,
        gt=0,
        le=10000,
        description="simulated seconds per second: for the "
        "virtual machine tool only; 1 on a real machine",
    )
    spindle: list[SpindleConfig] = Field(min_length=1, max_length=64)
    cooling: CoolingConfig | None = None
    status: StatusConfig = StatusConfig()
    mqtt: MqttConfig | None = None
    journal: JournalRetention = JournalRetention()

    @model_validator(mode="after")
    def _cooling_spindle(self) -> RuntimeConfig:
        c = self.cooling
        if c is None or c.mode == "off":
            return self
        names = [s.name for s in self.spindle]
        if c.spindle is None and len(names) > 1:
            raise ValueError(
                f"cooling.spindle: name the spindle whose estimate drives the chiller ({', '.join(names)})"
            )
        if c.spindle is not None and c.spindle not in names:
            raise ValueError(
                f"cooling.spindle: no spindle named {c.spindle!r} ({', '.join(names)})"
            )
        return self

    @property
    def cooling_spindle(self) -> str | None:
        """The spindle whose estimate drives the chiller, or None without active cooling."""
        c = self.cooling
        if c is None or c.mode == "off":
            return None
        return c.spindle or self.spindle[0].name

    @property
    def journal_path(self) -> Path:
        return self.journal_dir or self.state_dir / "journal"


_SPINDLE_KEY = re.compile(r"^spindle\[(\d+)\](?:\.(.*))?\Z", re.S)


def _spindle_scope(data: Any, index: int) -> str:
    """A ``[[spindle]]`` entry by its name as written (by its place when it has none)."""
    entries = data.get("spindle") if isinstance(data, dict) else None
    entry = entries[index] if isinstance(entries, list) and index < len(entries) else None
    name = entry.get("name") if isinstance(entry, dict) else None
    return spindle_scope(name) if isinstance(name, str) else f"spindle #{index + 1} (no name)"


def config_line(path: Path, data: Any, problem: Problem) -> str:
    """One problem of a configuration file in the product's dialect: the file, the spindle by
    name, the key as written inside it, the value given and what is wrong."""
    m = _SPINDLE_KEY.match(problem.key)
    if m is None:
        return problem.line(str(path))
    inside = Problem(m.group(2) or "", problem.text, problem.given)
    return inside.line(f"{path}: {_spindle_scope(data, int(m.group(1)))}")


def config_error(path: Path, data: Any, err: ValidationError) -> ConfigError:
    """Every problem ``err`` holds, one line each (:func:`config_line`)."""
    return ConfigError(
        problem_lines([config_line(path, data, p) for p in problems_of(RuntimeConfig, data, err)])
    )


def load_config(path: str | os.PathLike[str]) -> RuntimeConfig:
    """Read and validate; one-line :class:`ConfigError` on any problem."""
    p = Path(path)
    try:
        raw = read_regular(p, MAX_CONFIG_BYTES)  # a FIFO is refused, never waited on
        if len(raw) > MAX_CONFIG_BYTES:
            raise ConfigError(
                f"{p}: larger than {MAX_CONFIG_BYTES // 2**20} MiB: not a configuration"
            )
        data = tomllib.loads(raw.decode("utf-8"))
    except OSError as err:
        raise ConfigError(f"{p}: cannot read: {err.strerror or err}") from err
    except UnicodeDecodeError as err:
        line = raw[: err.start].count(b"\n") + 1
        raise ConfigError(
            f"{p}: line {line}: not UTF-8 text (byte 0x{raw[err.start]:02x}); "
            "save the file as UTF-8"
        ) from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{p}: not valid TOML: {err}") from err
    base = p.parent
    for sp in data.get("spindle", []) if isinstance(data.get("spindle"), list) else []:
        if (
            isinstance(sp, dict)
            and isinstance(sp.get("model"), str)
            and not os.path.isabs(sp["model"])
        ):
            sp["model"] = str(base / sp["model"])  # relative to the config file
    for key in ("state_dir", "journal_dir", "log_file"):
        if isinstance(data.get(key), str) and not os.path.isabs(data[key]):
            data[key] = str(base / data[key])
    for table, key in (("status", "token_file"), ("mqtt", "password_file"), ("mqtt", "ca_file")):
        t = data.get(table)
        if isinstance(t, dict) and isinstance(t.get(key), str) and not os.path.isabs(t[key]):
            t[key] = str(base / t[key])
    try:
        cfg = RuntimeConfig.model_validate(data)
    except ValidationError as err:
        raise config_error(p, data, err) from err
    names = [s.name for s in cfg.spindle]
    problems = [
        Problem(f"spindle[{i}].name", "another [[spindle]] has this name: names must be unique", n)
        for i, n in enumerate(names)
        if n in names[:i]
    ]
    problems += [
        Problem(f"spindle[{i}].name", why, n)
        for i, n in enumerate(names)
        if (why := spindle_name_problem(n)) is not None
    ]
    if problems:
        raise ConfigError(problem_lines([config_line(p, data, q) for q in problems]))
    return cfg
