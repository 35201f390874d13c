"""Trust at the edge: no input, clock, signal or fault makes the offset wrong, stops it silently,
or loses the record. Each test reproduces one break found by a fault run against the service,
and checks the class of fault, not only the case."""

from __future__ import annotations

import itertools
import math
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_closed_loop import simple_model  # noqa: F401 - the model file fixture

from cnc_adapters import AdapterError
from cnc_adapters.opcua import OpcUaAdapter
from compensator.clock import SteppedClock
from compensator.errors import ConfigError, ModelError, NonFiniteInputError
from compensator.estimate import Estimate
from compensator.io import Journal, load_model, read_run_log
from compensator.io.journal import cut_torn_tail
from compensator.io.retention import DAY_S, day_start_s
from compensator.io.state import load_state
from compensator.observer import SIGMA_LIMIT_UM, ObserverConfig, ObserverState, measurement_update
from compensator.shaping import ShaperConfig
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import VirtualCNC, VirtualMachine, running, step
from thermocomp.runtime import Alarm, Service, SpindleRuntime
from thermocomp.runtime.config import load_config
from thermocomp.runtime.lock import AlreadyRunningError, StateDirLock

WALL0 = day_start_s("2026-03-02") + 8 * 3600.0
CLAMP_UM, RATE = 60.0, 1.0


def write_config(
    tmp_path: Path, model: Path, *, observer: bool = True, faults: str = "", extra: str = ""
) -> Path:
    lines = [
        f'state_dir = "{tmp_path / "state"}"',
        "watchdog = false",
        "journal_fsync_s = 3600.0",
        extra,
        "[[spindle]]",
        'name = "s1"',
        f'model = "{model}"',
        "period_s = 1.0",
        'adapter = {url = "sim://"}',
        "[spindle.shaping]",
        f"max_offset_um = {CLAMP_UM}",
        f"max_rate_um_per_s = {RATE}",
        "deadband_um = 0.0",
        "[spindle.observer]",
        f"enabled = {str(observer).lower()}",
        "[spindle.faults]",
        faults,
    ]
    tmp_path.mkdir(parents=True, exist_ok=True)
    p = tmp_path / "machine.toml"
    p.write_text("\n".join(lines) + "\n")
    return p


class Rig:
    """One spindle's runtime on the virtual machine tool, on a clock the test moves."""

    def __init__(self, tmp_path: Path, model: Path, *, wall0: float = WALL0, **kw):
        self.t = 0.0
        self.wall0 = wall0  # what the wall clock says at t = 0 (a test may step it)
        cfg = load_config(write_config(tmp_path, model, **kw))
        self.vm = VirtualMachine(
            SpindlePlant(preset("motorized-27k"), seed=1), None, clock=lambda: self.t
        )
        self.adapter = SimAdapter(machine=self.vm)
        self.rt = SpindleRuntime(
            cfg.spindle[0],
            cfg.state_dir,
            cfg.journal_path,
            journal_fsync_s=cfg.journal_fsync_s,
            clock=lambda: self.t,
            wall=lambda: self.wall0 + self.t,
            adapter=self.adapter,
        )

    def cycles(self, n: int, dt: float = 1.0) -> list[dict]:
        out = []
        for _ in range(n):
            self.t += dt
            out.append(self.rt.cycle())
        return out


@pytest.fixture
def rig(tmp_path, simple_model):
    r = Rig(tmp_path, simple_model)
    yield r
    r.rt.close()


# -- a wrong offset on a part -------------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(
    measured=st.floats(allow_nan=True, allow_infinity=True, width=64),
    sigma=st.floats(allow_nan=True, allow_infinity=True, width=64),
    bias=st.floats(-1e4, 1e4),
    var=st.floats(0, 1e12),
)
def test_an_observer_update_is_refused_or_finite(measured, sigma, bias, var):
    cfg = ObserverConfig()
    z = ObserverState(bias, 0.0, ((var, 0.0), (0.0, 0.0)))
    try:
        up = measurement_update(cfg, z, measured, 5.0, sigma)
    except (ModelError, NonFiniteInputError):
        assert not (
            math.isfinite(measured) and math.isfinite(sigma) and 0 < sigma <= SIGMA_LIMIT_UM
        )
        return
    s = up.state
    assert all(math.isfinite(v) for v in (s.bias_um, s.drift_um_per_s, *s.cov[0], *s.cov[1]))


