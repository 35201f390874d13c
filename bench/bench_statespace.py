"""The state-space model's free run against one ``scipy.signal.lfilter`` pass of the same length,
measured side by side in one run.

The model has 16 inputs and 4 states: the form the identification fits (one first-order state
per time constant, each driven by speed, speed² and every input, and a static feed-through).
The log is 30 days at 1 Hz (2.59 M rows), with three clocks: the logger's regular 1 s; the
same with gaps (a 10-minute stop every day and one of two days); a wandering clock (steps
uniform in 0.9..1.1 s, no two alike).

For each clock, interleaved and best of ``--repeat``: one ``lfilter`` pass of one first-order
filter over a series of the same length (the baseline); the free run
(:meth:`StateSpaceModel.simulate_um`); and the previous free run, kept here as the reference
(one matrix product for every drive over the whole log, then one exact filter pass per state,
:func:`compensator.filters.lag`). Wall time, and the process's own CPU time, which other
processes on a shared machine disturb less. The free runs are checked against each other first.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_statespace.py [--repeat 5] [--days 30]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import scipy
from scipy.signal import lfilter

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from compensator.filters import Steps, lag
from compensator.statespace import SPEED_CLIP, InputChannel, StateSpaceModel
from compensator.units import SPEED_SCALE_RPM

INPUTS = 16
TAUS_S = (300.0, 1800.0, 5400.0, 16200.0)


def model(rng: np.random.Generator) -> StateSpaceModel:
    names = [f"temp{k:02d}_c" for k in range(INPUTS)]
    width = 2 + INPUTS
    fallback = StateSpaceModel(
        fitted_dt_s=1.0,
        speed_range_rpm=(0.0, 27000.0),
        taus_s=TAUS_S[:2],
        max_measured_um=50.0,
        drive_um=((1.0, 0.1), (2.0, 0.2)),
        feedthrough_um=(0.1, 0.0),
    )
    return StateSpaceModel(
        fitted_dt_s=1.0,
        speed_range_rpm=(0.0, 27000.0),
        taus_s=TAUS_S,
        max_measured_um=50.0,
        fallback=fallback,
        drive_um=tuple(tuple(rng.normal(0, 0.1, width)) for _ in TAUS_S),
        feedthrough_um=tuple(rng.normal(0, 0.01, width)),
        inputs=tuple(
            InputChannel(
                name=n,
                unit="degC",
                reference=22.0,
                trained_range=(15.0, 35.0),
                valid_range=(5.0, 45.0),
            )
            for n in names
        ),
    )


def previous_free_run(
    m: StateSpaceModel, speed: np.ndarray, t: np.ndarray, inputs: dict[str, np.ndarray]
) -> np.ndarray:
    """The free run as it was: every drive over the whole log from one matrix product (a block
    at a time), then one exact filter pass per state (inputs inside their range here)."""
    steps = Steps.of(t)
    gains = np.vstack([m.feedthrough_um, m.drive_um])
    refs = np.array([c.reference for c in m.inputs])
    constant = m.offset_um - float((gains[:, 2:] @ refs).sum())
    cap = SPEED_CLIP * m.speed_range_rpm[1]
    logged = [inputs[c.name] for c in m.inputs]
    y = np.empty((gains.shape[0], t.size))
    chunk = max(1024, 400_000 // gains.size)
    v = np.empty((gains.shape[1], min(chunk, t.size)))
    for s in range(0, t.size, chunk):
        e = min(s + chunk, t.size)
        vb = v[:, : e - s]
        np.abs(speed[s:e], out=vb[0])
        np.minimum(vb[0], cap, out=vb[0])
        vb[0] /= SPEED_SCALE_RPM
        np.multiply(vb[0], vb[0], out=vb[1])
        w = vb[2:]
        np.stack([u[s:e] for u in logged], out=w)
        np.minimum.reduce(w, axis=1), np.maximum.reduce(w, axis=1)  # the range check's cost
        np.matmul(gains, vb, out=y[:, s:e])
    out: np.ndarray = y[0]
    out += constant
    for tau, drive in zip(m.taus_s, y[1:]):
        out += lag(steps, drive, tau)
    return out


def clocks(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    regular = np.arange(n, dtype=float)
    dt = np.ones(n - 1)
    dt[86400 - 1 :: 86400] = 600.0  # a 10-minute stop each day
    dt[n // 2] = 2 * 86400.0
    return {
        "regular 1 s": regular,
        "regular with gaps": np.concatenate([[0.0], np.cumsum(dt)]),
        "wandering 0.9..1.1 s": np.cumsum(rng.uniform(0.9, 1.1, n)),
    }


def timed(fn: Callable[[], object]) -> tuple[float, float]:
    w, c = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - w, time.process_time() - c


def main(repeat: int, days: float) -> dict:
    rng = np.random.default_rng(0)
    n = int(days * 86400)
    m = model(rng)
    speed = np.repeat(rng.uniform(0, 27000, n // 600 + 1), 600)[:n]
    temps = {c.name: 22.0 + np.cumsum(rng.normal(0, 0.002, n)) for c in m.inputs}
    res: dict = {
        "rows": n,
        "inputs": INPUTS,
        "states": m.order,
        "repeat": repeat,
        "load_before": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "clocks": {},
    }
    for name, t in clocks(rng, n).items():
        new, old = m.simulate_um(speed, t, temps), previous_free_run(m, speed, t, temps)
        scale = float(np.max(np.abs(old)))
        diff = float(np.max(np.abs(new - old)))
        assert diff <= 1e-9 * scale, f"{name}: the free runs differ by {diff:g} um"
        runs: dict[str, Callable[[], object]] = {
            "lfilter": lambda: lfilter([0.01], [1.0, -0.99], speed),
            "free run": partial(m.simulate_um, speed, t, temps),
            "previous": partial(previous_free_run, m, speed, t, temps),
        }
        best = {k: [np.inf, np.inf] for k in runs}
        for _ in range(repeat):  # interleaved: a burst of load touches all three alike
            for k, fn in runs.items():
                w, c = timed(fn)
                best[k] = [min(best[k][0], w), min(best[k][1], c)]
        base = best["lfilter"]
        res["clocks"][name] = {
            "max_difference_um": diff,
            **{
                k: {
                    "wall_s": v[0],
                    "cpu_s": v[1],
                    "wall_vs_lfilter": v[0] / base[0],
                    "cpu_vs_lfilter": v[1] / base[1],
                }
                for k, v in best.items()
            },
        }
    res["load_after"] = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    return res


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5, help="best of this many, interleaved")
    ap.add_argument("--days", type=float, default=30.0, help="length of the 1 Hz log")
    args = ap.parse_args()
    res = main(args.repeat, args.days)
    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load "
        f"{res['load_before']:.1f} -> {res['load_after']:.1f}; Python {platform.python_version()}, "
        f"numpy {np.__version__}, scipy {scipy.__version__}, "
        f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}"
    )
    print(
        f"# {res['rows']:,} rows, {res['inputs']} inputs, {res['states']} states; best of "
        f"{res['repeat']}, interleaved; wall (CPU) time and the ratio to one lfilter pass"
    )
    for name, c in res["clocks"].items():
        lf = c["lfilter"]
        print(f"{name}: one lfilter pass {lf['wall_s'] * 1e3:.1f} ms ({lf['cpu_s'] * 1e3:.1f} ms)")
        for k in ("free run", "previous"):
            r = c[k]
            print(
                f"  {k:9s} {r['wall_s'] * 1e3:7.1f} ms ({r['cpu_s'] * 1e3:6.1f} ms)  "
                f"{r['wall_vs_lfilter']:5.1f}x ({r['cpu_vs_lfilter']:.1f}x) one lfilter pass"
            )
    print(json.dumps(res))
