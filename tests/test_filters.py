"""The exact first-order steps of compensator.filters: one step, a series at uniform, mixed and
wandering steps, the recursion under them, against a plain Python loop; and every model's step
and free run agreeing through them."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from conftest import rich_form
from hypothesis import given, settings
from hypothesis import strategies as st

from compensator.filters import (
    Steps,
    constant_decay,
    decaying_sum,
    first_order,
    lag,
    lag_step,
    lowpass,
    rate_gains,
    rate_step,
)
from compensator.statespace import InputChannel, StateSpaceModel


def loop(t: np.ndarray, u: np.ndarray, tau: float, y0: float | None = None) -> np.ndarray:
    y = np.empty_like(u)
    y[0] = u[0] if y0 is None else y0
    for k in range(1, u.size):
        a = math.exp(-(t[k] - t[k - 1]) / tau)
        y[k] = a * y[k - 1] + (1 - a) * u[k]
    return y


CLOCKS = {
    "uniform": lambda rng, n: 1.7e9 + np.arange(n) * 1.0,
    "runs with gaps": lambda rng, n: (
        1.7e9 + np.cumsum(np.repeat(rng.choice([1.0, 15.0, 3600.0], n // 500 + 1), 500)[:n])
    ),
    "mixed": lambda rng, n: np.cumsum(rng.choice([0.1, 1.0, 15.0, 60.0, 600.0], n)),
    "wandering": lambda rng, n: 1.7e9 + np.cumsum(rng.uniform(0.9, 1.1, n)),
}


@pytest.mark.parametrize("clock", CLOCKS.values(), ids=CLOCKS.keys())
@pytest.mark.parametrize("tau", [0.5, 45.0, 5400.0, 30 * 86400.0])
def test_lag_is_the_loop_at_any_clock(clock, tau):
    rng = np.random.default_rng(3)
    t = clock(rng, 20_000)
    u = rng.normal(size=t.size).cumsum() / 30
    steps = Steps.of(t)
    np.testing.assert_allclose(lag(steps, u, tau), loop(t, u, tau), rtol=0, atol=1e-11)
    np.testing.assert_allclose(lag(steps, u, tau, y0=2.0), loop(t, u, tau, 2.0), rtol=0, atol=1e-11)
    np.testing.assert_allclose(lowpass(np.diff(t), u, tau), loop(t, u, tau), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(lag(steps, u, 0.0), u)


def test_the_scalar_steps_are_the_loop_and_its_limits():
    assert lag_step(1.0, 5.0, 60.0, 600.0) == pytest.approx(5 + (1 - 5) * math.exp(-0.1), rel=1e-15)
    assert lag_step(1.0, 5.0, 60.0, 0.0) == 5.0  # no lag
    assert lag_step(1.0, 5.0, 0.0, 600.0) == 1.0  # no time
    assert lag_step(1.0, 5.0, 3.2e9, 1e-300) == 5.0  # any gap is one step
    a, h = rate_gains(1 / 600.0, 60.0)
    assert a == pytest.approx(math.exp(-0.1), rel=1e-15) and h == pytest.approx(
        600 * (1 - a), rel=1e-14
    )
    assert rate_gains(0.0, 60.0) == (1.0, 60.0)  # the limit: the drive integrates
    assert rate_step(2.0, 0.0, 0.5, 10.0) == 7.0
    # the lag is the rate form with rate 1/tau and drive u/tau
    assert rate_step(1.0, 1 / 600.0, 5.0 / 600.0, 60.0) == pytest.approx(
        lag_step(1.0, 5.0, 60.0, 600.0), rel=1e-14
    )


def test_first_order_takes_the_steps_ending_at_each_sample():
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.5, 30.0, 3000))
    u = rng.normal(size=t.size)
    got = first_order(u, np.diff(t, prepend=t[0]), 120.0, 0.3)
    np.testing.assert_allclose(got, loop(t, u, 120.0, 0.3), rtol=0, atol=1e-11)
    np.testing.assert_array_equal(first_order(u, np.diff(t, prepend=t[0]), 0.0, 0.3), u)


def test_the_recursion_with_a_decay_that_varies_step_by_step():
    rng = np.random.default_rng(7)
    ld = rng.uniform(0.0, 0.2, 40_000)
    ld[1000] = 900.0  # a gap: far longer than a block's span
    inc = rng.normal(size=ld.size)
    x, want = 0.7, np.empty(ld.size)
    for k in range(ld.size):
        x = math.exp(-ld[k]) * x + inc[k]
        want[k] = x
    np.testing.assert_allclose(decaying_sum(inc, 0.7, ld=ld), want, rtol=0, atol=1e-10)
    np.testing.assert_allclose(decaying_sum(inc, 0.7, cum=np.cumsum(ld)), want, rtol=0, atol=1e-10)
    a = 0.99
    want = np.empty(inc.size)
    x = 0.7
    for k in range(inc.size):
        x = a * x + 0.5 * inc[k]
        want[k] = x
    np.testing.assert_allclose(constant_decay(a, inc, 0.7, 0.5), want, rtol=0, atol=1e-11)


def test_the_recursion_stays_finite_near_the_float_range():
    inc = np.full(5000, 1e300)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with np.errstate(over="ignore"):  # only the first attempt overflows, and is redone
            x = decaying_sum(inc, 0.0, ld=np.full(5000, 1e-3))
    assert np.isfinite(x).all() and x[-1] == pytest.approx(
        1e300 * -math.expm1(-5.0) / -math.expm1(-1e-3), rel=1e-9
    )


@settings(max_examples=30, deadline=None)
@given(
    u=st.lists(st.floats(-1e6, 1e6), min_size=2, max_size=60),
    dts=st.lists(st.floats(0.0, 1e7), min_size=59, max_size=59),
    tau=st.floats(1e-3, 1e7),
)
def test_lag_stays_within_its_input_for_any_steps(u, dts, tau):
    u = np.array(u)
    t = np.concatenate([[0.0], np.cumsum(dts)])[: u.size]
    y = lag(Steps.of(t), u, tau)
    span = u.max() - u.min()
    assert np.all(y >= u.min() - 1e-9 * span) and np.all(y <= u.max() + 1e-9 * span)


def model_with_inputs() -> StateSpaceModel:
    names = ("a_c", "b_c", "c_c")
    chans = tuple(
        InputChannel(
            name=n, unit="degC", reference=22.0, trained_range=(15.0, 35.0), valid_range=(5.0, 45.0)
        )
        for n in names
    )
    fallback = StateSpaceModel(
        fitted_dt_s=1.0,
        speed_range_rpm=(0.0, 20000.0),
        taus_s=(300.0,),
        drive_um=((1.0, 0.1),),
        feedthrough_um=(0.1, 0.0),
        max_measured_um=60.0,
    )
    return StateSpaceModel(
        fitted_dt_s=1.0,
        speed_range_rpm=(0.0, 20000.0),
        taus_s=(300.0, 1800.0, 7200.0),
        drive_um=(
            (1.0, 0.1, 0.3, -0.2, 0.1),
            (2.0, 0.05, 0.1, 0.2, -0.3),
            (0.5, 0.02, -0.1, 0.4, 0.2),
        ),
        feedthrough_um=(0.1, 0.0, 0.05, 0.0, -0.02),
        offset_um=0.7,
        max_measured_um=60.0,
        inputs=chans,
        fallback=fallback,
    )


@pytest.mark.parametrize("clock", CLOCKS.values(), ids=CLOCKS.keys())
def test_state_space_free_run_is_its_own_step_at_any_clock(clock):
    """The vectorised free run and the runtime's per-cycle step are the same model: inputs
    clipped to their valid range, speed capped, at every kind of clock."""
    model = model_with_inputs()
    rng = np.random.default_rng(11)
    t = clock(rng, 12_000)
    speed = np.repeat(rng.uniform(-25000, 25000, t.size // 300 + 1), 300)[: t.size]
    inputs = {
        n: 22.0 + np.cumsum(rng.normal(0, 0.3, t.size)) for n in model.input_names
    }  # leaves its range
    free = model.simulate_um(speed, t, inputs)
    state = model.start(None, speed[0], {n: v[0] for n, v in inputs.items()})
    stepped = [state.elongation_um]
    for k in range(1, t.size):
        state = model.step(state, speed[k], t[k] - t[k - 1], {n: v[k] for n, v in inputs.items()})
        stepped.append(state.elongation_um)
    np.testing.assert_allclose(free, stepped, rtol=0, atol=1e-9)


def test_state_space_free_run_names_a_bad_input_sample():
    model = model_with_inputs()
    t = np.arange(10_000.0)
    inputs = {n: np.full(t.size, 22.0) for n in model.input_names}
    inputs["b_c"][7777] = math.inf
    with pytest.raises(ValueError, match="b_c at sample 7777 is inf"):
        model.simulate_um(np.zeros(t.size), t, inputs)


def test_speed_model_free_run_is_its_own_step_at_a_wandering_clock():
    model = rich_form()
    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(0.9, 1.1, 20_000))
    speed = np.repeat(rng.uniform(0, 27000, t.size // 500 + 1), 500)[: t.size]
    free = model.simulate(speed, t).elongation_um
    state = model.cold_state(speed[0])
    stepped = [state.elongation_um]
    for k in range(1, t.size):
        state = model.step(state, speed[k], t[k] - t[k - 1])
        stepped.append(state.elongation_um)
    np.testing.assert_allclose(free, stepped, rtol=0, atol=1e-9)
