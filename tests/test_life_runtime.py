"""The sign of life the runtime writes with the offset (a counter the control watches and a
"compensation valid" flag), the clean stop that says so, and a stop that SIGHUPs cannot turn
into a death by signal.

Cycle-level tests run the real sim link in lock-step (an injected clock); the link below only
records what the runtime hands to its one write, so what a control would see can be asserted
beat by beat."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from cnc_adapters import BadValueError, Failure, FailureKind, Life, WriteResult
from compensator.io import save_model
from compensator.model import ThermalModel
from compensator.speed_programs import job_shop_day
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import VirtualMachine
from thermocomp.runtime import Service, SpindleRuntime
from thermocomp.runtime.alarms import Alarm
from thermocomp.runtime.config import load_config
from thermocomp.runtime.states import state_of

WALL0 = 1.77e9


class LifeLink(SimAdapter):
    """The sim link with a sign of life: every write the runtime asks for is recorded (the
    offset or None, the life sign), and the controller's counter and flag are what it took.
    ``refuse`` makes the controller refuse the next writes."""

    writes_life = True

    def __init__(self, **kw: Any) -> None:
        super().__init__(**kw)
        self.asked: list[tuple[float | None, Life | None]] = []
        self.taken: list[Life] = []  # what the controller holds, beat by beat
        self.refuse = False
        self.not_ready_um: float | None = None  # E-stop: the control applies this offset
        self.bad_speed = False  # the speed reads as a value that is no number

    def _read_speed_raw(self) -> float:
        if self.bad_speed:
            raise BadValueError("speed: not a number")
        return super()._read_speed_raw()

    def not_ready_offset_um(self) -> float | None:
        return self.not_ready_um

    def write(self, offset_um: float | None, life: Life | None = None) -> WriteResult:
        self.asked.append((offset_um, life))
        if self.refuse:
            return WriteResult(Failure(FailureKind.REFUSED, "the control refuses"))
        return super().write(offset_um, life)

    def _write_life_raw(self, life: Life) -> None:
        self.taken.append(life)


def _model(tmp_path: Path) -> Path:
    model = tmp_path / "model.json"
    save_model(
        model,
        ThermalModel.from_discrete(0.99, (0.0, 0.002, 0.0, 0.0), 1.0, speed_range_rpm=(0, 24000)),
    )
    return model


def _config(tmp_path: Path, extra: str = "") -> Path:
    path = tmp_path / "machine.toml"
    path.write_text(
        f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\n[[spindle]]\nname = "s1"\n'
        f'model = "{_model(tmp_path)}"\nperiod_s = 1.0\nadapter = {{url = "sim://"}}\n'
        "[spindle.shaping]\nmax_offset_um = 40.0\nmax_rate_um_per_s = 2.0\n"
        "deadband_um = 0.1\n" + extra
    )
    return path


class Rig:
    """One spindle's runtime on a LifeLink over the virtual machine, in simulated time."""

    def __init__(self, tmp_path: Path, extra: str = "") -> None:
        self.cfg = load_config(_config(tmp_path, extra))
        self.t = [0.0]
        vm = VirtualMachine(
            SpindlePlant(preset("motorized-27k"), seed=3), None, clock=lambda: self.t[0]
        )
        vm.load_program(job_shop_day(preset("motorized-27k").max_rpm, seed=3, hours=1))
        self.link = LifeLink(machine=vm)
        self.rt = self.runtime()

    def runtime(self, previous: SpindleRuntime | None = None) -> SpindleRuntime:
        return SpindleRuntime(
            self.cfg.spindle[0],
            self.cfg.state_dir,
            self.cfg.journal_path,
            clock=lambda: self.t[0],
            wall=lambda: WALL0 + self.t[0],
            adapter=self.link,
            previous=previous,
        )

    def cycle(self) -> tuple[Any, list[tuple[float | None, Life | None]]]:
        self.t[0] += 1.0
        before, beats = len(self.link.asked), len(self.link.taken)
        out = self.rt.cycle()
        if len(self.link.taken) > beats:  # the flag is the state the status derives, every beat
            assert self.link.taken[-1].valid == state_of(self.rt, self.t[0]).compensating
        return out, self.link.asked[before:]


