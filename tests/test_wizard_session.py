"""Wizard sessions that behave: ``--new`` keeps the earlier session aside (its run log is not
resumed into), answers are kept as soon as they are given, a failed connection test asks again,
a resumed session says what it holds, and durations show in wall time too when the virtual
machine tool runs faster."""

from __future__ import annotations

import json
import socket
from pathlib import Path

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


# -- the typed session and its steps -----------------------------------------------------------

SESSIONS = Path(__file__).parent / "data" / "wizard-sessions"
"""Session files as the wizard wrote them before its session was typed: a live sensor route, the
tool-setter route and an import, each recorded (or imported), fitted and saved."""


@pytest.mark.parametrize("name", ["sensor", "tool-setter", "import"])
def test_a_session_file_written_before_the_typed_session_loads_and_writes_back_the_same(
    name, tmp_path
):
    from calibration.session.model import SCHEMA_VERSION, load_session, write_session

    raw = json.loads((SESSIONS / f"{name}.json").read_text())
    s = load_session(SESSIONS / f"{name}.json")
    assert s.schema_version == SCHEMA_VERSION == 1 and s.source == name
    assert s.machine_id == raw["machine_id"] and s.max_rpm == raw["max_rpm"]
    assert set(s.runs) == {"calibration", "validation"} and all(r.complete for r in s.runs.values())
    assert s.saved is not None and s.saved.model == raw["saved"]["model"]
    # written back: every value it held, the same; the version added; a null answer left out
    path = tmp_path / "session.json"
    stamped = write_session(path, s, "2030-01-01T00:00:00+00:00")
    back = json.loads(path.read_text())
    assert back.pop("schema_version") == 1
    assert back.pop("updated_utc") == "2030-01-01T00:00:00+00:00"
    assert back == {k: v for k, v in raw.items() if k != "updated_utc" and v is not None}, (
        "the session file changed"
    )
    assert load_session(path) == stamped and path.stat().st_mode & 0o777 == 0o600


def test_the_tool_setter_sessions_plan_and_an_import_sessions_runs_are_typed():
    from calibration.session.model import load_session

    setter = load_session(SESSIONS / "tool-setter.json")
    assert setter.probe_plan is not None and setter.probe_plan.touches == 1
    assert setter.probe_dwell_s == 21.0 and setter.probe_every_s == setter.probe_plan.interval_s
    assert setter.run("calibration").measurements > 0 and setter.sensor is None
    imported = load_session(SESSIONS / "import.json")
    assert imported.controller is None and imported.run("validation").imported_from.endswith(
        "val-daq.csv"
    )


@pytest.mark.parametrize(
    "edit, said",
    [
        ("{not json", "not a wizard session: "),
        ('{"format": "thermocomp.wizard/9"}', "not a wizard session ('thermocomp.wizard/9')"),
        ("[1, 2]", "not a wizard session ('list')"),
        ('{"format": "thermocomp.wizard/1", "max_rpm": 5}', "max_rpm"),
        ('{"format": "thermocomp.wizard/1", "machine_id": "../up"}', "machine_id"),
        ('{"format": "thermocomp.wizard/1", "dialect": "cobol"}', "dialect"),
        ('{"format": "thermocomp.wizard/1", "rate_s": "NaN"}', "rate_s"),
        ('{"format": "thermocomp.wizard/1", "runs": {"calibration": {}}}', "runs.calibration.log"),
        ('{"format": "thermocomp.wizard/1", "sensr": "typo"}', "sensr"),
    ],
)
def test_a_session_file_that_is_not_one_is_refused_in_one_line(tmp_path, edit, said):
    from calibration.session.model import load_session
    from compensator.errors import ConfigError

    path = tmp_path / "session.json"
    path.write_text(edit)
    with pytest.raises(ConfigError) as info:
        load_session(path)
    msg = str(info.value)
    assert msg.startswith(str(path)) and said in msg and "\n" not in msg, msg


def test_a_session_is_a_value_each_change_is_checked_and_makes_a_new_one():
    from pydantic import ValidationError

    from calibration.session.model import load_session
    from compensator.errors import ConfigError

    s = load_session(SESSIONS / "sensor.json")
    with pytest.raises(ValidationError):
        s.max_rpm = 1.0
    t = s.updated(max_rpm=12000.0)
    assert t.max_rpm == 12000.0 and s.max_rpm == 27000.0
    with pytest.raises(ConfigError, match="^--max-rpm inf: "):
        s.updated(max_rpm=float("inf"))
    u = s.with_run("calibration", complete=False, rows=0)
    assert not u.run("calibration").complete and s.run("calibration").complete
    assert u.run("validation") == s.run("validation")