def test_a_huge_sigma_never_stops_compensation(rig):
    rig.vm.override_speed(12000.0)
    rig.cycles(5)
    answers = []
    for sigma in (1e200, 1e3 + 1, math.inf):
        rig.rt.submit(rig.rt.estimate_um(), sigma, answers.append)
        rig.cycles(1)
    assert [a["ok"] for a in answers] == [False, False, False]
    assert all("sigma" in a["error"] for a in answers)
    before = rig.rt.counters["writes"]
    rows = rig.cycles(30)
    assert all(math.isfinite(r["predicted_um"]) for r in rows)
    assert rig.rt.counters["writes"] > before  # the offset still follows the model
    rig.rt.save_state()
    assert math.isfinite(load_state(rig.rt.state_path)["elongation_um"])
    rig.rt.submit(rig.rt.estimate_um() + 0.2, 0.5, answers.append)
    rig.cycles(1)
    assert answers[-1]["ok"] and answers[-1]["accepted"]  # and measurements are taken again


@pytest.mark.parametrize("held", [999.0, 1e6, 1e308, -1e308])
def test_an_absurd_held_offset_is_never_written_back(rig, held):
    rig.vm.override_speed(8000.0)
    rig.cycles(20)
    rig.vm.offset_um = held  # an outside write (or a corrupted variable) far beyond the clamp
    rows = rig.cycles(5)
    assert rows[0]["alarms"] & Alarm.OFFSET_MISMATCH
    assert rig.vm.offset_um != held and abs(rig.vm.offset_um) <= CLAMP_UM  # replaced at once
    assert all(abs(r["offset_um"]) <= CLAMP_UM for r in rows)


@pytest.mark.parametrize("over_range", ["clamp", "extrapolate"])
def test_an_impossible_speed_is_a_failed_read_in_every_mode(tmp_path, simple_model, over_range):
    r = Rig(tmp_path, simple_model, faults=f'over_range = "{over_range}"')
    try:
        r.vm.override_speed(10000.0)
        r.cycles(30)
        good = r.rt.estimate_um()
        r.adapter._read_speed_raw = lambda: 4.294967295e9  # a uint32 register read as 0xFFFFFFFF
        rows = r.cycles(3)
        assert all(row["alarms"] & Alarm.SPEED_READ_FAILED for row in rows)
        assert all(row["speed_rpm"] == 10000.0 for row in rows)  # the last good speed, held
        assert abs(r.rt.estimate_um() - good) < 1.0
        r.rt.save_state()
        assert abs(load_state(r.rt.state_path)["elongation_um"]) < 100.0
    finally:
        r.rt.close()
    est = Estimate(load_model(simple_model), over_range="extrapolate", max_speed_rpm=24000.0)
    assert est.plausible(26000.0) and not est.plausible(26500.0) and not est.plausible(math.nan)
    with pytest.raises(ModelError, match="no spindle's"):
        est.step(est.cold(), 4.294967295e9, 1.0, now_s=1.0, wall_s=WALL0)


def test_a_write_a_hung_controller_took_late_is_followed_at_the_slew_limit(rig):
    """The controller hangs 18 s inside a write, while the tool cuts; the next cycle runs 30 ms
    after the write returned. The offset moves by no more than the limit times the time since
    the write took effect, not by the limit times the cycle's 18 s."""
    rig.vm.override_speed(15000.0)
    rig.cycles(3)
    done: list[tuple[float, float]] = []
    write = rig.adapter._write_raw
    hang = {"s": 0.0}

    def slow_write(raw: float | None, life: object) -> None:
        rig.t += hang["s"]  # the time the write took, on the test's clock
        hang["s"] = 0.0
        write(raw, life)  # type: ignore[arg-type]
        if raw is not None:  # an offset, not only a sign of life
            done.append((rig.t, rig.adapter.offset_um_requested))

    rig.adapter._write_raw = slow_write  # type: ignore[method-assign]
    rig.cycles(5)
    hang["s"] = 18.0
    rig.cycles(1)
    rig.cycles(5, dt=0.03)
    rig.cycles(20)
    assert len(done) > 10
    for (t0, a0), (t1, a1) in itertools.pairwise(done):
        limit = rig.rt.cfg.shaping.rate_limit_um_per_s * (t1 - t0)
        assert abs(a1 - a0) <= limit + 1e-9, (t0, t1, a0, a1)


