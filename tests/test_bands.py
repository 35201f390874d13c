"""The stated error band holds what it states: the finite-sample quantile of forward residuals,
taken per fold because one fold's rows err together; no validated figure where validation never
measured (a model calibrated at rest says "not validated at speed", in the service as well); and
older statements still read as they did. Synthetic residuals of known distribution; the service
runs in lock-step on the virtual machine."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lfilter
from test_runtime_statespace import Bench, speed_only

from calibration.metrics import (
    MIN_FOLD_ROWS,
    against_expected,
    conformal_quantile,
    expected_error,
    fold_quantile,
)
from compensator.expected import (
    EXPECTED_FORMAT,
    EXPECTED_FORMAT_1,
    Band,
    ExpectedError,
    RecentMax,
    parse_expected,
    recent_rpm,
)
from thermocomp.runtime import Alarm

# -- the quantile ----------------------------------------------------------------------------


@pytest.mark.parametrize("n", [19, 40, 99])
def test_the_conformal_quantile_holds_its_finite_sample_guarantee(n):
    """A new draw exchangeable with n others lies within their ceil((n+1)*0.95)-th smallest
    |value| with probability at least 95 %, and at most 95 % + 1/(n+1) (continuous draws)."""
    rng = np.random.default_rng(n)
    draws = np.abs(rng.standard_t(3, size=(20000, n + 1)))  # heavy tails: no normal shortcut
    q = np.array([conformal_quantile(d[:n]) for d in draws])
    covered = float(np.mean(draws[:, n] <= q))
    sd = math.sqrt(0.95 * 0.05 / draws.shape[0])
    assert 0.95 - 3 * sd <= covered <= 0.95 + 1 / (n + 1) + 3 * sd
    # the order statistic itself
    x = np.arange(1.0, n + 1)
    assert conformal_quantile(-x) == x[math.ceil((n + 1) * 0.95) - 1]


def test_too_few_residuals_state_no_finite_quantile():
    assert MIN_FOLD_ROWS == 19
    assert math.isinf(conformal_quantile(np.ones(MIN_FOLD_ROWS - 1)))
    assert conformal_quantile(np.full(MIN_FOLD_ROWS, 2.0)) == 2.0
    # a fold with fewer rows is not a fold of its own; fewer than two folds state nothing
    big, small = np.linspace(0, 1, 50), np.ones(5)
    assert fold_quantile([big, small]) is None
    assert fold_quantile([big, 2 * big]) == (pytest.approx(2 * conformal_quantile(big)), 2)


def folds_of(rng, m: int, size: int = 200, sims: int = 2000) -> np.ndarray:
    """``sims`` runs of ``m`` folds each: every fold errs around its own offset (N(0, 1)) with
    slow AR(1) noise (sd 0.3, 0.95 per row), so its rows are far from independent."""
    offsets = rng.normal(0.0, 1.0, (sims, m, 1))
    white = rng.normal(0.0, 0.3 * math.sqrt(1 - 0.95**2), (sims, m, size))
    return offsets + lfilter([1.0], [1.0, -0.95], white, axis=-1)


def test_per_fold_the_next_fold_holds_where_the_pooled_quantile_promises_too_much():
    """With autocorrelated folds the pooled quantile counts every row as a draw; per fold, the
    next fold's own 95 % half-width stays within the worst of m folds with probability at least
    m/(m+1), and its rows are covered more often than by the pooled figure."""
    rng = np.random.default_rng(11)
    m = 4
    runs = folds_of(rng, m + 1)
    held_fold, held_pool, cov_fold, cov_pool = [], [], [], []
    for run in runs:
        q, used = fold_quantile(list(run[:m]))
        assert used == m
        qp = conformal_quantile(run[:m].ravel())
        nxt = np.abs(run[m])
        cov_fold.append(np.mean(nxt <= q))
        cov_pool.append(np.mean(nxt <= qp))
        held_fold.append(conformal_quantile(nxt) <= q)
        held_pool.append(conformal_quantile(nxt) <= qp)
    sd = math.sqrt(0.8 * 0.2 / len(runs))
    assert np.mean(held_fold) >= m / (m + 1) - 3 * sd
    assert np.mean(held_pool) < np.mean(held_fold) - 0.02
    assert np.mean(cov_fold) > np.mean(cov_pool) + 0.02


def test_below_nineteen_folds_the_worst_fold_states_it_above_the_order_statistic():
    rng = np.random.default_rng(3)
    few = [rng.normal(0, s, 60) for s in (1.0, 3.0, 2.0)]
    q, m = fold_quantile(few)
    assert m == 3 and q == max(conformal_quantile(f) for f in few)
    many = [rng.normal(0, 1 + k / 10, 60) for k in range(39)]
    q, m = fold_quantile(many)
    per = sorted(conformal_quantile(f) for f in many)
    assert m == 39 and q == per[37]  # ceil(40 * 0.95) = 38th of 39


# -- the statement ---------------------------------------------------------------------------

CYCLE = 600
TOP_RPM = 24000.0


def log_at_rest_measurements(folds: int = 4):
    """Cycles of a staircase to 24000 rpm and a rest, measured at rest only (a contact tool
    setter): the forward residuals exist at rest, never at speed."""
    k = np.arange(folds * CYCLE)
    phase = k % CYCLE
    speed = np.where(phase < CYCLE // 2, 6000.0 * (1 + phase // 75), 0.0)
    rng = np.random.default_rng(5)
    residual = np.where(speed == 0.0, rng.normal(0.0, 1.0, k.size), np.nan)
    residual[: 2 * CYCLE] = np.nan  # the first two cycles are only fitted on
    cycles = [(i * CYCLE, (i + 1) * CYCLE) for i in range(folds)]
    return speed, residual, cycles


def test_a_calibration_at_rest_is_not_validated_at_speed():
    speed, residual, cycles = log_at_rest_measurements()
    stated = expected_error(
        residual, None, speed, TOP_RPM, forward_folds=len(cycles) - 2, folds=cycles
    )
    assert stated is not None and stated.format == EXPECTED_FORMAT
    assert [b.label for b in stated.bands] == ["at rest"] and stated.measured_rpm == 0.0
    rest, fast = stated.at(0.0), stated.at(17600.0)
    assert rest.validated and rest.claim == f"expect ±{rest.p95_abs_um:.1f} µm (95 %)"
    assert not fast.validated and fast.claim == "not validated at speed"
    assert stated.why_unvalidated(17600.0, 0.0) == [
        "not validated at speed: the calibration measured the error at rest only"
    ]
    assert not stated.validated(np.array([1.5, 300.0, 17600.0])).any()
    # what the fit prints
    assert stated.describe()[-1] == "validated at rest only: not validated at speed"
    # two folds: the next cycle's 95 % stays within the worst of them with probability 2/3
    assert (
        "2 fold(s); 95 % of the next cycle within it with probability ≥ 67 %"
        in (stated.describe()[0])
    )
    # the same record in the first format took the at-rest band for every speed (a floor)
    older = ExpectedError.model_validate(
        {**stated.model_dump(mode="json", exclude={"measured_rpm"}), "format": EXPECTED_FORMAT_1}
    )
    assert older.at(17600.0).p95_abs_um == rest.p95_abs_um


def test_the_service_shows_not_validated_at_speed_instead_of_a_figure(tmp_path):
    speed, residual, cycles = log_at_rest_measurements()
    stated = expected_error(residual, None, speed, TOP_RPM, forward_folds=2, folds=cycles)
    model = speed_only(spindle_id="sp-A")
    model = model.model_copy(
        update={"fit": {**model.fit, "expected_error": stated.model_dump(mode="json")}}
    )
    b = Bench(tmp_path, model)
    row = b.run(3)[-1]
    assert row["speed_rpm"] > 1000.0
    ex = row["expected_error"]
    assert ex["validated"] is False and ex["claim"] == "not validated at speed"
    b.vm.override_speed(0.0)
    ex = b.run(3)[-1]["expected_error"]
    assert ex["validated"] is True and ex["claim"].startswith("expect ±")
    b.rt.close()
    # the status page prints the claim, not the figure, where there is one
    page = (Path(__file__).parents[1] / "thermocomp/runtime/static/status.html").read_text()
    assert "ex.claim ||" in page


def test_a_speed_band_without_forward_residuals_states_no_validated_figure():
    """Residuals at rest and up to 8000 rpm: 8000-16000 rpm has none (the fit's own held-out
    figure stays, as a floor), and above 8000 rpm nothing is validated."""
    n = np.tile(np.r_[np.zeros(100), np.full(100, 4000.0), np.full(100, 7900.0)], 4)
    n_log = n.copy()
    n_log[0] = TOP_RPM  # the log reached 24000 rpm once, unmeasured
    rng = np.random.default_rng(9)
    fwd = rng.normal(0, 1.0, n.size)
    fwd[:300] = np.nan
    fwd[0] = np.nan
    held = rng.normal(0, 0.5, n.size)
    cycles = [(i * 300, (i + 1) * 300) for i in range(4)]
    stated = expected_error(fwd, held, n_log, TOP_RPM, forward_folds=3, folds=cycles)
    assert stated.measured_rpm == 7900.0
    assert stated.validated(np.array([0.0, 4000.0, 7900.0])).all()
    assert not stated.validated(np.array([8100.0, 12000.0, 20000.0])).any()
    assert stated.at(12000.0).claim == "not validated at speed"


def test_outside_the_trained_range_only_what_forward_folds_measured_there_is_validated():
    rng = np.random.default_rng(4)
    n = np.full(4 * 300, 5000.0)
    cycles = [(i * 300, (i + 1) * 300) for i in range(4)]
    fwd = rng.normal(0, 1.0, n.size)
    fwd[:300] = np.nan
    inside_only = expected_error(
        fwd, None, n, 5000.0, np.zeros(n.size), forward_folds=3, folds=cycles
    )
    assert inside_only.validated(np.array([5000.0]), np.array([0.0]))[0]
    at = inside_only.at(5000.0, 0.1)
    assert not at.validated and at.claim == "not validated outside the trained range"


def test_forward_residuals_without_folds_are_pooled_and_the_held_out_ones_never_validate():
    rng = np.random.default_rng(1)
    n = np.tile(np.linspace(0, 9000, 300), 3)
    r = rng.normal(0, 2.0, n.size)
    pooled = expected_error(r, None, n, 9000.0, forward_folds=3)
    which = pooled.band_index(n)
    for k, b in enumerate(pooled.bands):
        assert b.source == "forward, pooled" and b.folds == 3
        assert np.mean(np.abs(r[which == k]) <= b.p95_abs_um) >= 0.95
    held = expected_error(None, r, n, 9000.0, forward_folds=0)
    assert {b.source for b in held.bands} == {"held out"}
    assert not held.validated(n).any()


def test_held_out_cycles_widen_a_forward_band_and_never_narrow_it():
    """Each held-out cycle was predicted by a model fitted without it (the jackknife+ draws):
    taken per cycle as the forward folds are, it widens a band where it reaches further."""
    rng = np.random.default_rng(8)
    n = np.full(4 * 200, 3000.0)
    cycles = [(i * 200, (i + 1) * 200) for i in range(4)]
    fwd = rng.normal(0, 1.0, n.size)
    fwd[:200] = np.nan
    wide = rng.normal(0, 3.0, n.size)
    base = expected_error(fwd, None, n, 3000.0, forward_folds=3, folds=cycles).bands[-1]
    widened = expected_error(fwd, wide, n, 3000.0, forward_folds=3, folds=cycles).bands[-1]
    assert widened.p95_abs_um == pytest.approx(
        max(conformal_quantile(wide[a:b]) for a, b in cycles)
    )
    assert widened.p95_abs_um > 2 * base.p95_abs_um and widened.folds == base.folds == 3
    assert widened.source == "forward, per fold, widened to held out"
    narrow = expected_error(fwd, wide / 10, n, 3000.0, forward_folds=3, folds=cycles).bands[-1]
    assert narrow == base


def test_replay_counts_the_rows_a_validated_band_covers():
    speed, residual, cycles = log_at_rest_measurements()
    stated = expected_error(residual, None, speed, TOP_RPM, forward_folds=2, folds=cycles)
    r = np.random.default_rng(2).normal(0, 1.0, speed.size)
    rows = against_expected(stated, r, speed)
    (rest,) = rows  # every speed above rest falls to the band at rest, never validated there
    assert rest["validated_samples"] == int((speed == 0).sum())
    assert rest["within_p95_validated"] is not None


# -- older statements ------------------------------------------------------------------------

FIRST_FORMAT = {
    "format": "thermocomp.expected-error/1",
    "bands": [
        {"speed_rpm": [0.0, 1.0], "source": "held out", "samples": 30, "rms_um": 0.3,
         "p95_abs_um": 0.6, "outside": None},
        {"speed_rpm": [1.0, 4000.0], "source": "forward", "samples": 90, "rms_um": 1.1,
         "p95_abs_um": 2.4, "outside": None},
        {"speed_rpm": [8000.0, 12000.0], "source": "forward", "samples": 90, "rms_um": 2.1,
         "p95_abs_um": 4.4, "outside": {"source": "forward, outside", "samples": 20,
                                        "rms_um": 3.0, "p95_abs_um": 6.0}},
    ],
    "outside_validated": 0.3,
    "forward_folds": 3,
}  # fmt: skip


def test_a_statement_in_the_first_format_still_loads_and_reads_as_it_did():
    stated = parse_expected({"expected_error": FIRST_FORMAT})
    assert stated is not None and stated.format == EXPECTED_FORMAT_1

    def drop_none(v):
        if isinstance(v, dict):
            return {k: drop_none(x) for k, x in v.items() if x is not None}
        return [drop_none(x) for x in v] if isinstance(v, list) else v

    assert stated.model_dump(mode="json", exclude_none=True) == drop_none(FIRST_FORMAT)
    # as before: a speed in the gap takes the top band's figure, validated up to the top band;
    # outside the range within the distance validated, the band's outside figure
    gap = stated.at(6000.0)
    assert gap.p95_abs_um == 4.4 and gap.validated
    assert stated.at(12500.0).validated is False
    assert stated.at(10000.0, 0.2).p95_abs_um == 6.0 and stated.at(10000.0, 0.2).validated
    assert stated.at(3000.0, 0.2).validated  # the first format had no outside figure per band
    assert stated.at(0.0).validated  # the statement's three folds, as before


# -- after running faster than validation saw ------------------------------------------------


def test_the_service_window_keeps_what_a_clock_step_back_would_forget():
    """The service's window (no restart): the fastest within a shorter span asked of it, an
    unread speed adding nothing, and a clock that steps back keeping the faster speed it saw,
    where a log's window starts over."""
    w = RecentMax(100.0)
    for t, n in [(0.0, 9000.0), (40.0, -3000.0), (80.0, float("nan")), (90.0, 1000.0)]:
        w.push(t, n)
    assert w.fastest(90.0) == 9000.0 and w.fastest(90.0, 60.0) == 3000.0
    assert w.fastest(90.0, 5.0) == 1000.0
    w.push(50.0, 500.0)  # the clock stepped back
    assert w.fastest(50.0) == 9000.0
    log = RecentMax(100.0, restart=True)
    log.push(0.0, 9000.0)
    log.push(-5.0, 500.0)
    assert log.fastest(-5.0) == 500.0
    # what a state file keeps is in time order even so, and taken up no later than now
    pairs = w.to_wall(50.0, 1000.0)
    assert [p[0] for p in pairs] == sorted(p[0] for p in pairs) and pairs[0][1] == 9000.0
    assert pairs[-1][0] <= 1000.0  # never after the save
    again = RecentMax(100.0)
    again.from_wall([[2000.0, 7000.0]], 10.0, 1000.0)  # saved "after" the restart's wall time
    again.push(11.0, 0.0)
    assert again.fastest(11.0) == 7000.0 and again.to_wall(11.0, 1001.0)[0][0] <= 1001.0
    w.span_s = 20.0  # a model with a shorter memory, loaded after
    w.push(200.0, 0.0)
    assert w.fastest(200.0) == 0.0


