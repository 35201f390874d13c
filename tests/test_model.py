"""The pure model: exact zero-order hold at any step size, stability, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import first_order, rich_form
from hypothesis import given, settings
from hypothesis import strategies as st

from compensator import (
    ModelError,
    NonFiniteInputError,
    ThermalModel,
    ThermalStateCoefficients,
    UnstableModelError,
)

FORMS = {"first-order": first_order, "rich": rich_form}


def staircase_60s(rng: np.random.Generator, minutes: int) -> np.ndarray:
    return rng.choice([0.0, 3000.0, 9000.0, 15000.0, 21000.0, 27000.0, -12000.0], size=minutes)


def loop(model: ThermalModel, speeds, dts, state=None):
    state = state or model.cold_state()
    out = []
    for n, dt in zip(speeds, dts):
        state = model.step(state, n, dt)
        out.append(state.elongation_um)
    return np.array(out), state


@pytest.mark.parametrize("form", FORMS)
def test_60s_model_stepped_at_1s_matches_60s_result(form):
    model = FORMS[form]()
    speeds = staircase_60s(np.random.default_rng(3), 300)
    coarse, _ = loop(model, speeds, [60.0] * speeds.size)
    fine, _ = loop(model, np.repeat(speeds, 60), [1.0] * speeds.size * 60)
    shared = fine[59::60]
    np.testing.assert_allclose(shared, coarse, rtol=1e-9, atol=1e-12)
    assert np.abs(coarse).max() > 5  # the comparison is not vacuous


@pytest.mark.parametrize("form", FORMS)
def test_batch_simulate_matches_60s_steps_at_1s_and_at_0p1s(form):
    model = FORMS[form]()
    speeds = staircase_60s(np.random.default_rng(4), 120)
    coarse, _ = loop(model, speeds, [60.0] * speeds.size)
    for sub in (60, 600):
        t = np.arange(speeds.size * sub + 1) * (60.0 / sub)
        n = np.concatenate([[0.0], np.repeat(speeds, sub)])
        sim = model.simulate(n, t)
        np.testing.assert_allclose(sim.elongation_um[sub::sub], coarse, rtol=1e-9, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    d0=st.floats(1 / 20000, 1 / 30),
    d1=st.floats(0, 1e-4),
    g=st.lists(st.floats(-1e-3, 1e-3), min_size=4, max_size=4),
    e=st.lists(st.floats(-0.05, 0.05), min_size=2, max_size=2),
    speeds=st.lists(st.floats(-27000, 27000), min_size=1, max_size=12),
    seed=st.integers(0, 2**31),
)
def test_step_size_invariance_with_irregular_substeps(d0, d1, g, e, speeds, seed):
    model = ThermalModel(
        fitted_dt_s=60.0,
        speed_range_rpm=(0.0, 27000.0),
        states=(
            ThermalStateCoefficients(dissipation_per_s=(d0, d1), generation_um_per_s=tuple(g)),
        ),
        elastic_um=tuple(e),
    )
    coarse, _ = loop(model, speeds, [60.0] * len(speeds))
    rng = np.random.default_rng(seed)
    state = model.cold_state()
    fine = []
    times, nn = [0.0], [0.0]
    for n in speeds:
        cuts = np.sort(rng.uniform(0, 60, size=rng.integers(0, 8)))
        dts = np.diff(np.concatenate([[0.0], cuts, [60.0]]))
        for dt in dts:
            state = model.step(state, n, float(dt))
            times.append(times[-1] + float(dt))
            nn.append(n)
        fine.append(state.elongation_um)
    scale = max(1.0, float(np.abs(coarse).max()))
    np.testing.assert_allclose(fine, coarse, rtol=1e-9, atol=1e-9 * scale)
    sim = model.simulate(np.array(nn), np.array(times))
    np.testing.assert_allclose(sim.elongation_um[-1], coarse[-1], rtol=1e-9, atol=1e-9 * scale)


@pytest.mark.parametrize("form", FORMS)
def test_simulate_matches_step_loop_on_jittery_times(form):
    model = FORMS[form]()
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.5, 1.5, 20000))
    n = np.repeat(rng.uniform(0, 27000, 200), 100)
    sim = model.simulate(n, t)
    ref, final = loop(model, n[1:], np.diff(t))
    np.testing.assert_allclose(sim.elongation_um[1:], ref, rtol=1e-9, atol=1e-9)
    assert sim.final.thermal_um == pytest.approx(final.thermal_um, rel=1e-9)


def test_general_path_survives_spans_beyond_exp_range():
    model = rich_form()
    # 40 h at irregular ~1 s with a 5-min state: lambda*t reaches ~480 per hour
    rng = np.random.default_rng(6)
    t = np.cumsum(rng.uniform(0.9, 1.1, 40 * 3600))
    n = np.repeat(rng.uniform(0, 27000, t.size // 600 + 1), 600)[: t.size]
    sim = model.simulate(n, t)
    assert np.isfinite(sim.elongation_um).all()
    ref, _ = loop(model, n[-3000:], np.diff(t[-3001:]), state=None)
    # compare the last stretch against a loop started from the batch state
    state0 = model.simulate(n[:-3000], t[:-3000]).final
    ref, _ = loop(model, n[-3000:], np.diff(t[-3001:]), state=state0)
    np.testing.assert_allclose(sim.elongation_um[-3000:], ref, rtol=1e-9)


def test_elastic_part_is_instantaneous_at_any_step():
    model = rich_form()
    warm = model.step(model.cold_state(), 27000, 3600)
    for dt in (0.1, 1.0, 60.0):
        after = model.step(warm, 12000, dt)
        jump = after.elastic_um - warm.elastic_um
        assert jump == pytest.approx(model.elastic(12000) - model.elastic(27000))
        # the thermal part moves continuously: less and less as dt -> 0
        thermal_change = sum(after.thermal_um) - sum(warm.thermal_um)
        assert abs(thermal_change) < abs(jump) * dt / 10


def test_negative_speed_is_reverse_rotation(model_rich):
    s = model_rich.cold_state()
    assert model_rich.step(s, -15000, 60) == model_rich.step(s, 15000, 60)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_speed_or_dt_raises(model1, bad):
    with pytest.raises(NonFiniteInputError):
        model1.step(model1.cold_state(), bad, 1.0)
    with pytest.raises(NonFiniteInputError):
        model1.step(model1.cold_state(), 1000.0, bad)
    with pytest.raises(NonFiniteInputError):
        model1.simulate(np.array([0.0, bad]), np.array([0.0, 1.0]))
    with pytest.raises(ValueError):  # also a builtin ValueError
        model1.simulate(np.array([0.0, 1.0]), np.array([0.0, bad]))


def test_time_going_backwards_raises(model1):
    with pytest.raises(NonFiniteInputError, match="backwards"):
        model1.simulate(np.array([0.0, 1.0, 2.0]), np.array([0.0, 2.0, 1.0]))


def test_unstable_anywhere_in_range_is_rejected():
    # stable at 0 rpm, unstable at 27 000 rpm: lambda = 1/1200 - 27*5e-5 < 0
    with pytest.raises(UnstableModelError, match="27000 rpm"):
        ThermalModel(
            fitted_dt_s=60.0,
            speed_range_rpm=(0.0, 27000.0),
            states=(
                ThermalStateCoefficients(
                    dissipation_per_s=(1 / 1200.0, -5e-5), generation_um_per_s=(0, 1e-3, 0, 0)
                ),
            ),
        )
    # the same coefficients are accepted over a range where they are stable
    ThermalModel(
        fitted_dt_s=60.0,
        speed_range_rpm=(0.0, 12000.0),
        states=(
            ThermalStateCoefficients(
                dissipation_per_s=(1 / 1200.0, -5e-5), generation_um_per_s=(0, 1e-3, 0, 0)
            ),
        ),
    )


def test_from_discrete_round_trips_paper_coefficients():
    beta = (0.02, 0.05, 0.004, 0.0001)
    model = ThermalModel.from_discrete(0.95, beta, 60.0, speed_range_rpm=(0, 27000))
    c = model.discretize(60.0).paper_coefficients()
    assert c["a"] == pytest.approx(0.95, rel=1e-12)
    assert [c[f"b{i}"] for i in range(4)] == pytest.approx(beta, rel=1e-12)
    # resampling is exact: a' = a**(dt'/dt), gain scales by (1-a')/(1-a)
    c1 = model.discretize(1.0).paper_coefficients()
    assert c1["a"] == pytest.approx(0.95 ** (1 / 60), rel=1e-12)
    assert c1["b1"] == pytest.approx(0.05 * (1 - c1["a"]) / (1 - 0.95), rel=1e-12)
    # and it is the paper's recursion
    s, n = 3.0, 15.0
    expected = 0.95 * s + beta[0] + beta[1] * n + beta[2] * n**2 + beta[3] * n**3
    assert model.step(model.state_at(s), 15000, 60).elongation_um == pytest.approx(expected)


@pytest.mark.parametrize(
    "a,err", [(1.0, UnstableModelError), (1.02, UnstableModelError), (-0.3, ModelError)]
)
def test_from_discrete_rejects_bad_poles(a, err):
    with pytest.raises(err):
        ThermalModel.from_discrete(a, (0, 1, 0, 0), 60.0, speed_range_rpm=(0, 27000))


def test_model_is_immutable(model1):
    with pytest.raises(Exception):
        model1.fitted_dt_s = 1.0  # type: ignore[misc]
    assert model1.replace(spindle_id="sp2").spindle_id == "sp2"


def test_state_at_reproduces_the_requested_elongation(model_rich):
    s = model_rich.state_at(12.5, 18000)
    assert s.elongation_um == pytest.approx(12.5)


def test_steady_state_is_reached(model1):
    state = model1.step(model1.cold_state(), 15000, 1200 * 40)
    assert state.elongation_um == pytest.approx(model1.steady_state_um(15000), rel=1e-9)