def test_every_cycle_with_the_link_up_writes_one_beat_and_the_counter_moves_by_one(
    tmp_path: Path,
) -> None:
    """An offset written carries the beat; a cycle with no new offset due confirms the held one
    with the beat alone. Either way one write, and the counter the control sees moves by one
    each cycle, valid while the spindle compensates."""
    rig = Rig(tmp_path)
    try:
        confirms = offsets = 0
        for k in range(1, 121):
            out, asked = rig.cycle()
            assert len(asked) == 1, asked  # the one write of the cycle
            offset, life = asked[0]
            assert life is not None and life.counter == k
            assert rig.link.taken[-1] == life and len(rig.link.taken) == k
            assert rig.rt.offset.life == life
            if offset is None:
                confirms += 1
                assert not out.written
            else:
                offsets += 1
                assert out.written and offset == out.offset_um
            # the flag is the spindle's state as the status derives it after the cycle
            assert life.valid == state_of(rig.rt, rig.t[0]).compensating, k
        assert offsets >= 10 and confirms >= 10  # both kinds of beat happened
        assert all(life.valid for life in rig.link.taken[5:])  # it compensates
    finally:
        rig.rt.close()


def test_a_refused_write_does_not_move_the_counter(tmp_path: Path) -> None:
    """The controller refuses every write: the counter stays where the controller last took
    it, and each write asks for the next one, never further: no gap when it comes back."""
    rig = Rig(tmp_path)
    try:
        for _ in range(30):
            rig.cycle()
        assert rig.link.taken[-1] == Life(30, True) and rig.rt.offset.life == Life(30, True)
        rig.link.refuse = True
        for _ in range(20):
            _, asked = rig.cycle()
            assert len(asked) == 1 and rig.rt.offset.life == Life(30, True)
        assert len(rig.link.taken) == 30
        assert {life.counter for _, life in rig.link.asked[30:] if life is not None} == {31}
        rig.link.refuse = False
        rig.cycle()
        assert rig.link.taken[-1].counter == 31
    finally:
        rig.rt.close()


def test_holding_on_a_sensor_fault_beats_with_compensation_not_valid(tmp_path: Path) -> None:
    """The speed cannot be read (a bad value, the link up): the spindle holds; the beat goes
    on (the service lives) and says compensation is not valid, then valid again."""
    rig = Rig(tmp_path)
    try:
        for _ in range(20):
            rig.cycle()
        rig.link.bad_speed = True
        for _ in range(5):
            out, asked = rig.cycle()
            assert out.alarms & Alarm.SPEED_READ_FAILED and len(asked) == 1
            assert asked[0][1] == rig.link.taken[-1] and not rig.link.taken[-1].valid
        assert rig.link.taken[-1].counter == 25
        rig.link.bad_speed = False
        rig.cycle()
        assert rig.link.taken[-1] == Life(26, True)
    finally:
        rig.rt.close()


def test_writes_backed_off_confirm_with_compensation_not_valid(tmp_path: Path) -> None:
    """Something on the control keeps zeroing the offset: the writes back off and the offset
    is held, then not written; the beat alone goes on, not valid, until writes follow again."""
    rig = Rig(
        tmp_path,
        "[spindle.faults]\nreadback_every = 1\nmax_mismatches = 1\nmax_write_backoff_s = 8\n",
    )
    try:
        for _ in range(120):
            rig.cycle()
        assert abs(rig.rt.offset.held_um) > 1.0 and rig.link.taken[-1].valid
        paused = 0
        for _ in range(30):
            rig.link.machine.offset_um = 0.0  # an NC program zeroes it each cycle
            out, asked = rig.cycle()
            assert len(asked) == 1 and asked[0][1] == rig.link.taken[-1]
            if out.alarms & Alarm.WRITE_BACKOFF:
                paused += 1
                assert asked[0][0] is None and not rig.link.taken[-1].valid
        assert paused >= 10 and rig.link.taken[-1].counter == 150
        for _ in range(30):
            rig.cycle()
        assert rig.link.taken[-1] == Life(180, True)
    finally:
        rig.rt.close()


