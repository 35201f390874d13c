"""Time that is not seconds is refused (or, named so in a DAQ file's column, converted) where a
log enters: the run-log reader that ``thermocomp fit`` and replay use, the calibration's own
entry (:func:`calibration.dataset.log_data`) and the wizard's import. A model whose time scale
is no spindle's is refused by ``thermocomp model check`` and the fit."""

from __future__ import annotations

import csv
import io
import json
import runpy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from plantdata import plant_run

from calibration.dataset import log_data
from calibration.session.record import ImportOptions, import_run, with_runs
from compensator.errors import CalibrationError, RunLogError
from compensator.io import read_run_log, save_model, write_run_log
from compensator.io.runlog import time_unit_refusal
from compensator.model import ThermalModel, ThermalStateCoefficients
from compensator.plausibility import time_constant_refusal
from compensator.statespace import StateSpaceModel

write_channels = runpy.run_path(
    str(Path(__file__).parent / "data" / "real-spindle" / "channels.py")
)["write_channels"]

THERMOCOMP = [sys.executable, "-m", "thermocomp"]


@pytest.fixture(scope="module")
def real_ch1(tmp_path_factory) -> Path:
    """Channel 1 of the real 40 h record: 15 s samples, time in seconds."""
    return write_channels(tmp_path_factory.mktemp("real"), ("ch1",))["ch1"]


