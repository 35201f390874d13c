"""The compensation service: configuration, end to end over OPC UA, restarts, outages, crashes."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from compensator import ConfigError
from compensator.clock import SteppedClock
from compensator.io import load_state, read_run_log
from compensator.speed_programs import job_shop_day
from machine_sim import SpindlePlant, preset
from machine_sim.vcnc import VirtualCNC, VirtualMachine, free_port, running
from thermocomp.runtime import Alarm, Service, SpindleRuntime
from thermocomp.runtime.config import load_config

EXAMPLES = Path(__file__).parents[1] / "examples"


@pytest.fixture
def model_file(calibrated_model):
    return calibrated_model


def write_config(tmp_path: Path, model: Path, adapter: str, **extra) -> Path:
    lines = [f'state_dir = "{tmp_path / "state"}"', "watchdog = false"]
    lines += [f"{k} = {json.dumps(v)}" for k, v in extra.pop("top", {}).items()]
    lines += [
        "[[spindle]]",
        'name = "s1"',
        f'model = "{model}"',
        "period_s = 1.0",
        f"state_save_every_s = {extra.pop('save_every', 5.0)}",
        adapter,
        "[spindle.shaping]",
        "max_offset_um = 40.0",
        "max_rate_um_per_s = 2.0",
        "deadband_um = 0.1",
    ]
    p = tmp_path / "machine.toml"
    p.write_text("\n".join(lines) + "\n")
    return p


def test_example_configuration_is_valid():
    cfg = load_config(EXAMPLES / "machine.toml")
    assert cfg.spindle[0].adapter["preset"] == "sinumerik"
    assert cfg.spindle[0].shaping.transient.mode == "dual-slew"


@pytest.mark.parametrize(
    "text,match",
    [
        (
            'state_dir = "x"\nbogus = 1\n[[spindle]]\nname="a"\nmodel="m"\nadapter={url="sim://"}\n',
            "bogus",
        ),
        ('[[spindle]]\nname="a"\nmodel="m"\nadapter={type="opcua", password="x"}\n', "password"),
        ('[[spindle]]\nname="a b"\nmodel="m"\nadapter={url="sim://"}\n', "name"),
        ("[[spindle\n", "not valid TOML"),
    ],
)
def test_bad_configuration_is_one_line(tmp_path, text, match):
    p = tmp_path / "c.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=match) as exc:
        load_config(p)
    assert "\n" not in str(exc.value)


WALL0 = 1699923600.0  # 01:00 UTC


def run_service_against_vcnc(tmp_path, model_file, hours=1.0, outage=None, wall0=WALL0):
    """The service against the OPC UA virtual CNC, in lock-step: the simulated time moves on by
    the service's own wait once it has written, so no stall of the computer changes the run.
    ``outage`` = (start, length) in simulated seconds: the server goes away and comes back."""
    from machine_sim.vcnc import call, step

    clock = SteppedClock()
    p = preset("motorized-27k")
    vm = VirtualMachine(SpindlePlant(p, seed=31), None, clock=clock)
    port = free_port()
    cfg = write_config(
        tmp_path,
        model_file,
        f'adapter = {{url = "opc.tcp://127.0.0.1:{port}/thermocomp/virtual-cnc/", '
        'preset = "virtual-cnc", timeout_s = 1.0, backoff_s = 0.2, max_backoff_s = 2.0}',
        # hours of simulated time in seconds: the journal's and the state's fsyncs are not what
        # these runs check (the stop saves the state, the journal is read after the close)
        top={"journal_fsync_s": 3600.0},
        save_every=600.0,
    )
    cnc = VirtualCNC(vm, port=port, tick_s=None)
    with running(cnc):
        step(cnc)
        # default 01:00 UTC: a run never crosses midnight into a second journal file
        svc = Service(cfg, clock=clock, wall=lambda: wall0 + clock())
        vm.history(clear=True)
        vm.load_program(job_shop_day(p.max_rpm, seed=31, hours=hours))
        start = clock()
        phase = "before"
        while not vm.program_done:
            if outage and phase == "before" and clock() - start > outage[0]:
                call(cnc, cnc.stop)
                phase, down_at = "down", clock()
            elif outage and phase == "down" and clock() - down_at > outage[1]:
                call(cnc, cnc.start)
                phase = "after"
            wait = svc.tick()
            clock.advance(wait)
            if phase == "down":
                vm.advance()  # the machine goes on; its server is gone
            else:
                step(cnc)
        svc.close()
    journal = sorted((tmp_path / "state" / "journal").glob("s1-*.csv"))
    return vm, svc, journal


def test_service_end_to_end_over_opcua_halves_the_error(tmp_path, model_file):
    # from 23:30 UTC: the journal rotates at midnight, half an hour in
    vm, _svc, journal = run_service_against_vcnc(
        tmp_path, model_file, hours=1.0, wall0=1700006400.0 - 1800
    )
    h = vm.history()
    rms = lambda e: float(np.sqrt(np.mean(e**2)))
    assert rms(h.tool_tip_error_um) < 0.5 * rms(h.true_um)
    assert [p.name for p in journal] == ["s1-2023-11-14.csv", "s1-2023-11-15.csv"]
    logs = [read_run_log(p) for p in journal]  # each file is a run log replay can read
    assert logs[0].time_s[-1] < 1700006400.0 <= logs[1].time_s[0]
    off = np.concatenate([lg.extras["offset_um"] for lg in logs])
    dt = np.concatenate([lg.extras["dt_s"] for lg in logs])[1:]  # the runtime's own step
    cut = np.concatenate([lg.extras["cutting"] for lg in logs]) == 1
    limit = np.concatenate([lg.extras["slew_limit_um_per_s"] for lg in logs])[1:]
    assert np.isfinite(off).all() and np.abs(off).max() <= 40.0
    assert (np.abs(np.diff(off)) <= limit * dt + 1e-6).all()
    # 2 um/s while the CNC says the tool cuts (its Cutting node), faster only while it does not
    both = cut[1:] & cut[:-1]
    assert both.sum() > 100 and (np.abs(np.diff(off))[both] <= 2.0 * dt[both] + 1e-6).all()
    assert (limit[cut[1:]] == 2.0).all() and (limit[~cut[1:]] > 2.0).all()
    assert np.abs(h.offset_um).max() <= 40.0
    state = load_state(tmp_path / "state" / "s1.state.json")
    assert state is not None and state["spindle"] == "s1"
    # `thermocomp replay` reads the journal directly
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "thermocomp",
            "replay",
            "--model",
            str(model_file),
            str(journal[1]),
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["samples"] == len(logs[1])


@pytest.mark.parametrize("outage_s", [20.0, 600.0])
def test_outage_of_the_controller(tmp_path, model_file, outage_s):
    vm, _svc, journal = run_service_against_vcnc(
        tmp_path, model_file, hours=0.5, outage=(600, outage_s)
    )
    assert len(journal) == 1
    log = read_run_log(journal[0])
    alarms = log.extras["alarms"].astype(int)
    written = log.extras["written"].astype(int)
    down = (alarms & int(Alarm.LINK_DOWN)) != 0
    assert down.any(), "the outage was not noticed"
    assert not written[down].any(), "a write was attempted while the link was down"
    # the last speed is held for speed_hold_s (30 s), then the spindle is taken as idle
    idle = (alarms & int(Alarm.IDLE_ASSUMED)) != 0
    assert idle.any() == (outage_s > 60)
    after = np.flatnonzero(down)[-1] + 1
    assert written[after:].any(), "writing did not resume after the outage"
    off = log.extras["offset_um"]
    assert np.isfinite(off).all()
    # each step within the limit in force, over the runtime's own step (dt_s); the restarted
    # controller holds 0, so the ramp on reconnect starts from 0 (OFFSET_MISMATCH), not from
    # the last value written before the outage
    dt, limit = log.extras["dt_s"][1:], log.extras["slew_limit_um_per_s"][1:]
    reset = ((alarms & int(Alarm.OFFSET_MISMATCH)) != 0)[1:]
    assert reset.sum() == 1
    assert (np.abs(np.diff(off))[~reset] <= limit[~reset] * dt[~reset] + 1e-6).all()
    assert (np.abs(off[1:][reset]) <= limit[reset] * dt[reset] + 1e-6).all()
    # what the CNC actually held never jumped either, outage included: after the link came
    # back the offset ramped from the held value (lock-step: the machine takes a write at its
    # next 0.5-s plant step; each step is held to the limit of the row that wrote it)
    h = vm.history()
    idx = np.concatenate([[0], np.flatnonzero(np.diff(h.offset_um) != 0) + 1])
    steps = np.abs(np.diff(h.offset_um[idx]))
    row = np.searchsorted(log.time_s - WALL0, h.time_s[idx][1:] - vm.plant_dt_s, side="right") - 1
    lim = log.extras["slew_limit_um_per_s"][np.clip(row, 0, None)]
    assert (steps <= lim * (np.diff(h.time_s[idx]) + vm.plant_dt_s) + 1e-6).all(), steps.max()


def test_restart_advances_the_state_through_the_downtime(tmp_path, model_file):

    t = {"now": 0.0}
    clock = lambda: t["now"]
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=clock)
    vm.override_speed(20000.0)
    from machine_sim.adapter import SimAdapter

    # the state the restart reads is the one the stop saves (no periodic save, no fsync needed)
    cfg = load_config(
        write_config(
            tmp_path,
            model_file,
            'adapter = {url = "sim://"}',
            top={"journal_fsync_s": 3600.0},
            save_every=3600.0,
        )
    )
    sc = cfg.spindle[0]
    a = SpindleRuntime(
        sc,
        cfg.state_dir,
        cfg.journal_path,
        clock=clock,
        wall=lambda: 1e9 + t["now"],
        adapter=SimAdapter(machine=vm),
        journal_fsync_s=cfg.journal_fsync_s,
    )
    assert a.alarms & Alarm.COLD_START
    for _ in range(1800):
        t["now"] += 1.0
        a.cycle()
    a.close()
    saved = a.state
    # two hours of downtime; the reference keeps running at 0 rpm in 1-s cycles
    ref = saved
    for _ in range(7200):
        ref = a.estimate.core.step(ref, 0.0, 1.0)
    t["now"] += 7200.0
    b = SpindleRuntime(
        sc,
        cfg.state_dir,
        cfg.journal_path,
        clock=clock,
        wall=lambda: 1e9 + t["now"],
        adapter=SimAdapter(machine=vm),
    )
    assert not b.alarms & Alarm.COLD_START
    assert abs(b.state.elongation_um - ref.elongation_um) < 1e-6
    assert saved.elongation_um - b.state.elongation_um > 1.0  # it did cool
    b.close()
    # too old: cold start, and said so
    t["now"] += 3 * 86400.0
    c = SpindleRuntime(
        sc,
        cfg.state_dir,
        cfg.journal_path,
        clock=clock,
        wall=lambda: 1e9 + t["now"],
        adapter=SimAdapter(machine=vm),
    )
    assert c.alarms & Alarm.COLD_START and c.est == c.estimate.cold()
    c.close()


def test_kill_9_while_writing_state(tmp_path, model_file):
    """24 hard kills at random moments: every restart finds a valid state file, and the
    restored elongation is within 0.5 um of what the killed run computed in its last or, killed
    between a row and its save, its last but one cycle."""
    cfg = write_config(
        tmp_path,
        model_file,
        'adapter = {url = "sim://motorized-27k?program=job-shop-day&seed=4"}',
        save_every=0.5,
        top={"time_scale": 300.0},
    )
    rng = random.Random(7)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    state_path = tmp_path / "state" / "s1.state.json"
    checked = progressed = 0
    last_saved = None
    for i in range(24):
        proc = subprocess.Popen(
            [sys.executable, "-m", "thermocomp", "run", "--config", str(cfg)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env=env,
        )
        if i % 6 != 5:  # most kills land while it cycles and saves; every sixth during start-up
            before = state_path.stat().st_mtime_ns if state_path.exists() else 0
            end = time.monotonic() + 60
            while time.monotonic() < end and (
                not state_path.exists() or state_path.stat().st_mtime_ns == before
            ):
                time.sleep(0.01)
        time.sleep(rng.uniform(0.0, 0.3))
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        state = load_state(state_path)  # raises on a torn or corrupt file
        assert state is not None and np.isfinite(state["thermal_um"]).all()
        progressed += state["saved_wall_s"] != last_saved
        last_saved = state["saved_wall_s"]
        # newest part: under time_scale each restart's time starts behind the last run's
        journal = sorted(
            (tmp_path / "state" / "journal").glob("s1-*.csv"), key=lambda p: p.stat().st_mtime_ns
        )
        if journal:
            lines = [ln for ln in journal[-1].read_text().splitlines() if ln and ln[0].isdigit()]
            # a cycle journals its row, then saves: a kill in between leaves the state one row
            # behind (in a run-up, one cycle apart is several um)
            last_preds = [float(ln.split(",")[2]) for ln in lines[-2:]]
            assert min(abs(state["elongation_um"] - p) for p in last_preds) <= 0.5, last_preds
            checked += 1
    assert checked >= 21
    assert progressed >= 18  # most kills landed while the service was cycling and saving


def start_service(cfg: Path, env_extra=None):
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env_extra or {})}
    return subprocess.Popen(
        [sys.executable, "-m", "thermocomp", "run", "--config", str(cfg)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def wait_file(path: Path, timeout=60.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if path.exists():
            return True
        time.sleep(0.02)
    return False


def test_two_spindles_sigterm_sighup_and_systemd_notify(tmp_path, model_file):
    import socket

    state = tmp_path / "state"
    cfg = tmp_path / "two.toml"
    body = f"""state_dir = "{state}"