def test_a_machine_that_is_not_ready_gets_the_beat_with_compensation_not_valid(
    tmp_path: Path,
) -> None:
    rig = Rig(tmp_path)
    try:
        for _ in range(10):
            rig.cycle()
        rig.link.not_ready_um = 0.0  # E-stop: the control applies its own offset
        for _ in range(5):
            out, asked = rig.cycle()
            assert out.alarms & Alarm.NOT_READY
            assert asked == [(None, rig.link.taken[-1])] and not rig.link.taken[-1].valid
        rig.link.not_ready_um = None
        for _ in range(5):
            out, asked = rig.cycle()
        assert rig.link.taken[-1].valid and rig.link.taken[-1].counter == 20
    finally:
        rig.rt.close()


class ReadinessUnknownLink(LifeLink):
    """A control whose readiness (off, E-stop, not homed) cannot be read while ``unknown``."""

    unknown = False

    def not_ready_offset_um(self) -> float | None:
        if self.unknown:
            raise BadValueError("ready: the machine's state cannot be read")
        return None


def test_a_cycle_that_cannot_tell_whether_the_machine_is_ready_is_not_valid(
    tmp_path: Path,
) -> None:
    """Whether the machine is ready cannot be read: no offset is written, the beat goes on
    and says compensation is not valid (a control in E-stop or not homed applies its own
    offset), and the state says holding with why (not writing once that lasts more than
    ``faults.not_writing_cycles`` cycles); valid again once it reads."""
    rig = Rig(tmp_path)
    rig.rt.close()
    link = ReadinessUnknownLink(machine=rig.link.machine)
    rig.link = link
    rig.rt = rig.runtime()
    try:
        for _ in range(3):
            rig.cycle()
        link.unknown = True
        beats, states = [], []
        for _ in range(5):
            _, asked = rig.cycle()
            beats += [life for offset, life in asked if life is not None]
            assert all(offset is None for offset, _ in asked)  # no offset written: it holds
            st = state_of(rig.rt, rig.t[0])
            assert st.state != "compensating", st
            assert "whether the machine is ready cannot be read" in st.reason, st
            states.append(st.state)
        assert beats, "no beat at all"
        assert not any(b.valid for b in beats), f"valid while readiness is unknown: {beats}"
        assert states[0] == "holding" and states[-1] == "not writing", states
        link.unknown = False
        for _ in range(3):
            rig.cycle()
        assert link.taken[-1].valid and state_of(rig.rt, rig.t[0]).compensating
    finally:
        rig.rt.close()


class LifeRefusedLink(LifeLink):
    """A control that takes the offset but not the sign of life while ``life_refused`` (a
    counter variable it lacks, a flag the user may not write): the write reports the offset
    taken and the sign's failure apart."""

    life_refused = False

    def write(self, offset_um: float | None, life: Life | None = None) -> WriteResult:
        if not self.life_refused:
            return super().write(offset_um, life)
        self.asked.append((offset_um, life))
        done = SimAdapter.write(self, offset_um, None) if offset_um is not None else WriteResult()
        if done.failure is not None:
            return done
        refused = Failure(FailureKind.REFUSED, "life counter R98: no such variable")
        return WriteResult(pending=done.pending, life_failure=refused)


