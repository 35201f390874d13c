"""Planning the closed loop (calibration.closedloop): the observer's noise fitted from residuals,
the interval table by held-out cycles, and what the fit writes into the model."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calibration import closedloop as cl
from compensator.fusion import FusedPredictor, observer_config_of
from compensator.observer import ObserverConfig


def _walk(
    seed: int, hours: float = 40.0, dt_s: float = 15.0, q_um2_per_h: float = 4.0, sd_um: float = 0.6
) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """A residual made of a random walk (q) plus white misses (sd), cut into 8 h cycles."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, hours * 3600.0, dt_s)
    walk = np.cumsum(rng.normal(0.0, math.sqrt(q_um2_per_h / 3600.0 * dt_s), t.size))
    r = walk + rng.normal(0.0, sd_um, t.size)
    n = int(8 * 3600 / dt_s)
    cycles = [(a, min(a + n, t.size)) for a in range(0, t.size, n)]
    return t, r, cycles


def test_the_variogram_fit_recovers_the_noise_it_was_made_of():
    qs, sds, kept = [], [], []
    for seed in range(6):
        t, r, cycles = _walk(seed)
        q, sd2 = cl._nnls_variogram(t, r, cycles, False)
        qs.append(q * 3600.0)
        sds.append(math.sqrt(sd2))
        cfg = cl.fit_noise(t, r, cycles)
        assert cfg.model_sd_um == pytest.approx(sds[-1])
        kept.append(cfg.bias_q_um2_per_s * 3600.0 / qs[-1])
    assert np.median(qs) == pytest.approx(4.0, rel=0.35)
    assert np.median(sds) == pytest.approx(0.6, rel=0.35)
    # the observer keeps the largest cycle's own walk: on the safe side, not wildly so
    assert all(1.0 <= k < 4.0 for k in kept)


def test_the_fitted_observer_beats_a_bias_reset_on_held_out_cycles():
    t, r, cycles = _walk(11, q_um2_per_h=0.5, sd_um=1.5)
    pieces = cl.anchored(t, r, cycles, 3600.0)
    starts = [a for a, _ in cycles]
    reset = ObserverConfig(bias_q_um2_per_s=1e3, gate_sigma=1e6)
    fitted = cl.fit_noise(t, np.concatenate(pieces), cycles)
    rms_reset = cl._scores([reset] * len(pieces), t, pieces, starts, 1800.0)[0]
    rms_fitted = cl._scores([fitted] * len(pieces), t, pieces, starts, 1800.0)[0]
    # a reset carries each probe's white miss for a whole interval; the filter averages it out
    assert rms_fitted < 0.92 * rms_reset


def test_the_plan_tabulates_every_interval_and_recommends_the_longest_that_meets_the_target():
    t, r, cycles = _walk(5)
    plan = cl.plan(t, r, cycles, 3600.0, target_um=1.5)
    rows = plan.table
    assert rows[0]["interval_s"] is None and [row["interval_s"] for row in rows[1:]] == list(
        cl.INTERVALS_S
    )
    rms = [row["rms_um"] for row in rows[1:]]
    assert rms == sorted(rms)  # probing less often never helps
    assert rows[0]["rms_um"] > rms[-1]  # and any probing beats none
    meets = [row["interval_s"] for row in rows[1:] if row["rms_um"] <= 1.5]
    assert plan.recommended_s == (max(meets) if meets else None)
    assert plan.variant in ("bias", "bias+drift") and plan.variant in plan.reason
    assert any("recommended" in line or "no interval" in line for line in plan.lines())
    report = plan.report()
    assert ObserverConfig(**report["observer"]) == plan.observer


def test_observer_settings_come_from_the_model_and_the_runtime_overrides_them():
    from compensator.model import ThermalModel

    m = ThermalModel.from_discrete(
        0.98, (0.0, 0.002, 0.0004, 0.0), 60.0, speed_range_rpm=(0.0, 20000.0)
    )
    assert observer_config_of(m) == ObserverConfig()
    fitted = m.model_copy(
        update={"fit": {"observer": {"bias_q_um2_per_s": 0.001, "model_sd_um": 0.3}}}
    )
    cfg = observer_config_of(fitted, {"gate_sigma": 4.0})
    assert (cfg.bias_q_um2_per_s, cfg.model_sd_um, cfg.gate_sigma) == (0.001, 0.3, 4.0)
    from compensator.errors import ModelError

    with pytest.raises(ModelError, match="observer settings"):
        observer_config_of(fitted, {"gate_sigma": -1.0})
    f = FusedPredictor(fitted, cfg)
    s = f.step(f.start(None, 0.0), 10000.0, 60.0)
    s2, up = f.measure(s, s.elongation_um + 3.0, 0.5)
    assert up.accepted and s2.elongation_um == pytest.approx(s.elongation_um + 3.0, abs=0.5)
    assert f.state_from_dict(f.state_dict(s2)) == s2
    # a state saved without an observer (before the closed loop was enabled) still loads
    plain = f.state_from_dict(m.state_dict(s.model))
    assert plain.bias_um == 0.0 and plain.since_measurement_s is None


def test_fit_for_a_closed_loop_chooses_by_the_closed_loop_on_held_out_cycles(tmp_path):
    import json
    import runpy
    import subprocess
    import sys
    from pathlib import Path

    from compensator.io import load_any_model

    channels = runpy.run_path(str(Path(__file__).parent / "data" / "real-spindle" / "channels.py"))
    log = channels["write_channels"](tmp_path, ("ch3",))["ch3"]
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "thermocomp",
            "fit",
            str(log),
            "--no-physical",
            "--no-nested",
            "--probe-every",
            "1800",
            "--output",
            str(tmp_path / "m.json"),
            "--json",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    speed = [c for c in rep["candidates"] if c["family"] == "speed" and c["accepted"]]
    loop = {c["name"]: c["closed_loop_rms_um"]["1800"] for c in speed}
    assert rep["chosen"] == min(loop, key=loop.get) and "closed-loop RMS" in rep["reason"]
    assert rep["closed_loop"]["intervals"][2]["rms_um"] == pytest.approx(
        loop[rep["chosen"]], abs=1e-3
    )
    assert load_any_model(tmp_path / "m.json").fit["observer"] == rep["closed_loop"]["observer"]
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "thermocomp",
            "fit",
            str(log),
            "--probe-every",
            "-5",
            "--output",
            str(tmp_path / "n.json"),
        ],
        capture_output=True,
        text=True,
    )
    assert (
        r.returncode != 0 and r.stderr.count("\n") == 1 and "--probe-every must be > 0" in r.stderr
    )
    assert not (tmp_path / "n.json").exists()
