"""``thermocomp status --config`` once the service has stopped: each spindle's saved state says
what the control was left holding, and the exit status says the service is not running.

The clean stop runs the real service in-process on a clock the test moves; the kill is a real
``kill -9`` of ``thermocomp run`` on the virtual machine tool.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from compensator.io import load_state, save_state
from thermocomp.cli import main as cli
from thermocomp.runtime import Service
from thermocomp.runtime.lock import StateDirLock
from thermocomp.status_codes import EXIT_STOPPED, EXIT_UNREACHABLE

WALL0 = 1_700_000_000.0


def config(directory: Path, model: Path, extra: str = "") -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    p = directory / "machine.toml"
    p.write_text(
        f'state_dir = "{directory / "state"}"\nwatchdog = false\n{extra}\n'
        "[status]\nport = 0\n"
        f'[[spindle]]\nname = "s1"\nmodel = "{model}"\nstate_save_every_s = 1.0\n'
        'adapter = {url = "sim://motorized-27k?program=job-shop-day&seed=4"}\n'
        "[spindle.shaping]\nmax_offset_um = 40.0\nmax_rate_um_per_s = 2.0\n"
    )
    return p


def status(cfg: Path, capsys: pytest.CaptureFixture[str], *more: str) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = cli(["status", "--config", str(cfg), *more])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_a_clean_stop_leaves_what_the_control_holds_in_status(
    tmp_path: Path, calibrated_model: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    t = [0.0]
    cfg = config(tmp_path, calibrated_model)
    svc = Service(cfg, clock=lambda: t[0], wall=lambda: WALL0 + t[0])
    svc.start_status()
    while t[0] < 300.0:  # warm: 22 um held after 5 min at the job shop's speeds
        t[0] += max(svc.tick(), 0.25)
    # running, its endpoint gone: the service holds the state directory, nothing is claimed
    assert svc.status_server is not None
    svc.status_server.close()
    rc, out, err = status(cfg, capsys)
    assert rc == EXIT_UNREACHABLE and "could not reach the service" in err and not out
    svc.status_server = None
    svc.close()
    saved = load_state(tmp_path / "state" / "s1.state.json")
    assert saved is not None and saved["clean_stop"] is True
    assert abs(saved["offset_um"]) > 1.0  # a warm spindle: a number that can be told apart
    rc, out, err = status(cfg, capsys)
    assert rc == EXIT_STOPPED, err
    lines = out.splitlines()
    assert lines[0].startswith("thermocomp is not running")
    at = time.strftime("%Y-%m-%d %H:%M:%SZ", time.gmtime(saved["saved_real_wall_s"]))
    assert lines[1].startswith(
        f"s1: stopped: the control holds {saved['offset_um']:.2f} µm (state saved at {at}, "
    )
    assert lines[1].endswith("; a clean stop)")
    rc, out, _ = status(cfg, capsys, "--json", "--exit-code")
    assert rc == EXIT_STOPPED
    (s1,) = json.loads(out)["spindles"]
    assert s1["state"] == "stopped" and s1["clean_stop"] is True
    assert s1["offset_held_um"] == saved["offset_um"]


def test_after_kill_9_status_reads_the_saved_state_on_the_real_clock(
    tmp_path: Path, calibrated_model: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The real service on a simulated clock 60 times real time, killed: the saved state is read,
    dated on the real clock (the simulated one runs ahead), and no clean stop is claimed."""
    cfg = config(tmp_path, calibrated_model, "time_scale = 60.0")
    state = tmp_path / "state" / "s1.state.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "thermocomp", "run", "--config", str(cfg)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        end = time.monotonic() + 120
        while time.monotonic() < end and not (state.exists() and proc.poll() is None):
            time.sleep(0.05)
        saved = load_state(state)
        assert saved is not None, proc.stderr.read().decode() if proc.stderr else ""
        rc, out, _ = status(cfg, capsys)  # running: never claimed stopped
        assert rc != EXIT_STOPPED and "not running" not in out, out
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
        if proc.stderr:
            proc.stderr.close()
    saved = load_state(state)
    assert saved is not None and saved["clean_stop"] is False
    assert saved["saved_wall_s"] > saved["saved_real_wall_s"]  # the simulated clock ran ahead
    rc, out, _ = status(cfg, capsys, "--json")
    assert rc == EXIT_STOPPED
    (s1,) = json.loads(out)["spindles"]
    assert s1["saved_wall_s"] == saved["saved_real_wall_s"] and s1["age_s"] >= 0.0
    assert s1["offset_held_um"] == saved["offset_um"]
    rc, out, _ = status(cfg, capsys)
    assert rc == EXIT_STOPPED
    assert out.splitlines()[1].endswith(
        "ago; not by a clean stop: killed, crashed, powered off, or its last save failed)"
    )


def test_never_ran_a_planted_link_and_an_older_state(
    tmp_path: Path, calibrated_model: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = config(tmp_path, calibrated_model)
    rc, out, _ = status(cfg, capsys)  # no state directory yet
    assert rc == EXIT_STOPPED and out.splitlines()[1] == "s1: never ran (no saved state)"
    # a link planted as the state file, to a state that reads well: never followed
    (tmp_path / "state").mkdir()
    elsewhere = tmp_path / "elsewhere.json"
    save_state(elsewhere, {"saved_wall_s": WALL0, "offset_um": 12.34})
    (tmp_path / "state" / "s1.state.json").symlink_to(elsewhere)
    rc, out, _ = status(cfg, capsys)
    assert rc == EXIT_STOPPED
    assert "s1: unknown:" in out and "not followed" in out and "12.34" not in out
    # an older version's state (no real time, no stop mark): its time, and no claim either way
    (tmp_path / "state" / "s1.state.json").unlink()
    save_state(tmp_path / "state" / "s1.state.json", {"saved_wall_s": WALL0, "offset_um": -3.5})
    rc, out, _ = status(cfg, capsys)
    assert rc == EXIT_STOPPED
    line = out.splitlines()[1]
    assert line.startswith("s1: stopped: the control holds -3.50 µm (state saved at 2023-11-14 ")
    assert line.endswith(" ago)")
    # a service holding the state directory (its endpoint not listening): not claimed stopped
    with StateDirLock(tmp_path / "state"):
        rc, out, err = status(cfg, capsys)
    assert rc == EXIT_UNREACHABLE and not out and "could not reach" in err
