"""MQTT: the service's status on a real broker (Debian's mosquitto, started here on a free
loopback port) and read back with paho. The in-process service runs on a fake clock; waits are
for a condition, in real time, with a timeout."""

from __future__ import annotations

import json
import logging
import os
import pwd
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import paho.mqtt.client as paho
import pytest

from thermocomp.runtime import Service
from thermocomp.runtime.mqtt import RECONNECT_MAX_S

MOSQUITTO = Path("/usr/sbin/mosquitto")
pytestmark = pytest.mark.skipif(
    not MOSQUITTO.exists(),
    reason="mosquitto is not installed (apt-get install mosquitto; scripts/system-deps.sh does)",
)
WALL0 = 1_700_000_000.0
TOPIC = "shop/m1"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(cond, timeout: float, what: str):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = cond()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")


class Brokers:
    """mosquitto processes on loopback, stopped at the end of the test."""

    def __init__(self, tmp_path: Path):
        self.tmp_path = tmp_path
        self.procs: list[subprocess.Popen] = []

    def start(self, port: int | None = None, users: dict[str, str] | None = None) -> int:
        port = port or free_port()
        d = self.tmp_path / f"mosquitto-{port}-{len(self.procs)}"
        d.mkdir()
        # as root it would switch to the user `mosquitto`, which cannot read tmp_path
        conf = [
            f"user {pwd.getpwuid(os.getuid()).pw_name}",
            f"listener {port} 127.0.0.1",
            "persistence false",
            "log_dest stderr",
            "log_type all",
        ]
        if users:
            pw = d / "passwd"
            for i, (user, password) in enumerate(users.items()):
                subprocess.run(
                    [
                        "mosquitto_passwd",
                        "-b",
                        *(["-c"] if i == 0 else []),
                        str(pw),
                        user,
                        password,
                    ],
                    check=True,
                    capture_output=True,
                )
            conf += ["allow_anonymous false", f"password_file {pw}"]
        else:
            conf.append("allow_anonymous true")
        (d / "mosquitto.conf").write_text("\n".join(conf) + "\n")
        self.log = d / "mosquitto.log"
        proc = subprocess.Popen(
            [str(MOSQUITTO), "-c", str(d / "mosquitto.conf")],
            stdout=subprocess.DEVNULL,
            stderr=self.log.open("w"),
        )
        self.procs.append(proc)

        def listening() -> bool:
            assert proc.poll() is None, self.log.read_text()
            with socket.socket() as s:
                return s.connect_ex(("127.0.0.1", port)) == 0

        wait_for(listening, 10, f"mosquitto on port {port}")
        return port

    def stop(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()


@pytest.fixture
def brokers(tmp_path):
    b = Brokers(tmp_path)
    yield b
    b.stop()


class Subscriber:
    """A paho client on ``<TOPIC>/#`` keeping every message: (topic, payload text, retain)."""

    def __init__(self, port: int, auth: tuple[str, str] | None = None):
        self.messages: list[tuple[str, str, bool]] = []
        self.lock = threading.Lock()
        self.c = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id=f"test-{id(self)}")
        if auth:
            self.c.username_pw_set(*auth)
        self.c.on_connect = lambda c, *_: c.subscribe(f"{TOPIC}/#", qos=1)
        self.c.on_message = self._on_message
        self.c.connect("127.0.0.1", port, keepalive=10)
        self.c.loop_start()

    def _on_message(self, client, userdata, msg) -> None:
        with self.lock:
            self.messages.append((msg.topic, msg.payload.decode(), msg.retain))

    def last(self, sub: str, pred=lambda payload, retain: True):
        """The newest message on ``<TOPIC>/<sub>`` that ``pred`` accepts, or None."""
        with self.lock:
            for topic, payload, retain in reversed(self.messages):
                if topic == f"{TOPIC}/{sub}" and pred(payload, retain):
                    return payload
        return None

    def wait(self, sub: str, pred=lambda payload, retain: True, timeout: float = 15.0) -> str:
        return wait_for(lambda: self.last(sub, pred), timeout, f"a message on {TOPIC}/{sub}")

    def close(self) -> None:
        self.c.disconnect()
        self.c.loop_stop()


def status_at(uptime_s: float, retained: bool | None = None):
    """A predicate: the status JSON of the tick at ``uptime_s`` (the fake clock)."""
    return lambda p, r: (
        json.loads(p)["uptime_s"] == uptime_s and (retained is None or r == retained)
    )


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def config(tmp_path: Path, model: Path, mqtt: str, top: str = "") -> Path:
    p = tmp_path / "machine.toml"
    p.write_text(
        f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\n{top}\n'
        "[status]\nenabled = false\n"
        f'[mqtt]\ntopic = "{TOPIC}"\n{mqtt}\n'
        f'[[spindle]]\nname = "s1"\nmodel = "{model}"\n'
        'adapter = {url = "sim://motorized-27k?program=job-shop-day&seed=4"}\n'
        "[spindle.shaping]\nmax_offset_um = 40.0\nmax_rate_um_per_s = 2.0\n"
    )
    return p


