"""Fusing occasional tool-setter or probe measurements with a model: a Kalman filter on
disturbance states. Pure: numpy and pydantic only, no I/O.

The model's free-run prediction S(t) misses what it does not see (coolant, ambient, load,
wear). The observer estimates that miss as a disturbance b(t) added to the prediction: a random
walk plus, optionally, a drift rate r (an integrated random walk)::

    b' = r + w_b,   r' = w_r,     E[w_b^2] = q_b [um^2/s],  E[w_r^2] = q_r [um^2/s^3]
    y  = S + b + e + v,           E[v^2] = sigma^2 (the stated sigma of the measurement),
                                  E[e^2] = model_sd^2 (the model's fast misses, minutes long)

``e`` is the part of the model's residual that changes faster than probes come (coolant
cycling, a few minutes long on the real record): no disturbance state can follow it, so it
counts as measurement noise. ``q_b`` and ``model_sd`` are fitted from the calibration residuals
(:mod:`calibration.closedloop`'s variogram, ``docs/PROBING.md``); the defaults are the order of the
real record's speed-only residuals.

The time update is the exact discretisation over the real Δt (F = [[1, Δt], [0, 1]], Q from the
continuous noise); the measurement update is exact at any time (Joseph form). An innovation
beyond ``gate_sigma`` standard deviations is rejected (the runtime raises ``PROBE_REJECTED``);
``reaccept_after`` consecutive rejected measurements that agree with each other are taken as a
real change (a step the model cannot know, e.g. a crash or a new tool holder) and the bias
restarts from them, so that one early refusal cannot lock the filter out for good.

Bounds on what measurements can do, whatever the filter concludes (:func:`measurement_update`):

- the **correction** (the bias: the estimate minus the model's free run) never leaves
  ``max_correction_um`` in either direction. A correction that large says the model no longer
  describes the spindle, or a source lies; measurements do not take it further.
- each **source** (the control socket, the controller's probe nodes, ...) moves the correction by
  at most ``max_source_move_um`` net: its moves are summed with their signs, and the sum drains
  toward zero by that much every ``source_window_s``. One source alone moves the correction at
  most that far at once, and that far per window after; moves that cancel (noise) cost nothing.
  The first measurement an observer takes (a start from nothing) is exempt (``first``).
  A drift rate moves the correction too: each source's share of the drift (what its
  measurements changed of it) is charged to that source as the time update carries the
  correction on, and once that source's move is spent its share stops (the drift rate loses
  it). The drift a source taught thus moves the correction no further than its own
  measurements may.

A measurement either limit cuts is taken only as far as the limit allows (:attr:`Update.limited`
says which), and the filter's covariance is left as it was: its information was not taken.
A correction already beyond the bound (a state restored from a wider setting, a switch between a
model with inputs and its fallback) is not cut: measurements can only take it back inside.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    model_serializer,
)

from .errors import ModelError
from .units import require_dt, require_finite

COV_LIMIT = 1e12  # um^2: a gap of years forgets the prior; the numbers stay finite


CORRECTION_LIMIT_UM = 1000.0
"""The largest correction bound that may be configured [um]: no spindle grows a millimetre."""

DEFAULT_WINDOW_S = 3600.0
"""The window of a source's move, unless configured: one hour."""

BOUND_KEYS = ("max_correction_um", "max_source_move_um", "source_window_s")
"""The settings of the bounds: left out of a stored record while unset."""

SIGMA_LIMIT_UM = 1000.0
"""The largest sigma a measurement may state [um]. One less sure than a millimetre says nothing
about a growth of microns, and its square must stay far from overflowing the filter."""


