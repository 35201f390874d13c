"""The thermocomp command end to end, as a user runs it: real processes, real files."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import first_order

from compensator.io import load_model, read_run_log, save_model, write_run_log

REPLAY_KEYS = {
    "samples",
    "duration_s",
    "max_abs_residual_um",
    "rms_residual_um",
    "mean_abs_residual_um",
    "std_uncompensated_um",
    "std_compensated_um",
    "std_reduction_pct",
    "equilibrium_time_s",
    "tevr_um",
}


def tc(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "thermocomp", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=600,
    )


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("logs")
    for prog, seed, dt, name in (
        ("paper-calibration", 0, 60, "cal.csv"),
        ("random-validation", 1, 60, "val.csv"),
        ("job-shop-day", 2, 1, "day.csv"),
    ):
        r = tc("simulate", "--program", prog, "--seed", seed, "--dt", dt, "--output", d / name)
        assert r.returncode == 0, r.stderr
    return d


@pytest.fixture(scope="module")
def fitted(logs):
    out = logs / "model.json"
    r = tc(
        "fit",
        logs / "cal.csv",
        logs / "val.csv",
        "--output",
        out,
        "--json",
        "--plot",
        logs / "fit.png",
    )
    assert r.returncode == 0, r.stderr
    return out, json.loads(r.stdout)


def test_fit_writes_a_loadable_model_and_a_json_report(fitted, logs):
    path, rep = fitted
    model = load_model(path)
    assert model.form == rep["model_form"]
    assert model.spindle_id == "sim-motorized-27k"  # from the logs' metadata
    assert (logs / "fit.png").stat().st_size > 10000
    assert (
        rep["candidates"]
        and rep["reason"]
        and rep["chosen"] in [c["name"] for c in rep["candidates"]]
    )
    assert model.fit["cv_rms_um"] == pytest.approx(
        next(c for c in rep["candidates"] if c["name"] == rep["chosen"])["cv_rms_um"], abs=1e-3
    )


def test_fit_human_report_names_the_winner_and_the_reference(logs, tmp_path):
    r = tc("fit", logs / "cal.csv", logs / "val.csv", "--output", tmp_path / "m.json")
    assert r.returncode == 0, r.stderr
    assert "Chosen:" in r.stdout and "paper-ols" in r.stdout and "R²" in r.stdout


def test_replay_json_keys_and_outputs(fitted, logs, tmp_path):
    path, _ = fitted
    r = tc(
        "replay",
        "--model",
        path,
        logs / "day.csv",
        "--json",
        "--output",
        tmp_path / "p.csv",
        "--plot",
        tmp_path / "p.png",
    )
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert REPLAY_KEYS <= set(rep)
    assert rep["samples"] == len(read_run_log(logs / "day.csv"))
    assert rep["rms_residual_um"] < 1.0 and rep["std_reduction_pct"] > 80
    pred = read_run_log(tmp_path / "p.csv")
    np.testing.assert_allclose(pred.extras["offset_um"], -pred.extras["predicted_um"])
    np.testing.assert_allclose(
        pred.extras["residual_um"], pred.elongation_um - pred.extras["predicted_um"], atol=1e-6
    )
    assert (tmp_path / "p.png").stat().st_size > 10000


def test_replay_without_measurement_has_null_residuals_and_warns_out_of_range(fitted, tmp_path):
    path, _ = fitted
    t = np.arange(0, 7200, 1.0)
    write_run_log(
        tmp_path / "speeds.csv", {"time_s": t, "speed_rpm": np.where(t > 3600, 30000.0, 9000.0)}
    )
    r = tc("replay", "--model", path, tmp_path / "speeds.csv", "--json", "--initial-um", "2.5")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["rms_residual_um"] is None and rep["std_reduction_pct"] is None
    assert rep["initial_um"] == 2.5
    assert any("above the calibrated range" in w for w in rep["warnings"])
    assert "above the calibrated range" in r.stderr


BAD_LOGS = {
    "malformed.csv": ("time_s,speed_rpm,elongation_um\n0,0,0\n60,3000,1,7\n", ":3: malformed CSV"),
    "nan.csv": ("time_s,speed_rpm,elongation_um\n0,0,0\n60,nan,1\n", ":3: column speed_rpm"),
    "unsorted.csv": (
        "time_s,speed_rpm,elongation_um\n0,0,0\n60,10,1\n30,10,1\n",
        ":4: time does not increase",
    ),
    "short.csv": ("time_s,speed_rpm,elongation_um\n0,0,0\n60,3000,1\n", "at least 20"),
    "text.csv": (
        "time_s,speed_rpm,elongation_um\n0,0,0\n60,fast,1\n",
        ":3: column speed_rpm: 'fast'",
    ),
}


def rows(speed, elong, n=40):
    return "time_s,speed_rpm,elongation_um\n" + "".join(
        f"{60 * k},{speed(k)},{elong(k)}\n" for k in range(n)
    )


BAD_LOGS["constant.csv"] = (rows(lambda k: 6000, lambda k: k * 0.1), "constant speed")
BAD_LOGS["krpm.csv"] = (rows(lambda k: k % 27, lambda k: k * 0.1), "krpm")
BAD_LOGS["nm.csv"] = (rows(lambda k: 1000 * (k % 27), lambda k: k * 900.0), "over 5 mm")


@pytest.mark.parametrize("name", sorted(BAD_LOGS))
def test_bad_calibration_input_one_line_error_no_model_file(tmp_path, name):
    text, expected = BAD_LOGS[name]
    (tmp_path / name).write_text(text)
    out = tmp_path / "model.json"
    r = tc("fit", tmp_path / name, "--output", out)
    assert r.returncode == 2
    err = r.stderr.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    assert err.startswith("thermocomp: error: ") and expected in err and name in err
    assert list(tmp_path.iterdir()) == [tmp_path / name]  # no model, no temp file


def test_bad_model_files(tmp_path, logs):
    good = tmp_path / "good.json"
    save_model(good, first_order())
    tampered = tmp_path / "tampered.json"
    tampered.write_text(good.read_text().replace('"spindle_id": "unknown"', '"spindle_id": "x"'))
    unknown = tmp_path / "unknown.json"
    unknown.write_text(json.dumps({"format": "other/2"}))
    missing = tmp_path / "missing.json"
    for path, expected in (
        (tampered, "checksum mismatch"),
        (unknown, "unknown model format"),
        (missing, "cannot read"),
    ):
        r = tc("replay", "--model", path, logs / "cal.csv")
        assert r.returncode == 2
        assert r.stderr.count("\n") == 1 and expected in r.stderr, r.stderr


def test_unstable_model_file_is_refused(tmp_path, logs):
    import hashlib

    from compensator.io.checksum import canonical as _canonical

    data = first_order().model_dump(mode="json")
    data["states"][0]["dissipation_per_s"] = [1e-4, -1e-5]  # unstable above 10 000 rpm
    data["sha256"] = hashlib.sha256(_canonical(data).encode()).hexdigest()
    p = tmp_path / "unstable.json"
    p.write_text(json.dumps(data))
    r = tc("replay", "--model", p, logs / "cal.csv")
    assert r.returncode == 2 and "unstable at 27000 rpm" in r.stderr


def test_model_command_shows_schema_and_a_model(fitted):
    path, _ = fitted
    r = tc("model", "schema")
    assert r.returncode == 0
    schema = json.loads(r.stdout)
    assert "states" in schema["properties"]
    r = tc("model", "show", path, "--json")
    assert r.returncode == 0 and json.loads(r.stdout)["form"]


def test_examples_schema_file_is_current():
    from compensator.model import ThermalModel

    on_disk = json.loads((Path(__file__).parents[1] / "examples" / "model.schema.json").read_text())
    assert on_disk == ThermalModel.model_json_schema()


def test_demo_end_to_end_with_a_relative_output_dir(tmp_path):
    """What `make demo` runs: record over OPC UA, fit, run the service, score; exit 0 only if
    compensation reduced the RMS error."""
    # a 3-hour day (the default is 5): both halves of a shift, lunch between, six probe cycles
    r = subprocess.run(
        [sys.executable, "-m", "thermocomp", "demo", "--output-dir", "out", "--hours", "3"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=600,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    out = tmp_path / "out"
    for name in (
        "calibration_run.csv",
        "validation_run.csv",
        "model.json",
        "machine.toml",
        "demo.png",
        "virtual_cnc_history.csv",
        "machine-closed-loop.toml",
        "demo_closed_loop.png",
        "closed_loop_history.csv",
    ):
        assert (out / name).stat().st_size > 0, name
    assert list((out / "runtime" / "journal").glob("demo-*.csv"))
    assert "reduction" in r.stdout and "compensated" in r.stdout
    hist = read_run_log(out / "virtual_cnc_history.csv")
    err = hist.extras["tool_tip_error_um"]
    assert np.sqrt(np.mean(err**2)) < 0.5 * np.sqrt(np.mean(hist.elongation_um**2))
    # the closed loop: the tool setter's values reached the service, journaled, and corrected it
    assert "Closed loop" in r.stdout and "probe cycles" in r.stdout
    meas = list((out / "runtime-closed-loop" / "journal").glob("demo.measurements-*.csv"))
    assert (
        meas
        and sum(line.count(",accepted,") for p in meas for line in p.read_text().splitlines()) >= 5
    )
    closed = read_run_log(out / "closed_loop_history.csv")
    assert np.sqrt(np.mean(closed.extras["tool_tip_error_um"] ** 2)) < 0.5 * np.sqrt(
        np.mean(closed.elongation_um**2)
    )
    # issue 18: the part sees at most 2 um in every phase (steady and after speed changes) and
    # 0.6 um RMS; every sample (the tool clear of the part too) 0.6 um RMS
    cutting = hist.extras["cutting"] == 1
    assert 0.5 < cutting.mean() < 0.95
    assert np.max(np.abs(err[cutting])) <= 2.0 and np.sqrt(np.mean(err[cutting] ** 2)) <= 0.6
    assert np.sqrt(np.mean(err**2)) <= 0.6
    # the service took the CNC's cutting signal, and moved slowly while the tool cut
    for jpath in (out / "runtime" / "journal").glob("demo-*.csv"):  # a day file each (UTC)
        j = read_run_log(jpath).extras
        assert set(j["cutting_source"]) == {"controller"}
        jcut = j["cutting"] == 1
        both = jcut[1:] & jcut[:-1]
        assert (np.abs(np.diff(j["offset_um"]))[both] <= 1.0 * j["dt_s"][1:][both] + 1e-9).all()
    assert "while cutting" in r.stdout and "transient phases" in r.stdout
    # the demo fits as `thermocomp fit` does: the same logs give the same model
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "thermocomp",
            "fit",
            "out/calibration_run.csv",
            "out/validation_run.csv",
            "--model-spindle-id",
            "demo-spindle",
            "--machine-id",
            "virtual",
            "--output",
            "fit.json",
            "--json",
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    demo_model, fit_model = (
        json.loads(p.read_text()) for p in (out / "model.json", tmp_path / "fit.json")
    )
    for m in (demo_model, fit_model):
        m.pop("created_utc", None)
        m.pop("sha256", None)  # of the file's contents, created_utc included
    assert demo_model == fit_model


def test_replay_applies_the_runtimes_shaping_and_compares_the_policies(fitted, logs, tmp_path):
    """Replay always runs the runtime's shaper (default settings here); the log's cutting column
    (the simulator's) is the controller's signal. Shaping adds at most 1 um to the model's worst
    error on a 1 s job-shop log (issue 18), and the report sets the policies side by side."""
    path, _ = fitted
    out = tmp_path / "pred.csv"
    r = tc("replay", logs / "day.csv", "--model", path, "--json", "--output", out)
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["applied_max_abs_residual_um"] <= rep["max_abs_residual_um"] + 1.0
    assert rep["applied_rms_residual_um"] <= rep["rms_residual_um"] + 0.1
    assert rep["shaping"]["policy"] == "dual-slew"
    assert rep["shaping"]["cutting_source"] == "the log's cutting column"
    assert 0.5 < rep["shaping"]["cutting_fraction"] < 0.95
    log = read_run_log(out)
    cols, t = log.extras, log.time_s
    applied, _ideal, cutting = cols["applied_offset_um"], cols["offset_um"], cols["cutting"] == 1
    rate = np.abs(np.diff(applied)) / np.diff(t)
    both = cutting[1:] & cutting[:-1]
    assert rate[both].max() <= 1.0 + 1e-9  # the runtime's default slew limit while cutting
    assert rate[~both].max() > 3.0  # and the elastic step lands in the run-up, fast
    policies = {p["policy"]: p for p in rep["policies"]}
    assert set(policies) == {"slow-slew", "dual-slew", "longer-cycle", "none"}
    assert (
        policies["dual-slew"]["configured"]
        and policies["dual-slew"]["max_abs_um"] == rep["applied_max_abs_residual_um"]
    )
    assert policies["none"]["max_abs_um"] == pytest.approx(rep["max_abs_residual_um"])
    # one slow limit lags the elastic step into the cut: what issue 18 fixes
    assert (
        policies["slow-slew"]["cutting_max_abs_um"]
        > policies["dual-slew"]["cutting_max_abs_um"] + 3.0
    )
    for name in ("slow-slew", "dual-slew", "longer-cycle"):
        assert policies[name]["max_cutting_rate_um_per_s"] <= 1.0 + 1e-9, name
    text = tc("replay", logs / "day.csv", "--model", path)
    assert "Transient policies" in text.stdout and "dual slew <- configured" in text.stdout


@pytest.mark.parametrize("seed", [9])
def test_shaping_adds_at_most_1_um_on_any_1s_job_shop_log(fitted, tmp_path, seed):
    """Other days, also with the cutting state inferred from the speed (a log without the
    column), and with instant speed steps (a drive that accelerates without limit)."""
    path, _ = fitted
    day = tmp_path / "day.csv"
    for accel in ("5000", "1e9"):
        r = tc(
            "simulate",
            "--program",
            "job-shop-day",
            "--seed",
            seed,
            "--dt",
            1,
            "--accel-rpm-per-s",
            accel,
            "--output",
            day,
        )
        assert r.returncode == 0, r.stderr
        log = read_run_log(day)
        plain = tmp_path / "plain.csv"
        write_run_log(
            plain,
            {"time_s": log.time_s, "speed_rpm": log.speed_rpm, "elongation_um": log.elongation_um},
        )
        for f in (day, plain):
            rep = json.loads(tc("replay", f, "--model", path, "--json").stdout)
            assert rep["applied_max_abs_residual_um"] <= rep["max_abs_residual_um"] + 1.0, (
                accel,
                f.name,
            )
            assert (f == plain) == (rep["shaping"]["cutting_source"] == "inferred from the speed")


def test_demo_hours_out_of_range_is_one_line(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "thermocomp", "demo", "--output-dir", "out", "--hours", "0.5"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert (
        r.returncode == 2 and "--hours 0.5: from 1 to 24" in r.stderr and r.stderr.count("\n") == 1
    ), r.stderr
    assert not (tmp_path / "out").exists()