def _service_on(tmp_path: Path, link: LifeLink, t: list[float]) -> Service:
    """The service of one spindle on ``link``, in simulated time ``t``."""
    service = Service(_config(tmp_path), clock=lambda: t[0], wall=lambda: WALL0 + t[0], lock=False)
    service.spindles["s1"].close()
    service.spindles["s1"] = SpindleRuntime(
        service.cfg.spindle[0],
        service.cfg.state_dir,
        service.cfg.journal_path,
        clock=lambda: t[0],
        wall=lambda: WALL0 + t[0],
        adapter=link,
        anchor_s=service.anchor_s,
    )
    return service


def _events(caplog: pytest.LogCaptureFixture, name: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if getattr(r, "event", None) == name]


def test_a_sign_of_life_the_control_refuses_never_keeps_the_offset_from_it(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The control takes the offset but refuses the life counter (a variable it lacks after an
    upgrade): every offset still reaches it and counts as written, the counter stays where the
    control last took it, SIGN_OF_LIFE is raised each cycle with one event where the run of
    failures begins, and the status line names it. Once the counter is taken again the alarm
    clears (one event) and the counter goes on from where it stopped."""
    t = [0.0]
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=3), None, clock=lambda: t[0])
    vm.override_speed(18000.0)  # warming: an offset due every cycle
    link = LifeRefusedLink(machine=vm)
    service = _service_on(tmp_path, link, t)
    rt = service.spindles["s1"]
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    try:
        for _ in range(10):
            t[0] += 1.0
            service.tick()
        before = rt.offset.life
        assert before == Life(10, True) and link.taken[-1] == before
        link.life_refused = True
        written, writes = 0, rt.counters["writes"]
        for k in range(30):
            t[0] += 1.0
            service.tick()
            out = rt.last
            assert out is not None and out.alarms & Alarm.SIGN_OF_LIFE, k
            assert not out.alarms & Alarm.WRITE_REJECTED, k
            written += out.written
            assert vm.offset_um == pytest.approx(rt.offset.held_um)  # the control holds it
            assert rt.offset.life == before and link.taken[-1] == before  # the counter stands
        assert written >= 5 and rt.counters["writes"] == writes + written
        assert abs(rt.offset.held_um) > 1.0
        assert rt.counters["life_failed"] == 30
        (failed,) = _events(caplog, "sign_of_life_failed")  # once, not every cycle
        assert "R98" in failed.getMessage() and "counter stop at 10" in failed.getMessage()
        assert state_of(rt, t[0]).compensating  # the offset follows the estimate
        line = service.status_text()
        assert line.startswith("compensating 1 spindle(s)")
        assert "s1: SIGN_OF_LIFE (the sign of life is not written: life counter R98" in line
        # the last beat of a stop cannot be written either: said, never raised
        assert rt.offset.last_beat(link.write, True) is None
        link.life_refused = False
        t[0] += 1.0
        service.tick()
        assert rt.offset.life == Life(11, True) and link.taken[-1] == Life(11, True)
        assert rt.last is not None and not rt.last.alarms & Alarm.SIGN_OF_LIFE
        assert len(_events(caplog, "sign_of_life_restored")) == 1
        assert "SIGN_OF_LIFE" not in service.status_text()
    finally:
        service.close()
    assert len(_events(caplog, "sign_of_life_failed")) == 1


def test_a_life_node_the_control_lacks_never_keeps_the_offset_from_it(
    tmp_path: Path, calibrated_model: Path
) -> None:
    """The real OPC UA link to the virtual CNC, its life counter pointed at a node the control
    does not have (a control commissioned before the sign of life): every offset reaches the
    control as the runtime counts it written, SIGN_OF_LIFE is raised every cycle, and the
    control's watch never sees a beat."""
    from machine_sim.vcnc import VirtualCNC, running, step

    t = [0.0]
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=lambda: t[0])
    vm.override_speed(18000.0)
    with running(VirtualCNC(vm, tick_s=None)) as cnc:
        step(cnc)
        missing = "ns=2;s=/CncInterface/CncSpindleList/Spindle1/NoSuchCounter"
        path = tmp_path / "machine.toml"
        path.write_text(
            f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\n[[spindle]]\nname = "s1"\n'
            f'model = "{calibrated_model}"\nperiod_s = 1.0\nadapter = {{url = "{cnc.url}", '
            f'preset = "virtual-cnc", life_node = "{missing}", valid_node = '
            '"ns={ns};s=/CncInterface/CncSpindleList/Spindle1/CompensationValid"}\n'
        )
        sc = load_config(path).spindle[0]
        rt = SpindleRuntime(
            sc,
            tmp_path / "state",
            tmp_path / "journal",
            clock=lambda: t[0],
            wall=lambda: WALL0 + t[0],
        )
        try:
            assert rt.adapter.capabilities.life_sign
            written = 0
            for k in range(25):
                t[0] += 1.0
                out = rt.cycle()
                step(cnc)  # the control takes what was written
                assert out.alarms & Alarm.SIGN_OF_LIFE, k
                assert not out.alarms & (Alarm.WRITE_REJECTED | Alarm.LINK_DOWN), k
                written += out.written
                assert vm.offset_um == pytest.approx(rt.offset.held_um, abs=1e-6), k
            assert written >= 5 and abs(rt.offset.held_um) > 1.0
            assert rt.offset.life == Life(0, False) and vm.watch.counter == 0
            assert rt.counters["life_failed"] == 25
            assert rt.offset.life_error is not None and "NoSuchCounter" in rt.offset.life_error
        finally:
            rt.close()


