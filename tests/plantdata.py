"""Calibration data from the virtual plant: richer than any candidate model
(five thermal nodes, speed-dependent convection, coolant jacket, elastic term,
ambient drift, 0.05 um noise and 0.1 um quantisation)."""

from __future__ import annotations

from functools import lru_cache

from calibration.data import Run
from cnc_adapters.sim import SpindlePlant, preset
from compensator.programs import job_shop_day, paper_calibration, random_validation


@lru_cache(maxsize=None)
def plant_run(program: str, dt_s: float, seed: int, preset_name: str = "motorized-27k") -> Run:
    p = preset(preset_name)
    prog = {
        "calibration": lambda: paper_calibration(p.max_rpm),
        "validation": lambda: random_validation(p.max_rpm, seed=seed),
        "jobshop": lambda: job_shop_day(p.max_rpm, seed=seed, hours=4),
    }[program]()
    t, n = prog.sample(dt_s)
    r = SpindlePlant(p, seed=seed).run(t, n)
    return Run(f"{program}-{dt_s:g}s-{seed}", t, n, r.measured_um)
