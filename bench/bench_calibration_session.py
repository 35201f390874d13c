"""Costs of a calibration session and of choosing inputs.

1. Recorder sample cost: one sample = speed over OPC UA (virtual CNC, loopback) + displacement
   from an ASCII amplifier on a socat pseudo-terminal + the checks + one flushed log row.
   It bounds the fastest sample period a recording can keep.
2. The identification with inputs (`calibration.fit.fit_data`, what `thermocomp fit --inputs`
   runs) on two 6-h runs at 20 s with the 5 sensor channels of the virtual plant, and on four
   runs at 30 s with 16 channels; the same without inputs is timed apart.
Run: .venv/bin/python bench/bench_calibration_session.py
"""

from __future__ import annotations

import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from devices import LineDevice, PtyPair

from calibration.acquire import AcquireConfig, Recorder
from calibration.fit import fit_data
from calibration.identify import LogData
from calibration.nc_programs import calibration_profile
from cnc_adapters.opcua import OpcUaAdapter
from cnc_adapters.sensors import AsciiSensor
from compensator.speed_programs import paper_calibration, random_validation
from machine_sim import SpindlePlant, preset
from machine_sim.vcnc import SimClock, VirtualCNC, VirtualMachine, running

P = preset("motorized-27k")


def recorder_cost(n: int = 1000) -> np.ndarray:
    vm = VirtualMachine(
        SpindlePlant(P, seed=1), calibration_profile(P.max_rpm), clock=SimClock(1.0)
    )
    with tempfile.TemporaryDirectory() as tmp, running(VirtualCNC(vm)) as cnc:
        pty = PtyPair(Path(tmp))
        dev = LineDevice(pty.dev, lambda text, mode: f"{vm.measured_um:+09.3f}")
        times: list[float] = []
        fake = {"t": 1.7e9}

        def clock() -> float:
            return fake["t"]

        def sleep(dt: float) -> None:
            fake["t"] += dt

        def on_sample(sample, rec) -> None:
            times.append(time.perf_counter())
            fake["t"] += 1.0
            if len(times) >= n:
                raise KeyboardInterrupt

        ctl = OpcUaAdapter(cnc.url, preset="virtual-cnc", verify_writes=False)
        sensor = AsciiSensor(pty.ctl, request="M", baudrate=115200)
        rec = Recorder(
            ctl,
            sensor,
            Path(tmp) / "run.csv",
            calibration_profile(P.max_rpm),
            max_rpm=P.max_rpm,
            config=AcquireConfig(rate_s=1.0, start_timeout_s=1e9),
            clock=clock,
            sleep=sleep,
            on_sample=on_sample,
        )
        try:
            rec.run()
        except KeyboardInterrupt:
            pass
        ctl.close()
        sensor.close()
        dev.stop()
        pty.close()
    return np.diff(times) * 1e3


def plant_input_run(prog, seed: int, dt_s: float) -> LogData:
    t, n = prog.sample(dt_s)
    plant = SpindlePlant(P, seed=seed)
    r = plant.run(t, n)
    return LogData(f"{prog.name}-{seed}", t, n, r.measured_um, plant.sensor_channels(r))


def main() -> None:
    print(
        f"machine: {platform.processor() or platform.machine()}, Python {platform.python_version()}"
    )
    ms = recorder_cost()
    print(
        f"recorder, one sample (OPC UA speed + ASCII probe on a pty + checks + flushed row): "
        f"p50 {np.percentile(ms, 50):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms over {ms.size} samples"
    )
    runs = [
        plant_input_run(paper_calibration(P.max_rpm), 1, 20.0),
        plant_input_run(random_validation(P.max_rpm, seed=2, hold_min=(10, 30)), 2, 20.0),
    ]
    t0 = time.perf_counter()
    fit_data(runs)
    t1 = time.perf_counter()
    fit = fit_data(runs, list(runs[0].inputs))
    t2 = time.perf_counter()
    rows = sum(r.time_s.size for r in runs)
    print(
        f"2 runs x {rows // 2} rows: speed only {t1 - t0:.1f} s; with 5 channels {t2 - t1:.1f} s "
        f"(chosen {fit.chosen.name}, {len(fit.model.input_names)} inputs)"
    )
    rng = np.random.default_rng(0)
    runs4 = [plant_input_run(paper_calibration(P.max_rpm), 1, 30.0)] + [
        plant_input_run(random_validation(P.max_rpm, seed=s, hold_min=(10, 30)), s, 30.0)
        for s in (2, 3, 4)
    ]
    for r in runs4:
        for k in range(11):
            r.inputs[f"extra{k:02d}_c"] = 21 + np.cumsum(rng.normal(0, 0.02, r.time_s.size))
    t3 = time.perf_counter()
    fit4 = fit_data(runs4, list(runs4[0].inputs))
    t4 = time.perf_counter()
    print(
        f"4 runs, 16 channels: {t4 - t3:.1f} s (chosen {fit4.chosen.name}, {len(fit4.model.input_names)} inputs)"
    )


if __name__ == "__main__":
    main()
