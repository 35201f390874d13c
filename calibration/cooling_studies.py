"""Active cooling on the virtual plant: the excitation run, the model, and paper 000's scenarios.

- :func:`excitation_run` drives the plant through heat-up/cool-down cycles while the chiller set
  point steps at random (within the chiller's range), so that a model can learn the coolant's
  effect: a speed-only model cannot see the coolant, and a loop closed on it would run the
  chiller to a limit.
- :func:`fit_cooling_model` fits it with the identification machinery (``calibration.identify``:
  every candidate on the same cycle folds, in free run), with the machine's temperatures as
  inputs, as paper 000 estimates Ê from temperatures.
- :func:`simulate_cooling` closes the loop on the plant, the way the runtime does: the virtual
  machine's lagged, noisy sensors, the model stepped every ``dt_s``, the pure
  :class:`compensator.cooling_law.CoolingLaw`, the chiller's own ramp and lag; ``offset=True`` also
  writes A = −Ê through the one shaper (``mode = "both"``).
- :data:`SCENARIOS` are the paper's four work conditions.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from compensator.cooling_law import CoolingLaw, CoolingState, PidGains
from compensator.errors import CalibrationError
from compensator.shaping import ShaperConfig, shape_series
from compensator.speed_programs import Program
from machine_sim.plant import PlantParams, SpindlePlant
from machine_sim.vcnc import VirtualMachine

from . import stability
from .identify import Identification, LogData, identify

COOLING_INPUTS: tuple[str, ...] = ("bearing_temp_c", "motor_temp_c", "coolant_temp_c")
"""The temperatures the cooling model reads: the front bearing, the housing and the coolant
(paper 000: housing temperatures near the heat sources)."""


@dataclass(frozen=True)
class Scenario:
    """One of paper 000's work conditions: the speed program, the shop, RITE."""

    name: str
    title: str
    segments: tuple[tuple[float, float], ...]
    """(duration_s, speed_rpm)."""
    rite_um: float
    air_c: float
    preheat_c: float

    def program(self) -> Program:
        return Program(self.name, self.segments)


_H = 8 * 3600.0
SCENARIOS: dict[str, Scenario] = {
    "wc1": Scenario(
        "wc1", "3000 rpm, TA 18 degC, TC 16 degC, RITE 17 um", ((_H, 3000.0),), 17.0, 18.0, 16.0
    ),
    "wc2": Scenario(
        "wc2", "2000 rpm, TA 18 degC, TC 14 degC, RITE 9 um", ((_H, 2000.0),), 9.0, 18.0, 14.0
    ),
    "wc3": Scenario(
        "wc3",
        "3000/4000/2000 rpm, TA 18 degC, TC 16 degC, RITE 17 um",
        ((6000.0, 3000.0), (9000.0, 4000.0), (_H - 15000.0, 2000.0)),
        17.0,
        18.0,
        16.0,
    ),
    "wc4": Scenario(
        "wc4",
        "2000/3000/2500 rpm, TA 16 degC, TC 14 degC, RITE 12 um",
        ((6000.0, 2000.0), (7200.0, 3000.0), (_H - 13200.0, 2500.0)),
        12.0,
        16.0,
        14.0,
    ),
}
"""Paper 000's work conditions #1-#4 (speeds and switch times from the paper, 8 h each)."""


def plant_for(params: PlantParams, air_c: float, chiller_c: float) -> PlantParams:
    """The preset in a shop at ``air_c`` with the chiller at ``chiller_c`` overnight."""
    return replace(params, ambient_c=air_c, chiller_c=chiller_c)