def test_a_saved_history_is_thinned_on_the_safe_side():
    """A slow run-down leaves a long window; the state file keeps at most 256 entries, and the
    history taken up from them remembers every speed at least as long as the full one."""
    full = RecentMax(5000.0)
    for k in range(1000):  # 10000 rpm down to 10 rpm, one a second
        full.push(float(k), 10000.0 - 10.0 * k)
    pairs = full.to_wall(999.0, 1.7e9 + 999.0)
    assert len(pairs) <= 256 and pairs[0][1] == 10000.0
    back = RecentMax(5000.0)
    back.from_wall(pairs, 2999.0, 1.7e9 + 999.0)  # restarted at the same wall time, another clock
    for later in (0.0, 100.0, 1000.0, 4000.0, 4999.0):
        assert back.fastest(2999.0 + later) >= full.fastest(999.0 + later)
    assert back.fastest(2999.0, 0.5) >= full.fastest(999.0, 0.5)


def test_the_speed_lately_is_the_fastest_within_the_memory():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.5, 3.0, 500))
    n = rng.uniform(-9000.0, 9000.0, 500)
    got = recent_rpm(t, n, 50.0)
    want = np.array([np.abs(n[(t >= ti - 50.0) & (t <= ti)]).max() for ti in t])
    assert np.array_equal(got, want)
    # a second log (time restarts) starts its own history
    assert recent_rpm(np.r_[0.0, 10.0, 0.0], np.r_[0.0, 8000.0, 100.0], 1e6).tolist() == [
        0.0,
        8000.0,
        100.0,
    ]


