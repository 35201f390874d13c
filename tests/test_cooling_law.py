"""The pure cooling controller: start rule, bumpless hand-over, limits, rate, anti-windup, holds."""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from compensator.cooling_law import CoolingLaw, CoolingState, PidGains, dew_point_c
from compensator.errors import ConfigError, NonFiniteInputError


def law(**kw):
    cfg = {
        "rite_um": 17.0,
        "preheat_c": 16.0,
        "min_c": 10.0,
        "max_c": 24.0,
        "rate_k_per_min": 1.0,
        "resolution_c": 0.1,
        "derivative_filter_s": 5.0,
    }
    cfg.update(kw)
    return CoolingLaw(**cfg)


def run(cl, estimates, dt=1.0, state=None, **kw):
    s = state or cl.initial()
    out = []
    for e in estimates:
        s = cl.step(s, e, dt, **kw)
        out.append(s)
    return out


def test_preheat_until_rite_then_closed_without_a_bump():
    cl = law(gains=PidGains(kp=2.0, ki_per_s=0.001, kd_s=50.0))
    states = run(cl, [10.0 + 0.01 * k for k in range(700)] + [17.0 + 0.001 * k for k in range(100)])
    phases = [s.phase for s in states]
    first = phases.index("closed")
    assert all(p == "preheat" for p in phases[:first])
    assert all(s.setpoint_c == 16.0 for s in states[:first])
    # Ê crossed RITE at sample 700: the loop closes there, and the first command is the one in force
    assert first == 700
    assert states[first].setpoint_c == pytest.approx(16.0, abs=0.05)
    # above RITE the error is negative: the command goes colder, one count at a time
    later = [s.setpoint_c for s in states[first:]]
    assert later[-1] < 16.0
    assert max(abs(a - b) for a, b in itertools.pairwise(later)) <= 0.1 + 1e-9


def test_immediate_start_and_a_long_rest_returns_to_preheat():
    cl = law(start="immediate", idle_release_s=600.0)
    s = run(cl, [5.0])[-1]
    assert s.phase == "closed"  # closes at once, far below RITE
    states = run(cl, [5.0] * 700, state=s, running=False)
    assert states[598].phase == "closed" and states[-1].phase == "closed"  # immediate closes again
    cl2 = law(idle_release_s=600.0)
    s = run(cl2, [18.0])[-1]
    assert s.phase == "closed"
    states = run(cl2, [16.0] * 700, state=s, running=False)
    assert states[-1].phase == "preheat"


def test_limits_and_rate_limit_hold_whatever_the_estimate():
    cl = law(gains=PidGains(kp=50.0, ki_per_s=1.0, kd_s=0.0))
    states = run(cl, [17.0] + [60.0] * 2000)  # far above RITE: wants far below min
    values = [s.setpoint_c for s in states]
    assert min(values) == pytest.approx(10.0)
    assert all(10.0 - 1e-9 <= v <= 24.0 + 1e-9 for v in values)
    # 6 K at 1 K/min: not before 6 min (one count of rounding aside)
    reached = next(k for k, v in enumerate(values) if v <= 10.0 + 1e-9)
    assert reached >= 6 * 60 - 6


def test_anti_windup_recovers_at_once_when_the_error_turns():
    """Back-calculation keeps the integral near what the limits allow: after 2 h pinned at the
    floor, the command leaves it within minutes of the error changing sign."""
    gains = PidGains(kp=1.0, ki_per_s=0.01, kd_s=0.0)
    wound = law(gains=gains, tracking_s=None)
    s = run(wound, [17.0] + [25.0] * 7200)[-1]
    assert s.setpoint_c == pytest.approx(10.0)
    assert s.bias_c > 10.0 - 8.0 * 1.0 - 1.0  # not wound far below: ~ floor + kp*8
    after = run(wound, [15.0] * 900, state=s)
    left = next(k for k, x in enumerate(after) if x.setpoint_c > 10.0 + 1e-9)
    assert left < 60  # a wound-up integral would need ki*|e|... hours
    # the same controller without back-calculation (a tracking time so long it does nothing)
    naive = law(gains=gains, tracking_s=1e12)
    s2 = run(naive, [17.0] + [25.0] * 7200)[-1]
    assert s2.bias_c < -100.0
    stuck = run(naive, [15.0] * 900, state=s2)
    assert all(x.setpoint_c == pytest.approx(10.0) for x in stuck)


def test_derivative_filter_damps_a_noisy_estimate():
    import numpy as np

    rng = np.random.default_rng(1)
    noisy = 17.0 + 0.05 * rng.standard_normal(600)
    gains = PidGains.paper()
    raw = run(
        law(gains=gains, derivative_filter_s=0.0, rate_k_per_min=1000.0, resolution_c=0.0),
        [17.0, *noisy],
    )
    filt = run(
        law(gains=gains, derivative_filter_s=30.0, rate_k_per_min=1000.0, resolution_c=0.0),
        [17.0, *noisy],
    )
    spread = lambda xs: float(np.std([x.setpoint_c for x in xs[100:]]))
    assert spread(filt) < spread(raw) / 4


