"""The ridge filter banks and their folds: cycles, the exact filter bank,
free-run prediction that does not depend on where a log starts, the state-space forms, the
paper's OLS for the comparison, and finite output for any finite input."""

from __future__ import annotations

import itertools
import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.estimators.baseline import BASELINE_TAUS_S
from calibration.estimators.paper_ols import fit_paper_ols, paper_ols_cv
from calibration.estimators.ridge_bank import (
    DEFAULT_ALPHAS,
    TauGrid,
    auto_grid,
    fit_ridge_cv,
    hac_stderr,
)
from calibration.folds import CYCLE_RULE, describe_cycles, split_cycles
from compensator.errors import CalibrationError, NonFiniteInputError
from compensator.filters import filter_bank

H = 3600.0


def profile(segments: list[tuple[float, float]], dt_s: float = 60.0, t0: float = 0.0):
    """(time_s, speed_rpm) of held speeds: ``segments`` of (duration_s, rpm)."""
    t, n, now = [t0], [0.0], t0
    for dur, rpm in segments:
        k = round(dur / dt_s)
        t += [now + dt_s * (i + 1) for i in range(k)]
        n += [rpm] * k
        now += dt_s * k
    return np.array(t), np.array(n)


# -- cycles ---------------------------------------------------------------------------------


def test_split_cycles_synthetic_profile():
    t, n = profile(
        [
            (1800, 0),  # leading rest: joins the first cycle
            (3600, 6000),
            (300, 0),
            (3600, 9000),  # a 5 min pause inside a heat-up: bridged
            (3 * H, 0),
            (2 * H, 12000),
            (H, 0),
            (300, 3000),
            (2 * H, 0),  # a 5 min blip during the cool-down: ignored
            (2 * H, 8000),  # the log ends running: a cycle without cool-down
        ]
    )
    cycles = split_cycles(t, n)
    starts = [a for a, _ in cycles]
    # the second and third cycles start at the first sample of their heat-ups
    assert len(cycles) == 3
    assert starts[0] == 0 and cycles[-1][1] == t.size
    assert all(a[1] == b[0] for a, b in itertools.pairwise(cycles))
    assert n[starts[1]] == 12000 and n[starts[1] - 1] == 0
    assert n[starts[2]] == 8000 and n[starts[2] - 1] == 0
    assert t[starts[1]] == pytest.approx(1800 + 3600 + 300 + 3600 + 3 * H + 60)
    lines = describe_cycles(t, n, cycles)
    assert len(lines) == 3 and "up to 9000 rpm" in lines[0]
    assert "heat-up and the cool-down" in CYCLE_RULE


def test_split_cycles_edge_cases():
    t, n = profile([(4 * H, 0)])
    assert split_cycles(t, n) == [(0, t.size)]  # never runs: one cycle
    assert split_cycles([], []) == []
    t, n = profile([(H, 5000), (H, 0), (H, -5000), (H, 0)])  # reverse rotation runs too
    assert len(split_cycles(t, n)) == 2
    # a longer pause is a rest when the threshold says so
    t, n = profile([(H, 5000), (900, 0), (H, 5000), (H, 0)])
    assert len(split_cycles(t, n)) == 1
    assert len(split_cycles(t, n, min_rest_s=600)) == 2
    with pytest.raises(NonFiniteInputError):
        split_cycles([0, 1, 2], [0, math.nan, 0])
    with pytest.raises(CalibrationError):
        split_cycles([0, 2, 1], [0, 1, 0])


# -- the filter bank -----------------------------------------------------------------------------


def reference_filter(t: np.ndarray, u: np.ndarray, tau: float) -> np.ndarray:
    """The zero-order-hold recursion, one step at a time."""
    y = np.empty_like(u)
    y[0] = u[0]
    for k in range(1, u.size):
        a = math.exp(-(t[k] - t[k - 1]) / tau)
        y[k] = a * y[k - 1] + (1 - a) * u[k]
    return y


def test_filter_bank_exact_at_mixed_dt():
    rng = np.random.default_rng(1)
    dt = rng.choice([0.1, 1.0, 15.0, 60.0, 600.0], size=3000)
    t = np.concatenate([[100.0], 100.0 + np.cumsum(dt)])
    # a step: u0 up to and including sample ks, u1 held over every later interval
    ks = 1200
    u = np.where(np.arange(t.size) <= ks, 2.0, 7.0)
    taus = (0.0, 30.0, 900.0, 4 * H, 30 * 86400.0)
    y = filter_bank(t, u, taus)
    elapsed = np.clip(t - t[ks], 0, None)
    for j, tau in enumerate(taus):
        exact = (
            u.copy()
            if tau == 0
            else np.where(np.arange(t.size) <= ks, 2.0, 7.0 + (2.0 - 7.0) * np.exp(-elapsed / tau))
        )
        np.testing.assert_allclose(y[:, j], exact, rtol=0, atol=1e-11)
    # an arbitrary input at mixed steps: the recursion itself
    v = rng.normal(size=t.size).cumsum()
    got = filter_bank(t, v, (45.0, 2 * H))
    for j, tau in enumerate((45.0, 2 * H)):
        np.testing.assert_allclose(got[:, j], reference_filter(t, v, tau), rtol=0, atol=1e-10)


