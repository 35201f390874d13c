"""Each spindle's state (compensating, holding, not writing, with one reason) and the cold start
on a turning spindle (COLD_START_TURNING), through every view: /status, the status line,
`thermocomp status` and its exit code, /metrics and MQTT (a real mosquitto on loopback). The
service runs on a fake clock stepped tick by tick; the controller is a real OPC UA endpoint that
is not there (a closed port) or the simulated machine of ``sim://``."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families
from test_mqtt import (
    MOSQUITTO,
    TOPIC,
    FakeClock,
    Subscriber,
    brokers,  # noqa: F401 - the fixture: mosquitto on loopback
    run_for,
    wait_for,
)

from compensator.io import read_run_log
from machine_sim.vcnc import free_port
from thermocomp.commands.status import EXIT_ATTENTION, EXIT_NOT_WRITING, EXIT_OK, exit_status, table
from thermocomp.runtime import Alarm, Service
from thermocomp.runtime.spindle import slowest_tau_s
from thermocomp.runtime.status import STATES, SpindleFacts, spindle_state

WALL0 = 1_700_000_000.0  # 22:13:20 UTC


def config(
    tmp_path: Path,
    model: Path,
    adapter: str,
    *,
    mqtt_port: int | None = None,
    spindle: str = "",
    sections: str = "",
) -> Path:
    tmp_path.mkdir(parents=True, exist_ok=True)
    p = tmp_path / "machine.toml"
    mqtt = (
        f'[mqtt]\nhost = "127.0.0.1"\nport = {mqtt_port}\ntopic = "{TOPIC}"\npublish_every_s = 5.0\n'
        if mqtt_port
        else ""
    )
    p.write_text(
        f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\n[status]\nport = 0\n{mqtt}'
        f'[[spindle]]\nname = "s1"\nmodel = "{model}"\n{spindle}\nadapter = {adapter}\n'
        "[spindle.shaping]\nmax_offset_um = 40.0\nmax_rate_um_per_s = 2.0\n" + sections
    )
    return p


@pytest.fixture
def services():
    made: list[Service] = []

    def make(cfg: Path, clock: FakeClock | None = None) -> tuple[Service, FakeClock]:
        clock = clock or FakeClock()
        svc = Service(cfg, clock=clock, wall=lambda: WALL0 + clock.t, lock=False)
        made.append(svc)
        return svc, clock

    yield make
    for svc in made:
        svc.close()


def tick(svc: Service, clock: FakeClock) -> str:
    """One tick (the cycle due now), the clock on to the next one due; the state it left."""
    clock.t += max(svc.tick(), 0.25)
    return svc.snapshot["spindles"][0]["state"]


def get_json(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=30) as r:
        return json.loads(r.read())


def metrics(base: str) -> dict[tuple[str, tuple], float]:
    with urllib.request.urlopen(base + "metrics", timeout=30) as r:
        fams = text_string_to_metric_families(r.read().decode())
        return {(s.name, tuple(sorted(s.labels.items()))): s.value for f in fams for s in f.samples}


def state_gauges(m: dict, spindle: str = "s1") -> dict[str, float]:
    return {
        word: m[("thermocomp_spindle_state", (("spindle", spindle), ("state", word)))]
        for word in STATES
    }


def status_cli(url: str, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "thermocomp", "status", "--url", url, *extra],
        capture_output=True,
        text=True,
        timeout=60,
    )


# -- the rule itself -------------------------------------------------------------------------


def facts(**kw) -> SpindleFacts:
    base = {
        "now_s": WALL0 + 100.0,
        "period_s": 1.0,
        "not_writing_cycles": 3,
        "cycles": 100,
        "link_up": True,
        "last_in_step_s": WALL0 + 100.0,
        "last_write_s": WALL0 + 90.0,
        "since_s": WALL0,
    }
    return SpindleFacts(**{**base, **kw})


def test_the_rule():
    assert spindle_state(facts()).line == "compensating"
    down = spindle_state(
        facts(
            link_up=False,
            link_state="retrying",
            link_down_since_s=WALL0 + 50.0,
            link_error="opc.tcp://10.0.0.7:4840: connection refused",
        )
    )
    assert (
        down.line
        == "not writing: link down since 22:14:10 UTC (opc.tcp://10.0.0.7:4840: connection refused)"
    )
    # in step 3 cycles ago: still writing; 3.5: not
    assert spindle_state(facts(last_in_step_s=WALL0 + 97.0)).state == "compensating"
    late = spindle_state(facts(last_in_step_s=WALL0 + 96.5, offset_mode="holding"))
    assert (
        late.line
        == "not writing: no write has gone through since 22:14:56 UTC; last write 22:14:50 UTC"
    )
    assert (
        spindle_state(facts(last_in_step_s=WALL0 + 99.0, offset_mode="holding")).state == "holding"
    )
    assert "never written" in spindle_state(facts(last_in_step_s=None, last_write_s=None)).reason
    refused = spindle_state(facts(last_in_step_s=WALL0 + 90.0, alarm_bits=int(Alarm.WRITE_BACKOFF)))
    assert refused.state == "not writing" and "refusing" in refused.reason
    assert spindle_state(facts(cycles=0, now_s=WALL0 + 2.0, last_in_step_s=None)).reason.startswith(
        "starting"
    )
    assert spindle_state(facts(alarm_bits=int(Alarm.NOT_READY))).state == "holding"
    sensor = spindle_state(facts(alarm_bits=int(Alarm.SPEED_READ_FAILED | Alarm.IDLE_ASSUMED)))
    assert sensor.line == "holding: sensor fault: speed not read, idle assumed"
    cold = spindle_state(
        facts(alarm_bits=int(Alarm.COLD_START_TURNING), cold_settle_s=WALL0 + 3600.0)
    )
    assert (
        cold.state == "compensating"
        and "until 23:13:20 UTC or a measurement accepted" in cold.reason
    )
    assert spindle_state(facts(writes_offset=False, last_in_step_s=None)).state == "compensating"


def test_exit_status_of_thermocomp_status():
    def snap(*spindles, cooling=None):
        return {
            "spindles": [
                {"name": f"s{i}", "state": w, "alarms": a} for i, (w, a) in enumerate(spindles)
            ],
            "cooling": cooling,
        }

    assert exit_status(snap(("compensating", []), ("compensating", []))) == EXIT_OK
    assert exit_status(snap(("compensating", ["COLD_START_TURNING"]))) == EXIT_ATTENTION
    assert exit_status(snap(("compensating", []), ("holding", []))) == EXIT_ATTENTION
    assert (
        exit_status(snap(("compensating", []), cooling={"alarm": "CHILLER_FAILED"}))
        == EXIT_ATTENTION
    )
    assert (
        exit_status(snap(("holding", ["WRITE_REJECTED"]), ("not writing", ["LINK_DOWN"])))
        == EXIT_NOT_WRITING
    )
    assert (
        exit_status({"spindles": [{"name": "s1", "alarms": []}]}) == EXIT_ATTENTION
    )  # an older service: no state


# -- (1) a wrong endpoint --------------------------------------------------------------------


def closed_endpoint(
    tmp_path: Path, model: Path, services, mqtt_port: int | None = None
) -> tuple[Service, int]:
    """A service whose controller's URL points where nothing listens (a wrong URL), 30 s on."""
    closed = free_port()
    svc, clock = services(
        config(
            tmp_path,
            model,
            mqtt_port=mqtt_port,
            adapter=f'{{url = "opc.tcp://127.0.0.1:{closed}/thermocomp/virtual-cnc/", preset = "virtual-cnc", '
            "timeout_s = 1.0, backoff_s = 0.2, max_backoff_s = 2.0}",
        )
    )
    svc.start_status()
    if mqtt_port is not None:
        wait_for(lambda: svc.mqtt.connected, 10, "the service's connection to the broker")
    run_for(svc, clock, 30)
    return svc, closed


