"""``thermocomp run``: the compensation service an edge box runs for months.

All spindles of one configuration in one process, each run by a
:class:`~thermocomp.runtime.spindle.SpindleRuntime` every ``period_s``; JSON logs with one
structured event per transition, systemd's notify protocol and watchdog, SIGTERM to stop and
SIGHUP to reload. One instance per state directory (:mod:`.lock`). A reload that does not
validate (bad configuration, a model that cannot be loaded or is implausible) keeps the running
one and raises ``RELOAD_FAILED``. A full disk never stops it: ``SIGXFSZ`` is ignored so a file
size limit is an error on the write, which the spindle turns into an alarm. Time is injected
(``clock`` monotonic seconds, ``wall`` epoch seconds, ``sleep``) so tests run in simulated time.

With a spindle's observer enabled the service listens on ``<state_dir>/control.sock``
(:mod:`.control`): each tick it takes, without blocking, the measurements ``thermocomp measure``
sends, hands each to its spindle, and answers once that spindle's next cycle has fused it.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cnc_adapters import open_adapter
from cnc_adapters.chiller import open_chiller
from compensator.clock import ScaledClock
from compensator.errors import ConfigError, ControlError, ThermocompError
from compensator.io import load_any_model
from compensator.observer import SIGMA_LIMIT_UM

from .config import RuntimeConfig, load_config, spindle_scope
from .control import ControlChannel, Pending, send_measurement
from .cooling import CoolingRuntime
from .events import JsonLines, event
from .lock import AlreadyRunningError, StateDirLock
from .spindle import Alarm, SpindleRuntime, cutting_from_controller
from .status import (
    History,
    SpindleState,
    StatusServer,
    snapshot,
    spindle_status,
    start_server,
    state_of,
)

log = logging.getLogger("thermocomp.runtime")

FAILING_EXIT_S = 60.0
"""A spindle whose every cycle has failed this long [s] stops the service (non-zero status)."""
ON_TIME_CYCLES = 10
"""Cycles in a row on time after late ones before the service says they are on time again."""


@dataclass
class _Late:
    """A spindle whose cycles run late: the latest lateness [s], the cycles on time since."""

    late_s: float
    on_time: int = 0


PLAUSIBLE_ELONGATION_UM = 5000.0
"""A model whose steady elongation anywhere in its speed range exceeds this (5 mm) is not a
spindle's: a reload refuses it."""


TIME_ERROR = 5
"""adjtimex's answer for a clock that is not synchronised."""


def kernel_clock_synchronized() -> bool | None:
    """Whether the kernel holds the wall clock synchronised (NTP, chrony or timesyncd keep it
    so: ``adjtimex`` answers other than ``TIME_ERROR``); None where it cannot be asked."""
    try:
        import ctypes

        buf = ctypes.create_string_buffer(512)  # a struct timex with modes 0: read only
        return int(ctypes.CDLL(None, use_errno=True).adjtimex(buf)) != TIME_ERROR
    except (OSError, AttributeError):
        return None


def setup_logging(cfg: RuntimeConfig) -> None:
    handler: logging.Handler = (
        logging.FileHandler(cfg.log_file) if cfg.log_file else logging.StreamHandler()
    )
    handler.setFormatter(JsonLines())
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(cfg.log_level.upper())
    logging.getLogger("asyncua").setLevel(logging.ERROR)
    logging.raiseExceptions = False  # a log that cannot be written must not stop compensation


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


def implausible(model) -> str | None:
    """Why a model that loads cannot be a spindle's, or None. ``model``: a speed-only one (the
    fallback of a model with inputs)."""
    lo, hi = model.speed_range_rpm
    for n in (lo, (lo + hi) / 2, hi):
        s = model.steady_state_um(n)
        if not math.isfinite(s) or abs(s) > PLAUSIBLE_ELONGATION_UM:
            return f"model predicts {s:g} um at {n:g} rpm: not plausible"
    return None