def scaled(src: Path, dst: Path, factor: float, header: str = "time_s") -> Path:
    """``src`` with its time multiplied by ``factor`` under the column ``header``."""
    with open(src, newline="") as fh:
        rows = list(csv.reader(fh))
    with open(dst, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow([header, *rows[0][1:]])
        w.writerows([repr(float(r[0]) * factor), *r[1:]] for r in rows[1:])
    return dst


def one_line(err: BaseException) -> str:
    text = str(err)
    assert "\n" not in text, text
    return text


# -- the reader: thermocomp fit and replay ----------------------------------------------------


def test_the_real_record_in_milliseconds_is_refused_by_fit_in_one_line(real_ch1, tmp_path):
    log = scaled(real_ch1, tmp_path / "ch1_ms.csv", 1000.0)
    out = tmp_path / "model.json"
    r = subprocess.run(
        [*THERMOCOMP, "fit", str(log), "--output", str(out)], capture_output=True, text=True
    )
    assert r.returncode == 2, r.stdout + r.stderr
    err = r.stderr.strip().splitlines()
    assert len(err) == 1, r.stderr
    assert "time_s looks like milliseconds" in err[0]
    assert "15 s steps over 40 h" in err[0] and "divide it by 1000" in err[0]
    assert not out.exists()  # nothing written


def test_microseconds_are_refused_naming_the_unit(tmp_path):
    t_us = np.arange(7201) * 1e6  # 2 h at 1 s, in microseconds
    write_run_log(tmp_path / "us.csv", {"time_s": t_us, "speed_rpm": np.zeros(t_us.size)})
    with pytest.raises(RunLogError) as info:
        read_run_log(tmp_path / "us.csv")
    text = one_line(info.value)
    assert "looks like microseconds" in text and "divide it by 1e6" in text, text
    assert "1 s steps over 2 h" in text, text


def test_hours_are_refused_where_a_log_calibrates(real_ch1, tmp_path):
    # 40 h in hours spans 40 "s": a replay may be that short, a calibration may not
    log = read_run_log(scaled(real_ch1, tmp_path / "ch1_h.csv", 1 / 3600))
    with pytest.raises(CalibrationError) as info:
        log_data([log])
    text = one_line(info.value)
    assert "looks like hours" in text and "multiply it by 3600" in text, text
    assert "15 s steps over 40 h" in text, text


@pytest.mark.parametrize("column,factor", [("time_min", "60"), ("time_h", "3600")])
def test_a_run_log_column_in_minutes_or_hours_is_refused_by_name(tmp_path, column, factor):
    p = tmp_path / "log.csv"
    p.write_text(f"{column},speed_rpm\n" + "".join(f"{k},0\n" for k in range(20)))
    with pytest.raises(RunLogError) as info:
        read_run_log(p)
    text = one_line(info.value)
    assert f"column {column}: time must be in seconds" in text and f"by {factor}" in text


def test_a_simulated_log_is_accepted_in_seconds_and_refused_in_milliseconds(tmp_path):
    run = plant_run("calibration", 60.0, 0)
    cols = {"time_s": run.time_s, "speed_rpm": run.speed_rpm, "elongation_um": run.elongation_um}
    write_run_log(tmp_path / "s.csv", cols)
    data, _ = log_data([read_run_log(tmp_path / "s.csv")])
    np.testing.assert_array_equal(data[0].time_s, run.time_s)
    write_run_log(tmp_path / "ms.csv", {**cols, "time_s": run.time_s * 1000})
    with pytest.raises(RunLogError, match="looks like milliseconds"):
        read_run_log(tmp_path / "ms.csv")


def test_real_seconds_logs_are_accepted(real_ch1, tmp_path):
    """The real record at 15 s, a 1 kHz log of three minutes, a week at 10 min and a journal
    that paused for a year: seconds, read and taken for calibration as they are."""
    log = read_run_log(real_ch1)
    assert log.median_dt_s == 15.0 and log.duration_s == 143985.0
    data, _ = log_data([log])
    assert data[0].time_s[-1] == 143985.0
    for name, t in {
        "khz": np.arange(180_001) * 1e-3,
        "week": np.arange(7 * 144 + 1) * 600.0,
        "paused": np.r_[np.arange(600.0), 600.0 + 400 * 86400 + np.arange(600.0)],
    }.items():
        speed = np.where((t % 600) < 300, 3000.0, 0.0)
        elong = np.sin(np.arange(t.size) / 50.0)
        write_run_log(
            tmp_path / f"{name}.csv", {"time_s": t, "speed_rpm": speed, "elongation_um": elong}
        )
        log = read_run_log(tmp_path / f"{name}.csv")
        np.testing.assert_allclose(log.time_s, t, rtol=1e-12)
        assert time_unit_refusal(log.time_s, min_span_s=60.0) is None, name


def test_minutes_read_as_seconds_cannot_be_told_by_the_numbers():
    """The limit, stated: 40 h at 15 s in minutes is 0.25 s steps over 40 min, a plausible
    fast log; the reader takes it (the column's name, or the fit's time constants, must tell)."""
    t_min = np.arange(9600) * 15.0 / 60.0
    assert time_unit_refusal(t_min, min_span_s=60.0) is None


# -- the wizard's import ----------------------------------------------------------------------


def daq(real: Path, dst: Path, factor: float, column: str) -> Path:
    """A DAQ file from the real record: time (times ``factor``), displacement and speed."""
    with open(real, newline="") as fh:
        rows = list(csv.reader(fh))[1:]
    with open(dst, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow([column, "displacement_um", "speed_rpm"])
        w.writerows([repr(float(r[0]) * factor), r[2], r[1]] for r in rows)
    return dst


def wizard_args(workdir: Path, source: Path, column: str) -> list[str]:
    return [
        "wizard",
        "--yes",
        "--workdir",
        str(workdir),
        "--machine-id",
        "m1",
        "--model-spindle-id",
        "s1",
        "--max-rpm",
        "5000",
        "--source",
        "import",
        "--dialect",
        "fanuc",
        "--no-validation",
        "--import-time-column",
        column,
        "--import-displacement-column",
        "displacement_um",
        "--import-speed-column",
        "speed_rpm",
        "--import-calibration",
        str(source),
    ]


def test_the_wizard_refuses_a_daq_file_in_milliseconds_under_time_s(real_ch1, tmp_path):
    src = daq(real_ch1, tmp_path / "daq_ms.csv", 1000.0, "time_s")
    wd = tmp_path / "w"
    r = subprocess.run(
        [*THERMOCOMP, *wizard_args(wd, src, "time_s")], capture_output=True, text=True
    )
    assert r.returncode == 2, r.stdout + r.stderr
    err = r.stderr.strip().splitlines()
    assert len(err) == 1, r.stderr
    assert "time_s looks like milliseconds" in err[0] and "divide it by 1000" in err[0]
    assert "time_ms: the import converts it" in err[0]
    session = json.loads((wd / "m1" / "s1" / "session.json").read_text())
    assert not session["runs"]["calibration"].get("complete")  # nothing imported
    assert not (wd / "m1" / "s1" / "runs" / "calibration.csv").exists()
    assert src.stat().st_size > 0  # the user's file untouched


@pytest.mark.parametrize(
    "column,factor", [("time_ms", 1000.0), ("Time [min]", 1 / 60), ("time (h)", 1 / 3600)]
)
def test_the_wizard_converts_a_column_named_for_its_unit_and_says_so(
    real_ch1, tmp_path, column, factor
):
    from rich.console import Console

    from calibration.wizard import Wizard
    from thermocomp.cli import build_parser

    src = daq(real_ch1, tmp_path / "daq.csv", factor, column)
    args = build_parser().parse_args(wizard_args(tmp_path / "w", src, column))
    shown = io.StringIO()
    wiz = Wizard(args, console=Console(file=shown, width=200))
    wiz.step_identify()
    wiz.step_programs()
    wiz.step_acquire()
    said = shown.getvalue()
    unit = {"time_ms": "milliseconds", "Time [min]": "minutes", "time (h)": "hours"}[column]
    assert f"calibration: {column} read as {unit} (its name says so) and converted" in said, said
    info = wiz.session.run("calibration")
    assert info is not None and info.complete
    log = read_run_log(info.log)
    np.testing.assert_allclose(log.median_dt_s, 15.0, rtol=1e-9)
    np.testing.assert_allclose(log.duration_s, 143985.0, rtol=1e-9)


def test_import_run_refuses_hours_under_an_unmarked_column(real_ch1, tmp_path):
    from calibration.session.model import WizardSession

    src = daq(real_ch1, tmp_path / "daq_h.csv", 1 / 3600, "time")
    session = WizardSession(machine_id="m1", spindle_id="s1", max_rpm=5000.0, source="import")
    session = with_runs(session, ["calibration"], tmp_path)
    opts = ImportOptions("time", "displacement_um", "speed_rpm", None, 1.0, 0.0)
    with pytest.raises(CalibrationError) as info:
        import_run(session, "calibration", src, opts)
    assert "time looks like hours" in one_line(info.value)
    run = session.run("calibration")
    assert run is not None and not Path(run.log).exists()


# -- a time scale no spindle has ---------------------------------------------------------------


def state_space(taus_s: tuple[float, ...], fitted_dt_s: float = 15.0) -> StateSpaceModel:
    return StateSpaceModel(
        fitted_dt_s=fitted_dt_s,
        speed_range_rpm=(0.0, 5000.0),
        taus_s=taus_s,
        drive_um=tuple((2.0, 0.2) for _ in taus_s),
        feedthrough_um=(0.1, 0.0),
        max_measured_um=40.0,
    )


def model_check(tmp_path: Path, model) -> subprocess.CompletedProcess[str]:
    path = tmp_path / "model.json"
    save_model(path, model)
    return subprocess.run(
        [*THERMOCOMP, "model", "check", str(path)], capture_output=True, text=True
    )


def first_order(tau_s: float, fitted_dt_s: float = 15.0) -> ThermalModel:
    return ThermalModel(
        form="exp-baseline",
        fitted_dt_s=fitted_dt_s,
        speed_range_rpm=(0.0, 5000.0),
        states=(
            ThermalStateCoefficients(
                dissipation_per_s=(1 / tau_s, 0.0),
                generation_um_per_s=(0.0, 20.0 / tau_s, 0.0, 0.0),
            ),
        ),
    )


def test_model_check_refuses_a_time_constant_of_15004_minutes(tmp_path):
    r = model_check(tmp_path, first_order(15004.3 * 60))
    assert r.returncode == 2, r.stdout + r.stderr
    err = r.stderr.strip().splitlines()
    assert len(err) == 1, r.stderr
    assert "to come 63 % of the way to steady (time constants 15004.3 min)" in err[0], err[0]
    assert "over 48 h: no spindle heats that slowly" in err[0]
    # a state-space model inside its own 10-day bound, as slow: refused alike
    r = model_check(tmp_path, state_space((5 * 86400.0,)))
    assert r.returncode == 2 and "no spindle heats that slowly" in r.stderr, r.stderr


def test_model_check_refuses_a_model_fitted_at_a_sample_period_of_hours(tmp_path):
    # what 15 s in milliseconds fits: taus from 4 x 15000 s, sampled every 4.17 h
    r = model_check(tmp_path, state_space((60000.0, 180000.0), fitted_dt_s=15000.0))
    assert r.returncode == 2, r.stdout + r.stderr
    assert "fitted at a sample period of 15000 s (4.17 h)" in r.stderr
    assert r.stderr.count("\n") == 1


def test_a_spindles_time_scale_is_accepted(tmp_path):
    r = model_check(tmp_path, state_space((600.0, 1800.0, 5400.0, 16200.0)))
    assert r.returncode == 0, r.stdout + r.stderr
    # slow but a spindle's: 20 h, fitted at 10 min
    assert time_constant_refusal(state_space((72000.0,), fitted_dt_s=600.0)) is None
    assert time_constant_refusal(first_order(20 * 3600.0)) is None


def test_time_constants_under_half_a_minute_are_refused():
    fast = ThermalModel(
        fitted_dt_s=1.0,
        speed_range_rpm=(0.0, 5000.0),
        states=(
            ThermalStateCoefficients(
                dissipation_per_s=(1 / 10.0, 0.0),
                generation_um_per_s=(0.0, 0.5, 0.05, 0.0),
            ),
        ),
    )
    why = time_constant_refusal(fast)
    assert why is not None and "slowest time constant is 10 s, under 30 s" in why, why
