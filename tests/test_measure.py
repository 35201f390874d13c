"""`thermocomp measure` and the service's control socket: a real Unix-domain socket in the state
directory, the service ticked on a fake clock (the request is in the socket before the tick
that reads it, so nothing waits on timing)."""

from __future__ import annotations

import json
import logging
import math
import os
import socket
import stat
import threading
from pathlib import Path

import pytest
from test_closed_loop import simple_model  # noqa: F401 - the model file fixture

from compensator import ConfigError
from compensator.errors import ControlError
from thermocomp.cli import main as cli
from thermocomp.runtime import Alarm, Service
from thermocomp.runtime.control import SOCKET_NAME, send_measurement

WALL0 = 1.7e9


def write_config(
    directory: Path, model: Path, spindles=(("s1", True),), observer: str = ""
) -> Path:
    lines = [f'state_dir = "{directory / "state"}"', "watchdog = false", "journal_fsync_s = 3600.0"]
    for name, enabled in spindles:
        lines += [
            "[[spindle]]",
            f'name = "{name}"',
            f'model = "{model}"',
            "period_s = 1.0",
            'adapter = {url = "sim://?program="}',
            "[spindle.observer]",
            f"enabled = {str(enabled).lower()}",
            observer,
        ]
    directory.mkdir(parents=True, exist_ok=True)
    p = directory / "machine.toml"
    p.write_text("\n".join(lines) + "\n")
    return p


@pytest.fixture(scope="module")
def model_file(simple_model: Path) -> Path:
    return simple_model


class Rig:
    """The service on a fake clock; :meth:`ask` sends a raw request line, ticks, reads the answer."""

    def __init__(self, directory: Path, model: Path, **kw):
        self.t = 0.0
        self.config = write_config(directory, model, **kw)
        self.svc = Service(self.config, clock=lambda: self.t, wall=lambda: WALL0 + self.t)
        self.path = directory / "state" / SOCKET_NAME
        self.tick()

    def tick(self) -> None:
        self.t += 1.0
        self.svc.tick()

    def connect(self) -> socket.socket:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(30)  # a safety net only: the answer is there when tick() returns
        s.connect(str(self.path))
        return s

    def ask(self, line: bytes) -> dict:
        with self.connect() as s:
            s.sendall(line)
            self.tick()
            return json.loads(s.makefile("rb").readline())

    def serve(self, client: threading.Thread) -> None:
        """Tick until ``client`` (another thread) has its answer. Its requests must not time out
        while that thread waits for the processor: the fake clock runs as fast as we tick."""
        assert self.svc.control is not None
        self.svc.control.request_timeout_s = math.inf
        client.start()
        limit = self.t + 1e5
        while client.is_alive() and self.t < limit:
            self.tick()
        client.join()

    def close(self) -> None:
        self.svc.close()


@pytest.fixture
def rig(tmp_path, model_file):
    r = Rig(tmp_path, model_file)
    yield r
    r.close()


def test_a_measurement_is_fused_at_the_next_cycle_and_answered(rig):
    assert stat.S_IMODE(os.stat(rig.path).st_mode) == 0o600 and stat.S_ISSOCK(
        os.stat(rig.path).st_mode
    )
    answer = rig.ask(b'{"elongation_um": 2.5, "sigma_um": 0.4}\n')
    assert answer["ok"] and answer["spindle"] == "s1" and answer["outcome"] == "accepted"
    assert answer["innovation_um"] == pytest.approx(2.5) and answer["sigma_um"] == 0.4
    assert answer["elongation_um"] == pytest.approx(2.5, abs=0.05)  # the estimate moved to it
    rt = rig.svc.spindles["s1"]
    assert rt.state.bias_um == pytest.approx(2.5, abs=0.05) and rt.counters["probes_accepted"] == 1
    # an outlier: answered rejected with its innovation, and raised as an alarm
    answer = rig.ask(b'{"elongation_um": 60.0, "spindle": "s1"}\n')
    assert answer["outcome"] == "rejected" and answer["innovation_um"] > 50
    assert rt.alarms & Alarm.PROBE_REJECTED
    assert "last measurement rejected" in rig.svc.status_text()


@pytest.mark.parametrize(
    "line,match",
    [
        (b"12.5\n", "JSON object"),
        (b"not json\n", "JSON object"),
        (b'{"elongation_um": NaN}\n', "finite"),
        (b'{"elongation_um": "12"}\n', "finite"),
        (b'{"elongation_um": 1, "sigma_um": 0}\n', "sigma_um"),
        (b'{"elongation_um": 1, "um": 2}\n', "unknown key 'um'"),
        (b'{"elongation_um": 1, "spindle": "s9"}\n', "no spindle 's9'"),
        (b'{"elongation_um": 1e6}\n', "not usable"),
        (b"\xff\xfe\n", "JSON object"),
    ],
)
def test_a_bad_request_is_answered_with_one_line_and_changes_nothing(rig, line, match):
    answer = rig.ask(line)
    assert answer["ok"] is False and match in answer["error"] and "\n" not in answer["error"]
    rt = rig.svc.spindles["s1"]
    assert rt.state.bias_um == 0.0 and rt.counters["probes_accepted"] == 0
    assert rig.ask(b'{"elongation_um": 0.5}\n')["outcome"] == "accepted"  # still serving


