"""A candidate in shadow (``thermocomp refit``): stepped beside the live model each cycle and
journaled, never written to the controller. Whatever it does, the live model is not touched."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Any

from compensator.errors import ConfigError, ModelError
from compensator.estimate import Estimate, EstimateState
from compensator.io import load_any_model, model_digest
from compensator.io.journal import SHADOW_COLUMN

from .config import SpindleConfig
from .events import event


class Shadow:
    """The candidate's estimate, stepped open loop (its own misses)."""

    def __init__(self, name: str, estimate: Estimate, digest: str):
        self.name = name
        self.estimate = estimate
        self.digest = digest
        self.est: EstimateState | None = None

    @classmethod
    def load(cls, path: Path, cfg: SpindleConfig, channels: tuple[str, ...]) -> Shadow | None:
        """The candidate in shadow, when ``path`` holds one for this spindle; a file that does
        not load or belongs to another spindle is said once and left alone: the live model runs
        on."""
        if not path.is_file():
            return None
        try:
            model = load_any_model(path)
            cfg.refuse_other_spindle(model.spindle_id)
            if model.input_names and not set(model.input_names) <= set(channels):
                raise ConfigError(
                    f"it needs input(s) {', '.join(model.input_names)} the link does not read"
                )
            # open loop: its own misses
            return cls(cfg.name, replace(cfg.estimate(model), observer=None), model_digest(model))
        except (ModelError, ConfigError, OSError) as err:
            event(
                "shadow_failed",
                cfg.name,
                "%s: the shadow candidate %s is not run: %s",
                cfg.name,
                path,
                str(err)[:200],
                level=logging.WARNING,
                path=str(path),
            )
            return None

    def start(self, old: Shadow | None, live_um: float, speed_rpm: float) -> None:
        """Go on from ``old`` when it ran the same candidate; else from the live model's own
        estimate (``live_um``, without the observer's bias) at ``speed_rpm``."""
        if old is not None and old.digest == self.digest and old.est is not None:
            self.est = old.est
            return
        self.est = self.estimate.begin(live_um, speed_rpm)
        event(
            "shadow_started",
            self.name,
            "%s: candidate %s runs in shadow from %.2f um (journaled as %s, never written)",
            self.name,
            self.digest[:16],
            live_um,
            SHADOW_COLUMN,
            digest=self.digest,
        )

    def step(
        self,
        speed_rpm: float,
        dt_s: float,
        now: float,
        wall_now: float,
        inputs: Any,
        input_error: str | None,
    ) -> bool:
        """One cycle of the candidate; False when it stopped (said once)."""
        assert self.est is not None
        try:
            self.est, _ = self.estimate.step(
                self.est,
                speed_rpm,
                dt_s,
                now_s=now,
                wall_s=wall_now,
                inputs=inputs,
                input_error=input_error,
            )
        except ModelError as err:
            event(
                "shadow_failed",
                self.name,
                "%s: the shadow candidate %s stopped: %s",
                self.name,
                self.digest[:16],
                str(err)[:200],
                level=logging.WARNING,
            )
            return False
        return True

    def status(self) -> dict[str, Any] | None:
        return (
            None
            if self.est is None
            else {"digest": self.digest, "estimate_um": self.est.estimate_um}
        )
