"""What a model with inputs does outside the range its inputs had in calibration: the policy the
fit chose (linear, clip, blend toward the fallback), the same in a whole-log run and cycle by
cycle, saved and restored with the state; and the physical bound on a temperature's gain."""

from __future__ import annotations

import numpy as np
import pytest

from compensator.estimate import Estimate
from compensator.statespace import InputChannel, StateSpaceModel


def model(policy: str = "linear", span: float = 1.0) -> StateSpaceModel:
    temp = InputChannel(
        name="temp1_c",
        unit="degC",
        reference=25.0,
        trained_range=(20.0, 30.0),
        valid_range=(10.0, 40.0),
    )
    fallback = StateSpaceModel(
        fitted_dt_s=15,
        speed_range_rpm=(0, 10000),
        taus_s=(600.0,),
        drive_um=((2.0, 0.1),),
        feedthrough_um=(0.0, 0.0),
        max_measured_um=40.0,
    )
    return StateSpaceModel(
        fitted_dt_s=15,
        speed_range_rpm=(0, 10000),
        taus_s=(600.0, 5400.0),
        drive_um=((0.5, 0.05, 0.8), (2.0, 0.2, 0.4)),
        feedthrough_um=(0.1, 0.0, 0.05),
        offset_um=0.5,
        max_measured_um=40.0,
        inputs=(temp,),
        fallback=fallback,
        extrapolation=policy,
        blend_span=span,
    )


def run(
    m: StateSpaceModel, temps: np.ndarray, speed: float = 5000.0
) -> tuple[np.ndarray, np.ndarray]:
    """The whole-log run and the cycle-by-cycle steps over the same inputs."""
    t = np.arange(temps.size) * 15.0
    sp = np.full(temps.size, speed)
    whole = m.simulate_um(sp, t, {"temp1_c": temps}, initial_um=3.0)
    st = m.start(3.0, speed, {"temp1_c": float(temps[0])})
    steps = [st.elongation_um]
    for k in range(1, temps.size):
        st = m.step(st, speed, 15.0, {"temp1_c": float(temps[k])})
        steps.append(st.elongation_um)
    return whole, np.array(steps)


RAMP = np.concatenate([np.linspace(22.0, 29.0, 200), np.linspace(29.0, 36.0, 200)])
"""Inside the trained 20..30 degC, then out to 0.6 span above it."""


@pytest.mark.parametrize("policy", ["linear", "clip", "blend"])
def test_each_policy_runs_the_same_whole_and_step_by_step(policy):
    whole, steps = run(model(policy, 0.5), RAMP)
    np.testing.assert_allclose(whole, steps, atol=1e-9)


def test_the_policies_agree_inside_the_range_and_part_outside_it():
    lin, clip, blend = (run(model(p, 0.5), RAMP)[0] for p in ("linear", "clip", "blend"))
    inside = RAMP <= 30.0
    np.testing.assert_allclose(lin[inside], clip[inside], atol=1e-12)
    np.testing.assert_allclose(lin[inside], blend[inside], atol=1e-12)
    assert lin[-1] > clip[-1] + 1.0  # the gain is positive: carried on, the growth goes on
    # clip: held at 30 degC, the states settle where 30 degC puts them
    held, _ = run(model("clip"), np.minimum(RAMP, 30.0))
    np.testing.assert_allclose(clip, held, atol=1e-12)
    # blend: the fallback alone half a span out and beyond
    fb = model().fallback.simulate_um(
        np.full(RAMP.size, 5000.0), np.arange(RAMP.size) * 15.0, None, 3.0
    )
    far = (RAMP - 30.0) / 10.0 >= 0.5
    np.testing.assert_allclose(blend[far], fb[far], atol=1e-9)
    between = (RAMP > 30.0) & ~far
    assert np.all((blend[between] - np.minimum(lin[between], fb[between])) >= -1e-9)
    assert np.all((blend[between] - np.maximum(lin[between], fb[between])) <= 1e-9)


