"""Calibration data from the virtual plant: richer than any candidate model
(five thermal nodes, speed-dependent convection, coolant jacket, elastic term,
ambient drift, 0.05 um noise and 0.1 um quantisation)."""

from __future__ import annotations

from functools import cache

from calibration.runs import Run
from compensator.speed_programs import job_shop_day, paper_calibration, random_validation
from machine_sim import SpindlePlant, preset


@cache
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


def identify_runs(runs, **kw):
    """The product's one identification (``calibration.fit.fit_data``) on plant runs held in memory."""
    from calibration.fit import fit_data
    from calibration.identify import LogData

    return fit_data([LogData(r.name, r.time_s, r.speed_rpm, r.elongation_um) for r in runs], **kw)


def inputs_model(fit, spindle_id: str = "sim"):
    """The ridge model with the inputs of ``fit`` (an identification with inputs), with the
    speed-only model ``fit`` chose as its fallback, whether or not the inputs won the choice:
    for tests of what a model with inputs does in the runtime and replay."""
    from calibration.estimators import ridge_bank
    from calibration.fit import unit_of

    if fit.model.input_names:
        return fit.model
    ds = fit.dataset
    res = ridge_bank.fit(
        ds,
        grids=[ridge_bank.auto_grid(ds.time_s, ds.speed_rpm, ds.cycles, True)],
        input_names=tuple(ds.inputs),
    )
    return res.to_model(
        "ridge+inputs",
        units={n: unit_of(n) for n in ds.inputs},
        fallback=fit.model,
        fit={},
        spindle_id=spindle_id,
    )
