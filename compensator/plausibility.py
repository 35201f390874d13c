"""Is a model one physics allows? Pure: no I/O.

Heat rises with speed, so a spindle's steady growth does too: a model whose steady growth turns
against the direction the calibration measured, falls back as speed rises, or stays flat while
the calibration measured a large growth was fitted to something other than the spindle's
heating (a job running instead of the calibration program, a loose sensor). And a calibration
whose rows mostly did not follow the program did not calibrate. A model whose time scale is no
spindle's (heat that takes days to settle, a sample period of hours: a log whose time was not
seconds) was not fitted to a spindle either. ``thermocomp fit`` (every fit) and ``thermocomp
model check`` refuse all three, in one line, with the numbers and the rule.

The growth direction is +1 when the growth is positive by the product's convention (elongation
toward the part: what the wizard's sensors measure) and -1 when a log measured it the other way.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .fitrecord import fit_of
from .io.runlog import MAX_SAMPLE_PERIOD_S

POINTS = 101
"""Speeds at which the steady growth is judged, evenly from rest to the calibrated top."""
MIN_TOLERANCE_UM = 0.5
"""The smallest tolerance [um]: noise and quantisation of a calibration's sensor."""
TOLERANCE_SHARE = 0.10
"""The tolerance as a share of the largest |steady growth| over the range."""
MEASURED_FACTOR = 5.0
"""A model flat at the top is refused only when the calibration measured more than this many
tolerances."""
NOT_FOLLOWING_LIMIT = 0.5
"""Above this share of calibration rows flagged NOT_FOLLOWING, the run did not calibrate."""
MAX_TIME_CONSTANT_S = 48 * 3600.0
"""The slowest a spindle's heat settles: 48 h to come 63 % of the way (spindles take minutes to
hours; a machine's structure a few hours more)."""
MIN_TIME_CONSTANT_S = 30.0
"""The fastest a spindle's slowest time constant can be: half a minute."""
RESPONSE_HORIZON_S = 1e7
"""How far (116 days) a step response is followed to time it."""

RULE = (
    "the steady growth relative to rest, g(n) = S(n) - S(0) from 0 to the calibrated top speed, "
    "must rise with speed in the growth direction d the calibration measured: d*g never below "
    "-tol, never more than tol below its maximum at a lower speed (below the top speed tol is "
    "at least the model's held-out RMS), and above tol at the top speed when the calibration "
    f"measured more than {MEASURED_FACTOR:g} tol; tol = max({MIN_TOLERANCE_UM:g} um, "
    f"{TOLERANCE_SHARE:.0%} of max|g|); a model with inputs is judged by its speed-only fallback"
)
"""The growth rule in one sentence, for reports."""

TIME_RULE = (
    f"the model's time scale must be a spindle's: fitted at a sample period of at most "
    f"{MAX_SAMPLE_PERIOD_S / 3600:g} h, its slowest time constant at least "
    f"{MIN_TIME_CONSTANT_S:g} s, and its growth after a step from rest to the top speed 63 % "
    f"of the way from its instant part to steady within {MAX_TIME_CONSTANT_S / 3600:g} h"
)
"""The time-scale rule in one sentence, for reports."""

NOT_FOLLOWING_RULE = (
    f"at most {NOT_FOLLOWING_LIMIT:.0%} of the calibration rows may be flagged "
    "NOT_FOLLOWING (the spindle not at the program's speed)"
)
"""The program rule in one sentence, for reports."""


def speed_only(model: Any) -> Any:
    """The model whose steady growth is judged: a model with inputs by its speed-only fallback
    (with the inputs held at their references, speed alone need not grow it: they carry the
    heat), any other as it is."""
    if model.input_names and model.fallback is not None:
        return model.fallback
    return model


def steady_state_um(model: Any, speed_rpm: float) -> float:
    """S(n): the model's steady elongation held at ``speed_rpm`` [um], inputs at their references
    (a model without ``steady_state_um`` of its own, the earlier with-inputs form, by its speed
    part's)."""
    steady = getattr(model, "steady_state_um", None)
    if steady is None:
        steady = model.speed_model.steady_state_um
    return float(steady(float(speed_rpm)))