def excitation_run(
    params: PlantParams,
    *,
    seed: int = 11,
    cycles: int = 4,
    dt_s: float = 60.0,
    run_h: float = 6.0,
    rest_h: float = 5.0,
) -> tuple[LogData, dict[str, np.ndarray]]:
    """Heat-up/cool-down cycles at mixed speeds with the chiller set point stepped at random
    every 20-60 min within ±5 K of its constant: a log a model with the coolant can be fitted on.
    Returns the log (with :data:`COOLING_INPUTS`) and its extra columns (set point, supply)."""
    rng = np.random.default_rng(seed)
    top = params.max_rpm
    speeds = np.array([1 / 6, 1 / 3, 5 / 12, 1 / 2, 7 / 12, 2 / 3, 5 / 6]) * top
    segs: list[tuple[float, float]] = []
    for _ in range(cycles):
        left = run_h * 3600.0
        while left > 0:
            d = min(left, float(rng.uniform(1800.0, 3600.0)))
            segs.append((d, float(np.round(rng.choice(speeds), -2))))
            left -= d
        segs.append((rest_h * 3600.0, 0.0))
    t, n = Program("cooling-excitation", tuple(segs)).sample(dt_s)
    lo = max(params.chiller_min_c, params.chiller_c - 5.0)
    hi = min(params.chiller_max_c, params.chiller_c + 5.0)
    sp = np.empty_like(t)
    value, change_at = params.chiller_c, 0.0
    for k, x in enumerate(t):
        if x >= change_at:
            value, change_at = float(rng.uniform(lo, hi)), x + float(rng.uniform(1200.0, 3600.0))
        sp[k] = value
    plant = SpindlePlant(params, seed=seed)
    run = plant.run(t, n, sp)
    sensors = plant.sensor_channels(run)
    log = LogData(
        "cooling-excitation",
        run.time_s,
        run.speed_rpm,
        run.measured_um,
        {k: sensors[k] for k in COOLING_INPUTS},
    )
    return log, {"chiller_setpoint_c": sp, "supply_c": np.asarray(run.supply_c)}


def fit_cooling_model(
    params: PlantParams,
    *,
    seed: int = 11,
    inputs: Sequence[str] = COOLING_INPUTS,
    progress: Any = None,
) -> Identification:
    """The model the loop estimates Ê with, fitted on :func:`excitation_run` by the default
    identification (cycle folds, free run)."""
    log, _ = excitation_run(params, seed=seed)
    return identify(
        [log],
        inputs,
        probe_target_um=None,
        progress=progress,
        spindle_id=f"sim-{params.name}",
        machine_id="virtual",
    )


@dataclass(frozen=True)
class CoolingRun:
    """One closed-loop run, sampled every ``dt_s``."""

    mode: str
    time_s: np.ndarray
    speed_rpm: np.ndarray
    true_um: np.ndarray
    measured_um: np.ndarray
    estimate_um: np.ndarray
    setpoint_c: np.ndarray
    supply_c: np.ndarray
    coolant_c: np.ndarray
    closed: np.ndarray
    """bool: the loop was closed (after the start rule)."""
    offset_um: np.ndarray
    """The offset written (0 unless the offset runs too)."""
    switch_s: float | None = None
    """When the loop closed (Ê reached RITE)."""
    meta: Mapping[str, Any] = field(default_factory=dict)

    @property
    def error_um(self) -> np.ndarray:
        """What the part sees: the measured growth plus the offset (the growth alone without one)."""
        return self.measured_um + self.offset_um

    def columns(self) -> dict[str, np.ndarray]:
        return {
            "time_s": self.time_s,
            "speed_rpm": self.speed_rpm,
            "elongation_um": self.measured_um,
            "estimate_um": self.estimate_um,
            "offset_um": self.offset_um,
            "chiller_setpoint_c": self.setpoint_c,
            "supply_c": np.round(self.supply_c, 3),
            "coolant_temp_c": np.round(self.coolant_c, 3),
            "cooling_closed": self.closed.astype(np.int64),
        }