def test_filter_bank_over_a_ten_hour_gap():
    t = np.concatenate([np.arange(0, 1800, 15.0), 1785 + 10 * H + np.arange(1, 121) * 15.0])
    k = int(np.flatnonzero(np.diff(t) > H)[0]) + 1  # first sample after the gap
    u = np.where(np.arange(t.size) < k, 0.0, 5.0)  # 5 held over the gap and after it
    taus = (60.0, H, 30 * 86400.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow, no underflow warning, no NaN
        y = filter_bank(t, u, taus)
    elapsed = t[k:] - t[k - 1]
    for j, tau in enumerate(taus):
        exact = 5.0 * -np.expm1(-elapsed / tau)  # from 0 toward 5, starting at the gap's start
        np.testing.assert_allclose(y[k:, j], exact, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(y[:k, j], 0.0, atol=1e-12)
    assert y[k, 0] == 5.0  # 10 h is 600 time constants of 60 s: fully settled
    # a gap of a century in one step
    y = filter_bank([0.0, 3.2e9, 3.2e9 + 15], [1.0, 2.0, 2.0], (15.0, 86400.0))
    assert np.all(np.isfinite(y)) and y[1, 0] == 2.0


def test_filter_bank_zero_dt_and_constant_input():
    y = filter_bank([0.0, 0.0, 10.0], [1.0, 9.0, 9.0], (10.0,))
    assert y[1, 0] == 1.0  # no time passed: no change
    assert y[2, 0] == pytest.approx(9 + (1 - 9) * math.exp(-1))
    np.testing.assert_array_equal(filter_bank([0, 1, 2], [3.0, 3.0, 3.0], (0.0, 5.0)), 3.0)


@settings(max_examples=25, deadline=None)
@given(
    u=st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=1, max_size=40),
    dts=st.lists(st.floats(0.0, 1e9, allow_nan=False), min_size=39, max_size=39),
    tau=st.floats(1e-3, 1e7),
)
def test_filter_bank_finite_and_bounded_for_any_finite_input(u, dts, tau):
    u = np.array(u)
    t = np.concatenate([[0.0], np.cumsum(dts)])[: u.size]
    y = filter_bank(t, u, (0.0, tau))
    assert np.all(np.isfinite(y))
    assert np.all(y >= u.min()) and np.all(y <= u.max())


# -- the ridge identification ---------------------------------------------------------------------


def synthetic(seed: int = 0, dt_s: float = 60.0):
    """Four cycles of a plant that the bank can represent exactly, plus an ambient input."""
    t, n = profile(
        [
            (H, 6000),
            (H, 9000),
            (2.5 * H, 0),
            (2 * H, 12000),
            (2.5 * H, 0),
            (H, 3000),
            (H, 15000),
            (2.5 * H, 0),
            (H, 9000),
            (H, 4000),
            (2.5 * H, 0),
        ],
        dt_s,
    )
    rng = np.random.default_rng(seed)
    amb = 21 + 1.5 * np.sin(2 * np.pi * t / (9 * H)) + 0.05 * rng.normal(size=t.size)
    k = n / 1000
    bank = lambda u, tau: filter_bank(t, u, (tau,))[:, 0]
    y = (
        0.4
        + 0.08 * k
        + 0.9 * bank(k, 600.0)
        + 0.05 * bank(k * k, 1800.0)
        + 1.2 * bank(amb - 21.0, 1800.0)
        + 0.3 * (amb - 21.0)
    )
    return t, n, {"amb_c": amb}, y + 0.02 * rng.normal(size=t.size)


GRID = TauGrid((0.0, 600.0, 1800.0), (0.0, 1800.0))


@pytest.fixture(scope="module")
def fitted():
    t, n, inputs, y = synthetic()
    return fit_ridge_cv(t, n, y, inputs, grids=[GRID], nested=True), (t, n, inputs, y)


def test_ridge_recovers_a_representable_plant(fitted):
    res, (t, n, inputs, y) = fitted
    assert len(res.cycles) == 4 and len(res.folds) == 4
    assert res.cv_rms_um < 0.05 and res.nested_rms_um < 0.05
    assert all(f.rms_um <= f.max_abs_um for f in res.folds)
    assert res.accepted and not res.refusals and "accepted" in res.describe()[0]
    assert res.baseline["cv_rms_um"] > 3 * res.cv_rms_um
    assert res.references["amb_c"] == pytest.approx(float(np.mean(inputs["amb_c"])))
    pred = res.predict(t, n, inputs)
    assert float(np.sqrt(np.mean((pred - y) ** 2))) < 0.04
    se = hac_stderr(res, t, n, y, inputs)
    assert se.shape == res.gains.shape and np.all(np.isfinite(se))


def test_hac_stderr_is_statsmodels_newey_west_at_alpha_zero():
    import statsmodels.api as sm

    t, n, inputs, y = synthetic()
    res = fit_ridge_cv(t, n, y, inputs, grids=[GRID], alphas=(0.0,))
    x = np.column_stack(
        [
            filter_bank(t, n / 1000, GRID.speed_taus_s),
            filter_bank(t, (n / 1000) ** 2, GRID.speed_taus_s),
            filter_bank(t, inputs["amb_c"] - res.references["amb_c"], GRID.input_taus_s),
        ]
    )
    ols = sm.OLS(y, sm.add_constant(x)).fit(
        cov_type="HAC", cov_kwds={"maxlags": 30, "use_correction": False}
    )
    np.testing.assert_allclose(res.gains, ols.params[1:], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(hac_stderr(res, t, n, y, inputs, maxlags=30), ols.bse[1:], rtol=1e-6)


def test_predict_is_a_free_run_of_the_runtime_model(fitted):
    """The fit's prediction and the runtime's state-space model stepped cycle by cycle (the
    core's exact first-order step) agree at irregular steps."""
    res, (t, n, inputs, y) = fitted
    ss = res.state_space()
    assert ss.taus_s == (600.0, 1800.0)  # one state per distinct time constant
    speed_only = fit_ridge_cv(t, n, y, grids=[TauGrid(GRID.speed_taus_s)]).to_model(
        "ridge", spindle_id="t"
    )
    model = res.to_model("ridge+inputs", fallback=speed_only, spindle_id="t")
    tt, nn = t[::7], n[::7]  # irregular steps
    tt = tt + np.linspace(0, 50, tt.size)
    uu = {k: v[::7] for k, v in inputs.items()}
    pred = res.predict(tt, nn, uu)
    state = model.start(None, nn[0], {k: float(v[0]) for k, v in uu.items()})
    out = [state.elongation_um]
    for k in range(1, tt.size):
        state = model.step(
            state, nn[k], tt[k] - tt[k - 1], {key: float(v[k]) for key, v in uu.items()}
        )
        out.append(state.elongation_um)
    np.testing.assert_allclose(pred, out, rtol=0, atol=1e-9)


def test_suffix_replay_invariance_after_settling(fitted):
    res, (t, n, inputs, _) = fitted
    full = res.predict(t, n, inputs)
    settle = res.settling_time_s(1e-8)
    assert settle == pytest.approx(1800 * math.log(1e8))
    for m in (37, 200, 400):  # start the log later: hot, cold, in a transient
        part = res.predict(t[m:], n[m:], {k: v[m:] for k, v in inputs.items()})
        late = t[m:] - t[m] >= settle
        assert late.any()
        np.testing.assert_allclose(part[late], full[m:][late], rtol=0, atol=1e-6)
    # at the start itself it differs: the state starts at equilibrium with the first sample
    assert (
        abs(res.predict(t[400:], n[400:], {"amb_c": inputs["amb_c"][400:]})[0] - full[400]) > 1e-3
    )


def test_speed_only_maps_onto_the_runtime_model():
    t, n, _, y = synthetic(1)
    res = fit_ridge_cv(t, n, y, grids=[TauGrid((0.0, 600.0, 1800.0))])
    model, state, offset_um = res.to_thermal_model(60.0)
    assert model.order == 2 and model.elastic_um != (0.0, 0.0)
    sim = model.simulate(n, t, state).elongation_um + offset_um
    np.testing.assert_allclose(sim, res.predict(t, n), rtol=0, atol=1e-9)
    assert res.steady_range_um() < 10 * res.max_measured_um


def test_sanity_checks_and_refusals():
    t, n, _, y = synthetic(2)
    with pytest.raises(CalibrationError, match="outside"):
        fit_ridge_cv(t, n, y, grids=[TauGrid((0.0, 5.0))])  # below the sample period
    with pytest.raises(CalibrationError, match="outside"):
        fit_ridge_cv(t, n, y, grids=[TauGrid((0.0, 30 * 86400.0))])  # beyond days
    with pytest.raises(CalibrationError, match="one cycle"):
        fit_ridge_cv(t, n, y, cycles=[(0, t.size)])
    # a plant with a 1 h lag and a candidate with static terms only: worse than the exponential
    # baseline (one lag), so it is refused
    k = n / 1000
    lagged = 2.0 + filter_bank(t, 0.8 * k + 0.05 * k * k, (BASELINE_TAUS_S[8],))[:, 0]
    res = fit_ridge_cv(t, n, lagged, grids=[TauGrid((0.0,))])
    assert res.baseline["cv_rms_um"] < 1e-6 < res.cv_rms_um
    assert not res.accepted and "exponential baseline" in res.refusals[0]
    assert "REFUSED" in res.describe()[0]
    grid = auto_grid(t, n, split_cycles(t, n), True)
    assert grid.speed_taus_s[0] == 0 and all(60.0 <= x <= 10 * 86400 for x in grid.speed_taus_s[1:])


@settings(max_examples=20, deadline=None)
@given(
    speed=st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=2, max_size=30),
    amb=st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=30, max_size=30),
    dts=st.lists(st.floats(0.0, 1e8, allow_nan=False), min_size=29, max_size=29),
)
def test_predict_finite_for_any_finite_input(fitted, speed, amb, dts):
    res, _ = fitted
    k = len(speed)
    t = np.concatenate([[0.0], np.cumsum(dts)])[:k]
    pred = res.predict(t, speed, {"amb_c": amb[:k]})
    assert pred.shape == (k,) and np.all(np.isfinite(pred))