@pytest.fixture
def services():
    made: list[Service] = []

    def make(cfg: Path) -> tuple[Service, FakeClock]:
        clock = FakeClock()
        svc = Service(cfg, clock=clock, wall=lambda: WALL0 + clock.t, lock=False)
        made.append(svc)
        svc.start_status()
        return svc, clock

    yield make
    for svc in made:
        if svc.mqtt is not None:  # not closed by the test
            svc.close()


def run_for(svc: Service, clock: FakeClock, seconds: float) -> None:
    end = clock.t + seconds
    while clock.t < end:
        clock.t += max(svc.tick(), 0.25)


def tick_until_published(svc: Service, clock: FakeClock) -> float:
    """Tick until the publisher hands a snapshot to paho; the fake time of that tick."""
    n = svc.mqtt.published
    while svc.mqtt.published == n:
        clock.t += max(svc.tick(), 0.25)
        assert clock.t < 3600, "nothing published in an hour"
    return svc.snapshot["uptime_s"]


def mqtt_events(caplog, name: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if getattr(r, "event", None) == name]


def test_retained_status_and_availability(tmp_path, calibrated_model, brokers, services):
    port = brokers.start()
    svc, clock = services(
        config(
            tmp_path, calibrated_model, f'host = "127.0.0.1"\nport = {port}\npublish_every_s = 10'
        )
    )
    live = Subscriber(port)
    try:
        wait_for(lambda: svc.mqtt.connected, 10, "the service's connection")
        run_for(svc, clock, 300)
        at = tick_until_published(svc, clock)
        live.wait("status", status_at(at))  # the broker has it
        snap = svc.snapshot
        # and the spindle's message of the same publish: it follows the status, and a subscriber
        # that connects between the two would get the previous one as the retained message
        live.wait(
            "spindle/s1", lambda p, r: json.loads(p)["time_s"] == snap["spindles"][0]["time_s"]
        )
        late = Subscriber(port)  # connects after the publish: retained messages only
        st = json.loads(late.wait("status", status_at(at, retained=True)))
        assert st == snap and st["spindles"][0]["name"] == "s1"
        assert st["spindles"][0]["elongation_um"] == snap["spindles"][0]["elongation_um"] > 0
        sp = json.loads(
            late.wait(
                "spindle/s1",
                lambda p, r: r and json.loads(p)["time_s"] == snap["spindles"][0]["time_s"],
            )
        )
        assert sp == snap["spindles"][0]
        assert late.wait("availability", lambda p, r: r) == "online"
        late.close()
        assert 25 <= svc.mqtt.published <= 45 and svc.mqtt.skipped <= 1  # every 10 s of 300 s

        svc.close()
        assert live.wait("availability", lambda p, r: p == "offline")
        after = Subscriber(port)
        assert after.wait("availability", lambda p, r: r) == "offline"
        after.close()
    finally:
        live.close()