def test_the_counter_survives_a_reload(tmp_path: Path) -> None:
    """A reload (the same model) and a promotion start the new runtime from the old one's:
    the control sees the counter go on, never back to 1."""
    rig = Rig(tmp_path)
    try:
        for _ in range(25):
            rig.cycle()
        old = rig.rt
        rig.rt = rig.runtime(previous=old)
        rig.rt.take_journal(old)
        assert rig.rt.offset.life == old.offset.life and old.offset.life is not None
        assert old.offset.life.counter == 25
        _, asked = rig.cycle()
        assert asked[0][1] is not None and asked[0][1].counter == 26
    finally:
        rig.rt.close()


def test_a_clean_stop_writes_valid_false_once_and_leaves_the_offset(tmp_path: Path) -> None:
    """The service's own stop: one last beat per spindle, compensation not valid, no offset;
    the status says stopped and what the control holds."""
    cfg = _config(tmp_path)
    t = [0.0]
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=3), None, clock=lambda: t[0])
    vm.load_program(job_shop_day(preset("motorized-27k").max_rpm, seed=3, hours=1))
    link = LifeLink(machine=vm)

    def sleep(s: float) -> None:
        t[0] += s

    service = Service(cfg, clock=lambda: t[0], wall=lambda: WALL0 + t[0], sleep=sleep, lock=False)
    service.spindles["s1"].close()
    service.spindles["s1"] = SpindleRuntime(
        service.cfg.spindle[0],
        service.cfg.state_dir,
        service.cfg.journal_path,
        clock=lambda: t[0],
        wall=lambda: WALL0 + t[0],
        adapter=link,
        anchor_s=service.anchor_s,
    )
    rt = service.spindles["s1"]
    while t[0] < 200:
        wait = service.tick()
        sleep(max(wait, 0.01))
    held = rt.offset.held_um
    assert abs(held) > 1.0 and link.taken[-1].valid
    n_asked, counter = len(link.asked), link.taken[-1].counter
    service.close()
    assert link.asked[n_asked:] == [(None, Life(counter + 1, False))]  # once, no offset
    assert link.taken[-1] == Life(counter + 1, False)
    assert vm.offset_um == pytest.approx(held)  # the offset stays where it was
    st = service.states["s1"]
    assert st.state == "stopped" and st.line == f"stopped: the control holds {held:.2f} µm"
    assert service.status_text().startswith("stopped; s1 stopped: the control holds")