def test_predict_refuses_nan_and_missing_inputs(fitted):
    res, (t, n, inputs, _) = fitted
    with pytest.raises(NonFiniteInputError):
        res.predict(t[:3], [0.0, math.nan, 0.0], {"amb_c": inputs["amb_c"][:3]})
    with pytest.raises(CalibrationError, match="amb_c"):
        res.predict(t[:3], n[:3])


# -- the paper's OLS, for the comparison --------------------------------------------------------


def test_paper_ols_recovers_its_own_form_and_runs_free():
    t, n = profile(
        [
            (H, 3000),
            (H, 6000),
            (H, 12000),
            (2 * H, 0),
            (H, 15000),
            (H, 9000),
            (H, 4000),
            (2 * H, 0),
        ],
        60.0,
    )
    k = n / 1000
    a, b = 0.97, (0.01, 0.02, 0.003, 0.0001)
    s = np.empty(t.size)
    s[0] = 0.0
    for i in range(1, t.size):
        s[i] = a * s[i - 1] + b[0] + b[1] * k[i] + b[2] * k[i] ** 2 + b[3] * k[i] ** 3
    fit = fit_paper_ols(t, n, s)
    assert fit.a == pytest.approx(a, abs=1e-9) and fit.one_step_r2 > 0.9999
    np.testing.assert_allclose(fit.b_um, b, atol=1e-8)
    np.testing.assert_allclose(fit.predict(t, n, 0.0), s, atol=1e-6)
    # the same model stepped at irregular times: its exact zero-order-hold form
    tt = t + np.concatenate([[0.0], np.full(t.size - 1, 1e-3)])
    assert np.max(np.abs(fit.predict(tt, n, 0.0) - s)) < 1e-3
    cv = paper_ols_cv(t, n, s, split_cycles(t, n))
    assert cv["cv_rms_um"] < 1e-5 and len(cv["folds"]) == 2


