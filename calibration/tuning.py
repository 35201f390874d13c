"""Controller tuning from a step response: FOPDT/SOPDT models, their fit, SIMC PID rules, the
discrete PID of paper 000 in closed loop. Pure functions and immutable values.

Paper 000 (thermal error feedback control by active cooling, docs/REFERENCES.md)
drives the coolant temperature with a discrete PID, ``u_k = u_k0 + kp*e_k + ki*sum(e) +
kd*(e_k - e_{k-1})``, ``e = RITE - E``, set "empirically" to kp = 2, ki = 0, kd = 50 at 1 s. This
module gives the alternative a step test affords: fit a first- or second-order-plus-dead-time
model to an input/output record (:func:`fit_step_model`), tune by Skogestad's SIMC rules
(:func:`simc`) and compare candidates in closed loop (:func:`closed_loop_step`,
:func:`step_metrics`). Gains come out as the cooling law's own
:class:`compensator.cooling_law.PidGains`, ready for :class:`compensator.cooling_law.CoolingLaw`; the
closed loop here is the paper's plain PID, without the law's filtered derivative on the
estimate, rate limit and back-calculation, so it compares tunings rather than predicting the
law's exact response.

Conventions. Models are in deviation variables, at rest with zero input before the record
starts. An input sample ``u[k]`` is held from ``time_s[k]`` until the next sample (the
controller's forward zero-order hold: a command issued at t_k holds until t_{k+1}; the run logs
of :mod:`compensator.filters` log the value held over the step *ending* at t_k instead, which
shifts a fitted delay by one sample period).

Reference: S. Skogestad, "Simple analytic rules for model reduction and PID controller tuning",
J. Process Control 13 (2003) 291-309 (SIMC).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import ValidationError
from scipy.linalg import expm
from scipy.optimize import least_squares

from compensator.cooling_law import PidGains
from compensator.errors import CalibrationError, ModelError

TAU_C_FLOOR_FRACTION = 0.1
"""The default SIMC closed-loop time constant is never below this fraction of the dominant
time constant tau1 (see :func:`simc`)."""
SETTLING_BAND = 0.02
"""Settling band of :func:`step_metrics`: 2 % of the target."""
_CHUNK_ELEMENTS = 4_000_000  # samples x input changes evaluated at once by response()
_MAX_LOOP_STEPS = 10_000_000


def _finite(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as err:
        raise ModelError(f"{name} must be a number, got {value!r}") from err
    if not math.isfinite(v):
        raise ModelError(f"{name} must be finite, got {v}")
    return v


def _io(time_s: Any, **series: Any) -> tuple[np.ndarray, ...]:
    """Time [s] (finite, strictly increasing) and equally long finite series; one-line errors."""
    try:
        arrays = [np.asarray(time_s, dtype=float)] + [
            np.asarray(v, dtype=float) for v in series.values()
        ]
    except (TypeError, ValueError) as err:
        raise CalibrationError(f"time_s and {', '.join(series)} must be numeric") from err
    names = ["time_s", *series]
    for name, a in zip(names, arrays, strict=True):
        if a.ndim != 1:
            raise CalibrationError(f"{name} must be one-dimensional")
        if a.size != arrays[0].size:
            raise CalibrationError(f"{name} has {a.size} samples but time_s has {arrays[0].size}")
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise CalibrationError(f"{name} at sample {int(bad[0])} is {a[bad[0]]}")
    t = arrays[0]
    if t.size == 0:
        raise CalibrationError("the record is empty")
    d = np.diff(t)
    if (d <= 0).any() or not np.isfinite(d).all():
        i = int(np.flatnonzero(~(d > 0))[0]) + 1
        raise CalibrationError(f"time_s does not increase at sample {i}")
    return tuple(arrays)


def _tail2(t: np.ndarray, tau1: float, tau2: float) -> np.ndarray:
    """(tau1*e^{-t/tau1} - tau2*e^{-t/tau2}) / (tau1 - tau2) for t >= 0, tau1 >= tau2 > 0, written
    as a1 + (t/tau1)*(a1 - a2)/z, z = t*(1/tau2 - 1/tau1), so equal time constants (the
    critically damped (1 + t/tau)*e^{-t/tau}) need no special case and near-equal ones lose
    nothing to cancellation."""
    a1 = np.exp(-t / tau1)
    a2 = np.exp(-t / tau2)
    z = t * (1.0 / tau2 - 1.0 / tau1)
    q = a2.copy()  # the limit z -> 0
    small = (z > 0) & (z < 1.0)
    q[small] *= np.expm1(z[small]) / z[small]
    big = z >= 1.0
    q[big] = (a1[big] - a2[big]) / z[big]
    return a1 + (t / tau1) * q


class _Model:
    """What the two model forms share: the response by superposition of step responses."""

    gain: float
    delay_s: float

    def step_response(self, t_s: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def response(self, time_s: Any, u: Any) -> np.ndarray:
        """The model's output [output units] at ``time_s`` [s] for the input ``u`` [input
        units], each ``u[k]`` held from ``time_s[k]`` to the next sample (forward zero-order
        hold), the model at rest with zero input before ``time_s[0]``.

        Exact at the samples for any delay and any sample spacing: the held input is a sum of
        steps ``du_j`` at ``time_s[j]``, so ``y(t) = sum_j du_j * S(t - time_s[j] - delay)`` with
        S the analytic step response. The cost grows with samples x input changes (a step test
        has a few changes; an input that changes every sample of a long record is slow).
        """
        t, uu = _io(time_s, u=u)
        du = np.diff(uu, prepend=0.0)
        changes = np.flatnonzero(du != 0.0)
        y = np.zeros(t.size)
        chunk = max(1, _CHUNK_ELEMENTS // t.size)
        for a in range(0, changes.size, chunk):
            j = changes[a : a + chunk]
            y += self.step_response(t[:, None] - t[j][None, :]) @ du[j]
        return y

    def _state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
        raise NotImplementedError


@dataclass(frozen=True)
class Fopdt(_Model):
    """First order plus dead time, ``G(s) = gain * e^{-delay*s} / (tau*s + 1)``."""

    gain: float
    """Steady-state output per input unit (e.g. um/K)."""
    tau_s: float
    """Time constant [s]."""
    delay_s: float
    """Dead time [s]."""
    rms: float | None = field(default=None, compare=False)
    """RMS of the fit's residual [output units]; None for a model not fitted."""

    def __post_init__(self) -> None:
        _finite("gain", self.gain)
        if not _finite("tau_s", self.tau_s) > 0:
            raise ModelError(f"tau_s must be positive, got {self.tau_s}")
        if not _finite("delay_s", self.delay_s) >= 0:
            raise ModelError(f"delay_s must not be negative, got {self.delay_s}")

    def step_response(self, t_s: np.ndarray) -> np.ndarray:
        """Output for a unit input step at t = 0 [output units], at times ``t_s`` [s]."""
        lag = np.maximum(np.asarray(t_s, float) - self.delay_s, 0.0)
        return self.gain * -np.expm1(-lag / self.tau_s)

    def _state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (
            np.array([[-1.0 / self.tau_s]]),
            np.array([self.gain / self.tau_s]),
            np.array([1.0]),
        )

    def describe(self) -> str:
        fit = "" if self.rms is None else f", fit RMS {self.rms:.3g}"
        return (
            f"FOPDT: gain {self.gain:.4g}, tau {self.tau_s:.4g} s, delay {self.delay_s:.4g} s{fit}"
        )