class ObserverConfig(BaseModel):
    """Noise levels of the disturbance model and the outlier gate (immutable)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    bias_q_um2_per_s: float = Field(
        25.0 / 3600.0,
        ge=0,
        description="random-walk intensity of the bias [um^2/s]; default (5 um)^2 per hour, the "
        "order of the speed-only residual's increments on the real record",
    )
    drift_q_um2_per_s3: float = Field(
        0.0,
        ge=0,
        description="random-walk intensity of a drift rate [um^2/s^3]; 0 = no drift state",
    )
    model_sd_um: float = Field(
        0.0, ge=0, description="the model's fast misses, counted as measurement noise [um]"
    )
    gate_sigma: float = Field(5.0, gt=0, description="innovations beyond this many sd are rejected")
    initial_bias_sd_um: float = Field(
        30.0, gt=0, description="prior spread of the bias before the first measurement [um]"
    )
    reaccept_after: int = Field(
        2,
        ge=0,
        description="consecutive rejected measurements that agree restart the bias (0 = never)",
    )
    max_correction_um: float | None = Field(
        None,
        gt=0,
        le=CORRECTION_LIMIT_UM,
        description="the largest |correction| (estimate minus the model's free run) measurements "
        "may build [um]; None: unbounded here, derived from the model where a model is fused "
        "(compensator.fusion.default_max_correction_um)",
    )
    max_source_move_um: float | None = Field(
        None,
        gt=0,
        le=CORRECTION_LIMIT_UM,
        description="the most one source may move the correction, net, per source_window_s "
        "[um]; None: half of max_correction_um",
    )
    source_window_s: float | None = Field(
        None,
        gt=0,
        le=365 * 86400.0,
        description="the window of max_source_move_um [s]; None: one hour",
    )

    @model_serializer(mode="wrap")
    def _as_stored(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        # the bounds only where set: a fit record written before them dumps as it was read, so
        # the checksum of its model file stays the same
        out: dict[str, Any] = handler(self)
        for key in BOUND_KEYS:
            if key not in self.model_fields_set and out.get(key) is None:
                out.pop(key, None)
        return out

    @property
    def source_move_um(self) -> float | None:
        """The net move one source may make per window [um]; None: unbounded."""
        if self.max_source_move_um is not None:
            return self.max_source_move_um
        return None if self.max_correction_um is None else self.max_correction_um / 2.0

    @property
    def window_s(self) -> float:
        """The window of :attr:`source_move_um` [s]."""
        return DEFAULT_WINDOW_S if self.source_window_s is None else self.source_window_s

    def noise_var_um2(self, sigma_um: float) -> float:
        """Variance of one measurement's error as the filter sees it [um^2]."""
        return sigma_um * sigma_um + self.model_sd_um**2


@dataclass(frozen=True)
class ObserverState:
    """Disturbance estimate (bias [um], drift rate [um/s]), its covariance, the implied
    biases of the rejected measurements since the last accepted one, each source's net move
    of the bias that has not drained yet [um] (sources with none left out), and each source's
    share of the drift rate, what its measurements changed of it [um/s] (a drift rate no
    source taught, e.g. restored from a state saved without shares, is nobody's)."""

    bias_um: float
    drift_um_per_s: float
    cov: tuple[tuple[float, float], tuple[float, float]]
    pending_um: tuple[float, ...] = ()
    moved_um: tuple[tuple[str, float], ...] = ()
    drift_by_um_per_s: tuple[tuple[str, float], ...] = ()

    @classmethod
    def prior(cls, cfg: ObserverConfig) -> ObserverState:
        v = cfg.initial_bias_sd_um**2
        return cls(
            0.0, 0.0, ((v, 0.0), (0.0, 0.0 if cfg.drift_q_um2_per_s3 == 0 else v / 3600.0**2))
        )

    @property
    def bias_sd_um(self) -> float:
        return math.sqrt(max(self.cov[0][0], 0.0))

    def moved_by(self, source: str) -> float:
        """The net move of the bias ``source`` made that has not drained yet [um]."""
        return dict(self.moved_um).get(source, 0.0)

    def drift_of(self, source: str) -> float:
        """``source``'s share of the drift rate [um/s]."""
        return dict(self.drift_by_um_per_s).get(source, 0.0)


def at_bound(cfg: ObserverConfig, bias_um: float) -> bool:
    """The correction is at (or beyond) ``max_correction_um``: measurements move it no further
    out."""
    b = cfg.max_correction_um
    return b is not None and abs(bias_um) >= b * (1.0 - 1e-9)


def _drained(
    cfg: ObserverConfig, moved: tuple[tuple[str, float], ...], dt: float
) -> tuple[tuple[str, float], ...]:
    """Each source's net move, drained toward zero over ``dt`` seconds."""
    limit = cfg.source_move_um
    if not moved or limit is None or dt <= 0:
        return moved
    d = limit / cfg.window_s * dt
    return tuple((k, math.copysign(abs(m) - d, m)) for k, m in moved if abs(m) > d)


