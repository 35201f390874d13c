"""The one way from run logs to a model: every caller (``thermocomp fit``, the wizard, the demo,
the tests and benchmarks) goes through :func:`fit_logs`, so the same logs give the same model
whoever fits them.

What it does once, for all of them:

- checks each log (:func:`calibration.data.run_from_log`);
- bridges each gap in a log by one rule, the last logged speed held across it
  (:func:`calibration.data.bridge_gaps`): a gap that begins at rest cools, one that begins at
  speed heats;
- fits on the measured rows: a log measured on every row goes to
  :func:`calibration.identify.identify`, one measured on some rows only (a journal export) to
  :func:`calibration.sparse.identify_sparse`; both choose by the same rules.

Pure computation on logs already read: no file I/O.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from compensator.errors import CalibrationError
from compensator.io.runlog import RunLog

from . import closedloop
from .data import Run, bridge_gaps, has_cooldown, run_from_log
from .identify import Identification, LogData, identify
from .sparse import identify_sparse

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


def log_data(logs: Sequence[RunLog], input_names: Sequence[str] = (),
             labels: Sequence[str] | None = None) -> tuple[list[LogData], list[str]]:
    """The logs checked, gaps bridged, the named inputs taken: what the identification fits.
    Returns the data and one line per log that had gaps."""
    labels = list(labels) if labels is not None else [lg.source or f"log{i + 1}" for i, lg in enumerate(logs)]
    if len(labels) != len(logs):
        raise CalibrationError(f"{len(labels)} labels for {len(logs)} logs")
    data, notes = [], []
    for label, lg in zip(labels, logs):
        run = run_from_log(lg, name=label, sparse=True)
        speed, gaps = bridge_gaps(run.time_s, run.speed_rpm)
        name = Path(label).name
        if gaps:
            notes.append(f"{name}: {len(gaps)} gap(s) of up to {max(g for _, g in gaps) / 3600:.1f} h: "
                         "integrated at the last logged speed (a gap that begins at rest cools)")
        inputs = {}
        for n in input_names:
            if n not in lg.extras:
                raise CalibrationError(f"{lg.source or name}: no column {n!r} for --inputs "
                                       f"(columns: {', '.join(lg.extras) or 'none'})")
            inputs[n] = np.asarray(lg.extras[n], dtype=float)
        data.append(LogData(name, run.time_s, speed, run.elongation_um, inputs))
    return data, notes


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
    sparse = next((d.name for d in data if not np.isfinite(d.elongation_um).all()), None)
    if sparse is not None:
        if probe_every_s is not None:
            raise CalibrationError("--probe-every plans the closed loop on an elongation measured on every "
                                   f"row; {sparse} has it on some rows only (sparse)")
        result = identify_sparse(data, input_names, units=units, progress=progress, nested=nested, **meta)
    else:
        result = identify(data, input_names, units=units, progress=progress, nested=nested,
                          physical=physical, probe_target_um=probe_target_um,
                          probe_every_s=probe_every_s, **meta)
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