def plausible(model, name: str) -> None:
    """Refuse a model that loads but cannot be a spindle's (ConfigError)."""
    why = implausible(model)
    if why is not None:
        raise ConfigError(f"{spindle_scope(name)}: {why}")


class Service:
    """All spindles of one configuration, in one process."""

    def __init__(
        self,
        config_path: str | os.PathLike[str],
        *,
        clock=time.monotonic,
        wall=time.time,
        sleep=time.sleep,
        cfg: RuntimeConfig | None = None,
        lock: bool = True,
        clock_synchronized: Callable[[], bool | None] | None = None,
    ):
        self.config_path = config_path
        self.cfg = cfg if cfg is not None else load_config(config_path)
        if self.cfg.time_scale != 1.0 and clock is time.monotonic:
            sim = ScaledClock(self.cfg.time_scale, time.monotonic)
            w0 = wall()
            clock, wall = sim, (lambda: w0 + sim())
            k = self.cfg.time_scale

            def sleep(s: float) -> None:
                time.sleep(s / k)

        self.clock, self.wall, self.sleep = clock, wall, sleep
        self.clock_synchronized = clock_synchronized or kernel_clock_synchronized
        self._age_paused_said = False
        self.anchor_s = wall() - clock()  # one journal time base for every spindle and reload
        self.spindles: dict[str, SpindleRuntime] = {}
        self._stop = False
        self._reload = False
        self._due: dict[str, float] = {}
        self._last_beat = -math.inf
        self.reload_failed = False
        self._lock = StateDirLock(self.cfg.state_dir) if lock else None
        self.control: ControlChannel | None = None
        self._status = ""
        self._prepare_state_dir()
        self.spindles = self._build(self.cfg)
        self.cooling: CoolingRuntime | None = None
        self._cooling_due = -math.inf
        self.cooling = self._build_cooling(self.cfg, self.spindles)
        self._open_control()
        self._started_s = clock()
        self.snapshot: dict | None = None
        self.history: History | None = None
        self.status_server: StatusServer | None = None
        self.mqtt = None
        self._sweep_due = -math.inf
        self._publish_warned = -math.inf
        self._failing: dict[str, float] = {}  # spindle -> since when every cycle has failed
        self._late: dict[str, _Late] = {}  # spindle -> how late its cycles run, while they do
        self._period: dict[str, float] = {}  # spindle -> the period its last cycle asked for
        self.not_started: list[str] = []  # optional parts that could not start (status, mqtt)
        self.exit_code = 0
        self.states: dict[str, SpindleState] = {}  # each spindle's state, derived once per tick

    def start_status(self) -> None:
        """The status endpoint and the MQTT publisher of the configuration (``run`` starts them;
        a test may call this). Neither is needed to compensate: one that cannot start is
        logged and left out."""
        st = self.cfg.status
        self.history = History(st.history_h, st.history_every_s)
        try:
            self.status_server = start_server(st, self.history, self.cfg.state_dir / "status.url")
        except ConfigError as err:  # a token missing: no endpoint (never an open one instead)
            self.not_started.append("status endpoint")
            event(
                "status_failed",
                None,
                "status endpoint not started: %s; compensation goes on",
                err,
                level=logging.ERROR,
                error=str(err)[:200],
            )
        if self.cfg.mqtt is not None and self.cfg.mqtt.enabled:
            from .mqtt import MqttPublisher

            try:
                self.mqtt = MqttPublisher(self.cfg.mqtt).start()
            except ConfigError as err:
                self.not_started.append("mqtt")
                event(
                    "mqtt_lost",
                    None,
                    "mqtt not started: %s; compensation goes on",
                    err,
                    level=logging.ERROR,
                    reason=str(err)[:200],
                )
        try:
            self._publish(self.clock())
        except Exception as err:  # noqa: BLE001 - the status never stops the offset
            log.error("status not published: %s", err)

    def _derive_states(self, now: float) -> dict[str, SpindleState]:
        """Each spindle's state at ``now`` (:func:`.status.spindle_state`, the one derivation);
        a change is one ``spindle_state`` event."""
        states = {name: state_of(rt, now) for name, rt in self.spindles.items()}
        for name, st in states.items():
            before = self.states.get(name)
            if before is None or before.state != st.state:
                event(
                    "spindle_state",
                    name,
                    "%s: %s",
                    name,
                    st.line,
                    level=logging.INFO if st.compensating or before is None else logging.WARNING,
                    state=st.state,
                    reason=st.reason,
                    was=None if before is None else before.state,
                )
        self.states = states
        return states

    def _publish(self, now: float) -> None:
        """Build the snapshot and hand it to the endpoint, the history and the broker."""
        states = self._derive_states(now)
        if self.status_server is None and self.mqtt is None and self.history is None:
            return
        spindles = [spindle_status(rt, now, states[name]) for name, rt in self.spindles.items()]
        snap = snapshot(
            version=_version(),
            pid=os.getpid(),
            time_s=self.anchor_s + now,
            uptime_s=now - self._started_s,
            text=self.status_text(),
            reload_failed=self.reload_failed,
            spindles=spindles,
            cooling=None if self.cooling is None else self.cooling.status(),
        )
        self.snapshot = snap
        if self.history is not None:
            for sp in spindles:
                if sp["time_s"] is not None:
                    self.history.add(
                        sp["name"],
                        sp["time_s"],
                        sp["speed_rpm"],
                        sp["elongation_um"],
                        sp["offset_held_um"],
                        sp["alarm_bits"],
                    )
        if self.status_server is not None:
            self.status_server.publish(snap)
        if self.mqtt is not None:
            self.mqtt.publish(snap, now)

    def _open_control(self) -> None:
        """The control socket, once a spindle fuses measurements; a socket that cannot be
        opened is logged, and compensation goes on without it."""
        if self.control is not None or not any(sc.observer.enabled for sc in self.cfg.spindle):
            return
        channel = ControlChannel(self.cfg.state_dir, self.clock)
        try:
            self.control = channel.open()
        except OSError as err:
            event(
                "control_failed",
                None,
                "cannot listen on %s: %s; `thermocomp measure` will not reach this service",
                channel.path,
                err.strerror or err,
                level=logging.ERROR,
                path=str(channel.path),
                error=str(err)[:200],
            )

    def _dispatch(self, request: Pending) -> None:
        """Hand a measurement to its spindle (named, or the only one with an observer)."""
        req = request.request
        assert req is not None
        fused = [name for name, rt in self.spindles.items() if rt.estimate.fused is not None]
        name = req.spindle
        if name is None:
            if len(fused) != 1:
                request.fail(
                    f"name the spindle (--spindle): observers on {', '.join(fused) or 'none'}"
                )
                return
            name = fused[0]
        rt = self.spindles.get(name)
        if rt is None:
            request.fail(f"no spindle {name!r}; spindles: {', '.join(self.spindles)}")
            return
        rt.submit(req.elongation_um, req.sigma_um, request.reply)

    def _prepare_state_dir(self) -> None:
        try:
            self.cfg.state_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            log.error(
                "state directory %s: %s; running without saving state",
                self.cfg.state_dir,
                err.strerror or err,
            )
        if self._lock is None:
            return
        try:
            self._lock.acquire()
        except AlreadyRunningError:
            raise
        except OSError as err:
            # nothing can write there either; compensation matters more than the lock
            event(
                "lock_failed",
                None,
                "cannot lock %s: %s; running unlocked",
                self._lock.path,
                err.strerror or err,
                level=logging.ERROR,
                path=str(self._lock.path),
            )

    def _build(self, cfg: RuntimeConfig) -> dict[str, SpindleRuntime]:
        for sc in cfg.spindle:  # every model first: a refused reload leaves no trace
            loaded = load_any_model(sc.model)
            sc.refuse_other_spindle(loaded.spindle_id)
            plausible(loaded.fallback or loaded, sc.name)
        out: dict[str, SpindleRuntime] = {}
        try:
            for sc in cfg.spindle:
                out[sc.name] = SpindleRuntime(
                    sc,
                    cfg.state_dir,
                    cfg.journal_path,
                    clock=self.clock,
                    wall=self.wall,
                    anchor_s=self.anchor_s,
                    journal_fsync_s=cfg.journal_fsync_s,
                    previous=self.spindles.get(sc.name),
                )
        except BaseException:
            for rt in out.values():
                rt.journal.close()
                rt.adapter.close()
            raise
        return out

    def _build_cooling(
        self, cfg: RuntimeConfig, spindles: dict[str, SpindleRuntime]
    ) -> CoolingRuntime | None:
        """The chiller loop of ``[cooling]``, or None; in mode ``cooling`` its spindle writes no offset."""
        name = cfg.cooling_spindle
        for sname, rt in spindles.items():
            rt.writes_offset = not (
                name == sname and cfg.cooling is not None and cfg.cooling.mode == "cooling"
            )
        if name is None or cfg.cooling is None:
            return None
        return CoolingRuntime(
            cfg.cooling,
            spindles[name],
            cfg.journal_path,
            clock=self.clock,
            wall=self.wall,
            anchor_s=self.anchor_s,
            journal_fsync_s=cfg.journal_fsync_s,
            previous=self.cooling,
        )

    def sweep_journal(self, now: float) -> None:
        """Retention: remove the oldest journal days past ``[journal]``'s age or size, never a
        file being written. A failure is logged; nothing here stops compensation."""
        from compensator.io.retention import sweep

        ret = self.cfg.journal
        journals = [j for rt in self.spindles.values() for j in (rt.journal, rt.measurements)]
        if self.cooling is not None:
            journals.append(self.cooling.journal)
        # by age only on a clock the kernel says is synchronised: a box that booted with its
        # clock months ahead must not age away the history (the size rule needs no clock)
        by_age = self.clock_synchronized() is not False
        if not by_age and not self._age_paused_said:
            self._age_paused_said = True
            log.warning(
                "journal retention: the wall clock is not synchronised: files are removed "
                "for the size limit only, not for their age, until it is"
            )
        try:
            res = sweep(
                self.cfg.journal_path,
                now_wall_s=self.anchor_s + now,
                max_age_days=ret.max_age_days,
                max_bytes=int(ret.max_size_mb * 2**20),
                keep=[j.path for j in journals if j.path],
                by_age=by_age,
            )
        except Exception as err:  # noqa: BLE001 - retention is housekeeping
            log.error("journal retention failed: %s", err)
            return
        if res.removed:
            event(
                "journal_swept",
                None,
                "journal: removed %d old file(s), %.1f MB freed; %.1f MB kept",
                len(res.removed),
                res.freed_bytes / 2**20,
                res.total_bytes / 2**20,
                removed=[p.name for p in res.removed][:50],
                freed_bytes=res.freed_bytes,
            )
        for err in res.errors[:3]:
            log.warning("journal retention: %s", err)

    def request_stop(self, *_: object) -> None:
        self._stop = True

    def request_reload(self, *_: object) -> None:
        self._reload = True

    def reload(self) -> None:
        """SIGHUP: re-read the configuration and the models. Each spindle keeps its thermal
        state through its state file, and the offset the controller holds is read back. Anything
        that does not validate keeps the running configuration, with ``RELOAD_FAILED``."""
        for rt in self.spindles.values():
            rt.save_state()  # a spindle whose model changed starts from here
        try:
            new = load_config(self.config_path)
            if new.state_dir.resolve() != self.cfg.state_dir.resolve():
                raise ConfigError("state_dir cannot change on reload; restart the service")
            built = self._build(new)
        except (ThermocompError, OSError) as err:
            self.reload_failed = True
            event(
                "reload_refused",
                None,
                "reload refused, keeping the running configuration: %s",
                err,
                level=logging.ERROR,
                error=str(err)[:300],
            )
            return
        try:
            cooling = self._build_cooling(new, built)
        except (ThermocompError, OSError) as err:
            for rt in built.values():
                rt.journal.close()
                rt.adapter.close()
            self.reload_failed = True
            event(
                "reload_refused",
                None,
                "reload refused, keeping the running configuration: %s",
                err,
                level=logging.ERROR,
                error=str(err)[:300],
            )
            return
        for name, rt in self.spindles.items():
            if name in built:
                built[name].take_journal(rt)
            rt.close()
        if self.cooling is not None:
            self.cooling.close()
        if new.status != self.cfg.status or new.mqtt != self.cfg.mqtt:
            log.warning("[status] and [mqtt] changes take effect at the next restart")
        self.cfg, self.spindles, self.reload_failed = new, built, False
        self.cooling = cooling
        self._open_control()
        event(
            "reload",
            None,
            "configuration reloaded: %d spindle(s)",
            len(self.spindles),
            spindles=list(self.spindles),
        )

    def tick(self) -> float:
        """Run every spindle that is due; the seconds until the next one is."""
        if self._reload:
            self._reload = False
            self.reload()
            self._due = {}
        now = self.clock()
        if self.control is not None:
            for request in self.control.poll():
                self._dispatch(request)
        for name, rt in self.spindles.items():
            due = self._due.setdefault(name, now)
            if now >= due:
                self._check_late(name, now - due)
                rt.sticky_alarms = Alarm.RELOAD_FAILED if self.reload_failed else Alarm.NONE
                try:
                    rt.cycle()
                except ThermocompError as err:  # a bad value: skip the cycle, never write it
                    self._cycle_failed(name, now, err)
                else:
                    self._failing.pop(name, None)
                period = self._period[name] = rt.next_period_s()
                due += period
                self._due[name] = due if due > now else now + period  # no catch-up burst
        if self.cooling is not None and now >= self._cooling_due:
            period = self.cooling.cfg.period_s
            self._cooling_due = max(self._cooling_due + period, now)
            try:
                self.cooling.cycle()
            except Exception as err:
                log.exception("cooling cycle skipped: %s", err)
        try:
            self._publish(now)
        except Exception as err:
            if now - self._publish_warned >= 600.0:  # one traceback per 10 min, not per tick
                self._publish_warned = now
                log.exception("status not published: %s", err)
        if now >= self._sweep_due:
            self._sweep_due = now + self.cfg.journal.sweep_every_s
            self.sweep_journal(now)
        beat = time.monotonic()  # real time: systemd's watchdog counts real seconds
        if self.cfg.watchdog and beat - self._last_beat >= 1.0 and not self._stop:
            self._last_beat = beat
            sd_notify("WATCHDOG=1")
        status = self.status_text()
        if status != self._status:  # `systemctl status` shows it
            self._status = status
            sd_notify(f"STATUS={status}")
        due_next = min(self._due.values())
        if self.cooling is not None:
            due_next = min(due_next, self._cooling_due)
        return max(0.0, due_next - self.clock())

    def _check_late(self, name: str, late_s: float) -> None:
        """A cycle that runs a whole period or more after it was due is never silent: the offset
        then follows the growth that much later (an overloaded box, a slow controller link, a
        virtual machine run faster than the box can follow). An event when it begins, one when
        :data:`ON_TIME_CYCLES` cycles in a row ran on time again; the status says so meanwhile."""
        period = self._period.get(name)
        if period is None:
            return
        late = self._late.get(name)
        if late_s >= period:
            if late is None:
                event(
                    "cycles_late",
                    name,
                    "%s: cycles late: this one ran %.1f s after it was due (period "
                    "%g s): the offset follows the growth that much later; an overloaded box or a slow "
                    "controller link",
                    name,
                    late_s,
                    period,
                    level=logging.WARNING,
                    late_s=round(late_s, 3),
                    period_s=period,
                )
            self._late[name] = _Late(late_s)
        elif late is not None:
            late.on_time += 1
            if late.on_time >= ON_TIME_CYCLES:
                del self._late[name]
                event(
                    "cycles_on_time",
                    name,
                    "%s: cycles on time again (%d in a row)",
                    name,
                    ON_TIME_CYCLES,
                )

    def _cycle_failed(self, name: str, now: float, err: ThermocompError) -> None:
        """A cycle that could not run is never silent: an event when the failures begin, and once
        every cycle has failed for ``FAILING_EXIT_S`` the service stops with one line and a
        non-zero status (it stops feeding the watchdog too), so that its supervisor restarts it
        from the last good state rather than leaving the controller's offset frozen."""
        since = self._failing.setdefault(name, now)
        if since == now:
            event(
                "cycle_failed",
                name,
                "%s: CYCLE_FAILED: %s; the offset is not written until a cycle runs again",
                name,
                err,
                level=logging.ERROR,
                error=str(err)[:200],
            )
        if now - since >= FAILING_EXIT_S and not self._stop:
            log.error(
                "%s: every cycle has failed for %.0f s (%s): stopping so that the service is "
                "restarted",
                name,
                now - since,
                str(err)[:200],
            )
            self.exit_code = 1
            self._stop = True

    def status_text(self) -> str:
        """One line for `systemctl status`, the page's header and `thermocomp status`: how many
        spindles compensate (by the states derived this tick, never by counting the configured
        ones), then each one that does not, with why, and what else needs attention."""
        states = self.states or self._derive_states(self.clock())
        good = [n for n, st in states.items() if st.compensating]
        if len(good) == len(states):
            head = f"compensating {len(states)} spindle(s)"
        elif not good:
            head = f"NOT compensating (0 of {len(states)} spindle(s))"
        else:
            head = f"compensating {len(good)} of {len(states)} spindle(s)"
        # a spindle that compensates with a caveat (an unsettled cold start) is named too
        notes = [f"{n} {st.line}" for n, st in states.items() if not st.compensating or st.reason]
        notes += (
            ["reload refused, running the previous configuration"] if self.reload_failed else []
        )
        notes += [f"{name}: cycles failing" for name in self._failing]
        notes += [f"{name}: cycles late ({late.late_s:.1f} s)" for name, late in self._late.items()]
        notes += [f"{what} not started (see the log)" for what in self.not_started]
        for name, rt in self.spindles.items():
            obs = rt.observer_status()
            if obs is None:
                continue
            if obs["stale"]:
                notes.append(
                    f"{name}: observer stale (no measurement for > "
                    f"{rt.cfg.observer.stale_after_s:g} s)"
                )
            if obs["rejected"]:
                notes.append(f"{name}: last measurement rejected")
            if obs["failed_sources"]:
                notes.append(f"{name}: measurement source failing")
        if self.cooling is not None and self.cooling.alarm:
            notes.append(f"cooling: {self.cooling.alarm} ({self.cooling.error})")
        return head + ("; " + "; ".join(notes) if notes else "")

    def run(self, early: Any = None) -> int:
        """Compensate until SIGTERM or SIGINT; SIGHUP reloads. ``early``: the signals recorded
        while the service started (``stop``, ``reload``), acted on now."""
        signal.signal(signal.SIGTERM, self.request_stop)
        signal.signal(signal.SIGINT, self.request_stop)
        if hasattr(signal, "SIGHUP"):
            signal.signal(signal.SIGHUP, self.request_reload)
        if early is not None:
            self._stop = self._stop or early.stop
            self._reload = self._reload or early.reload
        if hasattr(signal, "SIGXFSZ"):
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a size limit: EFBIG, not death
        try:
            self.start_status()
        except Exception as err:  # noqa: BLE001 - nothing optional keeps the offset from starting
            log.error("status and mqtt not started: %s", err)
        sd_notify("READY=1")
        event(
            "started",
            None,
            "running %d spindle(s), pid %d",
            len(self.spindles),
            os.getpid(),
            spindles=list(self.spindles),
            pid=os.getpid(),
        )
        try:
            while not self._stop:
                wait = self.tick()
                if wait > 0 and not self._stop:
                    self.sleep(wait)
        finally:
            sd_notify("STOPPING=1")
            self.close()
        return self.exit_code

    def close(self) -> None:
        if self.control is not None:
            self.control.close()
            self.control = None
        if self.status_server is not None:
            self.status_server.close()
            self.status_server = None
            try:  # the port is free now: `status --config` must not find it
                (self.cfg.state_dir / "status.url").unlink(missing_ok=True)
            except OSError:
                pass
        if self.mqtt is not None:
            self.mqtt.close()
            self.mqtt = None
        for rt in self.spindles.values():
            rt.close()
        if self.cooling is not None:
            self.cooling.close()
            self.cooling = None
        if self._lock is not None:
            self._lock.release()
        event("stopped", None, "stopped; state saved")


