"""Offline replay: what compensation would have done on a logged speed profile.

Also the thermal-equilibrium figures of paper 000: STE (stability of thermal
error) is the slope of a least-squares smooth fit of the error; equilibrium is
reached once |STE| stays below 0.5e-3 um/s; TEVR is max - min of the error
after that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from compensator.errors import NonFiniteInputError, RunLogError
from compensator.estimate import Estimate, EstimateState
from compensator.expected import parse_expected, place
from compensator.fusion import observer_config_of
from compensator.io import RunLog
from compensator.io.journal import ALARM_COLD_START
from compensator.io.measurements import read_measurements
from compensator.predictor import Predictor
from compensator.shaping import POLICIES, ShapedSeries, ShaperConfig, shape_series
from compensator.units import RANGE_TOLERANCE

from .closedloop import probe_rows
from .metrics import against_expected, residual_stats
from .runs import bridge_gaps, gap_threshold_s
from .stability import equilibrium_and_tevr

MAX_SPAN_S = 2 * 365.25 * 86400.0
"""No equilibrium figures for a log spanning longer than this: across a gap of years they mean
nothing."""


@dataclass
class Replay:
    time_s: np.ndarray
    speed_rpm: np.ndarray
    predicted_um: np.ndarray
    measured_um: np.ndarray | None
    initial_um: float | None
    """The elongation the estimate started from (None: the model's own initial state)."""
    report: dict[str, Any]
    applied_offset_um: np.ndarray | None = None
    """The offset the runtime's shaper would have written."""
    cutting: np.ndarray | None = None
    """bool: the samples the shaper took as cutting (the log's signal, or inferred)."""

    @property
    def offset_um(self) -> np.ndarray:
        return -self.predicted_um  # paper 001 eq. 13: A = -S

    @property
    def residual_um(self) -> np.ndarray | None:
        return None if self.measured_um is None else self.measured_um - self.predicted_um

    def columns(self) -> dict[str, np.ndarray]:
        cols = {"time_s": self.time_s, "speed_rpm": self.speed_rpm}
        if self.measured_um is not None:
            cols["elongation_um"] = self.measured_um
        cols["predicted_um"] = self.predicted_um
        cols["offset_um"] = self.offset_um
        if self.measured_um is not None:
            cols["residual_um"] = self.residual_um  # type: ignore[assignment]
        if self.applied_offset_um is not None:  # None only for a Replay built by hand
            cols["applied_offset_um"] = self.applied_offset_um
            if self.measured_um is not None:
                cols["applied_residual_um"] = self.measured_um + self.applied_offset_um
        if self.cutting is not None:
            cols["cutting"] = self.cutting.astype(np.int64)
        return cols


def _duration(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h" if seconds >= 3600 else f"{seconds / 60:.0f} min"


@dataclass(frozen=True)
class Probes:
    """Measurements to fuse: times [s] on the log's clock, values and sigma [um]."""

    time_s: np.ndarray
    elongation_um: np.ndarray
    sigma_um: np.ndarray
    source: str
    sources: tuple[str, ...] = ()
    """Each measurement's source, where known (the service's journal): bounded apart."""


def probes_every(log: RunLog, every_s: float, noise_um: float = 0.5, seed: int = 0) -> Probes:
    """Simulated tool-setter measurements: the log's measured elongation every ``every_s``
    seconds (at the first sample at or after each instant) plus Gaussian noise of ``noise_um``."""
    if log.elongation_um is None:
        raise RunLogError("--probe-every needs a measured elongation_um column", log.source)
    if not np.isfinite(np.asarray(log.elongation_um, float)).all():
        raise RunLogError(
            "--probe-every draws its probes from an elongation measured on every row; "
            "this log's is sparse (its measurements are probes already)",
            log.source,
        )
    if not (math.isfinite(every_s) and every_s > 0):
        raise NonFiniteInputError(f"--probe-every must be > 0 s, got {every_s}")
    if not (math.isfinite(noise_um) and noise_um > 0):
        raise NonFiniteInputError(f"--probe-noise-um must be > 0, got {noise_um}")
    t = log.time_s
    idx = probe_rows(t, every_s)
    rng = np.random.default_rng(seed)
    values = np.asarray(log.elongation_um, float)[idx] + rng.normal(0.0, noise_um, idx.size)
    return Probes(
        t[idx],
        values,
        np.full(idx.size, noise_um),
        f"every {every_s:g} s from the measured column, noise {noise_um:g} um, seed {seed}",
    )


def probes_from_file(log: RunLog, path: str, default_sigma_um: float = 0.5) -> Probes:
    """Real measurements (:func:`compensator.io.measurements.read_measurements`), on the log's
    clock; one outside the log's span is a one-line error (a different clock or another run)."""
    if not (math.isfinite(default_sigma_um) and default_sigma_um > 0):
        raise NonFiniteInputError(f"--probe-noise-um must be > 0, got {default_sigma_um}")
    m = read_measurements(path, default_sigma_um)
    t0, t1 = float(log.time_s[0]), float(log.time_s[-1])
    out = (m.time_s < t0) | (m.time_s > t1)
    if out.any():
        k = int(np.flatnonzero(out)[0])
        raise RunLogError(
            f"measurement at time_s {m.time_s[k]:g} lies outside the log's "
            f"{t0:g}..{t1:g} s: not on the log's clock",
            path,
        )
    return Probes(
        m.time_s,
        m.elongation_um,
        m.sigma_um,
        f"{m.time_s.size} measurement(s) from {path}",
        m.sources,
    )


CUTTING_COLUMN = "cutting"


def cutting_signal(log: RunLog, shaping: ShaperConfig) -> tuple[np.ndarray | None, str, str | None]:
    """The controller's cutting signal from the log's ``cutting`` column (0/1, as the journal
    and the simulator write it), its source, and a warning; None where the shaper is to infer
    it from the speed (no column, or ``cutting.signal = "speed"``). A journal's rows whose
    ``cutting_source`` says the runtime inferred it are NaN (inferred again, with this
    configuration); rows where it could not read the speed (``unread``) count as cutting, as
    they did; blank cells (an older journal's rows) are inferred. Any other cell that is not 0
    or 1 is a one-line error naming the line."""
    col = log.extras.get(CUTTING_COLUMN)
    signal = shaping.cutting.signal
    if col is None or signal == "speed":
        warn = (
            None
            if col is not None or signal != "controller"
            else (
                "the configuration takes the cutting signal from the controller, but the log has no "
                "cutting column: inferred from the speed"
            )
        )
        return None, "inferred from the speed", warn
    import pandas as pd  # as the run-log reader: text cells become NaN, refused below

    cells = np.asarray(col)
    values = pd.to_numeric(cells, errors="coerce").astype(float)
    # a blank cell (a row from an older journal without the column) is inferred from the speed
    blank = pd.isna(cells) | (pd.Series(cells).astype(str).str.strip() == "").to_numpy()
    bad = ~np.isin(values, (0.0, 1.0)) & ~blank
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise RunLogError(
            f"column cutting: {col[row]!r} is not 0 or 1", log.source, log.line_of(row)
        )
    values[blank] = np.nan
    if blank.all():
        return None, "inferred from the speed (the cutting column is blank)", None
    source = log.extras.get("cutting_source")
    if source is None:
        return values, "the log's cutting column", None
    source = np.asarray(source, dtype=object)
    values = np.where(source == "controller", values, np.nan)
    values[source == "unread"] = 1.0
    if np.isnan(values).all():
        return None, "inferred from the speed (as the runtime did)", None
    return values, "the journal's cutting column where the controller gave it", None


def _error_stats(error: np.ndarray | None, mask: np.ndarray) -> dict[str, float | None]:
    """The error's figures on the rows where it is known (a sparse log: the measured rows)."""
    if error is None:
        return {
            "rms_um": None,
            "max_abs_um": None,
            "cutting_rms_um": None,
            "cutting_max_abs_um": None,
        }
    known = np.isfinite(error)
    whole, cut = residual_stats(error[known]), residual_stats(error[mask & known])
    return {
        "rms_um": whole["rms_um"],
        "max_abs_um": whole["max_abs_um"],
        "cutting_rms_um": cut["rms_um"],
        "cutting_max_abs_um": cut["max_abs_um"],
    }


def compare_policies(
    shaping: ShaperConfig,
    time_s: np.ndarray,
    speed_rpm: np.ndarray,
    predicted_um: np.ndarray,
    measured_um: np.ndarray | None,
    cutting: np.ndarray | None,
    configured: ShapedSeries,
) -> list[dict[str, Any]]:
    """Every transient policy with the configuration's limits, side by side, on one log: the
    error of the offset it would write (all samples, and the samples taken as cutting), how far
    it lags the model, and the fastest it moves while cutting and overall. ``none`` is the model
    bound: the offset ``-S`` unshaped. The configured policy is marked (``configured``: its
    series, already shaped)."""
    rows = []
    ideal = -predicted_um
    dt = np.diff(time_s)
    for name in (*POLICIES, "none"):
        if name == "hold" and shaping.policy != "hold":
            continue  # a variant of the longer cycle: shown only where configured
        if name == "none":  # judged on the samples the configured shaping took as cutting
            offset, cut = ideal, configured.cutting
        else:
            series = (
                configured
                if name == shaping.policy
                else shape_series(
                    shaping.with_policy(name), time_s, speed_rpm, predicted_um, cutting=cutting
                )
            )
            offset, cut = series.offset_um, series.cutting
        rate = np.abs(np.diff(offset)) / np.where(dt > 0, dt, np.inf)
        both = cut[1:] & cut[:-1]  # a step between two cutting samples
        rows.append(
            {
                "policy": name,
                "configured": name == shaping.policy,
                **_error_stats(None if measured_um is None else measured_um + offset, cut),
                "max_lag_um": float(np.max(np.abs(offset - ideal))),
                "max_rate_um_per_s": float(rate.max()) if rate.size else 0.0,
                "max_cutting_rate_um_per_s": float(rate[both].max()) if both.any() else 0.0,
            }
        )
    return rows


def _steps(log: RunLog) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The time the model steps on, each step [s] and the wall clock: a journal's own ``dt_s``
    (what the service stepped by; its ``time_s`` is rounded to the millisecond) and ``wall_s``,
    else the log's time stamps."""
    t = np.asarray(log.time_s, dtype=float)
    col = log.extras.get("dt_s")
    dt = None if col is None or col.dtype == object else np.asarray(col, dtype=float)
    if dt is None or not (np.isfinite(dt).all() and (dt >= 0).all()):
        return t, np.diff(t, prepend=t[:1]), None
    dt = dt.copy()
    dt[0] = 0.0  # the first row starts the replay
    wall = log.extras.get("wall_s")
    wall = None if wall is None or wall.dtype == object else np.asarray(wall, dtype=float)
    return t[0] + np.cumsum(dt), dt, wall if wall is not None and np.isfinite(wall).all() else None


def _cold_start(log: RunLog) -> bool:
    """A service journal that begins with a cold start: the service's estimate began at the
    model's equilibrium at rest, and its offset at zero."""
    alarms = log.extras.get("alarms")
    return (
        alarms is not None
        and alarms.dtype != object
        and len(alarms) > 0
        and bool(int(alarms[0]) & ALARM_COLD_START)
    )


def _start(
    estimate: Estimate, log: RunLog, initial_um: float | None, speed_rpm: float
) -> EstimateState:
    """Where the estimate starts: where the service began for a journal that begins with a cold
    start (unless ``initial_um`` is given); else at ``initial_um`` (None: the model's
    equilibrium with the first speed)."""
    if initial_um is None and _cold_start(log):
        return estimate.cold()
    return estimate.begin(initial_um, speed_rpm)


EXPECTED_SHARE = 0.8
"""Fewer of a band's errors than this within the fit's stated 95 % band: replay says so."""


def replay(
    model: Predictor,
    log: RunLog,
    initial_um: float | None = None,
    shaping: ShaperConfig | None = None,
    probes: Probes | None = None,
    compare: bool = True,
    estimate: Estimate | None = None,
) -> Replay:
    """Free-run ``model`` over the log's own time stamps.

    A sparse log (a journal export: the elongation measured at the probe instants only, NaN on
    the other rows) is replayed over every row; its error figures are those of the measured rows
    (``measured_samples``), and the equilibrium figures come from the prediction.

    Gaps in the log (:func:`calibration.runs.bridge_gaps`) are integrated at the last logged
    speed (a gap that begins at rest cools), with a warning; :attr:`Replay.speed_rpm` keeps the logged speed. Every
    number returned is finite, or a one-line error says where the model overflowed.

    The offset is also passed through the runtime's own shaper
    (:func:`compensator.shaping.shape_series`) with ``shaping`` (default: the runtime's
    defaults), the cutting signal taken from the log's ``cutting`` column where it has one
    (:func:`cutting_signal`), else inferred from the speed as the runtime does: the report then
    gives the error of the offset the machine would have held (``applied_*``) beside the
    model's, and with ``compare`` every transient policy side by side (``policies``).

    The estimate is the service's own (:class:`compensator.estimate.Estimate`; ``estimate``,
    default the runtime's defaults for ``model``): a speed above the calibrated range is clamped
    to its top, a blank input cell makes the speed-only fallback stand in until the inputs have
    recovered, and probes are fused against the model in use. A journal's own ``dt_s`` and
    ``wall_s`` columns are the steps the service took, so a journal replays step for step.
    """
    shaping = ShaperConfig() if shaping is None else shaping
    if estimate is None:
        estimate = Estimate(model, observer_config_of(model) if probes is not None else None)
    elif (
        probes is not None and estimate.fused is None
    ):  # probes given: fuse them, as the model says
        estimate = replace(estimate, observer=observer_config_of(model))
    warnings: list[str] = []
    measured = None if log.elongation_um is None else np.asarray(log.elongation_um, dtype=float)
    rows = np.isfinite(measured) if measured is not None else np.zeros(len(log), dtype=bool)
    if measured is not None and np.isinf(measured).any():  # NaN: not measured; inf: garbage
        row = int(np.flatnonzero(np.isinf(measured))[0])
        raise RunLogError("column elongation_um: not a finite number", log.source, log.line_of(row))
    if measured is not None and not rows.any():
        warnings.append("the elongation_um column has no value: replayed without a measurement")
        measured = None
    sparse = measured is not None and not bool(rows.all())
    if initial_um is None and measured is not None:
        if rows[0]:
            initial_um = float(measured[0])
        else:
            warnings.append(
                "the first row has no measured elongation: the model starts from its own "
                "initial state (give --initial-um to start elsewhere)"
            )
    if initial_um is not None and not math.isfinite(initial_um):
        raise NonFiniteInputError(f"initial elongation is {initial_um}")
    missing = [n for n in model.input_names if n not in log.extras]
    if missing:
        raise RunLogError(f"the model needs input column(s) {', '.join(missing)}", log.source)
    inputs = {n: np.asarray(log.extras[n], dtype=float) for n in model.input_names}
    for name, col in inputs.items():
        if np.isinf(
            col
        ).any():  # a blank cell is an input the service could not use; inf is garbage
            row = int(np.flatnonzero(np.isinf(col))[0])
            raise RunLogError(f"column {name}: not a finite number", log.source, log.line_of(row))
    blank = np.zeros(len(log), bool)
    for col in inputs.values():
        blank |= np.isnan(col)
    # a gap of missing rows is the spindle at rest: hours of held speed would be invented heat
    speed_sim, gaps = bridge_gaps(log.time_s, log.speed_rpm)
    step_time, dt, wall = _steps(log)
    series = None
    if probes is None and estimate.with_inputs is None:
        pred = open_loop = estimate.simulate_um(speed_sim, step_time, initial_um)
    else:  # the service's estimate, cycle by cycle: inputs that fail, probes fused
        # the measurement journal moves each further measurement of one cycle 1 ms on (its times
        # must increase), and a journal's times read back carry float noise: up to 5 ms after a
        # row, a measurement is that row's cycle's
        at = np.searchsorted(log.time_s, np.asarray([] if probes is None else probes.time_s) - 5e-3)
        fused: list[tuple[int, float, float, str]] = (
            []
            if probes is None
            else list(
                zip(
                    at.tolist(),
                    probes.elongation_um.tolist(),
                    probes.sigma_um.tolist(),
                    probes.sources or ("measurement",) * len(at),
                )
            )
        )
        series = estimate.run(
            _start(estimate, log, initial_um, float(speed_sim[0])),
            step_time,
            speed_sim,
            dt_s=dt,
            wall_s=wall,
            inputs=inputs,
            probes=fused,
        )
        pred, open_loop = series.estimate_um, series.model_um
        if series.fallback.any():
            warnings.append(
                f"the speed-only fallback stands in on {int(series.fallback.sum())} rows "
                f"({int(blank.sum())} with a blank input cell), as in the service"
            )
    cut_signal, cut_source, cut_warning = cutting_signal(log, shaping)
    shaped = shape_series(
        shaping,
        step_time,
        estimate.clamp_series(speed_sim)[0],
        pred,
        initial_offset_um=0.0 if initial_um is None and _cold_start(log) else None,
        cutting=cut_signal,
    )
    applied = shaped.offset_um
    for name, values in (("predicted elongation", pred), ("applied offset", applied)):
        if not np.isfinite(values).all():  # no NaN reaches a report
            row = int(np.flatnonzero(~np.isfinite(values))[0])
            line = log.line_of(row)
            raise NonFiniteInputError(
                f"{log.source or 'log'}: the {name} is not finite from row {row}"
                + (f" (line {line})" if line else "")
                + ": the model overflows on the log's values or time steps"
            )

    if cut_warning:
        warnings.insert(0, cut_warning)
    _lo, hi = model.speed_range_rpm
    speed = np.abs(log.speed_rpm)
    over = speed > hi * (1 + RANGE_TOLERANCE)  # Predictor.above_range, vectorised
    if over.any():
        k = int(np.flatnonzero(over)[0])
        line = log.line_of(k)
        warnings.append(
            f"{over.sum()} samples ({100 * over.mean():.1f} %) above the calibrated range "
            f"(max {hi:.0f} rpm; {speed.max():.0f} rpm"
            + (f", first at line {line})" if line else ")")
            + (
                ": clamped to the top of the range, as the service does"
                if estimate.over_range == "clamp"
                else ": predictions there are extrapolated (over_range = extrapolate)"
            )
        )
    outside = getattr(model, "outside_trained", None)  # models that record trained input ranges
    if outside is not None:
        for name in model.input_names:
            col = inputs[name]
            for k in (int(np.argmin(col)), int(np.argmax(col))):
                why = outside({name: float(col[k])})
                if why is not None:
                    line = log.line_of(k)
                    warnings.append(
                        f"{why}"
                        + (f" (line {line})" if line else "")
                        + ": predictions there are extrapolated"
                    )
                    break
    if log.duration_s > MAX_SPAN_S:
        warnings.append(
            f"the log spans {log.duration_s / 86400:.0f} days: no equilibrium time or "
            f"TEVR beyond {MAX_SPAN_S / 86400:.0f} days"
        )
    if gaps:
        line = log.line_of(gaps[0][0])
        warnings.append(
            f"{len(gaps)} gap(s) of up to {_duration(max(g for _, g in gaps))} in the log"
            + (f" (first ending at line {line})" if line else "")
            + ": integrated at the last logged speed (a gap that begins at rest cools)"
        )
    limit_s = gap_threshold_s(log.time_s)
    held = [g for g in log.gaps if g.duration_s <= limit_s]  # short ones: bridge_gaps left them
    if held:
        total = sum(g.duration_s for g in held)
        warnings.append(
            f"{len(held)} short gap(s) in the log, {total:.0f} s in all; the speed is taken as "
            "held across each gap"
        )

    report: dict[str, Any] = {
        "format": "thermocomp.replay-report/1",
        "model_form": model.form,
        "spindle_id": model.spindle_id,
        "samples": len(log),
        "duration_s": log.duration_s,
        "initial_um": initial_um,
        "max_predicted_um": float(np.max(pred)),
        "min_predicted_um": float(np.min(pred)),
        "gaps": len(gaps),
    }
    if probes is not None and series is not None:
        report.update(
            probes=int(probes.time_s.size),
            probes_rejected=series.outcomes.count("rejected"),
            probe_restarts=series.outcomes.count("restarted"),
            probes_limited=series.outcomes.count("limited"),
            probe_source=probes.source,
        )
    report["measured_samples"] = int(rows.sum()) if measured is not None else 0
    if measured is not None:
        y = measured[rows]  # a sparse log: its measured rows only
        res = y - pred[rows]
        st = residual_stats(res)
        std_u = float(np.std(y))
        std_c = float(np.std(res))
        report.update(
            max_abs_residual_um=st["max_abs_um"],
            rms_residual_um=st["rms_um"],
            mean_abs_residual_um=st["mean_abs_um"],
            std_uncompensated_um=std_u,
            std_compensated_um=std_c,
            std_reduction_pct=100.0 * (1 - std_c / std_u) if std_u > 0 else None,
            max_abs_uncompensated_um=float(np.max(np.abs(y))),
        )
        if probes is not None:
            ost = residual_stats(y - open_loop[rows])
            report.update(
                open_loop_rms_residual_um=ost["rms_um"],
                open_loop_max_abs_residual_um=ost["max_abs_um"],
            )
        ast = residual_stats(y + applied[rows])
        cst = residual_stats((measured + applied)[rows & shaped.cutting])
        report.update(
            applied_rms_residual_um=ast["rms_um"],
            applied_max_abs_residual_um=ast["max_abs_um"],
            applied_cutting_rms_residual_um=cst["rms_um"],
            applied_cutting_max_abs_residual_um=cst["max_abs_um"],
        )
        expected = parse_expected(getattr(model, "fit", None))
        if expected is not None:
            spans = None
            if model.input_names and hasattr(model, "distance_outside"):
                spans = model.distance_outside({k: inputs[k][rows] for k in model.input_names})
            # the speeds lately, from the whole log: after a speed faster than validation saw
            # the statement vouches for nothing until the heat has settled
            lately = expected.recent_rpm(np.asarray(log.time_s, float), np.asarray(log.speed_rpm))
            report["expected_error"] = against_expected(
                expected,
                res,
                np.asarray(log.speed_rpm, float)[rows],
                spans,
                recent=None if lately is None else lately[rows],
            )
            for b in report["expected_error"]:
                if b["within_p95"] < EXPECTED_SHARE:
                    warnings.append(
                        f"the error is larger than the fit expected {place(str(b['label']))}: "
                        f"{100 * b['within_p95']:.0f} % of it within the stated 95 % band "
                        f"({b['expected_p95_abs_um']:.2f} um); probe or recalibrate"
                    )
        error = pred if sparse else measured
        if sparse:
            warnings.append(
                f"the elongation is measured on {int(rows.sum())} of {rows.size} rows (sparse): "
                "the error figures are on those rows; equilibrium time and TEVR from the "
                "prediction"
            )
    else:
        for key in (
            "max_abs_residual_um",
            "rms_residual_um",
            "mean_abs_residual_um",
            "std_uncompensated_um",
            "std_compensated_um",
            "std_reduction_pct",
            "max_abs_uncompensated_um",
            "applied_rms_residual_um",
            "applied_max_abs_residual_um",
            "applied_cutting_rms_residual_um",
            "applied_cutting_max_abs_residual_um",
        ):
            report[key] = None
        error = pred
    # paper 000's figures, as the cooling commands compute them (calibration.stability)
    t_eq, tevr = (
        (None, None) if log.duration_s > MAX_SPAN_S else equilibrium_and_tevr(log.time_s, error)
    )
    report["equilibrium_time_s"] = t_eq
    report["tevr_um"] = tevr
    report["ste_source"] = "measured" if measured is not None and not sparse else "predicted"
    report["shaping"] = {
        "policy": shaping.policy,
        "max_rate_um_per_s": shaping.max_rate_um_per_s,
        "not_cutting_rate_um_per_s": shaping.fast_rate_um_per_s,
        "max_offset_um": shaping.max_offset_um,
        "deadband_um": shaping.deadband_um,
        "cutting_source": cut_source,
        "cutting_fraction": float(np.mean(shaped.cutting)),
    }
    if compare:
        report["policies"] = compare_policies(
            shaping,
            step_time,
            estimate.clamp_series(speed_sim)[0],
            pred,
            measured,
            cut_signal,
            shaped,
        )
    report["warnings"] = warnings
    return Replay(
        log.time_s, log.speed_rpm, pred, measured, initial_um, report, applied, shaped.cutting
    )
