"""The wizard's step 4 as values: fit (the one identification ``thermocomp fit`` runs), validate
on the held-out run, and the report's figures, plot and advice."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from compensator.errors import CalibrationError
from compensator.io import RunLog, read_run_log
from compensator.modelbase import with_fit

from ..acquire import EXCLUDED, Problem
from ..fit import FEW_LEVELS, NO_COOLDOWN
from .model import LIVE, WizardSession, inside

LONG_GAP_S = 60.0
"""An interruption of the recording worth a warning [s]."""


def clean(log: RunLog) -> tuple[RunLog, int]:
    """The log without rows flagged saturated, frozen or jump (by the recorder), and how many
    rows that left out."""
    flags = log.extras.get("flags")
    if flags is None or flags.dtype == object:
        return log, 0
    keep = (flags.astype(int) & int(EXCLUDED)) == 0
    if keep.all():
        return log, 0
    return RunLog(
        log.time_s[keep],
        log.speed_rpm[keep],
        None if log.elongation_um is None else log.elongation_um[keep],
        {k: v[keep] for k, v in log.extras.items()},
        log.metadata,
        log.gaps,
        log.source,
    ), int((~keep).sum())


@dataclass(frozen=True)
class RunData:
    """A complete run's log as the fit reads it."""

    log: RunLog
    dropped: int
    """Rows left out, flagged by the recorder."""
    long_gaps: int
    gap_s: float
    """The long gaps (interruptions) and their seconds in all."""


def read_runs(session: WizardSession, workdir: Path) -> dict[str, RunData]:
    """The session's complete runs, each log checked to lie in the work directory."""
    out = {}
    for name, info in (session.runs or {}).items():
        if not info.complete:
            continue
        log, dropped = clean(read_run_log(inside(workdir, info.log, f"the {name} run log")))
        long = [g for g in log.gaps if g.duration_s > LONG_GAP_S]
        out[name] = RunData(log, dropped, len(long), float(sum(g.duration_s for g in long)))
    return out


@dataclass(frozen=True)
class Fitted:
    """The fit step's value: the identification and the calibration run's free run."""

    result: Any
    """The :class:`calibration.identify.Identification` ``fit_logs`` returned."""
    report: dict[str, Any]
    runs: dict[str, RunData]
    fitted_um: np.ndarray
    """The model's free run over the calibration run."""
    residual_um: np.ndarray
    """Measured minus free run; NaN where not measured (the tool-setter route)."""
    peak_um: float

    @property
    def model(self) -> Any:
        return self.result.model


def fit(session: WizardSession, runs: dict[str, RunData], created_utc: str) -> Fitted:
    """The one identification ``thermocomp fit`` runs (``calibration.fit.fit_logs``) on the
    calibration run: the same log gives the same model. A CalibrationError, nothing fitted,
    for a model physics forbids or a run that did not follow its program."""
    from ..fit import fit_logs

    if "calibration" not in runs:
        raise CalibrationError("no complete calibration run to fit")
    # a live recording measures growth toward the part as positive; an imported DAQ file's
    # sign is the device's, so the data says it
    direction = 1 if session.source in LIVE else None
    result = fit_logs(
        [runs["calibration"].log],
        labels=["calibration"],
        spindle_id=session.spindle_id,
        machine_id=session.machine_id,
        created_utc=created_utc,
        growth_direction=direction,
    )
    j = result.dataset
    fitted = result.free_run_um()["calibration"]
    return Fitted(
        result,
        result.report(),
        runs,
        fitted,
        j.elongation_um - fitted,
        float(np.max(np.abs(j.elongation_um[j.measured]))),
    )


@dataclass(frozen=True)
class Validated:
    """The validate step's value: the model to save (with its observer where the held-out run
    could fit one), the held-out run's replay and figures, and the probe-interval plan."""

    model: Any
    replay: Any = None
    """The :class:`calibration.replay.Replay` of the validation run, if there was one."""
    stats: dict[str, Any] | None = None
    dropped: int = 0
    closed_loop: Any = None
    """The :class:`calibration.closedloop.Plan` judged on the held-out run (a dense one only)."""


def validate(fitted: Fitted) -> Validated:
    """The model in free run on the validation run the fit never saw, through the service's own
    estimate (``calibration.replay.replay``); on a dense run, the observer's noise and how often a
    tool setter would have to measure (``calibration.closedloop.plan_on_run``)."""
    from ..metrics import residual_stats
    from ..replay import replay

    model = fitted.model
    val = fitted.runs.get("validation")
    if val is None:
        return Validated(model)
    rep = replay(model, val.log)
    res = rep.residual_um
    if res is None:  # a run log always has its elongation: replay measured it
        raise CalibrationError("the validation run has no measured elongation")
    stats = residual_stats(res[np.isfinite(res)])
    j = fitted.result.dataset
    loop = None
    if j.dense and bool(np.isfinite(res).all()):
        # how often a tool setter would have to measure, judged on the held-out run
        from ..closedloop import plan_on_run

        loop = plan_on_run(
            j.time_s, fitted.residual_um, rep.time_s, res, max(model.time_constants_s(0.0))
        )
        model = with_fit(model, observer=loop.observer)
    return Validated(model, rep, stats, val.dropped, loop)