def test_a_speed_or_signal_with_a_bad_status_is_never_used():
    """Every path that reads the speed (a plain poll, one batched with the cutting signal, one
    batched with the deferred write check, a subscription) refuses a value whose status is
    Bad, even one that carries a number; so do the held offset and the inputs."""
    clock = SteppedClock()
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=clock)
    vm.override_speed(9000.0)
    cutting = "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/Cutting"
    with running(VirtualCNC(vm, tick_s=None)) as cnc:
        clock.advance(10.0)
        step(cnc)
        links = {
            "poll": OpcUaAdapter(cnc.url, preset="virtual-cnc"),
            "cutting": OpcUaAdapter(cnc.url, preset="virtual-cnc", cutting_node=cutting),
            "deferred": OpcUaAdapter(cnc.url, preset="virtual-cnc", verify_writes="deferred"),
            "subscribe": OpcUaAdapter(cnc.url, preset="virtual-cnc", read_mode="subscribe"),
        }
        try:
            for name, link in links.items():
                assert link.read_speed() == 9000.0, name
                if name == "cutting":
                    link.read_cutting()  # from now on it comes with the speed's request
                    link.read_speed()
                if name == "deferred":
                    link.write_offset_um(-1.0)
            vm.override_speed(20000.0)
            cnc.failed["act_speed"] = "BadSensorFailure"
            cnc.failed["cutting"] = "BadSensorFailure"
            cnc.failed["bearing_temp_c"] = "BadSensorFailure"
            clock.advance(1.0)
            step(cnc)
            for name, link in links.items():
                value = None
                for _ in range(400):  # a subscription's notification arrives in its own time
                    try:
                        value = link.read_speed()
                    except AdapterError as err:
                        assert "BadSensorFailure" in str(err), (name, err)
                        break
                    assert value != 20000.0, name
                    time.sleep(0.025)
                else:
                    pytest.fail(f"{name}: the bad speed was never refused (last {value})")
            with pytest.raises(AdapterError, match="BadSensorFailure"):
                links["poll"].read_cutting()
            assert not math.isfinite(
                links["poll"].read_inputs()["bearing_temp_c"]
            )  # missing, not its value
        finally:
            for link in links.values():
                link.close()


def test_a_clock_behind_at_the_start_is_corrected_at_its_first_step(tmp_path, simple_model):
    """A box without a real-time clock boots with the clock where it stopped; 10 h later in
    truth. Time synchronisation steps the clock +10 h a minute after the start: the downtime is
    measured again, and the estimate ends where a right clock would have put it."""
    warm = Rig(tmp_path / "a", simple_model, observer=False)
    warm.vm.override_speed(15000.0)
    warm.cycles(1500)
    warm.rt.close()
    hot = warm.rt.estimate_um()
    shut = warm.wall0 + warm.t
    later = 10 * 3600.0
    runs = {}
    for name, wall0 in (("wrong", shut), ("right", shut + later)):
        d = tmp_path / name
        (d / "state").mkdir(parents=True)
        (d / "state" / "s1.state.json").write_bytes(
            (tmp_path / "a" / "state" / "s1.state.json").read_bytes()
        )
        r = Rig(d, simple_model, wall0=wall0, observer=False)
        r.vm.override_speed(0.0)
        r.cycles(60)
        if name == "wrong":
            assert r.rt.estimate_um() > 0.3 * hot  # "advanced 0 s": still warm
            r.wall0 += later  # the NTP step
        rows = r.cycles(120)
        runs[name] = (r.rt.estimate_um(), rows)
        r.rt.close()
    assert runs["right"][0] < 0.05 * hot
    assert runs["wrong"][0] == pytest.approx(runs["right"][0], abs=1e-6)
    assert runs["wrong"][1][0]["alarms"] & Alarm.CLOCK_STEP


# -- the service dead -----------------------------------------------------------------------------


def test_a_latin1_byte_in_the_configuration_is_one_line_and_a_reload_keeps_running(
    tmp_path, simple_model
):
    cfg = write_config(tmp_path, simple_model)
    bad = cfg.read_bytes() + "# für 20°C\n".encode("latin-1")
    other = tmp_path / "bad.toml"
    other.write_bytes(bad)
    with pytest.raises(ConfigError, match=r"line \d+: not UTF-8") as info:
        load_config(other)
    assert "\n" not in str(info.value)
    t = [0.0]
    svc = Service(cfg, clock=lambda: t[0], wall=lambda: WALL0 + t[0])
    try:
        svc.tick()
        cfg.write_bytes(bad)
        svc.request_reload()
        t[0] += 1.0
        svc.tick()
        assert svc.reload_failed and svc.spindles["s1"].alarms & Alarm.RELOAD_FAILED
        t[0] += 1.0
        svc.tick()
        assert svc.spindles["s1"].counters["cycles"] >= 3
    finally:
        svc.close()