def _version() -> str:
    from thermocomp import __version__

    return __version__


def shaping_check(sc, link) -> str:
    """What the shaping will do with this link: the policy, its limits, and where the cutting
    state comes from (read once now); a ConfigError where the controller's signal is required
    and the link has none."""
    sh = sc.shaping
    words = {
        "dual-slew": f"dual slew {sh.max_rate_um_per_s:g} um/s cutting, {sh.fast_rate_um_per_s:g} um/s not",
        "longer-cycle": f"longer cycle in transients, {sh.max_rate_um_per_s:g} um/s",
        "hold": f"hold in transients, {sh.max_rate_um_per_s:g} um/s",
        "slow-slew": f"one slew limit, {sh.max_rate_um_per_s:g} um/s",
    }
    if cutting_from_controller(sc, link.capabilities):
        source = f"cutting signal from the controller, now {'cutting' if link.read_cutting() else 'not cutting'}"
    else:
        source = (
            f"cutting inferred from the speed (held {sh.cutting.settle_s:g} s within "
            f"{sh.cutting.speed_tolerance_rpm:g} rpm or {sh.cutting.speed_tolerance_pct:g} %)"
        )
    return f"shaping: {words[sh.policy]}; {source}"


def check(config_path: str) -> int:
    """Validate the configuration, load the models, connect, read one speed; write nothing."""
    cfg = load_config(config_path)
    for sc in cfg.spindle:
        model = load_any_model(sc.model)
        sc.refuse_other_spindle(model.spindle_id)
        plausible(model.fallback or model, sc.name)
        with open_adapter(sc.adapter) as link:
            speed = link.read_speed()
            extra = ""
            names = model.input_names
            if names:
                missing = sorted(set(names) - set(link.input_channels()))
                if missing:
                    raise ConfigError(
                        f"{spindle_scope(sc.name)}: the model needs input(s) {', '.join(missing)}; "
                        "map them in the adapter"
                    )
                values = link.read_inputs()
                extra = ", inputs " + ", ".join(f"{n} {values[n]:g}" for n in names)
            if getattr(link, "can_read_offset", False):
                extra += f", holds offset {link.read_offset_um():.3f} um"
            extra += "; " + shaping_check(sc, link)
        print(f"{sc.name}: model {model.form} ({sc.model}), link ok, speed {speed:.0f} rpm{extra}")
        if sc.profile is not None:
            res = (
                f"; the offset moves in whole counts of {sc.shaping.resolution_um:g} um"
                if sc.shaping.resolution_um
                else ""
            )
            print(f"{sc.name}: {sc.profile.describe(sc.route)}{res}")
            ctl = sc.profile.control_rate_um_per_s
            if ctl is not None and ctl < sc.shaping.rate_limit_um_per_s:
                print(
                    f"{sc.name}: warning: the control moves the offset at most {ctl:g} um/s, slower "
                    f"than the shaping's {sc.shaping.rate_limit_um_per_s:g} um/s: the elastic step of a "
                    "speed change lands late, in the first seconds of the next cut"
                )
    c = cfg.cooling
    if c is not None and c.mode != "off":
        with open_chiller(c.chiller["type"], c.chiller_options) as chiller:
            supply = chiller.read_supply_c()
        mode = (
            "the chiller only, no offset" if c.mode == "cooling" else "the chiller and the offset"
        )
        print(
            f"cooling ({mode}) on {cfg.cooling_spindle}'s estimate: chiller {c.chiller['type']} ok, "
            f"supply {supply:.1f} degC"
        )
        for line in c.law().describe():
            print(f"cooling: {line}")
    st = cfg.status
    if st.enabled:
        st.token()  # a missing or short token: a one-line ConfigError now, not at the service's start
        print(
            f"status: http://{st.bind}:{st.port}/ ({'token' if st.access == 'token' else 'open'} access)"
        )
    if cfg.mqtt is not None and cfg.mqtt.enabled:
        m = cfg.mqtt
        m.password()
        if m.tls and m.ca_file is not None and not m.ca_file.is_file():
            raise ConfigError(f"mqtt.ca_file {m.ca_file}: not a file")
        print(f"mqtt: {m.host}:{m.port}, topic {m.topic} (not connected by --check)")
    print(f"configuration {config_path}: ok ({len(cfg.spindle)} spindle(s)); nothing was written")
    return 0