def test_a_blends_state_is_saved_and_restored_whole():
    m = model("blend", 0.5)
    st = m.start(3.0, 5000.0, {"temp1_c": 33.0})
    st = m.step(st, 5000.0, 15.0, {"temp1_c": 33.0})
    back = m.state_from_dict(m.state_dict(st))
    assert back == st and 0.0 < back.weight < 1.0
    # a state saved without its fallback (another policy's) restarts the fallback at its estimate
    plain = m.state_from_dict(
        {k: v for k, v in m.state_dict(st).items() if k not in ("fallback_state", "blend_weight")}
    )
    assert m.step(plain, 5000.0, 15.0, {"temp1_c": 25.0}).fallback is not None


def test_the_distance_outside_is_in_spans_of_the_trained_range():
    m = model()
    assert m.distance_outside({"temp1_c": 25.0}) == 0.0
    assert m.distance_outside({"temp1_c": 32.5}) == pytest.approx(0.25)
    assert m.distance_outside({"temp1_c": 15.0}) == pytest.approx(0.5)
    np.testing.assert_allclose(m.distance_outside({"temp1_c": np.array([25.0, 35.0])}), [0.0, 0.5])


def test_the_estimate_says_how_far_out_the_inputs_are():
    est = Estimate(model())
    st = est.begin(3.0, 5000.0)
    st, _ = est.step(st, 5000.0, 15.0, now_s=15.0, wall_s=15.0, inputs={"temp1_c": 35.0})
    assert st.outside_spans == pytest.approx(0.5) and "0.50 span" in st.extrapolated
    st, _ = est.step(st, 5000.0, 15.0, now_s=30.0, wall_s=30.0, inputs={"temp1_c": 25.0})
    assert st.outside_spans == 0.0 and st.extrapolated is None


def test_a_speed_only_model_has_no_extrapolation_policy():
    with pytest.raises(ValueError, match="for a model with inputs"):
        model().fallback.model_copy(update={}).model_validate(
            {**model().fallback.model_dump(), "extrapolation": "clip"}
        )


def test_bounded_sensitivities_keep_only_the_penalties_physics_allows():
    """Two nearly equal sensors whose small difference happens to follow the growth: an
    unpenalised fit trades them off at large opposite gains (+24 and -16 um/K); the bounded structure keeps only the penalties that bring each
    within the bound, and fails in one line when none does."""
    from calibration.estimators import ridge_bank as rb
    from compensator.errors import CalibrationError

    rng = np.random.default_rng(4)
    size = 2000
    t = np.arange(size) * 15.0
    common = 25 + 3 * np.sin(t / 20000.0)
    u = np.column_stack(
        [common + 0.01 * rng.normal(size=size), common + 0.01 * rng.normal(size=size)]
    )
    y = 4.0 * (common - 25) + 20.0 * (u[:, 0] - u[:, 1]) + rng.normal(0, 0.05, size)
    bank = rb.FilterBank(
        t,
        {"n": np.zeros(size), "n2": np.zeros(size), "in:a_c": u[:, 0] - 25, "in:b_c": u[:, 1] - 25},
    )
    grid = rb.TauGrid((0.0,), (0.0,))
    alphas = (0.0, 1e-4, 1e-2, 1.0)
    cfg = rb.Config(grid, alphas, ("a_c", "b_c"))
    rows = np.ones(size, bool)
    g, _ = rb.ridge_path(bank.design(grid, cfg.names), y, alphas)
    assert np.abs(g[2:, 0]).max() > rb.BOUND_UM_PER_K  # unpenalised: the pair trades off
    kept = rb._bounded(bank, y, rows, [cfg], np.full(2, rb.BOUND_UM_PER_K))
    assert 0.0 not in kept[0].alphas and kept[0].alphas
    with pytest.raises(CalibrationError, match="um/K"):
        rb._bounded(bank, y, rows, [cfg], np.full(2, 1e-6))
