"""Batch simulate throughput on a 10-million-sample log, against a plain lfilter pass. The
state-space model with 16 inputs has its own: bench/bench_statespace.py.

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
    print(json.dumps(res))