def test_the_forward_figure_uses_only_the_past(fitted):
    """Rolling origin every half cycle: the second cool-down is predicted from the rows before
    it only, so corrupting the last cycle leaves its score alone and ruins the last one's."""
    res, (t, n, inputs, y) = fitted
    assert len(res.forward_folds) == 2 * len(res.cycles) - 3 == 5
    corrupt = y.copy()
    a, b = res.cycles[-1]
    corrupt[a:b] += 50.0
    again = fit_ridge_cv(t, n, corrupt, inputs, grids=[GRID], nested=True)
    assert again.forward_folds[0].rms_um == pytest.approx(res.forward_folds[0].rms_um, rel=1e-9)
    assert again.forward_folds[-1].rms_um > res.forward_folds[-1].rms_um + 10.0
    # the spread over the penalty alone, one figure per alpha tried
    assert len(res.forward_rms_by_alpha_um) == len(DEFAULT_ALPHAS)
    assert all(math.isfinite(v) and v > 0 for v in res.forward_rms_by_alpha_um)


def _collinear(seed: int = 4):
    """The synthetic plant read by seven sensors: the ambient that drives it, five copies of it
    with their own noise and offsets (nearly collinear, as sensors on one casting are), and one
    that carries nothing."""
    t, n, inputs, y = synthetic()
    rng = np.random.default_rng(seed)
    amb = inputs["amb_c"]
    sensors = {
        "amb_c": amb,
        "decoy_c": 22 + 0.3 * np.sin(2 * np.pi * t / (5 * H)) + 0.05 * rng.normal(size=t.size),
    }
    for k, (gain, offset) in enumerate(
        ((1.0, 0.5), (0.8, 1.0), (1.1, -0.7), (0.9, 0.2), (1.05, 0.1))
    ):
        sensors[f"copy{k}_c"] = offset + gain * amb + 0.05 * rng.normal(size=t.size)
    return t, n, sensors, y


