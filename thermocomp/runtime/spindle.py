"""One spindle's cycle: read -> read back -> step -> shape -> write -> journal -> save.

Each period :meth:`SpindleRuntime.cycle` reads the speed through the adapter
(:meth:`_read_speed`), checks the offset the controller holds (:meth:`_read_back`), steps the
model on the measured elapsed time (``Predictor.step``), shapes the offset
(:meth:`OffsetTracker.plan`), writes ``A = -S`` (``Adapter.write_offset_um``), journals the
cycle and saves the state when due. The controller's offset is the truth:

- it is read back at start, after every reconnect and every ``faults.readback_every`` cycles;
  a value further than ``faults.offset_tolerance_um`` from the one written raises
  ``OFFSET_MISMATCH`` (cause: reset to zero, or an outside write) and the offset ramps from
  there to the model's through the slew limit, written again in the same cycle. A controller
  that keeps refusing (``faults.max_mismatches`` in a row) is not fought: writes back off;
- speed read fails: hold the last speed up to ``faults.speed_hold_s``, then assume idle
  (n = 0), with an alarm; the model keeps running on that assumption;
- the link is down or times out (:class:`LinkHealth`): no write at all (never a stale value),
  ``OUTAGE`` after ``faults.max_outage_s``;
- speed above the calibrated range: clamp to its top (default) or extrapolate, with an alarm;
- a model with inputs: its speed-only fallback is always stepped and stands in, with an alarm,
  while an input is missing, out of range or stale; an input outside the range seen in
  calibration (but valid) raises ``INPUTS_EXTRAPOLATED``;
- the error to expect: where the fit stated one (``fit.expected_error``), each cycle takes the
  figure of the model in use for the speed and how far the inputs lie outside the trained range
  (:meth:`_expected_error`); above ``max_expected_error_um``, or where validation scored nothing
  like it (the figure a floor) while a bound is set, ``EXPECTED_ERROR_HIGH``. Advice: the offset
  is the same;
- the disk fails: a journal row or a state save that cannot be written raises an alarm naming
  the file and the OS error and is retried with back-off; compensation goes on;
- start-up: the saved state is advanced through the downtime as an idle spindle; missing, older
  than ``max_state_age_s`` or corrupt (kept aside as ``*.corrupt-<time>``): a cold start, every
  model at its own equilibrium (the one with inputs at the first speed and inputs read);
- a model file for another spindle than the configured ``spindle_id`` is refused;
- the closed loop (``[spindle.observer] enabled``): the estimate is the model's plus the
  observer's bias (:class:`~compensator.fusion.FusedPredictor`). Each cycle, after the step, the
  controller's new measurement (``Adapter.read_measurement``) and those sent with
  ``thermocomp measure`` are fused against the estimate of this cycle or the last, whichever ran
  slower (a setter measures at rest), each journaled (:class:`MeasurementJournal`); a measurement
  beyond the gate raises ``PROBE_REJECTED`` and leaves the estimate alone, a source that fails
  ``PROBE_FAILED``, none accepted for ``stale_after_s`` ``OBSERVER_STALE``. One observer state
  serves the model in use: at a switch between the model with inputs and its fallback the bias
  is rebased so that the estimate does not jump. A correction reaches the controller through the
  shaper's slew limit like any change of the estimate;
- speed transients (``[spindle.shaping]``): each cycle the controller's cutting signal
  is read where the adapter has one (``Adapter.read_cutting``) and handed to the shaper, which
  otherwise infers it from the speed. With the default ``dual-slew`` policy the offset moves at
  ``not_cutting_rate_um_per_s`` while the tool is clear of the part (the elastic step of a speed
  change lands during the run-up) and at ``max_rate_um_per_s`` while it cuts. A signal that
  cannot be read raises ``CUTTING_SIGNAL_FAILED`` and the cycle infers it from the speed. The
  journal records, every cycle, whether the tool was taken to cut, from which source, the
  policy's state and the slew limit in force.

Every transition is a structured event (:mod:`.events`). Time is injected (``clock`` monotonic
seconds, ``wall`` epoch seconds): tests run in simulated time without sleeping. The journal's
``time_s`` is the monotonic clock anchored to the wall once, so its steps are the model's dt.
"""

from __future__ import annotations

import collections
import enum
import logging
import math
import re
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from cnc_adapters import AdapterError, UnreachableError, WriteRejectedError, open_adapter
from compensator.drift import DriftConfig, DriftState, miss_sd_um
from compensator.drift import update as drift_update
from compensator.errors import (
    AdapterTimeoutError,
    BadValueError,
    ConfigError,
    ModelError,
    ModelFileError,
)
from compensator.estimate import Estimate, EstimateState, Step
from compensator.expected import MIN_FORWARD_FOLDS, ExpectedError, parse_expected, place
from compensator.fusion import FusedState
from compensator.io import (
    Journal,
    MeasurementJournal,
    load_any_model,
    load_state,
    model_digest,
    quarantine,
    save_state,
)
from compensator.io.history import ModelHistory, fit_summary
from compensator.io.journal import ALARM_COLD_START, SHADOW_COLUMN
from compensator.io.journal_export import iso
from compensator.modelbase import SAVED_LIMIT_UM, saved_numbers
from compensator.observer import SIGMA_LIMIT_UM
from compensator.predictor import Predictor
from compensator.shaping import ShapedOffset

from .config import SpindleConfig
from .events import event
from .link import LinkHealth, LinkState
from .offset import OffsetTracker

log = logging.getLogger("thermocomp.runtime")

_SHA256 = re.compile(r"[0-9a-f]{64}")

JOURNAL_INPUTS_RETRY_S = 60.0
"""After a failed read of the input channels for the journal alone, wait this long [s]."""

CLOCK_STEP_S = 2.0
"""A jump of the wall clock against the monotonic clock larger than this is a clock step."""

DOWNTIME_RECHECK_S = 3600.0
"""For this long after a restore [s], the first forward clock step measures the downtime again
(a box that booted with its clock behind, until time synchronisation steps it)."""


class Alarm(enum.IntFlag):
    NONE = 0
    SPEED_READ_FAILED = 1
    IDLE_ASSUMED = 2
    OVER_RANGE = 4
    LINK_DOWN = 8
    WRITE_REJECTED = 16
    COLD_START = ALARM_COLD_START
    OUTAGE = 64
    NOT_READY = 128
    INPUT_FALLBACK = 256
    OFFSET_MISMATCH = 512
    WRITE_BACKOFF = 1024
    JOURNAL_FAILED = 2048
    STATE_SAVE_FAILED = 4096
    STATE_STALE = 8192
    STATE_CORRUPT = 16384
    CLOCK_STEP = 32768
    RELOAD_FAILED = 65536
    INPUTS_EXTRAPOLATED = 131072
    PROBE_REJECTED = 262144
    OBSERVER_STALE = 524288
    PROBE_FAILED = 1048576
    CUTTING_SIGNAL_FAILED = 2097152
    ESTIMATE_REFUSED = 4194304
    EXPECTED_ERROR_HIGH = 8388608
    MODEL_DRIFT = 16777216
    # a cold start (no usable saved state) whose first speed read shows the spindle turning (at
    # least TURNING_MIN_RPM, or 1 % of the calibrated top): the machine is probably warm, the
    # estimate starts from rest. Raised until cold_start_settle_taus (3) x the model's slowest
    # time constant have passed (the start's error decayed to exp(-k), 5 %), or until the observer
    # takes a measurement (accepted, or the bias restarted from it); a restart does not clear it.
    COLD_START_TURNING = 33554432


TURNING_MIN_RPM = 10.0
"""Below this |speed| [rpm] (or 1 % of the calibrated top, whichever is larger) a spindle is not
taken as turning at a cold start: a reading's noise, not a machine at work."""


def slowest_tau_s(model: Any) -> float | None:
    """The slowest time constant [s] of ``model`` anywhere in its speed range, its input lags
    and its fallback included; None where the model states none. A wrong initial state decays
    with the model's own dynamics, so after k of these it has fallen to exp(-k) of itself."""
    parts = [model, getattr(model, "model", None)]  # a fused model wraps its own
    parts += [
        getattr(m, k, None)
        for m in list(parts)
        if m is not None
        for k in ("speed_model", "fallback")
    ]
    taus: list[float] = []
    for m in parts:
        if m is None:
            continue
        lo, hi = getattr(m, "speed_range_rpm", (0.0, 0.0))
        if callable(getattr(m, "time_constants_s", None)):
            for n in (0.0, lo, (lo + hi) / 2, hi):
                taus += [float(t) for t in m.time_constants_s(n)]
        taus += [float(t.tau_s) for t in getattr(m, "inputs", None) or () if hasattr(t, "tau_s")]
    taus = [t for t in taus if math.isfinite(t) and t > 0]
    return max(taus) if taus else None


_LINK_ERRORS = (UnreachableError, AdapterTimeoutError)
"""Failures that mean the controller cannot be reached: refused, lost, or not answering."""

Reply = Callable[[dict[str, Any]], None]
"""Where the outcome of a measurement sent by ``thermocomp measure`` goes."""


