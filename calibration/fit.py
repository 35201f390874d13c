"""The one way from run logs to a model: every caller (``thermocomp fit``, the wizard, the demo,
the tests and benchmarks) goes through :func:`fit_logs`, so the same logs give the same model
whoever fits them.

What it does once, for all of them:

- checks each log (:func:`calibration.runs.run_from_log`);
- bridges each gap in a log by one rule, the last logged speed held across it
  (:func:`calibration.runs.bridge_gaps`): a gap that begins at rest cools, one that begins at
  speed heats;
- joins them into one :class:`calibration.dataset.Dataset`, whose measured rows are a mask (all
  true for a log measured on every row, some for a journal export), and fits it with
  :func:`calibration.identify.identify`, the one choice among the registered candidates.

Pure computation on logs already read: no file I/O.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from compensator.io.runlog import RunLog

from . import closedloop
from .runs import Run, has_cooldown
from .dataset import LogData, log_data
from .identify import Identification, identify

NO_COOLDOWN = "no log has a cool-down (10 min or more at rest after running)"
FEW_LEVELS = "distinct speed levels"
MIN_SPEED_LEVELS = 5
UNIT_SUFFIXES = (("_c", "degC"), ("_k", "K"), ("_pct", "%"), ("_kw", "kW"), ("_w", "W"), ("_a", "A"),
                 ("_nm", "N m"), ("_bar", "bar"))


def unit_of(name: str) -> str:
    """An input channel's unit from its name's suffix (``spindle_front_c`` is degC), else ``1``."""
    for suffix, unit in UNIT_SUFFIXES:
        if name.endswith(suffix):
            return unit
    return "1"


def fit_logs(logs: Sequence[RunLog], input_names: Sequence[str] = (), *,
             labels: Sequence[str] | None = None, nested: bool = True, physical: bool = True,
             probe_target_um: float | None = closedloop.DEFAULT_TARGET_UM,
             probe_every_s: float | None = None, units: Mapping[str, str] | None = None,
             progress: Callable[[str], None] | None = None, **meta: Any) -> Identification:
    """Identify a model from run logs: every candidate on the same whole-cycle folds, scored in free
    run, the choice printed with its reason (:class:`calibration.identify.Identification`).

    ``labels`` name the logs in the report (default: their file names); ``meta`` (spindle_id,
    machine_id, created_utc) goes into the model. Raises :class:`CalibrationError` in one line
    for logs that cannot calibrate.
    """
    data, notes = log_data(logs, input_names, labels)
    result = fit_data(data, input_names, nested=nested, physical=physical, probe_target_um=probe_target_um,
                      probe_every_s=probe_every_s, units=units, progress=progress, **meta)
    result.warnings[:0] = notes
    return result


def fit_data(data: Sequence[LogData], input_names: Sequence[str] = (), *, nested: bool = True,
             physical: bool = True, probe_target_um: float | None = closedloop.DEFAULT_TARGET_UM,
             probe_every_s: float | None = None, units: Mapping[str, str] | None = None,
             progress: Callable[[str], None] | None = None, **meta: Any) -> Identification:
    """:func:`fit_logs` on logs already checked and bridged (:func:`log_data`), or on series held
    in memory (the virtual plant's): dense or sparse by the elongation's NaN cells."""
    units = dict(units) if units is not None else {n: unit_of(n) for n in input_names}
    result = identify(data, input_names, units=units, progress=progress, nested=nested, physical=physical,
                      probe_target_um=probe_target_um, probe_every_s=probe_every_s, **meta)
    result.warnings[:0] = coverage_warnings(data)
    return result


def coverage_warnings(data: Sequence[LogData]) -> list[str]:
    """What the logs cannot teach a model, said before anyone trusts it: no cool-down (the
    dissipation time constant is then not identifiable) and too few speed levels (n and n² are
    then poorly separated)."""
    out = []
    if not any(has_cooldown(Run(d.name, d.time_s, d.speed_rpm, d.elongation_um)) for d in data):
        out.append(NO_COOLDOWN + ": the cooling time constant is not identifiable, and a slow heat-up "
                   "looks like a long time constant. Record a cool-down at 0 rpm")
    levels = np.unique(np.round(np.concatenate([np.abs(d.speed_rpm) for d in data]), -2))
    if levels.size < MIN_SPEED_LEVELS:
        out.append(f"only {levels.size} {FEW_LEVELS}: the n and n² terms are poorly separated; use a "
                   f"staircase of {MIN_SPEED_LEVELS} or more speeds")
    return out