@pytest.mark.parametrize("structure", ["pca", "few"])
def test_structures_that_share_strength_map_onto_the_runtime_model(structure):
    """Principal components and a forward selection of inputs fit in their own space, and the
    gains map back exactly: the runtime model free-runs the log to the fit's own prediction. The
    components' model reads every sensor; the selection's only those it kept."""
    from calibration.dataset import from_arrays
    from calibration.estimators import ridge_bank as rb

    t, n, sensors, y = _collinear()
    ds = from_arrays(t, n, y, sensors)
    res = rb.fit(ds, grids=[GRID], input_names=tuple(sensors), structure=structure, nested=True)
    if structure == "pca":
        assert (
            set(res.input_names) == set(sensors) and "principal component" in res.structure_detail
        )
    else:
        assert 1 <= len(res.input_names) <= rb.MAX_FEW and "decoy_c" not in res.input_names
        assert res.structure_detail.startswith("kept ")
    # the plant is still represented; the forward folds start from a cycle and a half of past
    assert res.nested_rms_um < 0.2 and np.median([f.rms_um for f in res.forward_folds]) < 0.2
    speed_only = fit_ridge_cv(t, n, y, grids=[TauGrid(GRID.speed_taus_s)]).to_model(
        "ridge", spindle_id="t"
    )
    model = res.to_model(f"ridge+{structure}", fallback=speed_only, spindle_id="t")
    used = {k: v for k, v in sensors.items() if k in model.input_names}
    np.testing.assert_allclose(
        model.simulate_um(n, t, used, None), res.predict(t, n, used), rtol=0, atol=1e-9
    )


def test_input_structures_compete_only_on_three_folds_and_six_inputs_or_more():
    """On two folds the choice among input structures is noise (it picked the wrong one on the
    real record), and a few sensors keep a bank each: only the plain bank is tried there."""
    from calibration.identify import LogData, identify

    t, n, sensors, y = _collinear()
    a, _b = split_cycles(t, n)[2]
    two = identify(
        [LogData("two", t[:a], n[:a], y[:a], {k: v[:a] for k, v in sensors.items()})],
        tuple(sensors),
        physical=False,
        probe_target_um=None,
    )
    four = identify(
        [LogData("four", t, n, y, sensors)], tuple(sensors), physical=False, probe_target_um=None
    )
    names = lambda r: [c.name for c in r.candidates if c.family == "inputs"]
    assert len(two.dataset.folds) == 2 and names(two) == ["ridge+inputs", "ridge+static"]
    assert names(four) == [
        "ridge+inputs",
        "ridge+static",
        "ridge+few",
        "ridge+pca",
        "ridge+bounded",
    ]
    few = identify(
        [LogData("few", t, n, y, {k: sensors[k] for k in list(sensors)[:3]})],
        tuple(sensors)[:3],
        physical=False,
        probe_target_um=None,
    )
    assert names(few) == ["ridge+inputs", "ridge+static"]
    assert sum(c.accepted for c in four.candidates if c.family == "inputs") == 1
    assert any(
        r.startswith("ridge+") for c in four.candidates if c.family == "inputs" for r in c.refusals
    )


def test_the_fit_states_the_error_to_expect_by_speed_band():
    """The model's fit record carries the error to expect at rest and in three bands of the
    calibrated speeds, from the forward residual where it covers a band (the future is what the
    model meets), else from the held-out one; each band's 95th percentile bounds 95 % of it."""
    from calibration.identify import LogData, identify
    from calibration.metrics import expected_error

    t, n, _inputs, y = synthetic()
    fit = identify([LogData("s", t, n, y)], physical=False, probe_target_um=None)
    bands = fit.model.fit["expected_error"]["bands"]
    assert bands[0]["speed_rpm"] == [0.0, 1.0] and len(bands) == 4
    assert all(b["source"].startswith(("forward", "held out")) for b in bands)
    assert all(0 < b["rms_um"] <= b["p95_abs_um"] * 2 and b["samples"] >= 10 for b in bands)
    # the percentile is the residual's own: 95 % of a band's rows lie within it
    rng = np.random.default_rng(1)
    r = rng.normal(0, 2.0, t.size)
    stated = expected_error(r, None, n, float(n.max()))
    which = stated.band_index(n)
    for k, b in enumerate(stated.bands):
        assert np.mean(np.abs(r[which == k]) <= b.p95_abs_um) == pytest.approx(0.95, abs=0.01)
    assert stated.band_of(1e6) is stated.bands[-1]  # above the calibrated range: the top band
    # the forward figure states a band, widened where the held-out one reaches further
    both = expected_error(r, 3 * r, n, float(n.max()))
    assert all(b.source.endswith("widened to held out") and b.p95_abs_um > 5.0 for b in both.bands)