def cutting_from_controller(cfg: SpindleConfig, adapter: Any) -> bool:
    """Whether the spindle takes its cutting state from the controller: the link has a signal
    and the configuration does not say ``speed``. ConfigError where the configuration requires
    one (``controller``) and the link has none."""
    signal = cfg.shaping.cutting.signal
    has_signal = bool(getattr(adapter, "can_read_cutting", False))
    if signal == "controller" and not has_signal:
        raise ConfigError(
            f"spindle {cfg.name}: shaping.cutting.signal = 'controller', but the "
            "adapter has no cutting signal configured (cutting_node for OPC UA, "
            "cutting for LinuxCNC, cutting_register for Modbus)"
        )
    return has_signal and signal != "speed"


def mismatch_cause(held_um: float, tolerance_um: float) -> str:
    """Who probably changed the controller's offset."""
    if abs(held_um) <= tolerance_um:
        return "reset to zero (controller restart, NC reset or power cycle)"
    return "an outside write (operator, NC program or another client)"


class SpindleRuntime:
    """One spindle's model, offset machine, link health, adapter, state file and journal."""

    def __init__(
        self,
        cfg: SpindleConfig,
        state_dir: Path,
        journal_dir: Path,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
        adapter: Any = None,
        anchor_s: float | None = None,
        journal_fsync_s: float = 10.0,
        previous: SpindleRuntime | None = None,
    ):
        self.cfg = cfg
        self.clock = clock
        self.wall = wall
        # journal time = monotonic + anchor: increasing, and its steps are the model's dt
        self.anchor_s = wall() - clock() if anchor_s is None else anchor_s
        self._skew_s: float | None = None
        # after a restore: the saved state, the downtime applied and the cycles since (speed, dt,
        # times, inputs), so that a clock that was wrong at the start can be corrected
        self._restored: tuple[Any, float, float, float, float] | None = None
        self._since_start: list[tuple[Any, ...]] | None = None
        loaded: Predictor = load_any_model(cfg.model)
        cfg.refuse_other_spindle(loaded.spindle_id)
        self.digest = model_digest(loaded)
        # the model, its fallback, the observer and the speed clamp: one object, as replay runs it
        self.estimate: Estimate = cfg.estimate(loaded)
        self.est: EstimateState = self.estimate.cold()
        # the error each model's fit stated, read once per load: the model with inputs carries
        # its own, its speed-only fallback (which stands in when an input fails) another
        fallback = getattr(loaded, "fallback", None)
        self.expected: ExpectedError | None = parse_expected(getattr(loaded, "fit", None))
        self.expected_fallback: ExpectedError | None = (
            None if fallback is None else parse_expected(getattr(fallback, "fit", None))
        )
        self._expected_high: str | None = None  # why EXPECTED_ERROR_HIGH is raised, while it is
        if cfg.max_expected_error_um is not None:
            if self.expected is None and self.expected_fallback is None:
                log.warning(
                    "%s: max_expected_error_um = %g, but model %s states no expected error "
                    "(fit it again to have one): the bound is not checked",
                    cfg.name,
                    cfg.max_expected_error_um,
                    cfg.model,
                )
            folds = min(
                (e.forward_folds for e in (self.expected, self.expected_fallback) if e is not None),
                default=MIN_FORWARD_FOLDS,
            )
            if folds < MIN_FORWARD_FOLDS:
                log.warning(
                    "%s: the expected error of model %s rests on %d fold(s) predicted forward "
                    "(fewer than %d): it is only a floor, so EXPECTED_ERROR_HIGH stands while "
                    "max_expected_error_um is set; fit on more cycles",
                    cfg.name,
                    cfg.model,
                    folds,
                    MIN_FORWARD_FOLDS,
                )
        self.state_path = Path(state_dir) / f"{cfg.name}.state.json"
        self.adapter = adapter if adapter is not None else open_adapter(cfg.adapter, clock=clock)
        if self.estimate.with_inputs is not None:
            missing = sorted(
                set(self.estimate.with_inputs.input_names) - set(self.adapter.input_channels())
            )
            if missing:
                raise ConfigError(
                    f"spindle {cfg.name}: the model needs input(s) {', '.join(missing)}; "
                    "map them in the adapter (input_nodes for OPC UA, input_registers "
                    "for Modbus)"
                )
        # a candidate in shadow (thermocomp refit): stepped beside the live model each cycle and
        # journaled, never written to the controller
        self.shadow: Estimate | None = None
        self.shadow_digest: str | None = None
        self.shadow_est: EstimateState | None = None
        self._load_shadow(ModelHistory.of(state_dir, cfg.name).shadow_path)
        self.cutting_from_controller = cutting_from_controller(cfg, self.adapter)
        self._cutting_error: str | None = None  # why the controller's signal failed
        self._run_up_until = -math.inf  # the speed was seen changing, the tool not cutting
        # every input channel the link reads is journaled, used by the model or not: a journal
        # can then be refitted with inputs
        self.journal = Journal(
            journal_dir,
            cfg.name,
            {"spindle": cfg.name, "model": cfg.model, "source": "thermocomp run"},
            fsync_every_s=journal_fsync_s,
            input_columns=tuple(self.adapter.input_channels())
            + ((SHADOW_COLUMN,) if self.shadow is not None else ()),
        )
        self._inputs_read: dict[str, float] = {}  # this cycle's input values, for the journal
        self._journal_inputs_after = -math.inf  # a failed journal-only read waits till then
        self.last: dict[str, Any] | None = None  # the last cycle's outcome, for the status
        self.last_write_s: float | None = None  # clock time of the last offset written
        self._write_done_s: float | None = None  # clock time the last write returned
        self.last_readback_um: float | None = None  # what the controller held when last read back
        self.measurements = MeasurementJournal(
            journal_dir,
            cfg.name,
            {"spindle": cfg.name, "model": cfg.model, "source": "thermocomp run"},
            fsync_every_s=journal_fsync_s,
        )
        self.counters = {
            "cycles": 0,
            "writes": 0,
            "write_rejected": 0,
            "read_failed": 0,
            "link_down_cycles": 0,
            "readbacks": 0,
            "mismatches": 0,
            "journal_failed": 0,
            "state_save_failed": 0,
            "probes_accepted": 0,
            "probes_rejected": 0,
            "probes_restarted": 0,
            "probes_failed": 0,
            "steps_refused": 0,
        }
        self._refused: str | None = None  # why the estimate's last step was refused, while it is
        # COLD_START_TURNING: the clock time the estimate counts as settled while raised (inf: only
        # a measurement settles it); _cold_unjudged from a cold start until a speed is read
        self.cold_settle_s: float | None = None
        self._cold_unjudged = False
        # until then the model alone still carries the cold start's error (a measurement corrects
        # the estimate through the bias, not the model): its misses are no evidence of drift
        self._cold_model_until_s = -math.inf
        self.link_error: str | None = None  # why the link went down, while it is
        # the last cycle the controller held the offset the shaper aimed at (a write went
        # through, or none was due): the spindle's state counts cycles from here
        self.last_in_step_s: float | None = None
        self.created_s = clock()
        # measurements from `thermocomp measure`: (um, sigma or None, reply), fused next cycle
        self._queued: collections.deque[tuple[float, float | None, Reply | None]] = (
            collections.deque()
        )
        self._probe_rejected = False  # the last measurement was beyond the gate
        # source -> (why it failed, whether a value was refused: held until a usable one)
        self._source_errors: dict[str, tuple[str, bool]] = {}
        self._observer_stale = False
        # has the spindle changed since the model was fitted: a CUSUM on the model's misses at
        # each measurement; a new runtime (start, reload) starts it afresh, a known event
        self.drift = DriftState()
        self._drift_config = DriftConfig(k=cfg.drift.k, h=cfg.drift.h, grace=cfg.drift.grace)
        self.alarms = Alarm.NONE
        self._startup_alarms = Alarm.NONE  # journaled with the first cycle
        self.sticky_alarms = Alarm.NONE  # set by the service (a refused reload)
        self.link = LinkHealth(cfg.faults.max_outage_s)
        self._last_t: float | None = None
        self._first_t: float | None = None
        self._last_good_read: float | None = None
        self._last_speed = 0.0
        self.writes_offset = True  # False: `[cooling] mode = "cooling"`, the chiller only
        self._idle_assumed = False
        self._last_save = -math.inf
        self._last_good_save: float | None = None
        self._save_failures = 0
        self._next_save_try = -math.inf
        self._save_error: str | None = None
        self._state_alarms = Alarm.NONE
        self._stale = False
        self._journal_error: str | None = None
        self._need_readback = True
        self._since_readback = 0
        self._reconnects = getattr(self.adapter, "reconnects", 0)
        self._mismatch_streak = 0
        self._wrote_since_check = False
        self._writes_paused_until = -math.inf
        self.history = ModelHistory.of(state_dir, cfg.name, cfg.learning.keep_models)
        self._record_in_use(
            loaded,
            "the service started with it"
            if previous is None
            else "a reload found it in the configuration",
        )
        if previous is not None and previous.digest == self.digest:
            self._carry_over(previous)  # a reload: the state in memory, not the one on disk
            self.drift = previous.drift  # the same model: the evidence holds
        elif previous is not None:
            self._switch_model(previous)  # a promotion or a rollback: from where the old one was
        else:
            self.restore()
        if self.shadow is not None:
            if (
                previous is not None
                and previous.shadow_digest == self.shadow_digest
                and previous.shadow_est is not None
            ):
                self.shadow_est = previous.shadow_est
            else:  # from the live model's own estimate (the bias is the live model's)
                self.shadow_est = self.shadow.begin(
                    self.est.estimate_um - self.est.bias_um, self._last_speed
                )
                event(
                    "shadow_started",
                    cfg.name,
                    "%s: candidate %s runs in shadow from %.2f um (journaled as %s, never written)",
                    cfg.name,
                    self.shadow_digest[:16],
                    self.est.estimate_um - self.est.bias_um,
                    SHADOW_COLUMN,
                    digest=self.shadow_digest,
                )
        self.alarms = self._startup_alarms

    @property
    def can_read_offset(self) -> bool:
        return bool(getattr(self.adapter, "can_read_offset", False))

    # -- state -------------------------------------------------------------------------

    def _cold(self, reason: str) -> None:
        # nothing known: the model's own equilibrium at rest (0 um for a speed-only ThermalModel)
        self.est = self.estimate.cold()
        self.offset = OffsetTracker(self.cfg.shaping, 0.0)
        self._startup_alarms |= Alarm.COLD_START
        self._cold_unjudged = True  # turning or not: judged at the first speed read
        event(
            "cold_start",
            self.cfg.name,
            "%s: cold start (%s)",
            self.cfg.name,
            reason,
            level=logging.WARNING,
            reason=reason,
        )

    def restore(self) -> None:
        """The saved state, advanced through the downtime; a cold start when there is none
        that fits. A corrupt file is moved aside and never crashes the start."""
        now = self.wall()
        try:
            saved = load_state(self.state_path)
            if saved is None:
                return self._cold("no saved state")
            sha = saved.get("model_sha256")
            if not (isinstance(sha, str) and _SHA256.fullmatch(sha)):
                raise ModelFileError(f"model_sha256 is {str(sha)[:70]!r}, not a digest")
            if sha != self.digest:
                return self._cold("saved state belongs to another model")
            saved_wall = saved_numbers("saved_wall_s", [saved["saved_wall_s"]], 1e11)[0]
            held = saved_numbers("offset_um", [saved.get("offset_um", 0.0)])[0]
            if saved_wall <= 0:
                raise ModelFileError(f"saved_wall_s {saved_wall:g} is not a time")
            parsed = self.estimate.parse_saved(saved)
        except (
            ModelError,
            ValueError,
            TypeError,
            KeyError,
            AttributeError,
            RecursionError,
            OverflowError,
        ) as err:
            stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(now))
            moved = quarantine(self.state_path, stamp)
            self._startup_alarms |= Alarm.STATE_CORRUPT
            event(
                "state_corrupt",
                self.cfg.name,
                "%s: state file %s is corrupt (%s); kept as %s",
                self.cfg.name,
                self.state_path,
                str(err)[:200],
                moved or "(could not be moved)",
                level=logging.ERROR,
                path=str(self.state_path),
                kept_as=moved,
            )
            return self._cold("corrupt state file")
        age = now - saved_wall
        if age > self.cfg.max_state_age_s:
            return self._cold(f"saved state is {age / 3600:.1f} h old")
        downtime = max(0.0, age)
        # the spindle stood still while we were down: the model's own cooling; the input
        # model's state is advanced once the inputs are read
        self.est = self.estimate.resume(parsed, downtime, now, self.cfg.max_state_age_s)
        self._restored, self._since_start = (parsed, saved_wall, downtime, self.clock(), now), []
        # what we last wrote; the first cycle reads back what the controller really holds
        self.offset = OffsetTracker(self.cfg.shaping, held)
        unsettled = saved.get("cold_start_unsettled_until_wall_s")
        if (
            isinstance(unsettled, (int, float))
            and not isinstance(unsettled, bool)
            and unsettled > now
        ):
            # a restart does not settle an estimate: the rest of the wait carries over
            self.cold_settle_s = self.clock() + min(float(unsettled) - now, 1e9)
            self._cold_model_until_s = self.cold_settle_s
            event(
                "cold_start_turning",
                self.cfg.name,
                "%s: COLD_START_TURNING carried over a restart: the "
                "estimate of the last cold start settles at %s, or at a measurement accepted",
                self.cfg.name,
                iso(float(unsettled)),
                level=logging.WARNING,
                settles_wall_s=float(unsettled),
                carried=True,
            )
        event(
            "state_restored",
            self.cfg.name,
            "%s: restored state, advanced %.0f s idle: S = %.2f um",
            self.cfg.name,
            downtime,
            self.state.elongation_um,
            downtime_s=round(downtime, 3),
            elongation_um=self.state.elongation_um,
            offset_um=held,
        )

    def _carry_over(self, old: SpindleRuntime) -> None:
        """Continue ``old`` (same model) after a reload: its thermal and input state, the offset
        the controller holds, the timing of the last cycle and the state-save bookkeeping. The
        new link reads the offset back first."""
        self.est = self.estimate.adopt(
            old.est
        )  # the whole estimate, the observer as configured now
        self._queued, old._queued = old._queued, collections.deque()
        self._probe_rejected, self._source_errors = old._probe_rejected, dict(old._source_errors)
        self._observer_stale = old._observer_stale
        self.offset = OffsetTracker(self.cfg.shaping, old.offset.held_um)
        self.offset.shaper.follow(old.offset.shaper)  # the speed it was settling at, and since when
        self._run_up_until, self._cutting_error = old._run_up_until, old._cutting_error
        self._expected_high = old._expected_high  # raised still: no second entry event
        self._carry_status(old)
        self._last_t, self._first_t = old._last_t, old._first_t
        self._last_good_read, self._last_speed = old._last_good_read, old._last_speed
        self._skew_s, self._write_done_s = old._skew_s, old._write_done_s
        for name in (
            "_last_save",
            "_last_good_save",
            "_save_failures",
            "_next_save_try",
            "_save_error",
            "_stale",
            "_state_alarms",
            "_journal_error",
            "_restored",
            "_since_start",
        ):
            setattr(self, name, getattr(old, name))

    def _carry_status(self, old: SpindleRuntime) -> None:
        """What the spindle's state is judged on goes on through a reload: the last writes, and an
        unsettled cold start (a new configuration does not settle an estimate)."""
        self.cold_settle_s, self._cold_unjudged = old.cold_settle_s, old._cold_unjudged
        self._cold_model_until_s = old._cold_model_until_s
        self.last_write_s, self.last_in_step_s = old.last_write_s, old.last_in_step_s
        self.created_s = old.created_s

    def _load_shadow(self, path: Path) -> None:
        """The candidate in shadow, when ``path`` holds one for this spindle; a file that does not
        load or belongs to another spindle is said once and left alone: the live model runs on."""
        if not path.is_file():
            return
        try:
            model = load_any_model(path)
            self.cfg.refuse_other_spindle(model.spindle_id)
            if model.input_names and not set(model.input_names) <= set(
                self.adapter.input_channels()
            ):
                raise ConfigError(
                    f"it needs input(s) {', '.join(model.input_names)} the link does not read"
                )
            self.shadow = replace(
                self.cfg.estimate(model), observer=None
            )  # open loop: its own misses
            self.shadow_digest = model_digest(model)
        except (ModelError, ConfigError, OSError) as err:
            event(
                "shadow_failed",
                self.cfg.name,
                "%s: the shadow candidate %s is not run: %s",
                self.cfg.name,
                path,
                str(err)[:200],
                level=logging.WARNING,
                path=str(path),
            )

    def _step_shadow(
        self,
        speed: float,
        dt: float,
        now: float,
        wall_now: float,
        inputs: Any,
        input_error: str | None,
    ) -> None:
        """One cycle of the shadow candidate; whatever it does, the live model is not touched."""
        assert self.shadow is not None and self.shadow_est is not None
        try:
            self.shadow_est, _ = self.shadow.step(
                self.shadow_est,
                speed,
                dt,
                now_s=now,
                wall_s=wall_now,
                inputs=inputs,
                input_error=input_error,
            )
        except ModelError as err:
            event(
                "shadow_failed",
                self.cfg.name,
                "%s: the shadow candidate %s stopped: %s",
                self.cfg.name,
                (self.shadow_digest or "")[:16],
                str(err)[:200],
                level=logging.WARNING,
            )
            self.shadow = self.shadow_est = None

    def _record_in_use(self, model: Predictor, reason: str) -> None:
        """Keep the model in the history when it is not the one recorded in use (a promotion or
        a rollback recorded it already). The history is a record: failing to write it never
        stops compensation."""
        try:
            live = self.history.live()
            if live is None or live.digest != self.digest:
                self.history.add(
                    "in_use",
                    self.cfg.model,
                    reason=reason,
                    at_wall_s=self.wall(),
                    fit=fit_summary(model),
                )
        except (OSError, ConfigError) as err:
            event(
                "history_failed",
                self.cfg.name,
                "%s: the model history %s could not be written: %s; compensation goes on",
                self.cfg.name,
                self.history.directory,
                getattr(err, "strerror", None) or err,
                level=logging.WARNING,
                path=str(self.history.directory),
            )

    def _switch_model(self, old: SpindleRuntime) -> None:
        """Continue ``old`` with another model (a promotion, a rollback, an edited file): the new
        model starts at the old estimate, at the speed last read (its states at equilibrium there,
        the difference decaying with its slowest time constant), so the estimate does not jump;
        the offset the controller holds, the shaper and the timing carry over like a reload's, and
        the offset moves from there at the slew limit as ever."""
        self.est = self.estimate.begin(old.estimate_um(), old._last_speed)
        self._queued, old._queued = old._queued, collections.deque()
        self.offset = OffsetTracker(self.cfg.shaping, old.offset.held_um)
        self.offset.shaper.follow(old.offset.shaper)
        self._run_up_until, self._cutting_error = old._run_up_until, old._cutting_error
        self._last_t, self._first_t = old._last_t, old._first_t
        self._last_good_read, self._last_speed = old._last_good_read, old._last_speed
        self._skew_s, self._write_done_s = old._skew_s, old._write_done_s
        for name in (
            "_last_save",
            "_last_good_save",
            "_save_failures",
            "_next_save_try",
            "_save_error",
            "_stale",
            "_state_alarms",
            "_journal_error",
        ):
            setattr(self, name, getattr(old, name))
        self._carry_status(old)  # the new model starts at the old estimate, unsettled as it was
        self._last_save = -math.inf  # the new model's state is saved at once
        event(
            "model_switched",
            self.cfg.name,
            "%s: model %s in use (was %s), starting at the old estimate %.2f um",
            self.cfg.name,
            self.digest[:16],
            old.digest[:16],
            old.estimate_um(),
            level=logging.WARNING,
            digest=self.digest,
            previous=old.digest,
            elongation_um=old.estimate_um(),
        )

    def take_journal(self, old: SpindleRuntime) -> None:
        """Write on through ``old``'s journal: the rows it still holds in memory are not lost."""
        if old.journal.directory == self.journal.directory:
            if (
                old.journal.input_columns == self.journal.input_columns
            ):  # else a new part, new header
                self.journal.close()  # never opened: nothing written yet
                self.journal, old.journal = old.journal, self.journal
            self.measurements.close()
            self.measurements, old.measurements = old.measurements, self.measurements

    def save_state(self, now: float | None = None) -> bool:
        """Save the state; a failure is an alarm and a retry with back-off, never an exception."""
        now = self.clock() if now is None else now
        wall_now = self.wall()
        try:
            save_state(
                self.state_path,
                {
                    "spindle": self.cfg.name,
                    "model_sha256": self.digest,
                    "saved_wall_s": wall_now,
                    **self.estimate.state_dict(self.est, wall_now),
                    "offset_um": self.offset.held_um,
                    **(
                        {}
                        if self.cold_settle_s is None
                        else {
                            "cold_start_unsettled_until_wall_s": wall_now
                            + min(self.cold_settle_s - now, 1e9)
                        }
                    ),
                },
            )
        except (OSError, ValueError) as err:
            self.counters["state_save_failed"] += 1
            self._save_failures += 1
            faults = self.cfg.faults
            self._next_save_try = now + min(
                faults.max_write_backoff_s, faults.state_retry_s * 2 ** (self._save_failures - 1)
            )
            why = f"{self.state_path}: {getattr(err, 'strerror', None) or err}"  # not the temp file
            if why != self._save_error:
                event(
                    "state_save_failed",
                    self.cfg.name,
                    "%s: cannot save the state: %s; compensation goes on, retrying",
                    self.cfg.name,
                    why,
                    level=logging.ERROR,
                    path=str(self.state_path),
                    error=why,
                )
            self._save_error = why
            return False
        self._last_save = now
        self._last_good_save = now
        if self._save_error is not None:
            event(
                "state_saved_again",
                self.cfg.name,
                "%s: state saved again after %d failure(s)",
                self.cfg.name,
                self._save_failures,
                path=str(self.state_path),
            )
        self._save_error, self._save_failures, self._stale = None, 0, False
        self._next_save_try = -math.inf
        return True

    # -- the observer ----------------------------------------------------------------

    # where the estimate stands (read-only views of ``self.est``)
    @property
    def state(self) -> Any:
        """The speed-only model's state, with the observer's when fused."""
        return self.est.core

    @property
    def input_state(self) -> Any:
        return self.est.inputs

    @property
    def refs(self) -> dict[str, float] | None:
        return None if self.est.references is None else dict(self.est.references)

    @property
    def speed_only_state(self) -> Any:
        """The speed-only model's own state (without the observer)."""
        return self.est.speed_only

    @property
    def last_speed_rpm(self) -> float:
        """The last speed read [rpm]."""
        return self._last_speed

    def estimate_um(self) -> float:
        """The estimate the offset follows: the model in use, plus the observer's bias."""
        return self.est.estimate_um

    def submit(
        self, elongation_um: float, sigma_um: float | None, reply: Reply | None = None
    ) -> None:
        """A measurement from `thermocomp measure`, fused at the next cycle; ``reply`` gets the
        outcome (or an error)."""
        if self.estimate.fused is None:
            if reply is not None:
                reply(
                    {
                        "ok": False,
                        "error": f"spindle {self.cfg.name} has no observer "
                        "([spindle.observer] enabled = true)",
                    }
                )
            return
        self._queued.append((elongation_um, sigma_um, reply))

    def observer_status(self) -> dict[str, Any] | None:
        """The observer's state for people and status lines; None without one."""
        if not isinstance(self.state, FusedState):
            return None
        z = self.state.observer
        age = self.state.since_measurement_s
        return {
            "bias_um": z.bias_um,
            "bias_sd_um": z.bias_sd_um,
            "since_measurement_s": age,
            "stale": self._observer_stale,
            "rejected": self._probe_rejected,
            "failed_sources": {k: why for k, (why, _) in self._source_errors.items()},
        }

    def _measurements(self, now: float, wall_now: float, speed: float) -> Alarm:
        """Fuse what came since the last cycle: the controller's new measurement, then those
        sent with `thermocomp measure`. A source that fails is an alarm, never a stop."""
        alarms = Alarm.NONE
        source = str(getattr(self.adapter, "name", "adapter"))
        if self.link.up and getattr(self.adapter, "can_read_measurement", False):
            try:
                m = self.adapter.read_measurement()
            except AdapterError as err:
                # a value refused (its counter taken as seen) or a failed read, even a timeout:
                # the speed read and the write judge the link, so the probe never stops them
                self._source_failed(now, wall_now, source, err, isinstance(err, BadValueError))
            else:
                failed = self._source_errors.get(source)
                if failed is not None and not failed[1]:
                    self._source_errors.pop(source)  # it reads again
                if m is not None:
                    self._fuse(now, wall_now, m.elongation_um, m.sigma_um, m.source, m.sequence)
        while self._queued:
            y, sigma, reply = self._queued.popleft()
            answer = self._fuse(now, wall_now, y, sigma, "control", None)
            if reply is not None:
                reply(answer)
        if self._probe_rejected:
            alarms |= Alarm.PROBE_REJECTED
        if self.drift.detected:
            alarms |= Alarm.MODEL_DRIFT
        if self._source_errors:
            alarms |= Alarm.PROBE_FAILED
        return alarms | self._staleness(now)

    def _source_failed(
        self, now: float, wall_now: float, source: str, err: Exception, refused: bool
    ) -> None:
        """PROBE_FAILED: until the source reads again, or, for a value refused, until it gives a
        usable one. A refused value is journaled; a failing read once per new reason."""
        self.counters["probes_failed"] += 1
        why = str(err)[:200]
        if self._source_errors.get(source, ("",))[0] != why:
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
        self._source_errors[source] = (why, refused)
        if refused:
            self.measurements.record(
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
        now: float,
        wall_now: float,
        y: float,
        sigma_um: float | None,
        source: str,
        sequence: int | None,
    ) -> dict[str, Any]:
        """Fuse one measurement against the estimate of the cycle it was taken in (this one, or
        the last when that ran slower: :meth:`compensator.estimate.Estimate.measure`); journal it."""
        assert self.estimate.fused is not None
        sigma = self.cfg.observer.sigma_um if sigma_um is None else sigma_um
        err: Exception | None = None
        if not (
            math.isfinite(y)
            and abs(y) <= SAVED_LIMIT_UM
            and math.isfinite(sigma)
            and 0 < sigma <= SIGMA_LIMIT_UM
        ):
            err = BadValueError(
                f"{source}: measurement {y!r} um (sigma {sigma!r} um) is not usable: "
                f"|value| <= {SAVED_LIMIT_UM:g} um and 0 < sigma <= {SIGMA_LIMIT_UM:g} um"
            )
        else:
            try:
                bias_before = self.state.observer.bias_um
                self.est, up, before = self.estimate.measure(self.est, y, sigma)
            except ModelError as refused:  # the estimate it would give is none a spindle has
                err = BadValueError(f"{source}: {refused}")
        if err is not None:
            self._source_failed(now, wall_now, source, err, True)
            return {"ok": False, "spindle": self.cfg.name, "error": str(err)}
        self._source_errors.pop(source, None)  # it gave a usable value
        self._since_start = None  # the estimate has been measured: it is not re-run from the start
        outcome = "accepted" if up.accepted else "restarted" if up.restarted else "rejected"
        # the model's own miss (without the bias, which absorbs a drift); a rejected one counts too
        self._drift_step(now, y - (before - bias_before), sigma)
        self.counters[f"probes_{outcome}"] += 1
        z = self.state.observer
        self.measurements.record(
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
        if outcome == "rejected":
            event(
                "probe_rejected",
                self.cfg.name,
                "%s: PROBE_REJECTED: measured %.3f um, estimate "
                "%.3f um: innovation %+.3f um is beyond %g sd (%.3f um); estimate unchanged",
                self.cfg.name,
                y,
                before,
                up.innovation_um,
                self.estimate.fused.config.gate_sigma,
                up.innovation_sd_um,
                level=logging.WARNING,
                **fields,
            )
        elif outcome == "restarted":
            event(
                "probe_restart",
                self.cfg.name,
                "%s: measurements agree on a change the model "
                "cannot know: bias restarted at %+.3f um (measured %.3f um, estimate was %.3f um)",
                self.cfg.name,
                z.bias_um,
                y,
                before,
                level=logging.WARNING,
                **fields,
            )
        else:
            event(
                "probe_accepted",
                self.cfg.name,
                "%s: measurement %.3f um accepted (estimate %.3f "
                "um, innovation %+.3f um); bias %+.3f um",
                self.cfg.name,
                y,
                before,
                up.innovation_um,
                z.bias_um,
                **fields,
            )
        # rejected: holds until a measurement is taken again (the estimate was not corrected)
        self._probe_rejected = outcome == "rejected"
        if outcome != "rejected" and self.cold_settle_s is not None:
            self.cold_settle_s = (
                None  # measured: the estimate no longer rests on the cold start's guess
            )
            event(
                "cold_start_settled",
                self.cfg.name,
                "%s: COLD_START_TURNING cleared: measurement %.3f um %s by the observer",
                self.cfg.name,
                y,
                outcome,
                reason="measurement",
                outcome=outcome,
                measured_um=y,
            )
        return {
            "ok": True,
            "spindle": self.cfg.name,
            "outcome": outcome,
            "accepted": up.accepted,
            "restarted": up.restarted,
            "measured_um": y,
            "sigma_um": sigma,
            "estimate_um": before,
            "innovation_um": up.innovation_um,
            "innovation_sd_um": up.innovation_sd_um,
            "gate_sigma": self.estimate.fused.config.gate_sigma,
            "bias_um": z.bias_um,
            "elongation_um": self.estimate_um(),
            "time_s": self.anchor_s + now,
        }

    def _drift_step(self, now: float, miss_um: float, sigma_um: float) -> None:
        """One measurement into the drift detector; MODEL_DRIFT with one event on entry (the
        size and start of the change, what to do) and one on leaving. Left out while the model
        alone still carries the error of a cold start on a turning spindle (the k slowest time
        constants of COLD_START_TURNING, even once a measurement cleared the alarm): that miss
        is the start's, not a change of the spindle."""
        if now < self._cold_model_until_s:
            log.debug(
                "%s: a measurement during an unsettled cold start: not a drift step", self.cfg.name
            )
            return
        stated = self._stated()[0]
        rms = None if stated is None else stated.at(self._last_speed).rms_um
        was = self.drift.detected
        self.drift = drift_update(
            self.drift, miss_um, miss_sd_um(rms, sigma_um), now, self._drift_config
        )
        change = self.drift.change()
        if change is not None and not was:
            size, since, n = change
            event(
                "model_drift",
                self.cfg.name,
                "%s: MODEL_DRIFT: the spindle grows %+.2f um %s the model "
                "says, over the last %d measurements (since %s); refit from production (thermocomp "
                "refit) or recalibrate",
                self.cfg.name,
                size,
                "beyond what" if size > 0 else "against what",
                n,
                iso(self.anchor_s + since),
                level=logging.WARNING,
                size_um=round(size, 3),
                since_s=self.anchor_s + since,
                measurements=n,
                statistic=round(self.drift.statistic, 3),
            )
        elif was and not self.drift.detected:
            event(
                "model_drift_cleared",
                self.cfg.name,
                "%s: MODEL_DRIFT cleared: the model's misses are back within what its fit stated",
                self.cfg.name,
                statistic=round(self.drift.statistic, 3),
            )

    def drift_status(self) -> dict[str, Any]:
        """The drift detector for status lines: its statistic, and the change while one is declared."""
        change = self.drift.change()
        out: dict[str, Any] = {
            "statistic": round(self.drift.statistic, 3),
            "threshold": self._drift_config.h,
            "measurements": self.drift.seen,
            "detected": self.drift.detected,
        }
        if change is not None:
            out.update(
                size_um=round(change[0], 3),
                since_s=self.anchor_s + change[1],
                since=iso(self.anchor_s + change[1]),
            )
        return out

    def _staleness(self, now: float) -> Alarm:
        """OBSERVER_STALE once no measurement has been taken for ``stale_after_s`` (counted from
        this start when there has been none yet, so a new installation does not alarm at once)."""
        assert isinstance(self.state, FusedState)
        limit = self.cfg.observer.stale_after_s
        age = self.state.since_measurement_s
        if age is None:
            age = now - (self._first_t if self._first_t is not None else now)
        stale = age > limit
        if stale and not self._observer_stale:
            event(
                "observer_stale",
                self.cfg.name,
                "%s: OBSERVER_STALE: no measurement taken for "
                "%.0f s (limit %.0f s); the estimate runs open loop",
                self.cfg.name,
                age,
                limit,
                level=logging.WARNING,
                since_measurement_s=round(age, 3),
                stale_after_s=limit,
            )
        elif not stale and self._observer_stale:
            event(
                "observer_fresh",
                self.cfg.name,
                "%s: observer fresh again: a measurement was taken",
                self.cfg.name,
                bias_um=self.state.bias_um,
            )
        self._observer_stale = stale
        return Alarm.OBSERVER_STALE if stale else Alarm.NONE

    def _save_if_due(self, now: float) -> Alarm:
        due = now - self._last_save >= self.cfg.state_save_every_s
        if due and now >= self._next_save_try:
            self.save_state(now)
        if self._save_error is None:
            return Alarm.NONE
        alarms = Alarm.STATE_SAVE_FAILED
        since = self._last_good_save if self._last_good_save is not None else self._first_t
        if since is not None and now - since > self.cfg.faults.state_stale_s:
            alarms |= Alarm.STATE_STALE
            if not self._stale:
                self._stale = True
                event(
                    "state_stale",
                    self.cfg.name,
                    "%s: no state saved for %.0f s: %s",
                    self.cfg.name,
                    now - since,
                    self._save_error,
                    level=logging.CRITICAL,
                    path=str(self.state_path),
                    error=self._save_error,
                )
        return alarms

    # -- the cycle -------------------------------------------------------------------

    def _read_speed(self, now: float) -> tuple[float, Alarm]:
        """The speed to step the model with, and the alarms of reading it."""
        alarms = Alarm.NONE
        try:
            speed = self.adapter.read_speed()
            if not self.estimate.plausible(speed):  # a register read as 0xFFFFFFFF, a unit slip
                raise BadValueError(
                    f"speed {speed:g} rpm is no spindle's (above "
                    f"{self.estimate.speed_limit_rpm:g} rpm): taken as a failed read"
                )
            self._last_good_read = now
            self._last_speed = speed
            if self._idle_assumed:
                self._idle_assumed = False
                event("speed_restored", self.cfg.name, "%s: speed read again", self.cfg.name)
            held = self.adapter.take_write_mismatch()
            if held is not None:  # a deferred check: the controller did not take our last write
                self.counters["write_rejected"] += 1
                alarms |= Alarm.WRITE_REJECTED | self._mismatch(now, held, "deferred write check")
            down_s = self.link.succeeded(now)
            self.link_error = None
            if down_s is not None:
                event(
                    "link_restored",
                    self.cfg.name,
                    "%s: link restored after %.1f s",
                    self.cfg.name,
                    down_s,
                    down_s=round(down_s, 3),
                )
                self._reconnected()
        except AdapterError as err:
            self.counters["read_failed"] += 1
            alarms |= Alarm.SPEED_READ_FAILED
            if isinstance(err, _LINK_ERRORS):
                alarms |= self._link_failed(now, err)
            else:
                log.warning("%s: speed read failed: %s", self.cfg.name, err)
            since = now - (self._last_good_read if self._last_good_read is not None else now)
            if self._last_good_read is not None and since <= self.cfg.faults.speed_hold_s:
                speed = self._last_speed
            else:
                speed = 0.0
                alarms |= Alarm.IDLE_ASSUMED
                if not self._idle_assumed:
                    self._idle_assumed = True
                    event(
                        "idle_assumed",
                        self.cfg.name,
                        "%s: no speed for %.0f s: assuming idle",
                        self.cfg.name,
                        since,
                        level=logging.WARNING,
                        since_s=round(since, 3),
                    )
        return speed, alarms

    def _reconnected(self) -> None:
        """The controller may have lost the offset (a restart clears it): read it back, or,
        where it cannot be read, write it again."""
        self._need_readback = True
        if not self.can_read_offset:
            self.offset.rewrite()

    def _link_failed(self, now: float, err: Exception) -> Alarm:
        before = self.link.state
        state = self.link.failed(now)
        if before is LinkState.CONNECTED:
            self.link_error = str(err)[:200]  # the cause; later attempts only say they failed again
            name = "timeout" if isinstance(err, AdapterTimeoutError) else "link_down"
            event(
                name,
                self.cfg.name,
                "%s: link down: %s",
                self.cfg.name,
                err,
                level=logging.ERROR,
                error=str(err)[:200],
            )
        if state is LinkState.OUTAGE and before is not LinkState.OUTAGE:
            event(
                "outage",
                self.cfg.name,
                "%s: OUTAGE: the controller has not answered for %.0f s; no offset is written",
                self.cfg.name,
                now - (self.link.down_since or now),
                level=logging.CRITICAL,
                down_s=round(now - (self.link.down_since or now), 3),
            )
        return Alarm.LINK_DOWN | (Alarm.OUTAGE if state is LinkState.OUTAGE else Alarm.NONE)

    def _mismatch(self, now: float, held_um: float, when: str) -> Alarm:
        """The controller holds ``held_um``; act on it if it is not what we wrote."""
        expected = self.offset.held_um
        diff = self.offset.observe(held_um, self.cfg.faults.offset_tolerance_um)
        wrote_since, self._wrote_since_check = self._wrote_since_check, False
        if diff is None:
            if wrote_since:  # it took a write of ours: not refusing
                self._mismatch_streak = 0
            return Alarm.NONE
        self.counters["mismatches"] += 1
        self._mismatch_streak += 1
        faults = self.cfg.faults
        cause = mismatch_cause(held_um, faults.offset_tolerance_um)
        if self._mismatch_streak <= faults.max_mismatches:  # then write_backoff speaks for it
            event(
                "offset_mismatch",
                self.cfg.name,
                "%s: OFFSET_MISMATCH (%s): the controller "
                "holds %.3f um, expected %.3f um; probably %s; ramping from there",
                self.cfg.name,
                when,
                held_um,
                expected,
                cause,
                level=logging.ERROR,
                held_um=held_um,
                expected_um=expected,
                cause=cause,
                when=when,
                streak=self._mismatch_streak,
            )
        if self._mismatch_streak >= faults.max_mismatches:
            k = self._mismatch_streak - faults.max_mismatches
            pause = min(faults.max_write_backoff_s, self.cfg.period_s * 2 ** (k + 1))
            self._writes_paused_until = now + pause
            event(
                "write_backoff",
                self.cfg.name,
                "%s: the controller keeps refusing the offset "
                "(%d mismatches in a row): no write for %.3g s",
                self.cfg.name,
                self._mismatch_streak,
                pause,
                level=logging.ERROR,
                pause_s=pause,
                streak=self._mismatch_streak,
            )
        return Alarm.OFFSET_MISMATCH

    def _read_back(self, now: float) -> Alarm:
        """Compare the offset the controller holds with ours, when due."""
        reconnects = getattr(self.adapter, "reconnects", 0)
        if reconnects != self._reconnects:  # the adapter reconnected on its own
            self._reconnects = reconnects
            self._reconnected()
        every = self.cfg.faults.readback_every
        self._since_readback += 1
        due = self._need_readback or (every > 0 and self._since_readback >= every)
        if not (due and self.link.up and self.can_read_offset):
            return Alarm.NONE
        when = (
            "at start"
            if self.counters["readbacks"] == 0
            else ("after a reconnect" if self._need_readback else "periodic check")
        )
        try:
            held = self.adapter.read_offset_um()
        except BadValueError as err:
            # it holds something that is not a number: write ours again, from where we were
            log.warning("%s: offset read-back: %s; writing it again", self.cfg.name, err)
            self._need_readback = False
            self._since_readback = 0
            self.offset.rewrite()
            return Alarm.OFFSET_MISMATCH
        except AdapterError as err:
            if isinstance(err, _LINK_ERRORS):
                return self._link_failed(now, err)
            log.warning("%s: offset read-back failed: %s", self.cfg.name, err)
            return Alarm.NONE
        self.counters["readbacks"] += 1
        self.last_readback_um = held
        self._need_readback = False
        self._since_readback = 0
        return self._mismatch(now, held, when)

    def _write(self, now: float, offset_um: float) -> tuple[bool, Alarm]:
        if now < self._writes_paused_until:
            return False, Alarm.WRITE_BACKOFF
        try:
            self.adapter.write_offset_um(offset_um)
        except WriteRejectedError as err:
            self.counters["write_rejected"] += 1
            self._need_readback = True  # what does it hold now?
            event(
                "write_rejected",
                self.cfg.name,
                "%s: write refused (%d so far): %s",
                self.cfg.name,
                self.counters["write_rejected"],
                err,
                level=logging.ERROR,
                error=str(err)[:200],
            )
            return False, Alarm.WRITE_REJECTED
        except AdapterError as err:
            alarms = Alarm.NONE
            if isinstance(err, _LINK_ERRORS):
                alarms |= self._link_failed(now, err)
            else:
                log.error("%s: write failed: %s", self.cfg.name, err)
            return False, alarms
        self.counters["writes"] += 1
        self.last_write_s = now
        self._write_done_s = self.clock()  # a write a hung controller held took effect only now
        self._wrote_since_check = True
        return True, Alarm.NONE

    def _clock_step(self, now: float, wall_now: float) -> Alarm:
        skew = wall_now - (self.anchor_s + now)
        prev, self._skew_s = self._skew_s, skew
        if prev is None or abs(skew - prev) <= CLOCK_STEP_S:
            return Alarm.NONE
        event(
            "clock_step",
            self.cfg.name,
            "%s: the wall clock stepped by %+.1f s; the journal keeps its monotonic time",
            self.cfg.name,
            skew - prev,
            level=logging.WARNING,
            step_s=round(skew - prev, 3),
        )
        if skew > prev and self._since_start is not None:
            self._downtime_again(now, wall_now)
        return Alarm.CLOCK_STEP

    def _downtime_again(self, now: float, wall_now: float) -> None:
        """The first forward clock step soon after a restore (a box without a real-time clock
        boots with its clock behind; time synchronisation then steps it): the downtime is
        measured again on the corrected clock, and where it was longer the estimate restarts
        from the saved state advanced through it, then is stepped again through every cycle
        since the start."""
        assert self._restored is not None and self._since_start is not None
        parsed, saved_wall, applied, started, restore_wall = self._restored
        since, self._since_start = self._since_start, None  # once
        start_wall = wall_now - (now - started)
        downtime = start_wall - saved_wall
        if downtime <= applied + CLOCK_STEP_S:
            return
        before = self.est.estimate_um
        try:
            est = self.estimate.resume(parsed, downtime, start_wall, self.cfg.max_state_age_s)
            for speed, dt, t, wall, inputs, error in since:
                est, _ = self.estimate.step(
                    est,
                    speed,
                    dt,
                    now_s=t,
                    wall_s=wall + (start_wall - restore_wall),
                    inputs=inputs,
                    input_error=error,
                )
        except ModelError as err:
            log.warning("%s: the downtime could not be applied again: %s", self.cfg.name, err)
            return
        self.est = est
        event(
            "downtime_corrected",
            self.cfg.name,
            "%s: the clock was wrong at the start: the downtime "
            "was %.0f s, not %.0f s; the saved state advanced through it again: S %.2f -> %.2f um",
            self.cfg.name,
            downtime,
            applied,
            before,
            self.est.estimate_um,
            level=logging.WARNING,
            downtime_s=round(downtime, 3),
            applied_s=round(applied, 3),
            elongation_um=self.est.estimate_um,
        )

    def cycle(self) -> dict[str, Any]:
        t_read = time.perf_counter()  # a measurement only: the read->write latency
        now = self.clock()
        wall_now = self.wall()
        if self._first_t is None:
            self._first_t = now
        dt = 0.0 if self._last_t is None else max(0.0, now - self._last_t)
        self._last_t = now
        alarms = self._startup_alarms | self.sticky_alarms | self._clock_step(now, wall_now)
        self._startup_alarms = Alarm.NONE
        read_rpm, read_alarms = self._read_speed(now)
        alarms |= read_alarms
        if self._cold_unjudged and not read_alarms & (Alarm.SPEED_READ_FAILED | Alarm.IDLE_ASSUMED):
            self._judge_cold_start(now, read_rpm)
        speed, over = self.estimate.clamp(read_rpm)  # the speed every part of the cycle uses
        if over:
            alarms |= Alarm.OVER_RANGE
        cutting, cutting_source, cutting_alarms = self._read_cutting()
        alarms |= cutting_alarms
        # a speed not read (held, or idle assumed) says nothing of the tool: it is taken to cut
        # (slow), and the shaper's inference goes on from the last speed read
        shaper_speed = speed
        if read_alarms & (Alarm.SPEED_READ_FAILED | Alarm.IDLE_ASSUMED) and cutting is None:
            cutting, cutting_source, shaper_speed = True, "unread", self._last_speed
        not_ready = self.adapter.not_ready_offset_um() if self.link.up else None
        if not_ready is None and self.writes_offset:  # a machine that is off applies its own value
            alarms |= self._read_back(now)
        self._inputs_read = {}
        inputs, input_error = None, None
        if self.estimate.with_inputs is not None:
            try:
                inputs = self._inputs_read = self.adapter.read_inputs()
            except AdapterError as err:
                input_error = f"inputs not read: {err}"
        extrapolated = self.est.extrapolated
        try:
            self.est, step = self.estimate.step(
                self.est,
                read_rpm,
                dt,
                now_s=now,
                wall_s=wall_now,
                inputs=inputs,
                input_error=input_error,
            )
        except ModelError as err:  # the estimate stays where it was; the offset holds it
            alarms |= self._estimate_refused(err)
        else:
            self._refused = None
            if self.estimate.with_inputs is not None:
                alarms |= self._input_events(step, extrapolated)
            if self.shadow is not None:
                self._step_shadow(read_rpm, dt, now, wall_now, inputs, input_error)
            if self._since_start is not None:  # for a clock found wrong at the start
                assert self._restored is not None
                self._since_start.append((read_rpm, dt, now, wall_now, inputs, input_error))
                if now - self._restored[3] > DOWNTIME_RECHECK_S:
                    self._since_start = None
        if self.estimate.fused is not None:
            alarms |= self._measurements(now, wall_now, speed)
        alarms |= self._cold_start_alarm(now)
        expected, expected_alarm = self._expected_error(
            read_rpm
        )  # the real speed, not the clamped one
        alarms |= expected_alarm
        s = self.estimate_um()
        shaped = self.offset.plan(s, shaper_speed, self._shaper_dt(dt), cutting)
        if shaped.cutting:
            self._run_up_until = -math.inf
        elif self.offset.shaper.state.settled_s == 0.0:  # the speed left its band this cycle
            # a controller may refresh its speed less often than we read: stay fast one period
            self._run_up_until = now + self.cfg.period_s
        wanted = self.offset.wants_write(shaped)
        wrote = False
        if not_ready is not None:
            # machine off, in E-stop or not homed: the controller applies `not_ready`; once it
            # is ready the offset is re-seeded from there through the slew limit
            alarms |= Alarm.NOT_READY
            self.offset.controller_holds(not_ready)
        elif self.link.up and wanted and self.writes_offset:
            wrote, write_alarms = self._write(now, shaped.offset_um)
            alarms |= write_alarms
        elif not self.link.up:
            self.counters["link_down_cycles"] += 1
        latency_ms = (time.perf_counter() - t_read) * 1e3
        if wrote or (not wanted and self.link.up and not_ready is None and self.writes_offset):
            self.last_in_step_s = now  # the controller holds what the shaper aims at
        if wrote:
            self.offset.written(shaped)
        elif not_ready is None:
            self.offset.kept(wanted)
        if now < self._writes_paused_until:
            alarms |= Alarm.WRITE_BACKOFF
        self.counters["cycles"] += 1
        held = self.offset.held_um
        self._journal_inputs(now)
        alarms |= self._state_alarms  # of the last save: a row is journaled before the save
        alarms |= self._journal(
            now, dt, wall_now, speed, s, held, wrote, shaped, cutting_source, alarms
        )
        self._state_alarms = self._save_if_due(now)
        self.alarms = alarms | self._state_alarms
        self.last = {
            "time_s": now,
            "dt_s": dt,
            "speed_rpm": speed,
            "predicted_um": s,
            "target_um": shaped.offset_um,
            "offset_um": held,
            "written": wrote,
            "flags": shaped.flags,
            "alarms": self.alarms,
            "read_to_write_ms": latency_ms,
            "offset_mode": self.offset.mode.value,
            "link": self.link.state.value,
            "observer": self.observer_status(),
            "cutting": shaped.cutting,
            "cutting_source": cutting_source,
            "policy_state": shaped.state,
            "slew_limit_um_per_s": shaped.rate_um_per_s,
            "estimate": (
                "fused"
                if self.estimate.fused is not None
                else "inputs"
                if self.input_state is not None
                else "speed"
            ),
            "inputs": dict(self._inputs_read),
            "expected_error": expected,
            "drift": self.drift_status() if self.estimate.fused is not None else None,
            "shadow": None
            if self.shadow_est is None
            else {"digest": self.shadow_digest, "estimate_um": self.shadow_est.estimate_um},
        }
        return {**self.last, "alarms": alarms}

    def _judge_cold_start(self, now: float, speed_rpm: float) -> None:
        """The first speed read after a cold start: turning, the machine is probably warm while
        the estimate starts from rest, so COLD_START_TURNING is raised until the estimate has
        settled (see :meth:`_cold_start_alarm`)."""
        self._cold_unjudged = False
        turning = max(TURNING_MIN_RPM, 0.01 * self.estimate.core.speed_range_rpm[1])
        if abs(speed_rpm) < turning:
            return
        tau = slowest_tau_s(self.estimate.model)
        k = self.cfg.cold_start_settle_taus
        self.cold_settle_s = now + k * tau if tau is not None else math.inf
        if tau is not None:
            self._cold_model_until_s = self.cold_settle_s
        until = (
            f"until {iso(self.anchor_s + self.cold_settle_s)} ({k:g} x the model's slowest time constant, "
            f"{tau / 60:.0f} min) or"
            if tau is not None
            else "(the model states no time constant) until"
        )
        event(
            "cold_start_turning",
            self.cfg.name,
            "%s: COLD_START_TURNING: cold start with the spindle at "
            "%.0f rpm: the machine is probably warm while the estimate starts from rest; expect a large "
            "error %s a measurement is accepted",
            self.cfg.name,
            speed_rpm,
            until,
            level=logging.WARNING,
            speed_rpm=speed_rpm,
            tau_s=tau,
            settle_taus=k,
            settles_s=None if tau is None else self.anchor_s + self.cold_settle_s,
        )

    def _cold_start_alarm(self, now: float) -> Alarm:
        """COLD_START_TURNING while raised: it clears once ``cold_start_settle_taus`` of the
        model's slowest time constant have passed since it was raised (the cold start's error
        has decayed to exp(-k) of itself, running or not), or at a measurement the observer
        accepts (:meth:`_fuse`)."""
        if self.cold_settle_s is None:
            return Alarm.NONE
        if now < self.cold_settle_s:
            return Alarm.COLD_START_TURNING
        self.cold_settle_s = None
        event(
            "cold_start_settled",
            self.cfg.name,
            "%s: COLD_START_TURNING cleared: the estimate has "
            "settled (%g x the model's slowest time constant since the cold start)",
            self.cfg.name,
            self.cfg.cold_start_settle_taus,
            reason="settled",
        )
        return Alarm.NONE

    def _shaper_dt(self, dt: float) -> float:
        """The time the offset may move over this cycle: the slew limit holds in wall time at
        the controller, from the last write that took effect. A controller that hung inside a
        write took it late; the next cycle, almost at once, may move the offset only by the
        limit times the time since then, not times the cycle's own dt."""
        if self._write_done_s is not None:
            dt = min(dt, max(0.0, self.clock() - self._write_done_s))
        return dt

    def _estimate_refused(self, err: ModelError) -> Alarm:
        """ESTIMATE_REFUSED: a step that would leave an estimate no spindle can have was not
        taken; an event when it begins and when its reason changes."""
        self.counters["steps_refused"] += 1
        why = str(err)[:200]
        if self._refused != why:
            self._refused = why
            event(
                "estimate_refused",
                self.cfg.name,
                "%s: ESTIMATE_REFUSED: %s",
                self.cfg.name,
                why,
                level=logging.ERROR,
                error=why,
            )
        return Alarm.ESTIMATE_REFUSED

    def _journal_inputs(self, now: float) -> None:
        """A speed-only model's link still reads its input channels, for the journal only: after
        the write, so it never delays the offset; a failure costs blank cells, and the next try
        waits ``JOURNAL_INPUTS_RETRY_S`` (a channel that times out must not slow every cycle)."""
        if (
            self.estimate.with_inputs is not None
            or not self.journal.input_columns
            or not self.link.up
            or now < self._journal_inputs_after
        ):
            return
        try:
            self._inputs_read = self.adapter.read_inputs()
        except AdapterError as err:
            self._journal_inputs_after = now + JOURNAL_INPUTS_RETRY_S
            log.info(
                "%s: input channels not read for the journal (next try in %g s): %s",
                self.cfg.name,
                JOURNAL_INPUTS_RETRY_S,
                err,
            )

    def next_period_s(self) -> float:
        """Seconds to the next cycle: ``run_up_period_s`` while the spindle changes speed with the
        tool clear of the part (the last cycle saw the speed move), else ``period_s``."""
        fast = self.cfg.run_up_period_s
        if fast is not None and self.clock() < self._run_up_until:
            return min(fast, self.cfg.period_s)
        return self.cfg.period_s

    def _read_cutting(self) -> tuple[bool | None, str, Alarm]:
        """The controller's cutting signal and its source; None (the shaper infers it from the
        speed) without one, with the link down, or when it fails (``CUTTING_SIGNAL_FAILED``, an
        event when it begins and one when it ends)."""
        if not (self.cutting_from_controller and self.link.up):
            return None, "speed", Alarm.NONE
        try:
            cutting = self.adapter.read_cutting()
        except AdapterError as err:
            why = str(err)[:200]
            if why != self._cutting_error:
                event(
                    "cutting_signal_failed",
                    self.cfg.name,
                    "%s: CUTTING_SIGNAL_FAILED: %s; the cutting state is inferred from the speed",
                    self.cfg.name,
                    why,
                    level=logging.WARNING,
                    error=why,
                )
            self._cutting_error = why
            return None, "speed-fallback", Alarm.CUTTING_SIGNAL_FAILED
        if self._cutting_error is not None:
            event(
                "cutting_signal_restored",
                self.cfg.name,
                "%s: the controller's cutting signal reads again",
                self.cfg.name,
            )
            self._cutting_error = None
        return cutting, "controller", Alarm.NONE

    def _journal(
        self,
        now: float,
        dt: float,
        wall_now: float,
        speed: float,
        s: float,
        held: float,
        wrote: bool,
        shaped: ShapedOffset,
        cutting_source: str,
        alarms: Alarm,
    ) -> Alarm:
        """One journal row; a disk that refuses it is an alarm, the row waits in memory."""
        j = self.journal
        if self._journal_error is not None:
            alarms |= Alarm.JOURNAL_FAILED  # the row says so itself once it lands
        ok = j.write(
            self.anchor_s + now,
            speed,
            s,
            held,
            wrote,
            int(shaped.flags),
            int(alarms),
            dt_s=dt,
            wall_s=wall_now,
            now_s=now,
            cutting=shaped.cutting,
            cutting_source=cutting_source,
            policy_state=shaped.state,
            slew_limit_um_per_s=shaped.rate_um_per_s,
            inputs=self._inputs_read
            if self.shadow_est is None
            else {**self._inputs_read, SHADOW_COLUMN: self.shadow_est.estimate_um},
        )
        if ok:
            if self._journal_error is not None:
                event(
                    "journal_restored",
                    self.cfg.name,
                    "%s: journal writing again (%s)",
                    self.cfg.name,
                    j.path,
                    path=str(j.path),
                    dropped_rows=j.dropped_rows,
                )
                self._journal_error = None
            return Alarm.NONE
        if j.error is not None and j.error != self._journal_error:
            self.counters["journal_failed"] += 1
            event(
                "journal_failed",
                self.cfg.name,
                "%s: cannot write the journal: %s; rows kept in memory (%d), compensation goes on",
                self.cfg.name,
                j.error,
                j.pending_rows,
                level=logging.ERROR,
                error=j.error,
                pending_rows=j.pending_rows,
            )
            self._journal_error = j.error
        return Alarm.JOURNAL_FAILED if self._journal_error is not None else Alarm.NONE

    def _input_events(self, step: Step, extrapolated_before: str | None) -> Alarm:
        """The events and alarms of the estimate's input decisions this cycle: the fallback
        standing in (``INPUT_FALLBACK``), the model with inputs back, and valid inputs outside the
        range seen in calibration (``INPUTS_EXTRAPOLATED``, one event on entry, one on leaving)."""
        model = self.estimate.with_inputs
        assert model is not None
        if step.fell_back is not None:
            event(
                "input_fallback",
                self.cfg.name,
                "%s: %s; speed-only fallback",
                self.cfg.name,
                step.fell_back,
                level=logging.ERROR,
                reason=step.fell_back,
            )
        if step.input_fallback:
            return Alarm.INPUT_FALLBACK
        if step.restored:
            event(
                "inputs_restored",
                self.cfg.name,
                "%s: inputs good: model with %s",
                self.cfg.name,
                ", ".join(model.input_names),
                inputs=list(model.input_names),
            )
        why = self.est.extrapolated
        if why is None:
            if extrapolated_before is not None:
                event(
                    "inputs_within_training",
                    self.cfg.name,
                    "%s: inputs back inside the trained range",
                    self.cfg.name,
                )
            return Alarm.NONE
        if extrapolated_before is None:
            event(
                "inputs_extrapolated",
                self.cfg.name,
                "%s: INPUTS_EXTRAPOLATED: %s; the model with inputs extrapolates",
                self.cfg.name,
                why,
                level=logging.WARNING,
                reason=why,
            )
        return Alarm.INPUTS_EXTRAPOLATED

    def _stated(self) -> tuple[ExpectedError | None, bool]:
        """The error statement of the model in use (the fallback's while it stands in), and
        whether the model with inputs is in use."""
        on_inputs = self.estimate.with_inputs is not None and self.est.inputs is not None
        return (
            self.expected
            if on_inputs or self.estimate.with_inputs is None
            else self.expected_fallback,
            on_inputs,
        )

    def _expected_error(self, speed: float) -> tuple[dict[str, Any] | None, Alarm]:
        """The error to expect this cycle (None where the model in use states none): the
        figure its fit stated for ``speed`` and for how far the inputs lie outside the trained
        range, with the configured bound. ``EXPECTED_ERROR_HIGH`` while a bound is set and the
        figure (95 % of |error|) exceeds it, or validation scored no prediction like this one (too
        few folds predicted forward, a speed above the calibrated range, inputs further out than
        it reached: the figure is then a floor); one event on entry, one on leaving. Advice only:
        the offset is never changed for it."""
        stated, on_inputs = self._stated()
        bound = self.cfg.max_expected_error_um
        out: dict[str, Any] | None = None
        why: str | None = None
        if stated is not None:
            spans = float(self.est.outside_spans) if on_inputs else 0.0
            e = stated.at(speed, spans)
            out = {
                "band": e.band,
                "rms_um": e.rms_um,
                "p95_abs_um": e.p95_abs_um,
                "source": e.source,
                "outside": e.outside,
                "outside_spans": spans,
                "validated": e.validated,
                "bound_um": bound,
            }
            if bound is not None and (e.p95_abs_um > bound or not e.validated):
                where = place(e.band)
                over = e.p95_abs_um > bound
                why = (
                    f"expected error {'' if e.validated else 'at least '}{e.p95_abs_um:.1f} um (95 %)"
                    + (
                        f" over the bound {bound:g} um {where}"
                        if over
                        else f" {where} (bound {bound:g} um)"
                    )
                )
                if not e.validated:  # the figure is a floor: the bound cannot be vouched for
                    why += ", not validated here: " + "; ".join(
                        stated.why_unvalidated(speed, spans)
                    )
                elif e.outside:
                    why += ", inputs outside the trained range"
                why += ": probe or recalibrate"
        if why is not None and self._expected_high is None:
            event(
                "expected_error_high",
                self.cfg.name,
                "%s: EXPECTED_ERROR_HIGH: %s",
                self.cfg.name,
                why,
                level=logging.WARNING,
                reason=why,
                **(out or {}),
            )
        elif why is None and self._expected_high is not None:
            now_is = (
                "the model in use states no expected error"
                if out is None
                else "no bound is set"
                if bound is None
                else f"expected error {out['p95_abs_um']:.1f} um (95 %) {place(out['band'])}, within "
                f"the bound {bound:g} um"
            )
            event(
                "expected_error_within_bound",
                self.cfg.name,
                "%s: EXPECTED_ERROR_HIGH cleared: %s",
                self.cfg.name,
                now_is,
                reason=now_is,
                **(out or {}),
            )
        self._expected_high = why
        return out, Alarm.EXPECTED_ERROR_HIGH if why is not None else Alarm.NONE

    def close(self) -> None:
        """Save the state and close; a failing disk or link never raises here."""
        for _, _, reply in self._queued:
            if reply is not None:
                reply(
                    {
                        "ok": False,
                        "spindle": self.cfg.name,
                        "error": "the spindle stopped before the measurement was fused",
                    }
                )
        self._queued.clear()
        try:
            self.save_state()
        finally:
            try:
                self.measurements.close(self.clock())
                self.journal.close(self.clock())
                if self.journal.pending_rows or self.journal.dropped_rows:
                    event(
                        "journal_failed",
                        self.cfg.name,
                        "%s: stopping with %d journal row(s) not written (%s)",
                        self.cfg.name,
                        self.journal.pending_rows + self.journal.dropped_rows,
                        self.journal.error,
                        level=logging.ERROR,
                        lost_rows=self.journal.pending_rows + self.journal.dropped_rows,
                        error=self.journal.error,
                    )
            finally:
                try:
                    self.adapter.close()
                except AdapterError as err:
                    log.warning("%s: closing the link: %s", self.cfg.name, err)
