"""``thermocomp run``: the compensation service an edge box runs for months.

Each spindle, every period: read the speed through its adapter, step the model with the
measured elapsed time (monotonic clock), shape the offset, write A = -S, journal the cycle,
and save the state every ``state_save_every_s``. Faults never produce a wrong write:

- speed read fails: hold the last speed up to ``faults.speed_hold_s``, then assume idle
  (n = 0), with an alarm; the model keeps running on that assumption;
- the link is down: no write at all (never a stale value); the shaper stays at what the
  controller holds, so after the link returns the offset ramps to the model value through
  the slew limit;
- a write is refused: alarm, count, retry next cycle;
- speed above the calibrated range: clamp to its top (default) or extrapolate, with an alarm;
- start-up: the saved state is advanced through the downtime as an idle spindle; missing or
  older than ``max_state_age_s``: a cold start, said in the log.

Time is injected (``clock`` monotonic seconds, ``wall`` epoch seconds) so tests run in
simulated time without sleeping.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import logging
import math
import os
import signal
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .config import RuntimeConfig, SpindleConfig, load_config
from .errors import ConfigError, ModelFileError, ThermocompError
from .io import Journal, load_any_model, load_state, model_digest, save_state
from .model import ModelState
from .shaping import OffsetShaper

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
    """One spindle's model, shaper, adapter, state file and journal."""

    def __init__(self, cfg: SpindleConfig, state_dir: Path, journal_dir: Path, *,
                 clock: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.time,
                 adapter: Any = None):
        from cnc_adapters.base import open_adapter

        self.cfg = cfg
        self.clock = clock
        self.wall = wall
        from .inputs import AugmentedModel

        loaded = load_any_model(cfg.model)
        self.digest = model_digest(loaded)
        # a model with inputs runs beside its speed-only fallback, which is always stepped
        self.aug: AugmentedModel | None = loaded if isinstance(loaded, AugmentedModel) else None
        self.model = loaded.fallback if self.aug is not None else loaded
        self.aug_state = None
        self.refs: dict[str, float] | None = None
        self._inputs_good_since: float | None = None
        self._last_inputs: dict[str, tuple[float, float]] = {}  # name -> (value, unchanged since)
        self.shaper = OffsetShaper(cfg.shaping)
        self.state_path = Path(state_dir) / f"{cfg.name}.state.json"
        self.adapter = adapter if adapter is not None else open_adapter(cfg.adapter, clock=clock)
        if self.aug is not None:
            missing = sorted(set(self.aug.input_names) - set(self.adapter.input_channels()))
            if missing:
                raise ConfigError(f"spindle {cfg.name}: the model needs input(s) {', '.join(missing)}; "
                                  "map them in the adapter (input_nodes for OPC UA, input_registers "
                                  "for Modbus)")
        self.journal = Journal(journal_dir, cfg.name, {"spindle": cfg.name, "model": cfg.model,
                                                       "source": "thermocomp run"})
        self.counters = {"cycles": 0, "writes": 0, "write_rejected": 0, "read_failed": 0,
                         "link_down_cycles": 0}
        self.alarms = Alarm.NONE
        self._last_t: float | None = None
        self._last_good_read: float | None = None
        self._last_speed = 0.0
        self._last_save = -math.inf
        self._pending_write = False
        self._link_down_since: float | None = None
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
        if saved is None:
            reason = "no saved state"
        elif saved.get("model_sha256") != self.digest:
            reason = "saved state belongs to another model"
        elif len(saved.get("thermal_um", [])) != self.model.order:
            reason = "saved state does not fit the model"
        elif now - float(saved["saved_wall_s"]) > self.cfg.max_state_age_s:
            reason = f"saved state is {(now - float(saved['saved_wall_s'])) / 3600:.1f} h old"
        if reason is not None:
            self.state = self.model.cold_state()
            self.shaper_state = self.shaper.initial(0.0)
            self._held_um = 0.0
            self.alarms |= Alarm.COLD_START
            log.warning("%s: cold start (%s)", self.cfg.name, reason)
            return
        assert saved is not None
        downtime = max(0.0, now - float(saved["saved_wall_s"]))
        state = ModelState(tuple(float(x) for x in saved["thermal_um"]), 0.0)
        # the spindle stood still while we were down: the model's own cooling
        self.state = self.model.step(state, 0.0, downtime)
        refs = saved.get("input_references")
        if self.aug is not None and isinstance(refs, dict) and set(refs) >= set(self.aug.input_names):
            self.refs = {k: float(v) for k, v in refs.items()}  # the cold start's, kept across restarts
        self.shaper_state = self.shaper.initial(float(saved.get("offset_um", 0.0)))
        self._held_um = self.shaper_state.output_um
        log.info("%s: restored state, advanced %.0f s idle: S = %.2f um", self.cfg.name, downtime,
                 self.state.elongation_um)

    def save_state(self) -> None:
        save_state(self.state_path, {
            "spindle": self.cfg.name,
            "model_sha256": self.digest,
            "saved_wall_s": self.wall(),
            "thermal_um": list(self.state.thermal_um),
            "elongation_um": self.state.elongation_um,
            "offset_um": self._held_um,
            **({"input_references": self.refs} if self.refs else {}),
        })
        self._last_save = self.clock()

    # -- the cycle -------------------------------------------------------------------

    def _speed(self, now: float) -> tuple[float, Alarm]:
        from cnc_adapters.base import AdapterError, UnreachableError

        alarms = Alarm.NONE
        try:
            speed = self.adapter.read_speed()
            self._last_good_read = now
            self._last_speed = speed
            held = getattr(self.adapter, "take_write_mismatch", lambda: None)()
            if held is not None:  # a deferred check: the controller did not take our last write
                self.counters["write_rejected"] += 1
                alarms |= Alarm.WRITE_REJECTED
                self._pending_write = True
                self._held_um = float(held)
                self.shaper_state = dataclasses.replace(self.shaper_state, output_um=self._held_um)
                log.error("%s: the controller holds %.3f um, not the offset written; retrying",
                          self.cfg.name, held)
            if self._link_down_since is not None:
                log.info("%s: link restored after %.0f s", self.cfg.name, now - self._link_down_since)
                self._link_down_since = None
                self._pending_write = True  # the controller may have lost it: write again
        except AdapterError as err:
            self.counters["read_failed"] += 1
            alarms |= Alarm.SPEED_READ_FAILED
            if isinstance(err, UnreachableError):
                alarms |= Alarm.LINK_DOWN
                if self._link_down_since is None:
                    self._link_down_since = now
                    log.error("%s: link down: %s", self.cfg.name, err)
                elif now - self._link_down_since > self.cfg.faults.max_outage_s:
                    alarms |= Alarm.OUTAGE
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

    def cycle(self) -> dict[str, Any]:
        from cnc_adapters.base import AdapterError, UnreachableError, WriteRejectedError

        t_read = time.perf_counter()  # a measurement only: the read->write latency
        now = self.clock()
        wall_now = self.wall()  # journal the cycle at the instant its dt was measured
        dt = 0.0 if self._last_t is None else max(0.0, now - self._last_t)
        self._last_t = now
        speed, alarms = self._speed(now)
        self.state = self.model.step(self.state, speed, dt)
        s = self.state.elongation_um
        if self.aug is not None:
            s_inputs, why = self._with_inputs(now, speed, dt)
            if s_inputs is None:
                alarms |= Alarm.INPUT_FALLBACK
            else:
                s = s_inputs
        self.shaper_state, shaped = self.shaper.update(self.shaper_state, s, speed, dt)
        wrote = False
        held = self.adapter.not_ready_offset_um() if self._link_down_since is None else None
        if held is not None:
            # machine off, in E-stop or not homed: the controller applies `held`; once it is
            # ready the offset is re-seeded from there through the slew limit
            alarms |= Alarm.NOT_READY
            self._held_um = float(held)
            self._pending_write = True
        elif self._link_down_since is None and (shaped.write or self._pending_write):
            try:
                self.adapter.write_offset_um(shaped.offset_um)
                wrote = True
                self._pending_write = False
                self.counters["writes"] += 1
            except WriteRejectedError as err:
                self.counters["write_rejected"] += 1
                alarms |= Alarm.WRITE_REJECTED
                self._pending_write = True
                log.error("%s: write refused (%d so far): %s", self.cfg.name,
                          self.counters["write_rejected"], err)
            except AdapterError as err:
                self._pending_write = True
                if isinstance(err, UnreachableError):
                    self._link_down_since = now
                    alarms |= Alarm.LINK_DOWN
                log.error("%s: write failed: %s", self.cfg.name, err)
        elif self._link_down_since is not None:
            self.counters["link_down_cycles"] += 1
        latency_ms = (time.perf_counter() - t_read) * 1e3
        if wrote:
            self._held_um = shaped.offset_um
        elif self.shaper_state.output_um != self._held_um:
            # the controller still holds the old value: ramp from there once writes resume
            self.shaper_state = dataclasses.replace(self.shaper_state, output_um=self._held_um)
        self.alarms = alarms
        self.counters["cycles"] += 1
        self.journal.write(wall_now, speed, s, self._held_um, wrote, int(shaped.flags), int(alarms))
        if now - self._last_save >= self.cfg.state_save_every_s:
            self.save_state()
        return {"time_s": now, "dt_s": dt, "speed_rpm": speed, "predicted_um": s,
                "offset_um": self._held_um, "written": wrote, "flags": shaped.flags, "alarms": alarms,
                "read_to_write_ms": latency_ms}

    def _with_inputs(self, now: float, speed: float, dt: float) -> tuple[float | None, str | None]:
        """The elongation from the model with inputs, or None (and why) when an input is faulty:
        the speed-only fallback then stands. After a fault the inputs must be good for
        ``input_recover_s`` again; the model with inputs then restarts from the fallback's
        elongation, so the switch does not jump."""
        from cnc_adapters.base import AdapterError

        from .inputs import AugmentedState

        assert self.aug is not None
        faults = self.cfg.faults
        try:
            values = self.adapter.read_inputs()
            why = self.aug.check_inputs(values)
        except AdapterError as err:
            values, why = {}, f"inputs not read: {err}"
        if why is None:
            for name in self.aug.input_names:
                v = values[name]
                prev = self._last_inputs.get(name)
                since = prev[1] if prev is not None and prev[0] == v else now
                self._last_inputs[name] = (v, since)
                if now - since >= faults.input_stale_s:
                    why = f"{name}: stale, {v:g} for {now - since:.0f} s"
        if why is not None:
            if self.aug_state is not None or self._inputs_good_since is not None:
                log.error("%s: %s; speed-only fallback", self.cfg.name, why)
            self.aug_state = None
            self._inputs_good_since = None
            return None, why
        if self.aug_state is None:
            if self._inputs_good_since is None:
                self._inputs_good_since = now
            if now - self._inputs_good_since < faults.input_recover_s and self.counters["cycles"] > 0:
                return None, "inputs recovering"
            if self.refs is None:
                self.refs = self.aug.references(values)  # a cold start: these are the cold values
            start = self.aug.start(self.aug.speed_model.cold_state(speed), values, self.refs)
            base = self.state.elongation_um - sum(start.inputs)  # continue from the fallback's S
            speed_state = self.aug.speed_model.state_at(base, speed)
            self.aug_state = AugmentedState(speed_state, start.inputs)
            log.info("%s: inputs good: model with %s", self.cfg.name, ", ".join(self.aug.input_names))
            return self.aug_state.elongation_um, None
        self.aug_state = self.aug.step(self.aug_state, speed, values, self.refs, dt)
        return self.aug_state.elongation_um, None

    def close(self) -> None:
        try:
            self.save_state()
        finally:
            self.journal.close()
            self.adapter.close()


