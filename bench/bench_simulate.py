"""Batch simulate throughput on a 10-million-sample log, against a plain lfilter pass; and
the state-space model with 16 inputs and 4 states on a 30-day 1 Hz log (2.6 M samples), against
one lfilter pass over the same length.

lfilter over the same data is the practical ceiling for a first-order
recursion. Run: .venv/bin/python bench/bench_simulate.py
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from conftest import first_order, rich_form

N = 10_000_000


def best_of(fn, repeat=3):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> dict:
    rng = np.random.default_rng(0)
    speeds = np.repeat(rng.uniform(0, 27000, N // 600 + 1), 600)[:N]
    uniform = np.arange(N) * 1.0
    jitter = np.cumsum(rng.uniform(0.9, 1.1, N))
    base = best_of(lambda: lfilter([0.01], [1.0, -0.99], speeds))
    out = {"samples": N, "lfilter_s": base, "lfilter_msps": N / base / 1e6, "cases": []}
    cases = [
        ("first-order, uniform dt", first_order(), uniform),
        ("first-order, jittery dt", first_order(), jitter),
        ("two-state + n*S + elastic, uniform dt", rich_form(), uniform),
        ("two-state + n*S + elastic, jittery dt", rich_form(), jitter),
    ]
    for name, model, times in cases:
        s = best_of(lambda: model.simulate(speeds, times))
        out["cases"].append(
            {"case": name, "seconds": s, "msps": N / s / 1e6, "vs_lfilter": s / base}
        )
    out["state_space"] = state_space_case(rng)
    return out


def state_space_case(rng: np.random.Generator) -> dict:
    """16 inputs, 4 states, a 30-day 1 Hz log: the model's simulate_um against one lfilter pass
    of the same length, in one run; with uniform steps and with a clock that wanders."""
    from compensator.statespace import InputChannel, StateSpaceModel

    n = 30 * 86400
    taus = (300.0, 1800.0, 5400.0, 16200.0)
    names = [f"temp{k:02d}_c" for k in range(16)]
    fallback = StateSpaceModel(
        fitted_dt_s=1.0,
        speed_range_rpm=(0.0, 27000.0),
        taus_s=taus[:2],
        max_measured_um=50.0,
        drive_um=((1.0, 0.1), (2.0, 0.2)),
        feedthrough_um=(0.1, 0.0),
    )
    model = StateSpaceModel(
        fitted_dt_s=1.0,
        speed_range_rpm=(0.0, 27000.0),
        taus_s=taus,
        max_measured_um=50.0,
        fallback=fallback,
        drive_um=tuple(tuple(rng.normal(0, 0.1, 18)) for _ in taus),
        feedthrough_um=tuple(rng.normal(0, 0.01, 18)),
        inputs=tuple(
            InputChannel(
                name=nm,
                unit="degC",
                reference=22.0,
                trained_range=(15.0, 35.0),
                valid_range=(5.0, 45.0),
            )
            for nm in names
        ),
    )
    speeds = np.repeat(rng.uniform(0, 27000, n // 600 + 1), 600)[:n]
    temps = {nm: 22.0 + np.cumsum(rng.normal(0, 0.002, n)) for nm in names}
    base = best_of(lambda: lfilter([0.01], [1.0, -0.99], speeds))
    out = {"samples": n, "lfilter_s": base}
    for label, t in (
        ("uniform", np.arange(n, dtype=float)),
        ("jittery", np.cumsum(rng.uniform(0.9, 1.1, n))),
    ):
        s = best_of(lambda: model.simulate_um(speeds, t, temps, None))
        out[label] = {"seconds": s, "vs_lfilter": s / base}
    return out


if __name__ == "__main__":
    res = main()
    load = f", load {os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else ""
    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores{load}, "
        f"Python {platform.python_version()}, numpy {np.__version__}"
    )
    print(f"plain lfilter: {res['lfilter_s']:.3f} s = {res['lfilter_msps']:.1f} M samples/s")
    for c in res["cases"]:
        print(
            f"{c['case']:40s} {c['seconds']:.3f} s = {c['msps']:5.1f} M samples/s  ({c['vs_lfilter']:.2f}x lfilter)"
        )
    ss = res["state_space"]
    print(
        f"state space, 16 inputs, 4 states, 30 days at 1 Hz: one lfilter pass {ss['lfilter_s']:.3f} s"
    )
    for label in ("uniform", "jittery"):
        print(
            f"  {label:8s} dt: {ss[label]['seconds']:.3f} s ({ss[label]['vs_lfilter']:.1f}x one lfilter pass)"
        )
    print(json.dumps(res))
