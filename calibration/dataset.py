"""The one dataset every estimator fits: the logs end to end, with the measured rows as a mask.

- :func:`log_data` checks each run log (its time must be seconds: judged by its sample period
  and span, :func:`compensator.io.runlog.time_unit_refusal`) and bridges its gaps by one rule, the last logged speed
  held across a gap (:func:`calibration.runs.bridge_gaps`): a gap that begins at rest cools, one
  that begins at speed heats.
- :func:`join` puts the logs end to end (time shifted so it keeps increasing; each log is a
  segment, where every filter restarts at equilibrium) and cuts the folds: leave-one-cycle-out
  when the logs hold two cycles or more (:func:`calibration.folds.split_cycles`, per log),
  otherwise contiguous blocks of one cycle.
- The elongation is NaN where it was not measured (a journal export's probe measurements):
  :attr:`Dataset.measured` is the mask, all true for a dense log. Speed and inputs are known on
  every row, so the free run always covers every row; fits and scores use the measured rows.
  A fold without a measurement is run through, never fitted or scored.

Pure computation on logs already read: no file I/O.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from compensator.errors import CalibrationError
from compensator.io.runlog import MIN_CALIBRATION_SPAN_S, RunLog, time_unit_refusal

from . import folds as fl
from .runs import MIN_MEASURED_ROWS, bridge_gaps, run_from_log


@dataclass(frozen=True)
class LogData:
    """One checked log: time [s], speed [rpm], elongation [um] (NaN: not measured), inputs."""

    name: str
    time_s: np.ndarray
    speed_rpm: np.ndarray
    elongation_um: np.ndarray
    inputs: Mapping[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class Dataset:
    """The logs end to end, with their segments, cycles and validation folds."""

    time_s: np.ndarray
    speed_rpm: np.ndarray
    elongation_um: np.ndarray
    inputs: Mapping[str, np.ndarray]
    segments: tuple[tuple[int, int], ...]
    names: tuple[str, ...]
    cycles: tuple[tuple[int, int], ...]
    folds: tuple[tuple[int, int], ...]
    scheme: str
    cycle_lines: tuple[str, ...]
    dropped_folds: int = 0
    """Folds without a measured row: run through, neither fitted nor scored."""

    @cached_property
    def measured(self) -> np.ndarray:
        """The rows whose elongation was measured (all of them in a dense log)."""
        return np.isfinite(self.elongation_um)

    @cached_property
    def dense(self) -> bool:
        return bool(self.measured.all())

    @cached_property
    def dt_s(self) -> float:
        """The median sample period [s]."""
        return float(np.median(np.diff(self.time_s))) if self.time_s.size > 1 else 1.0

    @property
    def unit(self) -> str:
        """What a fold is: a cycle or a block."""
        return _unit(self.scheme)

    def input_columns(self, names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        return {n: self.inputs[n] for n in (self.inputs if names is None else names)}


def _unit(scheme: str) -> str:
    return "block" if scheme.startswith("blocked") else "cycle"


def log_data(
    logs: Sequence[RunLog], input_names: Sequence[str] = (), labels: Sequence[str] | None = None
) -> tuple[list[LogData], list[str]]:
    """The logs checked, gaps bridged, the named inputs taken: what the identification fits.
    Returns the data and one line per log that had gaps."""
    labels = (
        list(labels)
        if labels is not None
        else [lg.source or f"log{i + 1}" for i, lg in enumerate(logs)]
    )
    if len(labels) != len(logs):
        raise CalibrationError(f"{len(labels)} labels for {len(logs)} logs")
    data, notes = [], []
    for label, lg in zip(labels, logs):
        run = run_from_log(lg, name=label, sparse=True)
        # the reader judged the unit; a calibration also needs a span of minutes at least
        why = time_unit_refusal(run.time_s, min_span_s=MIN_CALIBRATION_SPAN_S)
        if why is not None:
            raise CalibrationError(f"{lg.source or label}: {why}")
        speed, gaps = bridge_gaps(run.time_s, run.speed_rpm)
        name = Path(label).name
        if gaps:
            notes.append(
                f"{name}: {len(gaps)} gap(s) of up to {max(g for _, g in gaps) / 3600:.1f} h: "
                "integrated at the last logged speed (a gap that begins at rest cools)"
            )
        inputs = {}
        for n in input_names:
            if n not in lg.extras:
                raise CalibrationError(
                    f"{lg.source or name}: no column {n!r} for --inputs "
                    f"(columns: {', '.join(lg.extras) or 'none'})"
                )
            inputs[n] = np.asarray(lg.extras[n], dtype=float)
        data.append(LogData(name, run.time_s, speed, run.elongation_um, inputs))
    return data, notes


def join(logs: Sequence[LogData], input_names: Sequence[str] = ()) -> Dataset:
    """Join the logs and cut the folds: cycles per log, or blocks when there is one cycle. With
    sparse targets, a fold without a measurement is dropped from the folds (and counted)."""
    if not logs:
        raise CalibrationError("no calibration logs")
    t_parts, s_parts, y_parts, segs, cycles, lines = [], [], [], [], [], []
    ins: dict[str, list[np.ndarray]] = {k: [] for k in input_names}
    offset, start = 0.0, 0
    for log in logs:
        t = np.asarray(log.time_s, float)
        dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
        shift = offset - t[0]
        t_parts.append(t + shift)
        s_parts.append(np.asarray(log.speed_rpm, float))
        y_parts.append(np.asarray(log.elongation_um, float))
        for k in input_names:
            if k not in log.inputs:
                raise CalibrationError(f"{log.name}: no column {k!r} for --inputs")
            ins[k].append(np.asarray(log.inputs[k], float))
        cyc = fl.split_cycles(t, log.speed_rpm)
        for line in fl.describe_cycles(t, log.speed_rpm, cyc):
            lines.append(f"{log.name}: {line}")
        cycles += [(a + start, b + start) for a, b in cyc]
        segs.append((start, start + t.size))
        start += t.size
        offset = float(t[-1] + shift + dt)
    tj = np.concatenate(t_parts)
    if len(cycles) >= 2:
        folds, scheme = tuple(cycles), "leave-one-cycle-out"
    else:
        folds = fl.blocks(tj)
        scheme = f"blocked ({len(folds)} contiguous blocks of one cycle)"
        if len(folds) < 2 or min(b - a for a, b in folds) < fl.MIN_FOLD_ROWS:
            raise CalibrationError(
                f"too few rows ({tj.size}) to validate: record a heat-up and a "
                "cool-down, at least a few hundred samples"
            )
    y = np.concatenate(y_parts)
    measured = np.isfinite(y)
    dropped = 0
    if not measured.all():
        if measured.sum() < MIN_MEASURED_ROWS:
            raise CalibrationError(
                f"the elongation is measured on {int(measured.sum())} rows; a "
                f"calibration needs at least {MIN_MEASURED_ROWS}"
            )
        kept = tuple((a, b) for a, b in folds if measured[a:b].any())
        unit = _unit(scheme)
        if len(kept) < 2:
            raise CalibrationError(
                f"the {int(measured.sum())} measurements fall in one {unit} of "
                f"{len(folds)}: nothing to validate on; measure in another {unit} too"
            )
        dropped, folds = len(folds) - len(kept), kept
        scheme = f"{scheme} (on the measured rows)"
    return Dataset(
        tj,
        np.concatenate(s_parts),
        y,
        {k: np.concatenate(v) for k, v in ins.items()},
        tuple(segs),
        tuple(lg.name for lg in logs),
        tuple(cycles),
        folds,
        scheme,
        tuple(lines),
        dropped,
    )


def from_arrays(
    time_s: Any,
    speed_rpm: Any,
    elongation_um: Any,
    inputs: Mapping[str, Any] | None = None,
    *,
    folds: Sequence[tuple[int, int]] | None = None,
    segments: Sequence[tuple[int, int]] | None = None,
) -> Dataset:
    """A dataset from series already joined (the array-level entry points): ``folds`` default
    to the log's cycles (:func:`calibration.folds.split_cycles`), ``segments`` to one."""
    t = np.asarray(time_s, float)
    sp = np.asarray(speed_rpm, float)
    cyc = tuple(fl.split_cycles(t, sp))
    return Dataset(
        t,
        sp,
        np.asarray(elongation_um, float),
        {k: np.asarray(v, float) for k, v in (inputs or {}).items()},
        tuple(segments) if segments else ((0, int(t.size)),),
        ("log",),
        cyc,
        tuple(folds) if folds is not None else cyc,
        "leave-one-cycle-out",
        (),
    )