def test_signals_during_the_start_are_kept_not_fatal(tmp_path, simple_model):
    from thermocomp.cli import _EarlySignals

    saved = {s: signal.getsignal(s) for s in (signal.SIGHUP, signal.SIGTERM, signal.SIGINT)}
    try:
        early = _EarlySignals()
        os.kill(os.getpid(), signal.SIGHUP)  # its default action would end this process
        assert early.reload and not early.stop
        os.kill(os.getpid(), signal.SIGTERM)
        assert early.stop
        svc = Service(write_config(tmp_path, simple_model), clock=lambda: 0.0, wall=lambda: WALL0)
        assert svc.run(early) == 0  # the recorded SIGTERM: stopped before its first cycle
        assert svc.spindles["s1"].counters["cycles"] == 0
    finally:
        for s, h in saved.items():
            signal.signal(s, h)


def test_a_fifo_in_place_of_the_state_or_model_never_hangs_the_start(tmp_path, simple_model):
    cfg = write_config(tmp_path, simple_model)
    state = tmp_path / "state"
    state.mkdir()
    os.mkfifo(state / "s1.state.json")
    result: dict = {}

    def start() -> None:
        try:
            svc = Service(cfg, clock=lambda: 0.0, wall=lambda: WALL0)
            result["alarms"] = svc.spindles["s1"].pace.startup
            svc.close()
        except Exception as err:
            result["error"] = err

    th = threading.Thread(target=start, daemon=True)
    th.start()
    th.join(60)  # a safety net: a start that waits on the FIFO never returns
    assert not th.is_alive(), "the start hangs on a FIFO"
    assert "error" not in result, result
    assert result["alarms"] & Alarm.STATE_CORRUPT
    fifo_model = tmp_path / "model-fifo.json"
    os.mkfifo(fifo_model)
    with pytest.raises(ModelError, match="not a regular file"):
        load_model(fifo_model)


def test_the_lock_holds_when_its_file_is_removed(tmp_path):
    first = StateDirLock(tmp_path).acquire()
    try:
        (tmp_path / "thermocomp.lock").unlink()  # a stray rm
        with pytest.raises(AlreadyRunningError):
            StateDirLock(tmp_path).acquire()
    finally:
        first.release()
    StateDirLock(tmp_path).acquire().release()  # free once the first has gone


# -- the record lost ------------------------------------------------------------------------------


def test_a_clock_months_ahead_deletes_no_history(tmp_path, simple_model):
    cfg = write_config(tmp_path, simple_model)
    jdir = tmp_path / "state" / "journal"
    jdir.mkdir(parents=True)
    days = [jdir / f"s1-{_day(WALL0 - d * DAY_S)}.csv" for d in (30, 20, 10, 1)]
    for p in days:
        p.write_text("time_s,speed_rpm\n1,0\n")
    ahead = WALL0 + 91 * DAY_S  # a box without a real-time clock, its NTP not yet in
    for synced, kept in ((False, True), (True, False)):
        t = [0.0]
        svc = Service(
            cfg,
            clock=lambda: t[0],
            wall=lambda: ahead + t[0],
            lock=False,
            clock_synchronized=lambda synced=synced: synced,
        )
        svc.tick()
        svc.close()
        assert all(p.exists() for p in days) == kept


def test_a_stray_quote_or_a_huge_line_in_a_journal_loses_no_other_row(tmp_path, capsys):
    import argparse

    from thermocomp.commands.journal import export

    jdir = tmp_path / "journal"
    j = Journal(jdir, "s1", {"spindle": "s1"})
    for k in range(200):
        j.write(
            WALL0 + k, 1000.0, 1.0, -1.0, True, 0, 0, dt_s=1.0, wall_s=WALL0 + k, now_s=float(k)
        )
    j.close()
    path = next(jdir.glob("s1-*.csv"))
    lines = path.read_text().splitlines(keepends=True)
    lines[50] = lines[50].replace(",", ',"', 1)  # one stray quote
    lines[120] = "9" * 200_000 + "\n"  # a line over csv's 128 KB field limit
    path.write_text("".join(lines))
    out = tmp_path / "run.csv"
    ns = argparse.Namespace(
        journal_dir=str(jdir), config=None, spindle=None, from_=None, to=None, output=str(out)
    )
    assert export(ns) == 0
    assert "2 unreadable journal row(s) skipped" in capsys.readouterr().out
    assert read_run_log(out).time_s.size == 198