def simulate_cooling(
    params: PlantParams,
    program: Program,
    model: Any,
    law: CoolingLaw | None,
    *,
    dt_s: float = 1.0,
    seed: int = 0,
    offset: bool = False,
    shaper: ShaperConfig | None = None,
    sample_s: float = 60.0,
) -> CoolingRun:
    """Run ``program`` on the plant with the chiller held at ``params.chiller_c`` (``law`` None:
    constant cooling) or driven by ``law`` every ``dt_s`` on the estimate of ``model`` (any
    :class:`~compensator.predictor.Predictor`; its inputs from the machine's sensors). With
    ``offset``, A = −Ê is shaped by the runtime's shaper and applied. Sampled every
    ``sample_s``."""
    if not (math.isfinite(dt_s) and dt_s > 0 and sample_s >= dt_s):
        raise CalibrationError(f"simulate_cooling: dt {dt_s} s, sample {sample_s} s")
    plant = SpindlePlant(params, seed=seed)
    now = [0.0]
    vm = VirtualMachine(plant, program, clock=lambda: now[0], plant_dt_s=dt_s)
    names = tuple(model.input_names)
    state: Any = model.start(0.0, 0.0, _inputs(vm, names))  # the growth counts from the cold start
    law_state: CoolingState | None = law.initial(params.chiller_c) if law is not None else None
    steps = int(round(program.duration_s / dt_s))
    every = max(1, int(round(sample_s / dt_s)))
    rows: list[tuple[float, ...]] = []
    switch_s = None
    for k in range(1, steps + 1):
        now[0] = k * dt_s
        vm.advance()
        speed = vm.speed_rpm
        state = model.step(state, speed, dt_s, _inputs(vm, names))
        est = float(state.elongation_um)
        if law is not None and law_state is not None:
            law_state = law.step(law_state, est, dt_s, running=speed > 1.0)
            plant.set_chiller_setpoint_c(law_state.setpoint_c)
            if switch_s is None and law_state.phase == "closed":
                switch_s = now[0]
        if k % every == 0:
            true = plant.true_elongation_um()
            rows.append(
                (
                    now[0],
                    speed,
                    true,
                    float(plant.measure_um(true)),
                    est,
                    plant.chiller_setpoint_c,
                    plant.supply_c,
                    plant.coolant_c,
                    float(law_state is not None and law_state.phase == "closed"),
                )
            )
    a = np.array(rows, dtype=float)
    t, n, true_um, meas_um, est_um = a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4]
    off = np.zeros_like(t)
    if offset:
        cfg = shaper or ShaperConfig()
        off = shape_series(cfg, t, n, est_um).offset_um
    mode = ("pid" if law is not None else "constant") + ("+offset" if offset else "")
    return CoolingRun(
        mode,
        t,
        n,
        true_um,
        meas_um,
        est_um,
        a[:, 5],
        a[:, 6],
        a[:, 7],
        a[:, 8] > 0.5,
        off,
        switch_s,
        {"dt_s": dt_s, "seed": seed, "plant": params.name},
    )


def _inputs(vm: VirtualMachine, names: Sequence[str]) -> dict[str, float] | None:
    if not names:
        return None
    values = vm.sensor_values()
    return {k: values[k] for k in names}


@dataclass(frozen=True)
class ComparisonRow:
    scenario: str
    mode: str
    figures: stability.StabilityFigures
    switch_s: float | None
    setpoint_range_c: tuple[float, float]

    def row(self) -> dict[str, Any]:
        f = self.figures
        return {
            "scenario": self.scenario,
            "mode": self.mode,
            "equilibrium_min": None if f.equilibrium_s is None else round(f.equilibrium_s / 60, 1),
            "tevr_um": None if f.tevr_um is None else round(f.tevr_um, 2),
            "mean_after_um": None if f.mean_after_um is None else round(f.mean_after_um, 2),
            "max_abs_um": round(f.max_abs_um, 2),
            "switch_min": None if self.switch_s is None else round(self.switch_s / 60, 1),
            "setpoint_c": [round(v, 1) for v in self.setpoint_range_c],
        }


def figures_of(run: CoolingRun) -> ComparisonRow:
    return ComparisonRow(
        run.meta.get("scenario", ""),
        run.mode,
        stability.stability(run.time_s, run.error_um),
        run.switch_s,
        (float(run.setpoint_c.min()), float(run.setpoint_c.max())),
    )


def law_for(scenario: Scenario, gains: PidGains | None = None, **limits: Any) -> CoolingLaw:
    """The paper's controller for a scenario: preheat at its TC, RITE, the gains (paper's by
    default), limits (default 8-26 degC, 1 K/min)."""
    cfg: dict[str, Any] = {"min_c": 8.0, "max_c": 26.0, "rate_k_per_min": 1.0, **limits}
    return CoolingLaw(
        rite_um=scenario.rite_um,
        preheat_c=scenario.preheat_c,
        gains=gains or PidGains.paper(),
        **cfg,
    )


def run_scenario(
    params: PlantParams,
    scenario: Scenario,
    model: Any,
    mode: str,
    *,
    gains: PidGains | None = None,
    dt_s: float = 1.0,
    seed: int = 0,
    shaper: ShaperConfig | None = None,
    sample_s: float = 60.0,
) -> CoolingRun:
    """``mode``: ``constant``, ``pid``, ``pid+offset`` (``both``) or ``constant+offset``."""
    p = plant_for(params, scenario.air_c, scenario.preheat_c)
    law = law_for(scenario, gains) if mode.startswith("pid") else None
    run = simulate_cooling(
        p,
        scenario.program(),
        model,
        law,
        dt_s=dt_s,
        seed=seed,
        offset=mode.endswith("+offset"),
        shaper=shaper,
        sample_s=max(sample_s, dt_s),
    )
    return replace(run, meta={**run.meta, "scenario": scenario.name})
