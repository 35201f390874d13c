"""What the wizard writes at its last step, checked with the product's own components: the
runtime configuration (``calibration.report.runtime_config``) runs as written, from anywhere,
with the product's shaping, and refuses another spindle's model; the calibration report states
each figure by what it was scored on. The session is fitted by the wizard's own step 4 on the
virtual plant (a calibration and a validation run), saved by its step 5."""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from plantdata import plant_run
from rich.console import Console

from calibration.report import calibration_report, runtime_config
from calibration.wizard import SESSION_FORMAT, Wizard, WizardSession
from compensator.errors import ConfigError
from compensator.io import load_model, save_model, write_run_log
from compensator.shaping import ShaperConfig
from compensator.speed_programs import job_shop_day
from machine_sim import SpindlePlant, preset
from thermocomp.cli import build_parser
from thermocomp.cli import main as cli_main
from thermocomp.runtime.config import load_config
from thermocomp.runtime.service import check

CONTROLLER = "sim://motorized-27k?program=job-shop-day&seed=3"  # in process: --check reads a speed
DEMO_CUTTING_MAX_UM = 2.0
"""What `make demo` holds the tool-tip error to while cutting (tests/test_cli.py, the demo test)."""
OLD_SHAPING = """
[spindle.shaping]
max_offset_um = 55
max_rate_um_per_s = 1.0
deadband_um = 0.2

[spindle.shaping.transient]
enabled = true
mode = "slow"
"""
"""What the wizard used to write for this spindle (its clamp: 1.5 x 35 um, rounded up to 5)."""


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A wizard session on the virtual plant, fitted and saved by the wizard's steps 4 and 5."""
    work = tmp_path_factory.mktemp("wizard") / "cal"
    sdir = work / "vmc-7" / "main"
    (sdir / "runs").mkdir(parents=True)
    runs = {}
    for name, run in (
        ("calibration", plant_run("calibration", 20.0, 1)),
        ("validation", plant_run("validation", 20.0, 2)),
    ):
        log = sdir / "runs" / f"{name}.csv"
        write_run_log(
            log,
            {"time_s": run.time_s, "speed_rpm": run.speed_rpm, "elongation_um": run.elongation_um},
            {"machine_id": "vmc-7", "spindle_id": "main", "run": name},
        )
        runs[name] = {"log": str(log), "complete": True, "rows": len(run.time_s)}
    args = build_parser().parse_args(
        ["wizard", "--yes", "--workdir", str(work), "--report-format", "md"]
    )
    wiz = Wizard(args, console=Console(file=io.StringIO(), width=130))
    wiz.dir = sdir
    wiz.session = WizardSession.model_validate(
        {
            "format": SESSION_FORMAT,
            "machine_id": "vmc-7",
            "spindle_id": "main",
            "max_rpm": preset("motorized-27k").max_rpm,
            "source": "import",
            "controller": CONTROLLER,
            "validation": True,
            "runs": runs,
        }
    )
    summary = wiz.step_fit()
    saved = wiz.step_save(summary)
    return {
        "dir": sdir,
        "session": wiz.session.as_dict(),
        "summary": summary,
        "model": wiz.model,
        "model_path": Path(saved["model"]),
        "report": Path(saved["report"]),
        "config": Path(saved["config"]),
    }


def moved(session, dest: Path) -> Path:
    """The session's config and models copied to ``dest`` as a whole: the config's new path."""
    for sub in ("config", "models"):
        shutil.copytree(session["dir"] / sub, dest / sub)
    return dest / "config" / session["config"].name


