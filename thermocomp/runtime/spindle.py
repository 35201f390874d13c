"""One spindle's cycle: read -> step -> shape -> write -> journal.

Each period :meth:`SpindleRuntime.cycle` reads the speed through the adapter
(:meth:`_read_speed`), steps the model on the measured elapsed time (``Predictor.step``), shapes
the offset (:meth:`OffsetTracker.plan`), writes ``A = -S`` (``Adapter.write_offset_um``) and
journals the cycle (:class:`compensator.io.Journal`). Faults never produce a wrong write:

- speed read fails: hold the last speed up to ``faults.speed_hold_s``, then assume idle
  (n = 0), with an alarm; the model keeps running on that assumption;
- the link is down (:class:`LinkHealth`): no write at all (never a stale value); the offset
  machine (:class:`OffsetTracker`) stays at what the controller holds, so after the link
  returns the offset ramps to the model value through the slew limit;
- a write is refused: alarm, count, retry next cycle;
- speed above the calibrated range: clamp to its top (default) or extrapolate, with an alarm;
- a model with inputs: its speed-only fallback is always stepped and stands in, with an alarm,
  while an input is missing, out of range or stale;
- start-up: the saved state is advanced through the downtime as an idle spindle; missing or
  older than ``max_state_age_s``: a cold start, said in the log.

Time is injected (``clock`` monotonic seconds, ``wall`` epoch seconds): tests run in simulated
time without sleeping.
"""

from __future__ import annotations

import enum
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cnc_adapters import AdapterError, UnreachableError, WriteRejectedError, open_adapter
from compensator.errors import ConfigError, ModelError, ModelFileError
from compensator.io import Journal, load_any_model, load_state, model_digest, save_state
from compensator.predictor import Predictor

from .config import SpindleConfig
from .link import LinkHealth, LinkState
from .offset import OffsetTracker

log = logging.getLogger("thermocomp.runtime")


class Alarm(enum.IntFlag):
    NONE = 0
    SPEED_READ_FAILED = 1
    IDLE_ASSUMED = 2
    OVER_RANGE = 4
    LINK_DOWN = 8
    WRITE_REJECTED = 16
    COLD_START = 32
    OUTAGE = 64
    NOT_READY = 128
    INPUT_FALLBACK = 256


