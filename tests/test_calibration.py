"""Calibration judged in free run on plant data, and the replay figures."""

from __future__ import annotations

import numpy as np
import pytest
from plantdata import plant_run

from calibration.calibrate import calibrate, free_run
from calibration.data import Run, has_cooldown, resample
from calibration.fitting import FORM_BY_NAME, fit_paper_ols
from calibration.replay import equilibrium
from compensator import CalibrationError


def rms(x):
    return float(np.sqrt(np.mean(np.asarray(x) ** 2)))


def held_out_rms(model, run: Run) -> float:
    return rms(run.elongation_um - free_run(model, run))


@pytest.fixture(scope="module")
def cal60():
    return calibrate([plant_run("calibration", 60.0, 0), plant_run("validation", 60.0, 1)],
                     spindle_id="t")


def test_chosen_model_beats_paper_form_fitted_at_60s_replayed_at_1s(cal60):
    paper = next(c for c in cal60.candidates if c.result.form.name == "paper-ols").result.model
    assert paper is not None
    heldout = [plant_run("validation", 1.0, 5), plant_run("jobshop", 1.0, 6)]
    for run in heldout:
        chosen_rms, paper_rms = held_out_rms(cal60.model, run), held_out_rms(paper, run)
        assert chosen_rms < paper_rms / 2, (run.name, chosen_rms, paper_rms)
        assert chosen_rms < 1.0
    assert cal60.model.form != "paper-ols"


def test_chosen_model_beats_paper_form_fitted_at_1s_replayed_at_60s():
    cal = calibrate([plant_run("calibration", 1.0, 2), plant_run("validation", 1.0, 3)])
    paper = next(c for c in cal.candidates if c.result.form.name == "paper-ols").result.model
    for run in (plant_run("validation", 60.0, 7), plant_run("jobshop", 60.0, 8)):
        chosen_rms = held_out_rms(cal.model, run)
        paper_rms = held_out_rms(paper, run) if paper is not None else np.inf
        assert chosen_rms < paper_rms / 2, (run.name, chosen_rms, paper_rms)


def test_report_has_every_candidate_scored_in_free_run_with_cross_validation(cal60):
    rep = cal60.report()
    assert [c["form"] for c in rep["candidates"]] == list(FORM_BY_NAME)
    assert rep["scored_by"] == "leave-one-run-out free run"
    for c in rep["candidates"]:
        if c["usable"]:
            assert c["cross_validation"]["rms_um"] > 0
    chosen = next(c for c in rep["candidates"] if c["form"] == rep["chosen"])
    best = min(c["score_rms_um"] for c in rep["candidates"] if c["score_rms_um"] is not None)
    assert chosen["score_rms_um"] <= best * 1.02 + 1e-12
    assert 0.9 < rep["reference_one_step_r2"] <= 1.0
    for r in rep["residuals"]:
        assert r["phases"]["transient"]["samples"] > 0 and r["phases"]["steady"]["samples"] > 0
    assert any(c["stderr"] for c in rep["coefficients"])


def test_paper_ols_rows_never_cross_runs():
    a, b = plant_run("calibration", 60.0, 0), plant_run("validation", 60.0, 1)
    res = fit_paper_ols([a, b], 60.0)
    both = fit_paper_ols([Run("joined", np.concatenate([a.time_s, b.time_s + 1e6]),
                              np.concatenate([a.speed_rpm, b.speed_rpm]),
                              np.concatenate([a.elongation_um, b.elongation_um]))], 60.0)
    # joining the runs adds one bogus row (last of a -> first of b) and changes the fit
    assert res.coefficients[1]["value"] != pytest.approx(both.coefficients[1]["value"], rel=1e-9)


def test_single_run_without_cooldown_warns_about_identifiability():
    run = plant_run("calibration", 60.0, 0)
    cut = run.time_s <= 180 * 60  # the staircase only
    heat_only = Run("heat-only", run.time_s[cut], run.speed_rpm[cut], run.elongation_um[cut])
    assert not has_cooldown(heat_only) and has_cooldown(run)
    cal = calibrate([heat_only])
    text = " ".join(cal.warnings)
    assert "not identifiable" in text and "one run only" in text


def test_resampling_1s_to_60s_matches_a_60s_log_of_the_same_program():
    fine, coarse = plant_run("calibration", 1.0, 0), plant_run("calibration", 60.0, 0)
    r = resample(fine, 60.0)
    np.testing.assert_array_equal(r.time_s, coarse.time_s)
    np.testing.assert_allclose(r.speed_rpm, coarse.speed_rpm)


def test_constant_speed_runs_are_refused():
    t = np.arange(100) * 60.0
    from calibration.data import run_from_log
    from compensator.io import RunLog

    log = RunLog(t, np.full(100, 6000.0), np.linspace(0, 10, 100))
    with pytest.raises(CalibrationError, match="constant speed"):
        run_from_log(log, "c")
    with pytest.raises(CalibrationError, match="krpm"):
        run_from_log(RunLog(t, np.linspace(0, 27, 100), np.linspace(0, 10, 100)), "k")
    with pytest.raises(CalibrationError, match="over 5 mm"):
        run_from_log(RunLog(t, np.linspace(0, 9000, 100), np.linspace(0, 34000, 100)), "nm")


def test_equilibrium_time_and_tevr_on_a_warm_up():
    t = np.arange(0, 6 * 3600, 10.0)
    rng = np.random.default_rng(0)
    e = 20 * (1 - np.exp(-t / 1800)) + rng.normal(0, 0.05, t.size)
    t_eq, tevr = equilibrium(t, e)
    # |dE/dt| = 20/1800*exp(-t/1800) < 0.5e-3 um/s from t = 1800*ln(22.2) = 5580 s
    assert t_eq == pytest.approx(5580, abs=400)
    # what is left of the warm-up after equilibrium (0.9 um) plus the noise band
    assert 0.85 < tevr < 1.4
    t_eq, tevr = equilibrium(t, 0.004 * t)  # still drifting at the end
    assert t_eq is None and tevr is None
