"""A model physics forbids is refused: by every fit (``calibration.fit``) and by ``thermocomp model
check``. The steady growth must rise with speed in the direction the calibration measured, and a
calibration whose rows mostly did not follow its program does not calibrate
(``compensator.plausibility``)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from plantdata import identify_runs, plant_run

from calibration.acquire import Problem
from calibration.fit import PROBLEM_FLAGS, fit_data, growth_direction_of, not_following_rows
from calibration.identify import LogData
from calibration.runs import Run
from compensator.errors import CalibrationError
from compensator.io import RunLog, save_model, write_run_log
from compensator.model import ThermalModel
from compensator.plausibility import (
    NOT_FOLLOWING_LIMIT,
    NOT_FOLLOWING_RULE,
    RULE,
    not_following_refusal,
    steady_growth_refusal,
    steady_growth_um,
)
from compensator.statespace import InputChannel, StateSpaceModel
from thermocomp.cli import main

ROOT = Path(__file__).resolve().parents[1]
FIT = {"nested": False, "physical": False, "probe_target_um": None, "spindle_id": "t"}


def speed_only(
    n_um: float,
    n2_um: float,
    *,
    top_rpm: float = 10000.0,
    measured_um: float = 40.0,
    fit: dict | None = None,
) -> StateSpaceModel:
    """A one-state model whose steady growth is g(n) = n_um * n + n2_um * n**2 (n in krpm)."""
    return StateSpaceModel(
        fitted_dt_s=15,
        speed_range_rpm=(0, top_rpm),
        taus_s=(600.0,),
        drive_um=((n_um, n2_um),),
        feedthrough_um=(0.0, 0.0),
        offset_um=1.5,
        max_measured_um=measured_um,
        spindle_id="sp-A",
        fit=fit or {},
    )


def with_inputs(fallback: StateSpaceModel, fit: dict | None = None) -> StateSpaceModel:
    """A model with one temperature, its speed part growing with speed, over ``fallback``."""
    temp = InputChannel(
        name="temp1_c",
        unit="degC",
        reference=25.0,
        trained_range=(20.0, 30.0),
        valid_range=(10.0, 40.0),
    )
    return StateSpaceModel(
        fitted_dt_s=15,
        speed_range_rpm=(0, 10000),
        taus_s=(600.0,),
        drive_um=((2.0, 0.1, 1.0),),
        feedthrough_um=(0.0, 0.0, 0.0),
        max_measured_um=40.0,
        inputs=(temp,),
        fallback=fallback,
        spindle_id="sp-A",
        fit=fit or {},
    )


GROWING = (2.6, 0.25)  # 0 .. 51 um over 0 .. 10 krpm
BELOW_ZERO = (-3.0, 0.5)  # -4.5 um at 3 krpm, +20 um at the top
NOT_MONOTONIC = (6.0, -0.45)  # +20 um at 6.7 krpm, +15 um at the top: never below zero
FLAT = (0.02, 0.0)  # 0.2 um at the top


# -- the rule on models built directly ---------------------------------------------------------


def test_a_model_growing_with_speed_passes_either_way_it_is_asked():
    m = speed_only(*GROWING)
    assert steady_growth_refusal(m) is None
    assert steady_growth_refusal(m, 1) is None
    g = steady_growth_um(m, np.array([0.0, 5000.0, 10000.0]))
    assert g == pytest.approx([0.0, 19.25, 51.0])  # relative to rest: the offset drops out


@pytest.mark.parametrize(
    "gains, words",
    [
        (
            BELOW_ZERO,
            [
                "-4.50 um at 3000 rpm",
                "runs against the measured growth direction +1",
                "tolerance 2.00 um",
            ],
        ),
        (
            NOT_MONOTONIC,
            [
                "falls 5.00 um as speed rises",
                "+20.00 um at 6700 rpm",
                "+15.00 um at 10000 rpm",
                "tolerance 2.00 um",
            ],
        ),
        (
            FLAT,
            [
                "only +0.20 um at the top speed 10000 rpm",
                "tolerance 0.50 um",
                "measured up to 40.00 um",
            ],
        ),
    ],
)
def test_growth_below_zero_not_monotonic_or_flat_is_refused_in_one_line_with_its_numbers(
    gains, words
):
    why = steady_growth_refusal(speed_only(*gains), 1)
    assert why is not None and "\n" not in why and len(why) < 250  # one line the CLI prints whole
    for w in words:
        assert w in why


def test_a_flat_model_passes_when_the_calibration_measured_no_more():
    # nothing grew in calibration either: a well-cooled spindle is no physics violation
    assert steady_growth_refusal(speed_only(*FLAT, measured_um=2.0), 1) is None
    assert steady_growth_refusal(speed_only(*FLAT), 1, measured_um=2.0) is None
    # a speed-only ThermalModel has no measured figure of its own: the fit hands it in
    flat = ThermalModel.from_discrete(
        0.99, (0.0, 0.0001, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 10000.0)
    )
    assert steady_growth_refusal(flat, 1) is None
    assert "does not grow with speed" in steady_growth_refusal(flat, 1, measured_um=30.0)


def test_a_log_measuring_growth_negative_passes_with_its_direction_and_is_refused_against_it():
    ch3_like = speed_only(-2.6, -0.25)  # 0 .. -51 um: the sensor measures the other way
    assert steady_growth_refusal(ch3_like, -1) is None
    assert steady_growth_refusal(ch3_like) is None  # its own direction
    why = steady_growth_refusal(ch3_like, 1)
    assert why is not None and "-51.00 um at 10000 rpm" in why and "direction +1" in why
    thermal = ThermalModel.from_discrete(
        0.99, (0.0, -0.02, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 27000.0)
    )
    assert (
        steady_growth_refusal(thermal, -1) is None and steady_growth_refusal(thermal, 1) is not None
    )


def test_below_the_top_speed_the_shape_is_judged_within_the_models_held_out_error():
    # ch3's speed-only model: +11 um at 1350 rpm, -67.7 um at 5000 rpm, held out to 14.4 um RMS
    gains = (16.20788733, -5.95077055)
    bare = speed_only(*gains, top_rpm=5000.0, measured_um=71.0)
    why = steady_growth_refusal(bare, -1)
    assert why is not None and "+11.04 um at 1350 rpm" in why and "tolerance 6.77 um" in why
    known = speed_only(*gains, top_rpm=5000.0, measured_um=71.0, fit={"cv_rms_um": 14.4466})
    assert steady_growth_refusal(known, -1) is None
    # the top speed itself is held to the plain tolerance, whatever the held-out error
    assert "at 5000 rpm" in steady_growth_refusal(known, 1)


def test_a_model_with_inputs_is_judged_by_its_speed_only_fallback():
    good = with_inputs(speed_only(*GROWING))
    assert steady_growth_refusal(good, 1) is None
    bad = with_inputs(speed_only(*NOT_MONOTONIC))  # its own speed part grows
    assert "falls 5.00 um" in steady_growth_refusal(bad, 1)


def test_not_following_more_than_half_the_rows_is_refused():
    assert NOT_FOLLOWING_LIMIT == 0.5 and "50%" in NOT_FOLLOWING_RULE and "held-out RMS" in RULE
    why = not_following_refusal(0.9)
    assert why is not None and why.startswith("90.0% of the calibration rows") and "50%" in why
    assert not_following_refusal(0.5) is None and not_following_refusal(0.1) is None
    assert not_following_refusal(None) is None


# -- every fit -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def plant_cal() -> Run:
    return plant_run("calibration", 60.0, 0)


@pytest.fixture(scope="module")
def plant_fit(plant_cal):
    return identify_runs([plant_cal], **FIT)


def test_a_model_fitted_on_the_plant_grows_with_speed_and_keeps_the_direction(plant_fit):
    m = plant_fit.model
    assert m.fit["growth_direction"] == 1 and "not_following_share" not in m.fit
    assert steady_growth_refusal(m, 1) is None
    g = steady_growth_um(m, np.linspace(0, m.speed_range_rpm[1], 11))
    assert g[-1] > 10 and np.all(np.diff(g) >= 0)


def test_fit_refuses_a_direction_the_model_runs_against_and_takes_the_datas_own(plant_cal):
    with pytest.raises(CalibrationError) as err:
        identify_runs([plant_cal], growth_direction=-1, **FIT)
    msg = str(err.value)
    # every speed-only candidate is refused for it, so none is left to choose
    assert msg.startswith("no speed-only candidate passed the checks: ")
    assert (
        "exp-baseline: physics: " in msg and "runs against the measured growth direction -1" in msg
    )
    assert "\n" not in msg
    # the same run measured the other way (a sensor facing the spindle): fits, direction -1
    flipped = Run("flipped", plant_cal.time_s, plant_cal.speed_rpm, -plant_cal.elongation_um)
    fit = identify_runs([flipped], **FIT)
    assert fit.model.fit["growth_direction"] == -1
    assert steady_growth_refusal(fit.model, -1) is None
    with pytest.raises(CalibrationError, match="growth_direction must be"):
        identify_runs([plant_cal], growth_direction=2, **FIT)


def test_the_growth_direction_the_data_shows_is_from_the_cold_start(plant_cal):
    d = LogData("cal", plant_cal.time_s, plant_cal.speed_rpm, plant_cal.elongation_um)
    assert growth_direction_of([d]) == 1
    assert growth_direction_of([LogData("neg", d.time_s, d.speed_rpm, -d.elongation_um)]) == -1
    # warm at rest (a long cool-down) but at its top speed above the cold start: positive
    t = np.arange(0.0, 100.0)
    speed = np.r_[np.zeros(10), np.full(20, 6000.0), np.zeros(70)]
    y = np.r_[np.zeros(10), np.full(20, 10.0), np.full(70, 30.0)]
    assert growth_direction_of([LogData("warm-rest", t, speed, y)]) == 1
    assert growth_direction_of([LogData("flat", t, speed, np.zeros(100))]) is None


def test_fit_refuses_a_run_that_mostly_did_not_follow_the_program(plant_cal):
    d = LogData("cal", plant_cal.time_s, plant_cal.speed_rpm, plant_cal.elongation_um)
    with pytest.raises(CalibrationError) as err:
        fit_data([d], not_following=(90, 100), **FIT)
    assert str(err.value).startswith("calibration refused: 90.0% of the calibration rows")
    assert "(90 of 100 rows)" in str(err.value)
    fit = fit_data([d], not_following=(10, 100), **FIT)
    assert fit.model.fit["not_following_share"] == 0.1


def test_only_the_recorders_flags_are_counted():
    t = np.arange(10.0)
    flags = np.array([16, 17, 16, 0, 48, 0, 0, 0, 0, 0], dtype=float)
    rec = RunLog(t, t, t, {"flags": flags}, {"columns": f"flags: {PROBLEM_FLAGS}"})
    assert not_following_rows([rec]) == (4, 10)
    undeclared = RunLog(t, t, t, {"flags": flags})
    assert not_following_rows([undeclared, rec]) == (8, 20)
    # a journal export: its flags are the runtime's shaping flags, 16 there is another thing
    journal = RunLog(t, t, t, {"predicted_um": t, "offset_um": -t, "flags": flags})
    assert not_following_rows([journal]) is None
    assert not_following_rows([RunLog(t, t, t)]) is None
    assert int(Problem.NOT_FOLLOWING) == 16


def job_shop_log(path: Path, share: float) -> Path:
    """A job-shop day recorded where the calibration program was expected, ``share`` of its rows
    flagged NOT_FOLLOWING by the recorder."""
    run = plant_run("jobshop", 60.0, 3)
    flags = np.zeros(run.time_s.size, dtype=int)
    flags[: int(round(share * flags.size))] = int(Problem.NOT_FOLLOWING)
    write_run_log(
        path,
        {
            "time_s": run.time_s,
            "speed_rpm": run.speed_rpm,
            "elongation_um": run.elongation_um,
            "flags": flags,
        },
        {"run": "calibration", "columns": f"flags: {PROBLEM_FLAGS}"},
    )
    return path


def test_the_fit_command_refuses_it_in_one_line_and_writes_no_model(tmp_path):
    log = job_shop_log(tmp_path / "calibration.csv", 0.9)
    out = tmp_path / "model.json"
    r = subprocess.run(
        [sys.executable, "-m", "thermocomp", "fit", str(log), "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert r.returncode != 0 and r.stdout == ""
    assert r.stderr.count("\n") == 1
    rows = plant_run("jobshop", 60.0, 3).time_s.size
    flagged = int(round(0.9 * rows))
    assert r.stderr.startswith(
        f"thermocomp: error: calibration refused: {flagged / rows:.1%} of the "
        "calibration rows did not follow the program's speed (NOT_FOLLOWING)"
    )
    assert r.stderr.endswith(f"({flagged} of {rows} rows)\n") and len(r.stderr) < 300
    assert not out.exists()


# -- thermocomp model check ----------------------------------------------------------------------


def check(capsys, path) -> tuple[int, str, str]:
    code = main(["model", "check", str(path)])
    out, err = capsys.readouterr()
    return code, out, err


def test_model_check_says_ok_for_a_good_model(capsys, tmp_path, plant_fit):
    p = tmp_path / "good.json"
    save_model(p, plant_fit.model)
    code, out, err = check(capsys, p)
    assert code == 0 and err == "" and out.startswith(f"{p}: ok: ")


def test_model_check_refuses_a_calibration_that_did_not_follow_its_program(capsys, tmp_path):
    p = tmp_path / "jobshop.json"
    save_model(p, speed_only(*GROWING, fit={"not_following_share": 0.9, "growth_direction": 1}))
    code, out, err = check(capsys, p)
    assert code == 2 and out == "" and err.count("\n") == 1
    assert err.startswith(f"thermocomp: error: {p}: 90.0% of the calibration rows did not follow")


def test_model_check_refuses_a_steady_growth_physics_forbids(capsys, tmp_path):
    p = tmp_path / "bump.json"
    save_model(p, speed_only(*NOT_MONOTONIC))
    code, out, err = check(capsys, p)
    assert code == 2 and out == "" and err.count("\n") == 1
    assert f"{p}: steady growth falls 5.00 um as speed rises" in err
    # the direction its fit record states is the one it is held to
    q = tmp_path / "against.json"
    save_model(q, speed_only(*GROWING, fit={"growth_direction": -1}))
    code, _, err = check(capsys, q)
    assert code == 2 and "runs against the measured growth direction -1" in err
    code, out, _ = check(capsys, save_and(tmp_path / "own.json", speed_only(-2.6, -0.25)))
    assert code == 0 and ": ok: " in out  # negative and monotonic: a log measuring it the other way
    assert main(["model", "check", "--json", str(p)]) == 2
    body = json.loads(capsys.readouterr().out)
    assert body["ok"] is False and body["reason"].startswith("steady growth falls 5.00 um")


def save_and(path: Path, model) -> Path:
    save_model(path, model)
    return path
