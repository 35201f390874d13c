"""A spindle's sections of the runtime configuration (``[[spindle]]`` and the tables inside it:
``faults``, ``drift``, ``learning``, ``observer``), validated by pydantic (``extra="forbid"``).
:mod:`.config` holds the service's sections and reads the file."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from cnc_adapters import check_adapter
from cnc_adapters.base import Problem, short
from cnc_adapters.control_profiles import ControllerProfile, control_count_um, profile
from compensator.errors import ConfigError, ModelError, clip
from compensator.estimate import Estimate
from compensator.fusion import observer_config_of
from compensator.observer import SIGMA_LIMIT_UM, ObserverConfig
from compensator.predictor import Predictor
from compensator.shaping import ShaperConfig

FROZEN = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)
"""Every section of the configuration: immutable, no unknown key, no NaN or infinity."""


def spindle_scope(name: str) -> str:
    """``spindle "sp1"``: how every message names a spindle (an odd name quoted as Python would)."""
    return f'spindle "{name}"' if re.fullmatch(r"[\w.-]{1,64}", name) else f"spindle {short(name)}"


class FaultPolicy(BaseModel):
    """What the runtime does when the inputs, the controller or the disk misbehave."""

    model_config = FROZEN

    speed_hold_s: float = Field(
        30.0,
        ge=0,
        le=86400,
        description="hold the last speed this long after a failed read, then assume idle",
    )
    over_range: Literal["clamp", "extrapolate"] = Field(
        "clamp",
        description="speed above the calibrated range: clamp to its top, or trust the model beyond it",
    )
    max_speed_rpm: float | None = Field(
        None,
        gt=0,
        le=1e6,
        description="the spindle's rated maximum speed [rpm]: a speed read more than "
        "10 % above it is a failed read, in either over_range policy (default: twice the calibrated top)",
    )
    max_outage_s: float = Field(
        600.0,
        gt=0,
        le=86400,
        description="a link outage (refused, lost or timing out) "
        "longer than this raises the OUTAGE alarm",
    )
    input_stale_s: float = Field(
        300.0,
        gt=0,
        le=86400,
        description="an input (temperature, load) unchanged this long "
        "is stale: the speed-only fallback takes over",
    )
    input_recover_s: float = Field(
        60.0,
        ge=0,
        le=86400,
        description="after an input fault, inputs must be good "
        "this long before the model with inputs takes over again",
    )
    readback_every: int = Field(
        1,
        ge=0,
        le=1_000_000,
        description="read back the offset the controller holds "
        "every this many cycles (also at start and after every reconnect); 0: only then. "
        "1 (one more read a cycle) sees a reset before the next write could jump",
    )
    offset_tolerance_um: float = Field(
        0.5,
        gt=0,
        le=1000,
        description="a held offset further than this from the "
        "one written raises OFFSET_MISMATCH (covers the controller's rounding)",
    )
    max_mismatches: int = Field(
        3,
        ge=1,
        le=1000,
        description="this many mismatches in a row: the controller keeps "
        "refusing; writes back off (doubling, up to max_write_backoff_s)",
    )
    max_write_backoff_s: float = Field(300.0, gt=0, le=86400)
    not_writing_cycles: int = Field(
        3,
        ge=1,
        le=1_000_000,
        description="a spindle whose controller has not "
        "held the offset aimed at (no write went through, and one was due) for more "
        "than this many cycles (period_s each) is shown as 'not writing' in the "
        "status, the page, /metrics and MQTT, like one whose link is down",
    )
    state_retry_s: float = Field(
        5.0, gt=0, le=3600, description="first retry after a failed state save (doubling)"
    )
    state_stale_s: float = Field(
        600.0,
        gt=0,
        le=7 * 86400,
        description="no state saved this long: the "
        "STATE_STALE alarm (a restart would then start further from the truth)",
    )


class DriftSettings(BaseModel):
    """The drift detector on the model's misses at each measurement (``compensator.drift``): a
    two-sided CUSUM in units of the error the fit stated, raising MODEL_DRIFT."""

    model_config = FROZEN

    k: float = Field(
        0.5, ge=0, le=10, description="reference value [sd]: half the shift to find quickly"
    )
    h: float = Field(
        5.0,
        gt=0,
        le=100,
        description="decision interval [sd]: larger, fewer false alarms and later detection",
    )
    grace: int = Field(
        2, ge=0, le=1000, description="measurements left out after a start or a new model"
    )


class LearningSettings(BaseModel):
    """Refits from production (``thermocomp refit``) and the model history
    (``<state_dir>/history/<spindle>/``): when a candidate may replace the live model."""

    model_config = FROZEN

    min_train: int = Field(
        24, ge=4, le=100_000, description="measurements a candidate must be fitted on, at least"
    )
    min_holdout: int = Field(
        8, ge=3, le=100_000, description="newest measurements it must be judged on, at least"
    )
    holdout_share: float = Field(
        0.25, gt=0, lt=1, description="the newest share of the measurements held out to judge"
    )
    margin: float = Field(
        0.10,
        ge=0,
        lt=1,
        description="open loop, the candidate must miss less than the live "
        "model by this share on the held-out measurements",
    )
    observer_tolerance: float = Field(
        0.05,
        ge=0,
        le=1,
        description="with the observer, it may miss more than the live model by this share at most",
    )
    keep_models: int = Field(
        20, ge=2, le=1000, description="model copies kept in the history (the live one always)"
    )
    shadow_h: float = Field(
        24.0,
        ge=0,
        le=24 * 365,
        description="a candidate the rule accepts first runs in "
        "shadow at least this long (hours): stepped beside the live model and journaled, never "
        "written; the next refit promotes it only if, run as the service runs it (the same "
        "observer fusing the same measurements), it missed the measurements taken meanwhile "
        "by the margin less than the live model, beyond their noise. 0: promote at once",
    )
    shadow_min: int = Field(
        24,
        ge=3,
        le=100_000,
        description="measurements a candidate in shadow must be judged on, at least",
    )
    fit_days: float = Field(
        7.0,
        ge=0,
        le=3650,
        description="a candidate is fitted on the newest this many days of the journal before "
        "the measurements that judge it (0: all since the live model went into use)",
    )


class ObserverSettings(BaseModel):
    """The closed loop: tool-setter or probe measurements fused with the model.

    The keys from ``bias_q_um2_per_s`` on override the observer settings fitted with the model
    (``fit.observer`` in the model file), key by key; unset, the fitted (or default) value holds.
    """

    model_config = FROZEN

    enabled: bool = Field(
        False,
        description="fuse measurements: from the controller (the adapter's "
        "measurement nodes or variables) and from `thermocomp measure`",
    )
    sigma_um: float = Field(
        0.5, gt=0, le=SIGMA_LIMIT_UM, description="sigma of a measurement that states none [um]"
    )
    stale_after_s: float = Field(
        3600.0,
        gt=0,
        le=365 * 86400,
        description="no accepted measurement "
        "this long: OBSERVER_STALE (the estimate is open loop again)",
    )
    bias_q_um2_per_s: float | None = Field(None, ge=0, le=1e6)
    drift_q_um2_per_s3: float | None = Field(None, ge=0, le=1e6)
    model_sd_um: float | None = Field(None, ge=0, le=1000)
    gate_sigma: float | None = Field(None, gt=0, le=1000)
    initial_bias_sd_um: float | None = Field(None, gt=0, le=1e4)
    reaccept_after: int | None = Field(None, ge=0, le=1000)
    max_correction_um: float | None = Field(
        None,
        gt=0,
        le=1000,
        description="the largest |correction| (the estimate minus the model's free run) "
        "measurements may build [um]; reached: OBSERVER_BOUND. Unset: half the model's largest "
        "steady growth over its calibrated range, at least 10 um",
    )
    max_source_move_um: float | None = Field(
        None,
        gt=0,
        le=1000,
        description="the most one measurement source (the control socket, the controller's "
        "probe) may move the correction, net, per source_window_s [um]; beyond: OBSERVER_BOUND. "
        "Unset: half of max_correction_um",
    )
    source_window_s: float | None = Field(
        None, gt=0, le=365 * 86400, description="the window of max_source_move_um; unset: 3600"
    )

    @model_validator(mode="after")
    def _valid(self) -> ObserverSettings:
        ObserverConfig(**self.overrides())  # the observer's own checks, at load time
        return self

    def overrides(self) -> dict[str, Any]:
        """The observer settings given here (the rest come from the model file)."""
        return {
            k: v for k in ObserverConfig.model_fields if (v := getattr(self, k, None)) is not None
        }


class SpindleConfig(BaseModel):
    model_config = FROZEN

    name: str = Field(
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$", description="used in file names and logs"
    )
    model: Path = Field(description="model file (JSON) written by thermocomp fit")
    spindle_id: str | None = Field(
        None,
        min_length=1,
        max_length=200,
        description="the spindle id the model file must carry (thermocomp fit --model-spindle-id, the "
        "wizard's): a model for any other spindle, or one that names none ('unknown'), is refused "
        "at start and at reload. Unset: not checked; the name above is only a label and need not "
        "match the model's spindle id",
    )
    adapter: dict[str, Any] = Field(
        description="adapter settings: a 'type' key and its options, or a 'url'"
    )
    period_s: float = Field(1.0, ge=0.01, le=3600, description="cycle period")
    run_up_period_s: float | None = Field(
        None,
        ge=0.01,
        le=3600,
        description="while the spindle changes speed and the tool is not "
        "cutting, cycle this often instead (the offset follows the elastic growth through the "
        "run-up in finer steps); unset: period_s",
    )
    shaping: ShaperConfig = ShaperConfig()
    faults: FaultPolicy = FaultPolicy()
    observer: ObserverSettings = ObserverSettings()
    drift: DriftSettings = DriftSettings()
    learning: LearningSettings = LearningSettings()
    state_save_every_s: float = Field(30.0, gt=0, le=86400)
    max_state_age_s: float = Field(
        2 * 86400.0, gt=0, le=365 * 86400, description="older saved state: start cold"
    )
    cold_start_settle_taus: float = Field(
        3.0,
        gt=0,
        le=100,
        description="after a cold start with the spindle turning, COLD_START_TURNING stands "
        "for this many of the model's slowest time constants (the error of the cold start then decays to "
        "exp(-k) of itself: 5 % at 3), or until a measurement is accepted by the observer",
    )
    max_expected_error_um: float | None = Field(
        None,
        gt=0,
        le=10000,
        description="the error the work tolerates [um]: when the error the "
        "model's fit states for the current speed and inputs (95 % of |error|) is larger, or is "
        "only a floor there (validation scored nothing like it: too few folds predicted forward, "
        "a speed above the calibrated range, inputs further out than it reached), "
        "EXPECTED_ERROR_HIGH is raised (advice: the offset is unchanged). Unset: no alarm; a "
        "model that states no expected error is never checked",
    )

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if ".." in v:
            raise ValueError("a name may not contain '..'")
        return v

    @model_validator(mode="before")
    @classmethod
    def _control_resolution(cls, data: Any) -> Any:
        """The controller's count (a profile's resolution, a Haas link's decimals, LinuxCNC's
        count) becomes the shaper's resolution, so that the offset moves in whole counts and the
        controller's rounding crosses neither the clamp nor the slew limit; a resolution that
        shaping names must be a whole multiple of it."""
        if not isinstance(data, dict) or not isinstance(data.get("adapter"), dict):
            return data
        try:
            count = control_count_um(check_adapter(data["adapter"]))
        except ConfigError:
            return data  # the adapter's own validator reports it, in its order
        if not count:
            return data
        shaping = data.get("shaping")
        given = (
            (shaping.resolution_um if "resolution_um" in shaping.model_fields_set else None)
            if isinstance(shaping, ShaperConfig)
            else (shaping or {}).get("resolution_um")
        )
        if given is None:
            shaping = (
                shaping.model_copy(update={"resolution_um": count})
                if isinstance(shaping, ShaperConfig)
                else {**(shaping or {}), "resolution_um": count}
            )
            return {**data, "shaping": shaping}
        k = float(given) / count if isinstance(given, (int, float)) else -1.0
        if not (k >= 1 - 1e-9 and abs(k - round(k)) <= 1e-6):
            raise ValueError(
                f"shaping.resolution_um {given!r} must be a whole multiple of the "
                f"controller's count, {count:g} um (or left out)"
            )
        return data

    @model_validator(mode="after")
    def _within_profile(self) -> SpindleConfig:
        """The clamp within what the control takes: its limit, and twice the clamp (the largest
        move the shaper can make) below the step that raises its alarm."""
        p = self.profile
        if p is None:
            return self
        m = self.shaping.max_offset_um
        if m > p.limit_um:
            raise ValueError(
                f"shaping.max_offset_um {m:g} is past what profile {p.name!r} takes "
                f"({p.limit:g} {p.unit} = {p.limit_um:g} um)"
            )
        if p.max_step_um is not None and 2 * m > p.max_step_um:
            raise ValueError(
                f"shaping.max_offset_um {m:g}: a move across the clamp ({2 * m:g} um) "
                f"would raise profile {p.name!r}'s step alarm ({p.max_step_um:g} um)"
            )
        return self

    @property
    def profile(self) -> ControllerProfile | None:
        """The controller profile the adapter names, if any."""
        name = self.adapter.get("profile")
        return None if name is None else profile(name)

    @property
    def route(self) -> str | None:
        p = self.profile
        return None if p is None else p.route_name(self.adapter.get("route"))

    def refuse_other_spindle(self, model_spindle_id: str) -> None:
        """ConfigError when ``spindle_id`` is set and the model file is for another spindle."""
        if self.spindle_id is not None and model_spindle_id != self.spindle_id:
            raise ConfigError(
                clip(
                    Problem(
                        "spindle_id",
                        f"the model file {self.model} is for spindle {model_spindle_id!r}",
                        self.spindle_id,
                    ).line(spindle_scope(self.name)),
                    500,
                )
            )

    def estimate(self, model: Predictor) -> Estimate:
        """The estimate this spindle runs ``model`` with: the observer when enabled (its settings
        fitted with the model, overridden key by key here), the speed policy above the calibrated
        range and the input-fault timing. The runtime and ``thermocomp replay --config`` both
        build it here. ConfigError for observer settings that do not fit."""
        observer = None
        if self.observer.enabled:
            try:
                observer = observer_config_of(model, self.observer.overrides())
            except ModelError as err:
                raise ConfigError(f"{spindle_scope(self.name)}: observer: {err}") from err
        return Estimate(
            model,
            observer,
            self.faults.over_range,
            self.faults.input_stale_s,
            self.faults.input_recover_s,
            self.faults.max_speed_rpm,
        )

    @field_validator("adapter")
    @classmethod
    def _adapter(cls, v: dict[str, Any]) -> dict[str, Any]:
        if "type" not in v and "url" not in v and "profile" not in v:
            raise ValueError("adapter needs a 'type', a 'url' or a 'profile'")
        for secret in ("password", "passwd", "secret"):
            if secret in v:
                raise ValueError(
                    f"adapter.{secret}: passwords never go in the configuration file; "
                    "use password_file, password_credential (systemd LoadCredential=) "
                    "or the environment"
                )
        url = v.get("url")
        if isinstance(url, str):
            try:
                has_password = urlsplit(url).password is not None
            except ValueError:
                has_password = False
            if has_password:
                raise ValueError(
                    "adapter.url carries a password: refused; put it in password_file, "
                    "password_credential (systemd LoadCredential=) or the environment"
                )
        check_adapter(
            v
        )  # the backend's own typed settings: one line naming key, value, what is allowed
        return v
