"""``thermocomp fit`` (cycles method) and the state-space model it writes, on the real 40 h
record (tests/data/real-spindle) and on the virtual plant. Everything is scored in free run."""

from __future__ import annotations

import json
import math
import runpy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from compensator.errors import ModelError, ModelFileError
from compensator.fitrecord import FIT_SCHEMA_VERSION
from compensator.io import load_any_model, read_run_log, save_model
from compensator.io.checksum import digest
from compensator.statespace import InputChannel, StateSpaceModel

ROOT = Path(__file__).resolve().parents[1]
CHANNELS = runpy.run_path(str(ROOT / "tests/data/real-spindle/channels.py"))["write_channels"]


def tc(*args, check=False):
    return subprocess.run(
        [sys.executable, "-m", "thermocomp", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=check,
    )


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    return CHANNELS(tmp_path_factory.mktemp("real"), ("ch1", "ch3"))


@pytest.fixture(scope="module")
def ch3_fit(real, computed_once):
    def make(d: Path) -> None:
        r = tc(
            "fit",
            real["ch3"],
            "--inputs",
            "all",
            "--no-physical",
            "--model-spindle-id",
            "real-1",
            "--output",
            d / "ch3.json",
            "--json",
        )
        assert r.returncode == 0, r.stderr
        (d / "report.json").write_text(r.stdout)

    d = computed_once("ch3-fit", make)  # two minutes: once for every worker
    return d / "ch3.json", json.loads((d / "report.json").read_text())


def _cand(rep, name):
    return next(c for c in rep["candidates"] if c["name"] == name)


def test_one_long_file_is_cut_into_cycles_and_scored_by_them(ch3_fit):
    _, rep = ch3_fit
    assert rep["scored_by"] == "leave-one-cycle-out free run"
    assert len(rep["cycles"]) == 5 and len(rep["folds"]) == 5
    assert "heat-up and the cool-down" in rep["cycle_rule"]
    for c in rep["candidates"]:
        assert len(c["folds_rms_um"]) == 5 and all(math.isfinite(v) for v in c["folds_rms_um"])


def test_temperatures_win_on_ch3_and_fit_says_speed_alone_cannot(ch3_fit):
    path, rep = ch3_fit
    model = load_any_model(path)
    # the temperatures win; which structure shares their strength is the data's choice
    assert (
        rep["chosen"] in ("ridge+static", "ridge+few", "ridge+pca", "ridge+bounded", "ridge+inputs")
        and model.form == rep["chosen"]
    )
    assert model.input_names and model.spindle_id == "real-1"
    base, ridge, with_t, paper = (
        _cand(rep, n) for n in ("exp-baseline", "ridge", rep["chosen"], "paper-ols")
    )
    # every candidate carries both held-out figures, and the choice reads the worse of them
    assert rep["forward_decides"] is True  # the folds are cycles
    for c in (base, ridge, with_t):
        # origins every half cycle: the cool-down of cycle 2, then each start and cool-down
        assert len(c["forward_folds_rms_um"]) == len(rep["forward_splits"]) == 7
        assert c["decisive_rms_um"] == pytest.approx(max(c["nested_rms_um"], c["forward_rms_um"]))
    assert model.fit["forward_rms_um"] == pytest.approx(with_t["forward_rms_um"], abs=1e-3)
    # the speed-only fallback is a speed-only candidate that passed, and the reason says why
    speed = _cand(rep, model.fallback.form)
    assert speed in (base, ridge) and speed["accepted"]
    assert f"{speed['name']} stands in, speed only" in rep["reason"]
    assert "Runner-up:" in rep["reason"] and "one standard error" in rep["reason"]
    # the honest figures with temperatures beat speed alone and the paper several fold
    assert with_t["decisive_rms_um"] < speed["decisive_rms_um"] / 3
    assert with_t["nested_rms_um"] < paper["cv_rms_um"] / 5
    assert model.fit["nested_rms_um"] == pytest.approx(with_t["nested_rms_um"], abs=1e-3)
    # and the report says in one line that speed alone cannot carry ch3, with the figures
    said = [w for w in rep["warnings"] if w.startswith("speed alone cannot carry")]
    assert len(said) == 1 and f"{speed['decisive_rms_um']:.1f} um held out" in said[0]
    assert "The logged inputs carry it" in said[0]


def test_replay_of_a_suffix_settles_onto_the_full_replay(ch3_fit, real):
    """A log that starts on a warm machine starts at equilibrium: the difference to the full
    replay decays as exp(-t/tau_max), to under 6 % within 3 tau_max (the documented settling)."""
    model = load_any_model(ch3_fit[0])
    log = read_run_log(real["ch3"])
    inputs = {k: np.asarray(log.extras[k], float) for k in model.input_names}
    full = model.simulate_um(log.speed_rpm, log.time_s, inputs, None)
    settle_s = 3 * max(model.taus_s)
    for start_h in (20.1, 22.1, 24.5):  # a rest after 4 h at 3750 rpm, 2 h into it, into a run
        k = int(np.searchsorted(log.time_s, start_h * 3600))
        part = model.simulate_um(
            log.speed_rpm[k:], log.time_s[k:], {a: b[k:] for a, b in inputs.items()}, None
        )
        diff = np.abs(part - full[k:])
        since = log.time_s[k:] - log.time_s[k]
        assert diff[since < 3600].max() > 2.0  # it did start elsewhere: the check can fail
        assert diff[since >= settle_s].max() < 0.06 * diff[since < 3600].max()


def test_measured_start_goes_to_the_unexplained_part(ch3_fit, real):
    model = load_any_model(ch3_fit[0])
    log = read_run_log(real["ch3"])
    first = {k: float(log.extras[k][0]) for k in model.input_names}
    eq = model.start(None, 0.0, first)
    warm = model.start(eq.elongation_um + 7.0, 0.0, first)
    assert warm.states_um == eq.states_um  # the speed/input states stay at equilibrium
    assert warm.residual_um == pytest.approx(7.0) and warm.elongation_um == pytest.approx(
        eq.elongation_um + 7.0
    )
    later = model.step(warm, 0.0, 4 * 3600.0, first)
    assert later.residual_um == pytest.approx(7.0 * math.exp(-4 * 3600.0 / max(model.taus_s)))


def test_speed_only_fit_beats_the_papers_method_on_ch1(real, tmp_path):
    r = tc("fit", real["ch1"], "--no-physical", "--output", tmp_path / "m.json", "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    chosen = _cand(rep, rep["chosen"])
    assert (
        rep["chosen"] in ("ridge", "exp-baseline")
        and not load_any_model(tmp_path / "m.json").input_names
    )
    assert chosen["honest_rms_um"] < _cand(rep, "paper-ols")["cv_rms_um"] / 2
    assert rep["derived"] and all(d["hac_stderr"] > 0 for d in rep["derived"])
    # the closed-loop plan: an interval table by held-out cycles, its observer kept in the model
    loop = rep["closed_loop"]
    never, *rows = loop["intervals"]
    assert never["interval_s"] is None and all(r["rms_um"] < never["rms_um"] for r in rows)
    assert load_any_model(tmp_path / "m.json").fit["observer"] == loop["observer"]
    # the record the identification wrote is the typed one, in this version
    fit = load_any_model(tmp_path / "m.json").fit
    assert fit.schema_version == FIT_SCHEMA_VERSION and fit.method == rep["chosen"]
    assert fit.observer is not None and fit.observer.model_dump() == loop["observer"]
    assert fit.expected_error is not None and fit.growth_direction in (-1, 1)
    r = tc("replay", real["ch1"], "--model", tmp_path / "m.json", "--probe-every", 1800, "--json")
    rp = json.loads(r.stdout)
    assert rp["rms_residual_um"] < rp["open_loop_rms_residual_um"] / 2, rp


def test_virtual_plant_targets_at_60_s_and_at_1_s(tmp_path):
    for dt in (60, 1):
        r = tc("simulate", "--dt", dt, "--output", tmp_path / f"cal{dt}.csv")
        assert r.returncode == 0, r.stderr
    r = tc("fit", tmp_path / "cal60.csv", "--output", tmp_path / "m.json", "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["scored_by"].startswith("blocked")  # one cycle: contiguous blocks
    for dt in (60, 1):
        r = tc("replay", tmp_path / f"cal{dt}.csv", "--model", tmp_path / "m.json", "--json")
        assert r.returncode == 0, r.stderr
        rp = json.loads(r.stdout)
        assert rp["max_abs_residual_um"] <= 1.0 and rp["rms_residual_um"] <= 0.4, (dt, rp)


def test_fit_refusals_are_one_line_and_write_nothing(tmp_path, real):
    out = tmp_path / "m.json"
    r = tc("fit", real["ch1"], "--method", "forms", "--output", out, "--json")
    assert (
        r.returncode == 2 and "invalid choice: 'forms'" in r.stderr and "Traceback" not in r.stderr
    )
    r = tc("fit", real["ch1"], "--inputs", "nope_c", "--output", out, "--json")
    assert r.returncode == 2 and "no column 'nope_c'" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()


# -- the model value -------------------------------------------------------------------------------


def _speed_model(**kw):
    base = {
        "fitted_dt_s": 15.0,
        "speed_range_rpm": (0.0, 10000.0),
        "taus_s": (600.0, 5400.0),
        "drive_um": ((0.5, 0.05), (2.0, 0.2)),
        "feedthrough_um": (0.1, 0.0),
        "offset_um": 0.3,
        "max_measured_um": 40.0,
    }
    return StateSpaceModel(**{**base, **kw})


def _input_model(**kw):
    ch = InputChannel(
        name="temp1_c",
        unit="degC",
        reference=25.0,
        trained_range=(20.0, 30.0),
        valid_range=(10.0, 40.0),
    )
    base = {
        "fitted_dt_s": 15.0,
        "speed_range_rpm": (0.0, 10000.0),
        "taus_s": (600.0, 5400.0),
        "drive_um": ((0.5, 0.05, 0.2), (2.0, 0.2, 0.5)),
        "feedthrough_um": (0.1, 0.0, 0.1),
        "inputs": (ch,),
        "max_measured_um": 40.0,
        "fallback": _speed_model(),
    }
    return StateSpaceModel(**{**base, **kw})


@pytest.mark.parametrize(
    "change, why",
    [
        ({"taus_s": (5.0, 5400.0)}, "outside 15 s (the sample period)"),
        ({"taus_s": (600.0, 1e7)}, "outside 15 s"),
        ({"drive_um": ((0.5, 0.05), (2000.0, 0.2))}, "over 10 x the largest measured"),
        ({"drive_um": ((0.5, 0.05),)}, "1 drive rows for 2 time constants"),
        ({"feedthrough_um": (0.1,)}, "need 2"),
        ({"offset_um": math.inf}, "finite"),
    ],
)
def test_insane_coefficients_are_refused(change, why):
    with pytest.raises(ModelError, match=why.replace("(", r"\(").replace(")", r"\)")):
        _speed_model(**change)


def test_a_signed_but_insane_file_is_refused_at_load(tmp_path):
    path = tmp_path / "m.json"
    save_model(path, _input_model())
    assert load_any_model(path).input_names == ("temp1_c",)
    payload = json.loads(path.read_text())
    payload.pop("sha256")
    payload["taus_s"] = [600.0, 1e9]
    payload["sha256"] = digest(payload)
    path.write_text(json.dumps(payload))
    with pytest.raises(ModelFileError, match="time constant 1e\\+09 s is outside"):
        load_any_model(path)


def test_stepping_matches_the_free_run_at_irregular_dt():
    m = _input_model()
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.5, 120.0, 400))
    t[200:] += 36000.0  # a 10 h gap
    n = rng.choice([0.0, 3000.0, 8000.0], t.size)
    u = 25 + np.cumsum(rng.normal(0, 0.05, t.size))
    sim = m.simulate_um(n, t, {"temp1_c": u}, 2.0)
    s = m.start(2.0, n[0], {"temp1_c": u[0]})
    out = [s.elongation_um]
    for k in range(1, t.size):
        s = m.step(s, n[k], t[k] - t[k - 1], {"temp1_c": u[k]})
        out.append(s.elongation_um)
    assert np.abs(np.array(out) - sim).max() < 1e-9
    saved = m.state_from_dict(json.loads(json.dumps(m.state_dict(s))))
    assert saved == s


@settings(max_examples=150, deadline=None)
@given(
    speed=st.floats(-1e300, 1e300),
    dt=st.floats(0, 1e300),
    temp=st.floats(-1e300, 1e300),
    start=st.floats(-1e4, 1e4),
)
def test_no_finite_input_gives_a_non_finite_output(speed, dt, temp, start):
    m = _input_model()
    s = m.start(start, speed, {"temp1_c": temp})
    s = m.step(s, speed, dt, {"temp1_c": temp})
    assert math.isfinite(s.elongation_um)
    sim = m.simulate_um(
        np.array([0.0, speed, speed]),
        np.array([0.0, dt / 2, dt]),
        {"temp1_c": np.array([25.0, temp, temp])},
        start,
    )
    assert np.isfinite(sim).all()


def test_json_mode_never_prints_a_traceback_even_for_a_bug(real, tmp_path):
    code = (
        "import sys, calibration.identify as m\n"
        "def boom(*a, **k): raise RuntimeError('boom')\n"
        "m.identify = boom\n"
        "from thermocomp.cli import main\n"
        f"sys.exit(main(['fit', {str(real['ch1'])!r}, '--output', {str(tmp_path / 'm.json')!r}, '--json']))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr == "thermocomp: error: internal error: RuntimeError: boom\n"
    assert not (tmp_path / "m.json").exists()


def test_a_log_with_hours_missing_fits_and_says_how_the_gap_was_taken(real, tmp_path):
    lines = Path(real["ch1"]).read_text().splitlines(keepends=True)
    gappy = tmp_path / "gappy.csv"
    # 10 h of rows missing from a rest (held at speed across 10 h, the fit is refused: a
    # growth that falls with speed, which the plausibility tests cover)
    gappy.write_text("".join(lines[:1700] + lines[4100:]))
    r = tc("fit", gappy, "--no-physical", "--no-nested", "--output", tmp_path / "m.json", "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert any(
        "gap" in w and "last logged speed" in w and "10.0 h" in w for w in rep["warnings"]
    ), rep["warnings"]
    log = read_run_log(gappy)
    pred = load_any_model(tmp_path / "m.json").simulate_um(log.speed_rpm, log.time_s, None, None)
    assert np.isfinite(pred).all() and np.abs(pred).max() < 100


def test_replay_warns_when_an_input_leaves_its_trained_range(ch3_fit, real, tmp_path):
    lines = Path(real["ch3"]).read_text().splitlines(keepends=True)
    head = lines[0].rstrip("\n").split(",")
    j = head.index("temp5_c")
    row = lines[5].rstrip("\n").split(",")
    row[j] = "45.0"  # trained up to ~42 degC, valid up to ~55
    hot = tmp_path / "hot.csv"
    hot.write_text("".join(lines[:5]) + ",".join(row) + "\n" + "".join(lines[6:]))
    r = tc("replay", hot, "--model", ch3_fit[0], "--json")
    assert r.returncode == 0, r.stderr
    warnings = json.loads(r.stdout)["warnings"]
    assert any(
        w.startswith("temp5_c: 45 degC is outside the trained") and "line 6" in w for w in warnings
    ), warnings
    r = tc("replay", real["ch3"], "--model", ch3_fit[0], "--json")
    assert not any("trained" in w for w in json.loads(r.stdout)["warnings"])


def test_a_channel_the_inputs_carry_is_not_refused_for_its_speed_only_fallback(real, tmp_path):
    """ch1 on its first three cycles with the 16 temperatures: every speed-only candidate fails
    the physics check (the exponential baseline's steady growth falls as speed rises), yet a
    model with the temperatures passes. The fit keeps it, with the most conservative speed-only
    fallback (its steady growth held to rise with speed), and says so in the reason, the
    warnings and the model file; the model check passes it."""
    lines = Path(real["ch1"]).read_text().splitlines()
    log = read_run_log(real["ch1"])
    from calibration.folds import split_cycles

    stop = split_cycles(log.time_s, log.speed_rpm)[2][1]
    head = tmp_path / "ch1_three_cycles.csv"
    head.write_text("\n".join(lines[: stop + 1]) + "\n")
    out = tmp_path / "m.json"
    r = tc("fit", head, "--inputs", "all", "--no-physical", "--output", out, "--json")
    assert r.returncode == 0, r.stderr + r.stdout
    rep = json.loads(r.stdout)
    model = load_any_model(out)
    assert model.input_names and model.fallback.form == "monotone-baseline"
    assert model.fit.fallback is not None and "no speed-only candidate passed" in model.fit.fallback
    assert "no speed-only candidate passed" in rep["reason"]
    assert any("the fallback, used only when an input fails" in w for w in rep["warnings"])
    fb = next(c for c in rep["candidates"] if c["name"] == "monotone-baseline")
    assert fb["accepted"] and fb["forward_folds_rms_um"]
    assert tc("model", "check", out).returncode == 0
