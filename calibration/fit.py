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
  :func:`calibration.identify.identify`, the one choice among the registered candidates;
- refuses (:class:`CalibrationError`, one line) what physics forbids
  (:mod:`compensator.plausibility`): a run whose rows mostly did not follow the calibration
  program (the recorder's NOT_FOLLOWING flag), and a model whose steady growth does not rise
  with speed in the direction the logs measured. The model's fit record keeps both figures
  (``not_following_share``, ``growth_direction``) for ``thermocomp model check``.

Pure computation on logs already read: no file I/O.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from compensator.errors import CalibrationError
from compensator.io.journal import Journal
from compensator.io.runlog import RunLog
from compensator.modelbase import with_fit
from compensator.plausibility import (
    MIN_TOLERANCE_UM,
    not_following_refusal,
    steady_growth_refusal,
    time_constant_refusal,
)

from . import closedloop
from .acquire import Problem
from .dataset import LogData, log_data
from .identify import Identification, identify
from .runs import IDLE_RPM, Run, has_cooldown

NO_COOLDOWN = "no log has a cool-down (10 min or more at rest after running)"
FEW_LEVELS = "distinct speed levels"
MIN_SPEED_LEVELS = 5
TOP_SHARE = 2 / 3
"""The growth direction compares the elongation at speeds from this share of the top up with
the elongation at rest."""
PROBLEM_FLAGS = f"{Problem.__module__}.{Problem.__qualname__}"
"""What the recorder's run logs declare their ``flags`` column to hold (``# columns:``)."""
UNIT_SUFFIXES = (
    ("_c", "degC"),
    ("_k", "K"),
    ("_pct", "%"),
    ("_kw", "kW"),
    ("_w", "W"),
    ("_a", "A"),
    ("_nm", "N m"),
    ("_bar", "bar"),
)


def unit_of(name: str) -> str:
    """An input channel's unit from its name's suffix (``spindle_front_c`` is degC), else ``1``."""
    for suffix, unit in UNIT_SUFFIXES:
        if name.endswith(suffix):
            return unit
    return "1"


def fit_logs(
    logs: Sequence[RunLog],
    input_names: Sequence[str] = (),
    *,
    labels: Sequence[str] | None = None,
    nested: bool = True,
    physical: bool = True,
    probe_target_um: float | None = closedloop.DEFAULT_TARGET_UM,
    probe_every_s: float | None = None,
    units: Mapping[str, str] | None = None,
    progress: Callable[[str], None] | None = None,
    growth_direction: int | None = None,
    **meta: Any,
) -> Identification:
    """Identify a model from run logs: every candidate on the same whole-cycle folds, scored in free
    run, the choice printed with its reason (:class:`calibration.identify.Identification`).

    ``labels`` name the logs in the report (default: their file names); ``meta`` (spindle_id,
    machine_id, created_utc) goes into the model; ``growth_direction`` as in :func:`fit_data`.
    Raises :class:`CalibrationError` in one line for logs that cannot calibrate, among them logs
    whose rows mostly did not follow the calibration program (the recorder's flags).
    """
    data, notes = log_data(logs, input_names, labels)
    result = fit_data(
        data,
        input_names,
        nested=nested,
        physical=physical,
        probe_target_um=probe_target_um,
        probe_every_s=probe_every_s,
        units=units,
        progress=progress,
        growth_direction=growth_direction,
        not_following=not_following_rows(logs),
        **meta,
    )
    result.warnings[:0] = notes
    return result


def fit_data(
    data: Sequence[LogData],
    input_names: Sequence[str] = (),
    *,
    nested: bool = True,
    physical: bool = True,
    probe_target_um: float | None = closedloop.DEFAULT_TARGET_UM,
    probe_every_s: float | None = None,
    units: Mapping[str, str] | None = None,
    progress: Callable[[str], None] | None = None,
    growth_direction: int | None = None,
    not_following: tuple[int, int] | None = None,
    **meta: Any,
) -> Identification:
    """:func:`fit_logs` on logs already checked and bridged (:func:`log_data`), or on series held
    in memory (the virtual plant's): dense or sparse by the elongation's NaN cells.

    ``growth_direction``: +1 when the logs measure growth positive (the product's convention,
    what the wizard's sensors measure), -1 when they measure it the other way; None: what the
    data shows (:func:`growth_direction_of`). ``not_following``: (rows flagged NOT_FOLLOWING,
    all rows) of the logs that carry the recorder's flags (:func:`not_following_rows`). Refuses
    in one line a calibration whose rows mostly did not follow its program (before identifying:
    nothing to wait for) and a model whose steady growth physics forbids
    (:func:`compensator.plausibility.steady_growth_refusal`)."""
    if growth_direction not in (None, 1, -1) or isinstance(growth_direction, bool):
        raise CalibrationError(f"growth_direction must be +1, -1 or None, got {growth_direction!r}")
    share = None
    if not_following is not None and not_following[1] > 0:
        share = not_following[0] / not_following[1]
        why = not_following_refusal(share)
        if why is not None:
            raise CalibrationError(
                f"calibration refused: {why} ({not_following[0]} of {not_following[1]} rows)"
            )
    units = dict(units) if units is not None else {n: unit_of(n) for n in input_names}
    direction = growth_direction if growth_direction is not None else growth_direction_of(data)
    measured = np.concatenate([np.asarray(d.elongation_um, float) for d in data])
    measured = measured[np.isfinite(measured)]
    span_um = float(np.ptp(measured)) if measured.size else None  # the growth, wherever zero was
    result = identify(
        data,
        input_names,
        units=units,
        progress=progress,
        nested=nested,
        physical=physical,
        probe_target_um=probe_target_um,
        probe_every_s=probe_every_s,
        growth_direction=direction,
        measured_span_um=span_um,
        **meta,
    )
    result.warnings[:0] = coverage_warnings(data)
    stated: dict[str, Any] = {}
    if share is not None:
        stated["not_following_share"] = round(share, 4)
    if direction is not None:
        stated["growth_direction"] = int(direction)
    model = result.model
    if stated:
        model = result.model = with_fit(model, **stated)
    why = steady_growth_refusal(model, direction, measured_um=span_um) or time_constant_refusal(
        model
    )
    if why is not None:
        raise CalibrationError(f"calibration refused: {model.form}: {why}")
    return result


def not_following_rows(logs: Sequence[RunLog]) -> tuple[int, int] | None:
    """(rows flagged NOT_FOLLOWING, rows) over the logs whose ``flags`` column is the recorder's
    (:class:`calibration.acquire.Problem`); None when none has one. A journal export's ``flags``
    are the runtime's shaping flags (another meaning for the same bits): not counted."""
    bad = rows = 0
    seen = False
    for log in logs:
        flags = program_flags(log)
        if flags is None:
            continue
        seen = True
        value = np.nan_to_num(np.asarray(flags, dtype=float), nan=0.0, posinf=0.0, neginf=0.0)
        bad += int(np.count_nonzero(value.astype(np.int64) & int(Problem.NOT_FOLLOWING)))
        rows += int(value.size)
    return (bad, rows) if seen else None


def program_flags(log: RunLog) -> np.ndarray | None:
    """The log's ``flags`` column when it holds the recorder's :class:`calibration.acquire.Problem`
    flags: declared so in its ``# columns:`` line, or undeclared in a log that is no journal
    export; else None."""
    flags = log.extras.get("flags")
    if flags is None or flags.dtype == object:
        return None
    if PROBLEM_FLAGS in str(log.metadata.get("columns", "")):
        return flags
    journal_own = set(Journal.COLUMNS) - {"time_s", "speed_rpm", "flags"}
    if journal_own & set(log.extras):
        return None  # the runtime's journal: compensator.shaping.Flag
    return flags


def growth_direction_of(data: Sequence[LogData]) -> int | None:
    """The direction the logs measure growth in: the sign of the mean elongation at the top third
    of speeds minus the mean at rest before the spindle first turns in each log (the cold start;
    the mean at rest when no log starts at rest). None when the logs cannot tell: no measured
    row at the top or at rest, or a difference within the tolerance's floor (0.5 um)."""
    top_rpm = max(
        (float(np.max(np.abs(d.speed_rpm))) for d in data if len(d.speed_rpm)), default=0.0
    )
    if top_rpm <= 0:
        return None
    hot, cold, rest = [], [], []
    for d in data:
        speed = np.abs(np.asarray(d.speed_rpm, float))
        y = np.asarray(d.elongation_um, float)
        idle = speed < IDLE_RPM
        turned = np.cumsum(~idle) > 0
        hot.append(y[speed >= TOP_SHARE * top_rpm])
        cold.append(y[idle & ~turned])
        rest.append(y[idle])
    hot_um = np.concatenate(hot)
    hot_um = hot_um[np.isfinite(hot_um)]
    rest_um = np.concatenate(cold)
    rest_um = rest_um[np.isfinite(rest_um)]
    if not rest_um.size:
        rest_um = np.concatenate(rest)
        rest_um = rest_um[np.isfinite(rest_um)]
    if not (hot_um.size and rest_um.size):
        return None
    diff_um = float(np.mean(hot_um) - np.mean(rest_um))
    if abs(diff_um) <= MIN_TOLERANCE_UM:
        return None
    return 1 if diff_um > 0 else -1


def coverage_warnings(data: Sequence[LogData]) -> list[str]:
    """What the logs cannot teach a model, said before anyone trusts it: no cool-down (the
    dissipation time constant is then not identifiable) and too few speed levels (n and n² are
    then poorly separated)."""
    out = []
    if not any(has_cooldown(Run(d.name, d.time_s, d.speed_rpm, d.elongation_um)) for d in data):
        out.append(
            NO_COOLDOWN + ": the cooling time constant is not identifiable, and a slow heat-up "
            "looks like a long time constant. Record a cool-down at 0 rpm"
        )
    levels = np.unique(np.round(np.concatenate([np.abs(d.speed_rpm) for d in data]), -2))
    if levels.size < MIN_SPEED_LEVELS:
        out.append(
            f"only {levels.size} {FEW_LEVELS}: the n and n² terms are poorly separated; use a "
            f"staircase of {MIN_SPEED_LEVELS} or more speeds"
        )
    return out
