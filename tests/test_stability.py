"""Paper 000's stability figures (calibration.stability): STE, the equilibrium time, TEVR, on
synthetic records whose answers are known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calibration import stability as st
from compensator.errors import CalibrationError

TIME_S = np.arange(0.0, 8 * 3600.0 + 1.0, 60.0)  # 8 h, one sample a minute
LIMIT = 0.5e-3

# y = A(1 - e^{-t/tau}): STE = A/tau e^{-t/tau} falls below the limit at tau*ln(A/(tau*limit))
A_UM, TAU_S = 20.0, 3600.0
EXP_EQ_S = TAU_S * math.log(A_UM / (TAU_S * LIMIT))  # 144.5 min

# a first-order rise held at 17 um by a controller from the knee on
RISE_UM, RISE_TAU_S, HELD_UM = 30.0, 6456.0, 17.0
KNEE_S = -RISE_TAU_S * math.log(1 - HELD_UM / RISE_UM)  # 90.0 min


def _approach(noise_um: float = 0.0, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return A_UM * -np.expm1(-TIME_S / TAU_S) + rng.normal(0.0, noise_um, TIME_S.size)


def _held(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rise = np.minimum(RISE_UM * -np.expm1(-TIME_S / RISE_TAU_S), HELD_UM)
    return rise + rng.normal(0.0, 0.05, TIME_S.size)


def test_ste_follows_the_analytic_slope_of_a_clean_approach():
    ste = st.ste_um_per_s(TIME_S, _approach())
    exact = A_UM / TAU_S * np.exp(-TIME_S / TAU_S)
    # a natural spline has no curvature at its ends: the steep start's slope is low at first
    assert np.max(np.abs(ste[:10] - exact[:10])) < 0.12 * exact[0]  # 10 % measured
    inner = slice(10, -10)
    assert np.max(np.abs(ste[inner] - exact[inner])) < 0.01 * exact[0]
    # where the equilibrium is judged the slope is accurate to a few percent of the threshold
    near = np.abs(TIME_S - EXP_EQ_S) < 1800
    assert np.max(np.abs(ste[near] - exact[near])) < 0.05 * LIMIT


def test_equilibrium_of_a_clean_approach_is_the_analytic_time():
    eq = st.equilibrium_time_s(TIME_S, _approach())
    assert eq == pytest.approx(EXP_EQ_S, abs=60.0)


def test_equilibrium_of_a_noisy_approach_is_within_minutes():
    # an error d in STE moves the time by d*tau/limit: the slow approach is the hard case
    # (-4.9 to +6.5 min over 60 noise draws, median -0.1 min)
    found = np.array([st.equilibrium_time_s(TIME_S, _approach(0.05, seed)) for seed in range(3)])
    assert np.all(np.abs(found - EXP_EQ_S) < 10 * 60.0)
    assert abs(np.median(found) - EXP_EQ_S) < 4 * 60.0


@pytest.fixture(scope="module", params=[0, 1])
def held(request) -> tuple[np.ndarray, st.StabilityFigures]:
    y = _held(request.param)
    return y, st.stability(TIME_S, y)


def test_equilibrium_of_a_held_record_is_at_the_knee(held):
    _, figures = held
    assert figures.equilibrium_s is not None
    assert KNEE_S <= figures.equilibrium_s <= KNEE_S + 10 * 60.0  # 3.4-4.3 min late measured
    assert figures.ste_max_after_um_per_s < LIMIT
    assert figures.mean_after_um == pytest.approx(HELD_UM, abs=0.02)
    # TEVR of the held part is the noise's range only: 0.05 um over ~390 samples
    assert 0.15 < figures.tevr_um < 0.45
    assert figures.tevr_um == st.tevr_um(TIME_S, held[0], figures.equilibrium_s)


def test_the_paper_polynomial_rings_on_the_knee(held):
    # why the spline is the default: a fixed-degree polynomial cannot settle after a knee
    poly = st.equilibrium_time_s(TIME_S, held[0], degree=7)
    assert poly is None or poly > KNEE_S + 20 * 60.0


def test_the_polynomial_finds_a_smooth_approach():
    eq = st.equilibrium_time_s(TIME_S, _approach(), method="poly")
    assert eq == pytest.approx(EXP_EQ_S, abs=3 * 60.0)


def test_a_record_that_keeps_drifting_is_never_in_equilibrium():
    rng = np.random.default_rng(3)
    ramp = 1e-3 * TIME_S + rng.normal(0.0, 0.05, TIME_S.size)  # twice the threshold throughout
    figures = st.stability(TIME_S, ramp)
    assert figures.equilibrium_s is None and figures.tevr_um is None
    assert figures.max_abs_um == pytest.approx(np.max(np.abs(ramp)))
    assert figures.describe()[0].startswith("never in equilibrium")


def test_a_flat_record_is_in_equilibrium_from_the_start():
    rng = np.random.default_rng(4)
    flat = 5.0 + rng.normal(0.0, 0.05, TIME_S.size)
    assert st.equilibrium_time_s(TIME_S, flat) == TIME_S[0]


def test_a_lower_threshold_finds_a_later_equilibrium():
    strict = st.equilibrium_time_s(TIME_S, _approach(), threshold_um_per_s=0.2e-3)
    assert strict == pytest.approx(TAU_S * math.log(A_UM / (TAU_S * 0.2e-3)), abs=60.0)


def test_tevr_is_max_minus_min_from_the_given_time():
    t = np.arange(20.0)
    y = np.array([0, 9, 1, 2, 3, 4, 5.5, 5, 6, 4.5, 5, 5, 5.2, 4.9, 5, 5.1, 5, 5, 5, 5.0])
    assert st.tevr_um(t, y, 0.0) == pytest.approx(9.0)
    assert st.tevr_um(t, y, 8.0) == pytest.approx(6.0 - 4.5)  # from a sample: it counts
    assert st.tevr_um(t, y, 8.5) == pytest.approx(5.2 - 4.5)
    with pytest.raises(CalibrationError, match="no sample"):
        st.tevr_um(t, y, 20.5)


def test_start_s_leaves_out_the_start_and_keeps_the_clock():
    junk = _held()
    junk[TIME_S < 3600.0] = 100.0  # a junk start that start_s drops
    figures = st.stability(TIME_S, junk, start_s=3600.0)
    assert KNEE_S <= figures.equilibrium_s <= KNEE_S + 10 * 60.0
    assert figures.max_abs_um < 18.0


def test_describe_reads_like_the_paper():
    figures = st.StabilityFigures(
        equilibrium_s=97.2 * 60,
        tevr_um=1.92,
        ste_max_after_um_per_s=0.2e-3,
        mean_after_um=17.0,
        max_abs_um=17.8,
    )
    lines = figures.describe()
    assert lines[0] == "equilibrium at 97.2 min (|STE| < 0.5e-3 um/s), TEVR 1.92 um"
    assert "0.20e-3 um/s" in lines[1]
    with pytest.raises(AttributeError):
        figures.tevr_um = 0.0  # type: ignore[misc]


def test_a_long_record_at_one_second_is_binned_to_the_same_answer():
    t = np.arange(0.0, 8 * 3600.0 + 1.0, 1.0)
    rng = np.random.default_rng(5)
    y = A_UM * -np.expm1(-t / TAU_S) + rng.normal(0.0, 0.05, t.size)
    assert st.equilibrium_time_s(t, y) == pytest.approx(EXP_EQ_S, abs=5 * 60.0)


@pytest.mark.parametrize(
    ("time_s", "error_um", "match"),
    [
        (np.arange(20.0), np.zeros(19), "20 samples but error_um has 19"),
        (np.arange(5.0), np.zeros(5), "at least 10"),
        (np.arange(20.0), np.r_[np.zeros(7), np.nan, np.zeros(12)], "error_um at sample 7 is nan"),
        (
            np.r_[np.arange(10.0), np.inf, np.arange(11.0, 20.0)],
            np.zeros(20),
            "time_s at sample 10",
        ),
        (
            np.r_[np.arange(10.0), 9.0, np.arange(11.0, 20.0)],
            np.zeros(20),
            "does not increase at sample 10",
        ),
        (np.zeros((4, 5)), np.zeros((4, 5)), "one-dimensional"),
        (["a"] * 20, np.zeros(20), "numeric"),
    ],
)
def test_bad_input_is_one_clear_line(time_s, error_um, match):
    for call in (st.ste_um_per_s, st.equilibrium_time_s, st.stability):
        with pytest.raises(CalibrationError, match=match) as info:
            call(time_s, error_um)
        assert "\n" not in str(info.value)
    assert issubclass(CalibrationError, ValueError)


def test_bad_options_are_refused():
    y = _approach()
    with pytest.raises(CalibrationError, match="threshold"):
        st.equilibrium_time_s(TIME_S, y, threshold_um_per_s=0.0)
    with pytest.raises(CalibrationError, match="method"):
        st.ste_um_per_s(TIME_S, y, method="lowess")  # type: ignore[arg-type]
    with pytest.raises(CalibrationError, match="degree"):
        st.ste_um_per_s(TIME_S, y, method="spline", degree=5)
    with pytest.raises(CalibrationError, match="degree"):
        st.ste_um_per_s(TIME_S, y, degree=0)
    with pytest.raises(CalibrationError, match="samples from"):
        st.stability(TIME_S, y, start_s=TIME_S[-3])