def test_a_spindle_cooling_from_a_speed_validation_never_saw_is_not_validated():
    """Forward residuals after running up to 3750 rpm: at rest after 5000 rpm the at-rest band
    is not vouched for until the memory (3 slowest time constants) has passed."""
    t = np.arange(4 * 300) * 60.0
    n = np.tile(np.r_[np.full(150, 3750.0), np.zeros(150)], 4)
    cycles = [(i * 300, (i + 1) * 300) for i in range(4)]
    fwd = np.random.default_rng(6).normal(0, 1.0, n.size)
    fwd[:300] = np.nan
    stated = expected_error(
        fwd, None, n, 3750.0, forward_folds=3, folds=cycles, time_s=t, memory_s=7200.0
    )
    assert stated.history_rpm == 3750.0 and stated.memory_s == 7200.0
    assert stated.at(0.0, 0.0, recent=3750.0).validated
    cooling = stated.at(0.0, 0.0, recent=5000.0)
    assert not cooling.validated
    assert cooling.claim == "not validated after running faster than calibrated"
    assert stated.why_unvalidated(0.0, 0.0, 5000.0)[0].startswith(
        "the spindle ran at 5000 rpm within the last 2.0 h"
    )
    # over a log: rows within 2 h after the 5000 rpm stretch are not validated, later ones are
    t2 = np.arange(400) * 60.0
    n2 = np.r_[np.full(100, 5000.0), np.zeros(300)]
    ok = stated.validated(n2, None, stated.recent_rpm(t2, n2))
    assert not ok[:220].any() and ok[221:].all()