def test_a_closed_endpoint_is_not_writing(tmp_path, calibrated_model, services, caplog):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    svc, closed = closed_endpoint(tmp_path, calibrated_model, services)
    base = svc.status_server.url
    st = get_json(base + "status")
    (s1,) = st["spindles"]
    assert s1["state"] == "not writing" and s1["compensating"] is False
    assert s1["state_reason"].startswith("link down since 22:13:20 UTC (")
    assert f"127.0.0.1:{closed}" in s1["state_reason"] and s1["last_write_age_s"] is None
    # the header counts no spindle that does not write
    assert st["status"].startswith(
        "NOT compensating (0 of 1 spindle(s)); s1 not writing: link down"
    )
    assert "compensating 1 spindle" not in st["status"]

    m = metrics(base)
    assert m[("thermocomp_compensating", (("spindle", "s1"),))] == 0.0
    assert state_gauges(m) == {"compensating": 0.0, "holding": 0.0, "not writing": 1.0}
    assert m[("thermocomp_link_up", (("spindle", "s1"),))] == 0.0

    r = status_cli(base, "--exit-code")
    assert r.returncode == EXIT_NOT_WRITING == 3, r.stderr
    lines = r.stdout.splitlines()
    assert "NOT compensating" in lines[0]
    assert next(x for x in lines if x.split()[:1] == ["s1"]).split()[1:3] == ["not", "writing"]
    assert any(x.startswith("s1: not writing: link down since 22:13:20 UTC") for x in lines)
    assert status_cli(base).returncode == 0  # without --exit-code: the table only
    assert any(
        getattr(r, "event", None) == "spindle_state" and r.fields["state"] == "not writing"
        for r in caplog.records
    )


