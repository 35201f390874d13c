"""The edge box's install: `pip install thermocomp` without extras (scripts/slim-venv.sh builds it
in .venv-slim; `make test` runs that first). It stays small, carries no calibration libraries,
compensates for real over OPC UA, serves its status, and a command that needs an extra says
which one in one line."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from machine_sim.vcnc import free_port

ROOT = Path(__file__).parents[1]
SLIM = ROOT / ".venv-slim"
LIMIT_MB = 150.0
CALIBRATION_LIBRARIES = ("scipy", "statsmodels", "pandas", "matplotlib", "rich")

if not (SLIM / "bin" / "thermocomp").exists():
    if os.environ.get("CI"):
        raise RuntimeError(
            "CI: .venv-slim is missing; `make test` builds it (scripts/slim-venv.sh)"
        )
    pytest.skip("no .venv-slim: run scripts/slim-venv.sh (make test does)", allow_module_level=True)


def slim(*args: str, timeout: float = 120.0, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(SLIM / "bin" / "thermocomp"), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        **kw,
    )


def size_mb(path: Path) -> float:
    """Disk usage, as `du` counts it (allocated blocks; hard links once)."""
    seen, total = set(), 0
    for root, _, files in os.walk(path):
        for name in files:
            st = os.lstat(os.path.join(root, name))
            if (st.st_dev, st.st_ino) not in seen:
                seen.add((st.st_dev, st.st_ino))
                total += st.st_blocks * 512
    return total / 2**20


def test_the_slim_venv_is_small_and_has_no_calibration_libraries():
    assert size_mb(SLIM) <= LIMIT_MB
    r = subprocess.run(
        [
            str(SLIM / "bin" / "python"),
            "-c",
            "import importlib.util as u, json; "
            f"print(json.dumps([m for m in {CALIBRATION_LIBRARIES!r} if u.find_spec(m)]))",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and json.loads(r.stdout) == []
    r = subprocess.run(
        [
            str(SLIM / "bin" / "python"),
            "-c",
            "import numpy, pydantic, asyncua, serial, "
            "pymodbus, prometheus_client, paho.mqtt, cryptography",
        ],
        capture_output=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize(
    "argv",
    [
        ["fit", "run.csv", "--output", "m.json"],
        ["replay", "run.csv", "--model", "m.json"],
        ["demo"],
        ["simulate", "--output", "x.csv"],
        ["cooling", "compare"],
    ],
)
def test_a_command_that_needs_the_calibration_extra_says_so_in_one_line(argv, tmp_path):
    r = slim(*argv, cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "pip install 'thermocomp[calibration]'" in r.stderr


def test_init_writes_the_shipped_examples(tmp_path):
    r = slim("init", str(tmp_path / "etc"))
    assert r.returncode == 0, r.stderr
    names = {
        p.relative_to(tmp_path / "etc").as_posix()
        for p in (tmp_path / "etc").rglob("*")
        if p.is_file()
    }
    assert {
        "machine.toml",
        "cooling.toml",
        "thermocomp.service",
        "linuxcnc/thermocomp.hal",
    } <= names
    assert (tmp_path / "etc" / "machine.toml").read_bytes() == (
        ROOT / "examples" / "machine.toml"
    ).read_bytes()
    assert (
        slim("init", str(tmp_path / "etc")).returncode == 2
    )  # nothing overwritten without --force


def wait(cond, timeout_s: float = 120.0, what: str = "") -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


def test_the_slim_install_compensates_over_opcua_and_serves_its_status(tmp_path, calibrated_model):
    """The virtual CNC (full install) on loopback; the slim install's `thermocomp run` against it."""
    port, status_port = free_port(), free_port()
    vcnc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "thermocomp",
            "virtual-cnc",
            "--port",
            str(port),
            "--time-scale",
            "60",
            "--program",
            "job-shop-day",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    cfg = tmp_path / "machine.toml"
    state = tmp_path / "state"
    cfg.write_text(
        f'state_dir = "{state}"\nwatchdog = false\ntime_scale = 60.0\n'
        f'log_file = "{tmp_path / "log.jsonl"}"\n'
        f"[status]\nport = {status_port}\n"
        f'[[spindle]]\nname = "s1"\nmodel = "{calibrated_model}"\n'
        f'adapter = {{url = "opc.tcp://127.0.0.1:{port}/thermocomp/virtual-cnc/", '
        'preset = "virtual-cnc", timeout_s = 2.0, backoff_s = 0.2}\n'
        "[spindle.shaping]\nmax_offset_um = 40.0\nmax_rate_um_per_s = 2.0\n"
    )
    service = None
    try:
        wait(lambda: _listening(port), 60, "the virtual CNC")
        service = subprocess.Popen(
            [str(SLIM / "bin" / "thermocomp"), "run", "--config", str(cfg)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        url = f"http://127.0.0.1:{status_port}/"

        def written() -> bool:
            try:
                st = json.loads(urllib.request.urlopen(url + "status", timeout=5).read())
            except OSError:
                return False
            return st["spindles"][0]["counters"]["writes"] >= 5

        wait(written, 120, "offsets written by the slim service")
        r = slim("status", "--url", url)
        assert r.returncode == 0 and "s1" in r.stdout, r.stderr
        metrics = urllib.request.urlopen(url + "metrics", timeout=5).read().decode()
        assert 'thermocomp_offset_held_micrometres{spindle="s1"}' in metrics
        assert "<canvas" in urllib.request.urlopen(url, timeout=5).read().decode()
        service.send_signal(signal.SIGTERM)
        assert service.wait(60) == 0
        rows = [
            line
            for p in (state / "journal").glob("s1-*.csv")
            for line in p.read_text().splitlines()
            if line[:1].isdigit()
        ]
        assert len(rows) >= 5 and any(line.split(",")[4] == "1" for line in rows)  # written
        out = tmp_path / "export.csv"
        r = slim("journal", "export", "--config", str(cfg), "--output", str(out))
        assert r.returncode == 0, r.stderr
        assert out.read_text().count("\n") >= len(rows)
    finally:
        for proc in (service, vcnc):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait(10)


def _listening(port: int) -> bool:
    import socket

    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0