# -- logging, systemd, the loop ----------------------------------------------------


class JsonLines(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        out = {"ts": round(record.created, 3), "level": record.levelname.lower(),
               "logger": record.name, "msg": record.getMessage()}
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info).splitlines()[-1]
        return json.dumps(out)


def setup_logging(cfg: RuntimeConfig) -> None:
    handler: logging.Handler = (logging.FileHandler(cfg.log_file) if cfg.log_file
                                else logging.StreamHandler())
    handler.setFormatter(JsonLines())
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(cfg.log_level.upper())
    logging.getLogger("asyncua").setLevel(logging.ERROR)


def sd_notify(message: str) -> None:
    """systemd's notify protocol (Type=notify, WatchdogSec=); a no-op outside systemd."""
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return
    if addr.startswith("@"):
        addr = "\0" + addr[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
            s.connect(addr)
            s.send(message.encode(), socket.MSG_DONTWAIT)  # never block the control loop
    except OSError as err:
        log.debug("sd_notify %s failed: %s", message, err)


class Service:
    """All spindles of one configuration, in one process."""

    def __init__(self, config_path: str | os.PathLike[str], *, clock=time.monotonic, wall=time.time,
                 sleep=time.sleep):
        self.config_path = config_path
        self.cfg = load_config(config_path)
        if self.cfg.time_scale != 1.0 and clock is time.monotonic:
            from cnc_adapters.sim.vcnc import SimClock

            sim = SimClock(self.cfg.time_scale)
            w0 = wall()
            clock, wall = sim, (lambda: w0 + sim())
            sleep = (lambda s, _k=self.cfg.time_scale: time.sleep(s / _k))
        self.clock, self.wall, self.sleep = clock, wall, sleep
        self.spindles: dict[str, SpindleRuntime] = {}
        self._stop = False
        self._reload = False
        self._due: dict[str, float] = {}
        self._last_beat = -math.inf
        self._build()

    def _build(self) -> None:
        self.cfg.state_dir.mkdir(parents=True, exist_ok=True)
        for sc in self.cfg.spindle:
            self.spindles[sc.name] = SpindleRuntime(sc, self.cfg.state_dir, self.cfg.journal_path,
                                                    clock=self.clock, wall=self.wall)

    def request_stop(self, *_: object) -> None:
        self._stop = True

    def request_reload(self, *_: object) -> None:
        self._reload = True

    def reload(self) -> None:
        """SIGHUP: re-read the configuration; each spindle keeps its thermal state via its file."""
        try:
            new = load_config(self.config_path)
        except ThermocompError as err:
            log.error("reload refused, keeping the running configuration: %s", err)
            return
        for rt in self.spindles.values():
            rt.close()
        self.cfg = new
        self.spindles = {}
        self._build()
        log.info("configuration reloaded: %d spindle(s)", len(self.spindles))

    def tick(self) -> float:
        """Run every spindle that is due; the seconds until the next one is."""
        if self._reload:
            self._reload = False
            self.reload()
            self._due = {}
        now = self.clock()
        for name, rt in self.spindles.items():
            due = self._due.setdefault(name, now)
            if now >= due:
                try:
                    rt.cycle()
                except ThermocompError as err:  # a bad value: skip the cycle, never write it
                    log.error("%s: cycle skipped: %s", name, err)
                due += rt.cfg.period_s
                self._due[name] = due if due > now else now + rt.cfg.period_s  # no catch-up burst
        beat = time.monotonic()  # real time: systemd's watchdog counts real seconds
        if self.cfg.watchdog and beat - self._last_beat >= 1.0:
            self._last_beat = beat
            sd_notify("WATCHDOG=1")
        return max(0.0, min(self._due.values()) - self.clock())

    def run(self) -> int:
        signal.signal(signal.SIGTERM, self.request_stop)
        signal.signal(signal.SIGINT, self.request_stop)
        if hasattr(signal, "SIGHUP"):
            signal.signal(signal.SIGHUP, self.request_reload)
        sd_notify("READY=1")
        log.info("running %d spindle(s)", len(self.spindles))
        try:
            while not self._stop:
                wait = self.tick()
                if wait > 0 and not self._stop:
                    self.sleep(wait)
        finally:
            sd_notify("STOPPING=1")
            self.close()
        return 0

    def close(self) -> None:
        for rt in self.spindles.values():
            rt.close()
        log.info("stopped; state saved")


def check(config_path: str) -> int:
    """Validate the configuration, load the models, connect, read one speed; write nothing."""
    cfg = load_config(config_path)
    for sc in cfg.spindle:
        model = load_any_model(sc.model)
        from cnc_adapters.base import open_adapter

        with open_adapter(sc.adapter) as link:
            speed = link.read_speed()
            extra = ""
            names = getattr(model, "input_names", ())
            if names:
                missing = sorted(set(names) - set(link.input_channels()))
                if missing:
                    raise ConfigError(f"spindle {sc.name}: the model needs input(s) {', '.join(missing)}; "
                                      "map them in the adapter")
                values = link.read_inputs()
                extra = ", inputs " + ", ".join(f"{n} {values[n]:g}" for n in names)
        print(f"{sc.name}: model {model.form} ({sc.model}), link ok, speed {speed:.0f} rpm{extra}")
    print(f"configuration {config_path}: ok ({len(cfg.spindle)} spindle(s)); nothing was written")
    return 0


def main(args) -> int:
    if args.check:
        return check(args.config)
    service = Service(args.config)
    setup_logging(service.cfg)
    return service.run()