@pytest.mark.skipif(
    not MOSQUITTO.exists(), reason="mosquitto is not installed (scripts/system-deps.sh)"
)
def test_a_closed_endpoint_is_not_writing_on_mqtt(tmp_path, calibrated_model, services, brokers):
    broker = brokers.start()
    sub = Subscriber(broker)
    try:
        svc, _ = closed_endpoint(tmp_path, calibrated_model, services, broker)
        reason = svc.snapshot["spindles"][0]["state_reason"]
        assert reason.startswith("link down since 22:13:20 UTC (")
        # the spindle's own topic and the whole status say it, as /status does
        spindle = json.loads(
            sub.wait("spindle/s1", lambda p, r: json.loads(p).get("state") == "not writing")
        )
        assert spindle["state_reason"] == reason and spindle["compensating"] is False
        whole = json.loads(
            sub.wait("status", lambda p, r: json.loads(p)["status"].startswith("NOT"))
        )
        assert whole["spindles"][0]["state"] == "not writing"
        assert "compensating 1 spindle" not in whole["status"]
    finally:
        sub.close()


# -- (2) writes that stop ----------------------------------------------------------------------


def test_writes_that_stop_turn_to_not_writing_after_n_cycles(
    tmp_path, calibrated_model, services, caplog
):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    svc, clock = services(
        config(
            tmp_path,
            calibrated_model,
            '{url = "sim://motorized-27k?program="}',
            sections="[spindle.faults]\nnot_writing_cycles = 5\n",
        )
    )
    svc.start_status()
    rt = svc.spindles["s1"]
    vm = rt.adapter.machine
    vm.override_speed(20000.0)  # warming: the offset moves every cycle
    run_for(svc, clock, 120)
    assert (
        svc.snapshot["spindles"][0]["state"] == "compensating"
        and rt.offset.last_in_step_s == rt.last["time_s"]
    )
    real, vm.apply_offset = vm.apply_offset, (lambda v: False)  # the controller refuses every write
    before = []
    while not rt.counters["write_rejected"]:  # within the deadband no write is due: still in step
        before.append(tick(svc, clock))
        assert len(before) < 60
    assert set(before[:-1]) <= {"compensating"}
    states = before[-1:] + [tick(svc, clock) for _ in range(7)]  # from the first write refused
    assert rt.counters["write_rejected"] == 8
    # within not_writing_cycles the offset is held at its last value; past them, not writing
    assert states[:5] == ["holding"] * 5 and states[5:] == ["not writing"] * 3, states
    st = svc.snapshot
    assert (
        "refus" in st["spindles"][0]["state_reason"]
        and "last write" in st["spindles"][0]["state_reason"]
    )
    assert st["status"].startswith("NOT compensating") and exit_status(st) == EXIT_NOT_WRITING
    assert "s1: not writing: the controller" in table(st)
    m = metrics(svc.status_server.url)
    assert (
        state_gauges(m)["not writing"] == 1.0
        and m[("thermocomp_compensating", (("spindle", "s1"),))] == 0.0
    )
    vm.apply_offset = real  # it takes writes again: compensating once the back-off has passed
    run_for(svc, clock, 600)
    st = svc.snapshot
    assert (
        st["spindles"][0]["state"] == "compensating" and st["status"] == "compensating 1 spindle(s)"
    )
    words = [
        r.fields["state"] for r in caplog.records if getattr(r, "event", None) == "spindle_state"
    ]
    assert words[-3:] == ["holding", "not writing", "compensating"]