def test_last_will_when_the_service_is_killed(tmp_path, calibrated_model, brokers):
    port = brokers.start()
    cfg = config(
        tmp_path,
        calibrated_model,
        f'host = "127.0.0.1"\nport = {port}\nkeepalive_s = 5',
        top=f'time_scale = 60.0\nlog_file = "{tmp_path / "log.jsonl"}"',
    )
    sub = Subscriber(port)
    proc = subprocess.Popen(
        [sys.executable, "-m", "thermocomp", "run", "--config", str(cfg)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        sub.wait("availability", lambda p, r: p == "online", timeout=60)
        st = json.loads(sub.wait("status", timeout=30))
        assert st["pid"] == proc.pid and st["spindles"][0]["name"] == "s1"
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        # the broker's last will: the socket closed without a DISCONNECT
        sub.wait("availability", lambda p, r: p == "offline", timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        sub.close()
    lines = [json.loads(x) for x in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [x["event"] for x in lines if x.get("event", "").startswith("mqtt")] == [
        "mqtt_connected"
    ]


def test_broker_down_at_start_then_up(tmp_path, calibrated_model, brokers, services, caplog):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    port = free_port()  # nobody listens yet
    svc, clock = services(
        config(
            tmp_path, calibrated_model, f'host = "127.0.0.1"\nport = {port}\npublish_every_s = 10'
        )
    )
    wait_for(lambda: mqtt_events(caplog, "mqtt_lost"), 10, "the mqtt_lost event")
    run_for(svc, clock, 1800)
    rt = svc.spindles["s1"]
    assert rt.counters["cycles"] >= 1700 and rt.counters["writes"] > 100
    assert abs(rt.offset.held_um) > 1.0 and rt.offset.last_write_s is not None
    assert svc.mqtt.published == 0 and 150 <= svc.mqtt.skipped <= 200  # one per 10 s due
    (lost,) = mqtt_events(caplog, "mqtt_lost")  # one line for the outage, not one per attempt
    assert "refused" in lost.fields["reason"].lower() and lost.levelno == logging.WARNING

    brokers.start(port)
    sub = Subscriber(port)
    try:
        # paho's back-off: the next attempt within RECONNECT_MAX_S
        wait_for(lambda: svc.mqtt.connected, RECONNECT_MAX_S + 10, "the reconnection")
        at = tick_until_published(svc, clock)  # at once after connecting, not 10 s later
        assert at < 1800 + 2
        st = json.loads(sub.wait("status", status_at(at)))
        assert st["spindles"][0]["counters"]["cycles"] >= 1700
        assert sub.wait("availability") == "online"
        assert len(mqtt_events(caplog, "mqtt_connected")) == 1
        assert len(mqtt_events(caplog, "mqtt_lost")) == 1
    finally:
        sub.close()

    # the broker goes away: one more event, however many attempts paho makes
    attempts = []
    svc.mqtt.client.on_connect_fail = lambda *a: (attempts.append(1), svc.mqtt._on_fail(*a))
    brokers.stop()
    run_for(svc, clock, 60)
    wait_for(lambda: len(attempts) >= 2, 15, "two reconnection attempts")
    run_for(svc, clock, 60)
    assert len(mqtt_events(caplog, "mqtt_lost")) == 2
    assert "connection lost" in mqtt_events(caplog, "mqtt_lost")[1].fields["reason"]
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


def test_name_that_does_not_resolve(tmp_path, calibrated_model, services, caplog):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    svc, clock = services(config(tmp_path, calibrated_model, 'host = "broker.invalid"'))
    run_for(svc, clock, 120)
    assert svc.spindles["s1"].counters["cycles"] >= 110
    wait_for(lambda: mqtt_events(caplog, "mqtt_lost"), 30, "the mqtt_lost event")
    t0 = time.monotonic()
    svc.close()
    assert time.monotonic() - t0 < 5  # close waits only a moment for paho's thread


def test_username_and_password(tmp_path, calibrated_model, brokers, services, caplog, monkeypatch):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    port = brokers.start(users={"thermo": "right-pass", "reader": "reader-pass"})
    sub = Subscriber(port, ("reader", "reader-pass"))
    (tmp_path / "good").mkdir()
    pw = tmp_path / "mqtt.pass"
    pw.write_text("right-pass\n")
    good, gclock = services(
        config(
            tmp_path / "good",
            calibrated_model,
            f'host = "127.0.0.1"\nport = {port}\nusername = "thermo"\n'
            f'password_file = "{pw}"\nclient_id = "good"',
        )
    )
    try:
        wait_for(lambda: good.mqtt.connected, 10, "the connection with the right password")
        at = tick_until_published(good, gclock)
        assert json.loads(sub.wait("status", status_at(at)))["spindles"][0]["name"] == "s1"
        good.close()
        sub.wait("availability", lambda p, r: p == "offline")

        # the wrong one: refused, said once, compensation goes on
        monkeypatch.setenv("THERMOCOMP_MQTT_PASSWORD", "wrong-pass")
        (tmp_path / "bad").mkdir()
        caplog.clear()
        bad, clock = services(
            config(
                tmp_path / "bad",
                calibrated_model,
                f'host = "127.0.0.1"\nport = {port}\nusername = "thermo"\nclient_id = "bad"',
            )
        )
        run_for(bad, clock, 600)
        # paho retries after 1 s, then 2 s: three refusals at the broker
        wait_for(
            lambda: brokers.log.read_text().count("not authorised") >= 3,
            15,
            "three refused attempts",
        )
        run_for(bad, clock, 600)
        assert bad.spindles["s1"].counters["cycles"] >= 1100
        assert bad.spindles["s1"].counters["writes"] > 10
        (lost,) = mqtt_events(caplog, "mqtt_lost")
        assert "not authorized" in lost.fields["reason"].lower()
        assert not mqtt_events(caplog, "mqtt_connected") and not bad.mqtt.connected
        assert not any("wrong-pass" in r.getMessage() for r in caplog.records)
    finally:
        sub.close()


def test_an_alarm_change_is_published_at_once(tmp_path, calibrated_model, brokers, services):
    port = brokers.start()
    svc, clock = services(
        config(
            tmp_path, calibrated_model, f'host = "127.0.0.1"\nport = {port}\npublish_every_s = 600'
        )
    )
    sub = Subscriber(port)
    try:
        wait_for(lambda: svc.mqtt.connected, 10, "the service's connection")
        run_for(svc, clock, 120)
        assert svc.snapshot["spindles"][0]["alarms"] == []
        n = svc.mqtt.published
        run_for(svc, clock, 60)
        assert svc.mqtt.published == n  # no change, not due: nothing sent
        svc.reload_failed = True  # raises RELOAD_FAILED on the next cycle
        at = tick_until_published(svc, clock)
        assert at <= 181  # the next tick, not 600 s after the last publish
        st = json.loads(sub.wait("status", status_at(at)))
        assert st["spindles"][0]["alarms"] == ["RELOAD_FAILED"] and st["reload_failed"] is True
        sp = json.loads(
            sub.wait("spindle/s1", lambda p, r: "RELOAD_FAILED" in json.loads(p)["alarms"])
        )
        assert sp["alarm_bits"] == st["spindles"][0]["alarm_bits"]
    finally:
        sub.close()
