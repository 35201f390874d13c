"""The state-space model's free run (``simulate_um``, a block at a time) is its own per-cycle
``step()`` at every sample: at the usual step and at any other, across gaps and block edges,
with inputs outside their range, a measured start, fast states and drives near the float
range; and it refuses what it refused before (a non-finite input, time going backwards).
Correctness only: the speed is measured by ``bench/bench_simulate.py``."""

from __future__ import annotations

import math

import numpy as np
import pytest

from compensator.errors import ModelError, NonFiniteInputError
from compensator.statespace import _BLOCK, _FEW_ODD, Extrapolation, InputChannel, StateSpaceModel

NAMES = ("a_c", "b_c", "c_c")


def model(
    taus: tuple[float, ...] = (300.0, 1800.0, 7200.0),
    policy: Extrapolation = "linear",
) -> StateSpaceModel:
    rng = np.random.default_rng(5)
    width = 2 + len(NAMES)
    fallback = StateSpaceModel(
        fitted_dt_s=1.0,
        speed_range_rpm=(0.0, 20000.0),
        taus_s=(600.0,),
        drive_um=((1.0, 0.1),),
        feedthrough_um=(0.1, 0.0),
        max_measured_um=60.0,
    )
    return StateSpaceModel(
        fitted_dt_s=1.0,
        speed_range_rpm=(0.0, 20000.0),
        taus_s=taus,
        drive_um=tuple(tuple(rng.normal(0, 0.3, width)) for _ in taus),
        feedthrough_um=tuple(rng.normal(0, 0.05, width)),
        offset_um=0.7,
        max_measured_um=60.0,
        inputs=tuple(
            InputChannel(
                name=n,
                unit="degC",
                reference=22.0,
                trained_range=(15.0, 30.0),
                valid_range=(5.0, 40.0),
            )
            for n in NAMES
        ),
        fallback=fallback,
        extrapolation=policy,
    )


def log(t: np.ndarray, seed: int = 1) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Speed steps over the whole range and both directions; temperatures that wander, and
    leave their valid range (held at its end) for a while."""
    rng = np.random.default_rng(seed)
    speed = np.repeat(rng.uniform(-25000, 25000, t.size // 700 + 1), 700)[: t.size]
    temps = {n: 22.0 + np.cumsum(rng.normal(0, 0.25, t.size)) for n in NAMES}
    third = t.size // 3
    temps["a_c"][third : third + 300] = 47.0  # past the valid range: held at its end
    temps["b_c"][third - 200 : third + 100] = 1.0
    return speed, temps


def stepped(
    m: StateSpaceModel,
    speed: np.ndarray,
    t: np.ndarray,
    temps: dict[str, np.ndarray],
    initial_um: float | None = None,
) -> np.ndarray:
    """The runtime's cycle path: start() at the first sample, then step() at every other."""
    state = m.start(initial_um, float(speed[0]), {n: float(v[0]) for n, v in temps.items()})
    out = [state.elongation_um]
    for k in range(1, t.size):
        inputs = {n: float(v[k]) for n, v in temps.items()}
        state = m.step(state, float(speed[k]), float(t[k] - t[k - 1]), inputs)
        out.append(state.elongation_um)
    return np.array(out)


def same(free: np.ndarray, steps: np.ndarray) -> None:
    """Agreement to 1e-9 of the run's scale: both are exact, only rounding differs."""
    scale = float(np.max(np.abs(steps)))
    assert scale > 0
    np.testing.assert_allclose(free, steps, rtol=0, atol=1e-9 * scale)


def regular_with_gaps(n: int) -> np.ndarray:
    dt = np.ones(n - 1)
    dt[[100, _BLOCK - 1, n - 2000]] = [900.0, 40.0, 3 * 86400.0]  # one gap on a block edge
    return 1.7e9 + np.concatenate([[0.0], np.cumsum(dt)])


def scattered_odd_steps(n: int) -> np.ndarray:
    """Odd steps where the block's usual runs are cut: at a block's first and last step,
    side by side, a run shorter than a sub-block; then a block with just too many to cut."""
    dt = np.ones(n - 1)
    odd = [0, 1, 17, 40, 41, 42, _BLOCK - 2, _BLOCK - 1]  # the first block (its step 0 is none)
    odd += [_BLOCK + 5 * k for k in range(_FEW_ODD + 1)]  # the second: past the few
    dt[odd] = 2.5
    return np.concatenate([[0.0], np.cumsum(dt)])


