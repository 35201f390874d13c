"""Offset shaping: clamp, slew, deadband and the transient policy."""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from compensator import (
    CuttingSignal,
    Flag,
    NonFiniteInputError,
    OffsetShaper,
    ShaperConfig,
    TransientPolicy,
)

NO_TRANSIENT = TransientPolicy(enabled=False)


def run(shaper: OffsetShaper, samples):
    """samples: (elongation_um, speed_rpm, dt_s), fed to the shaper, which keeps its state.
    Returns outputs, results, final state."""
    outs, results = [], []
    for s, n, dt in samples:
        res = shaper.update(s, n, dt)
        outs.append(res.offset_um)
        results.append(res)
    return outs, results, shaper.state


def test_offset_is_minus_elongation_when_unconstrained():
    sh = OffsetShaper(ShaperConfig(max_rate_um_per_s=100, deadband_um=0, transient=NO_TRANSIENT))
    outs, res, _ = run(sh, [(5.0, 1000, 1.0), (7.5, 1000, 1.0)])
    assert outs == [-5.0, -7.5]
    assert all(r.write for r in res)


def test_clamp():
    sh = OffsetShaper(
        ShaperConfig(max_offset_um=20, max_rate_um_per_s=100, deadband_um=0, transient=NO_TRANSIENT)
    )
    outs, res, _ = run(sh, [(15, 0, 1.0), (35, 0, 1.0), (-50, 0, 1.0)])
    assert outs == [-15, -20, 20]
    assert Flag.CLAMPED in res[1].flags and Flag.CLAMPED in res[2].flags
    assert Flag.CLAMPED not in res[0].flags


def test_slew_limit_ramps_a_step():
    sh = OffsetShaper(ShaperConfig(max_rate_um_per_s=0.5, deadband_um=0, transient=NO_TRANSIENT))
    outs, res, _ = run(sh, [(10.0, 0, 1.0)] * 25)
    assert outs[:3] == pytest.approx([-0.5, -1.0, -1.5])
    assert outs[-1] == pytest.approx(-10.0)
    assert Flag.SLEW_LIMITED in res[0].flags
    assert Flag.SLEW_LIMITED not in res[-1].flags


def test_deadband_suppresses_small_changes_but_never_stalls():
    sh = OffsetShaper(ShaperConfig(max_rate_um_per_s=0.05, deadband_um=0.3, transient=NO_TRANSIENT))
    # below the deadband: nothing is written
    outs, res, _ = run(sh, [(0.2, 0, 1.0)] * 5)
    assert outs == [0.0] * 5 and not any(r.write for r in res)
    assert Flag.DEADBAND in res[0].flags
    # above it (the same shaper, continuing), the output keeps moving even though each slew
    # step (0.05) < deadband
    outs, res, _ = run(sh, [(1.0, 0, 1.0)] * 40)
    assert outs[-1] < -0.69 and all(r.write for r in res[:10])


def test_hold_mode_freezes_the_offset_during_a_transient_then_releases_smoothly():
    pol = TransientPolicy(
        mode="hold",
        window_s=30,
        speed_step_rpm=5000,
        speed_rate_rpm_per_s=2000,
        release_rate_um_per_s=0.2,
    )
    sh = OffsetShaper(ShaperConfig(max_rate_um_per_s=2.0, deadband_um=0, transient=pol))
    warm = [(30.0, 27000, 1.0)] * 60  # settle at -30
    drop = [(14.0, 12000, 1.0)] * 200  # elastic drop: 16 um at once
    outs, res, _ = run(sh, warm + drop)
    assert outs[59] == pytest.approx(-30.0)
    window = outs[60:90]
    assert all(o == pytest.approx(-30.0) for o in window)  # held
    assert all(Flag.TRANSIENT in r.flags for r in res[60:90])
    after = outs[91:]
    steps = [abs(b - a) for a, b in zip(outs[90:], after)]
    assert max(steps) <= 0.2 + 1e-12  # released at the release rate, not max rate
    assert any(Flag.RELEASING in r.flags for r in res[91:])
    assert outs[-1] == pytest.approx(-14.0)


