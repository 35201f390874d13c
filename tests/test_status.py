"""Live status: /status, /history, /metrics and the token, served by the real service on
loopback; `thermocomp status` reads them. The service runs in simulated time (a fake clock);
the HTTP server answers from its own thread with what the last tick published."""

from __future__ import annotations

import json
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from thermocomp.runtime import Alarm, Service

WALL0 = 1_700_000_000.0


@pytest.fixture
def model_file(calibrated_model):
    return calibrated_model


def config(tmp_path: Path, model: Path, status: str = "port = 0", extra: str = "") -> Path:
    tmp_path.mkdir(parents=True, exist_ok=True)
    p = tmp_path / "machine.toml"
    p.write_text(
        f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\n{extra}\n'
        f"[status]\n{status}\n"
        f'[[spindle]]\nname = "s1"\nmodel = "{model}"\n'
        'adapter = {url = "sim://motorized-27k?program=job-shop-day&seed=4"}\n'
        "[spindle.shaping]\nmax_offset_um = 40.0\nmax_rate_um_per_s = 2.0\n"
    )
    return p


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def run_for(svc: Service, clock: FakeClock, seconds: float) -> None:
    end = clock.t + seconds
    while clock.t < end:
        clock.t += max(svc.tick(), 0.25)


def get(url: str, token: str | None = None) -> tuple[int, bytes, str]:
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, r.read(), r.headers.get("Content-Type", "")
    except urllib.error.HTTPError as err:
        return err.code, err.read(), err.headers.get("Content-Type", "")


@pytest.fixture
def service(tmp_path, model_file):
    clock = FakeClock()
    svc = Service(
        config(tmp_path, model_file), clock=clock, wall=lambda: WALL0 + clock.t, lock=False
    )
    svc.start_status()
    yield svc, clock
    svc.close()


def test_status_history_and_metrics_of_a_running_service(service):
    svc, clock = service
    base = svc.status_server.url
    assert base.startswith("http://127.0.0.1:")
    assert (svc.cfg.state_dir / "status.url").read_text().strip() == base
    run_for(svc, clock, 2 * 3600)
    code, body, ctype = get(base + "status")
    assert code == 200 and ctype.startswith("application/json")
    st = json.loads(body)
    (s1,) = st["spindles"]
    rt = svc.spindles["s1"]
    assert s1["name"] == "s1" and s1["speed_rpm"] == rt.last["speed_rpm"]
    assert s1["elongation_um"] == pytest.approx(rt.estimate_um())
    assert s1["offset_held_um"] == pytest.approx(rt.offset.held_um)
    assert s1["offset_read_back_um"] is not None  # the sim link reads the offset back
    assert 0 <= s1["last_write_age_s"] <= 3600
    assert s1["model"]["speed_range_rpm"][1] > s1["model"]["speed_range_rpm"][0] > -1
    assert len(s1["model"]["digest"]) == 64 and s1["link"] == "connected"
    assert set(s1["inputs"]) >= {"bearing_temp_c", "spindle_load_pct"}
    assert st["time_s"] == pytest.approx(WALL0 + clock.t, abs=1.0)
    assert st["uptime_s"] == pytest.approx(clock.t, abs=1.0)
    assert s1["counters"]["cycles"] > 7000

    # the plot's history: one point per 10 s over the two hours, then only what is new
    code, body, _ = get(base + "history?spindle=s1")
    h = json.loads(body)
    assert code == 200 and 700 <= len(h["time_s"]) <= 721
    assert all(b > a for a, b in zip(h["time_s"], h["time_s"][1:]))
    assert max(h["elongation_um"]) > 5.0 and max(h["speed_rpm"]) > 1000
    last = h["time_s"][-2]
    run_for(svc, clock, 60)
    newer = json.loads(get(base + f"history?since={last}")[1])
    assert newer["time_s"][0] > last and 6 <= len(newer["time_s"]) <= 8
    assert get(base + "history?spindle=nope")[0] == 404
    assert get(base + "history?since=x")[0] == 400
    assert get(base + "nothing")[0] == 404

    # Prometheus: parsed by prometheus_client's own parser, values as in /status
    code, body, ctype = get(base + "metrics")
    assert code == 200 and ctype.startswith("text/plain")
    st = json.loads(get(base + "status")[1])
    fams = {f.name: f for f in text_string_to_metric_families(body.decode())}
    val = lambda fam, **lab: next(
        s.value for s in fams[fam].samples if all(s.labels.get(k) == v for k, v in lab.items())
    )
    assert val("thermocomp_up") == 1.0
    assert val("thermocomp_elongation_micrometres", spindle="s1") == pytest.approx(
        st["spindles"][0]["elongation_um"]
    )
    assert val("thermocomp_offset_held_micrometres", spindle="s1") == pytest.approx(
        st["spindles"][0]["offset_held_um"]
    )
    assert val("thermocomp_alarm", spindle="s1", alarm="LINK_DOWN") == 0.0
    assert val("thermocomp_cycles", spindle="s1") == st["spindles"][0]["counters"]["cycles"]
    assert len(list(fams["thermocomp_alarm"].samples)) == len([a for a in Alarm if a])