def test_a_torn_or_nul_filled_last_line_is_cut_and_kept_aside(tmp_path):
    jdir = tmp_path / "journal"
    for tail in (b"1700000123.5,120", b"\x00" * 300, b"17000001\x00\x00\x00,1,2\n"):
        j = Journal(jdir, "s1", {"spindle": "s1"})
        for k in range(5):
            j.write(
                WALL0 + k, 1000.0, 1.0, -1.0, True, 0, 0, dt_s=1.0, wall_s=WALL0 + k, now_s=float(k)
            )
        j.close()
        path = next(jdir.glob("s1-*.csv"))
        whole = path.read_bytes()
        path.write_bytes(whole + tail)  # a power loss while the row was written
        j = Journal(jdir, "s1", {"spindle": "s1"})
        j.write(WALL0 + 10, 1000.0, 1.0, -1.0, True, 0, 0, dt_s=1.0, wall_s=WALL0 + 10, now_s=10.0)
        j.close()
        log = read_run_log(path)
        assert log.time_s.size == 6 and log.time_s[-1] == pytest.approx(WALL0 + 10)
        aside = list(jdir.glob("s1-*.csv.torn-*"))
        assert len(aside) == 1 and aside[0].read_bytes() == tail
        for p in jdir.iterdir():
            p.unlink()
    assert cut_torn_tail(tmp_path / "missing.csv") is None


def _day(epoch_s: float) -> str:
    from compensator.io.retention import utc_day

    return utc_day(epoch_s)


def test_an_export_across_an_older_journal_replays(tmp_path, simple_model):
    """A day written by a version whose journal had 9 columns, then one with the cutting columns:
    what `journal export` writes, `replay` reads."""
    import argparse

    from calibration.replay import replay
    from thermocomp.commands.journal import export

    jdir = tmp_path / "journal"
    jdir.mkdir()
    old = jdir / f"s1-{_day(WALL0 - DAY_S)}.csv"
    rows = ["time_s,speed_rpm,predicted_um,offset_um,written,flags,alarms,dt_s,wall_s"]
    t0 = WALL0 - DAY_S
    rows += [f"{t0 + k:.3f},8000,1.0,-1.0,1,0,0,1,{t0 + k:.3f}" for k in range(100)]
    old.write_text("# spindle: s1\n" + "\n".join(rows) + "\n")
    j = Journal(jdir, "s1", {"spindle": "s1"})
    for k in range(100):
        j.write(
            WALL0 + k,
            8000.0,
            1.0,
            -1.0,
            True,
            0,
            0,
            dt_s=1.0,
            wall_s=WALL0 + k,
            now_s=float(k),
            cutting=True,
            cutting_source="controller",
            policy_state="cutting",
            slew_limit_um_per_s=1.0,
        )
    j.close()
    out = tmp_path / "run.csv"
    ns = argparse.Namespace(
        journal_dir=str(jdir), config=None, spindle=None, from_=None, to=None, output=str(out)
    )
    assert export(ns) == 0
    res = replay(load_model(simple_model), read_run_log(out), shaping=ShaperConfig())
    assert np.isfinite(res.predicted_um).all() and res.predicted_um.size == 200


def test_idle_connections_to_the_control_socket_never_keep_a_measurement_waiting(
    tmp_path, simple_model
):
    import socket

    from test_measure import Rig as ServiceRig

    rig = ServiceRig(tmp_path, simple_model)
    idle = []
    try:
        for _ in range(2):  # more than the socket keeps at once, each sending nothing
            for _ in range(12):  # within the listen backlog: a connect beyond it would wait
                s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                s.connect(str(rig.path))
                idle.append(s)
            rig.tick()
        start = rig.t
        answer = rig.ask(b'{"elongation_um": 0.5}\n')
        assert answer["ok"] and rig.t - start <= 2.0  # the next cycle, not the request timeout
    finally:
        for s in idle:
            s.close()
        rig.close()


