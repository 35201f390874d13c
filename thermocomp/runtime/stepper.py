"""The estimate stepped each cycle: the model, its speed-only fallback while an input fails,
the speed clamp and the observer (:class:`compensator.estimate.Estimate`, as replay runs it),
with a candidate in shadow beside it and the cycles kept for a downtime measured again.

- a model with inputs: its speed-only fallback is always stepped and stands in, with
  ``INPUT_FALLBACK``, while an input is missing, out of range or stale; an input outside the
  range seen in calibration (but valid) raises ``INPUTS_EXTRAPOLATED``;
- a step that would leave an estimate no spindle can have is not taken: ``ESTIMATE_REFUSED``,
  and the offset holds where it was.
"""

from __future__ import annotations

import logging
from typing import Any

from compensator.errors import ModelError
from compensator.estimate import Estimate, EstimateState, Step

from .alarms import Alarm
from .events import event
from .keeper import DowntimeCheck, Restored
from .shadow import Shadow


class EstimateRunner:
    """One spindle's estimate and what steps beside it."""

    def __init__(
        self,
        name: str,
        estimate: Estimate,
        shadow: Shadow | None,
        downtime: DowntimeCheck,
        counters: dict[str, int],
    ):
        self.name = name
        self.estimate = estimate
        self.est: EstimateState = estimate.cold()
        self.shadow = shadow
        self.downtime = downtime
        self.counters = counters
        self.refused: str | None = None  # why the last step was refused, while it is

    def cold_start(self, reason: str) -> None:
        """Nothing known: the model's own equilibrium at rest (0 um for a speed-only model)."""
        self.est = self.estimate.cold()
        event(
            "cold_start",
            self.name,
            "%s: cold start (%s)",
            self.name,
            reason,
            level=logging.WARNING,
            reason=reason,
        )

    def restored(self, got: Restored, saved: Any, now: float, wall_now: float) -> None:
        """The saved state, advanced through the downtime."""
        self.est = got.est
        self.downtime.started(saved, got.downtime_s, now, wall_now)
        event(
            "state_restored",
            self.name,
            "%s: restored state, advanced %.0f s idle: S = %.2f um",
            self.name,
            got.downtime_s,
            self.est.core.elongation_um,
            downtime_s=round(got.downtime_s, 3),
            elongation_um=self.est.core.elongation_um,
            offset_um=got.held_um,
        )

    def take_up(self, carry: Any, digest: str, speed_rpm: float) -> None:
        """Go on from a predecessor's estimate: the same model continues it whole (a reload, the
        observer as configured now); another (a promotion, a rollback, an edited file) starts at
        the old estimate at ``speed_rpm`` (its states at equilibrium there, the difference
        decaying with its slowest time constant), so the estimate does not jump."""
        same = carry.digest == digest
        self.downtime.follow(carry.downtime, same_model=same)
        if same:
            self.est = self.estimate.adopt(carry.est)
            return
        self.est = self.estimate.begin(carry.est.estimate_um, speed_rpm)
        event(
            "model_switched",
            self.name,
            "%s: model %s in use (was %s), starting at the old estimate %.2f um",
            self.name,
            digest[:16],
            carry.digest[:16],
            carry.est.estimate_um,
            level=logging.WARNING,
            digest=digest,
            previous=carry.digest,
            elongation_um=carry.est.estimate_um,
        )

    @property
    def kind(self) -> str:
        """Which estimate is in use: "fused", "inputs" or "speed"."""
        if self.estimate.fused is not None:
            return "fused"
        return "inputs" if self.est.inputs is not None else "speed"

    def step(
        self,
        speed_rpm: float,
        dt: float,
        now: float,
        wall_now: float,
        inputs: dict[str, float],
        input_error: str | None,
    ) -> Alarm:
        """Step the estimate (and the shadow beside it) on the speed read, not the clamped one:
        the estimate clamps it as configured."""
        with_inputs = self.estimate.with_inputs is not None
        values = inputs if with_inputs and input_error is None else None
        error = input_error if with_inputs else None
        extrapolated = self.est.extrapolated
        try:
            self.est, step = self.estimate.step(
                self.est,
                speed_rpm,
                dt,
                now_s=now,
                wall_s=wall_now,
                inputs=values,
                input_error=error,
            )
        except ModelError as err:  # the estimate stays where it was; the offset holds it
            return self._refused(err)
        self.refused = None
        alarms = self._input_events(step, extrapolated) if with_inputs else Alarm.NONE
        if self.shadow is not None and not self.shadow.step(
            speed_rpm, dt, now, wall_now, values, error
        ):
            self.shadow = None
        self.downtime.record((speed_rpm, dt, now, wall_now, values, error))
        return alarms

    def again(self, now: float, wall_now: float) -> None:
        """The clock was found wrong at the start: the downtime measured again."""
        self.est = self.downtime.rerun(self.estimate, self.est, now, wall_now)

    def shadow_status(self) -> dict[str, Any] | None:
        return None if self.shadow is None else self.shadow.status()

    def shadow_um(self) -> float | None:
        return (
            None if self.shadow is None or self.shadow.est is None else self.shadow.est.estimate_um
        )

    def _refused(self, err: ModelError) -> Alarm:
        """ESTIMATE_REFUSED: an event when it begins and when its reason changes."""
        self.counters["steps_refused"] += 1
        why = str(err)[:200]
        if self.refused != why:
            self.refused = why
            event(
                "estimate_refused",
                self.name,
                "%s: ESTIMATE_REFUSED: %s",
                self.name,
                why,
                level=logging.ERROR,
                error=why,
            )
        return Alarm.ESTIMATE_REFUSED

    def _input_events(self, step: Step, extrapolated_before: str | None) -> Alarm:
        """The events and alarms of the estimate's input decisions this cycle: the fallback
        standing in (``INPUT_FALLBACK``), the model with inputs back, and valid inputs outside the
        range seen in calibration (``INPUTS_EXTRAPOLATED``, one event on entry, one on leaving)."""
        model = self.estimate.with_inputs
        assert model is not None
        name = self.name
        if step.fell_back is not None:
            event(
                "input_fallback",
                name,
                "%s: %s; speed-only fallback",
                name,
                step.fell_back,
                level=logging.ERROR,
                reason=step.fell_back,
            )
        if step.input_fallback:
            return Alarm.INPUT_FALLBACK
        if step.restored:
            event(
                "inputs_restored",
                name,
                "%s: inputs good: model with %s",
                name,
                ", ".join(model.input_names),
                inputs=list(model.input_names),
            )
        why = self.est.extrapolated
        if why is None:
            if extrapolated_before is not None:
                event(
                    "inputs_within_training", name, "%s: inputs back inside the trained range", name
                )
            return Alarm.NONE
        if extrapolated_before is None:
            event(
                "inputs_extrapolated",
                name,
                "%s: INPUTS_EXTRAPOLATED: %s; the model with inputs extrapolates",
                name,
                why,
                level=logging.WARNING,
                reason=why,
            )
        return Alarm.INPUTS_EXTRAPOLATED