# -- (3) a cold start on a warm, turning spindle ----------------------------------------------------


def warm_cold_start(
    tmp_path: Path, model: Path, services, sections: str = ""
) -> tuple[Service, FakeClock]:
    """A spindle turning for an hour at 20000 rpm (the machine is warm), then a service with no
    saved state starts: a cold start, the estimate from rest."""
    svc, clock = services(
        config(
            tmp_path,
            model,
            '{url = "sim://motorized-27k?program="}',
            spindle="period_s = 2.0",
            sections=sections,
        )
    )
    vm = svc.spindles["s1"].adapter.machine
    vm.override_speed(20000.0)
    clock.t = 3600.0
    vm.advance()
    assert vm.plant.true_elongation_um() > 10.0
    svc.start_status()
    return svc, clock


def test_cold_start_on_a_turning_spindle_alarms_until_settled(
    tmp_path, calibrated_model, services, caplog
):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    svc, clock = warm_cold_start(tmp_path, calibrated_model, services)
    rt = svc.spindles["s1"]
    run_for(svc, clock, 10)
    s1 = svc.snapshot["spindles"][0]
    assert "COLD_START_TURNING" in s1["alarms"] and s1["state"] == "compensating"
    assert s1["state_reason"].startswith(
        "estimate unsettled after a cold start on a turning spindle (until "
    )
    # the status line counts it as compensating, and says on what
    assert svc.snapshot["status"].startswith(
        "compensating 1 spindle(s); s1 compensating: estimate unsettled"
    )
    tau = slowest_tau_s(rt.estimate.model)
    assert tau is not None and 300 < tau < 86400
    # settled: 3 slowest time constants after the first cycle (the default cold_start_settle_taus)
    assert s1["cold_start_settles_s"] == pytest.approx(WALL0 + 3600.0 + 3 * tau)
    m = metrics(svc.status_server.url)
    assert m[("thermocomp_alarm", (("alarm", "COLD_START_TURNING"), ("spindle", "s1")))] == 1.0
    raised = [r for r in caplog.records if getattr(r, "event", None) == "cold_start_turning"]
    assert len(raised) == 1 and raised[0].fields["speed_rpm"] == pytest.approx(20000.0, rel=0.01)
    settles = rt.cold.settle_s
    run_for(svc, clock, settles - clock.t - 10.0)
    assert "COLD_START_TURNING" in svc.snapshot["spindles"][0]["alarms"]
    run_for(svc, clock, 20.0)
    s1 = svc.snapshot["spindles"][0]
    assert (
        "COLD_START_TURNING" not in s1["alarms"]
        and s1["state_reason"] == ""
        and s1["state"] == "compensating"
    )
    assert [
        r.fields["reason"]
        for r in caplog.records
        if getattr(r, "event", None) == "cold_start_settled"
    ] == ["settled"]
    svc.close()
    # the journal's rows carry the alarm from the first cycle until it settled, not after
    logs = [
        read_run_log(p) for p in sorted((tmp_path / "state" / "journal").glob("s1-*.csv"))
    ]  # by day
    bits = (
        np.concatenate(
            [lg.extras["alarms"].astype(int) & int(Alarm.COLD_START_TURNING) for lg in logs]
        )
        != 0
    )
    t = np.concatenate([lg.time_s for lg in logs]) - WALL0
    assert bits[0] and bits[t < settles - 1].all() and not bits[t > settles + 1].any()