CLOCKS = {
    "regular": lambda rng, n: 1.7e9 + np.arange(n) * 1.0,
    "regular, 15 s": lambda rng, n: np.arange(n) * 15.0,
    "regular with gaps": lambda rng, n: regular_with_gaps(n),
    "scattered odd steps": lambda rng, n: scattered_odd_steps(n),
    "wandering": lambda rng, n: 1.7e9 + np.cumsum(rng.uniform(0.9, 1.1, n)),
    "mixed, repeated stamps": lambda rng, n: np.cumsum(rng.choice([0.0, 0.1, 1.0, 60.0, 600.0], n)),
}


@pytest.mark.parametrize("clock", CLOCKS.values(), ids=CLOCKS.keys())
def test_the_free_run_is_the_cycle_path_at_any_clock(clock):
    m = model()
    t = clock(np.random.default_rng(2), 2 * _BLOCK + 3000)  # three blocks, the last partial
    speed, temps = log(t)
    same(m.simulate_um(speed, t, temps), stepped(m, speed, t, temps))


@pytest.mark.parametrize("clock", CLOCKS.values(), ids=CLOCKS.keys())
def test_a_speed_only_model_runs_the_same(clock):
    m = model().fallback
    assert isinstance(m, StateSpaceModel) and not m.input_names
    t = clock(np.random.default_rng(3), _BLOCK + 900)
    speed, _ = log(t, seed=12)
    same(m.simulate_um(speed, t, None, 4.0), stepped(m, speed, t, {}, 4.0))


@pytest.mark.parametrize("initial_um", [None, -12.5])
@pytest.mark.parametrize("policy", ["linear", "clip", "blend"])
def test_a_measured_start_and_every_policy_carry_through_the_blocks(initial_um, policy):
    m = model(policy=policy)
    t = regular_with_gaps(_BLOCK + 2500)
    speed, temps = log(t, seed=4)
    free = m.simulate_um(speed, t, temps, initial_um)
    same(free, stepped(m, speed, t, temps, initial_um))
    if initial_um is not None:
        assert free[0] == pytest.approx(initial_um)


def test_a_state_within_a_few_steps_runs_the_same():
    """tau of 2 and 8 usual steps (filtered over the whole log) beside a slow one."""
    m = model(taus=(2.0, 8.0, 3600.0))
    t = np.arange(_BLOCK + 700) * 1.0
    t[5000:] += 7.5  # one odd step
    speed, temps = log(t, seed=6)
    same(m.simulate_um(speed, t, temps), stepped(m, speed, t, temps))


@pytest.mark.parametrize("size", [1, 2, 17, _BLOCK, _BLOCK + 1])
def test_short_logs_and_block_edges(size):
    m = model()
    t = 100.0 + np.arange(size) * 1.0
    speed, temps = log(t, seed=size)
    same(m.simulate_um(speed, t, temps), stepped(m, speed, t, temps))


def test_drives_near_the_float_range_stay_exact():
    """Two states whose gains of 1e300 cancel in steady state (so the model is valid): the
    closed form's sums overflow; they are redone scaled, and stay exact."""
    m = model(taus=(30.0, 1800.0, 7200.0))
    assert 1e300 / 30.0 * math.exp(_BLOCK / 30.0) > 1e308  # a block's sums would overflow
    big = np.array(m.drive_um[0]) * 1e300
    m = m.model_copy(update={"drive_um": (tuple(big), tuple(-big), m.drive_um[2])})
    m = StateSpaceModel.model_validate(m.model_dump())  # the checks hold
    rng = np.random.default_rng(8)
    for t in (np.arange(2 * _BLOCK) * 1.0, np.cumsum(rng.uniform(0.5, 1.5, 2 * _BLOCK))):
        speed, temps = log(t, seed=9)
        free = m.simulate_um(speed, t, temps)
        assert np.isfinite(free).all() and np.max(np.abs(free)) > 1e280
        same(free, stepped(m, speed, t, temps))


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_input_in_a_later_block_is_named(bad):
    m = model()
    t = np.arange(2 * _BLOCK) * 1.0
    speed, temps = log(t)
    temps["b_c"][_BLOCK + 77] = bad
    with pytest.raises(NonFiniteInputError, match=f"b_c at sample {_BLOCK + 77} is"):
        m.simulate_um(speed, t, temps)


def test_time_going_backwards_in_a_later_block_is_named():
    m = model()
    t = np.arange(2 * _BLOCK) * 1.0
    t[_BLOCK + 300] -= 5.0
    speed, temps = log(t)
    with pytest.raises(ModelError, match=f"time goes backwards at sample {_BLOCK + 300}"):
        m.simulate_um(speed, t, temps)
    t = np.arange(10) * 1.0
    t[4] = math.nan
    with pytest.raises(NonFiniteInputError, match="time_s at sample 4 is nan"):
        m.simulate_um(speed[:10], t, {n: v[:10] for n, v in temps.items()})