def test_slow_mode_lengthens_the_target_update_cycle():
    pol = TransientPolicy(
        mode="slow",
        window_s=60,
        slow_period_s=20,
        speed_step_rpm=5000,
        speed_rate_rpm_per_s=2000,
        release_rate_um_per_s=1.0,
    )
    sh = OffsetShaper(ShaperConfig(max_rate_um_per_s=1.0, deadband_um=0, transient=pol))
    warm = [(30.0, 27000, 1.0)] * 40
    # during the window the prediction keeps falling; targets are latched every 20 s
    falling = [(14.0 - 0.05 * k, 12000, 1.0) for k in range(60)]
    _, res, _ = run(sh, warm + falling)
    window = res[40:100]
    latched = {round(r.desired_um, 6) for r in window}
    assert len(latched) > 10  # desired kept changing every sample ...
    outs = [r.offset_um for r in window]
    # ... but the output only started moving after the first slow period
    assert all(o == pytest.approx(-30.0) for o in outs[:20])
    assert outs[-1] > -30.0 + 10


def test_transient_detected_from_speed_rate_on_short_samples():
    pol = TransientPolicy(mode="hold", window_s=5, speed_step_rpm=20000, speed_rate_rpm_per_s=1000)
    sh = OffsetShaper(ShaperConfig(max_rate_um_per_s=10, deadband_um=0, transient=pol))
    _, res, _ = run(sh, [(1.0, 0, 0.1), (1.0, 500, 0.1)])  # 5000 rpm/s, a 500 rpm step
    assert Flag.TRANSIENT in res[1].flags


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_prediction_raises_and_never_reaches_the_output(bad):
    sh = OffsetShaper()
    with pytest.raises(NonFiniteInputError):
        sh.update(bad, 0, 1.0)
    assert sh.output_um == 0.0


def test_config_rejects_extra_keys_and_inconsistent_limits():
    with pytest.raises(ValueError):
        ShaperConfig(max_offset_um=10, bogus=1)  # type: ignore[call-arg]
    with pytest.raises(ValueError):
        ShaperConfig(max_offset_um=10, deadband_um=10)
    with pytest.raises(ValueError):
        ShaperConfig(max_rate_um_per_s=1, transient=TransientPolicy(release_rate_um_per_s=2))


samples = st.lists(
    st.tuples(
        st.floats(-500, 500, allow_nan=False),
        st.floats(-30000, 30000, allow_nan=False),
        st.floats(0, 30, allow_nan=False),
    ),
    min_size=1,
    max_size=80,
)


@settings(max_examples=300, deadline=None)
@given(
    samples=samples,
    clamp=st.floats(1, 200),
    rate=st.floats(0.01, 20),
    fast=st.floats(1, 5),
    deadband=st.floats(0, 0.9),
    mode=st.sampled_from(["dual-slew", "hold", "slow"]),
    enabled=st.booleans(),
    start=st.floats(-1000, 1000),
    signals=st.lists(st.sampled_from([None, True, False]), min_size=80, max_size=80),
)
def test_invariants_clamp_slew_deadband_finite(
    samples, clamp, rate, fast, deadband, mode, enabled, start, signals
):
    cfg = ShaperConfig(
        max_offset_um=clamp,
        max_rate_um_per_s=rate,
        not_cutting_rate_um_per_s=rate * fast,
        deadband_um=deadband,
        transient=TransientPolicy(enabled=enabled, mode=mode, window_s=20, slow_period_s=7),
        cutting=CuttingSignal(settle_s=3.0),
    )
    sh = OffsetShaper(cfg, start)
    assert sh.output_um == start  # what the controller holds, even beyond the clamp
    prev = sh.output_um
    for (s, n, dt), signal in zip(samples, signals):
        res = sh.update(s, n, dt, signal)
        state = sh.state
        y = res.offset_um
        assert math.isfinite(y)
        assert abs(y) <= clamp  # never a value beyond the clamp, even from one held beyond it
        if abs(prev) > clamp:  # straight to the clamp, on the controller's side, then slewed
            lim = cfg.rate_limit_um_per_s * dt * (1 + 1e-12) + 1e-12
            assert Flag.CLAMPED in res.flags
            assert y == math.copysign(clamp, prev) or abs(y - prev) <= lim
            prev = y
            continue
        assert abs(y - prev) <= cfg.rate_limit_um_per_s * dt * (1 + 1e-12) + 1e-12
        if signal is not None:
            assert res.cutting is signal  # the controller's word wins
        if (
            res.cutting or cfg.policy != "dual-slew"
        ):  # while cutting: never faster than the slow limit
            assert abs(y - prev) <= rate * dt * (1 + 1e-12) + 1e-12
        assert res.write == (y != prev)
        if not res.write:
            assert y == prev
        # a write never moves by less than needed to cross the deadband, unless it lands on target
        if res.write and abs(y - prev) < deadband:
            assert Flag.SLEW_LIMITED in res.flags or y == pytest.approx(state.target_um)
        prev = y