def test_the_error_to_expect_grows_where_the_inputs_left_the_trained_range():
    """Rows predicted forward whose inputs lay outside the range their past saw state the
    outside figure; the service reads it when the inputs are out, the inside one when in; beyond
    the farthest distance validation scored the figure is marked as not validated."""
    from calibration.metrics import against_expected, expected_error

    rng = np.random.default_rng(2)
    t, n, _inputs, _y = synthetic()
    dist = np.where(np.arange(t.size) % 3 == 0, 0.4, 0.0)
    r = rng.normal(0, 1.0, t.size) * np.where(dist > 0, 4.0, 1.0)
    stated = expected_error(r, None, n, float(n.max()), dist, forward_folds=3)
    assert stated.outside_validated == pytest.approx(0.4)
    for b in stated.bands:
        assert b.outside is not None and b.outside.p95_abs_um > 2.5 * b.p95_abs_um
    top = float(n.max())
    inside, out, far = stated.at(top, 0.0), stated.at(top, 0.2), stated.at(top, 0.9)
    assert inside.p95_abs_um < out.p95_abs_um and out.outside and out.validated
    assert far.p95_abs_um == out.p95_abs_um and not far.validated
    # above the calibrated speeds, or from one fold predicted forward, nothing is validated
    assert not stated.at(1.5 * top, 0.0).validated and stated.at(top, 0.0).validated
    assert not expected_error(r, None, n, top, dist, forward_folds=1).at(top, 0.0).validated
    # judged against the bound for where each row was, the statement holds about 95 %
    rows = against_expected(stated, r, n, dist)
    assert all(row["within_p95"] == pytest.approx(0.95, abs=0.03) for row in rows)
    # against the inside bounds alone the outside rows break it
    assert min(row["within_p95"] for row in against_expected(stated, r, n)) < 0.9


def test_extrapolation_is_chosen_by_data_on_the_rows_that_left_the_range():
    """Clip wins where holding the inputs did better on the forward rows outside the range;
    linear stands when the others are no better by more than the parsimony margin, and when
    too few rows left the range to choose by."""
    from calibration.candidate import Candidate
    from calibration.identify import extrapolation

    rng = np.random.default_rng(3)
    size = 400
    d = np.where(np.arange(size) >= 200, 0.3, 0.0)
    base = rng.normal(0, 1.0, size)
    fb = Candidate("ridge", "speed", "", forward_residual_um=base * 6)
    two = {"forward_folds_rms_um": [1.0, 1.0]}
    clip_better = Candidate(
        "ridge+inputs",
        "inputs",
        "",
        forward_residual_um=base * np.where(d > 0, 3, 1),
        forward_clipped_residual_um=base,
        forward_distance=d,
        **two,
    )
    policy, _, residual, why = extrapolation(clip_better, fb)
    assert policy == "clip" and np.array_equal(residual, base) and "clip" in why
    same = Candidate(
        "ridge+inputs",
        "inputs",
        "",
        forward_residual_um=base,
        forward_clipped_residual_um=base * 1.01,
        forward_distance=d,
        **two,
    )
    assert extrapolation(same, fb)[0] == "linear"
    few = Candidate(
        "ridge+inputs",
        "inputs",
        "",
        forward_residual_um=base * 3,
        forward_clipped_residual_um=base,
        forward_distance=np.where(np.arange(size) < 5, 0.3, 0.0),
        **two,
    )
    policy, _, _, why = extrapolation(few, fb)
    assert policy == "linear" and "too few" in why
    # a blend toward a fallback that did better out there
    blend = Candidate(
        "ridge+inputs",
        "inputs",
        "",
        forward_residual_um=base * np.where(d > 0, 5, 1),
        forward_clipped_residual_um=base * np.where(d > 0, 5, 1),
        forward_distance=d,
        **two,
    )
    good_fb = Candidate("ridge", "speed", "", forward_residual_um=base * 0.5)
    assert extrapolation(blend, good_fb)[:2] == ("blend", 0.25)
    # one fold predicted forward is too noisy to choose by
    one = Candidate(
        "ridge+inputs",
        "inputs",
        "",
        forward_residual_um=base * 3,
        forward_clipped_residual_um=base,
        forward_distance=d,
        forward_folds_rms_um=[1.0],
    )
    assert extrapolation(one, fb)[0] == "linear"


