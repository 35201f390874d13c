"""``thermocomp wizard --source tool-setter``: calibration with the machine's tool setter alone,
end to end against the virtual machine tool over OPC UA in lock-step. The wizard plans the probe
interval, writes programs that stop for the tool-setter cycle, records the measurements the
controller link reads (a sparse log), fits and validates on them, and writes a configuration
whose service fuses the same measurements. No eddy-current sensor anywhere."""

from __future__ import annotations

import json
import subprocess
import tomllib
from pathlib import Path

import numpy as np
import pytest
from test_wizard import RATE_S, THERMOCOMP, lockstep  # noqa: F401 - the fixture

from compensator.io import load_model, read_run_log
from machine_sim.nc import parse_nc


def setter_args(work: Path, cnc, *extra: str) -> list[str]:
    return [
        "--yes",
        "--workdir",
        str(work),
        "--machine-id",
        "vmc-7",
        "--model-spindle-id",
        "main",
        "--max-rpm",
        "27000",
        "--source",
        "tool-setter",
        "--controller",
        cnc.url + "?preset=virtual-cnc",
        "--rate-s",
        str(RATE_S),
        "--dialect",
        "sinumerik",
        "--step-min",
        "10",
        "--cooldown-min",
        "60",
        "--report-format",
        "md",
        *extra,
    ]


def said(ls) -> str:
    return " ".join("".join(ls.lines).split())


def session_of(tmp_path_factory, *extra: str, at_speed: bool = False) -> dict:
    """One tool-setter session, calibration and validation run, fitted and saved."""
    from test_wizard import LockStep

    from machine_sim.vcnc import ToolSetter, VirtualCNC, running, step

    ls = LockStep(seed=21)
    ls.vm.tool_setter = ToolSetter(at_speed=at_speed)
    work = tmp_path_factory.mktemp("setter") / "cal"
    ls.session_dir = sdir = work / "vmc-7" / "main"
    with running(VirtualCNC(ls.vm, tick_s=None)) as cnc:
        ls.cnc = cnc
        step(cnc)
        code = ls.wizard(setter_args(work, cnc, "--validation", *extra))
    session = json.loads((sdir / "session.json").read_text())
    return {"code": code, "out": said(ls), "dir": sdir, "session": session, "vm": ls.vm}


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    return session_of(tmp_path_factory)


@pytest.fixture(scope="module")
def laser(tmp_path_factory):
    return session_of(tmp_path_factory, "--probe-spindle", "keep", at_speed=True)


def test_the_tool_setter_route_records_sparse_runs_measured_at_rest(calibrated):
    c = calibrated
    assert c["code"] == 0, c["out"][-2000:]
    s = c["session"]
    # the plan: at least 3 stops per 10-min step, so every 3 min (the default time constant's
    # half is 5 min); its costs are printed
    assert s["probe_every_s"] == 180.0 and s["probe_plan"]["bound"] == "step"
    assert "tool-setter stop every 3 min" in c["out"] and "longer" in c["out"]
    assert "thermocomp probe-program --dialect sinumerik --reference" in c["out"]
    for name in ("calibration", "validation"):
        prog = parse_nc(Path(s["programs"][name]).read_text())
        log = read_run_log(s["runs"][name]["log"])
        assert log.sparse, name
        # one measurement per stop the program made, each taken with the spindle at rest
        assert int(log.measured.sum()) == len(prog.probe_at_s) == s["runs"][name]["measurements"]
        assert (log.speed_rpm[log.measured] == 0.0).all()
        assert np.nanmax(log.elongation_um) > 5.0
        assert not s["runs"][name].get("flagged"), s["runs"][name]