@dataclass(frozen=True)
class Sopdt(_Model):
    """Second order plus dead time, ``G(s) = gain * e^{-delay*s} / ((tau*s + 1)(tau2*s + 1))``,
    ``tau_s >= tau2_s`` (tau1, the dominant lag, first as in SIMC)."""

    gain: float
    """Steady-state output per input unit (e.g. um/K)."""
    tau_s: float
    """Dominant time constant tau1 [s]."""
    tau2_s: float
    """Second time constant [s], 0 < tau2 <= tau1."""
    delay_s: float
    """Dead time [s]."""
    rms: float | None = field(default=None, compare=False)
    """RMS of the fit's residual [output units]; None for a model not fitted."""

    def __post_init__(self) -> None:
        _finite("gain", self.gain)
        if not _finite("tau_s", self.tau_s) > 0:
            raise ModelError(f"tau_s must be positive, got {self.tau_s}")
        if not 0 < _finite("tau2_s", self.tau2_s) <= self.tau_s:
            raise ModelError(f"tau2_s must be in (0, tau_s = {self.tau_s}], got {self.tau2_s}")
        if not _finite("delay_s", self.delay_s) >= 0:
            raise ModelError(f"delay_s must not be negative, got {self.delay_s}")

    def step_response(self, t_s: np.ndarray) -> np.ndarray:
        """Output for a unit input step at t = 0 [output units], at times ``t_s`` [s]."""
        lag = np.maximum(np.asarray(t_s, float) - self.delay_s, 0.0)
        return self.gain * (1.0 - _tail2(lag, self.tau_s, self.tau2_s))

    def _state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # two lags in series: x1' = (k*u - x1)/tau1, x2' = (x1 - x2)/tau2, y = x2
        a = np.array([[-1.0 / self.tau_s, 0.0], [1.0 / self.tau2_s, -1.0 / self.tau2_s]])
        return a, np.array([self.gain / self.tau_s, 0.0]), np.array([0.0, 1.0])

    def describe(self) -> str:
        fit = "" if self.rms is None else f", fit RMS {self.rms:.3g}"
        return (
            f"SOPDT: gain {self.gain:.4g}, tau1 {self.tau_s:.4g} s, tau2 {self.tau2_s:.4g} s, "
            f"delay {self.delay_s:.4g} s{fit}"
        )