def test_replay_sets_the_error_beside_what_the_fit_expected(tmp_path):
    """Replay of a log holds its error, band by band, against the error the fit stated: a log
    like the calibration stays within the stated 95 % band; one whose spindle grew 3 um more
    than the model knows does not, and replay says to probe or recalibrate."""
    from calibration.identify import LogData, identify
    from calibration.replay import replay
    from compensator.io import read_run_log, write_run_log

    t, n, inputs, y = synthetic()
    model = identify(
        [LogData("s", t, n, y, inputs)], ("amb_c",), physical=False, probe_target_um=None
    ).model
    assert model.input_names == ("amb_c",)
    for name, shift in (("same", 0.0), ("grown", 3.0)):
        write_run_log(
            tmp_path / f"{name}.csv",
            {"time_s": t, "speed_rpm": n, "elongation_um": y + shift, **inputs},
        )
        rep = replay(model, read_run_log(tmp_path / f"{name}.csv"), compare=False).report
        bands = rep["expected_error"]
        assert bands and all(b["samples"] >= 10 for b in bands)
        said = [
            w for w in rep["warnings"] if w.startswith("the error is larger than the fit expected")
        ]
        if shift == 0.0:
            assert min(b["within_p95"] for b in bands) >= 0.8 and not said
        else:
            assert (
                max(b["within_p95"] for b in bands) < 0.5
                and said
                and "probe or recalibrate" in said[0]
            )


# -- forward origins and the choice between structures ----------------------------------------


def _four_cycles():
    return profile([(2 * H, 6000), (3 * H, 0)] * 4, dt_s=60.0)


def test_forward_origins_every_half_cycle_use_only_the_rows_before():
    """Four cycles give five forward splits (whole cycles alone gave two): each cycle's start
    from the third and each cool-down from the second, the past ending where the stretch
    predicted begins, a heat-up in the past a fold of its own."""
    from calibration import folds as fl

    t, n = _four_cycles()
    cycles = split_cycles(t, n)
    assert len(cycles) == 4
    splits = fl.forward_origins(t, n, cycles)
    assert len(splits) == 5 and len(fl.forward_splits(cycles, first=2)) == 2
    for past, (a, b) in splits:
        assert past[0][0] == 0 and past[-1][1] == a and b > a  # the rows before, nothing after
        assert all(x[1] == y[0] for x, y in itertools.pairwise(past))
    first_past, (a, _b) = splits[0]
    assert first_past[-1] == (cycles[1][0], a) and n[a] == 0 and n[a - 1] == 6000
    assert [s[1] for s in splits][-1][1] == t.size  # the last stretch ends with the log
    assert len(fl.forward_origins(t, n, cycles[:2])) == 1  # two cycles: the second cool-down
    blocks = fl.halves(t, n, cycles)  # the blocks a penalty chosen forward-chained is judged on
    assert len(blocks) == 8 and all(
        (n[a:b] > 0).all() == (k % 2 == 0) for k, (a, b) in enumerate(blocks[1:], 1)
    )


def _duel_of(rich_fold_um, simple_fold_um, need=0):
    """The choice's duel between two candidates whose forward residual is the given constant on
    each of the five forward folds of four cycles."""
    from calibration import folds as fl
    from calibration.candidate import Candidate
    from calibration.dataset import from_arrays
    from calibration.identify import _duel

    t, n = _four_cycles()
    ds = from_arrays(t, n, np.zeros(t.size), None)
    splits = fl.forward_of(t, n, ds.folds, True)

    def cand(name, per_fold):
        r = np.full(t.size, np.nan)
        for (_p, (a, b)), v in zip(splits, per_fold, strict=True):
            r[a:b] = v
        return Candidate(name, "inputs", name, forward_residual_um=r, held_out_residual_um=r)

    return _duel(cand("rich", rich_fold_um), cand("simple", simple_fold_um), splits, ds, need)


def test_a_flexible_structure_must_beat_the_simpler_by_more_than_the_folds_spread():
    """One standard error of the paired per-fold difference, and no worse median or worst fold:
    lower on every fold wins; lower on one fold and higher on another does not; lower on
    average by far but with a worse worst fold does not either; a far lower worst fold with a
    median within 10 % does."""
    ones = [1.0] * 5
    assert _duel_of([0.5] * 5, ones).won
    lucky = _duel_of([0.5, 1.1, 1.0, 1.0, 1.0], ones)
    assert not lucky.won and "less than one standard error" in lucky.text
    tail = _duel_of([0.1, 0.1, 0.1, 0.1, 1.5], ones)
    assert not tail.won and "worst 1.50 against 1.00 um" in tail.text
    assert "more than one standard error" in tail.text  # the average alone would have taken it
    # within one standard error, but one stretch the simpler one misses by 3x: the worst decides
    rescue = _duel_of([1.05, 1.05, 1.05, 1.05, 1.0], [1.0, 1.0, 1.0, 1.0, 3.0])
    assert rescue.won and "less than one standard error" in rescue.text
    assert "the worst fold decides" in rescue.text