def test_alarms_show_in_status_history_and_metrics(service):
    svc, clock = service
    base = svc.status_server.url
    run_for(svc, clock, 600)
    vm = svc.spindles["s1"].adapter.machine
    vm.sensor_faults["bearing_temp_c"] = "nan"  # not used by a speed-only model: no alarm
    run_for(svc, clock, 30)
    assert json.loads(get(base + "status")[1])["spindles"][0]["alarms"] == []
    svc.spindles["s1"].sticky_alarms = Alarm.RELOAD_FAILED
    svc.reload_failed = True
    run_for(svc, clock, 30)
    st = json.loads(get(base + "status")[1])
    assert "RELOAD_FAILED" in st["spindles"][0]["alarms"] and st["reload_failed"] is True
    h = json.loads(get(base + "history?spindle=s1")[1])
    assert h["alarm_bits"][0] & int(Alarm.COLD_START)  # the first interval: a cold start
    assert h["alarm_bits"][-1] & int(Alarm.RELOAD_FAILED) and not h["alarm_bits"][10]
    fams = {f.name: f for f in text_string_to_metric_families(get(base + "metrics")[1].decode())}
    raised = {s.labels["alarm"] for s in fams["thermocomp_alarm"].samples if s.value == 1.0}
    assert raised == {"RELOAD_FAILED"}


def test_token_access(tmp_path, model_file, monkeypatch):
    monkeypatch.setenv("THERMOCOMP_STATUS_TOKEN", "s3cret-token-0123456789")
    clock = FakeClock()
    svc = Service(
        config(tmp_path, model_file, 'port = 0\naccess = "token"'),
        clock=clock,
        wall=lambda: WALL0 + clock.t,
        lock=False,
    )
    svc.start_status()
    try:
        run_for(svc, clock, 60)
        base = svc.status_server.url
        for path in ("", "status", "history", "metrics"):
            assert get(base + path)[0] == 401
            assert get(base + path, "wrong-token-0123456789")[0] == 401
        assert get(base + "status", "s3cret-token-0123456789")[0] == 200
        assert get(base + "metrics?token=s3cret-token-0123456789")[0] == 200
        r = subprocess.run(
            [sys.executable, "-m", "thermocomp", "status", "--url", base],
            capture_output=True,
            text=True,
            timeout=60,
            env={**__import__("os").environ, "THERMOCOMP_STATUS_TOKEN": ""},
        )
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and "token" in r.stderr
    finally:
        svc.close()


def test_a_short_token_or_busy_port_never_stops_compensation(tmp_path, model_file, monkeypatch):
    from compensator.errors import ConfigError

    monkeypatch.setenv("THERMOCOMP_STATUS_TOKEN", "short")
    clock = FakeClock()
    svc = Service(
        config(tmp_path, model_file, 'port = 0\naccess = "token"'),
        clock=clock,
        wall=lambda: WALL0 + clock.t,
        lock=False,
    )
    with pytest.raises(ConfigError, match="at least 16"):
        svc.cfg.status.token()  # what `run --check` says in one line
    svc.start_status()
    assert svc.status_server is None  # no endpoint, and never an open one instead
    run_for(svc, clock, 120)
    assert svc.spindles["s1"].counters["writes"] > 0
    svc.close()
    # a port another program holds: logged, and the service compensates without the endpoint
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        svc = Service(
            config(tmp_path / "b", model_file, f"port = {port}"),
            clock=clock,
            wall=lambda: WALL0 + clock.t,
            lock=False,
        )
        svc.start_status()
        assert svc.status_server is None
        run_for(svc, clock, 120)
        assert svc.spindles["s1"].counters["writes"] > 0
        svc.close()


def test_thermocomp_status_prints_a_table_and_json(service):
    svc, clock = service
    run_for(svc, clock, 1800)
    url = svc.status_server.url
    r = subprocess.run(
        [sys.executable, "-m", "thermocomp", "status", "--url", url],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    st = json.loads(get(url + "status")[1])
    s1 = st["spindles"][0]
    lines = r.stdout.splitlines()
    row = next(x for x in lines if x.split()[:1] == ["s1"])
    assert f"{s1['elongation_um']:.2f}" in row.split() or f"{s1['elongation_um']:.2f}" in row
    assert lines[1].split()[:4] == [
        "spindle",
        "state",
        "speed_rpm",
        "S_um",
    ]  # the header, then the row
    assert row.split()[1] == "compensating" and "s1: compensating" in lines
    assert lines[0].endswith("compensating 1 spindle(s)")
    r = subprocess.run(
        [sys.executable, "-m", "thermocomp", "status", "--config", str(svc.config_path), "--json"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["spindles"][0]["name"] == "s1"
    # nothing listening: one line, exit 2
    svc.status_server.close()
    r = subprocess.run(
        [sys.executable, "-m", "thermocomp", "status", "--url", url],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "not reach" in r.stderr
    svc.status_server = None


def test_a_malformed_request_is_answered_and_the_server_goes_on(service, capfd):
    import socket

    svc, clock = service
    run_for(svc, clock, 30)
    host, port = "127.0.0.1", svc.status_server.port
    for raw in (b"GET /" + b"x" * 70_000 + b" HTTP/1.1\r\n\r\n", b"\x16\x03\x01garbage\r\n\r\n"):
        with socket.create_connection((host, port), timeout=10) as s:
            s.sendall(raw)
            answer = s.recv(200)
        assert answer  # an error page (HTTP/0.9 style for a request line with no version)
        if raw.startswith(b"GET"):
            assert answer.split()[1] == b"414"
    assert get(svc.status_server.url + "status")[0] == 200
    assert "Traceback" not in capfd.readouterr().err