def fit_step_model(time_s: Any, u: Any, y: Any, *, order: int = 2) -> Fopdt | Sopdt:
    """Least-squares fit of a first- (``order=1``) or second-order-plus-dead-time model
    (``order=2``) to an input/output record.

    The input may be any piecewise-constant signal (one step, several, a pseudo-random
    sequence), each ``u[k]`` held until the next sample (see :meth:`Fopdt.response`). The record
    must start at rest: the fit uses ``u - u[0]`` and ``y`` less its mean over the samples up to
    the first change of ``u`` (they are all the rest value; a mean of several is less noisy
    than ``y[0]`` alone).

    The gain enters linearly, so it is solved in closed form for each set of time constants
    and delay (variable projection); :func:`scipy.optimize.least_squares` with bounds searches
    the rest: ln(tau1/T) in [ln 1e-4, ln 10], tau2/tau1 in [1e-3, 1], delay/T in [0, 0.5], T the
    span after the first change. It starts from a grid of time constants (T/30, T/8, T/2),
    delays (0, T/20) and, for SOPDT, ratios (0.1, 0.5) and keeps the least residual: the sum of
    squares has local minima (tau2 against delay above all).

    Parameters
    ----------
    time_s : array-like
        Sample times [s], strictly increasing.
    u, y : array-like
        Input [input units] and output [output units] at those times.
    order : {1, 2}
        1 for :class:`Fopdt`, 2 for :class:`Sopdt`.

    Returns
    -------
    Fopdt or Sopdt
        The fitted model; its ``rms`` attribute is the RMS residual [output units].

    Raises
    ------
    CalibrationError
        Bad input, an input that never changes, fewer than 4 samples after the first change,
        or an order other than 1 or 2.
    """
    if order not in (1, 2):
        raise CalibrationError(f"order must be 1 or 2, got {order!r}")
    t, uu, yy = _io(time_s, u=u, y=y)
    du = uu - uu[0]
    moved = np.flatnonzero(du != 0.0)
    if moved.size == 0:
        raise CalibrationError("the input never changes: a step response needs a step")
    first = int(moved[0])
    if t.size - first < 4:
        raise CalibrationError("fewer than 4 samples after the input's first change")
    dy = yy - np.mean(yy[: first + 1])
    span = float(t[-1] - t[first])

    def unit_model(p: np.ndarray) -> Fopdt | Sopdt:
        tau = span * math.exp(p[0])
        delay = span * p[-1]
        if order == 1:
            return Fopdt(1.0, tau, delay)
        return Sopdt(1.0, tau, tau * p[1], delay)

    def residual(p: np.ndarray) -> np.ndarray:
        s = unit_model(p).response(t, du)
        ss = float(s @ s)
        gain = float(s @ dy) / ss if ss > 0 else 0.0
        return dy - gain * s

    if order == 1:
        lower, upper = [math.log(1e-4), 0.0], [math.log(10.0), 0.5]
        starts = [[math.log(f), d] for f in (1 / 30, 1 / 8, 1 / 2) for d in (0.0, 0.05)]
    else:
        lower, upper = [math.log(1e-4), 1e-3, 0.0], [math.log(10.0), 1.0, 0.5]
        starts = [
            [math.log(f), r, d]
            for f in (1 / 30, 1 / 8, 1 / 2)
            for r in (0.1, 0.5)
            for d in (0.0, 0.05)
        ]
    best = None
    for x0 in starts:
        sol = least_squares(residual, x0, bounds=(lower, upper), x_scale=1.0)
        if best is None or sol.cost < best.cost:
            best = sol
    assert best is not None
    unit = unit_model(best.x)
    s = unit.response(t, du)
    gain = float(s @ dy) / float(s @ s) if float(s @ s) > 0 else 0.0
    rms = float(np.sqrt(np.mean((dy - gain * s) ** 2)))
    if order == 1:
        return Fopdt(gain, unit.tau_s, unit.delay_s, rms=rms)
    return Sopdt(gain, unit.tau_s, unit.tau2_s, unit.delay_s, rms=rms)  # type: ignore[union-attr]