def test_the_written_configuration_passes_run_check_as_written_from_anywhere(session, tmp_path):
    # moved elsewhere and checked from yet another directory, by a relative path: nothing in it
    # points back at the workstation's session or depends on the current directory
    config = moved(session, tmp_path / "moved" / "main")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "thermocomp",
            "run",
            "--config",
            os.path.relpath(config, elsewhere),
            "--check",
        ],
        capture_output=True,
        text=True,
        cwd=elsewhere,
        timeout=120,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "link ok" in r.stdout and ": ok (1 spindle(s))" in r.stdout
    # the model file the copy names, found next to it
    assert f"moved/main/config/../models/{session['model_path'].name}" in r.stdout
    assert str(session["dir"]) not in r.stdout
    assert not (tmp_path / "moved" / "main" / "state").exists()  # --check writes nothing
    raw = tomllib.loads(config.read_text())
    sp = raw["spindle"][0]
    assert sp["spindle_id"] == "main" == load_model(session["model_path"]).spindle_id
    assert (
        sp["model"] == f"../models/{session['model_path'].name}" and raw["state_dir"] == "../state"
    )
    cfg = load_config(config)
    assert cfg.state_dir == config.parent / ".." / "state" and cfg.spindle[0].adapter == {
        "url": CONTROLLER
    }


def test_a_session_on_a_faster_virtual_machine_writes_its_time_scale(session, tmp_path):
    """The service must run at the clock the calibration ran at: a wizard run with --time-scale
    against the virtual machine tool writes it; a real machine's session writes none."""
    assert "time_scale" not in tomllib.loads(session["config"].read_text())
    path = tmp_path / "config" / "fast.toml"
    path.parent.mkdir()
    path.write_text(
        runtime_config(
            {**session["session"], "time_scale": 600.0},
            session["model"],
            session["model_path"],
            config_dir=path.parent,
        )
    )
    assert tomllib.loads(path.read_text())["time_scale"] == 600.0
    assert load_config(path).time_scale == 600.0


def test_the_configuration_keeps_the_products_shaping(session):
    text = session["config"].read_text()
    assert 'mode = "slow"' not in text and "transient" not in text and "deadband" not in text
    sc = load_config(session["config"]).spindle[0]
    assert sc.shaping == ShaperConfig() and sc.shaping.policy == "dual-slew"
    # the clamp is the default: 100 um is over 1.5 x the growth the model predicts at top speed
    top = session["model"].steady_state_um(session["session"]["max_rpm"])
    assert 20 < top < ShaperConfig().max_offset_um / 1.5
    # only a spindle whose predicted growth the default clamp would cut gets its own
    big = runtime_config(
        {**session["session"], "max_rpm": 1e5}, session["model"], session["model_path"]
    )
    clamp = tomllib.loads(big)["spindle"][0]["shaping"]
    assert set(clamp) == {"max_offset_um"} and clamp["max_offset_um"] > ShaperConfig().max_offset_um


def test_the_configuration_refuses_a_model_of_another_spindle(session, tmp_path, capsys):
    config = moved(session, tmp_path / "s")
    assert check(str(config)) == 0
    other = session["model"].model_copy(update={"spindle_id": "spindle-2"})
    save_model(config.parent / ".." / "models" / session["model_path"].name, other)
    with pytest.raises(
        ConfigError, match="spindle_id = 'main': the model file .* is for spindle 'spindle-2'"
    ):
        check(str(config))
    # the spindle_id line is what refuses it: without it the same model is taken
    lax = config.with_name("no-id.toml")
    lax.write_text(
        "".join(
            ln
            for ln in config.read_text().splitlines(keepends=True)
            if not ln.startswith("spindle_id")
        )
    )
    assert check(str(lax)) == 0


def replay_cutting_max(log: Path, config: Path, capsys) -> dict:
    """``thermocomp replay LOG --config CONFIG --json``, in this process."""
    capsys.readouterr()
    assert cli_main(["replay", str(log), "--config", str(config), "--json", "--no-compare"]) == 0
    return json.loads(capsys.readouterr().out)