def measure(args) -> int:
    """``thermocomp measure``: one measurement to the running service; exit 0 when it was
    taken (accepted, or the bias restarted from it), 1 when the observer rejected it."""
    um, sigma = args.um, args.sigma_um
    if not math.isfinite(um) or abs(um) > 1e4:
        raise ConfigError(f"--um must be a finite elongation in um (|um| <= 10000), not {um:g}")
    if sigma is not None and not (math.isfinite(sigma) and 0 < sigma <= SIGMA_LIMIT_UM):
        raise ConfigError(
            f"--sigma-um must be a number > 0 and at most {SIGMA_LIMIT_UM:g} um, not {sigma:g}"
        )
    if args.timeout_s is not None and not (math.isfinite(args.timeout_s) and args.timeout_s > 0):
        raise ConfigError("--timeout-s must be a number > 0")
    if args.state_dir and args.config:
        raise ConfigError("give --state-dir or --config, not both")
    state_dir = args.state_dir or (
        load_config(args.config).state_dir
        if args.config
        else RuntimeConfig.model_fields["state_dir"].default
    )
    answer = send_measurement(state_dir, um, sigma, args.spindle, args.timeout_s or 60.0)
    if not answer.get("ok"):
        raise ControlError(f"the service refused it: {answer.get('error', 'no reason given')}")
    if args.json:
        print(json.dumps(answer, allow_nan=False))
    else:
        print(
            f"{answer.get('spindle')}: {answer.get('outcome')}: measured {answer.get('measured_um', um):.3f} um, "
            f"estimate {answer.get('estimate_um', math.nan):.3f} um, innovation "
            f"{answer.get('innovation_um', math.nan):+.3f} um (sd {answer.get('innovation_sd_um', math.nan):.3f} "
            f"um); bias now {answer.get('bias_um', math.nan):+.3f} um"
        )
    return 1 if answer.get("outcome") == "rejected" else 0


def main(args) -> int:
    if args.check:
        return check(args.config)
    cfg = load_config(args.config)
    setup_logging(cfg)  # before anything else is said
    service = Service(args.config, cfg=cfg)
    return service.run(getattr(args, "early_signals", None))