def test_past_the_static_structure_a_flexible_one_needs_four_forward_folds():
    """Lower on every fold by half wins on five forward folds; asked for six, it cannot try, and
    says how many folds it had and how many it needed."""
    from calibration.identify import MIN_FLEXIBLE_FOLDS

    assert MIN_FLEXIBLE_FOLDS == 5
    assert _duel_of([0.5] * 5, [1.0] * 5, need=MIN_FLEXIBLE_FOLDS).won  # five folds: it may
    short = _duel_of([0.5] * 5, [1.0] * 5, need=6)
    assert not short.won and "5 forward fold(s), fewer than the 6" in short.text


def test_with_inputs_the_static_structure_stands_first_and_keeps_them():
    """On two cycles (one forward fold) the static structure is the choice with inputs, whatever
    the more flexible ones score, and the inputs are not dropped for speed alone; the reason
    says so. On one cycle (blocks) too."""
    from calibration.identify import STATIC, LogData, identify

    t, n, sensors, y = _collinear()
    a, _b = split_cycles(t, n)[2]
    for end in (a, split_cycles(t, n)[1][0]):
        got = identify(
            [LogData("short", t[:end], n[:end], y[:end], {k: v[:end] for k, v in sensors.items()})],
            tuple(sensors),
            physical=False,
            probe_target_um=None,
        )
        assert got.chosen.name == STATIC, (end, got.reason)
        assert set(got.model.input_names) == set(sensors)
        assert got.model.fallback is not None  # speed only stands in when an input fails
        flexible = [c for c in got.candidates if c.family == "inputs" and c.name != STATIC]
        assert flexible and not any(c.accepted for c in flexible)
        assert STATIC in got.reason and "stands" in got.reason


def test_the_held_out_paired_difference_uses_the_rows_both_scored():
    """The physical form's one-standard-error check: per fold, the difference of the two
    candidates' mean square on the rows both scored (a row one of them did not score, or
    diverged on, leaves both out), then its mean and standard error over the folds."""
    from calibration.candidate import Candidate
    from calibration.dataset import from_arrays
    from calibration.identify import _paired_fold_mse_um2

    t, n = _four_cycles()
    ds = from_arrays(t, n, np.zeros(t.size), None)
    rng = np.random.default_rng(3)
    a, b = rng.normal(0, 1.0, t.size), rng.normal(0, 0.8, t.size)
    a[5], b[7] = np.inf, np.nan
    cand = lambda r: Candidate("c", "speed", "c", held_out_residual_um=r)
    d = []
    for lo, hi in ds.folds:
        ok = np.isfinite(a[lo:hi]) & np.isfinite(b[lo:hi])
        d.append(np.mean(a[lo:hi][ok] ** 2) - np.mean(b[lo:hi][ok] ** 2))
    mean, se, k = _paired_fold_mse_um2(cand(a), cand(b), ds)
    assert k == len(ds.folds) == 4
    assert mean == pytest.approx(np.mean(d), rel=1e-12)
    assert se == pytest.approx(np.std(d, ddof=1) / np.sqrt(len(d)), rel=1e-12)
    assert mean > 0  # the first errs more


def test_a_temperatures_valid_range_reaches_ten_kelvin_beyond_calibration():
    """A sensor reading one span beyond a narrow calibration is a warmer machine, not a fault:
    a temperature's valid range reaches 10 K beyond what calibration saw (or one span, when
    that is wider); another input keeps one span."""
    from calibration.dataset import from_arrays
    from calibration.estimators import ridge_bank as rb

    t, n = _four_cycles()
    warm = 22.0 + 0.5 * np.sin(t / 3600.0)  # a 1 K span
    wide = 22.0 + 15.0 * np.sin(t / 3600.0)  # a 30 K span
    load = 2.0 + 0.5 * np.sin(t / 1800.0)
    y = 0.001 * n + 3.0 * (warm - 22.0) + 0.1 * (wide - 22.0) + 0.2 * load
    ds = from_arrays(t, n, y, {"warm_c": warm, "wide_c": wide, "load_w": load})
    res = rb.fit(
        ds,
        input_names=("warm_c", "wide_c", "load_w"),
        units={"warm_c": "degC", "wide_c": "degC", "load_w": "W"},
        nested=False,
    )
    span = lambda u: float(u.max() - u.min())
    assert res.valid_ranges["warm_c"] == pytest.approx((warm.min() - 10.0, warm.max() + 10.0))
    assert res.valid_ranges["wide_c"] == pytest.approx(
        (wide.min() - span(wide), wide.max() + span(wide))
    )
    assert res.valid_ranges["load_w"] == pytest.approx(
        (load.min() - span(load), load.max() + span(load))
    )