def pid_gains(kp: float, ki_per_s: float, kd_s: float, source: str = "") -> PidGains:
    """:class:`compensator.cooling_law.PidGains` (the cooling law's gains), or a one-line
    CalibrationError: the cooling loop takes non-negative gains only (a warmer coolant lets the
    spindle grow), so a negative one means a sign mixed up in the record or the model."""
    try:
        return PidGains(kp=kp, ki_per_s=ki_per_s, kd_s=kd_s, source=source)
    except ValidationError as err:
        raise CalibrationError(
            f"PID gains kp {kp:.4g}, ki {ki_per_s:.4g} /s, kd {kd_s:.4g} s are not finite and "
            "non-negative (a negative plant gain? the cooling loop expects warmer coolant to "
            "let the spindle grow)"
        ) from err


@dataclass(frozen=True)
class DiscretePid:
    """Paper 000's discrete PID, ``u_k = u_k0 + kp*e_k + ki*sum_{j<=k} e_j + kd*(e_k - e_{k-1})``,
    run every ``dt_s``; ``ki`` and ``kd`` are per sample."""

    kp: float
    """[input units per error unit]"""
    ki: float
    """Integral gain per sample [input units per error unit]."""
    kd: float
    """Derivative gain per sample difference [input units per error unit]."""
    dt_s: float
    """Sample period [s]."""
    source: str = ""
    """Where the gains come from."""

    def __post_init__(self) -> None:
        for name in ("kp", "ki", "kd"):
            _finite(name, getattr(self, name))
        if not _finite("dt_s", self.dt_s) > 0:
            raise ModelError(f"dt_s must be positive, got {self.dt_s}")

    def continuous(self) -> PidGains:
        """The same controller as continuous parallel gains: ki_per_s = ki/dt, kd_s = kd*dt."""
        return pid_gains(self.kp, self.ki / self.dt_s, self.kd * self.dt_s, self.source)


def discrete_gains(gains: PidGains, dt_s: float) -> DiscretePid:
    """Paper 000's discrete form of parallel ``gains`` at ``dt_s`` [s]: ki = ki_per_s*dt
    (rectangle rule for the integral), kd = kd_s/dt (backward difference for the derivative).

    Raises
    ------
    CalibrationError
        A ``dt_s`` that is not positive and finite.
    """
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise CalibrationError(f"dt_s must be positive, got {dt_s}")
    return DiscretePid(gains.kp, gains.ki_per_s * dt_s, gains.kd_s / dt_s, dt_s, gains.source)


