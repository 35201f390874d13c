"""Exact first-order filters over logged series, at any sample period. Pure: numpy (and scipy
for batch work over whole logs).

A logged value ``u[k]`` is held over ``(t[k-1], t[k]]`` (the run-log convention), so a first-order
lag ``dy/dt = (u - y)/tau`` has the exact zero-order-hold solution::

    y_k = a_k*y_{k-1} + (1 - a_k)*u_k,   a_k = exp(-(t_k - t_{k-1})/tau)

:func:`lowpass` evaluates it in closed form per block instead of a Python loop, and takes a gap of
hours as one exact step. Used by the identification (``calibration.ident``) to build its
regressors and by :class:`compensator.statespace.StateSpaceModel` to free-run a log, so both
compute the same numbers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from .errors import ModelError, NonFiniteInputError

SPAN = 50.0
"""Largest exponent inside one closed-form block: exp(50) ~ 5e21, far from overflow."""
_BLOCK = 8192  # samples per closed-form block: keeps the cumulative sums precise
_LD_MAX = 1e4  # dt/tau beyond this is a full reset (exp(-1e4) == 0); keeps sums finite
_MIN_RUN = 64  # equal steps per run, on average, for the recursive pass to pay


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
    if not np.isfinite(a).all():
        i = int(np.flatnonzero(~np.isfinite(a))[0])
        raise NonFiniteInputError(f"{name} at sample {i} is {a[i]}")
    return a


def times(time_s: Any) -> np.ndarray:
    """Time stamps [s]: finite and never going backwards."""
    t = series("time_s", time_s)
    if t.size > 1:
        d = np.diff(t)
        if not np.isfinite(d).all():
            raise NonFiniteInputError("time_s spans more than a float can hold")
        if (d < 0).any():
            raise ModelError(f"time goes backwards at sample {int(np.flatnonzero(d < 0)[0]) + 1}")
    return t


def _runs(dt_s: np.ndarray) -> np.ndarray | None:
    """Where the step changes: the starts of the runs of equal steps (indices into ``dt_s``), when
    there are few enough for one recursive filter pass each; None otherwise (a jittery clock)."""
    change = np.flatnonzero(dt_s[1:] != dt_s[:-1]) + 1
    if change.size > dt_s.size // _MIN_RUN:
        return None
    return np.concatenate([[0], change])


def lowpass(dt_s: np.ndarray, w: np.ndarray, tau_s: float, y0: float | None = None) -> np.ndarray:
    """y_k = a_k*y_{k-1} + (1 - a_k)*w_k, a_k = exp(-dt_k/tau), y_0 = ``y0`` (default w_0).

    ``dt_s[k-1]`` is the step ending at sample k. Where the steps are equal over long runs (a
    logger's clock, gaps apart) each run is one recursive pass (``scipy.signal.lfilter``: the
    same recursion, with its constant coefficient). Otherwise closed form per block,
    ``y_k = exp(-R_k) * (y_s + sum_j b_j*w_j*exp(R_j))`` with R the cumulative dt/tau since the
    block's first sample s, itself reached by one direct step: one step as long as a gap of hours
    is exact, and no exponent exceeds :data:`SPAN`. Callers keep ``|w|`` of order one.
    """
    n = w.size
    y = np.empty(n)
    if n == 0:
        return y
    y[0] = w[0] if y0 is None else y0
    if n == 1:
        return y
    runs = _runs(dt_s)
    if runs is not None:
        from scipy.signal import lfilter  # batch work only: the runtime's install has no scipy

        ends = np.concatenate([runs[1:], [dt_s.size]])
        for s, e in zip(runs.tolist(), ends.tolist()):  # steps s..e-1 end at samples s+1..e
            with np.errstate(over="ignore"):
                ld = min(float(dt_s[s]) / tau_s, _LD_MAX)
            a, b = math.exp(-ld), -math.expm1(-ld)
            y[s + 1:e + 1] = lfilter([b], [1.0, -a], w[s + 1:e + 1], zi=[a * y[s]])[0]
        return y
    with np.errstate(over="ignore"):  # a tiny tau: dt/tau is inf, capped like any full reset
        ld = np.minimum(dt_s / tau_s, _LD_MAX)
    a = np.exp(-ld)
    b = -np.expm1(-ld)
    big = np.concatenate([[0.0], np.cumsum(ld)])  # only to find block ends
    s = 1
    while s < n:
        y[s] = a[s - 1] * y[s - 1] + b[s - 1] * w[s]
        e = int(np.searchsorted(big, big[s] + SPAN, side="right")) - 1
        e = min(e, s + _BLOCK, n - 1)
        if e > s:
            rel = np.cumsum(ld[s:e])  # steps s+1..e, from sample s
            if rel[-1] > SPAN:  # rounding in the global sum: cut where the local one says
                m = max(1, int(np.searchsorted(rel, SPAN, side="right")))
                rel, e = rel[:m], s + m
            g = np.exp(rel)
            c = np.cumsum(b[s:e] * w[s + 1:e + 1] * g)
            c += y[s]
            c /= g
            y[s + 1:e + 1] = c
        s = e + 1
    return y


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
    t = times(time_s)
    x = series("u", u, t.size)
    taus = check_taus(taus_s)
    out = np.empty((x.size, len(taus)))
    if x.size == 0:
        return out
    lo, hi = float(x.min()), float(x.max())
    centre = lo / 2 + hi / 2
    half = hi / 2 - lo / 2
    dt = np.diff(t)
    w = (x - centre) / half if half > 0 else None
    for j, tau in enumerate(taus):
        if tau == 0 or w is None:
            out[:, j] = x
            continue
        y = np.clip(lowpass(dt, w, tau), -1.0, 1.0)
        with np.errstate(over="ignore"):  # only at the very ends of the float range
            y *= half
            y += centre
        np.clip(y, lo, hi, out=y)
        out[:, j] = y
    return out


def decay(time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """exp(-(t - t_0)/tau): how much of an initial error is left at each sample (0 < tau)."""
    with np.errstate(over="ignore"):
        return np.exp(-np.minimum((time_s - time_s[0]) / tau_s, _LD_MAX))