def test_a_request_too_long_or_never_finished_is_refused(rig):
    assert "longer than" in rig.ask(b"{" + b" " * 5000 + b"}\n")["error"]
    with rig.connect() as s:
        s.sendall(b'{"elongation_um": ')  # and then nothing
        for _ in range(12):
            rig.tick()  # over 10 s of the service's clock from the tick that took it
        answer = json.loads(s.makefile("rb").readline())
    assert answer["ok"] is False and "no complete request" in answer["error"]


def test_two_spindles_need_the_name_and_one_without_an_observer_says_so(tmp_path, model_file):
    r = Rig(tmp_path, model_file, spindles=(("a", True), ("b", True), ("c", False)))
    try:
        assert "name the spindle" in r.ask(b'{"elongation_um": 1.0}\n')["error"]
        assert "no observer" in r.ask(b'{"elongation_um": 1.0, "spindle": "c"}\n')["error"]
        assert r.ask(b'{"elongation_um": 1.0, "spindle": "b"}\n')["spindle"] == "b"
    finally:
        r.close()
    assert not (tmp_path / "state" / SOCKET_NAME).exists()  # removed at stop


def test_no_socket_without_an_observer(tmp_path, model_file):
    r = Rig(tmp_path, model_file, spindles=(("s1", False),))
    assert r.svc.control is None and not r.path.exists()
    with pytest.raises(ControlError, match="no thermocomp service is running"):
        send_measurement(tmp_path / "state", 1.0, None, None, timeout_s=5)
    r.close()


def test_a_deep_state_directory_and_a_dead_instances_socket(tmp_path, model_file):
    deep = tmp_path / ("d" * 60) / ("e" * 60)  # longer than a socket address holds
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    (deep / "state").mkdir(parents=True)
    os.chdir(deep / "state")
    try:
        dead.bind(SOCKET_NAME)  # left by a killed instance: nobody listens
    finally:
        os.chdir(tmp_path)
    dead.close()
    r = Rig(deep, model_file)
    try:
        out: list = []
        r.serve(
            threading.Thread(
                target=lambda: out.append(
                    send_measurement(deep / "state", 1.5, 0.5, None, timeout_s=60)
                )
            )
        )
        assert out[0]["outcome"] == "accepted" and out[0]["measured_um"] == 1.5
    finally:
        r.close()


def test_a_file_in_the_sockets_place_is_left_alone(tmp_path, model_file, caplog):
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / SOCKET_NAME).write_text("somebody's file")
    with caplog.at_level(logging.ERROR, logger="thermocomp.runtime"):
        r = Rig(tmp_path, model_file)
    assert r.svc.control is None  # compensation runs; the channel does not
    assert any(getattr(x, "event", None) == "control_failed" for x in caplog.records)
    assert (tmp_path / "state" / SOCKET_NAME).read_text() == "somebody's file"
    r.tick()
    r.close()


def test_thermocomp_measure_end_to_end(tmp_path, model_file, capsys):
    r = Rig(tmp_path, model_file)
    try:
        codes: list[int] = []
        args = ["measure", "--um", "3.0", "--sigma-um", "0.5", "--config", str(r.config), "--json"]
        r.serve(threading.Thread(target=lambda: codes.append(cli(args))))
        assert codes == [0]
        answer = json.loads(capsys.readouterr().out)
        assert answer["outcome"] == "accepted" and answer["measured_um"] == 3.0
        rows = (tmp_path / "state" / "journal").glob("s1.measurements-*.csv")
        r.svc.spindles["s1"].measurements.flush(r.t)
        text = "".join(p.read_text() for p in rows)
        assert ",3,0.5,control,,accepted," in text
        # rejected: exit 1, and a line for people
        r.serve(
            threading.Thread(
                target=lambda: codes.append(
                    cli(["measure", "--um", "90", "--state-dir", str(tmp_path / "state")])
                )
            )
        )
        assert codes[-1] == 1 and capsys.readouterr().out.startswith(
            "s1: rejected: measured 90.000 um"
        )
    finally:
        r.close()


@pytest.mark.parametrize(
    "args,match",
    [
        (["--um", "nan"], "--um must be a finite"),
        (["--um", "1", "--sigma-um", "-1"], "--sigma-um must be"),
        (["--um", "1", "--sigma-um", "inf"], "--sigma-um must be"),
        (["--um", "1"], "no thermocomp service is running"),
    ],
)
def test_thermocomp_measure_errors_are_one_line(tmp_path, capsys, args, match):
    code = cli(["measure", *args, "--state-dir", str(tmp_path)])
    err = capsys.readouterr().err
    assert (
        code == 2 and match in err and err.count("\n") == 1 and err.startswith("thermocomp: error:")
    )


def test_thermocomp_measure_with_a_bad_config_is_one_line(tmp_path, capsys):
    (tmp_path / "bad.toml").write_text("[[spindle\n")
    assert cli(["measure", "--um", "1", "--config", str(tmp_path / "bad.toml")]) == 2
    assert "not valid TOML" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse: one of the two
        cli(["measure", "--um", "1", "--config", "a", "--state-dir", "b"])
    with pytest.raises(ConfigError):
        from thermocomp.runtime.control import parse_request

        parse_request(b'{"elongation_um": true}')
