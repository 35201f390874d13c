"""The virtual spindle plant reproduces its documented figures."""

from __future__ import annotations

import numpy as np
import pytest

from compensator.speed_programs import paper_calibration
from machine_sim import PRESETS, SpindlePlant, preset
from machine_sim.plant import _system


def run(name, dt, seed=0, **changes):
    p = preset(name)
    plant = SpindlePlant(p, seed=seed)
    if changes:
        plant = plant.with_params(**changes)
    t, n = paper_calibration(p.max_rpm).sample(dt)
    return t, n, plant.run(t, n)


def test_motorized_preset_matches_the_paper_figures():
    _t, n, r = run("motorized-27k", 1.0)
    at = lambda minutes: r.true_um[int(minutes * 60)]
    assert at(180) == pytest.approx(34.4, abs=1.5)  # paper: 34.4 um at 27 000 rpm
    assert at(180) - at(181) > 10.0  # paper: -16.5 um within a minute of the drop to 12 000
    assert n[180 * 60] == 27000 and n[181 * 60] == 12000


def test_elastic_jump_is_instantaneous():
    p = preset("motorized-27k")
    plant = SpindlePlant(p, seed=0)
    plant.advance(27000, 3600)
    before = plant.true_elongation_um()
    plant.advance(12000, 0.001)
    e1, e2 = p.elastic_um
    expected = e1 * (27 - 12) + e2 * (27**2 - 12**2)
    assert before - plant.true_elongation_um() == pytest.approx(expected, rel=0.01)


@pytest.mark.parametrize(
    "name,fast_min,slow_min", [("motorized-27k", 1.0, 10), ("mechanical-8k", 10, 90)]
)
def test_time_constants(name, fast_min, slow_min):
    p = preset(name)
    taus = sorted(-1 / np.linalg.eigvals(_system(p, p.max_rpm / 1000)[0]).real / 60)
    assert taus[0] > fast_min
    assert taus[-2] > slow_min  # the slowest spindle mode (the structure is slower still)
    assert taus[-1] > 6 * 60


def test_mechanical_preset_is_slow_and_large():
    p = preset("mechanical-8k")
    plant = SpindlePlant(
        p,
        seed=0,
    ).with_params(ambient_daily_amplitude_k=0, ambient_walk_k_per_sqrt_h=0)
    plant.advance(8000, 3600)
    one_hour = plant.true_elongation_um()
    plant.advance(8000, 5 * 3600)
    six_hours = plant.true_elongation_um()
    assert six_hours > 20 and one_hour < 0.75 * six_hours  # still warming after an hour


def test_step_size_invariance_of_the_plant():
    calm = {"ambient_daily_amplitude_k": 0.0, "ambient_walk_k_per_sqrt_h": 0.0}
    _, _, fine = run("motorized-27k", 1.0, **calm)
    _, _, coarse = run("motorized-27k", 60.0, **calm)
    np.testing.assert_allclose(fine.true_um[::60], coarse.true_um, rtol=1e-9, atol=1e-9)


def test_seeded_and_reproducible_with_noise_and_quantisation():
    _, _, a = run("motorized-27k", 60.0, seed=3)
    _, _, b = run("motorized-27k", 60.0, seed=3)
    _, _, c = run("motorized-27k", 60.0, seed=4)
    np.testing.assert_array_equal(a.measured_um, b.measured_um)
    assert not np.array_equal(a.measured_um, c.measured_um)
    q = preset("motorized-27k").quantum_um
    np.testing.assert_allclose(a.measured_um / q, np.round(a.measured_um / q), atol=1e-9)
    noise = a.measured_um - a.true_um
    assert 0.03 < noise.std() < 0.1
    assert np.ptp(a.air_c) > 0  # the ambient drifts


def test_presets_are_documented():
    for p in PRESETS.values():
        assert p.description and p.max_rpm > 0


def _chiller_run(dt_s):
    """3000 rpm with the chiller set point stepped 16 -> 11 -> 19 degC."""
    # still air: the ambient walk draws one number per step, which no step size can share
    plant = SpindlePlant(preset("mechanical-cooled"), seed=3).with_params(
        ambient_walk_k_per_sqrt_h=0.0, ambient_daily_amplitude_k=0.0
    )
    t = np.arange(0.0, 4 * 3600 + dt_s / 2, dt_s)
    sp = np.where(t <= 3600, 16.0, np.where(t <= 7200, 11.0, 19.0))
    return t, plant.run(t, np.full(t.size, 3000.0), sp)


def test_the_chiller_lags_ramps_and_the_step_is_exact_at_any_dt():
    t1, fine = _chiller_run(1.0)
    t60, coarse = _chiller_run(60.0)
    at = lambda t, x, s: x[np.searchsorted(t, s)]
    for s in (1800.0, 3660.0, 3600 + 300.0, 7200.0 + 600.0, 14400.0):
        # same trajectory at the shared instants, however the set point ramp falls in a step
        assert at(t1, fine.temps_c[:, 2], s) == pytest.approx(
            at(t60, coarse.temps_c[:, 2], s), abs=1e-6
        )
        assert at(t1, fine.supply_c, s) == pytest.approx(at(t60, coarse.supply_c, s), abs=1e-6)
    p = preset("mechanical-cooled")
    rate = np.diff(fine.supply_c) / np.diff(t1)
    # the outlet never moves faster than the set-point ramp (it lags behind it)
    assert np.max(np.abs(rate)) <= p.chiller_rate_k_per_min / 60 + 1e-9
    # one lag after the 5 K ramp has ended (5 min), the outlet is within 1/e of the rest
    k = np.searchsorted(t1, 3600 + 300 + p.chiller_lag_s)
    assert (
        11.0
        < fine.supply_c[k]
        < 11.0 + 5.0 * (1 - np.exp(-300 / p.chiller_lag_s)) * np.exp(-1) + 0.5
    )
    # colder coolant shrinks the spindle; warmer grows it
    assert at(t1, fine.true_um, 7200) < at(t1, fine.true_um, 3600) + 1.0
    assert at(t1, fine.true_um, 14400) > at(t1, fine.true_um, 7200) + 3.0


def test_the_chiller_clamps_to_its_range_and_refuses_nan():
    plant = SpindlePlant(preset("mechanical-cooled"), seed=0)
    assert plant.set_chiller_setpoint_c(-40.0) == plant.params.chiller_min_c
    assert plant.set_chiller_setpoint_c(99.0) == plant.params.chiller_max_c
    with pytest.raises(ValueError):
        plant.set_chiller_setpoint_c(float("nan"))
    assert plant.chiller_setpoint_c == plant.params.chiller_max_c


def test_paper_000_preset_keeps_creeping_under_constant_cooling():
    plant = SpindlePlant(preset("mechanical-cooled"), seed=0)
    t = np.arange(0.0, 8 * 3600 + 1, 60.0)
    e = plant.run(t, np.full(t.size, 3000.0)).true_um
    assert 14.0 < e[90] < 18.0  # the paper's RITE (17 um) is reached after about 1.5 h
    assert e[-1] > e[240] + 2.0  # and constant cooling is still creeping at 4 h