def report(
    session: WizardSession, fitted: Fitted, validated: Validated, plot: Path
) -> dict[str, Any]:
    """The calibration's figures as the report reads them (the summary), with the plot written
    to ``plot``, the drift test of ISO 230-3 and the advice."""
    from ..iso230_3 import report_rows, spindle_thermal_test
    from ..metrics import residual_stats
    from ..plots import Panel, plot_panels

    j = fitted.result.dataset
    model = validated.model
    summary: dict[str, Any] = {
        "form": model.form,
        "reason": fitted.result.reason,
        "calibration": residual_stats(fitted.residual_um[j.measured]),
        "warnings": list(fitted.result.warnings),
        "report": fitted.report,
    }
    panels = [Panel("calibration run", j.time_s, j.speed_rpm, fitted.fitted_um, j.elongation_um)]
    # the standard's drift test, from the same runs: what a shop hands its customer
    tests = {
        "calibration": spindle_thermal_test(
            j.time_s, j.speed_rpm, j.elongation_um, fitted.fitted_um
        )
    }
    rep = validated.replay
    if rep is not None:
        summary["validation"] = validated.stats
        summary["validation_report"] = rep.report
        if validated.closed_loop is not None:
            summary["closed_loop"] = validated.closed_loop.report()
        panels.append(
            Panel(
                "validation run (held out)",
                rep.time_s,
                rep.speed_rpm,
                rep.predicted_um,
                rep.measured_um,
            )
        )
        tests["validation"] = spindle_thermal_test(
            rep.time_s, rep.speed_rpm, rep.measured_um, rep.predicted_um
        )
    summary["iso230_3"] = report_rows(tests)
    plot_panels(
        plot,
        panels,
        f"{session.machine_id} / {session.spindle_id}: {model.form}",
        max_rpm=session.max_rpm,
    )
    summary["plot"] = str(plot)
    summary["peak_um"] = fitted.peak_um
    summary["advice"] = advise(summary, session)
    return summary


def advise(summary: dict[str, Any], session: WizardSession) -> list[str]:
    """What to re-run when the fit is poor, from the figures and warnings."""
    out: list[str] = []
    peak = max(summary.get("peak_um", 0.0), 1e-9)
    cal = summary["calibration"]
    val = summary.get("validation")
    limit = max(1.0, 0.1 * peak)
    warnings = " ".join(summary.get("warnings", []))
    if NO_COOLDOWN in warnings:
        out.append(
            "record the calibration run again with its cool-down (>= 60 min at 0 rpm at the end)"
        )
    if FEW_LEVELS in warnings:
        out.append("the run has too few speed levels: run the full staircase")
    if cal["rms_um"] is not None and cal["rms_um"] > limit:
        out.append(
            f"the model misses the calibration run itself (RMS {cal['rms_um']:.2f} um > {limit:.2f} um): "
            "check the probe bracket for its own thermal drift (Invar bracket, coolant off the probe) "
            "and that the spindle was cold at the start"
        )
    if val is None:
        if not session.validation:
            out.append(
                "no validation run: record one (a different profile) to see how the model does "
                "on speeds it was not fitted on"
            )
    elif val["rms_um"] is not None and val["rms_um"] > limit:
        out.append(
            f"the model does not carry over to the validation run (RMS {val['rms_um']:.2f} um > "
            f"{limit:.2f} um): record a second calibration run and fit both with "
            "`thermocomp fit cal1.csv cal2.csv`, or check that ambient and coolant were steady"
        )
    if session.source == "tool-setter" and (session.probe_spindle or "stop") != "keep":
        out.append(
            "the tool setter measured at rest: the growth that exists only while the spindle turns "
            "(centrifugal, bearing preload; 10 um and more on a fast spindle) is not in the model, so "
            "it is good at rest and misses that part while cutting; calibrate with a laser setter at "
            "speed (--probe-spindle keep) or an eddy-current sensor, or keep probing in production so "
            "the observer carries it"
        )
    for name, info in (session.runs or {}).items():
        bad = sum(v for k, v in (info.flagged or {}).items() if Problem[k] & EXCLUDED)
        if bad > 0.05 * max(info.rows or 1, 1):
            out.append(
                f"{name}: {bad} flagged samples (saturated, frozen, jumps): fix the sensor set-up and "
                "record it again"
            )
    return out