@settings(max_examples=100, deadline=None)
@given(target=st.floats(-80, 80), rate=st.floats(0.1, 5), deadband=st.floats(0, 0.5))
def test_converges_to_within_deadband_of_a_steady_target(target, rate, deadband):
    sh = OffsetShaper(
        ShaperConfig(max_rate_um_per_s=rate, deadband_um=deadband, transient=NO_TRANSIENT)
    )
    outs, _, _ = run(sh, [(target, 0, 1.0)] * int(100 / rate + 5))
    assert abs(outs[-1] - (-target)) <= deadband + 1e-9


def test_hold_moves_on_from_what_the_controller_holds_through_the_slew_limit():
    sh = OffsetShaper(
        ShaperConfig(max_offset_um=50, max_rate_um_per_s=1.0, deadband_um=0, transient=NO_TRANSIENT)
    )
    run(sh, [(10.0, 0, 1.0)] * 20)
    assert sh.output_um == pytest.approx(-10.0)
    sh.hold(0.0)  # the controller was reset: it holds 0, not -10
    assert sh.output_um == 0.0
    outs, _, _ = run(sh, [(10.0, 0, 1.0)] * 3)
    assert outs == pytest.approx([-1.0, -2.0, -3.0])
    sh.hold(80.0)  # an outside write beyond the clamp: never written back, straight to the clamp
    assert sh.output_um == 80.0
    outs, _, _ = run(sh, [(10.0, 0, 1.0)] * 40)
    assert outs[:3] == pytest.approx([50.0, 49.0, 48.0])  # the clamp, and the slew limit from there
    assert all(b < a for a, b in itertools.pairwise(outs))
    outs, _, _ = run(sh, [(10.0, 0, 1.0)] * 60)
    assert outs[-1] == pytest.approx(-10.0)  # and on to the model's value
    for absurd in (1e6, 1e308, -1e308):  # far beyond: one step to the clamp, whatever the float
        sh.hold(absurd)
        outs, _, _ = run(sh, [(10.0, 0, 1.0)])
        assert abs(outs[0]) <= 50.0 and outs[0] * absurd > 0


def test_shape_series_is_the_runtime_shaper_over_a_log():
    import numpy as np

    from compensator.shaping import shape_series

    cfg = ShaperConfig(max_rate_um_per_s=0.5, deadband_um=0, transient=NO_TRANSIENT)
    t = np.arange(30.0)
    s = np.where(t < 10, 0.0, 5.0)
    series = shape_series(cfg, t, np.zeros_like(t), s)
    out, flags = series.offset_um, series.flags
    expected, _, _ = run(
        OffsetShaper(cfg), [(float(v), 0, 1.0 if k else 0.0) for k, v in enumerate(s)]
    )
    assert out.tolist() == pytest.approx(expected)
    assert out[-1] == pytest.approx(-5.0) and out[12] == pytest.approx(-1.5)
    assert int(flags[10]) & int(Flag.SLEW_LIMITED)
    assert (series.rate_um_per_s == 0.5).all() and not series.cutting.any()  # at rest: not cutting


# -- dual slew: fast while the tool is clear of the part, slow while it cuts (issue 18) -----------


def dual(**kw) -> ShaperConfig:
    kw.setdefault("cutting", CuttingSignal(settle_s=2.0))
    return ShaperConfig(
        max_rate_um_per_s=1.0, not_cutting_rate_um_per_s=50.0, deadband_um=0.0, **kw
    )


