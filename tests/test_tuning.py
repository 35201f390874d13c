"""Controller tuning from a step response (calibration.tuning): the models' exact responses,
their fit, SIMC, the PID forms, the closed loop and its metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from calibration import tuning as tu
from compensator.cooling_law import PidGains
from compensator.errors import CalibrationError, ModelError


def _steps(time_s: np.ndarray) -> np.ndarray:
    """Several steps, up and down: 0, then 1 from 300 s, -0.5 from 2400 s, 0.5 from 4500 s."""
    return np.select([time_s < 300, time_s < 2400, time_s < 4500], [0.0, 1.0, -0.5], 0.5)


# --- the models' responses ---------------------------------------------------------------------


def test_fopdt_step_response_is_the_analytic_curve():
    m = tu.Fopdt(gain=2.0, tau_s=100.0, delay_s=30.0)
    t = np.arange(0.0, 600.0, 7.0)
    y = m.response(t, np.ones(t.size))
    exact = np.where(t > 30.0, 2.0 * (1 - np.exp(-(t - 30.0) / 100.0)), 0.0)
    assert np.max(np.abs(y - exact)) < 1e-12


@pytest.mark.parametrize("tau2_s", [40.0, 100.0 * (1 - 1e-9), 100.0])
def test_sopdt_step_response_matches_scipy_including_equal_time_constants(tau2_s):
    m = tu.Sopdt(gain=1.5, tau_s=100.0, tau2_s=tau2_s, delay_s=0.0)
    t = np.linspace(0.0, 800.0, 201)
    _, ref = signal.step(([1.5], np.polymul([100.0, 1.0], [tau2_s, 1.0])), T=t)
    assert np.max(np.abs(m.step_response(t) - ref)) < 1e-9


def test_response_is_exact_for_a_delay_between_samples():
    # the held input shifted by a delay that is no multiple of the sample period
    m = tu.Sopdt(gain=1.0, tau_s=50.0, tau2_s=20.0, delay_s=13.0)
    t = np.arange(0.0, 400.0, 10.0)
    u = np.where(t >= 100.0, 1.0, 0.0) - np.where(t >= 250.0, 2.0, 0.0)
    y = m.response(t, u)
    exact = m.step_response(t - 100.0) - 2.0 * m.step_response(t - 250.0)
    assert np.max(np.abs(y - exact)) < 1e-12
    assert np.all(y[t <= 113.0] == 0.0)


def test_model_values_are_checked_and_frozen():
    with pytest.raises(ModelError, match="tau_s"):
        tu.Fopdt(1.0, 0.0, 1.0)
    with pytest.raises(ModelError, match="delay_s"):
        tu.Fopdt(1.0, 10.0, -1.0)
    with pytest.raises(ModelError, match="tau2_s"):
        tu.Sopdt(1.0, 10.0, 20.0, 0.0)  # tau1 is the dominant one
    with pytest.raises(ModelError, match="gain"):
        tu.Sopdt(math.nan, 10.0, 5.0, 0.0)
    with pytest.raises(AttributeError):
        tu.Fopdt(1.0, 10.0, 1.0).gain = 2.0  # type: ignore[misc]


# --- the fit -----------------------------------------------------------------------------------


def test_fit_recovers_a_fopdt_from_one_noisy_step():
    true = tu.Fopdt(gain=2.0, tau_s=600.0, delay_s=120.0)
    t = np.arange(0.0, 3600.0, 10.0)
    u = 3.0 + np.where(t >= 300.0, 1.0, 0.0)  # u and y relative to their start
    rng = np.random.default_rng(1)
    y = 5.0 + true.response(t, u - 3.0) + rng.normal(0.0, 0.02, t.size)
    fit = tu.fit_step_model(t, u, y, order=1)
    assert isinstance(fit, tu.Fopdt)
    # over 20 noise draws: gain within 0.5 %, tau 1.2 %, delay 3.5 %
    assert fit.gain == pytest.approx(2.0, rel=0.02)
    assert fit.tau_s == pytest.approx(600.0, rel=0.03)
    assert fit.delay_s == pytest.approx(120.0, abs=8.0)
    assert fit.rms == pytest.approx(0.02, rel=0.2)  # the noise is all that is left


def test_fit_recovers_a_sopdt_from_several_steps():
    true = tu.Sopdt(gain=1.5, tau_s=900.0, tau2_s=200.0, delay_s=60.0)
    t = np.arange(0.0, 7200.0, 10.0)
    u = _steps(t)
    rng = np.random.default_rng(0)
    fit = tu.fit_step_model(t, u, true.response(t, u) + rng.normal(0.0, 0.01, t.size))
    assert isinstance(fit, tu.Sopdt)
    # over 20 noise draws: gain within 0.8 %, tau1 1.5 %, tau2 4.4 %, delay 5.5 s (tau2 and the
    # delay trade against each other)
    assert fit.gain == pytest.approx(1.5, rel=0.02)
    assert fit.tau_s == pytest.approx(900.0, rel=0.03)
    assert fit.tau2_s == pytest.approx(200.0, rel=0.08)
    assert fit.delay_s == pytest.approx(60.0, abs=8.0)
    assert fit.rms < 0.012


def test_a_second_order_fit_of_a_first_order_record_collapses_tau2():
    true = tu.Fopdt(gain=-1.0, tau_s=300.0, delay_s=40.0)  # a negative gain is a gain
    t = np.arange(0.0, 2400.0, 5.0)
    u = np.where(t >= 100.0, 2.0, 0.0)
    fit = tu.fit_step_model(t, u, true.response(t, u))
    assert fit.gain == pytest.approx(-1.0, rel=1e-3)
    assert fit.tau_s == pytest.approx(300.0, rel=0.01)
    assert fit.tau2_s < 3.0 and fit.tau2_s + fit.delay_s == pytest.approx(40.0, abs=2.0)


def test_fit_refuses_what_it_cannot_fit():
    t = np.arange(50.0)
    with pytest.raises(CalibrationError, match="never changes"):
        tu.fit_step_model(t, np.ones(50), t)
    with pytest.raises(CalibrationError, match="order"):
        tu.fit_step_model(t, t, t, order=3)
    with pytest.raises(CalibrationError, match="y has 49 samples"):
        tu.fit_step_model(t, t, t[:-1])
    with pytest.raises(CalibrationError, match="u at sample 3 is nan"):
        tu.fit_step_model(t, np.r_[0, 0, 0, np.nan, np.ones(46)], t)
    with pytest.raises(CalibrationError, match="does not increase"):
        tu.fit_step_model(np.r_[t[:10], t[9:-1]], t, t)
    with pytest.raises(CalibrationError, match="fewer than 4"):
        tu.fit_step_model(t, np.r_[np.zeros(48), 1.0, 1.0], t)


# --- SIMC and the PID forms --------------------------------------------------------------------


def test_simc_gives_skogestads_numbers():
    # Skogestad (2003): k = 1, tau1 = 1, theta = 0.1, tau_c = theta -> Kc = 5, tauI = 0.8
    pi = tu.simc(tu.Fopdt(1.0, 1.0, 0.1))
    assert (pi.kc, pi.ti_s, pi.td_s) == pytest.approx((5.0, 0.8, 0.0))
    assert "tau_c = theta" in pi.rule
    # a delay-dominant process: tauI = tau1
    slow = tu.simc(tu.Fopdt(2.0, 1.0, 1.0))
    assert (slow.kc, slow.ti_s) == pytest.approx((0.25, 1.0))
    # SOPDT: the same with tauD = tau2 (series form)
    pid = tu.simc(tu.Sopdt(1.0, 1.0, 0.3, 0.1))
    assert (pid.kc, pid.ti_s, pid.td_s) == pytest.approx((5.0, 0.8, 0.3))
    # an explicit tau_c
    soft = tu.simc(tu.Fopdt(1.0, 1.0, 0.1), tau_c_s=0.4)
    assert (soft.kc, soft.ti_s) == pytest.approx((2.0, 1.0))


def test_simc_floors_tau_c_where_the_delay_vanishes():
    pi = tu.simc(tu.Fopdt(0.5, 100.0, 0.0))
    # tau_c = tau1/10 = 10 s: Kc = 100/(0.5*10), tauI = min(100, 40)
    assert (pi.kc, pi.ti_s) == pytest.approx((20.0, 40.0))
    assert "floor" in pi.rule
    with pytest.raises(CalibrationError, match="tau_c_s"):
        tu.simc(tu.Fopdt(1.0, 1.0, 0.0), tau_c_s=0.0)
    with pytest.raises(CalibrationError, match="gain is 0"):
        tu.simc(tu.Fopdt(0.0, 1.0, 0.1))


def test_series_to_parallel_and_discrete():
    tuning = tu.PidTuning(kc=5.0, ti_s=0.8, td_s=0.3)
    g = tuning.parallel()
    # kc' = kc(1 + td/ti), ti' = ti + td, td' = ti*td/(ti + td)
    kc_, ti_, td_ = 5.0 * (1 + 0.3 / 0.8), 0.8 + 0.3, 0.8 * 0.3 / 1.1
    assert (g.kp, g.ki_per_s, g.kd_s) == pytest.approx((kc_, kc_ / ti_, kc_ * td_))
    assert (g.kp, g.ki_per_s, g.kd_s) == pytest.approx((6.875, 6.25, 1.5))
    d = tuning.discrete(0.01)
    assert (d.kp, d.ki, d.kd, d.dt_s) == pytest.approx((6.875, 0.0625, 150.0, 0.01))
    back = d.continuous()
    assert (back.kp, back.ki_per_s, back.kd_s) == pytest.approx((g.kp, g.ki_per_s, g.kd_s))
    # no integral action
    pd = tu.PidTuning(kc=2.0, ti_s=math.inf, td_s=4.0).parallel()
    assert (pd.kp, pd.ki_per_s, pd.kd_s) == (2.0, 0.0, 8.0)


def test_paper_gains():
    g = tu.paper_tuning()
    assert isinstance(g, PidGains)  # the cooling law's own gains
    assert (g.kp, g.ki_per_s, g.kd_s) == (2.0, 0.0, 50.0)
    assert "paper 000" in g.source
    d = tu.discrete_gains(g, 1.0)
    assert (d.kp, d.ki, d.kd) == (2.0, 0.0, 50.0)
    assert tu.discrete_gains(g, 0.5).kd == 100.0  # the same derivative action at twice the rate
    assert tu.DiscretePid(2.0, 0.0, 50.0, 1.0).continuous() == PidGains(kp=2.0, kd_s=50.0)


def test_a_negative_plant_gain_gives_gains_the_cooling_loop_refuses():
    tuning = tu.simc(tu.Fopdt(-1.0, 1.0, 0.1))
    assert tuning.kc == pytest.approx(-5.0)
    with pytest.raises(CalibrationError, match="negative plant gain"):
        tuning.parallel()


# --- the closed loop ---------------------------------------------------------------------------


@pytest.mark.parametrize(("tau_s", "delay_s"), [(1.0, 0.1), (10.0, 0.5), (1.0, 1.0)])
def test_simc_settles_a_fopdt_with_the_overshoot_simc_predicts(tau_s, delay_s):
    model = tu.Fopdt(2.0, tau_s, delay_s)
    t, y = tu.closed_loop_step(
        model, tu.simc(model), dt_s=delay_s / 20, duration_s=5 * tau_s + 40 * delay_s
    )
    m = tu.step_metrics(t, y, 1.0)
    # SIMC's tight tuning: about 10 % setpoint overshoot (4-10 % measured here)
    assert 2.0 < m.overshoot_pct < 15.0
    assert m.settling_s is not None and m.settling_s < 0.8 * t[-1]
    assert y[-1] == pytest.approx(1.0, abs=0.005)


def test_the_loop_simulation_is_the_models_response_to_the_controllers_output():
    model = tu.Sopdt(1.0, 1.0, 0.3, 0.1)
    t, y, u = tu._simulate_loop(model, tu.simc(model), dt_s=0.013, duration_s=5.0)
    assert np.max(np.abs(model.response(t, u) - y)) < 1e-10
    assert u[0] == pytest.approx(5.0 * (1 + 0.3 / 0.8) + 6.25 * 0.013 + 1.5 / 0.013)  # the kick


def test_limits_clamp_the_output_without_winding_up():
    model = tu.Fopdt(1.0, 1.0, 0.1)
    gains = tu.simc(model)
    t, y, u = tu._simulate_loop(model, gains, dt_s=0.01, duration_s=10.0, u_limits=(-1.5, 1.5))
    assert u.min() >= -1.5 and u.max() <= 1.5
    limited = tu.step_metrics(t, y, 1.0)
    assert limited.settling_s is not None and limited.overshoot_pct < 15.0
    with pytest.raises(CalibrationError, match="u_limits"):
        tu.closed_loop_step(model, gains, dt_s=0.01, duration_s=1.0, u_limits=(1.0, 1.0))
    with pytest.raises(CalibrationError, match="dt_s"):
        tu.closed_loop_step(model, gains, dt_s=0.0, duration_s=1.0)


def test_step_metrics_of_a_first_order_response():
    t = np.arange(0.0, 10.0, 0.001)
    m = tu.step_metrics(t, -2.0 * -np.expm1(-t), -2.0)  # a negative target is mirrored
    assert m.overshoot_pct == 0.0
    assert m.rise_s == pytest.approx(math.log(9.0), abs=1e-3)
    assert m.settling_s == pytest.approx(math.log(50.0), abs=2e-3)
    assert m.iae == pytest.approx(2.0 * (1 - math.exp(-t[-1])), rel=1e-4)
    over = tu.step_metrics(t, 1.0 + 0.2 * np.sin(t) * np.exp(-t) - np.exp(-5 * t), 1.0)
    assert over.overshoot_pct > 0.0
    assert tu.step_metrics(t, 0.5 * np.ones(t.size), 1.0).settling_s is None
    with pytest.raises(CalibrationError, match="target"):
        tu.step_metrics(t, t, 0.0)
