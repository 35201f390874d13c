"""Replay shows what the service did: a service journal replayed through `calibration.replay`
gives the service's estimate and the offset it held, step for step.

The service runs on the in-process virtual machine tool (the `sim` link) on a fake clock: a model
with five inputs and its speed-only fallback, the observer on, a job-shop day that runs above
the calibrated speed range, an input sensor that fails (NaN, then frozen), tool-setter probe
cycles read through the link and measurements sent as `thermocomp measure` sends them, and a
reload of the configuration half-way through.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from plantdata import inputs_model

from calibration.fit import fit_data
from calibration.identify import LogData
from calibration.replay import probes_from_file, replay
from compensator.io import load_any_model, read_run_log, save_model
from compensator.speed_programs import Program, job_shop_day, paper_calibration, random_validation
from compensator.units import RANGE_TOLERANCE
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import ToolSetter, VirtualMachine
from thermocomp.runtime import Alarm, SpindleRuntime
from thermocomp.runtime.config import load_config

P = preset("motorized-27k")
SENSORS = ("bearing_temp_c", "motor_temp_c", "coolant_temp_c", "ambient_c", "spindle_load_pct")
WALL0 = 1699923600.0  # 01:00 UTC: three hours in one journal file
TOP_RPM = 0.7 * P.max_rpm  # calibrated up to here; the day runs faster at times


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    logs = []
    for prog, seed in (
        (paper_calibration(TOP_RPM), 1),
        (random_validation(TOP_RPM, seed=2, hold_min=(10, 30)), 2),
    ):
        t, n = prog.sample(20.0)
        plant = SpindlePlant(P, seed=seed)
        r = plant.run(t, n)
        ch = plant.sensor_channels(r)
        logs.append(
            LogData(f"{prog.name}-{seed}", t, n, r.measured_um, {k: ch[k] for k in SENSORS})
        )
    model = inputs_model(fit_data(logs, SENSORS, spindle_id="sim", nested=False, physical=False))
    assert model.input_names and model.fallback is not None
    path = tmp_path_factory.mktemp("model") / "model.json"
    save_model(path, model)
    return path


def write_config(tmp_path: Path, model: Path, save_every_s: float) -> Path:
    path = tmp_path / "machine.toml"
    path.write_text(f"""state_dir = "{tmp_path / "state"}"
