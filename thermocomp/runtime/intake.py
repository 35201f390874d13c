"""Measurements into the estimate: the controller's probe cycle and ``thermocomp measure``.

Each cycle, after the step, the controller's new measurement (:attr:`Reading.measurement`) and
those sent with ``thermocomp measure`` are fused against the estimate of this cycle or the last,
whichever ran slower (a setter measures at rest), each journaled (:class:`MeasurementJournal`).
A measurement beyond the gate raises ``PROBE_REJECTED`` and leaves the estimate alone, a source
that fails ``PROBE_FAILED``, none accepted for ``stale_after_s`` ``OBSERVER_STALE``. The model's
own miss at each measurement goes into the drift detector (``MODEL_DRIFT``). A measurement the
observer's bounds cut (the correction at ``max_correction_um``, or its source beyond
``max_source_move_um``) is journaled ``limited``, counted and evented, and ``OBSERVER_BOUND`` is
raised while the correction is at its bound or a source's last measurement was cut.
"""

from __future__ import annotations

import collections
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cnc_adapters import Failure, FailureKind, Measurement, Reading
from compensator.drift import DriftConfig, DriftState, miss_sd_um
from compensator.drift import update as drift_update
from compensator.errors import ModelError
from compensator.estimate import Estimate, EstimateState
from compensator.fusion import FusedState
from compensator.io import MeasurementJournal
from compensator.io.journal_export import iso
from compensator.modelbase import SAVED_LIMIT_UM
from compensator.observer import SIGMA_LIMIT_UM

from .alarms import Alarm
from .bounds import BoundWatch
from .config import SpindleConfig
from .events import event

log = logging.getLogger("thermocomp.runtime")

Reply = Callable[[dict[str, Any]], None]
"""Where the outcome of a measurement sent by ``thermocomp measure`` goes."""


@dataclass(frozen=True)
class Taken:
    """What one cycle's measurements did."""

    est: EstimateState
    alarms: Alarm
    measured: bool = False
    """A usable measurement was fused (accepted, restarted or rejected)."""
    settled: tuple[float, str] | None = None
    """The first measurement the observer took (accepted or restarted): value [um], outcome."""


class DriftWatch:
    """Has the spindle changed since the model was fitted: a CUSUM on the model's misses at each
    measurement (``MODEL_DRIFT``); a new runtime (start, reload with another model) starts it
    afresh, a known event."""

    def __init__(self, cfg: SpindleConfig, anchor_s: float):
        self.name = cfg.name
        self.anchor_s = anchor_s
        self.state = DriftState()
        self.config = DriftConfig(k=cfg.drift.k, h=cfg.drift.h, grace=cfg.drift.grace)

    def step(
        self,
        now: float,
        miss_um: float,
        sigma_um: float,
        stated_rms_um: float | None,
        drift_from_s: float,
    ) -> None:
        """One measurement into the drift detector; MODEL_DRIFT with one event on entry (the
        size and start of the change, what to do) and one on leaving. Left out while the model
        alone still carries the error of a cold start on a turning spindle (the k slowest time
        constants of COLD_START_TURNING, even once a measurement cleared the alarm): that miss
        is the start's, not a change of the spindle."""
        name = self.name
        if now < drift_from_s:
            log.debug("%s: a measurement during an unsettled cold start: not a drift step", name)
            return
        was = self.state.detected
        self.state = drift_update(
            self.state, miss_um, miss_sd_um(stated_rms_um, sigma_um), now, self.config
        )
        change = self.state.change()
        if change is not None and not was:
            size, since, n = change
            event(
                "model_drift",
                name,
                "%s: MODEL_DRIFT: the spindle grows %+.2f um %s the model says, over the last %d "
                "measurements (since %s); refit from production (thermocomp refit) or "
                "recalibrate",
                name,
                size,
                "beyond what" if size > 0 else "against what",
                n,
                iso(self.anchor_s + since),
                level=logging.WARNING,
                size_um=round(size, 3),
                since_s=self.anchor_s + since,
                measurements=n,
                statistic=round(self.state.statistic, 3),
            )
        elif was and not self.state.detected:
            event(
                "model_drift_cleared",
                name,
                "%s: MODEL_DRIFT cleared: the model's misses are back within what its fit stated",
                name,
                statistic=round(self.state.statistic, 3),
            )

    def status(self) -> dict[str, Any]:
        """The drift detector for status lines: its statistic, and the change while one is
        declared."""
        change = self.state.change()
        out: dict[str, Any] = {
            "statistic": round(self.state.statistic, 3),
            "threshold": self.config.h,
            "measurements": self.state.seen,
            "detected": self.state.detected,
        }
        if change is not None:
            out.update(
                size_um=round(change[0], 3),
                since_s=self.anchor_s + change[1],
                since=iso(self.anchor_s + change[1]),
            )
        return out


