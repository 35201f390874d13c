"""The wizard's step 2 as values: the probe plan of the tool-setter route and the NC programs."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from compensator.errors import ConfigError, ThermocompError
from compensator.io import load_model, write_text
from compensator.speed_programs import Program

from ..nc_programs import (
    EXTENSIONS,
    calibration_profile,
    rest_hours,
    to_nc,
    validation_profile,
    with_probe_stops,
)
from ..toolsetter_plan import ProbePlan
from .model import WizardSession

PROBE_MOVES_S = 10.0
"""The rapid moves to the tool setter and back, on top of the cycle's measuring time [s]: the
default of ``--probe-dwell-s`` with the cycle's measuring time."""


def programs(session: WizardSession) -> dict[str, Program]:
    """The session's calibration program, and its validation program if it records one."""
    s = session
    if s.max_rpm is None or s.step_min is None or s.cooldown_min is None:
        raise ConfigError("the session has no program yet: run the wizard's step 2")
    every = s.probe_every_s if s.source == "tool-setter" else None
    cal = calibration_profile(
        s.max_rpm, step_min=s.step_min, cooldown_min=s.cooldown_min, probe_every_s=every
    )
    progs = {"calibration": cal}
    if s.validation:
        val = validation_profile(s.max_rpm, seed=int(s.validation_seed or 1))
        # with the tool setter alone, the validation run is measured by the same stops
        progs["validation"] = val if every is None else with_probe_stops(val, every)
    return progs


def cycle_s(session: WizardSession) -> float:
    """One tool-setter stop as planned, every touch included [s] (0 without the tool setter)."""
    if session.probe_plan is not None:
        return float(session.probe_plan.dwell_s)
    return float(session.probe_dwell_s or 0.0)


def former_time_constants(directory: Path) -> tuple[float, ...] | None:
    """The time constants of the newest readable model the session saved, if any."""
    models = (
        sorted((directory / "models").glob("*.json")) if (directory / "models").is_dir() else []
    )
    for p in reversed(models):
        try:
            return load_model(p).time_constants_s()
        except ThermocompError:
            continue
    return None


@dataclass(frozen=True)
class ProbesPlanned:
    """The plan step's value: the session with the plan in it, the plan, and what to say."""

    session: WizardSession
    plan: ProbePlan
    sparser_than_planned: bool
    """The stops given (``--probe-every-min``) are sparser than the plan's."""


def plan_probes(
    session: WizardSession,
    *,
    probe_spindle: str | None,
    touches: float | None,
    dwell_s: float | None,
    every_min: float | None,
    former_taus: tuple[float, ...] | None,
) -> ProbesPlanned:
    """The tool-setter route: how often the program stops for a measurement, and what the stops
    cost (``calibration.toolsetter_plan``). The arguments are the flags (None: not given); an
    answer the session holds stands where a flag is not given."""
    from ..probeprog import MAX_TOUCHES, measuring_time_s, probe_cycle, touch_time_s
    from ..toolsetter_plan import plan_probe_interval

    s = session
    dialect = str(s.dialect)
    spindle = probe_spindle or s.probe_spindle or "stop"
    if touches is None:
        touches = s.probe_touches
    n_touches: int | None = None
    if touches is not None:
        if not (math.isfinite(touches) and touches == int(touches) and 1 <= touches <= MAX_TOUCHES):
            raise ConfigError(
                f"--probe-touches {touches:g}: a whole number from 1 to {MAX_TOUCHES}"
            )
        if int(touches) > 1 and dialect == "heidenhain":
            raise ConfigError(
                "--probe-touches is not for heidenhain: TCH PROBE 481 measures once per call"
            )
        n_touches = int(touches)
    if dwell_s is not None:
        dwell, touch_s = float(dwell_s), 0.0  # the cycle as timed on the machine, every touch
    elif s.probe_dwell_s is not None:
        dwell, touch_s = float(s.probe_dwell_s), float(s.probe_touch_s or 0.0)
    else:
        # the cycle's own measuring time with its default feeds, one touch, and the moves to and
        # from the setter; each further touch adds one slow touch's time
        cycle = probe_cycle(
            dialect, spindle=spindle, approach_z_mm=-5.0 if dialect == "heidenhain" else None
        )
        dwell = round(measuring_time_s(cycle) + PROBE_MOVES_S)
        touch_s = 0.0 if dialect == "heidenhain" else touch_time_s(cycle)
    if not (math.isfinite(dwell) and 0 <= dwell <= 3600):
        raise ConfigError(f"--probe-dwell-s {dwell:g}: one tool-setter cycle's seconds, 0 to 3600")
    plan = plan_probe_interval(
        60 * float(s.step_min or 0.0),
        60 * float(s.cooldown_min or 0.0),
        dwell,
        min(former_taus) if former_taus else None,
        at_speed=spindle == "keep",
        touches=n_touches,
        touch_s=touch_s,
    )
    if every_min is None:
        every_min = s.probe_every_min
    sparser = False
    if every_min is not None:
        every_min = float(every_min)
        if not (math.isfinite(every_min) and 1 <= every_min <= 240):
            raise ConfigError(f"--probe-every-min {every_min:g}: 1 to 240 minutes")
        sparser = 60 * every_min > plan.interval_s
    every_s = 60 * every_min if every_min is not None else plan.interval_s
    planned = s.updated(
        probe_spindle=spindle,
        probe_touches=n_touches,
        probe_dwell_s=dwell,
        probe_touch_s=touch_s,
        probe_every_min=every_min,
        probe_every_s=every_s,
        probe_plan={
            "interval_s": every_s,
            "planned_interval_s": plan.interval_s,
            "dwell_s": plan.cycle_s,
            "touches": plan.touches,
            "bound": plan.bound,
            "fastest_tau_s": plan.fastest_tau_s,
            "tau_assumed": plan.tau_assumed,
        },
    )
    return ProbesPlanned(planned, plan, sparser)


@dataclass(frozen=True)
class ProgramFile:
    """One NC program written: its run, file, length and top speed."""

    run: str
    path: Path
    duration_s: float
    """The program's time, every tool-setter stop included [s]."""
    top_rpm: float


@dataclass(frozen=True)
class ProgramsWritten:
    session: WizardSession
    files: tuple[ProgramFile, ...]


def write_programs(
    session: WizardSession, directory: Path, former_taus: tuple[float, ...] | None
) -> ProgramsWritten:
    """The session's NC programs in its dialect, written into ``directory`` with the cold start
    they need; the session with their paths and the rest time."""
    s = session
    rest = rest_hours(former_taus)
    dialect = str(s.dialect)
    ext = EXTENSIONS[dialect]
    files = []
    for name, prog in programs(s.updated(rest_h=rest)).items():
        text = to_nc(
            prog,
            dialect,
            name=f"TC_{name[:5]}",
            notes=(
                f"MACHINE {s.machine_id} SPINDLE {s.spindle_id}",
                f"COLD START: SPINDLE AT REST FOR {rest:g} H BEFOREHAND",
            ),
        )
        path = directory / f"{name}{ext}"
        write_text(path, text)
        # with the tool setter, the program waits at each stop for the cycle
        files.append(
            ProgramFile(
                name,
                path,
                prog.duration_s + len(prog.probe_at_s) * cycle_s(s),
                max(sp for _, sp in prog.segments),
            )
        )
    done = s.updated(rest_h=rest, programs={f.run: str(f.path) for f in files})
    return ProgramsWritten(done, tuple(files))