def test_the_plan_step_returns_the_planned_session_and_asks_nothing(tmp_path):
    """The probe plan and the programs as values: the same session in, a new one out, the files
    written where asked; a stop sparser than the plan is said, not prompted."""
    from calibration.nc_programs import to_nc  # noqa: F401 - the program writer the step uses
    from calibration.session.model import WizardSession
    from calibration.session.plan import plan_probes, programs, write_programs

    s = WizardSession(
        machine_id="m1",
        spindle_id="s1",
        max_rpm=12000.0,
        source="tool-setter",
        dialect="fanuc",
        step_min=10.0,
        cooldown_min=60.0,
        validation=True,
        validation_seed=1,
    )
    planned = plan_probes(
        s, probe_spindle=None, touches=None, dwell_s=None, every_min=None, former_taus=None
    )
    p = planned.session
    assert s.probe_plan is None and p.probe_plan is not None and not planned.sparser_than_planned
    assert p.probe_spindle == "stop" and p.probe_every_s == planned.plan.interval_s == 180.0
    sparse = plan_probes(
        s, probe_spindle="keep", touches=None, dwell_s=30.0, every_min=20.0, former_taus=None
    )
    assert sparse.sparser_than_planned and sparse.session.probe_every_s == 1200.0
    assert sparse.session.probe_dwell_s == 30.0 and sparse.session.probe_touch_s == 0.0
    from compensator.errors import ConfigError

    with pytest.raises(ConfigError, match="--probe-every-min 0.5: 1 to 240 minutes"):
        plan_probes(
            s, probe_spindle=None, touches=None, dwell_s=None, every_min=0.5, former_taus=None
        )
    written = write_programs(p, tmp_path, None)
    assert set(written.session.programs) == {"calibration", "validation"} == set(programs(p))
    assert written.session.rest_h == 8.0 and p.programs is None
    for f in written.files:
        prog = programs(p)[f.run]
        assert f.path.is_file() and f.path.suffix == ".nc"
        assert f.top_rpm == max(sp for _, sp in prog.segments) <= 12000.0
        # the program waits at each stop for the cycle: its length counts the stops
        assert f.duration_s == pytest.approx(
            prog.duration_s + len(prog.probe_at_s) * p.probe_plan.dwell_s
        )


def test_the_fit_step_is_the_identification_thermocomp_fit_runs_and_the_steps_save_it(tmp_path):
    """fit, validate, report and save on a session of two plant runs, with no terminal: the fit
    step's model is ``calibration.fit.fit_logs``'s for the same log, the save step writes it."""
    from plantdata import plant_run

    from calibration.fit import fit_logs
    from calibration.session.fit import fit, read_runs, report, validate
    from calibration.session.model import WizardSession
    from calibration.session.save import save
    from compensator.io import load_model, read_run_log

    work = tmp_path / "w"
    sdir = work / "m1" / "s1"
    (sdir / "runs").mkdir(parents=True)
    runs = {}
    for name, seed in (("calibration", 1), ("validation", 2)):
        run = plant_run(name, 20.0, seed)
        log = sdir / "runs" / f"{name}.csv"
        write_run_log(
            log,
            {"time_s": run.time_s, "speed_rpm": run.speed_rpm, "elongation_um": run.elongation_um},
        )
        runs[name] = {"log": str(log), "complete": True, "rows": len(run.time_s)}
    s = WizardSession(
        machine_id="m1", spindle_id="s1", max_rpm=27000.0, source="sensor", validation=True
    ).updated(runs=runs)
    data = read_runs(s, work.resolve())
    fitted = fit(s, data, "2030-01-01T00:00:00+00:00")
    direct = fit_logs(
        [read_run_log(sdir / "runs" / "calibration.csv")],
        labels=["calibration"],
        spindle_id="s1",
        machine_id="m1",
        created_utc="2030-01-01T00:00:00+00:00",
        growth_direction=1,
    )
    assert fitted.model.model_dump() == direct.model.model_dump()
    checked = validate(fitted)
    assert checked.stats["samples"] == len(plant_run("validation", 20.0, 2).time_s)
    assert checked.closed_loop is not None and "observer" in checked.model.fit
    summary = report(s, fitted, checked, sdir / "fit.png")
    assert (sdir / "fit.png").is_file() and summary["validation"] == checked.stats
    rows = {r[0] for r in summary["iso230_3"]}
    assert {"calibration: machine", "validation: with thermocomp"} <= rows, rows
    done = save(s, sdir, summary, checked.model, report_format="md", date="2030-01-01", now_utc="x")
    assert done.session.saved == done.saved and s.saved is None
    assert load_model(done.saved.model).fit["observer"] == checked.model.fit["observer"]
    assert done.saved.version == "v1" and Path(done.saved.report).read_text().startswith("#")


@pytest.mark.parametrize(
    "flag, value, said",
    [
        ("--step-min", "0", "--step-min 0.0: Input should be greater than 0"),
        ("--cooldown-min", "-5", "--cooldown-min -5.0: Input should be greater than or equal"),
        ("--step-min", "nan", "--step-min nan"),
    ],
)
def test_a_flag_the_session_cannot_hold_is_refused_in_one_line_naming_it(
    tmp_path, flag, value, said
):
    """A value the screen passes on unchecked is checked where it enters the session."""
    import io

    from rich.console import Console

    from calibration.wizard import Wizard
    from compensator.errors import ConfigError
    from thermocomp.cli import build_parser

    argv = "wizard --yes --machine-id m1 --model-spindle-id s1 --max-rpm 9000 --source import"
    argv += " --dialect fanuc --no-validation"
    args = build_parser().parse_args([*argv.split(), "--workdir", str(tmp_path), flag, value])
    wiz = Wizard(args, console=Console(file=io.StringIO()))
    wiz.step_identify()
    with pytest.raises(ConfigError) as info:
        wiz.step_programs()
    assert str(info.value).startswith(said) and "\n" not in str(info.value), str(info.value)
    assert not list((tmp_path / "m1" / "s1").glob("calibration.*"))  # no program written
