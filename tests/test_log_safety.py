"""Issue 16, numerical safety: a bad log is refused in one line naming its line, a gap is
integrated at the last logged speed (cooling when it begins at rest), and no NaN reaches a replay's output."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration.replay import replay
from calibration.runs import MIN_GAP_S, bridge_gaps, gap_threshold_s, run_from_log
from compensator.errors import CalibrationError, RunLogError, ThermocompError
from compensator.io import RunLog, read_run_log, save_model, write_run_log
from compensator.io.runlog import MAX_ABS_TIME_S, MAX_SPEED_RPM
from compensator.model import ThermalModel

H = 3600.0
THERMOCOMP = Path(sys.executable).parent / "thermocomp"  # .venv/bin/thermocomp


def model() -> ThermalModel:
    # tau = 60 s / -ln(0.99) ~ 100 min; heats ~ 0.0100 um/krpm + 0.001 um/krpm^2 per step
    return ThermalModel.from_discrete(
        0.99, (0.0, 0.01, 0.001, 0.0), 60.0, speed_range_rpm=(0.0, 12000.0)
    )


@pytest.fixture()
def model_file(tmp_path):
    p = tmp_path / "model.json"
    save_model(p, model())
    return p


def write(tmp_path, text, name="log.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def cli_replay(log, model_path):
    return subprocess.run(
        [str(THERMOCOMP), "replay", str(log), "--model", str(model_path), "--json"],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def rows(times, speeds):
    return "".join(f"{float(t)!r},{float(n)!r}\n" for t, n in zip(times, speeds))


HEADER = "# spindle_id: sp1\ntime_s,speed_rpm\n"  # data row k is on line k + 3


# -- refused, in one line naming the line ---------------------------------------------------

EPOCH_MS = 1_700_000_000_000.0  # 2023-11-14 in milliseconds

BAD = {
    "epoch_ms": (
        HEADER + rows(EPOCH_MS + 60_000 * np.arange(5), [0, 100, 100, 100, 0]),
        3,
        r"time_s looks like milliseconds \(.*\); divide by 1000",
    ),
    "epoch_us": (
        HEADER + rows(EPOCH_MS * 1e3 + 6e7 * np.arange(5), [0] * 5),
        3,
        r"time_s looks like microseconds .*divide by 1e6",
    ),
    "absurd_time": (
        HEADER + "0,0\n60,0\n1e21,0\n1e22,0\n",
        5,
        r"time_s 1e\+21 s is beyond 1e\+11 s",
    ),
    "speed_1e12": (
        HEADER + "0,0\n60,3000\n120,1e12\n180,3000\n",
        5,
        r"column speed_rpm: 1e\+12 rpm is beyond 1e\+06 rpm",
    ),
    "negative_speed_1e12": (HEADER + "0,0\n60,-1e12\n", 4, r"speed_rpm: -1e\+12 rpm is beyond"),
    "elongation_in_pm": (
        "time_s,speed_rpm,elongation_um\n0,0,0\n60,100,2e9\n",
        3,
        r"column elongation_um: 2e\+09 um is beyond 1e\+06 um",
    ),
    "nan_cell": (HEADER + "0,0\n60,3000\n120,nan\n", 5, r"column speed_rpm: 'nan' is not a finite"),
    "time_steps_back": (
        HEADER + "0,0\n60,3000\n120,3000\n90,3000\n",
        6,
        r"time does not increase \(90 s after 120 s\)",
    ),
    "time_ms_column": (
        "time_ms,speed_rpm\n0,0\n1000,100\n",
        1,
        r"column time_ms: time must be in seconds.*divide by 1000",
    ),
}


@pytest.mark.parametrize("name", sorted(BAD))
def test_bad_log_is_refused_in_one_line_naming_the_line(tmp_path, name):
    text, line, match = BAD[name]
    p = write(tmp_path, text)
    with pytest.raises(RunLogError, match=match) as err:
        read_run_log(p)
    assert err.value.line == line
    assert err.value.path == str(p)
    assert str(err.value).startswith(f"{p}:{line}: ")
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("name", ["epoch_ms", "speed_1e12", "nan_cell", "time_steps_back"])
def test_cli_refuses_bad_log_with_one_line_and_exit_2(tmp_path, model_file, name):
    text, line, match = BAD[name]
    p = write(tmp_path, text)
    r = cli_replay(p, model_file)
    assert r.returncode == 2
    assert r.stdout == ""  # no half report
    err = r.stderr.strip().splitlines()
    assert len(err) == 1, r.stderr
    assert err[0].startswith(f"thermocomp: error: {p}:{line}: ")
    assert re.search(match, err[0])


def test_seconds_are_not_mistaken_for_milliseconds(tmp_path):
    # epoch seconds with milliseconds, and a legitimate step of 1000 s (the false positive to avoid)
    t_epoch = 1_700_000_000.123 + np.arange(5) * 1.0
    log = read_run_log(write(tmp_path, HEADER + rows(t_epoch, [0, 1, 2, 3, 4]), "epoch.csv"))
    np.testing.assert_array_equal(log.time_s, t_epoch)
    t_slow = np.arange(5) * 1000.0
    log = read_run_log(write(tmp_path, HEADER + rows(t_slow, [0, 1, 2, 3, 4]), "slow.csv"))
    np.testing.assert_array_equal(log.time_s, t_slow)
    # the bound itself is seconds; just above it is not
    read_run_log(write(tmp_path, HEADER + rows([0.0, MAX_ABS_TIME_S], [0, 0]), "edge.csv"))
    with pytest.raises(RunLogError, match="milliseconds"):
        over = HEADER + rows([0.0, 1.01 * MAX_ABS_TIME_S], [0, 0])
        read_run_log(write(tmp_path, over, "over.csv"))


def test_fast_but_possible_speed_is_read(tmp_path):
    log = read_run_log(write(tmp_path, HEADER + rows([0, 60], [0, MAX_SPEED_RPM])))
    assert log.speed_rpm[-1] == MAX_SPEED_RPM


def test_run_from_log_names_the_line_of_an_implausible_elongation(tmp_path):
    t = np.arange(30) * 60.0
    n = np.where(np.arange(30) > 2, 6000.0, 0.0)
    e = np.linspace(0, 20, 30)
    e[17] = 8000.0  # 8 mm: nm taken for um
    write_run_log(tmp_path / "cal.csv", {"time_s": t, "speed_rpm": n, "elongation_um": e})
    with pytest.raises(
        CalibrationError, match=r"cal\.csv:19: elongation 8000 um is over 5 mm"
    ) as err:
        run_from_log(read_run_log(tmp_path / "cal.csv"))
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    "col,value,match",
    [
        ("speed_rpm", math.nan, r"row 7\): column speed_rpm: nan is not a finite"),
        ("speed_rpm", 1e12, r"row 7\): column speed_rpm: 1e\+12 is beyond"),
        ("time_s", 1.0, r"row 7\): time does not increase"),
    ],
)
def test_run_from_log_checks_a_log_built_in_memory(col, value, match):
    cols = {
        "time_s": np.arange(30) * 60.0,
        "speed_rpm": np.linspace(0, 6000, 30),
        "elongation_um": np.linspace(0, 20, 30),
    }
    cols[col][7] = value
    log = RunLog(cols["time_s"], cols["speed_rpm"], cols["elongation_um"])
    with pytest.raises(CalibrationError, match=match):
        run_from_log(log, "mem")


# -- gaps: integrated at the last logged speed ----------------------------------------------


def test_bridge_gaps_holds_the_last_logged_speed_over_each_gap():
    t = np.array([0, 60, 120, 180, 180 + 10 * H, 180 + 10 * H + 60, 180 + 10 * H + 120])
    n = np.array([6000.0, 6000, 6000, 0, 9000, 6000, 6000])  # at rest when the rows stop
    assert gap_threshold_s(t) == MIN_GAP_S  # 10 x 60 s is no more than 600 s
    speed, gaps = bridge_gaps(t, n)
    assert gaps == [(4, 10 * H)]
    np.testing.assert_array_equal(speed, [6000, 6000, 6000, 0, 0, 6000, 6000])
    assert n[4] == 9000  # the caller's array is untouched
    running = np.full(t.size, 6000.0)  # a recording that stalls while the spindle runs
    assert (bridge_gaps(t, running)[0] == 6000).all()
    # an explicit threshold, and one above the gap
    assert bridge_gaps(t, n, gap_s=59.0)[1] == [(k, float(t[k] - t[k - 1])) for k in range(1, 7)]
    assert bridge_gaps(t, n, gap_s=11 * H)[1] == []


def test_gap_threshold_scales_with_a_coarse_log():
    t = np.arange(20) * 120.0
    assert gap_threshold_s(t) == 1200.0  # 10 x median step beats 600 s
    t2 = np.concatenate([t, [t[-1] + 1100.0]])  # 1100 s: late, but not a gap at a 2-min step
    assert bridge_gaps(t2, np.ones(t2.size))[1] == []
    with pytest.raises(CalibrationError, match="not a positive number"):
        bridge_gaps(t, np.ones(t.size), gap_s=math.nan)


def gap_log(tmp_path) -> Path:
    """2 h at 9000 rpm every 10 s, stopped, 10 h of missing rows, 1 h more at 9000 rpm."""
    before = np.arange(0, 2 * H + 1, 10.0)
    after = before[-1] + 10 * H + np.arange(0, H + 1, 10.0)
    t = np.concatenate([before, after])
    n = np.full(t.size, 9000.0)
    n[before.size - 1] = 0.0  # the last row before the gap: at rest
    p = tmp_path / "gap.csv"
    write_run_log(p, {"time_s": t, "speed_rpm": n})
    return p


def test_a_ten_hour_gap_cools_gives_finite_predictions_and_a_warning(tmp_path):
    log = read_run_log(gap_log(tmp_path))
    k = int(np.flatnonzero(np.diff(log.time_s) > H)[0]) + 1  # first row after the gap
    rep = replay(model(), log, initial_um=0.0)
    assert np.isfinite(rep.predicted_um).all()
    assert rep.report["gaps"] == 1
    gap_warnings = [w for w in rep.report["warnings"] if "gap" in w]
    assert gap_warnings == [
        (
            f"1 gap(s) of up to 10.0 h in the log (first ending at line {k + 2}): "
            "integrated at the last logged speed (a gap that begins at rest cools)"
        )
    ]
    np.testing.assert_array_equal(rep.speed_rpm, log.speed_rpm)  # the plot shows what was logged
    hot = rep.predicted_um[k - 2]
    assert hot > 1.0
    # 10 h is ~6 time constants at rest: almost all the heat is gone (held speed would keep it)
    assert rep.predicted_um[k] < 0.01 * hot
    held = model().simulate_um(log.speed_rpm, log.time_s, None, 0.0)
    assert held[k] > 0.9 * hot


def test_cli_replays_a_ten_hour_gap_with_a_warning(tmp_path, model_file):
    r = cli_replay(gap_log(tmp_path), model_file)
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["gaps"] == 1
    assert "last logged speed" in r.stderr
    assert all(math.isfinite(rep[k]) for k in ("max_predicted_um", "min_predicted_um"))


# -- replay output is finite ----------------------------------------------------------------


def _numbers(obj):
    if isinstance(obj, dict):
        for v in obj.values():
            yield from _numbers(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            yield from _numbers(v)
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield float(obj)


@pytest.mark.parametrize("seed", range(25))
def test_replay_output_is_finite_or_refused(tmp_path, seed):
    """Seeded random logs at the edges the reader accepts: irregular steps, gaps of hours to
    years, speeds up to the limit, epoch-second offsets. Replay either refuses in one line or
    every number it returns is finite."""
    rng = np.random.default_rng(seed)
    size = int(rng.integers(2, 400))
    dt = rng.choice(
        [1e-3, 1.0, 60.0, 10 * H, 60 * 24 * H, 3e9],
        size=size - 1,
        p=[0.2, 0.4, 0.3, 0.06, 0.03, 0.01],
    )
    steps_s = dt * rng.uniform(0.5, 1.5, size - 1)
    t = rng.choice([0.0, 1.7e9]) + np.concatenate([[0.0], np.cumsum(steps_s)])
    top = rng.choice([12000.0, 3e5, MAX_SPEED_RPM])
    speed = rng.uniform(-top, top, size) * (rng.random(size) < 0.8)
    elong = rng.normal(0, 50, size)
    p = tmp_path / "random.csv"
    write_run_log(p, {"time_s": t, "speed_rpm": speed, "elongation_um": elong})
    log = read_run_log(p)
    try:
        rep = replay(model(), log)
    except ThermocompError as err:
        assert "\n" not in str(err)
        return
    for name, col in rep.columns().items():
        assert np.isfinite(col).all(), name
    assert all(math.isfinite(x) for x in _numbers(rep.report))
    json.dumps(rep.report, allow_nan=False)  # what the CLI prints
    assert rep.report["gaps"] == len(bridge_gaps(log.time_s, log.speed_rpm)[1])


def month_gap_log(tmp_path) -> Path:
    t = np.array([0.0, 60.0, 120.0, 120.0 + 60 * 24 * H, 180.0 + 60 * 24 * H])
    p = tmp_path / "months.csv"
    write_run_log(p, {"time_s": t, "speed_rpm": np.array([0.0, 6000.0, 0.0, 6000.0, 6000.0])})
    return p


def test_a_log_spanning_a_century_replays_quickly_without_equilibrium(tmp_path):
    t = np.concatenate([np.arange(100) * 60.0, 3e9 + np.arange(100) * 60.0])
    log = RunLog(t, np.full(t.size, 5000.0), np.zeros(t.size))
    rep = replay(model(), log)  # the 1-min bins of the equilibrium figures would need gigabytes
    assert rep.report["equilibrium_time_s"] is None and rep.report["tevr_um"] is None
    assert any("no equilibrium time or TEVR" in w for w in rep.report["warnings"])
    assert np.isfinite(rep.predicted_um).all() and rep.report["gaps"] == 1


def test_a_gap_of_months_cools_completely(tmp_path):
    # one step of 60 days at rest: the exponent of the free run spans far beyond exp()'s range
    rep = replay(model(), read_run_log(month_gap_log(tmp_path)), initial_um=0.0)
    assert np.isfinite(rep.predicted_um).all()
    assert rep.predicted_um[1] > 0.05 and abs(rep.predicted_um[3]) < 1e-9  # heated, then cooled
