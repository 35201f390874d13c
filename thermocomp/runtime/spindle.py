"""One spindle's cycle: read -> step -> measure -> shape -> write -> journal -> save.

Each period :meth:`SpindleRuntime.cycle` asks the link once for what the cycle needs
(:meth:`cnc_adapters.Adapter.read` with :class:`~cnc_adapters.Wants`): the speed, the cutting
signal, the offset the controller holds, the inputs and a new measurement, each checked where it
entered (a :class:`~cnc_adapters.Reading`). The parts then take their turn, each with its own
state and events:

- :class:`~.link.LinkWatch`: the speed to step with (held up to ``faults.speed_hold_s`` while a
  read fails, then idle assumed), link down and ``OUTAGE``, the cutting signal;
- :class:`~.offset.ControllerOffset`: the read-back (``OFFSET_MISMATCH``), write back-off, and
  the shaped offset ``A = -S`` written at most once a cycle (:meth:`cnc_adapters.Adapter.write`),
  with the sign of life where the link writes one (or the sign alone, confirming the held
  offset);
- the estimate (:class:`compensator.estimate.Estimate`, as replay runs it): the model, its
  speed-only fallback while an input fails, the speed clamp;
- :class:`~.intake.ProbeIntake`: measurements fused by the observer, ``PROBE_*``,
  ``OBSERVER_STALE`` and ``MODEL_DRIFT``;
- :class:`~.expected.ExpectedWatch`: the error to expect (``EXPECTED_ERROR_HIGH``, advice only);
- :class:`~.cold.ColdStart`: ``COLD_START_TURNING``;
- :class:`~.shadow.Shadow`: a refit candidate stepped beside the live model, never written;
- :class:`~.recorder.Recorder` and :class:`~.keeper.StateKeeper`: the journal row and the state
  file, each failing alone with an alarm while compensation goes on.

A cycle returns a frozen :class:`~.outcome.CycleOutcome`. A reload, a promotion or a rollback
starts the new runtime from the old one's :class:`Carry` by the one constructor path. Time is
injected (``clock`` monotonic seconds, ``wall`` epoch seconds): tests run in simulated time
without sleeping. The journal's ``time_s`` is the monotonic clock anchored to the wall once, so
its steps are the model's dt.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cnc_adapters import Adapter, Capabilities, Failure, Reading, Wants, open_adapter
from compensator.errors import ConfigError
from compensator.estimate import Estimate, EstimateState
from compensator.io import load_any_model, model_digest
from compensator.io.history import ModelHistory
from compensator.predictor import Predictor

from .alarms import Alarm
from .cold import ColdStart, slowest_tau_s
from .config import SpindleConfig
from .expected import ExpectedWatch
from .intake import ProbeIntake, Reply
from .keeper import Cold, DowntimeCheck, StateKeeper, record_in_use
from .link import LinkWatch
from .offset import ControllerOffset
from .outcome import CycleOutcome, Pace
from .recorder import Recorder
from .shadow import Shadow
from .stepper import EstimateRunner

__all__ = [
    "Alarm",
    "Carry",
    "CycleOutcome",
    "Reply",
    "SpindleRuntime",
    "cutting_from_controller",
    "slowest_tau_s",
]

log = logging.getLogger("thermocomp.runtime")

COUNTERS = (
    "cycles",
    "writes",
    "write_rejected",
    "read_failed",
    "link_down_cycles",
    "readbacks",
    "mismatches",
    "journal_failed",
    "state_save_failed",
    "probes_accepted",
    "probes_rejected",
    "probes_restarted",
    "probes_failed",
    "steps_refused",
    "life_failed",
)


def cutting_from_controller(cfg: SpindleConfig, caps: Capabilities) -> bool:
    """Whether the spindle takes its cutting state from the controller: the link has a signal
    and the configuration does not say ``speed``. ConfigError where the configuration requires
    one (``controller``) and the link has none."""
    signal = cfg.shaping.cutting.signal
    if signal == "controller" and not caps.cutting:
        raise ConfigError(
            f"spindle {cfg.name}: shaping.cutting.signal = 'controller', but the adapter has no "
            "cutting signal configured (cutting_node for OPC UA, cutting for LinuxCNC, "
            "cutting_register for Modbus)"
        )
    return caps.cutting and signal != "speed"


@dataclass(frozen=True)
class Carry:
    """What a reload, a promotion or a rollback keeps of the runtime it replaces: its parts,
    each taken up by its successor's ``follow``."""

    digest: str
    est: EstimateState
    pace: Pace
    link: LinkWatch
    offset: ControllerOffset
    keeper: StateKeeper
    downtime: DowntimeCheck
    intake: ProbeIntake
    cold: ColdStart
    expected: ExpectedWatch
    shadow: Shadow | None