def test_a_job_shop_day_through_the_configuration_holds_the_demos_bound(session, tmp_path, capsys):
    p = preset("motorized-27k")
    t, n = job_shop_day(p.max_rpm, seed=2, hours=4).sample(1.0)
    day = tmp_path / "day.csv"
    write_run_log(day, SpindlePlant(p, seed=2).run(t, n).columns(), {"spindle_id": "main"})
    config = moved(session, tmp_path / "s")
    new = replay_cutting_max(day, config, capsys)
    assert new["shaping"]["policy"] == "dual-slew"
    assert new["shaping"]["cutting_source"] == "the log's cutting column"
    assert new["applied_cutting_max_abs_residual_um"] <= DEMO_CUTTING_MAX_UM, new
    old = config.with_name("old-slow.toml")
    old.write_text(config.read_text() + OLD_SHAPING)
    slow = replay_cutting_max(day, old, capsys)
    assert slow["shaping"]["policy"] == "longer-cycle"
    # the longer update cycle lags the elastic step of a speed change into the cut
    assert slow["applied_cutting_max_abs_residual_um"] > 3 * DEMO_CUTTING_MAX_UM
    assert (
        slow["applied_cutting_max_abs_residual_um"] > 5 * new["applied_cutting_max_abs_residual_um"]
    )
    print(
        f"cutting max: dual slew {new['applied_cutting_max_abs_residual_um']:.2f} um, "
        f"slow {slow['applied_cutting_max_abs_residual_um']:.2f} um"
    )


def md_table(md: str, heading: str) -> list[dict[str, str]]:
    """The table under the Markdown heading that starts with ``heading``, as rows by column."""
    block = md.split("\n## " + heading, 1)[1].split("\n## ", 1)[0]
    lines = [ln for ln in block.splitlines() if ln.startswith("|") and not ln.startswith("|---")]
    cells = [[c.strip() for c in ln.strip("|").split(" | ")] for ln in lines]
    return [dict(zip(cells[0], row)) for row in cells[1:]]


def test_the_report_states_each_figure_by_what_it_was_scored_on(session):
    md = session["report"].read_text()
    summary, rep = session["summary"], session["summary"]["report"]
    chosen = next(c for c in rep["candidates"] if c["name"] == rep["chosen"])
    assert "one run only" not in md and "scores are in-sample" not in md
    rows = {r["figure"].split(":")[0]: r for r in md_table(md, "Free-run error")}
    labels = [r["figure"] for r in md_table(md, "Free-run error")]
    # every held-out figure is called held out, with the identification's and the run's own values
    held = [lb for lb in labels if "(held out)" in lb]
    assert len(held) >= 3 and not any("in sample" in lb or "in-sample" in lb for lb in held)
    ident = [
        r
        for r in md_table(md, "Free-run error")
        if r["figure"].startswith("identification (held out)")
    ]
    assert float(ident[0]["RMS [um]"]) == pytest.approx(chosen["honest_rms_um"], abs=0.006)
    assert "forward" in ident[1]["figure"]
    assert float(ident[1]["RMS [um]"]) == pytest.approx(chosen["forward_rms_um"], abs=0.006)
    assert float(ident[1]["max [um]"]) == pytest.approx(chosen["forward_max_abs_um"], abs=0.006)
    val = next(
        r
        for r in md_table(md, "Free-run error")
        if r["figure"].startswith("validation (held out): a run")
    )
    v = summary["validation"]
    assert float(val["RMS [um]"]) == pytest.approx(v["rms_um"], abs=0.006)
    assert float(val["max [um]"]) == pytest.approx(v["max_abs_um"], abs=0.006) and val[
        "samples"
    ] == str(v["samples"])
    # the one figure called in sample is the calibration run's own free run
    (insample,) = [lb for lb in labels if "in sample" in lb or "in-sample" in lb]
    cal = rows["calibration (in sample)"]
    assert insample.startswith("calibration")
    assert float(cal["RMS [um]"]) == pytest.approx(summary["calibration"]["rms_um"], abs=0.006)
    # the candidates: each column what its header says; the decisive one what the refusals cite
    table = md_table(md, "Candidates")
    assert len(table) == len(rep["candidates"])
    for row, c in zip(table, rep["candidates"]):
        assert row["candidate"].startswith(c["name"])
        assert float(row["held-out RMS [um]"]) == pytest.approx(c["honest_rms_um"], abs=0.006)
        held_max = c["nested_max_abs_um"] if c["nested_rms_um"] is not None else c["cv_max_abs_um"]
        assert float(row["held-out max [um]"]) == pytest.approx(held_max, abs=0.006)
        assert float(row["forward RMS [um]"]) == pytest.approx(c["forward_rms_um"], abs=0.006)
        assert float(row["decisive RMS [um]"]) == pytest.approx(c["decisive_rms_um"], abs=0.006)
        assert float(row["in-sample RMS [um]"]) == pytest.approx(c["in_sample_rms_um"], abs=0.006)
        for cited in re.findall(
            r"held-out RMS \(the worse of nested and forward\) ([0-9.]+) um", row["verdict"]
        ):
            assert cited == row["decisive RMS [um]"]
    # the runs: which was fitted and which held out
    use = {r["run"]: r["in this report"] for r in md_table(md, "Runs")}
    assert use == {"calibration": "fitted (in sample)", "validation": "held out: free run only"}
    # the fit's one-cycle warning is put beside the run that is the check on a second cycle
    if rep["scored_by"].startswith("blocked"):
        assert f"second cycle, which the fit never saw: free-run RMS {v['rms_um']:.2f} um" in md
    html = calibration_report(
        session["session"], summary, session["model"], session["model_path"], "html", "v1"
    )
    assert "validation (held out): a run the fit never saw" in html and "one run only" not in html