def test_the_tool_setter_models_held_out_error_is_small_against_the_growth(calibrated):
    c = calibrated
    out = c["out"]
    assert (
        "validation run, free run on data the fit never saw" in out
        and "tool-setter measurements" in out
    )
    rms = float(
        out.split("validation run, free run on data the fit never saw: RMS ")[1].split(" ")[0]
    )
    val = read_run_log(c["session"]["runs"]["validation"]["log"])
    peak = float(np.nanmax(np.abs(val.elongation_um)))
    assert rms < 0.2 * peak, (rms, peak)
    # the fitted model's steady growth against the plant's true thermal growth at rest after
    # each step: a standstill measurement sees the thermal part
    model = load_model(c["session"]["saved"]["model"])
    assert model.spindle_id == "main"
    assert model.steady_state_um(27000.0) > 0.5 * peak


def test_the_configuration_fuses_the_tool_setter_and_passes_run_check(calibrated):
    c = calibrated
    config = Path(c["session"]["saved"]["config"])
    cfg = tomllib.loads(config.read_text())
    sp = cfg["spindle"][0]
    assert sp["observer"]["enabled"] is True and sp["spindle_id"] == "main"
    report = Path(c["session"]["saved"]["report"]).read_text()
    assert "tool setter" in report and "ISO 230-3" in report
    # the drift test on measurements at stops: finite figures, the compensated drift smaller
    iso = [ln for ln in report.splitlines() if ln.startswith(("| calibration:", "| validation:"))]
    assert len(iso) == 4 and not any("nan" in ln.lower() for ln in iso), iso
    drift = {ln.split("|")[1].strip(): abs(float(ln.split("|")[5])) for ln in iso}
    assert drift["validation: with thermocomp"] < 0.5 * drift["validation: machine"], drift
    # run --check needs the controller: the link is gone with the fixture's CNC; the
    # configuration and model are checked offline
    r = subprocess.run(
        [*THERMOCOMP, "model", "check", c["session"]["saved"]["model"]],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stdout + r.stderr


def test_the_route_at_rest_says_what_it_cannot_see(calibrated):
    out = calibrated["out"]
    assert "the tool setter measured at rest" in out and "--probe-spindle keep" in out
    assert "the model is good" not in out


def test_a_laser_setter_at_speed_measures_the_turning_tool_and_sees_the_elastic_growth(
    laser, calibrated
):
    """--probe-spindle keep: the cycles keep the spindle turning, the measurements land on rows at
    the program's speed, and the model's steady growth at top speed takes in the growth that
    exists only while it turns (the at-rest model's misses it)."""
    c = laser
    assert c["code"] == 0, c["out"][-2000:]
    s = c["session"]
    assert s["probe_spindle"] == "keep" and "no growth decays while it measures" in c["out"]
    assert "--probe-spindle keep" in c["out"] and "the tool setter measured at rest" not in c["out"]
    # its stops average as many touches as fit, and the probe program to write says how many
    n = s["probe_plan"]["touches"]
    assert n > 1 and f"{n} touches averaged per stop" in c["out"] and f"--touches {n} " in c["out"]
    assert (
        calibrated["session"]["probe_plan"]["touches"] == 1 and "--touches" not in calibrated["out"]
    )
    # the service takes the mean's sigma for the cycle's values, and its configuration loads
    from thermocomp.runtime.config import load_config

    fused = load_config(s["saved"]["config"]).spindle[0].observer
    assert fused.enabled and fused.sigma_um == pytest.approx(0.5 / n**0.5, abs=1e-3)
    assert "sigma_um" not in Path(calibrated["session"]["saved"]["config"]).read_text()
    log = read_run_log(s["runs"]["calibration"]["log"])
    turning = log.speed_rpm[log.measured] > 1.0
    assert turning.mean() > 0.6  # the staircase turns at most stops; the cool-down ones are at rest
    top = load_model(s["saved"]["model"]).steady_state_um(27000.0)
    rest_only = load_model(calibrated["session"]["saved"]["model"]).steady_state_um(27000.0)
    elastic = c["vm"].plant.elastic_um(27000.0)
    assert top - rest_only > 0.5 * elastic, (top, rest_only, elastic)