def test_cold_start_on_a_turning_spindle_clears_at_an_accepted_measurement(
    tmp_path, calibrated_model, services, caplog
):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    svc, clock = warm_cold_start(
        tmp_path, calibrated_model, services, "[spindle.observer]\nenabled = true\n"
    )
    rt = svc.spindles["s1"]
    run_for(svc, clock, 10)
    assert "COLD_START_TURNING" in svc.snapshot["spindles"][0]["alarms"]
    vm = rt.adapter.machine
    outcomes: list[str] = []
    for _ in range(10):  # the tool setter measures the real growth, far from the cold estimate
        answers: list[dict] = []
        rt.submit(vm.plant.true_elongation_um(), 0.5, answers.append)
        tick(svc, clock)
        outcomes.append(answers[0]["outcome"])
        alarms = svc.snapshot["spindles"][0]["alarms"]
        if outcomes[-1] == "rejected":  # beyond the gate: the estimate was not corrected
            assert "COLD_START_TURNING" in alarms
        else:
            assert "COLD_START_TURNING" not in alarms
            break
    assert outcomes[-1] in ("accepted", "restarted"), outcomes
    assert (
        clock.t < 3600.0 + 600.0 < rt.pace.created_s + 3600.0 + slowest_tau_s(rt.estimate.model)
    )  # long before settling
    cleared = [r for r in caplog.records if getattr(r, "event", None) == "cold_start_settled"]
    assert len(cleared) == 1 and cleared[0].fields["reason"] == "measurement"
    # the model alone still carries the start's error: its misses are not taken as drift
    assert rt.drift.seen == 0 and not rt.drift.detected
    run_for(svc, clock, 60)
    assert "COLD_START_TURNING" not in svc.snapshot["spindles"][0]["alarms"]


def test_an_unsettled_cold_start_survives_a_restart(tmp_path, calibrated_model, services):
    svc, clock = warm_cold_start(tmp_path, calibrated_model, services)
    run_for(svc, clock, 60)
    settles = svc.spindles["s1"].cold.settle_s
    svc.close()  # saves the state, with when the estimate settles
    clock.t += 600.0
    again, _ = services(svc.config_path, clock)
    assert again.spindles["s1"].cold.settle_s == pytest.approx(settles, abs=1.0)  # the same instant
    again.start_status()
    run_for(again, clock, 10)
    assert "COLD_START_TURNING" in again.snapshot["spindles"][0]["alarms"]


# -- (4) a healthy spindle ---------------------------------------------------------------------------


def test_a_healthy_spindle_is_compensating(tmp_path, calibrated_model, services):
    svc, clock = services(
        config(
            tmp_path, calibrated_model, '{url = "sim://motorized-27k?program=job-shop-day&seed=4"}'
        )
    )
    svc.start_status()
    seen = set()
    run_for(svc, clock, 60)
    while clock.t < 1800:  # idle, run-ups, cutting: the deadband leaves many cycles without a write
        seen.add(tick(svc, clock))
    assert seen == {"compensating"}
    rt = svc.spindles["s1"]
    assert rt.counters["writes"] < rt.counters["cycles"]  # not every cycle wrote, yet compensating
    base = svc.status_server.url
    st = get_json(base + "status")
    assert st["status"] == "compensating 1 spindle(s)" and st["spindles"][0]["state_reason"] == ""
    assert "COLD_START_TURNING" not in st["spindles"][0]["alarms"]  # a cold start at rest
    m = metrics(base)
    assert m[("thermocomp_compensating", (("spindle", "s1"),))] == 1.0
    assert state_gauges(m) == {"compensating": 1.0, "holding": 0.0, "not writing": 0.0}
    r = status_cli(base, "--exit-code")
    assert r.returncode == (EXIT_OK if not st["spindles"][0]["alarms"] else 1), r.stdout
    assert "s1: compensating" in r.stdout.splitlines()
