"""The drift detector (``compensator.drift``): its run lengths against Page's CUSUM figures, and
in the service, where it must find a sustained change of the spindle, name its size and start,
and hold back on what is no change: a model that holds, the grace after a start, a new model."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from test_closed_loop import Bench, events, simple_model  # noqa: F401 - the model file fixture

from compensator.drift import DriftConfig, DriftState, miss_sd_um, update
from compensator.errors import ConfigError
from compensator.io import save_model
from compensator.model import ThermalModel
from thermocomp.runtime import Alarm


def run_length(misses, cfg=DriftConfig(grace=0)) -> int | None:
    st = DriftState()
    for k, m in enumerate(misses, start=1):
        st = update(st, float(m), 1.0, float(k), cfg)
        if st.detected:
            return k
    return None


def test_run_lengths_match_pages_cusum():
    """k = 0.5, h = 5: about 465 measurements between false alarms of a model that holds, about
    10 to find a shift of one sd (Montgomery, sec. 9.1, table 9.3: 465 and 10.4)."""
    rng = np.random.default_rng(7)
    arl0 = [run_length(rng.normal(0.0, 1.0, 20_000)) for _ in range(60)]
    assert None not in arl0
    assert 300 < np.mean(arl0) < 700, np.mean(arl0)
    arl1 = [run_length(rng.normal(1.0, 1.0, 1000)) for _ in range(300)]
    assert 8.5 < np.mean(arl1) < 12.5, np.mean(arl1)


def test_the_change_is_dated_and_sized_and_clears_when_it_ends():
    misses = [0.3, -0.3] * 10 + [2.0] * 8 + [0.0] * 30
    st, found, cleared = DriftState(), None, None
    for k, m in enumerate(misses):
        st = update(st, m, 1.0, 100.0 * k, DriftConfig(grace=0))
        if st.detected and found is None:
            found = (k, st.change())
        if found is not None and not st.detected and cleared is None:
            cleared = k
    k, (size, since, n) = found
    assert k == 23 and since == 2000.0 and n == 4 and size == pytest.approx(2.0)  # 4 x 1.5 > 5
    assert (
        cleared is not None and 28 + 10 <= cleared <= 28 + 16
    )  # below h/2 after about 1.5 h/k normal ones


def test_grace_and_bad_values_hold_back():
    st = DriftState()
    for m in (50.0, -50.0):  # a start on a warm machine: the first two misses are left out
        st = update(st, m, 1.0, 0.0)
    assert st.statistic == 0.0 and st.seen == 2
    for bad in (float("nan"), float("inf")):
        assert update(st, bad, 1.0, 1.0) == st
    assert update(st, 1.0, 0.0, 1.0) == st
    with pytest.raises(ConfigError):
        DriftConfig(h=0.0)
    assert miss_sd_um(None, 0.5) == 0.5 and miss_sd_um(0.3, 0.4) == pytest.approx(0.5)
    assert (
        miss_sd_um(0.0, 0.0) == 0.1
    )  # a fit that states no error does not make every miss a drift


def test_one_wild_measurement_is_no_drift_but_three_are():
    assert run_length([0.0, 60.0, 0.0, 0.0, -0.2, 0.1]) is None  # a chip on the tool setter
    assert run_length([60.0, 60.0, 60.0]) == 3


# -- in the service ---------------------------------------------------------------------------------

SIGMA = 0.5


def model_only(rt) -> float:
    return rt.estimate_um() - rt.observer_status()["bias_um"]


def measure(bench, y: float, cycles: int = 60) -> dict:
    bench.rt.submit(y, SIGMA)
    rows = bench.run(cycles)
    return rows[0]


@pytest.fixture
def settled(tmp_path, simple_model):
    b = Bench(tmp_path / "a", simple_model, observer="enabled = true\ngate_sigma = 1000.0")
    b.run(1200)  # 12 time constants at speed: the model has settled
    return b


def test_a_model_that_holds_raises_no_drift(settled, caplog):
    caplog.set_level(logging.INFO)
    for k in range(60):
        row = measure(settled, model_only(settled.rt) + (0.4 if k % 2 else -0.4))
        assert not row["alarms"] & Alarm.MODEL_DRIFT
    assert not events(caplog, "model_drift") and settled.rt.drift.seen == 60


def test_a_sustained_shift_raises_model_drift_naming_its_size_and_start(
    settled, caplog, tmp_path, simple_model
):
    caplog.set_level(logging.INFO)
    for k in range(6):
        measure(settled, model_only(settled.rt) + (0.2 if k % 2 else -0.2))
    start = settled.rt.anchor_s + settled.t + 1.0  # the next measurement's cycle
    raised = []
    for _ in range(6):  # the spindle now grows 3 um more than the model says
        raised.append(
            bool(measure(settled, model_only(settled.rt) + 3.0)["alarms"] & Alarm.MODEL_DRIFT)
        )
    assert raised.index(True) == 2, raised  # each miss counts 3 sd at most: the third crosses
    ev = events(caplog, "model_drift")
    assert len(ev) == 1
    fields = ev[0].fields
    assert fields["size_um"] == pytest.approx(3.0, abs=0.1) and fields["since_s"] == pytest.approx(
        start
    )
    assert "refit" in ev[0].getMessage()
    # the observer follows the change (its bias), which is why the detector reads the model alone
    assert settled.rt.observer_status()["bias_um"] > 1.5
    status = settled.rt.last["drift"]
    assert status["detected"] and status["size_um"] == pytest.approx(3.0, abs=0.1)
    # a new model is a known event: the detector starts again, and the estimate does not jump
    other = tmp_path / "other.json"
    save_model(
        other,
        ThermalModel.from_discrete(
            0.995, (0.0, 0.021, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 27000.0)
        ),
    )
    before = settled.rt.estimate_um()
    settled.reload(tmp_path / "a", other, observer="enabled = true\ngate_sigma = 1000.0")
    assert settled.rt.drift.statistic == 0.0 and not settled.rt.drift.detected
    assert abs(settled.rt.estimate_um() - before) < 1e-9
    row = settled.run(1)[0]
    assert not row["alarms"] & Alarm.MODEL_DRIFT
    assert (
        abs(row["predicted_um"] - before) < 0.1
    )  # one second of the new model, from the old estimate