def _cov(p: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
    p = np.minimum(p, COV_LIMIT)
    return ((float(p[0, 0]), float(p[0, 1])), (float(p[1, 0]), float(p[1, 1])))


def time_update(cfg: ObserverConfig, z: ObserverState, dt_s: float) -> ObserverState:
    """The exact discretisation over ``dt_s`` of the integrated random walk."""
    dt = require_dt(dt_s)
    p = np.array(z.cov)
    f = np.array([[1.0, dt], [0.0, 1.0]])
    qb, qr = cfg.bias_q_um2_per_s, cfg.drift_q_um2_per_s3
    q = np.array([[qb * dt + qr * dt**3 / 3, qr * dt**2 / 2], [qr * dt**2 / 2, qr * dt]])
    moved = _drained(cfg, z.moved_um, dt)
    step, drift, shares = dt * z.drift_um_per_s, z.drift_um_per_s, z.drift_by_um_per_s
    n = cfg.source_move_um
    if n is not None and shares:
        # the drift each source taught moves the correction on that source's account, as its
        # measurements would: as far as its net move allows, then its share stops
        spent = dict(moved)
        kept: list[tuple[str, float]] = []
        for source, rate in shares:
            want, have = rate * dt, spent.get(source, 0.0)
            cap = max(n - have, 0.0) if want > 0 else min(-n - have, 0.0)
            if abs(want) > abs(cap):
                step += cap - want
                drift -= rate
                want = cap
            else:
                kept.append((source, rate))
            spent[source] = have + want
        moved = tuple((k, m) for k, m in spent.items() if m != 0.0)
        shares = tuple(kept)
    bias = z.bias_um + step
    bound = cfg.max_correction_um
    if bound is not None and abs(bias) > max(bound, abs(z.bias_um)):
        # a drift rate carries the correction no further than measurements may: it stops there
        bias, drift, shares = math.copysign(max(bound, abs(z.bias_um)), bias), 0.0, ()
    return ObserverState(bias, drift, _cov(f @ p @ f.T + q), z.pending_um, moved, shares)


Limit = Literal["bound", "source"]
"""Why a measurement was taken only in part: the correction reached ``max_correction_um``
(``bound``), or its source its ``max_source_move_um`` (``source``)."""


@dataclass(frozen=True)
class Update:
    state: ObserverState
    accepted: bool
    innovation_um: float
    innovation_sd_um: float
    restarted: bool = False
    """The measurement was outside the gate but agreed with the ones rejected before it: the
    bias restarted from them."""
    limited: Limit | None = None
    """The bias moved less than the filter concluded (a bound cut it; see the module)."""
    wanted_bias_um: float | None = None
    """Where the filter would have put the bias, when ``limited``."""

    @property
    def outcome(self) -> str:
        """``limited``, ``restarted``, ``accepted`` or ``rejected``: one word for journals."""
        if self.limited is not None:
            return "limited"
        return "accepted" if self.accepted else "restarted" if self.restarted else "rejected"


def measurement_update(
    cfg: ObserverConfig,
    z: ObserverState,
    measured_um: float,
    predicted_um: float,
    sigma_um: float,
    source: str = "measurement",
    first: bool = False,
) -> Update:
    """Fuse one measurement of the elongation taken now, from ``source``; refused beyond the
    gate, taken only in part beyond the bounds (see the module). ``first``: the observer has
    taken no measurement yet (a start from nothing); the source's move is not cut then, only
    the correction's bound holds (nothing is known yet to protect, and a cold start on a warm
    spindle needs the whole of its first measurement)."""
    up = _filtered(cfg, z, measured_um, predicted_um, sigma_um)
    return _bounded(cfg, z, up, source, first)


def _bounded(cfg: ObserverConfig, z: ObserverState, up: Update, source: str, first: bool) -> Update:
    """``up`` with the bias's move cut to the source's net move and the correction's bound."""
    if not (up.accepted or up.restarted):
        return up
    b0, wanted = z.bias_um, up.state.bias_um
    step = wanted - b0
    why: Limit | None = None
    moved = z.moved_by(source)
    n = cfg.source_move_um
    if n is not None and not first:
        # as far as the source's net move allows, never back the other way
        cap = max(n - moved, 0.0) if step > 0 else min(-n - moved, 0.0)
        if abs(step) > abs(cap):
            step, why = cap, "source"
    bound = cfg.max_correction_um
    if bound is not None:
        lo, hi = min(-bound, b0), max(bound, b0)  # never further out than it already is
        if not lo <= b0 + step <= hi:
            step, why = min(max(b0 + step, lo), hi) - b0, "bound"
    rest = tuple((k, m) for k, m in z.moved_um if k != source)
    left = moved + step
    state_moved = (*rest, (source, left)) if left != 0.0 else rest
    if why is None:
        # what this measurement changed of the drift rate is this source's to answer for
        # (a restart forgets the drift, and every share with it)
        shares: tuple[tuple[str, float], ...] = ()
        if not up.restarted:
            others = tuple((k, r) for k, r in z.drift_by_um_per_s if k != source)
            mine = z.drift_of(source) + up.state.drift_um_per_s - z.drift_um_per_s
            shares = (*others, (source, mine)) if mine != 0.0 else others
        return replace(up, state=replace(up.state, moved_um=state_moved, drift_by_um_per_s=shares))
    # taken in part: the covariance stays as it was (the measurement's information was not
    # taken); refusals a restart was cut from still wait, so that the next agreeing one (from
    # another source, say) restarts again, as far as its own move allows
    pending: tuple[float, ...] = ()
    if up.restarted:
        keep = max(cfg.reaccept_after, 1)
        pending = (*z.pending_um, up.innovation_um + b0)[-keep:]
    kept = ObserverState(
        b0 + step, z.drift_um_per_s, z.cov, pending, state_moved, z.drift_by_um_per_s
    )
    return replace(up, state=kept, limited=why, wanted_bias_um=wanted)


def _filtered(
    cfg: ObserverConfig, z: ObserverState, measured_um: float, predicted_um: float, sigma_um: float
) -> Update:
    """The filter's own update: the gate, a restart, or the Kalman update (the bias unbounded)."""
    y = require_finite("measured_um", measured_um)
    s_model = require_finite("predicted_um", predicted_um)
    sigma = require_finite("sigma_um", sigma_um)
    if not 0 < sigma <= SIGMA_LIMIT_UM:
        raise ModelError(
            f"a measurement's sigma must be > 0 and at most {SIGMA_LIMIT_UM:g} um, got {sigma:g}"
        )
    r = cfg.noise_var_um2(sigma)
    p = np.array(z.cov)
    nu = y - (s_model + z.bias_um)
    s = float(p[0, 0]) + r
    sd = math.sqrt(s)
    if abs(nu) > cfg.gate_sigma * sd:
        pending = (*z.pending_um, y - s_model)[-max(cfg.reaccept_after, 1) :]
        agree = (
            cfg.reaccept_after > 0
            and len(pending) == cfg.reaccept_after
            and max(pending) - min(pending) <= cfg.gate_sigma * math.sqrt(2.0 * r)
        )
        if not agree:
            return Update(replace(z, pending_um=pending), False, nu, sd)
        # a real change: start again from the agreeing measurements, drift forgotten
        n = len(pending)
        p0 = np.array([[r / n, 0.0], [0.0, ObserverState.prior(cfg).cov[1][1]]])
        return Update(
            ObserverState(float(np.mean(pending)), 0.0, _cov(p0), (), z.moved_um),
            False,
            nu,
            sd,
            True,
        )
    k = p[:, 0] / s
    x = np.array([z.bias_um, z.drift_um_per_s]) + k * nu
    i_kh = np.eye(2) - np.outer(k, [1.0, 0.0])  # Joseph form: stays symmetric and positive
    p = i_kh @ p @ i_kh.T + np.outer(k, k) * r
    if not (np.isfinite(x).all() and np.isfinite(p).all()):
        # never a state no spindle can have: the measurement is refused, the state kept
        raise ModelError(f"the measurement {y:g} um (sigma {sigma:g} um) gives no finite estimate")
    return Update(ObserverState(float(x[0]), float(x[1]), _cov(p), (), z.moved_um), True, nu, sd)


@dataclass(frozen=True)
class Fusion:
    fused_um: np.ndarray
    bias_um: np.ndarray
    accepted: int
    rejected: int
    restarts: int = 0


def fuse_series(
    cfg: ObserverConfig,
    time_s: np.ndarray,
    predicted_um: np.ndarray,
    probe_time_s: np.ndarray,
    probe_um: np.ndarray,
    probe_sigma_um: np.ndarray,
) -> Fusion:
    """The fused estimate at every sample of a log: the model's free run plus the bias
    estimated from the probes taken at or before each sample (causal). Probe times must
    increase; a probe between two samples meets the model interpolated to its instant."""
    t = np.asarray(time_s, float)
    s = np.asarray(predicted_um, float)
    pt, py, ps = (np.asarray(a, float) for a in (probe_time_s, probe_um, probe_sigma_um))
    if pt.size and (np.any(np.diff(pt) < 0)):
        raise ModelError("probe times must not go backwards")
    z = ObserverState.prior(cfg)
    t_z = float(t[0])
    bias = np.empty(t.size)
    j, acc, rej, restarts = 0, 0, 0, 0
    for k in range(t.size):
        while j < pt.size and pt[j] <= t[k]:
            z = time_update(cfg, z, max(pt[j] - t_z, 0.0))
            t_z = max(t_z, float(pt[j]))
            up = measurement_update(
                cfg, z, float(py[j]), float(np.interp(pt[j], t, s)), float(ps[j])
            )
            z = up.state
            acc += up.accepted
            rej += not up.accepted
            restarts += up.restarted
            j += 1
        # the mean of the time update; its covariance is not needed between probes
        bias[k] = z.bias_um + max(t[k] - t_z, 0.0) * z.drift_um_per_s
    return Fusion(s + bias, bias, acc, rej, restarts)