def _remembering(memory_s: float = 60.0):
    """A speed-only model whose statement validated at rest after at most 3000 rpm, with a
    thermal memory of ``memory_s``."""
    stated = ExpectedError(
        bands=(
            Band(speed_rpm=(0.0, 1.0), source="forward", samples=50, rms_um=0.4, p95_abs_um=0.8),
            Band(
                speed_rpm=(1.0, 10000.0), source="forward", samples=50, rms_um=1.0, p95_abs_um=2.0
            ),
        ),
        forward_folds=3,
        measured_rpm=10000.0,
        history_rpm=3000.0,
        memory_s=memory_s,
    )
    model = speed_only(spindle_id="sp-A")
    return model.model_copy(
        update={"fit": {**model.fit, "expected_error": stated.model_dump(mode="json")}}
    )


def test_a_restart_within_the_memory_still_knows_the_spindle_ran_faster(tmp_path):
    """The speeds lately go into the state file: a service stopped after 5000 rpm and started
    again 30 s later, at rest, does not claim the at-rest band until the memory has passed; one
    started after the memory does at once. A saved history that is not one is a corrupt state."""
    faster = "not validated after running faster than calibrated"
    b = Bench(tmp_path / "soon", _remembering(600.0))
    b.run(20)  # 5000 rpm
    b.rt.close()  # a clean stop saves the state
    saved = json.loads(next((tmp_path / "soon" / "state").glob("*.json")).read_text())
    assert saved["speeds_lately"][-1][1] == 5000.0
    b.t += 30.0
    b.vm.override_speed(0.0)
    b.rt = b.start()
    claims = [r["expected_error"]["claim"] for r in b.run(600)]
    assert claims[0] == faster and claims[-1] == "expect ±0.8 µm (95 %)"
    assert 560 <= claims.index("expect ±0.8 µm (95 %)") <= 575  # 600 s after the last 5000 rpm
    b.rt.close()
    late = Bench(tmp_path / "late", _remembering(600.0))
    late.run(20)
    late.rt.close()
    late.t += 700.0
    late.vm.override_speed(0.0)
    late.rt = late.start()
    assert late.run(1)[0]["expected_error"]["claim"] == "expect ±0.8 µm (95 %)"
    late.rt.close()
    for bad in ([[1.0, -5.0]], [[2.0, 1.0], [1.0, 1.0]], "5000", [[1.0, "5000"]]):
        state = next((tmp_path / "late" / "state").glob("*.json"))
        body = json.loads(state.read_text())
        body["speeds_lately"] = bad
        state.write_text(json.dumps(body))
        late.rt = late.start()
        assert late.rt.alarms & Alarm.STATE_CORRUPT, bad
        late.rt.close()


def test_the_service_remembers_the_speed_it_ran_at(tmp_path):
    model = _remembering(60.0)
    b = Bench(tmp_path, model)
    ex = b.run(3)[-1]["expected_error"]  # 5000 rpm, faster than any before a forward residual
    assert ex["validated"] is False
    assert ex["claim"] == "not validated after running faster than calibrated"
    b.vm.override_speed(0.0)
    rows = b.run(80)
    claims = [r["expected_error"]["claim"] for r in rows]
    # at rest the memory of 5000 rpm lasts 60 s of the service's clock, then the band holds
    assert claims[0] == "not validated after running faster than calibrated"
    assert claims[-1] == "expect ±0.8 µm (95 %)"
    assert 50 <= claims.index("expect ±0.8 µm (95 %)") <= 62
    b.rt.close()
