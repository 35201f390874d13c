"""Runtime configuration: TOML validated by pydantic (``extra="forbid"``).

See ``examples/machine.toml`` for an annotated example.
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from compensator.errors import ConfigError
from compensator.shaping import ShaperConfig


class FaultPolicy(BaseModel):
    """What the runtime does when the inputs are bad."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    speed_hold_s: float = Field(30.0, ge=0, description="hold the last speed this long after a failed read, then assume idle")
    over_range: Literal["clamp", "extrapolate"] = Field(
        "clamp", description="speed above the calibrated range: clamp to its top, or trust the model beyond it")
    max_outage_s: float = Field(600.0, gt=0, description="a link outage longer than this is logged as an outage alarm")
    input_stale_s: float = Field(300.0, gt=0, description="an input (temperature, load) unchanged this long "
                                 "is stale: the speed-only fallback takes over")
    input_recover_s: float = Field(60.0, ge=0, description="after an input fault, inputs must be good "
                                   "this long before the model with inputs takes over again")


class SpindleConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$", description="used in file names and logs")
    model: Path = Field(description="model file (JSON) written by thermocomp fit")
    adapter: dict[str, Any] = Field(description="adapter settings: a 'type' key and its options, or a 'url'")
    period_s: float = Field(1.0, gt=0, description="cycle period")
    shaping: ShaperConfig = ShaperConfig()
    faults: FaultPolicy = FaultPolicy()
    state_save_every_s: float = Field(30.0, gt=0)
    max_state_age_s: float = Field(2 * 86400.0, gt=0, description="older saved state: start cold")

    @field_validator("adapter")
    @classmethod
    def _adapter(cls, v: dict[str, Any]) -> dict[str, Any]:
        if "type" not in v and "url" not in v:
            raise ValueError("adapter needs a 'type' or a 'url'")
        for secret in ("password", "passwd", "secret"):
            if secret in v:
                raise ValueError(f"adapter.{secret}: passwords never go in the configuration file; "
                                 "use the environment or a password_file")
        return v


class RuntimeConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    state_dir: Path = Path("/var/lib/thermocomp")
    journal_dir: Path | None = Field(None, description="default: <state_dir>/journal")
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    log_file: Path | None = Field(None, description="JSON-lines log; default stderr")
    watchdog: bool = True
    time_scale: float = Field(1.0, gt=0, description="simulated seconds per second: for the "
                              "virtual machine tool only; 1 on a real machine")
    spindle: list[SpindleConfig] = Field(min_length=1)

    @property
    def journal_path(self) -> Path:
        return self.journal_dir or self.state_dir / "journal"


def load_config(path: str | os.PathLike[str]) -> RuntimeConfig:
    """Read and validate; one-line :class:`ConfigError` on any problem."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as err:
        raise ConfigError(f"{p}: cannot read: {err.strerror}") from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{p}: not valid TOML: {err}") from err
    base = p.parent
    for sp in data.get("spindle", []) if isinstance(data.get("spindle"), list) else []:
        if isinstance(sp, dict) and isinstance(sp.get("model"), str) and not os.path.isabs(sp["model"]):
            sp["model"] = str(base / sp["model"])  # relative to the config file
    for key in ("state_dir", "journal_dir", "log_file"):
        if isinstance(data.get(key), str) and not os.path.isabs(data[key]):
            data[key] = str(base / data[key])
    try:
        cfg = RuntimeConfig.model_validate(data)
    except ValidationError as err:
        e = err.errors()[0]
        where = ".".join(str(x) for x in e["loc"])
        more = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
        raise ConfigError(f"{p}: {where}: {e['msg']}{more}") from err
    names = [s.name for s in cfg.spindle]
    if len(set(names)) != len(names):
        raise ConfigError(f"{p}: spindle names must be unique")
    return cfg