class SpindleRuntime:
    """One spindle: its estimate, its link and the parts of its cycle."""

    def __init__(
        self,
        cfg: SpindleConfig,
        state_dir: Path,
        journal_dir: Path,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
        adapter: Adapter | None = None,
        anchor_s: float | None = None,
        journal_fsync_s: float = 10.0,
        previous: SpindleRuntime | None = None,
    ):
        self.cfg = cfg
        self.clock, self.wall = clock, wall
        # journal time = monotonic + anchor: increasing, and its steps are the model's dt
        anchor = wall() - clock() if anchor_s is None else anchor_s
        self.anchor_s = anchor
        loaded: Predictor = load_any_model(cfg.model)
        cfg.refuse_other_spindle(loaded.spindle_id)
        self.digest = model_digest(loaded)
        estimate = cfg.estimate(loaded)
        self.expected = ExpectedWatch(cfg, loaded)
        self.adapter: Adapter = (
            adapter if adapter is not None else open_adapter(cfg.adapter, clock=clock)
        )
        caps = self.adapter.capabilities
        if estimate.with_inputs is not None:
            missing = sorted(set(estimate.with_inputs.input_names) - set(caps.inputs))
            if missing:
                raise ConfigError(
                    f"spindle {cfg.name}: the model needs input(s) {', '.join(missing)}; map them "
                    "in the adapter (input_nodes for OPC UA, input_registers for Modbus)"
                )
        self.counters = dict.fromkeys(COUNTERS, 0)
        history = ModelHistory.of(state_dir, cfg.name, cfg.learning.keep_models)
        shadow = Shadow.load(history.shadow_path, cfg, caps.inputs)
        # the model, its fallback, the observer and the speed clamp: one object, as replay runs it
        self.runner = EstimateRunner(
            cfg.name,
            estimate,
            shadow,
            DowntimeCheck(cfg.name, anchor, cfg.max_state_age_s),
            self.counters,
        )
        self.recorder = Recorder(
            cfg,
            journal_dir,
            channels=caps.inputs,
            shadow=shadow is not None,
            anchor_s=anchor,
            fsync_s=journal_fsync_s,
            counters=self.counters,
        )
        self.intake = ProbeIntake(
            cfg,
            journal_dir,
            observer=estimate.fused is not None,
            anchor_s=anchor,
            fsync_s=journal_fsync_s,
            counters=self.counters,
        )
        self.link = LinkWatch(
            cfg.name,
            cfg.faults,
            self.counters,
            cutting_from_controller=cutting_from_controller(cfg, caps),
            reconnects=self.adapter.reconnects,
        )
        self.cold = ColdStart(cfg.name, cfg.cold_start_settle_taus, anchor)
        self.keeper = StateKeeper(
            cfg, Path(state_dir) / f"{cfg.name}.state.json", self.counters, wall
        )
        self.pace = Pace(clock())
        self.offset = self._offset(caps, 0.0)
        self.sticky_alarms = Alarm.NONE  # set by the service (a refused reload)
        self.last: CycleOutcome | None = None  # the last cycle's outcome, for the status
        record_in_use(
            history,
            cfg,
            loaded,
            self.digest,
            "the service started with it"
            if previous is None
            else "a reload found it in the configuration",
            wall(),
        )
        if previous is None:
            self.restore()
        else:
            self._take_up(previous.carry())
        if shadow is not None:
            old = None if previous is None else previous.runner.shadow
            shadow.start(old, self.est.estimate_um - self.est.bias_um, self.link.last_speed_rpm)
        self.alarms = self.pace.startup

    def _offset(self, caps: Capabilities, held_um: float) -> ControllerOffset:
        return ControllerOffset(
            self.cfg.name,
            self.cfg.shaping,
            self.cfg.faults,
            self.cfg.period_s,
            self.counters,
            held_um=held_um,
            can_read_back=caps.held_offset,
            writes_life=caps.life_sign,
        )

    # -- views --------------------------------------------------------------------------

    @property
    def estimate(self) -> Estimate:
        """The model, its fallback, the observer and the speed clamp."""
        return self.runner.estimate

    @property
    def est(self) -> EstimateState:
        return self.runner.est

    @property
    def shadow(self) -> Shadow | None:
        return self.runner.shadow

    @property
    def writes_offset(self) -> bool:
        """False: ``[cooling] mode = "cooling"``, the chiller only."""
        return self.offset.writes

    @writes_offset.setter
    def writes_offset(self, value: bool) -> None:
        self.offset.writes = bool(value)

    @property
    def state_path(self) -> Path:
        return self.keeper.path

    @property
    def journal(self) -> Any:
        return self.recorder.journal

    @property
    def measurements(self) -> Any:
        return self.intake.journal

    @property
    def drift(self) -> Any:
        return self.intake.drift.state

    @property
    def state(self) -> Any:
        """The speed-only model's state, with the observer's when fused."""
        return self.est.core

    @property
    def input_state(self) -> Any:
        return self.est.inputs

    @property
    def last_speed_rpm(self) -> float:
        """The last speed read [rpm]."""
        return self.link.last_speed_rpm

    def estimate_um(self) -> float:
        """The estimate the offset follows: the model in use, plus the observer's bias."""
        return self.est.estimate_um

    def observer_status(self) -> dict[str, Any] | None:
        """The observer's state for people and status lines; None without one."""
        return self.intake.status(self.est)

    def next_period_s(self) -> float:
        """Seconds to the next cycle: ``run_up_period_s`` while the spindle changes speed with the
        tool clear of the part (the last cycle saw the speed move), else ``period_s``."""
        fast = self.cfg.run_up_period_s
        if fast is not None and self.clock() < self.pace.run_up_until_s:
            return min(fast, self.cfg.period_s)
        return self.cfg.period_s

    # -- start, reload, save ------------------------------------------------------------

    def restore(self) -> None:
        """The saved state, advanced through the downtime; a cold start when there is none
        that fits."""
        now_wall = self.wall()
        got, alarms, saved = self.keeper.restore(self.estimate, self.digest, now_wall)
        self.pace.startup |= alarms
        if isinstance(got, Cold):
            self.runner.cold_start(got.reason)
            self.pace.startup |= Alarm.COLD_START
            self.cold.started()
            return
        self.runner.restored(got, saved, self.clock(), now_wall)
        self.expected.restored(got.speeds_lately, self.clock(), now_wall)
        # what we last wrote; the first cycle reads back what the controller really holds
        self.offset = self._offset(self.adapter.capabilities, got.held_um)
        if got.unsettled_until_wall_s is not None:
            self.cold.carried(self.clock(), got.unsettled_until_wall_s, now_wall)

    def carry(self) -> Carry:
        """What a successor keeps of this runtime (its queue of measurements moves with it)."""
        return Carry(
            self.digest,
            self.est,
            self.pace,
            self.link,
            self.offset,
            self.keeper,
            self.runner.downtime,
            self.intake,
            self.cold,
            self.expected,
            self.runner.shadow,
        )

    def _take_up(self, carry: Carry) -> None:
        """Go on from ``carry``: the same model continues its whole estimate (a reload); another
        (a promotion, a rollback, an edited file) starts at the old estimate, at the speed last
        read (its states at equilibrium there, the difference decaying with its slowest time
        constant), so the estimate does not jump. The offset the controller holds, the shaper
        and the timing carry over either way; the new link reads the offset back first."""
        same = carry.digest == self.digest
        self.pace.follow(carry.pace)
        self.link.follow(carry.link)
        self.offset = self._offset(self.adapter.capabilities, carry.offset.held_um)
        self.offset.follow(carry.offset)
        self.keeper.follow(carry.keeper, same_model=same)
        self.runner.take_up(carry, self.digest, self.link.last_speed_rpm)
        self.intake.follow(carry.intake, same_model=same)
        self.cold.follow(carry.cold)  # a new configuration does not settle an estimate
        if same:
            self.expected.follow(carry.expected)

    def take_journal(self, old: SpindleRuntime) -> None:
        """Write on through ``old``'s journals: the rows they still hold in memory are not lost."""
        self.recorder.follow(old.recorder)
        self.intake.take_journal(old.intake)

    def save_state(self, now: float | None = None) -> bool:
        """Save the state; a failure is an alarm and a retry with back-off, never an exception."""
        now = self.clock() if now is None else now
        wall_now = self.wall()
        return self.keeper.save(
            now,
            {
                "spindle": self.cfg.name,
                "model_sha256": self.digest,
                "saved_wall_s": wall_now,
                **self.estimate.state_dict(self.est, wall_now),
                "offset_um": self.offset.held_um,
                **self.cold.saved_fields(now, wall_now),
                **self.expected.saved_fields(now, wall_now),
            },
        )

    def submit(
        self, elongation_um: float, sigma_um: float | None, reply: Reply | None = None
    ) -> None:
        """A measurement from `thermocomp measure`, fused at the next cycle; ``reply`` gets the
        outcome (or an error)."""
        self.intake.submit(elongation_um, sigma_um, reply)

    # -- the cycle -------------------------------------------------------------------------

    def _wants(self, now: float) -> Wants:
        caps = self.adapter.capabilities
        inputs = bool(caps.inputs) and (
            self.estimate.with_inputs is not None or self.recorder.wants_inputs(now)
        )
        return Wants(
            cutting=self.link.cutting.from_controller,
            held_offset=self.offset.wants_readback(self.link.up),
            inputs=inputs,
            measurement=self.estimate.fused is not None and caps.measurement,
        )

    def _inputs(self, now: float, reading: Reading) -> tuple[dict[str, float], str | None]:
        """This cycle's input values (NaN for a channel that failed: the estimate treats it as
        a sensor fault) and why they were not read at all."""
        got = reading.inputs
        if got is None or isinstance(got, Failure):
            why = f"inputs not read: {got if got is not None else self.link.error or 'the link is down'}"
            if self.estimate.with_inputs is None and isinstance(got, Failure) and not got.link_lost:
                self.recorder.inputs_failed(now, got.reason)  # a slow channel, not a lost link
            return {}, why
        return {k: (math.nan if isinstance(v, Failure) else v) for k, v in got.items()}, None

    def cycle(self) -> CycleOutcome:
        t_read = time.perf_counter()  # a measurement only: the read->write latency
        now, wall_now = self.clock(), self.wall()
        dt = self.pace.tick(now)
        alarms = self.pace.startup | self.sticky_alarms
        alarms |= self.runner.downtime.clock_step(now, wall_now, self.runner.again)
        self.pace.startup = Alarm.NONE
        wants = self._wants(now)
        reading = self.adapter.read(wants)
        heard = self.link.take(now, reading, self.estimate.speed_limit_rpm)
        alarms |= heard.alarms | self.offset.take(now, reading, heard, self.link)
        read_rpm = heard.read_rpm
        if self.cold.unjudged and not heard.unread:
            self.cold.judge(now, read_rpm, self.estimate)
        speed, over = self.estimate.clamp(read_rpm)  # the speed every part of the cycle uses
        if over:
            alarms |= Alarm.OVER_RANGE
        inputs, input_error = self._inputs(now, reading)
        alarms |= self.runner.step(read_rpm, dt, now, wall_now, inputs, input_error)
        if self.estimate.fused is not None:
            alarms |= self._measure(now, wall_now, reading, wants)
        alarms |= self.cold.alarm(now)
        expected, expected_alarm = self.expected.at(self.estimate, self.est, read_rpm, now)
        alarms |= expected_alarm  # the real speed, not the clamped one
        s = self.est.estimate_um
        shaper_rpm = speed if heard.shaper_rpm is None else heard.shaper_rpm
        shaped = self.offset.plan(
            s, shaper_rpm, self.offset.shaper_dt(dt, self.clock()), heard.cutting
        )
        if shaped.cutting:
            self.pace.run_up_until_s = -math.inf
        elif self.offset.shaper.state.settled_s == 0.0:  # the speed left its band this cycle
            # a controller may refresh its speed less often than we read: stay fast one period
            self.pace.run_up_until_s = now + self.cfg.period_s
        wrote, write_alarms = self.offset.apply(
            now, shaped, heard, self.link, self.adapter.write, self.clock, alarms
        )
        alarms |= write_alarms
        latency_ms = (time.perf_counter() - t_read) * 1e3
        self.counters["cycles"] += 1
        alarms |= self.keeper.alarms  # of the last save: a row is journaled before the save
        out = CycleOutcome(
            time_s=now,
            dt_s=dt,
            speed_rpm=speed,
            predicted_um=s,
            target_um=shaped.offset_um,
            offset_um=self.offset.held_um,
            written=wrote,
            flags=int(shaped.flags),
            alarms=alarms,
            read_to_write_ms=latency_ms,
            offset_mode=self.offset.mode.value,
            link=self.link.health.state.value,
            cutting=shaped.cutting,
            cutting_source=heard.cutting_source,
            policy_state=shaped.state,
            slew_limit_um_per_s=shaped.rate_um_per_s,
            estimate=self.runner.kind,
            inputs=inputs,
            observer=self.observer_status(),
            expected_error=None if expected is None else expected.as_dict(),
            drift=self.intake.drift.status() if self.estimate.fused is not None else None,
            shadow=self.runner.shadow_status(),
        )
        journaled = self.recorder.write(out, wall_now, self.runner.shadow_um())
        out = dataclasses.replace(out, alarms=alarms | journaled)
        if self.keeper.due(now):
            self.save_state(now)
        self.alarms = out.alarms | self.keeper.judge(now, self.pace.first_s)
        self.last = out
        return out

    def _measure(self, now: float, wall_now: float, reading: Reading, wants: Wants) -> Alarm:
        """The controller's new measurement and those sent with `thermocomp measure`."""
        stated = self.expected.stated(self.estimate, self.est)[0]
        taken = self.intake.take(
            self.estimate,
            self.est,
            reading if wants.measurement else None,
            source=str(self.adapter.name),
            now=now,
            wall_now=wall_now,
            first_s=self.pace.first_s,
            stated_rms_um=None if stated is None else stated.at(self.link.last_speed_rpm).rms_um,
            drift_from_s=self.cold.model_until_s,
        )
        self.runner.est = taken.est
        if taken.measured:
            self.runner.downtime.measured()  # measured: not re-run from the start
        if taken.settled is not None:
            self.cold.measured(*taken.settled)
        return taken.alarms

    def close(self) -> None:
        """Save the state and close; a failing disk or link never raises here."""
        try:
            self.save_state()
        finally:
            try:
                now = self.clock()
                try:
                    self.intake.close(now)
                finally:
                    self.recorder.close(now)
            finally:
                try:
                    self.adapter.close()
                except Exception as err:  # noqa: BLE001 - closing must not raise
                    log.warning("%s: closing the link: %s", self.cfg.name, err)
