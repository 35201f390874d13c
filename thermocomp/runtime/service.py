"""``thermocomp run``: the compensation service an edge box runs for months.

All spindles of one configuration in one process, each run by a
:class:`~thermocomp.runtime.spindle.SpindleRuntime` every ``period_s``; JSON logs, systemd's
notify protocol and watchdog, SIGTERM to stop and SIGHUP to reload. Time is injected
(``clock`` monotonic seconds, ``wall`` epoch seconds, ``sleep``) so tests run in simulated
time without sleeping.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import socket
import time

from cnc_adapters import open_adapter
from compensator.clock import ScaledClock
from compensator.errors import ConfigError, ThermocompError
from compensator.io import load_any_model

from .config import RuntimeConfig, load_config
from .spindle import SpindleRuntime

log = logging.getLogger("thermocomp.runtime")


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
            sim = ScaledClock(self.cfg.time_scale, time.monotonic)
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
        with open_adapter(sc.adapter) as link:
            speed = link.read_speed()
            extra = ""
            names = model.input_names
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