def _wait_for(path: Path, text: str, proc: subprocess.Popen[str]) -> None:
    """Until ``text`` is in the log at ``path`` (the service is up), or the process ended."""
    while proc.poll() is None:
        if path.exists() and text in path.read_text():
            return
        time.sleep(0.01)
    raise AssertionError(f"the service ended before {text!r}: {proc.returncode}")


def test_sighups_while_the_service_stops_never_kill_it(tmp_path: Path) -> None:
    """SIGHUPs every 2 ms, then SIGTERM, and more SIGHUPs until the process is gone: it stops
    cleanly (exit 0, never a death by SIGHUP's default action as the interpreter shuts down).
    One run: without the fix every run dies (-1), each one tried."""
    model = _model(tmp_path)
    log = tmp_path / "log.jsonl"
    cfg = tmp_path / "machine.toml"
    cfg.write_text(
        f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\nlog_file = "{log}"\n'
        f'[[spindle]]\nname = "s1"\nmodel = "{model}"\nperiod_s = 0.5\n'
        'adapter = {url = "sim://motorized-27k?program=job-shop-day&seed=2"}\n'
    )
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "thermocomp", "run", "--config", str(cfg)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        _wait_for(log, '"event": "started"', proc)
        for _ in range(100):
            proc.send_signal(signal.SIGHUP)
            time.sleep(0.002)
        proc.send_signal(signal.SIGTERM)
        while proc.poll() is None:  # SIGHUPs all through the stop and the exit
            try:
                os.kill(proc.pid, signal.SIGHUP)
            except ProcessLookupError:
                break
            time.sleep(0.002)
        code = proc.wait(60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    err = proc.stderr.read() if proc.stderr else ""
    assert code == 0, (code, err[-2000:])
    msgs = [json.loads(line)["msg"] for line in log.read_text().splitlines()]
    assert msgs[-1] == "stopped; state saved"


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_stop_ends_a_long_wait_between_cycles_at_once(
    tmp_path: Path, calibrated_model: Path, sig: signal.Signals
) -> None:
    """The real service on the virtual CNC over OPC UA with period_s = 600: after its first
    beat it is sent SIGTERM (SIGINT): the wait for the next cycle ends at once and it stops
    cleanly (exit 0) with its last beat, compensation not valid, in the control's variables.
    A wait that went on after the signal would write it only 600 s later."""
    from machine_sim.vcnc import VirtualCNC, running, step

    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=lambda: 0.0)
    log = tmp_path / "log.jsonl"
    with running(VirtualCNC(vm, tick_s=None)) as cnc:
        step(cnc)
        cfg = tmp_path / "machine.toml"
        cfg.write_text(
            f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\nlog_file = "{log}"\n'
            f'[[spindle]]\nname = "s1"\nmodel = "{calibrated_model}"\nperiod_s = 600.0\n'
            f'adapter = {{url = "{cnc.url}", preset = "virtual-cnc"}}\n'
        )
        proc = subprocess.Popen(
            [sys.executable, "-m", "thermocomp", "run", "--config", str(cfg)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        try:
            deadline = time.monotonic() + 120  # a bound on a loaded box, not a measurement
            while vm.watch.counter == 0:  # the first cycle's beat, as the control took it
                assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
                assert time.monotonic() < deadline, "no first beat"
                time.sleep(0.05)
                step(cnc)
            assert vm.watch.counter == 1
            proc.send_signal(sig)
            code = proc.wait(120)  # far less than the period: the wait did not run on
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
        step(cnc)
        err = proc.stderr.read() if proc.stderr else ""
        assert code == 0, err[-2000:]
        assert (vm.watch.counter, vm.watch.valid) == (2, False)  # the last beat
    msgs = [json.loads(line)["msg"] for line in log.read_text().splitlines()]
    assert any(m.startswith("s1: last sign of life 2: compensation no longer valid") for m in msgs)
    assert msgs[-1] == "stopped; state saved"


def test_a_clean_stop_leaves_stopped_retained_on_the_broker(
    tmp_path: Path, calibrated_model: Path
) -> None:
    """A real broker (mosquitto): the clean stop publishes each spindle as ``stopped`` with the
    offset the control holds, retained, before ``offline``; a dashboard that connects later
    reads it."""
    from test_mqtt import MOSQUITTO, TOPIC, Brokers, FakeClock, Subscriber, config, wait_for

    if not MOSQUITTO.exists():
        pytest.skip("mosquitto is not installed (scripts/system-deps.sh installs it)")
    brokers = Brokers(tmp_path)
    try:
        port = brokers.start()
        cfg = config(tmp_path, calibrated_model, f'host = "127.0.0.1"\nport = {port}')
        clock = FakeClock()
        svc = Service(cfg, clock=clock, wall=lambda: WALL0 + clock.t, lock=False)
        svc.start_status()
        live = Subscriber(port)
        try:
            assert svc.mqtt is not None
            wait_for(lambda: svc.mqtt is not None and svc.mqtt.connected, 10, "the connection")
            while clock.t < 300:
                clock.t += max(svc.tick(), 0.25)
            held = svc.spindles["s1"].offset.held_um
            assert abs(held) > 1.0
            svc.close()
            live.wait("availability", lambda p, r: p == "offline")
            with live.lock:
                got = list(live.messages)
            offline = max(
                i for i, m in enumerate(got) if m[:2] == (f"{TOPIC}/availability", "offline")
            )
            last = max(i for i, m in enumerate(got) if m[0] == f"{TOPIC}/spindle/s1")
            assert last < offline and json.loads(got[last][1])["state"] == "stopped"
        finally:
            live.close()
        late = Subscriber(port)
        try:
            sp = json.loads(late.wait("spindle/s1", lambda p, r: r))
            assert sp["state"] == "stopped"
            assert sp["state_reason"] == f"the control holds {held:.2f} µm"
            st = json.loads(late.wait("status", lambda p, r: r))
            assert st["status"].startswith("stopped; s1 stopped: the control holds")
            assert late.wait("availability", lambda p, r: r) == "offline"
        finally:
            late.close()
    finally:
        brokers.stop()


def test_run_check_warns_where_the_control_cannot_see_the_service_stop(
    tmp_path: Path, calibrated_model: Path
) -> None:
    """`run --check` on the virtual CNC over OPC UA: its preset names the life counter and the
    flag (no warning); with both turned off, one warning line naming the family's page."""
    from machine_sim.vcnc import VirtualCNC, running, step

    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=lambda: 0.0)
    with running(VirtualCNC(vm, tick_s=None)) as cnc:
        step(cnc)
        out = {}
        for name, life in (("with", ""), ("without", ', life_node = "", valid_node = ""')):
            cfg = tmp_path / f"{name}.toml"
            cfg.write_text(
                f'state_dir = "{tmp_path / "state"}"\n[[spindle]]\nname = "s1"\n'
                f'model = "{calibrated_model}"\n'
                f'adapter = {{url = "{cnc.url}", preset = "virtual-cnc"{life}}}\n'
            )
            r = subprocess.run(
                [sys.executable, "-m", "thermocomp", "run", "--config", str(cfg), "--check"],
                capture_output=True,
                text=True,
                timeout=120,
            )
            assert r.returncode == 0, r.stderr
            out[name] = r.stdout
    warning = "s1: warning: the control cannot tell when thermocomp stops: set life_node and "
    assert warning not in out["with"] and "link ok" in out["with"]
    assert f"{warning}valid_node (docs/reference/virtual-machine-tool.md)\n" in out["without"]


def test_the_page_says_stopped_and_what_the_control_holds(
    tmp_path: Path, calibrated_model: Path
) -> None:
    """The status page in a real headless Chromium: the clean stop's last status shows the
    spindle stopped with the offset the control holds, and once the service is gone the page
    still says so."""
    from test_status_page import CHROMIUM, JS, Page

    if not CHROMIUM.exists() or not (JS / "node_modules" / "playwright-core").is_dir():
        pytest.skip("Chromium and tests/js/node_modules: scripts/system-deps.sh installs them")
    from machine_sim.vcnc import free_port

    cfg = tmp_path / "machine.toml"
    cfg.write_text(
        f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\n'
        f"[status]\nport = {free_port()}\nhistory_every_s = 5\n"
        f'[[spindle]]\nname = "s1"\nmodel = "{calibrated_model}"\n'
        'adapter = {url = "sim://motorized-27k?program=job-shop-day&seed=1"}\n'
    )
    t = [0.0]
    svc = Service(cfg, clock=lambda: t[0], wall=lambda: WALL0 + t[0], lock=False)
    svc.start_status()
    page, closed = None, False
    try:
        while t[0] < 300:
            t[0] += max(svc.tick(), 0.25)
        assert svc.status_server is not None
        page = Page(svc.status_server.url, tmp_path / "stopped.png", "stopped", tmp_path / "b.log")
        live = page.expect("live")
        assert live["state_class"].startswith("state compensating") and live["errors"] == []
        held = svc.spindles["s1"].offset.held_um
        said = f"the control holds {held:.2f} µm"
        svc._publish(t[0], stopped=True)  # what close() publishes, served until it closes
        stopped = page.expect("stopped")
        assert stopped["state_class"] == "state stopped"
        assert "STOPPED" in stopped["state_bar"] and said in stopped["state_bar"]
        svc.close()
        closed = True
        gone = page.expect("gone")
        assert gone["conn"] == "not reachable" and gone["state_class"] == "state stopped"
        assert f"The service stopped cleanly: {said}." in gone["offline"]
        assert page.finish() == 0, (tmp_path / "b.log").read_text()[-3000:]
    finally:
        if page is not None:
            page.close()
        if not closed:
            svc.close()


def test_a_spindle_a_reload_removes_is_told_compensation_stopped(tmp_path: Path) -> None:
    """SIGHUP with a spindle gone from the configuration: its control gets the last beat
    (compensation not valid); the spindle that stays goes on counting."""
    model = _model(tmp_path)
    spindle = (
        '[[spindle]]\nname = "{}"\nmodel = "' + str(model) + '"\nperiod_s = 1.0\n'
        'adapter = {{url = "sim://"}}\n'
    )
    cfg = tmp_path / "machine.toml"
    head = f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\n'
    cfg.write_text(head + spindle.format("a") + spindle.format("b"))
    t = [0.0]

    def sleep(s: float) -> None:
        t[0] += s

    svc = Service(cfg, clock=lambda: t[0], wall=lambda: WALL0 + t[0], sleep=sleep, lock=False)
    links = {}
    for name in ("a", "b"):
        vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=lambda: t[0])
        vm.override_speed(12000.0)
        links[name] = LifeLink(machine=vm)
        svc.spindles[name].close()
        svc.spindles[name] = SpindleRuntime(
            svc.cfg.spindle[0 if name == "a" else 1],
            svc.cfg.state_dir,
            svc.cfg.journal_path,
            clock=lambda: t[0],
            wall=lambda: WALL0 + t[0],
            adapter=links[name],
            anchor_s=svc.anchor_s,
        )
    try:
        while t[0] < 60:
            sleep(max(svc.tick(), 0.01))
        b = links["b"].taken[-1]
        assert b.valid and b.counter >= 50
        a = svc.spindles["a"].offset.life
        cfg.write_text(head + spindle.format("a"))
        svc.reload()
        assert list(svc.spindles) == ["a"]
        assert links["b"].asked[-1] == (None, Life(b.counter + 1, False))
        assert links["b"].taken[-1] == Life(b.counter + 1, False)
        # a's new runtime (a new sim link of the configuration) goes on from a's counter
        assert a is not None and svc.spindles["a"].offset.life == a
    finally:
        svc.close()