watchdog = false
journal_fsync_s = 3600.0
[[spindle]]
name = "s1"
model = "{model}"
period_s = 1.0
state_save_every_s = {save_every_s}
adapter = {{url = "sim://"}}
[spindle.shaping]
max_offset_um = 80.0
max_rate_um_per_s = 1.0
not_cutting_rate_um_per_s = 20.0
deadband_um = 0.1
[spindle.faults]
input_stale_s = 240.0
input_recover_s = 30.0
[spindle.observer]
enabled = true
sigma_um = 0.5
""")
    return path


def test_replay_of_a_service_journal_reproduces_its_estimate_and_offset_step_for_step(
    tmp_path, model_path
):
    clock = {"t": 0.0}
    vm = VirtualMachine(
        SpindlePlant(P, seed=5),
        job_shop_day(P.max_rpm, seed=3, hours=3),
        clock=lambda: clock["t"],
        tool_setter=ToolSetter(dwell_s=20.0, seed=4),
    )
    cfg = load_config(write_config(tmp_path, model_path, 600.0))

    def start(previous=None) -> SpindleRuntime:
        return SpindleRuntime(
            cfg.spindle[0],
            cfg.state_dir,
            cfg.journal_path,
            journal_fsync_s=cfg.journal_fsync_s,
            clock=lambda: clock["t"],
            wall=lambda: WALL0 + clock["t"],
            adapter=SimAdapter(machine=vm),
            previous=previous,
        )

    rt = start()
    alarms = Alarm.NONE
    for k in range(1, 3 * 3600 + 1):
        clock["t"] = float(k)
        if k == 1500:
            vm.sensor_faults["bearing_temp_c"] = "nan"
        elif k == 1800:
            vm.sensor_faults.clear()
        elif k == 5000:
            vm.sensor_faults["motor_temp_c"] = "frozen"
        elif k == 5600:
            vm.sensor_faults.clear()
        if k % 1800 == 900:
            vm.start_probe()  # a tool-setter cycle, read through the link
        if k in (2500, 7000):
            rt.submit(vm.plant.true_elongation_um() + 1.5, 0.5)  # `thermocomp measure`
        if k == 4000:  # SIGHUP: a new configuration goes on from the old one
            cfg = load_config(write_config(tmp_path, model_path, 300.0))
            new = start(previous=rt)
            new.take_journal(rt)
            rt.close()
            rt = new
        alarms |= rt.cycle()["alarms"]
    rt.close()
    # what the scenario is made of really happened
    for alarm in (Alarm.OVER_RANGE, Alarm.INPUT_FALLBACK):
        assert alarms & alarm, alarm
    journal_dir = cfg.state_dir / "journal"
    (journal,) = sorted(journal_dir.glob("s1-*.csv"))
    (measurements,) = sorted(journal_dir.glob("s1.measurements-*.csv"))
    log = read_run_log(journal)
    outcomes = [
        line.split(",")[5]
        for line in measurements.read_text().splitlines()
        if line and not line.startswith(("#", "time_s"))
    ]
    assert outcomes.count("accepted") >= 4 and len(outcomes) >= 7, outcomes

    model = load_any_model(model_path)
    probes = probes_from_file(log, str(measurements), 0.5)
    rep = replay(
        model,
        log,
        shaping=cfg.spindle[0].shaping,
        probes=probes,
        estimate=cfg.spindle[0].estimate(model),
        compare=False,
    )
    service_estimate = np.asarray(log.extras["predicted_um"], dtype=float)
    service_offset = np.asarray(log.extras["offset_um"], dtype=float)
    assert len(rep.predicted_um) == 3 * 3600
    np.testing.assert_allclose(rep.predicted_um, service_estimate, rtol=0, atol=1e-6)
    np.testing.assert_allclose(rep.applied_offset_um, service_offset, rtol=0, atol=1e-6)
    assert rep.report["probes"] == len(outcomes) and rep.report[
        "probes_rejected"
    ] == outcomes.count("rejected")
    assert any("fallback stands in" in w for w in rep.report["warnings"])
    # the service journals the speed it stepped with: clamped to the calibrated top, the alarm beside it
    over = (np.asarray(log.extras["alarms"], dtype=int) & int(Alarm.OVER_RANGE)) != 0
    top = model.fallback.speed_range_rpm[1]
    assert over.sum() > 60 and np.abs(log.speed_rpm[over]).min() == pytest.approx(top)


def test_the_vectorised_replay_is_the_cycle_by_cycle_estimate(calibrated_model):
    """A speed-only model without probes replays vectorised; it gives what the service's
    cycle-by-cycle estimate gives, over-range speeds (clamped) and jittery steps included."""
    from compensator.estimate import Estimate

    model = load_any_model(calibrated_model)
    top = model.speed_range_rpm[1]
    rng = np.random.default_rng(1)
    steps = tuple(
        (float(d), float(f) * top)
        for d, f in zip(rng.uniform(120, 900, 24), rng.uniform(0, 1.3, 24))
    )
    t, n = Program("over-range", (*steps, (1800.0, 0.0))).sample(1.0)
    t = np.cumsum(rng.uniform(0.5, 1.5, t.size))  # a clock that wanders
    t[t.size // 2 :] += 1800.0  # and a gap
    for policy in ("clamp", "extrapolate"):
        est = Estimate(model, over_range=policy)
        fast = est.simulate_um(n, t, 3.0)
        series = est.run(est.begin(3.0, float(n[0])), t, n)
        np.testing.assert_allclose(series.estimate_um, fast, rtol=0, atol=1e-9)
        assert (
            series.over_range.any()
            and (series.over_range == (np.abs(n) > top * (1 + RANGE_TOLERANCE))).all()
        )
        clamped = np.abs(series.speed_rpm).max()
        limit = top * (1 + RANGE_TOLERANCE)
        assert (clamped <= limit) if policy == "clamp" else (clamped > limit)