class ProbeIntake:
    """The measurement sources of one spindle, the observer's gate and staleness, and drift."""

    def __init__(
        self,
        cfg: SpindleConfig,
        journal_dir: Path,
        *,
        observer: bool,
        anchor_s: float,
        fsync_s: float,
        counters: dict[str, int],
    ):
        self.cfg = cfg
        self.observer = observer
        self.anchor_s = anchor_s
        self.counters = counters
        self.journal = MeasurementJournal(
            journal_dir,
            cfg.name,
            {"spindle": cfg.name, "model": cfg.model, "source": "thermocomp run"},
            fsync_every_s=fsync_s,
        )
        # measurements from `thermocomp measure`: (um, sigma or None, reply), fused next cycle
        self.queued: collections.deque[tuple[float, float | None, Reply | None]] = (
            collections.deque()
        )
        self.rejected = False  # the last measurement was beyond the gate
        # source -> (why it failed, whether a value was refused: held until a usable one)
        self.source_errors: dict[str, tuple[str, bool]] = {}
        self.stale = False
        self.drift = DriftWatch(cfg, anchor_s)
        self.bounds = BoundWatch(cfg.name, counters)

    def follow(self, old: ProbeIntake, *, same_model: bool) -> None:
        """Go on from ``old`` (a reload): its queue (moved, not copied); the same model keeps
        the gate's and the sources' state and the drift evidence."""
        self.queued, old.queued = old.queued, collections.deque()
        if same_model:
            self.rejected, self.source_errors = old.rejected, dict(old.source_errors)
            self.stale = old.stale
            self.drift = old.drift
            self.bounds = old.bounds

    def take_journal(self, old: ProbeIntake) -> None:
        """Write on through ``old``'s measurement journal (a reload): its rows are not lost."""
        if old.journal.directory == self.journal.directory:
            self.journal.close()
            self.journal, old.journal = old.journal, self.journal

    def submit(self, elongation_um: float, sigma_um: float | None, reply: Reply | None) -> None:
        if not self.observer:
            if reply is not None:
                reply(
                    {
                        "ok": False,
                        "error": f"spindle {self.cfg.name} has no observer "
                        "([spindle.observer] enabled = true)",
                    }
                )
            return
        self.queued.append((elongation_um, sigma_um, reply))

    def close(self, now: float) -> None:
        """Answer what is still queued, and close the journal."""
        try:
            for _, _, reply in self.queued:
                if reply is None:
                    continue
                try:
                    reply(
                        {
                            "ok": False,
                            "spindle": self.cfg.name,
                            "error": "the spindle stopped before the measurement was fused",
                        }
                    )
                except Exception as err:  # noqa: BLE001 - one caller gone must not lose the journal
                    log.warning("%s: a measurement's reply failed: %s", self.cfg.name, err)
            self.queued.clear()
        finally:
            self.journal.close(now)

    # -- one cycle ------------------------------------------------------------------------

    def take(
        self,
        estimate: Estimate,
        est: EstimateState,
        reading: Reading | None,
        *,
        source: str,
        now: float,
        wall_now: float,
        first_s: float | None,
        stated_rms_um: float | None,
        drift_from_s: float,
    ) -> Taken:
        """Fuse what came since the last cycle: the controller's new measurement in ``reading``
        (None: its source was not asked this cycle), then those queued. A source that fails is
        an alarm, never a stop. ``stated_rms_um``: the
        error the model in use states at the last speed (the drift detector's scale); before
        ``drift_from_s`` a miss is the cold start's, not drift."""
        got = None if reading is None else reading.measurement
        # read: the controller's source was asked, and no request before it found the link lost
        read = reading is not None and (
            isinstance(got, (Measurement, Failure))
            or not any(
                isinstance(v, Failure) and v.link_lost
                for v in (
                    reading.speed_rpm,
                    reading.cutting,
                    reading.not_ready_offset_um,
                    reading.held_offset_um,
                    reading.inputs,
                )
            )
        )
        measured = False
        settled: tuple[float, str] | None = None
        if isinstance(got, Failure):
            # a value refused (its counter taken as seen) or a failed read, even a timeout: the
            # speed read and the write judge the link, so the probe never stops them
            self._source_failed(now, wall_now, source, got.reason, got.kind is FailureKind.VALUE)
        elif read:
            failed = self.source_errors.get(source)
            if failed is not None and not failed[1]:
                self.source_errors.pop(source)  # it reads again
        inputs: list[tuple[float, float | None, str, int | None, Reply | None]] = []
        if isinstance(got, Measurement):
            inputs.append((got.elongation_um, got.sigma_um, got.source, got.sequence, None))
        while self.queued:
            y, sigma, reply = self.queued.popleft()
            inputs.append((y, sigma, "control", None, reply))
        for y, sigma, src, seq, reply in inputs:
            est, answer = self._fuse(
                estimate, est, now, wall_now, y, sigma, src, seq, stated_rms_um, drift_from_s
            )
            if answer["ok"]:
                measured = True
                # one cut by the bounds did not settle the estimate: it was not taken whole
                if answer["outcome"] in ("accepted", "restarted") and settled is None:
                    settled = (y, answer["outcome"])
            if reply is not None:
                reply(answer)
        alarms = Alarm.NONE
        if self.rejected:
            alarms |= Alarm.PROBE_REJECTED
        if self.drift.state.detected:
            alarms |= Alarm.MODEL_DRIFT
        if self.source_errors:
            alarms |= Alarm.PROBE_FAILED
        alarms |= self.bounds.alarm(estimate, est)
        return Taken(est, alarms | self._staleness(est, now, first_s), measured, settled)

    def _source_failed(
        self, now: float, wall_now: float, source: str, why: str, refused: bool
    ) -> None:
        """PROBE_FAILED: until the source reads again, or, for a value refused, until it gives a
        usable one. A refused value is journaled; a failing read once per new reason."""
        self.counters["probes_failed"] += 1
        why = why[:200]
        if self.source_errors.get(source, ("",))[0] != why:
            event(
                "probe_failed",
                self.cfg.name,
                "%s: PROBE_FAILED: %s; compensation goes on",
                self.cfg.name,
                why,
                level=logging.ERROR,
                source=source,
                error=why,
            )
        self.source_errors[source] = (why, refused)
        if refused:
            self.journal.record(
                self.anchor_s + now,
                elongation_um=None,
                sigma_um=None,
                source=source,
                sequence=None,
                outcome="refused",
                wall_s=wall_now,
                now_s=now,
            )

    def _fuse(
        self,
        estimate: Estimate,
        est: EstimateState,
        now: float,
        wall_now: float,
        y: float,
        sigma_um: float | None,
        source: str,
        sequence: int | None,
        stated_rms_um: float | None,
        drift_from_s: float,
    ) -> tuple[EstimateState, dict[str, Any]]:
        """Fuse one measurement against the estimate of the cycle it was taken in (this one, or
        the last when that ran slower: :meth:`compensator.estimate.Estimate.measure`); journal it."""
        fused = estimate.fused
        assert fused is not None
        name = self.cfg.name
        sigma = self.cfg.observer.sigma_um if sigma_um is None else sigma_um
        why: str | None = None
        if not (
            math.isfinite(y)
            and abs(y) <= SAVED_LIMIT_UM
            and math.isfinite(sigma)
            and 0 < sigma <= SIGMA_LIMIT_UM
        ):
            why = (
                f"{source}: measurement {y!r} um (sigma {sigma!r} um) is not usable: "
                f"|value| <= {SAVED_LIMIT_UM:g} um and 0 < sigma <= {SIGMA_LIMIT_UM:g} um"
            )
        else:
            try:
                bias_before = est.core.observer.bias_um
                est, up, before = estimate.measure(est, y, sigma, source)
            except ModelError as refused:  # the estimate it would give is none a spindle has
                why = f"{source}: {refused}"
        if why is not None:
            self._source_failed(now, wall_now, source, why, True)
            return est, {"ok": False, "spindle": name, "error": why}
        self.source_errors.pop(source, None)  # it gave a usable value
        outcome = up.outcome
        # the model's own miss (without the bias, which absorbs a drift); a rejected one counts too
        self.drift.step(now, y - (before - bias_before), sigma, stated_rms_um, drift_from_s)
        self.counters[f"probes_{outcome}"] += 1
        z = est.core.observer
        self.journal.record(
            self.anchor_s + now,
            elongation_um=y,
            sigma_um=sigma,
            source=source,
            sequence=sequence,
            outcome=outcome,
            predicted_um=before,
            innovation_um=up.innovation_um,
            innovation_sd_um=up.innovation_sd_um,
            bias_um=z.bias_um,
            bias_sd_um=z.bias_sd_um,
            wall_s=wall_now,
            now_s=now,
        )
        fields = {
            "source": source,
            "sequence": sequence,
            "measured_um": y,
            "sigma_um": sigma,
            "estimate_um": before,
            "innovation_um": up.innovation_um,
            "innovation_sd_um": up.innovation_sd_um,
            "bias_um": z.bias_um,
        }
        if up.limited is not None:
            self.bounds.cut(fused, source, up, y, before, fields)
        elif outcome == "rejected":
            event(
                "probe_rejected",
                name,
                "%s: PROBE_REJECTED: measured %.3f um, estimate %.3f um: innovation %+.3f um is "
                "beyond %g sd (%.3f um); estimate unchanged",
                name,
                y,
                before,
                up.innovation_um,
                fused.config.gate_sigma,
                up.innovation_sd_um,
                level=logging.WARNING,
                **fields,
            )
        elif outcome == "restarted":
            self.bounds.taken_whole(source)
            event(
                "probe_restart",
                name,
                "%s: measurements agree on a change the model cannot know: bias restarted at "
                "%+.3f um (measured %.3f um, estimate was %.3f um)",
                name,
                z.bias_um,
                y,
                before,
                level=logging.WARNING,
                **fields,
            )
        else:
            self.bounds.taken_whole(source)
            event(
                "probe_accepted",
                name,
                "%s: measurement %.3f um accepted (estimate %.3f um, innovation %+.3f um); "
                "bias %+.3f um",
                name,
                y,
                before,
                up.innovation_um,
                z.bias_um,
                **fields,
            )
        # rejected: holds until a measurement is taken again (the estimate was not corrected)
        self.rejected = outcome == "rejected"
        return est, {
            "ok": True,
            "spindle": name,
            "outcome": outcome,
            "accepted": up.accepted,
            "restarted": up.restarted,
            "limited": up.limited,
            "measured_um": y,
            "sigma_um": sigma,
            "estimate_um": before,
            "innovation_um": up.innovation_um,
            "innovation_sd_um": up.innovation_sd_um,
            "gate_sigma": fused.config.gate_sigma,
            "bias_um": z.bias_um,
            "elongation_um": est.estimate_um,
            "time_s": self.anchor_s + now,
        }

    def _staleness(self, est: EstimateState, now: float, first_s: float | None) -> Alarm:
        """OBSERVER_STALE once no measurement has been taken for ``stale_after_s`` (counted from
        this start when there has been none yet, so a new installation does not alarm at once)."""
        state = est.core
        assert isinstance(state, FusedState)
        limit = self.cfg.observer.stale_after_s
        age = state.since_measurement_s
        if age is None:
            age = now - (first_s if first_s is not None else now)
        stale = age > limit
        if stale and not self.stale:
            event(
                "observer_stale",
                self.cfg.name,
                "%s: OBSERVER_STALE: no measurement taken for %.0f s (limit %.0f s); the "
                "estimate runs open loop",
                self.cfg.name,
                age,
                limit,
                level=logging.WARNING,
                since_measurement_s=round(age, 3),
                stale_after_s=limit,
            )
        elif not stale and self.stale:
            event(
                "observer_fresh",
                self.cfg.name,
                "%s: observer fresh again: a measurement was taken",
                self.cfg.name,
                bias_um=state.bias_um,
            )
        self.stale = stale
        return Alarm.OBSERVER_STALE if stale else Alarm.NONE

    def status(self, est: EstimateState) -> dict[str, Any] | None:
        """The observer's state for people and status lines; None without one."""
        state = est.core
        if not isinstance(state, FusedState):
            return None
        z = state.observer
        return {
            "bias_um": z.bias_um,
            "bias_sd_um": z.bias_sd_um,
            "since_measurement_s": state.since_measurement_s,
            "stale": self.stale,
            "rejected": self.rejected,
            "failed_sources": {k: why for k, (why, _) in self.source_errors.items()},
            **self.bounds.status(),
            "moved_um": dict(z.moved_um),
        }