def test_the_report_without_a_validation_run_claims_none(session):
    summary = {
        k: v
        for k, v in session["summary"].items()
        if k not in ("validation", "validation_report", "closed_loop")
    }
    s = {
        **session["session"],
        "validation": False,
        "runs": {"calibration": session["session"]["runs"]["calibration"]},
    }
    md = calibration_report(s, summary, session["model"], session["model_path"], "md", "v1")
    labels = [r["figure"] for r in md_table(md, "Free-run error")]
    assert not any(lb.startswith("validation") for lb in labels) and "Closed loop" not in md
    assert "second cycle" not in md


def test_a_password_in_the_controller_link_is_never_written(session, tmp_path):
    secret = "s3cr3t-pw"
    s = {
        **session["session"],
        "controller": f"opc.tcp://operator:{secret}@127.0.0.1:4840/x?preset=virtual-cnc",
        "sensor": f"opc.tcp://operator:{secret}@127.0.0.1:4840/x?preset=virtual-cnc",
    }
    (tmp_path / "config").mkdir()
    text = runtime_config(
        s, session["model"], session["model_path"], config_dir=tmp_path / "config"
    )
    assert (
        secret not in text
        and 'url = "opc.tcp://operator@127.0.0.1:4840/x?preset=virtual-cnc"' in text
    )
    path = tmp_path / "config" / "c.toml"
    path.write_text(text)
    sc = load_config(path).spindle[0]  # the runtime takes it (it refuses a URL with a password)
    assert sc.model.resolve() == session["model_path"].resolve()
    md = calibration_report(
        s, session["summary"], session["model"], session["model_path"], "md", "v1"
    )
    assert secret not in md
    # ids of 64 characters each: the spindle's name stays within what the runtime takes
    long = {**session["session"], "machine_id": "m" * 64, "spindle_id": "s" * 64}
    path.write_text(
        runtime_config(
            long, session["model"], session["model_path"], config_dir=tmp_path / "config"
        )
    )
    sc = load_config(path).spindle[0]
    assert sc.name == "s" * 64 == sc.spindle_id


def test_the_configuration_is_valid_toml_whatever_the_link_holds(session):
    for url in (
        'sim://motorized-27k?seed=3#"\\x',
        "opc.tcp://h:4840/a\x01b\x7f",
        "opc.tcp://h:4840/é",
    ):
        raw = tomllib.loads(
            runtime_config(
                {**session["session"], "controller": url}, session["model"], session["model_path"]
            )
        )
        assert raw["spindle"][0]["adapter"]["url"] == url
