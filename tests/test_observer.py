"""The probe observer (compensator.observer): exact at any Δt, bounded under an unmodelled
drift, outliers gated. Pure: no plant process needed."""

from __future__ import annotations

import numpy as np
import pytest

from compensator.errors import ModelError
from compensator.observer import (
    ObserverConfig,
    ObserverState,
    fuse_series,
    measurement_update,
    time_update,
)


def test_time_update_is_exact_at_any_step_partition():
    cfg = ObserverConfig(bias_q_um2_per_s=1e-3, drift_q_um2_per_s3=1e-9)
    z = ObserverState(1.0, 1e-4, ((2.0, 0.01), (0.01, 1e-6)))
    one = time_update(cfg, z, 1800.0)
    many = z
    for dt in (1.0, 99.0, 700.0, 1000.0):
        many = time_update(cfg, many, dt)
    assert one.bias_um == pytest.approx(many.bias_um)
    assert np.allclose(one.cov, many.cov, rtol=1e-9)


def test_fused_error_stays_bounded_while_the_open_loop_grows():
    t = np.arange(0, 12 * 3600.0 + 1, 15.0)
    model = 10 * (1 - np.exp(-t / 3600.0))  # what the model predicts
    truth = model + 1.5 * t / 3600.0  # an unmodelled ambient drift: 1.5 um per hour
    rng = np.random.default_rng(3)
    pt = t[::120][1:]  # a probe every 30 min
    py = np.interp(pt, t, truth) + rng.normal(0, 0.5, pt.size)
    f = fuse_series(ObserverConfig(), t, model, pt, py, np.full(pt.size, 0.5))
    open_loop = np.abs(truth - model)
    fused = np.abs(truth - f.fused_um)
    late = t > 6 * 3600
    assert open_loop[late].max() > 9.0  # the open loop has drifted away
    assert fused[late].max() < 2.5 and np.sqrt(np.mean(fused[late] ** 2)) < 1.2
    assert f.accepted == pt.size and f.rejected == 0


def test_an_outlier_is_refused_by_the_gate():
    cfg = ObserverConfig()
    z = measurement_update(cfg, ObserverState.prior(cfg), 5.0, 4.0, 0.5).state
    z = time_update(cfg, z, 900.0)
    sd = np.sqrt(z.cov[0][0] + 0.25)
    bad = measurement_update(cfg, z, 4.0 + z.bias_um + 6 * sd, 4.0, 0.5)
    assert (
        not bad.accepted
        and bad.state.bias_um == z.bias_um
        and bad.state.cov == z.cov
        and bad.innovation_um > 5 * bad.innovation_sd_um
    )
    good = measurement_update(cfg, z, 4.0 + z.bias_um + 2 * sd, 4.0, 0.5)
    assert good.accepted and good.state.bias_um > z.bias_um


def test_bad_measurements_are_one_line_errors():
    cfg = ObserverConfig()
    with pytest.raises(ModelError, match="sigma must be > 0"):
        measurement_update(cfg, ObserverState.prior(cfg), 1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="measured_um"):
        measurement_update(cfg, ObserverState.prior(cfg), float("nan"), 0.0, 0.5)
    with pytest.raises(ValueError, match="gate_sigma"):
        ObserverConfig(gate_sigma=0.0)


def test_replay_probe_every_fuses_and_keeps_the_open_loop_beside(tmp_path):
    import json
    import subprocess
    import sys

    from compensator.io import save_model
    from compensator.model import ThermalModel

    run = lambda *a: subprocess.run(
        [sys.executable, "-m", "thermocomp", *map(str, a)],
        capture_output=True,
        text=True,
    )
    assert run("simulate", "--dt", 60, "--output", tmp_path / "cal.csv").returncode == 0
    # a deliberately poor model: half the plant's gain, so the open loop drifts away
    save_model(
        tmp_path / "m.json",
        ThermalModel.from_discrete(
            0.98, (0.0, 0.002, 0.0004, 0.0), 60.0, speed_range_rpm=(0.0, 27000.0)
        ),
    )
    r = run(
        "replay",
        tmp_path / "cal.csv",
        "--model",
        tmp_path / "m.json",
        "--probe-every",
        900,
        "--json",
    )
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["probes"] >= 10 and 0 <= rep["probes_rejected"] < rep["probes"] // 4
    assert rep["rms_residual_um"] < 0.8 * rep["open_loop_rms_residual_um"]
    assert rep["max_abs_residual_um"] < rep["open_loop_max_abs_residual_um"]
    r = run(
        "replay", tmp_path / "cal.csv", "--model", tmp_path / "m.json", "--probe-every", 0, "--json"
    )
    assert (
        r.returncode == 2 and r.stderr.count("\n") == 1 and "--probe-every must be > 0" in r.stderr
    )


def test_replay_fuses_real_measurements_from_a_file(tmp_path):
    import json
    import subprocess
    import sys

    from compensator.io import read_run_log, save_model
    from compensator.model import ThermalModel

    run = lambda *a: subprocess.run(
        [sys.executable, "-m", "thermocomp", *map(str, a)],
        capture_output=True,
        text=True,
    )
    assert run("simulate", "--dt", 60, "--output", tmp_path / "cal.csv").returncode == 0
    save_model(
        tmp_path / "m.json",
        ThermalModel.from_discrete(
            0.98, (0.0, 0.002, 0.0004, 0.0), 60.0, speed_range_rpm=(0.0, 27000.0)
        ),
    )
    log = read_run_log(tmp_path / "cal.csv")
    k = np.arange(15, log.time_s.size, 15)
    rows = [
        f"{log.time_s[i]:.3f},{log.elongation_um[i]:.4f},0.5,setter,{n},accepted"
        for n, i in enumerate(k)
    ]
    rows.insert(3, f"{log.time_s[k[2]] + 1:.3f},,,setter,99,refused")  # the journal's unusable row
    (tmp_path / "meas.csv").write_text(
        "# a measurement journal\ntime_s,elongation_um,sigma_um,source,"
        "sequence,outcome\n" + "\n".join(rows) + "\n"
    )
    r = run(
        "replay",
        tmp_path / "cal.csv",
        "--model",
        tmp_path / "m.json",
        "--measurements",
        tmp_path / "meas.csv",
        "--json",
    )
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["probes"] == k.size and rep["probes_rejected"] < k.size // 4
    assert rep["rms_residual_um"] < 0.8 * rep["open_loop_rms_residual_um"]
    bad = {
        "time_s,elongation_um\n1e9,3\n": "outside the log",
        "time_s,elongation_um\n60,nan\n": "not a finite number",
        "time_s,elongation_um,sigma_um\n60,1,0\n": "must be > 0",
        "time_s,elongation_um\n120,1\n60,1\n": "does not increase",
        "time,elongation_um\n60,1\n": "missing column",
    }
    for text, why in bad.items():
        (tmp_path / "bad.csv").write_text(text)
        r = run(
            "replay",
            tmp_path / "cal.csv",
            "--model",
            tmp_path / "m.json",
            "--measurements",
            tmp_path / "bad.csv",
            "--json",
        )
        assert r.returncode != 0 and r.stderr.count("\n") == 1 and why in r.stderr, (text, r.stderr)
    r = run(
        "replay",
        tmp_path / "cal.csv",
        "--model",
        tmp_path / "m.json",
        "--measurements",
        tmp_path / "meas.csv",
        "--probe-every",
        900,
    )
    assert r.returncode == 2 and "exclude each other" in r.stderr