def test_dual_slew_lands_the_elastic_step_during_the_run_up_and_creeps_while_cutting():
    sh = OffsetShaper(dual(), -20.0)
    # the spindle has run at 22 500 rpm (settled, cutting) and the model says 20 um
    outs, res, _ = run(sh, [(20.0, 22500, 1.0)] * 5)
    assert all(r.cutting and r.state == "cutting" for r in res)
    # a speed change to 12 000 rpm over 3 s: the elastic part drops by 12 um as it runs down
    ramp = [(17.0, 19000, 1.0), (12.0, 15500, 1.0), (8.0, 12000, 1.0)]
    outs, res, _ = run(sh, ramp)
    assert outs == pytest.approx([-17.0, -12.0, -8.0])  # followed at once: not cutting
    assert not any(r.cutting for r in res) and all(r.rate_um_per_s == 50.0 for r in res)
    assert all(r.state == "clear" for r in res)
    # held at 12 000: cutting again after settle_s; a further model change creeps at 1 um/s
    outs, res, _ = run(sh, [(8.0, 12000, 1.0)] * 2 + [(11.0, 12000, 1.0)] * 4)
    assert [r.cutting for r in res] == [False, True, True, True, True, True]
    assert outs[2:] == pytest.approx([-9.0, -10.0, -11.0, -11.0])
    assert all(Flag.SLEW_LIMITED in r.flags for r in res[2:4])


def test_a_controller_signal_overrides_the_inference_both_ways():
    sh = OffsetShaper(dual(), 0.0)
    _outs, res, _ = run(sh, [(0.0, 0, 1.0)])
    # the controller says cutting while the speed jumps: slow, whatever the speed does
    res = [sh.update(10.0, 20000, 1.0, True) for _ in range(3)]
    assert [r.offset_um for r in res] == pytest.approx([-1.0, -2.0, -3.0])
    assert all(r.cutting for r in res)
    # ... and not cutting at a steady speed (a tool change at speed): fast
    r = sh.update(10.0, 20000, 1.0, False)
    assert r.offset_um == pytest.approx(-10.0) and not r.cutting and r.rate_um_per_s == 50.0


def test_inference_at_rest_at_start_and_within_the_speed_band():
    sig = CuttingSignal(settle_s=2.0, speed_tolerance_rpm=30.0, speed_tolerance_pct=1.0)
    sh = OffsetShaper(dual(cutting=sig), 0.0)
    # a start with the spindle turning: it may be cutting already, so slow
    r = sh.update(5.0, 10000, 1.0)
    assert r.cutting and r.offset_um == pytest.approx(-1.0)
    # jitter within 1 % of the speed does not count as a change
    res = [sh.update(5.0, n, 1.0) for n in (10050, 9950, 10080)]
    assert all(r.cutting for r in res)
    # beyond the band it does; at rest the tool never cuts
    assert not sh.update(5.0, 10500, 1.0).cutting
    res = [sh.update(5.0, 0, 1.0) for _ in range(10)]
    assert not any(r.cutting for r in res)
    assert not OffsetShaper(dual(cutting=sig)).update(1.0, 0.0, 1.0).cutting


def test_the_longer_cycle_and_slow_slew_policies_stay_selectable():
    base = dual()
    assert base.policy == "dual-slew" and base.rate_limit_um_per_s == 50.0
    slow = base.with_policy("slow-slew")
    assert slow.policy == "slow-slew" and slow.rate_limit_um_per_s == 1.0
    longer = base.with_policy("longer-cycle")
    assert longer.transient.mode == "slow" and longer.policy == "longer-cycle"
    r = OffsetShaper(slow, 0.0).update(10.0, 0.0, 1.0)  # at rest, not cutting: still slow
    assert r.offset_um == pytest.approx(-1.0) and not r.cutting and r.state == "tracking"
    with pytest.raises(ValueError):
        base.with_policy("fast")


def test_the_not_cutting_limit_defaults_to_50_and_never_below_the_cutting_one():
    assert ShaperConfig().fast_rate_um_per_s == 50.0
    assert ShaperConfig(max_rate_um_per_s=100.0).fast_rate_um_per_s == 100.0
    with pytest.raises(ValueError, match="not_cutting_rate_um_per_s"):
        ShaperConfig(max_rate_um_per_s=2.0, not_cutting_rate_um_per_s=1.0)
    with pytest.raises(ValueError):
        ShaperConfig(cutting=CuttingSignal(signal="sometimes"))  # type: ignore[arg-type]