def steady_growth_um(model: Any, speed_rpm: np.ndarray) -> np.ndarray:
    """g(n) = S(n) - S(0): the steady growth relative to rest at each speed [um], inputs at their
    references (:func:`steady_state_um`)."""
    rest_um = steady_state_um(model, 0.0)
    return np.array([steady_state_um(model, n) - rest_um for n in np.asarray(speed_rpm, float)])


def held_out_rms_um(model: Any) -> float:
    """The model's held-out free-run RMS from its fit record (``cv_rms_um``) [um], 0 if none."""
    value = fit_of(model).cv_rms_um
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return 0.0
    return max(float(value), 0.0)


def direction_of(value: Any) -> int | None:
    """+1 or -1 from a fit record's ``growth_direction``, None for anything else."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return 1 if value == 1 else -1 if value == -1 else None


def steady_growth_refusal(
    model: Any, direction: int | None = None, *, measured_um: float | None = None
) -> str | None:
    """Why ``model``'s steady growth is one physics forbids, in one line, or None (see
    :data:`RULE`).

    ``direction``: +1 or -1 as the calibration measured the growth; None: the sign of g at the
    top speed. ``measured_um``: the largest growth the calibration measured (default: the
    model's ``max_measured_um`` if it has one; without either, a flat model is not judged).
    """
    if direction not in (None, 1, -1):
        raise ValueError(f"growth direction must be +1, -1 or None, got {direction!r}")
    judged = speed_only(model)
    top_rpm = float(judged.speed_range_rpm[1])
    speed_rpm = np.linspace(0.0, top_rpm, POINTS)
    growth_um = steady_growth_um(judged, speed_rpm)
    bad = ~np.isfinite(growth_um)
    if bad.any():
        return f"the steady growth is not a finite number at {speed_rpm[bad][0]:.0f} rpm: not a spindle's"
    d = int(direction) if direction is not None else (1 if growth_um[-1] >= 0 else -1)
    tol_um = max(MIN_TOLERANCE_UM, TOLERANCE_SHARE * float(np.max(np.abs(growth_um))))
    shape_tol_um = max(tol_um, held_out_rms_um(judged))
    signed_um = d * growth_um
    way = f"{'measured' if direction is not None else 'its own'} growth direction {d:+d}"
    if signed_um[-1] < -tol_um or signed_um[:-1].min() < -shape_tol_um:
        allowed_um = np.full(POINTS, shape_tol_um)
        allowed_um[-1] = tol_um
        k = int(np.argmin(signed_um + allowed_um))  # the worst against what is allowed there
        return (
            f"steady growth {growth_um[k]:+.2f} um at {speed_rpm[k]:.0f} rpm (relative to rest) runs "
            f"against the {way} by more than the tolerance {allowed_um[k]:.2f} um: heat rises with "
            "speed, so the steady growth must follow the growth direction"
        )
    drop_um = np.maximum.accumulate(signed_um) - signed_um
    if drop_um.max() > shape_tol_um:
        k = int(np.argmax(drop_um))
        j = int(np.argmax(signed_um[: k + 1]))
        return (
            f"steady growth falls {drop_um[k]:.2f} um as speed rises ({growth_um[j]:+.2f} um at "
            f"{speed_rpm[j]:.0f} rpm, {growth_um[k]:+.2f} um at {speed_rpm[k]:.0f} rpm; {way}; "
            f"tolerance {shape_tol_um:.2f} um): heat rises with speed, so the steady growth must too"
        )
    measured = measured_um if measured_um is not None else getattr(judged, "max_measured_um", None)
    if (
        measured is not None
        and math.isfinite(measured)
        and abs(measured) > MEASURED_FACTOR * tol_um
        and signed_um[-1] <= tol_um
    ):
        return (
            f"steady growth only {growth_um[-1]:+.2f} um at the top speed {top_rpm:.0f} rpm ({way}; "
            f"tolerance {tol_um:.2f} um) while the calibration measured up to {abs(measured):.2f} um: "
            "the model does not grow with speed"
        )
    return None


def time_constants_s(model: Any) -> tuple[float, ...]:
    """The model's time constants [s] (a state-space model's ``taus_s``, a physical model's at
    rest); () for a model that states none."""
    taus = getattr(model, "taus_s", None)
    if taus is None and callable(getattr(model, "time_constants_s", None)):
        taus = model.time_constants_s(0.0)
    return tuple(float(t) for t in taus or ())


def response_time_s(model: Any, speed_rpm: float) -> float | None:
    """How long the model's growth after a step from rest to ``speed_rpm`` takes to come 63 %
    of the way from its instant part (a static term) to steady [s]: the time constant that
    carries the heat, whatever the form. inf beyond :data:`RESPONSE_HORIZON_S`; None when the
    model has no lagging growth to time (within :data:`MIN_TOLERANCE_UM`)."""
    time_s = np.r_[0.0, 1e-3, np.geomspace(1.0, RESPONSE_HORIZON_S, 600)]
    speed = np.r_[0.0, np.full(time_s.size - 1, float(speed_rpm))]
    growth_um = np.asarray(model.simulate_um(speed, time_s), float)
    growth_um = growth_um - growth_um[0]
    lag_um = steady_state_um(model, speed_rpm) - steady_state_um(model, 0.0) - growth_um[1]
    if not (math.isfinite(lag_um) and abs(lag_um) > MIN_TOLERANCE_UM):
        return None
    share = (growth_um - growth_um[1]) / lag_um
    reached = np.flatnonzero(share >= 1 - math.exp(-1))
    return float(time_s[reached[0]]) if reached.size else math.inf


def _hours(seconds: float) -> str:
    return f"{seconds / 3600:.3g} h" if seconds >= 3600 else f"{seconds:.3g} s"


def time_constant_refusal(model: Any) -> str | None:
    """Why ``model``'s time scale is no spindle's, in one line, or None (see
    :data:`TIME_RULE`): fitted at a sample period no spindle's logger has, a heat that settles
    slower than :data:`MAX_TIME_CONSTANT_S`, or time constants all under
    :data:`MIN_TIME_CONSTANT_S`. Each is what a log whose time was not seconds fits (milliseconds
    read as seconds stretch every time constant a thousandfold). A model with inputs is judged
    by its speed-only fallback."""
    judged = speed_only(model)
    dt_s = getattr(judged, "fitted_dt_s", None)
    if isinstance(dt_s, (int, float)) and math.isfinite(dt_s) and dt_s > MAX_SAMPLE_PERIOD_S:
        return (
            f"fitted at a sample period of {dt_s:g} s ({_hours(dt_s)}), longer than "
            f"{_hours(MAX_SAMPLE_PERIOD_S)}: no spindle's log samples that slowly; was the "
            "log's time in milliseconds? Refit on a log whose time is in seconds"
        )
    taus = [t for t in time_constants_s(judged) if t > 0]
    if taus and max(taus) < MIN_TIME_CONSTANT_S:
        return (
            f"its slowest time constant is {max(taus):.3g} s, under {MIN_TIME_CONSTANT_S:g} s: no "
            "spindle heats that fast; was the log's time in minutes or hours? Refit on a log "
            "whose time is in seconds"
        )
    top_rpm = float(judged.speed_range_rpm[1])
    settle_s = response_time_s(judged, top_rpm) if top_rpm > 0 else None
    if settle_s is not None and settle_s > MAX_TIME_CONSTANT_S:
        took = "longer than 116 days" if math.isinf(settle_s) else _hours(settle_s)
        shown = ", ".join(f"{t / 60:.1f}" for t in sorted(taus))
        return (
            f"its growth at {top_rpm:.0f} rpm takes {took} to come 63 % of the way to steady"
            + (f" (time constants {shown} min)" if shown else "")
            + f", over {_hours(MAX_TIME_CONSTANT_S)}: no spindle heats that slowly; was the "
            "log's time in milliseconds? Refit on a log whose time is in seconds"
        )
    return None


def not_following_refusal(share: float | None) -> str | None:
    """Why a calibration whose rows did not follow its program cannot calibrate, in one line, or
    None: refused when more than :data:`NOT_FOLLOWING_LIMIT` of its rows were flagged
    NOT_FOLLOWING (None: not known, not judged)."""
    if isinstance(share, bool) or not isinstance(share, (int, float)) or not math.isfinite(share):
        return None
    if share > NOT_FOLLOWING_LIMIT:
        return (
            f"{share:.1%} of the calibration rows did not follow the program's speed "
            f"(NOT_FOLLOWING), over the limit of {NOT_FOLLOWING_LIMIT:.0%}: the machine ran something "
            "else; record the calibration run again with the machine running its program"
        )
    return None
