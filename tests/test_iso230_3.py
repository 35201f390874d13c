"""The spindle thermal test in the terms of ISO 230-3 from a recorded run: the kind of test, the
drift along Z while running and over the rest, and what remains with compensation."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.iso230_3 import report_rows, spindle_thermal_test
from compensator.speed_programs import paper_calibration
from machine_sim import SpindlePlant, preset


def test_a_staircase_and_rest_is_a_speed_spectrum_test_with_its_drift():
    p = preset("motorized-27k")
    t, n = paper_calibration(p.max_rpm).sample(10.0)
    run = SpindlePlant(p, seed=3).run(t, n)
    z = run.measured_um
    r = spindle_thermal_test(t, n, z)
    assert r.kind == "speed spectrum" and len(r.speeds_rpm) >= 5
    turning = n > 1
    k = int(np.argmax(np.abs(z - z[0]) * turning))
    assert r.machine.running_um == pytest.approx(z[k] - z[0])
    assert r.machine.running_at_s == pytest.approx(t[k] - t[0])
    last = np.flatnonzero(turning)[-1]
    assert r.machine.rest_um == pytest.approx(z[-1] - z[last + 1])
    assert r.rest_s > 0 and r.machine.rest_um < 0  # the spindle cools while it stands
    # a model that predicts the growth within 1 um leaves a drift within about that
    pred = z + np.random.default_rng(0).uniform(-1, 1, z.size)
    with_comp = spindle_thermal_test(t, n, z, pred)
    assert abs(with_comp.compensated.running_um) <= 2.0 < abs(with_comp.machine.running_um)
    rows = report_rows({"calibration": with_comp})
    assert rows[1][0] == "calibration: machine" and rows[2][0] == "calibration: with thermocomp"
    assert "not measured" in rows[-1][1]


def test_one_speed_is_a_constant_speed_test():
    t = np.arange(0, 4 * 3600, 10.0)
    n = np.where(t < 3 * 3600, 12000.0, 0.0)
    z = 20 * (1 - np.exp(-np.minimum(t, 3 * 3600) / 1800))
    r = spindle_thermal_test(t, n, z)
    assert r.kind == "constant speed" and r.speeds_rpm == (12000.0,)
    assert r.running_s == pytest.approx(3 * 3600, abs=20) and r.rest_s == pytest.approx(
        3600, abs=20
    )
    with pytest.raises(ValueError, match="one time, speed and displacement"):
        spindle_thermal_test(t[:1], n[:1], z[:1])