@dataclass(frozen=True)
class PidTuning:
    """PID in series (cascade, "interacting") form, as SIMC gives it:
    ``C(s) = kc * (1 + 1/(ti*s)) * (1 + td*s)``; ``ti_s = inf`` for no integral action."""

    kc: float
    """Controller gain [input units per error unit]."""
    ti_s: float
    """Integral time [s]."""
    td_s: float
    """Derivative time [s]."""
    rule: str = ""
    """How the numbers were found."""

    def __post_init__(self) -> None:
        _finite("kc", self.kc)
        if not (self.ti_s > 0 and not math.isnan(self.ti_s)):
            raise ModelError(f"ti_s must be positive (inf for none), got {self.ti_s}")
        if not _finite("td_s", self.td_s) >= 0:
            raise ModelError(f"td_s must not be negative, got {self.td_s}")

    def parallel(self) -> PidGains:
        """The ideal parallel form. Expanding the series form gives ``kc' = kc*(1 + td/ti)``,
        ``ti' = ti + td``, ``td' = ti*td/(ti + td)`` in the ideal form, so ``kp = kc'``,
        ``ki = kc'/ti' = kc/ti``, ``kd = kc'*td' = kc*td`` (Skogestad 2003). The gains are the
        cooling law's :class:`compensator.cooling_law.PidGains`: non-negative, or a CalibrationError
        (see :func:`pid_gains`)."""
        ratio = 0.0 if math.isinf(self.ti_s) else self.td_s / self.ti_s
        ki = 0.0 if math.isinf(self.ti_s) else self.kc / self.ti_s
        return pid_gains(self.kc * (1.0 + ratio), ki, self.kc * self.td_s, self.rule)

    def discrete(self, dt_s: float) -> DiscretePid:
        """Paper 000's discrete gains at ``dt_s`` [s] (through :meth:`parallel`)."""
        return discrete_gains(self.parallel(), dt_s)

    def describe(self) -> str:
        return f"Kc {self.kc:.4g}, tauI {self.ti_s:.4g} s, tauD {self.td_s:.4g} s" + (
            f" ({self.rule})" if self.rule else ""
        )


def paper_tuning() -> PidGains:
    """Paper 000's empirical gains, kp = 2, ki = 0, kd = 50 per sample at 1 s, as parallel gains
    (kd_s = 50 s): :meth:`compensator.cooling_law.PidGains.paper`. Units of the paper's loop:
    coolant temperature [K] per um of thermal error."""
    return PidGains.paper()


def simc(model: Fopdt | Sopdt, *, tau_c_s: float | None = None) -> PidTuning:
    """Skogestad's SIMC PI/PID tuning of a FOPDT or SOPDT model (series form).

    ``Kc = (1/k) * tau1/(tau_c + theta)``, ``tauI = min(tau1, 4*(tau_c + theta))``,
    ``tauD = tau2`` for SOPDT (0 for FOPDT: a PI controller), with k the gain, theta the delay
    (Skogestad 2003).

    ``tau_c_s`` is the desired closed-loop time constant [s]. The default is SIMC's "tight
    control" choice tau_c = theta (gain margin about 3, phase margin about 47 deg or more;
    set-point overshoot 4-10 % measured on exact FOPDT models sampled at theta/20), but never
    below ``TAU_C_FLOOR_FRACTION * tau1``. The fitted delay is the least certain parameter: a
    record sampled at dt cannot resolve theta < dt, and small unmodelled lags (the chiller's
    own loop, the thermal-error estimator) hide in it; as theta -> 0 the rule's gain grows
    without bound while those hidden lags stay. The floor caps Kc at 10/|k|, a closed loop at
    most ten times faster than the open loop. At theta/tau1 = 0.1 (Skogestad's example) floor
    and rule agree. An explicit ``tau_c_s`` is used as given (tau_c + theta must be positive).

    Raises
    ------
    CalibrationError
        A zero gain, or a ``tau_c_s`` that is negative, non-finite or leaves tau_c + theta = 0.
    """
    k, theta, tau1 = model.gain, model.delay_s, model.tau_s
    tau2 = model.tau2_s if isinstance(model, Sopdt) else 0.0
    if k == 0:
        raise CalibrationError("the model's gain is 0: no controller can move its output")
    if tau_c_s is None:
        floor = TAU_C_FLOOR_FRACTION * tau1
        tau_c = max(theta, floor)
        why = (
            "tau_c = theta" if theta >= floor else f"tau_c = {TAU_C_FLOOR_FRACTION:g}*tau1 (floor)"
        )
    else:
        tau_c = float(tau_c_s)
        if not (math.isfinite(tau_c) and tau_c >= 0 and tau_c + theta > 0):
            raise CalibrationError(f"tau_c_s must be >= 0 with tau_c + delay > 0, got {tau_c_s}")
        why = "tau_c given"
    kc = tau1 / (k * (tau_c + theta))
    ti = min(tau1, 4.0 * (tau_c + theta))
    rule = f"SIMC (Skogestad 2003), {why} = {tau_c:.4g} s"
    return PidTuning(kc, ti, tau2, rule)


