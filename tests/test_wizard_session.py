"""Wizard sessions that behave: ``--new`` keeps the earlier session aside (its run log is not
resumed into), answers are kept as soon as they are given, a failed connection test asks again,
a resumed session says what it holds, and durations show in wall time too when the virtual
machine tool runs faster."""

from __future__ import annotations

import json
import socket

import numpy as np
import pytest
from test_wizard import RATE_S, at_a_terminal, in_thread, lockstep, unattended_args  # noqa: F401 - the fixture

from compensator.io import write_run_log


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def said(ls) -> str:
    """What the wizard printed, as one line: the console wraps long paths where it likes."""
    return " ".join("".join(ls.lines).split())


def fake_partial_log(sdir, rows: int = 25) -> None:
    """What an interrupted recording leaves: a run log cut short, the session pointing at it."""
    log = sdir / "runs" / "calibration.csv"
    t = np.arange(rows) * float(RATE_S)
    write_run_log(log, {"time_s": t, "speed_rpm": np.full(rows, 3000.0), "elongation_um": 0.01 * t})
    session = json.loads((sdir / "session.json").read_text())
    session["runs"] = {"calibration": {"log": str(log), "complete": False}}
    (sdir / "session.json").write_text(json.dumps(session))


def test_new_keeps_the_earlier_session_aside_and_starts_a_fresh_log(lockstep, tmp_path):
    ls = lockstep
    work = tmp_path / "cal"
    ls.session_dir = sdir = work / "vmc-7" / "main"
    assert ls.wizard(unattended_args(work, ls.cnc, "--programs-only", "--no-validation")) == 0
    fake_partial_log(sdir)
    # resuming says what the session holds, rows of an unfinished run included
    assert ls.wizard(unattended_args(work, ls.cnc, "--programs-only", "--no-validation")) == 0
    assert "calibration 25 rows, not complete" in said(ls)
    ls.lines.clear()
    assert (
        ls.wizard(unattended_args(work, ls.cnc, "--new", "--programs-only", "--no-validation")) == 0
    )
    out = said(ls)
    assert "a new session" in out and "resuming" not in out
    aside = list((sdir / "earlier").iterdir())
    assert len(aside) == 1 and (aside[0] / "runs" / "calibration.csv").is_file()
    # named so that it opens from where the wizard ran (here, absolute: tmp_path is elsewhere)
    assert f"kept in {aside[0].resolve()}" in out
    assert (aside[0] / "session.json").is_file() and (aside[0] / "calibration.ngc").is_file()
    assert not (sdir / "runs" / "calibration.csv").exists()  # nothing left to append to
    assert "runs" not in json.loads((sdir / "session.json").read_text())


def test_durations_show_wall_time_when_the_machine_runs_faster(lockstep, tmp_path):
    ls = lockstep
    work = tmp_path / "cal"
    ls.session_dir = work / "vmc-7" / "main"
    assert (
        ls.wizard(
            unattended_args(
                work, ls.cnc, "--programs-only", "--no-validation", "--time-scale", "600"
            )
        )
        == 0
    )
    assert "wall at 600x" in said(ls)


def test_a_failed_connection_test_asks_again_and_keeps_every_answer(
    lockstep, tmp_path, monkeypatch
):
    """At a real terminal: a controller link that does not answer returns to its question; the
    answers given before it are already in the session file; the right link then passes."""
    pytest.importorskip("pexpect")
    ls = lockstep
    work = tmp_path / "cal"
    ls.session_dir = sdir = work / "vmc-9" / "sp1"
    dead = f"opc.tcp://127.0.0.1:{free_port()}?preset=virtual-cnc"
    with at_a_terminal(monkeypatch) as (child, tty_out):
        th, result = in_thread(
            lambda: ls.wizard(
                ["--workdir", str(work), "--programs-only", "--no-validation"],
                stdin_tty=True,
                out=tty_out,
            )
        )
        for prompt, answer in [
            ("Machine id", "vmc-9"),
            ("Spindle id", "sp1"),
            ("Maximum spindle speed", "27000"),
            ("Displacement from", "sensor"),
            ("Controller link", dead),
            ("Sensor", ls.cnc.url + "?preset=virtual-cnc&range_um=-250,250"),
            ("Sample period", str(RATE_S)),
            ("Test the connections now", "y"),
        ]:
            child.expect(prompt)
            child.sendline(answer)
        child.expect("connection test failed")
        child.expect("Controller link")
        kept = json.loads((sdir / "session.json").read_text())
        assert kept["max_rpm"] == 27000 and kept["source"] == "sensor" and "controller" not in kept
        child.sendline(ls.cnc.url + "?preset=virtual-cnc")
        child.expect("Test the connections now")
        child.sendline("y")
        child.expect("controller: .*ok")
        child.expect("NC dialect")
        child.sendline("fanuc")
        th.join(60)
    assert result == [0], result
    assert json.loads((sdir / "session.json").read_text())["controller"].startswith(ls.cnc.url)


def test_unattended_wizard_on_a_machine_not_running_the_program_saves_nothing(lockstep, tmp_path):
    """Pointed at a machine working a job-shop day instead of the calibration program, the
    unattended wizard stops with the reason and a non-zero exit, and writes no model and no
    runtime configuration."""
    from compensator.errors import CalibrationError
    from compensator.speed_programs import job_shop_day

    ls = lockstep
    work = tmp_path / "cal"
    ls.session_dir = sdir = work / "vmc-7" / "main"
    ls.vm.load_program(job_shop_day(27000.0, seed=3))  # already at work: nothing to load
    ls.pending = False
    ls.on_line = lambda line: ls.lines.append(line)  # the operator does not load the program
    with pytest.raises(CalibrationError, match="did not follow the program"):
        ls.wizard(unattended_args(work, ls.cnc, "--no-validation"))
    assert not (sdir / "models").exists() and not (sdir / "config").exists()
    assert "refused" in said(ls)