def test_no_estimate_holds_then_goes_to_the_constant_and_resumes_bumplessly():
    cl = law(hold_s=120.0)
    s = run(cl, [17.0] + [19.0] * 600)[-1]
    assert s.phase == "closed" and s.setpoint_c < 16.0
    before = s.setpoint_c
    held = run(cl, [None] * 119, state=s)
    assert all(h.setpoint_c == before and h.phase == "hold" for h in held)
    back = run(cl, [19.0], state=held[-1])[-1]
    assert back.phase == "closed" and abs(back.setpoint_c - before) <= 0.1 + 1e-9
    gone = run(cl, [math.nan] * 600, state=s)
    assert gone[-1].setpoint_c == pytest.approx(16.0)  # the constant after hold_s, ramped
    assert all(abs(a.setpoint_c - b.setpoint_c) <= 0.1 + 1e-9 for a, b in itertools.pairwise(gone))


def test_dew_point_guard_wins_over_the_rate():
    assert dew_point_c(18.0, 50.0) == pytest.approx(7.4, abs=0.2)  # tables: 7.4 degC
    assert dew_point_c(25.0, 100.0) == pytest.approx(25.0, abs=0.01)
    with pytest.raises(NonFiniteInputError):
        dew_point_c(20.0, 0.0)
    cl = law(min_c=5.0, dew_margin_k=2.0)
    s = run(cl, [17.0] + [40.0] * 900)[-1]
    assert s.setpoint_c == pytest.approx(5.0)
    s = cl.step(s, 40.0, 1.0, dew_point_c=12.0)  # humid shop: jumps up at once
    assert s.setpoint_c == pytest.approx(14.0)
    with pytest.raises(ValidationError, match="outside the limits"):
        law(dew_point_c=15.0)  # preheat at 16 is below 15 + 2


def test_bad_settings_and_steps_are_refused():
    with pytest.raises(ValidationError):
        law(min_c=30.0)
    with pytest.raises(ValidationError):
        law(rite_um=math.inf)
    with pytest.raises(ValidationError):
        law(surprise=1)
    with pytest.raises(NonFiniteInputError):
        law().step(law().initial(), 17.0, 0.0)
    with pytest.raises(ConfigError):
        CoolingState.from_dict({"phase": "closed"})
    s = run(law(), [18.0] * 3)[-1]
    assert CoolingState.from_dict(s.to_dict()).setpoint_c == s.setpoint_c


estimates = st.one_of(
    st.none(),
    st.sampled_from([math.nan, math.inf, -math.inf]),
    st.floats(-1e6, 1e6, allow_nan=False),
)


@settings(max_examples=200, deadline=None)
@given(
    kp=st.floats(0, 1e3),
    ki=st.floats(0, 10),
    kd=st.floats(0, 1e4),
    lo=st.floats(-20, 30),
    span=st.floats(0.5, 30),
    rate=st.floats(0.01, 20),
    res=st.sampled_from([0.0, 0.01, 0.1, 0.5]),
    seq=st.lists(
        st.tuples(
            estimates, st.floats(0.05, 600), st.booleans(), st.one_of(st.none(), st.floats(-30, 40))
        ),
        min_size=1,
        max_size=60,
    ),
)
# a denormal kp makes the back-calculation's tracking time kp/ki underflow to zero
@example(
    kp=5e-324,
    ki=2.0,
    kd=0.0,
    lo=0.0,
    span=1.0,
    rate=1.0,
    res=0.0,
    seq=[(10.0, 1.0, False, None), (0.0, 1.0, False, None)],
)
def test_never_a_set_point_outside_the_limits_or_faster_than_the_rate(
    kp, ki, kd, lo, span, rate, res, seq
):
    cl = CoolingLaw(
        rite_um=10.0,
        preheat_c=lo + span / 2,
        min_c=lo,
        max_c=lo + span,
        gains=PidGains(kp=kp, ki_per_s=ki, kd_s=kd),
        rate_k_per_min=rate,
        resolution_c=res,
        dew_margin_k=1.0,
        hold_s=30.0,
    )
    s = cl.initial()
    prev = s.setpoint_c
    for est, dt, running, dew in seq:
        s = cl.step(s, est, dt, running=running, dew_point_c=dew)
        low, high = cl.limits_c(dew)
        assert math.isfinite(s.setpoint_c)
        assert low - 1e-9 <= s.setpoint_c <= high + 1e-9
        if dew is None or cl.floor_c(dew) <= prev:  # the dew point may force a jump up
            assert abs(s.setpoint_c - prev) <= rate / 60 * dt + res + 1e-9
        prev = s.setpoint_c