def test_a_broker_that_takes_the_connection_and_never_answers_is_an_outage(caplog):
    import logging
    import socket

    from thermocomp.runtime.config import MqttConfig
    from thermocomp.runtime.mqtt import MqttPublisher

    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)  # the kernel accepts; nothing ever answers the MQTT CONNECT
    pub = MqttPublisher(
        MqttConfig(host="127.0.0.1", port=srv.getsockname()[1], keepalive_s=5)
    ).start()
    try:
        with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
            for now in (0.0, 10.0, 20.0):  # the service's clock: publishes due every 10 s
                pub.publish({"spindles": []}, now)
        lost = [r for r in caplog.records if getattr(r, "event", None) == "mqtt_lost"]
        assert len(lost) == 1 and "no answer" in lost[0].getMessage()
    finally:
        pub.close()
        srv.close()


def test_no_secret_is_echoed_and_a_host_with_a_password_is_refused(tmp_path, simple_model):
    base = write_config(tmp_path, simple_model).read_text()
    for extra, secret in (
        ('[mqtt]\nhost = "broker"\npassword = "hunter2-secret"\n', "hunter2-secret"),
        ('[status]\ntoken = "tok-very-secret-0123"\n', "tok-very-secret-0123"),
        ('[mqtt]\nhost = "user:pw-secret@broker"\n', "pw-secret"),
        ('[mqtt]\nhost = "mqtt://user:pw-secret@broker"\n', "pw-secret"),
    ):
        p = tmp_path / "secret.toml"
        p.write_text(base + extra)
        with pytest.raises(ConfigError) as info:
            load_config(p)
        assert secret not in str(info.value), info.value
    token = tmp_path / "token"
    token.write_bytes(b"\xff\xfe-not-utf8-token-0123456789")
    p.write_text(base + f'[status]\nenabled = true\naccess = "token"\ntoken_file = "{token}"\n')
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_config(p).status.token()


def test_a_spindle_whose_every_cycle_fails_stops_the_service_with_one_line(
    tmp_path, simple_model, caplog
):
    import logging

    t = [0.0]
    svc = Service(
        write_config(tmp_path, simple_model), clock=lambda: t[0], wall=lambda: WALL0 + t[0]
    )

    def broken() -> dict:
        raise ModelError("the model cannot step")  # whatever makes every cycle fail

    try:
        svc.tick()
        svc.spindles["s1"].cycle = broken  # type: ignore[method-assign]
        with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
            while t[0] < 120.0 and not svc._stop:
                t[0] += 1.0
                svc.tick()
        assert svc.exit_code == 1 and 60.0 <= t[0] <= 63.0  # stopped, not frozen
        assert sum(getattr(r, "event", None) == "cycle_failed" for r in caplog.records) == 1
        assert "cycles failing" in svc.status_text()
    finally:
        svc.close()


def test_cycles_that_run_late_are_said_and_so_is_their_end(tmp_path, simple_model, caplog):
    """A box too busy (or a link too slow) for its period lags the offset behind the growth: the
    service says so when a cycle runs a whole period late, in its status meanwhile, and again when
    ten cycles in a row ran on time. Time moves only by the test's hand."""
    import logging

    from thermocomp.runtime.service import ON_TIME_CYCLES

    t = [0.0]
    svc = Service(
        write_config(tmp_path, simple_model), clock=lambda: t[0], wall=lambda: WALL0 + t[0]
    )
    period = svc.spindles["s1"].next_period_s()

    def events(name: str) -> list:
        return [r for r in caplog.records if getattr(r, "event", None) == name]

    try:
        with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
            for _ in range(5):  # on time: nothing said
                svc.tick()
                t[0] += period
            assert not events("cycles_late") and "late" not in svc.status_text()
            t[0] += 2.5 * period  # the box stalled: this cycle runs 2.5 periods after it was due
            svc.tick()
            late = events("cycles_late")
            assert len(late) == 1 and late[0].fields["late_s"] == pytest.approx(2.5 * period)
            assert "s1: cycles late" in svc.status_text()
            t[0] += 3 * period  # late again: said once, the figure updated
            svc.tick()
            assert (
                len(events("cycles_late")) == 1
                and f"cycles late ({2 * period:.1f} s)" in svc.status_text()
            )
            for k in range(ON_TIME_CYCLES):
                t[0] += period
                svc.tick()
                assert bool(events("cycles_on_time")) == (k == ON_TIME_CYCLES - 1)
            assert "late" not in svc.status_text()
        assert svc.spindles["s1"].counters["cycles"] >= 5 + 2 + ON_TIME_CYCLES
    finally:
        svc.close()