def _discretise(a: np.ndarray, b: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold transition over ``h`` [s]: x+ = phi*x + gamma*u."""
    n = a.shape[0]
    m = np.zeros((n + 1, n + 1))
    m[:n, :n] = a * h
    m[:n, n] = b * h
    e = expm(m)
    return e[:n, :n], e[:n, n]


def _simulate_loop(
    model: Fopdt | Sopdt,
    gains: PidGains | PidTuning,
    *,
    dt_s: float,
    duration_s: float,
    u_limits: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(time [s], output, controller output u) of :func:`closed_loop_step`."""
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise CalibrationError(f"dt_s must be positive, got {dt_s}")
    if not (math.isfinite(duration_s) and duration_s >= dt_s):
        raise CalibrationError(f"duration_s must be at least dt_s = {dt_s}, got {duration_s}")
    steps = round(duration_s / dt_s)
    if steps > _MAX_LOOP_STEPS:
        raise CalibrationError(f"{steps} steps: at most {_MAX_LOOP_STEPS} are simulated")
    lo, hi = -math.inf, math.inf
    if u_limits is not None:
        lo, hi = float(u_limits[0]), float(u_limits[1])
        if not lo < hi:
            raise CalibrationError(f"u_limits must be (low, high) with low < high, got {u_limits}")
    pid = discrete_gains(gains.parallel() if isinstance(gains, PidTuning) else gains, dt_s)
    a, b, c = model._state_space()
    # delay = (m + f)*dt: over [t_k, t_k+1) the plant sees u_{k-m-1} for f*dt, then u_{k-m}
    m = math.floor(model.delay_s / dt_s)
    f = model.delay_s / dt_s - m
    phi1, g1 = _discretise(a, b, f * dt_s)
    phi2, g2 = _discretise(a, b, (1.0 - f) * dt_s)
    x = np.zeros(a.shape[0])
    y = np.zeros(steps + 1)
    u = np.zeros(steps + 1)
    e_prev, integral = 0.0, 0.0  # at rest before the set point steps from 0 to 1 at t = 0
    for k in range(steps + 1):
        y[k] = c @ x
        e = 1.0 - y[k]
        trial = integral + e
        raw = pid.kp * e + pid.ki * trial + pid.kd * (e - e_prev)
        u[k] = min(max(raw, lo), hi)
        # conditional integration: a saturated output keeps the sum, so it cannot wind up
        if u[k] == raw:
            integral = trial
        e_prev = e
        if k == steps:
            break
        x = phi1 @ x + g1 * (u[k - m - 1] if k - m - 1 >= 0 else 0.0)
        x = phi2 @ x + g2 * (u[k - m] if k - m >= 0 else 0.0)
    return np.arange(steps + 1) * dt_s, y, u


def closed_loop_step(
    model: Fopdt | Sopdt,
    gains: PidGains | PidTuning,
    *,
    dt_s: float,
    duration_s: float,
    u_limits: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The model's output under paper 000's discrete PID for a unit set-point step at t = 0.

    Every ``dt_s`` the controller reads ``y_k`` and writes ``u_k = kp*e_k + ki*sum e +
    kd*(e_k - e_{k-1})`` (``gains`` discretised by :func:`discrete_gains`; derivative on the
    error and unfiltered, as in the paper, so the step gives a derivative kick of
    ``kd_s/dt_s``), held until the next sample; ``e = 1 - y``, everything at rest and 0 before
    t = 0. The plant is stepped exactly (matrix exponential of its state space over the
    sub-steps the delay splits each sample into), so ``model.response(time_s, u)`` of the
    controller's outputs reproduces ``y``. With ``u_limits = (low, high)`` the output is
    clamped and the integral is not accumulated while clamped (conditional integration).

    Returns
    -------
    (time_s, y)
        Times ``0, dt, ..., duration`` [s] and the output there [output units].

    Raises
    ------
    CalibrationError
        A non-positive ``dt_s``, a duration shorter than ``dt_s``, or bad ``u_limits``.
    """
    t, y, _ = _simulate_loop(model, gains, dt_s=dt_s, duration_s=duration_s, u_limits=u_limits)
    return t, y


@dataclass(frozen=True)
class StepMetrics:
    """How a response followed a set-point step."""

    overshoot_pct: float
    """Largest excursion past the target, % of the target (0 if none)."""
    rise_s: float | None
    """Time from 10 % to 90 % of the target [s], None if 90 % is never reached."""
    settling_s: float | None
    """Time from the first sample after which the output stays within 2 % of the target [s],
    None if it is outside at the end."""
    iae: float
    """Integral of |target - y| dt [output units * s] (trapezoid rule)."""

    def describe(self) -> str:
        rise = "never rises to 90 %" if self.rise_s is None else f"rise {self.rise_s:.4g} s"
        settle = (
            "never settles within 2 %"
            if self.settling_s is None
            else f"settles (2 %) in {self.settling_s:.4g} s"
        )
        return f"overshoot {self.overshoot_pct:.1f} %, {rise}, {settle}, IAE {self.iae:.4g}"


def _first_reach(t: np.ndarray, z: np.ndarray, level: float) -> float | None:
    i = np.flatnonzero(z >= level)
    if i.size == 0:
        return None
    j = int(i[0])
    if j == 0:
        return float(t[0])
    return float(t[j - 1] + (level - z[j - 1]) / (z[j] - z[j - 1]) * (t[j] - t[j - 1]))


def step_metrics(time_s: Any, y: Any, target: float) -> StepMetrics:
    """Overshoot, 10-90 % rise time, 2 % settling time and IAE of a step response.

    ``y`` starts from 0 and heads for ``target`` (non-zero; a negative target is mirrored).
    Rise times are interpolated between samples; the settling time is the first sample time
    after which ``|y - target| <= 2 % |target|`` to the end, counted from ``time_s[0]``.

    Raises
    ------
    CalibrationError
        Bad input or a zero or non-finite target.
    """
    t, yy = _io(time_s, y=y)
    if not (math.isfinite(target) and target != 0):
        raise CalibrationError(f"target must be finite and non-zero, got {target}")
    z = yy / target  # normalised: the target is 1
    overshoot = max(0.0, float(np.max(z)) - 1.0) * 100.0
    r10, r90 = _first_reach(t, z, 0.1), _first_reach(t, z, 0.9)
    rise = None if r10 is None or r90 is None else r90 - r10
    outside = np.flatnonzero(np.abs(z - 1.0) > SETTLING_BAND)
    if outside.size == 0:
        settling: float | None = 0.0
    elif outside[-1] == t.size - 1:
        settling = None
    else:
        settling = float(t[outside[-1] + 1] - t[0])
    err = np.abs(target - yy)
    iae = float(np.sum(0.5 * (err[1:] + err[:-1]) * np.diff(t)))
    return StepMetrics(overshoot, rise, settling, iae)