time_scale = 120.0
log_file = "{tmp_path / "log.jsonl"}"
[[spindle]]
name = "a"
model = "{model_file}"
state_save_every_s = 10
adapter = {{url = "sim://motorized-27k?program=job-shop-day&seed=1"}}
[[spindle]]
name = "b"
model = "{model_file}"
period_s = 2.0
state_save_every_s = 10
adapter = {{url = "sim://mechanical-8k?program=job-shop-day&seed=2"}}
"""
    cfg.write_text(body)
    sock_path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(sock_path)
    sock.settimeout(60)
    proc = start_service(cfg, {"NOTIFY_SOCKET": sock_path})
    try:
        assert sock.recv(100) == b"READY=1"
        assert sock.recv(100) == b"WATCHDOG=1"
        assert wait_file(state / "a.state.json") and wait_file(state / "b.state.json")
        # SIGHUP: reload a changed configuration (spindle b removed) without stopping
        cfg.write_text(body.split('[[spindle]]\nname = "b"')[0])
        proc.send_signal(signal.SIGHUP)
        log = tmp_path / "log.jsonl"
        end = time.monotonic() + 30
        while time.monotonic() < end and "reloaded: 1 spindle" not in log.read_text():
            time.sleep(0.05)
        assert proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        sock.close()
    lines = [json.loads(x) for x in (tmp_path / "log.jsonl").read_text().splitlines()]
    msgs = [x["msg"] for x in lines]
    assert any("reloaded: 1 spindle" in m for m in msgs)
    assert msgs[-1] == "stopped; state saved"
    assert all({"ts", "level", "logger", "msg"} <= set(x) for x in lines)
    journals = sorted(p.name.split("-")[0] for p in (state / "journal").glob("*.csv"))
    assert set(journals) == {"a", "b"}


def test_run_check_reads_one_speed_and_writes_nothing(tmp_path, model_file):
    cfg = write_config(
        tmp_path, model_file, 'adapter = {url = "sim://motorized-27k?program=job-shop-day"}'
    )
    r = subprocess.run(
        [sys.executable, "-m", "thermocomp", "run", "--config", str(cfg), "--check"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    assert "link ok" in r.stdout and "nothing was written" in r.stdout
    assert "shaping: dual slew" in r.stdout and "cutting signal from the controller" in r.stdout
    assert not (tmp_path / "state").exists()
    # the speed decides where the configuration says so; a signal required but missing: refused
    cfg.write_text(cfg.read_text() + '[spindle.shaping.cutting]\nsignal = "speed"\n')
    r = subprocess.run(
        [sys.executable, "-m", "thermocomp", "run", "--config", str(cfg), "--check"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0 and "cutting inferred from the speed" in r.stdout, r.stderr


def test_run_check_unreachable_controller_is_one_line(tmp_path, model_file):
    cfg = write_config(
        tmp_path,
        model_file,
        f'adapter = {{url = "opc.tcp://127.0.0.1:{free_port()}/x", preset = "virtual-cnc", timeout_s = 1.0}}',
    )
    r = subprocess.run(
        [sys.executable, "-m", "thermocomp", "run", "--config", str(cfg), "--check"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "thermocomp: error:" in r.stderr


def test_write_refused_raises_an_alarm_and_is_retried(tmp_path, model_file):
    from machine_sim.adapter import SimAdapter

    t = {"now": 0.0}
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=lambda: t["now"])
    vm.override_speed(20000.0)
    cfg = load_config(write_config(tmp_path, model_file, 'adapter = {url = "sim://"}'))
    rt = SpindleRuntime(
        cfg.spindle[0],
        cfg.state_dir,
        cfg.journal_path,
        clock=lambda: t["now"],
        wall=lambda: 1e9 + t["now"],
        adapter=SimAdapter(machine=vm),
    )
    real = vm.apply_offset
    vm.apply_offset = lambda v: False  # the controller refuses every write
    for _ in range(20):
        t["now"] += 1.0
        rec = rt.cycle()
    assert rec["alarms"] & Alarm.WRITE_REJECTED and rt.counters["write_rejected"] >= 19
    vm.apply_offset = real
    t["now"] += 1.0
    rt.cycle()
    assert vm.offset_um == rt.offset.shaper.output_um != 0.0  # retried once accepted
    rt.close()


def test_deferred_write_check_alarms_and_retries_over_opcua(tmp_path, model_file):
    from machine_sim.vcnc import step

    clock = SteppedClock()  # lock-step: the CNC takes (or refuses) each write before the next cycle
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=clock)
    vm.override_speed(20000.0)
    with running(VirtualCNC(vm, tick_s=None)) as cnc:
        step(cnc)
        cfg = load_config(
            write_config(
                tmp_path,
                model_file,
                f'adapter = {{url = "{cnc.url}", preset = "virtual-cnc", verify_writes = "deferred"}}',
            )
        )
        rt = SpindleRuntime(
            cfg.spindle[0], cfg.state_dir, cfg.journal_path, clock=clock, wall=lambda: 1e9 + clock()
        )
        real = vm.apply_offset
        vm.apply_offset = lambda v: False  # this CNC now refuses every offset (and reverts it)
        alarms = Alarm.NONE
        for _ in range(40):
            clock.advance(1.2)
            step(cnc)
            alarms |= rt.cycle()["alarms"]
        step(cnc)
        assert alarms & Alarm.WRITE_REJECTED and rt.counters["write_rejected"] > 0
        assert vm.offset_um == 0.0
        vm.apply_offset = real
        for _ in range(40):
            clock.advance(1.2)
            step(cnc)
            rt.cycle()
        step(cnc)
        assert vm.offset_um != 0.0 and vm.offset_um == pytest.approx(
            rt.offset.shaper.output_um, abs=0.01
        )
        rt.close()
