"""Exact first-order steps: one step for the per-cycle paths, and whole logged series at any
sample period. Pure: numpy (and scipy for batch work over whole logs).

Every model here is built of first-order lags, ``dx/dt = (u - x)/tau`` or in rate form
``dx/dt = -lambda*x + g``. With the input held over a step of ``dt`` both have the exact
zero-order-hold solution::

    x' = a*x + (1 - a)*u,            a = exp(-dt/tau)
    x' = a*x + (1 - a)/lambda * g,   a = exp(-lambda*dt)   (dt*g at lambda = 0)

- one step: :func:`lag_step`, :func:`rate_step` (and :func:`rate_gains`, its two factors);
- a logged series: a logged value ``u[k]`` is held over ``(t[k-1], t[k]]`` (the run-log
  convention). :class:`Steps` checks the time stamps once; :func:`lag` filters a series over
  them; :func:`filter_bank` is the checked, bounded form the identification builds its
  regressors with (``calibration``); :func:`first_order` takes the steps themselves;
- the recursion underneath, ``x_k = exp(-ld_k)*x_{k-1} + inc_k`` with any per-step decay ``ld``
  (a rate that varies with speed): :func:`decaying_sum`, and :func:`constant_decay` when it is
  constant (one ``scipy.signal.lfilter`` pass).

A series is one recursive filter pass per run of equal steps (a logger's clock, gaps apart), and
otherwise closed form per block, ``x_k = exp(-L_k) * (x_s + sum_j inc_j*exp(L_j))`` with L the
cumulative decay since the block's start: no Python loop over samples, and a gap of hours is one
exact step. The models, the identification and the virtual machine all step through here, so
they compute the same numbers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import ModelError, NonFiniteInputError

SPAN = 50.0
"""Largest exponent inside one closed-form block: exp(50) ~ 5e21, far from overflow."""
_BLOCK = 16384  # samples per closed-form block: keeps the cumulative sums precise and in cache
_LD_MAX = 1e4  # dt/tau beyond this is a full reset (exp(-1e4) == 0); keeps sums finite
_MIN_RUN = 64  # equal steps per run, on average, for the recursive pass to pay


# -- one step ---------------------------------------------------------------------------------


def lag_step(x: float, u: float, dt_s: float, tau_s: float) -> float:
    """``x`` after ``dt_s`` of ``dx/dt = (u - x)/tau`` with ``u`` held: ``a*x + (1 - a)*u``,
    ``a = exp(-dt/tau)``. ``tau_s`` 0 is no lag (``u``); a step of any length is exact."""
    if tau_s == 0:
        return u
    ld = dt_s / tau_s
    return math.exp(-ld) * x - math.expm1(-ld) * u


def rate_gains(rate_per_s: float, dt_s: float) -> tuple[float, float]:
    """``(a, h)`` of the step ``x' = a*x + h*g`` of ``dx/dt = -rate*x + g``: ``a = exp(-rate*dt)``,
    ``h = (1 - a)/rate``, ``dt`` at rate 0 (the limit)."""
    ld = rate_per_s * dt_s
    h = -math.expm1(-ld) / rate_per_s if rate_per_s != 0.0 else dt_s
    return math.exp(-ld), h


def rate_step(x: float, rate_per_s: float, drive: float, dt_s: float) -> float:
    """``x`` after ``dt_s`` of ``dx/dt = -rate*x + drive`` with both held (exact)."""
    a, h = rate_gains(rate_per_s, dt_s)
    return a * x + h * drive


# -- the recursion over a series ----------------------------------------------------------------


def one_minus_exp(ld: np.ndarray) -> np.ndarray:
    """1 - exp(-ld), accurate for tiny ld: the input gain of every step."""
    gain: np.ndarray = -np.expm1(-ld)
    return gain


def constant_decay(a: float, inc: np.ndarray, x0: float, gain: float = 1.0) -> np.ndarray:
    """``x_k = a*x_{k-1} + gain*inc_k`` for every k, from ``x_{-1} = x0``: one recursive pass
    (``scipy.signal.lfilter``: the same recursion, with its constant coefficients)."""
    from scipy.signal import lfilter  # batch work only: the runtime's install has no scipy

    x: np.ndarray = lfilter([gain], [1.0, -a], inc, zi=[a * x0])[0]  # scipy has no types
    return x


def decaying_sum(
    inc: np.ndarray,
    x0: float,
    *,
    ld: np.ndarray | None = None,
    cum: np.ndarray | None = None,
    span: float = SPAN,
) -> np.ndarray:
    """``x_k = exp(-ld_k)*x_{k-1} + inc_k`` for every k, from ``x_{-1} = x0``, in closed form.

    ``x_k = exp(-L_k) * (x_s + sum_{s<j<=k} inc_j*exp(L_j))`` with ``L`` the cumulative ``ld``
    since the block's start ``s``; a block ends before L passes ``span``, so every exponential
    is finite. Give the decay of each step, ``ld`` (>= 0), or its cumulative sum from the start,
    ``cum`` (finite), when the caller has it more exactly than a running sum (elapsed time
    over tau). A block whose sums overflow (an input near the float range) is redone scaled by
    a power of two, which is exact.
    """
    m = inc.size
    out = np.empty(m)
    s, xs = 0, float(x0)
    while s < m:
        if cum is None:
            step = ld[s:]  # type: ignore[index]
            big = float(step.max())
            if big > span:  # one step longer than the span: exp(-span) is already 0 in floats
                step = np.minimum(step, span)
            L = np.cumsum(step)
        else:
            L = cum[s:] - cum[s - 1] if s else cum
        e = m
        if L[-1] > span:
            e = s + max(1, int(np.searchsorted(L, span)))
            L = L[: e - s]
        if e == s + 1:  # one long step: direct
            a = math.exp(-min(float(L[0]), _LD_MAX))
            out[s] = xs = a * xs + float(inc[s])
            s = e
            continue
        g = np.exp(L)
        c = inc[s:e] * g
        np.cumsum(c, out=c)
        c += xs
        c /= g
        if not math.isfinite(float(c[-1])):
            peak = max(float(np.max(np.abs(inc[s:e]))), abs(xs))
            k = math.frexp(peak)[1] + 80  # scale to 2**-80: far from overflow after exp(span)
            c = inc[s:e] * (g * 2.0**-k)
            np.cumsum(c, out=c)
            c += xs * 2.0**-k
            c /= g
            c *= 2.0**k
        out[s:e] = c
        xs = float(c[-1])
        s = e
    return out


# -- time stamps ----------------------------------------------------------------------------------


def series(name: str, values: Any, size: int | None = None) -> np.ndarray:
    """``values`` as a finite 1-D float array; a one-line error naming the sample otherwise."""
    try:
        a = np.asarray(values, dtype=float)
    except (TypeError, ValueError) as err:
        raise ModelError(f"{name} is not numeric") from err
    if a.ndim != 1:
        raise ModelError(f"{name} must be one-dimensional")
    if size is not None and a.size != size:
        raise ModelError(f"{name} has {a.size} values for {size} time stamps")
    if not all_finite(a):
        i = int(np.flatnonzero(~np.isfinite(a))[0])
        raise NonFiniteInputError(f"{name} at sample {i} is {a[i]}")
    return a


def all_finite(a: np.ndarray) -> bool:
    """Every value finite. A sum is finite when every term is (and, but for overflow, only
    then): one cheap pass without a mask."""
    with np.errstate(over="ignore", invalid="ignore"):
        if math.isfinite(float(np.add.reduce(a, axis=None))):
            return True
    return bool(np.isfinite(a).all())


def times(time_s: Any) -> np.ndarray:
    """Time stamps [s]: finite and never going backwards."""
    return Steps.of(time_s).time_s


@dataclass(frozen=True, slots=True, eq=False)
class Steps:
    """Time stamps checked once for any number of filters: ``dt_s[k-1]`` is the step ending at
    sample k; ``runs`` the starts of the runs of equal steps (indices into ``dt_s``), or None
    where there are too many for one recursive pass each (a clock that wanders)."""

    time_s: np.ndarray
    dt_s: np.ndarray
    runs: np.ndarray | None

    @classmethod
    def of(cls, time_s: Any) -> Steps:
        """From time stamps [s]: finite and never going backwards, else an error naming the sample."""
        t = series("time_s", time_s)
        d = np.diff(t)
        if d.size:
            lo = float(d.min())
            if not math.isfinite(lo) or not math.isfinite(float(d.max())):
                raise NonFiniteInputError("time_s spans more than a float can hold")
            if lo < 0:
                raise ModelError(
                    f"time goes backwards at sample {int(np.flatnonzero(d < 0)[0]) + 1}"
                )
        return cls(t, d, _runs(d))

    @classmethod
    def from_dt(cls, dt_s: np.ndarray) -> Steps:
        """From the steps themselves (>= 0, unchecked), the first sample at time 0."""
        d = np.asarray(dt_s, dtype=float)
        t = np.empty(d.size + 1)
        t[0] = 0.0
        np.cumsum(d, out=t[1:])
        return cls(t, d, _runs(d))

    @property
    def size(self) -> int:
        return self.time_s.size


def _runs(dt_s: np.ndarray) -> np.ndarray | None:
    """Where the step changes, when there are few enough changes for one recursive filter pass
    per run of equal steps; None otherwise."""
    if dt_s.size < 2:
        return np.zeros(1, dtype=np.intp)
    changed = dt_s[1:] != dt_s[:-1]
    if np.count_nonzero(changed) > dt_s.size // _MIN_RUN:
        return None
    return np.concatenate([[0], np.flatnonzero(changed) + 1])


def lag(steps: Steps, u: np.ndarray, tau_s: float, y0: float | None = None) -> np.ndarray:
    """``u`` (finite, one value per time stamp) through ``dy/dt = (u - y)/tau``, exact at every
    step: ``y_k = a_k*y_{k-1} + (1 - a_k)*u_k``, ``a_k = exp(-dt_k/tau)``, ``y_0 = y0`` (default
    ``u_0``). ``tau_s`` 0 is ``u`` itself. Nothing is checked here: :meth:`Steps.of` checks the
    time stamps, callers the values (:func:`series`)."""
    n = u.size
    if tau_s == 0:
        return np.array(u, dtype=float)
    y = np.empty(n)
    if n == 0:
        return y
    y[0] = u[0] if y0 is None else y0
    if n == 1:
        return y
    dt, runs = steps.dt_s, steps.runs
    if runs is not None and runs.size == 1:  # one run of equal steps: one pass, no copy
        from scipy.signal import lfilter

        ld = min(float(dt[0]) / tau_s, _LD_MAX)
        b = -math.expm1(-ld)
        start = y[0]
        # lfilter's first output is b*u_0 + zi: the state that makes it y_0
        y = np.asarray(lfilter([b], [1.0, -math.exp(-ld)], u, zi=[start - b * float(u[0])])[0])
        y[0] = start
        return y
    if runs is not None:
        ends = np.concatenate([runs[1:], [dt.size]])
        for s, e in zip(runs.tolist(), ends.tolist()):  # steps s..e-1 end at samples s+1..e
            ld = min(float(dt[s]) / tau_s, _LD_MAX)
            y[s + 1 : e + 1] = constant_decay(
                math.exp(-ld), u[s + 1 : e + 1], y[s], -math.expm1(-ld)
            )
        return y
    t = steps.time_s
    s = 0
    with np.errstate(over="ignore"):  # a tiny tau: dt/tau is inf, a full reset
        while s < n - 1:  # steps s..e-1, ending at samples s+1..e, spanning at most SPAN*tau
            reach = int(np.searchsorted(t, t[s] + SPAN * tau_s, side="right")) - 1
            e = max(min(s + _BLOCK, n - 1, reach), s + 1)
            ys = float(y[s])
            # -(1 - a_k)*u_k, and the time since the block's start over tau (exact, where a
            # running sum of steps is not)
            c = np.divide(dt[s:e], -tau_s)
            np.expm1(c, out=c)
            c *= u[s + 1 : e + 1]
            g = t[s + 1 : e + 1] - t[s]
            g /= tau_s
            if e - s == 1 or not g[-1] <= SPAN * 1.01:  # one long step, or a subnormal tau
                y[s + 1 : e + 1] = decaying_sum(
                    np.negative(c), ys, ld=np.minimum(dt[s:e] / tau_s, _LD_MAX)
                )
                s = e
                continue
            np.exp(g, out=g)
            c *= g  # the closed form of decaying_sum, fused: this is the hot loop of a free run
            np.cumsum(c, out=c)
            np.subtract(ys, c, out=c)
            np.divide(c, g, out=y[s + 1 : e + 1])
            if not math.isfinite(float(y[e])):  # an input near the float range: rescaled there
                c = np.expm1(np.divide(dt[s:e], -tau_s)) * u[s + 1 : e + 1]
                y[s + 1 : e + 1] = decaying_sum(np.negative(c), ys, cum=np.log(g))
            s = e
    return y


def lowpass(dt_s: np.ndarray, w: np.ndarray, tau_s: float, y0: float | None = None) -> np.ndarray:
    """:func:`lag` over the steps ``dt_s`` (``dt_s[k-1]`` ends at sample k)."""
    return lag(Steps.from_dt(dt_s), np.asarray(w, dtype=float), tau_s, y0)


def first_order(drive: np.ndarray, dt_s: np.ndarray, tau_s: float, x0: float) -> np.ndarray:
    """``dx/dt = (drive - x)/tau``, exact for a drive held over each step, from ``x[0] = x0``;
    ``dt_s[k]`` is the step ending at sample k (``dt_s[0]`` is not used); tau 0: x = drive."""
    d = np.asarray(drive, dtype=float)
    if tau_s == 0:
        return d.copy()
    return lag(Steps.from_dt(np.asarray(dt_s, dtype=float)[1:]), d, tau_s, x0)


def check_taus(taus_s: Sequence[float]) -> tuple[float, ...]:
    out = tuple(float(t) for t in taus_s)
    if not all(math.isfinite(t) and t >= 0 for t in out):
        raise ModelError(f"time constants must be finite and >= 0, got {out}")
    return out


def filter_bank(time_s: Any, u: Any, taus_s: Sequence[float]) -> np.ndarray:
    """``u`` through first-order filters, one column per time constant: shape (len(u), len(taus)).

    Exact zero-order hold at any Δt: ``u[k]`` is held over ``(time_s[k-1], time_s[k]]``; each
    filter starts at equilibrium with the first input (``y_0 = u_0``); tau = 0 is the input
    itself. A gap of hours is one exact step (no overflow: exponents stay below 50). Every output
    lies within the range of ``u`` (it is a convex combination of its values), which the result
    is clipped to, so any finite input gives a finite output.
    """
    steps = Steps.of(time_s)
    x = series("u", u, steps.size)
    taus = check_taus(taus_s)
    out = np.empty((x.size, len(taus)))
    if x.size == 0:
        return out
    lo, hi = float(x.min()), float(x.max())
    centre = lo / 2 + hi / 2
    half = hi / 2 - lo / 2
    w = (x - centre) / half if half > 0 else None
    for j, tau in enumerate(taus):
        if tau == 0 or w is None:
            out[:, j] = x
            continue
        y = np.clip(lag(steps, w, tau), -1.0, 1.0)
        with np.errstate(over="ignore"):  # only at the very ends of the float range
            y *= half
            y += centre
        np.clip(y, lo, hi, out=y)
        out[:, j] = y
    return out


def decay(time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """exp(-(t - t_0)/tau): how much of an initial error is left at each sample (0 < tau)."""
    with np.errstate(over="ignore"):
        left: np.ndarray = np.exp(-np.minimum((time_s - time_s[0]) / tau_s, _LD_MAX))
    return left
