"""The virtual spindle plant: 8 simulated hours at 1 s steps (target: well under a second)."""

from __future__ import annotations

import platform
import time

import numpy as np

from compensator.speed_programs import job_shop_day
from machine_sim import SpindlePlant, preset


def main() -> dict:
    p = preset("motorized-27k")
    t, n = job_shop_day(p.max_rpm, seed=1, hours=8).sample(1.0)
    t, n = t[: 8 * 3600 + 1], n[: 8 * 3600 + 1]
    best = np.inf
    for _ in range(3):
        plant = SpindlePlant(p, seed=1)
        t0 = time.perf_counter()
        plant.run(t, n)
        best = min(best, time.perf_counter() - t0)
    return {"steps": int(t.size), "seconds": best, "times_real_time": 8 * 3600 / best}


if __name__ == "__main__":
    r = main()
    print(f"# {platform.machine()}, Python {platform.python_version()}")
    print(
        f"8 h of plant at 1 s ({r['steps']} steps): {r['seconds']:.3f} s = {r['times_real_time']:.0f}x real time"
    )
