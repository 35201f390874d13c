"""``thermocomp run``: the compensation service an edge box runs for months.

All spindles of one configuration in one process, each run by a
:class:`~thermocomp.runtime.spindle.SpindleRuntime` every ``period_s``; JSON logs with one
structured event per transition, systemd's notify protocol and watchdog, SIGTERM to stop (at once, even
in the middle of a long wait between cycles) and SIGHUP to reload. One instance per state directory (:mod:`.lock`). A reload that does not
validate (bad configuration, a model that cannot be loaded or is implausible) keeps the running
one and raises ``RELOAD_FAILED``. A full disk never stops it: ``SIGXFSZ`` is ignored so a file
size limit is an error on the write, which the spindle turns into an alarm. Time is injected
(``clock`` monotonic seconds, ``wall`` epoch seconds, ``sleep``) so tests run in simulated time;
the real wait between cycles is a :class:`~.host.Wake` that SIGTERM and SIGINT end at once.

With a spindle's observer enabled the service listens on ``<state_dir>/control.sock``
(:mod:`.control`): each tick it takes, without blocking, the measurements ``thermocomp measure``
sends, hands each to its spindle, and answers once that spindle's next cycle has fused it.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

from compensator.clock import ScaledClock
from compensator.errors import ThermocompError

from .checks import PLAUSIBLE_ELONGATION_UM, check, implausible, measure, plausible, shaping_check
from .config import RuntimeConfig, load_config
from .control import ControlChannel
from .cooling import CoolingRuntime
from .events import event
from .fleet import Builder, Fleet, last_beat
from .host import TIME_ERROR, Systemd, Wake, kernel_clock_synchronized, sd_notify, setup_logging
from .inbox import Inbox
from .keeper import ScaledWall
from .lock import AlreadyRunningError, StateDirLock
from .publish import Publisher
from .spindle import Alarm, SpindleRuntime
from .status import History, SpindleState, StatusServer
from .sweep import JournalSweep
from .watch import FAILING_EXIT_S, ON_TIME_CYCLES, CycleWatch

if TYPE_CHECKING:
    from .mqtt import MqttPublisher

__all__ = [
    "FAILING_EXIT_S",
    "ON_TIME_CYCLES",
    "PLAUSIBLE_ELONGATION_UM",
    "TIME_ERROR",
    "Service",
    "check",
    "implausible",
    "kernel_clock_synchronized",
    "main",
    "measure",
    "plausible",
    "sd_notify",
    "setup_logging",
    "shaping_check",
]

log = logging.getLogger("thermocomp.runtime")


class EarlySignals(Protocol):
    """The signals recorded while the service started (the command line's)."""

    stop: bool
    reload: bool


class Service:
    """All spindles of one configuration, in one process."""

    def __init__(
        self,
        config_path: str | os.PathLike[str],
        *,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
        sleep: Callable[[float], object] | None = None,
        cfg: RuntimeConfig | None = None,
        lock: bool = True,
        clock_synchronized: Callable[[], bool | None] | None = None,
    ) -> None:
        self.cfg = cfg if cfg is not None else load_config(config_path)
        # the real wait between cycles: ended at once by a stop (``sleep`` None)
        self._wake = Wake()
        wait: Callable[[float], object] = self._wake.wait if sleep is None else sleep
        if self.cfg.time_scale != 1.0 and clock is time.monotonic:
            sim = ScaledClock(self.cfg.time_scale, time.monotonic)
            k = self.cfg.time_scale
            # the real wall time goes with it: a restart measures the downtime on it
            sim_wall = ScaledWall(sim, wall, k)

            def sim_sleep(s: float) -> None:
                self._wake.wait(s / k)

            clock, wall, wait = sim, sim_wall, sim_sleep

        self.clock, self.wall, self.sleep = clock, wall, wait
        self.anchor_s = wall() - clock()  # one journal time base for every spindle and reload
        self.builder = Builder(config_path, clock=clock, wall=wall, anchor_s=self.anchor_s)
        self.watch = CycleWatch()
        self.publisher = Publisher()
        self.sweeper = JournalSweep(clock_synchronized or kernel_clock_synchronized)
        self.inbox = Inbox()
        self.systemd = Systemd()
        self.spindles: dict[str, SpindleRuntime] = {}
        self.cooling: CoolingRuntime | None = None
        self._cooling_due = -math.inf
        self._stop = False
        self.exit_code = 0
        self._lock = StateDirLock(self.cfg.state_dir) if lock else None
        self._prepare_state_dir()
        self.spindles = self.builder.spindles(self.cfg, {})
        self.cooling = self.builder.cooling(self.cfg, self.spindles, None)
        self._open_control()
        self._started_s = clock()

    # -- the parts' state, read (and in tests set) where it always was -------------------------

    @property
    def config_path(self) -> str | os.PathLike[str]:
        return self.builder.config_path

    @property
    def reload_failed(self) -> bool:
        return self.builder.failed

    @reload_failed.setter
    def reload_failed(self, value: bool) -> None:
        self.builder.failed = value

    @property
    def control(self) -> ControlChannel | None:
        return self.inbox.channel

    @property
    def status_server(self) -> StatusServer | None:
        return self.publisher.server

    @status_server.setter
    def status_server(self, value: StatusServer | None) -> None:
        self.publisher.server = value

    @property
    def mqtt(self) -> MqttPublisher | None:
        return self.publisher.mqtt

    @property
    def history(self) -> History | None:
        return self.publisher.history

    @property
    def snapshot(self) -> dict[str, Any] | None:
        return self.publisher.snapshot

    @property
    def states(self) -> dict[str, SpindleState]:
        return self.publisher.states

    @property
    def not_started(self) -> list[str]:
        return self.publisher.not_started

    # -- start ---------------------------------------------------------------------------------

    def start_status(self) -> None:
        """The status endpoint and the MQTT publisher of the configuration (``run`` starts them;
        a test may call this). Neither is needed to compensate: one that cannot start is
        logged and left out."""
        self.publisher.start(self.cfg)
        try:
            self._publish(self.clock())
        except Exception as err:  # noqa: BLE001 - the status never stops the offset
            log.error("status not published: %s", err)

    def _publish(self, now: float, *, stopped: bool = False) -> None:
        self.publisher.publish(
            self.spindles,
            now,
            text=self.status_text,
            time_s=self.anchor_s + now,
            uptime_s=now - self._started_s,
            reload_failed=self.reload_failed,
            cooling=None if self.cooling is None else self.cooling.status(),
            stopped=stopped,
        )

    def _open_control(self) -> None:
        """The control socket, once a spindle fuses measurements."""
        if any(sc.observer.enabled for sc in self.cfg.spindle):
            self.inbox.open(self.cfg.state_dir, self.clock)

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

    def sweep_journal(self, now: float) -> None:
        """Retention: remove the oldest journal days past ``[journal]``'s age or size, never a
        file being written. A failure is logged; nothing here stops compensation."""
        journals = [j for rt in self.spindles.values() for j in (rt.journal, rt.measurements)]
        if self.cooling is not None:
            journals.append(self.cooling.journal)
        self.sweeper.sweep(
            self.cfg.journal_path,
            self.cfg.journal,
            now_wall_s=self.anchor_s + now,
            keep=[j.path for j in journals],
        )

    def request_stop(self, *_: object) -> None:
        """SIGTERM, SIGINT: stop after the tick that runs, ending the wait for the next one."""
        self._stop = True
        self._wake.set()

    def request_reload(self, *_: object) -> None:
        self.builder.requested = True

    def reload(self) -> None:
        """SIGHUP: re-read the configuration and the models. Each spindle keeps its thermal
        state through its state file, and the offset the controller holds is read back. Anything
        that does not validate keeps the running configuration, with ``RELOAD_FAILED``."""
        for rt in self.spindles.values():
            rt.save_state()  # a spindle whose model changed starts from here
        fleet = self.builder.reload(Fleet(self.cfg, self.spindles, self.cooling))
        if fleet is None:
            return
        self.cfg, self.spindles, self.cooling = fleet.cfg, fleet.spindles, fleet.cooling
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
        if self.builder.requested:
            self.builder.requested = False
            self.reload()
            self.watch.restart()
        now = self.clock()
        self.inbox.take(self.spindles)
        for name, rt in self.spindles.items():
            if not self.watch.due(name, now):
                continue
            rt.sticky_alarms = Alarm.RELOAD_FAILED if self.reload_failed else Alarm.NONE
            try:
                rt.cycle()
            except ThermocompError as err:  # a bad value: skip the cycle, never write it
                if self.watch.failed(name, now, err, self._stop):
                    self.exit_code = 1
                    self._stop = True
            else:
                self.watch.succeeded(name)
            self.watch.ran(name, now, rt.next_period_s())
        if self.cooling is not None and now >= self._cooling_due:
            period = self.cooling.cfg.period_s
            self._cooling_due = max(self._cooling_due + period, now)
            try:
                self.cooling.cycle()
            except Exception as err:
                log.exception("cooling cycle skipped: %s", err)
        try:
            self._publish(now)
        except Exception as err:  # noqa: BLE001 - the status never stops the offset
            self.publisher.failed(now, err)
        if self.sweeper.due(now, self.cfg.journal.sweep_every_s):
            self.sweep_journal(now)
        if self.cfg.watchdog and not self._stop:
            self.systemd.beat()  # real time: systemd's watchdog counts real seconds
        self.systemd.status(self.status_text())  # `systemctl status` shows it
        due_next = self.watch.next_due()
        if self.cooling is not None:
            due_next = min(due_next, self._cooling_due)
        return max(0.0, due_next - self.clock())

    def status_text(self) -> str:
        """One line for `systemctl status`, the page's header and `thermocomp status`: how many
        spindles compensate (by the states derived this tick, never by counting the configured
        ones), then each one that does not, with why, and what else needs attention."""
        states = self.states or self.publisher.derive(self.spindles, self.clock())
        good = [n for n, st in states.items() if st.compensating]
        if states and all(st.state == "stopped" for st in states.values()):
            head = "stopped"
        elif len(good) == len(states):
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
        notes += self.watch.notes()
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
            if obs.get("bounded"):
                notes.append(f"{name}: OBSERVER_BOUND (measurements taken only in part)")
        notes += [
            f"{name}: SIGN_OF_LIFE (the sign of life is not written: {rt.offset.life_error})"
            for name, rt in self.spindles.items()
            if rt.alarms & Alarm.SIGN_OF_LIFE
        ]
        if self.cooling is not None and self.cooling.alarm:
            notes.append(f"cooling: {self.cooling.alarm} ({self.cooling.error})")
        return head + ("; " + "; ".join(notes) if notes else "")

    def run(self, early: EarlySignals | None = None) -> int:
        """Compensate until SIGTERM or SIGINT; SIGHUP reloads. ``early``: the signals recorded
        while the service started (``stop``, ``reload``), acted on now."""
        self._wake.open()  # before the handlers: a stop from now on ends the wait
        signal.signal(signal.SIGTERM, self.request_stop)
        signal.signal(signal.SIGINT, self.request_stop)
        if hasattr(signal, "SIGHUP"):
            signal.signal(signal.SIGHUP, self.request_reload)
        if early is not None:
            self._stop = self._stop or early.stop
            self.builder.requested = self.builder.requested or early.reload
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
            try:
                self.close()
            finally:
                self._wake.close()
        return self.exit_code

    def close(self) -> None:
        """A clean stop: each spindle's last sign of life says compensation is no longer valid
        and the offset stays where it is (the control's watcher reacts as its integrator chose);
        the status and the broker say so, then everything closes."""
        self.inbox.close()
        for rt in self.spindles.values():
            last_beat(rt)
        try:
            self._publish(self.clock(), stopped=True)
        except Exception as err:  # noqa: BLE001 - stopping goes on
            log.error("status not published at the stop: %s", err)
        self.publisher.close(self.cfg.state_dir / "status.url")
        for rt in self.spindles.values():
            rt.keeper.stopping = True  # its last save says so (`thermocomp status`)
            rt.close()
        if self.cooling is not None:
            self.cooling.close()
            self.cooling = None
        if self._lock is not None:
            self._lock.release()
        event("stopped", None, "stopped; state saved")


def main(args: argparse.Namespace) -> int:
    if args.check:
        return check(args.config)
    try:
        cfg = load_config(args.config)
        setup_logging(cfg)  # before anything else is said
        service = Service(args.config, cfg=cfg)
        return service.run(getattr(args, "early_signals", None))
    finally:
        # Python puts back SIGHUP's default action (death) as the interpreter shuts down: a
        # reload asked for then would kill a service that stopped cleanly
        if hasattr(signal, "SIGHUP"):
            signal.signal(signal.SIGHUP, signal.SIG_IGN)