class SpindleRuntime:
    """One spindle's model, offset machine, link health, adapter, state file and journal."""

    def __init__(self, cfg: SpindleConfig, state_dir: Path, journal_dir: Path, *,
                 clock: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.time,
                 adapter: Any = None):
        self.cfg = cfg
        self.clock = clock
        self.wall = wall
        loaded: Predictor = load_any_model(cfg.model)
        self.digest = model_digest(loaded)
        # a model with inputs runs beside its speed-only fallback, which is always stepped
        self.with_inputs: Predictor | None = loaded if loaded.input_names else None
        self.model: Predictor = loaded.fallback or loaded
        self.input_state: Any = None
        self.refs: dict[str, float] | None = None
        self._inputs_good_since: float | None = None
        self._last_inputs: dict[str, tuple[float, float]] = {}  # name -> (value, unchanged since)
        self.state_path = Path(state_dir) / f"{cfg.name}.state.json"
        self.adapter = adapter if adapter is not None else open_adapter(cfg.adapter, clock=clock)
        if self.with_inputs is not None:
            missing = sorted(set(self.with_inputs.input_names) - set(self.adapter.input_channels()))
            if missing:
                raise ConfigError(f"spindle {cfg.name}: the model needs input(s) {', '.join(missing)}; "
                                  "map them in the adapter (input_nodes for OPC UA, input_registers "
                                  "for Modbus)")
        self.journal = Journal(journal_dir, cfg.name, {"spindle": cfg.name, "model": cfg.model,
                                                       "source": "thermocomp run"})
        self.counters = {"cycles": 0, "writes": 0, "write_rejected": 0, "read_failed": 0,
                         "link_down_cycles": 0}
        self.alarms = Alarm.NONE
        self.link = LinkHealth(cfg.faults.max_outage_s)
        self._last_t: float | None = None
        self._last_good_read: float | None = None
        self._last_speed = 0.0
        self._last_save = -math.inf
        self.restore()

    # -- state -------------------------------------------------------------------------

    def restore(self) -> None:
        try:
            saved = load_state(self.state_path)
        except ModelFileError as err:
            log.warning("%s: %s; cold start", self.cfg.name, err)
            saved = None
        now = self.wall()
        reason = None
        state = None
        if saved is None:
            reason = "no saved state"
        elif saved.get("model_sha256") != self.digest:
            reason = "saved state belongs to another model"
        else:
            try:
                state = self.model.state_from_dict(saved)
            except ModelError:
                reason = "saved state does not fit the model"
            else:
                if now - float(saved["saved_wall_s"]) > self.cfg.max_state_age_s:
                    reason = f"saved state is {(now - float(saved['saved_wall_s'])) / 3600:.1f} h old"
        if reason is not None:
            self.state = self.model.start(0.0, 0.0)
            self.offset = OffsetTracker(self.cfg.shaping, 0.0)
            self.alarms |= Alarm.COLD_START
            log.warning("%s: cold start (%s)", self.cfg.name, reason)
            return
        assert saved is not None
        downtime = max(0.0, now - float(saved["saved_wall_s"]))
        # the spindle stood still while we were down: the model's own cooling
        self.state = self.model.step(state, 0.0, downtime)
        refs = saved.get("input_references")
        if self.with_inputs is not None and isinstance(refs, dict) \
                and set(refs) >= set(self.with_inputs.input_names):
            self.refs = {k: float(v) for k, v in refs.items()}  # the cold start's, kept across restarts
        self.offset = OffsetTracker(self.cfg.shaping, float(saved.get("offset_um", 0.0)))
        log.info("%s: restored state, advanced %.0f s idle: S = %.2f um", self.cfg.name, downtime,
                 self.state.elongation_um)

    def save_state(self) -> None:
        save_state(self.state_path, {
            "spindle": self.cfg.name,
            "model_sha256": self.digest,
            "saved_wall_s": self.wall(),
            **self.model.state_dict(self.state),
            "elongation_um": self.state.elongation_um,
            "offset_um": self.offset.held_um,
            **({"input_references": self.refs} if self.refs else {}),
        })
        self._last_save = self.clock()

    # -- the cycle -------------------------------------------------------------------

    def _read_speed(self, now: float) -> tuple[float, Alarm]:
        """The speed to step the model with, and the alarms of reading it."""
        alarms = Alarm.NONE
        try:
            speed = self.adapter.read_speed()
            self._last_good_read = now
            self._last_speed = speed
            held = self.adapter.take_write_mismatch()
            if held is not None:  # a deferred check: the controller did not take our last write
                self.counters["write_rejected"] += 1
                alarms |= Alarm.WRITE_REJECTED
                self.offset.controller_holds(held)
                log.error("%s: the controller holds %.3f um, not the offset written; retrying",
                          self.cfg.name, held)
            down_s = self.link.succeeded(now)
            if down_s is not None:
                log.info("%s: link restored after %.0f s", self.cfg.name, down_s)
                self.offset.rewrite()  # the controller may have lost it: write again
        except AdapterError as err:
            self.counters["read_failed"] += 1
            alarms |= Alarm.SPEED_READ_FAILED
            if isinstance(err, UnreachableError):
                alarms |= self._link_failed(now, err)
            else:
                log.warning("%s: speed read failed: %s", self.cfg.name, err)
            since = now - (self._last_good_read if self._last_good_read is not None else now)
            if self._last_good_read is not None and since <= self.cfg.faults.speed_hold_s:
                speed = self._last_speed
            else:
                speed = 0.0
                alarms |= Alarm.IDLE_ASSUMED
        if self.model.above_range(speed):
            alarms |= Alarm.OVER_RANGE
            if self.cfg.faults.over_range == "clamp":
                speed = math.copysign(self.model.speed_range_rpm[1], speed)
        return speed, alarms

    def _link_failed(self, now: float, err: Exception) -> Alarm:
        first = self.link.down_since is None
        state = self.link.failed(now)
        if first:
            log.error("%s: link down: %s", self.cfg.name, err)
        return Alarm.LINK_DOWN | (Alarm.OUTAGE if state is LinkState.OUTAGE else Alarm.NONE)

    def _write(self, now: float, offset_um: float) -> tuple[bool, Alarm]:
        try:
            self.adapter.write_offset_um(offset_um)
        except WriteRejectedError as err:
            self.counters["write_rejected"] += 1
            log.error("%s: write refused (%d so far): %s", self.cfg.name,
                      self.counters["write_rejected"], err)
            return False, Alarm.WRITE_REJECTED
        except AdapterError as err:
            alarms = Alarm.NONE
            if isinstance(err, UnreachableError):
                self.link.failed(now)
                alarms |= Alarm.LINK_DOWN
            log.error("%s: write failed: %s", self.cfg.name, err)
            return False, alarms
        self.counters["writes"] += 1
        return True, Alarm.NONE

    def cycle(self) -> dict[str, Any]:
        t_read = time.perf_counter()  # a measurement only: the read->write latency
        now = self.clock()
        wall_now = self.wall()  # journal the cycle at the instant its dt was measured
        dt = 0.0 if self._last_t is None else max(0.0, now - self._last_t)
        self._last_t = now
        speed, alarms = self._read_speed(now)
        self.state = self.model.step(self.state, speed, dt)
        s = self.state.elongation_um
        if self.with_inputs is not None:
            s_inputs = self._with_inputs(now, speed, dt)
            if s_inputs is None:
                alarms |= Alarm.INPUT_FALLBACK
            else:
                s = s_inputs
        shaped = self.offset.plan(s, speed, dt)
        wanted = self.offset.wants_write(shaped)
        wrote = False
        not_ready = self.adapter.not_ready_offset_um() if self.link.up else None
        if not_ready is not None:
            # machine off, in E-stop or not homed: the controller applies `not_ready`; once it
            # is ready the offset is re-seeded from there through the slew limit
            alarms |= Alarm.NOT_READY
            self.offset.controller_holds(not_ready)
        elif self.link.up and wanted:
            wrote, write_alarms = self._write(now, shaped.offset_um)
            alarms |= write_alarms
        elif not self.link.up:
            self.counters["link_down_cycles"] += 1
        latency_ms = (time.perf_counter() - t_read) * 1e3
        if wrote:
            self.offset.written(shaped)
        elif not_ready is None:
            self.offset.kept(wanted)
        self.alarms = alarms
        self.counters["cycles"] += 1
        held = self.offset.held_um
        self.journal.write(wall_now, speed, s, held, wrote, int(shaped.flags), int(alarms))
        if now - self._last_save >= self.cfg.state_save_every_s:
            self.save_state()
        return {"time_s": now, "dt_s": dt, "speed_rpm": speed, "predicted_um": s,
                "offset_um": held, "written": wrote, "flags": shaped.flags, "alarms": alarms,
                "read_to_write_ms": latency_ms, "offset_mode": self.offset.mode.value,
                "link": self.link.state.value}

    def _with_inputs(self, now: float, speed: float, dt: float) -> float | None:
        """The elongation from the model with inputs, or None when an input is faulty: the
        speed-only fallback then stands. After a fault the inputs must be good for
        ``input_recover_s`` again; the model with inputs then restarts from the fallback's
        elongation, so the switch does not jump."""
        model = self.with_inputs
        assert model is not None
        faults = self.cfg.faults
        try:
            values = self.adapter.read_inputs()
            why = model.check_inputs(values)
        except AdapterError as err:
            values, why = {}, f"inputs not read: {err}"
        if why is None:
            for name in model.input_names:
                v = values[name]
                prev = self._last_inputs.get(name)
                since = prev[1] if prev is not None and prev[0] == v else now
                self._last_inputs[name] = (v, since)
                if now - since >= faults.input_stale_s:
                    why = f"{name}: stale, {v:g} for {now - since:.0f} s"
        if why is not None:
            if self.input_state is not None or self._inputs_good_since is not None:
                log.error("%s: %s; speed-only fallback", self.cfg.name, why)
            self.input_state = None
            self._inputs_good_since = None
            return None
        if self.input_state is None:
            if self._inputs_good_since is None:
                self._inputs_good_since = now
            if now - self._inputs_good_since < faults.input_recover_s and self.counters["cycles"] > 0:
                return None
            # continue from the fallback's elongation; a cold start takes these values as references
            self.input_state = model.start(self.state.elongation_um, speed, values, self.refs)
            self.refs = dict(self.input_state.references)
            log.info("%s: inputs good: model with %s", self.cfg.name, ", ".join(model.input_names))
            return self.input_state.elongation_um
        self.input_state = model.step(self.input_state, speed, dt, values)
        return self.input_state.elongation_um

    def close(self) -> None:
        try:
            self.save_state()
        finally:
            self.journal.close()
            self.adapter.close()
