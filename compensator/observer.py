"""Fusing occasional tool-setter or probe measurements with a model: a Kalman filter on
disturbance states. Pure: numpy only, no I/O.

The model's free-run prediction S(t) misses what it does not see (coolant, ambient, load,
wear). The observer estimates that miss as a disturbance d(t) = b(t) added to the prediction,
with b a random walk plus, optionally, a drift rate r (an integrated random walk)::

    b' = r + w_b,   r' = w_r,     E[w_b^2] = q_b [um^2/s],  E[w_r^2] = q_r [um^2/s^3]
    y  = S + b + v,               E[v^2] = sigma^2 (the stated sigma of the measurement)

The time update is the exact discretisation over the real Δt (F = [[1, Δt], [0, 1]], Q from the
continuous noise); the measurement update is exact at any time. An innovation beyond ``gate``
standard deviations is rejected (the caller raises ``PROBE_REJECTED``). The fused estimate is
S + b at every sample, using only the measurements taken up to that sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import ModelError
from .units import require_dt, require_finite


@dataclass(frozen=True)
class ObserverConfig:
    """Noise levels of the disturbance model and the outlier gate."""

    bias_q_um2_per_s: float = 25.0 / 3600.0
    """Random-walk intensity of the bias: (5 um)^2 per hour, the order of the speed-only model's
    free-run residual increments on the real record (21-36 um^2/h at 15 min to 1 h lags, ch3).
    Too small a value makes the gate refuse the real changes and the filter diverge."""
    drift_q_um2_per_s3: float = 0.0
    """Random-walk intensity of the drift rate [um^2/s^3]; 0 (default) = no drift state: on the
    real record a drift state did not help (in-sample, ch3, probes every 15 min to 2 h)."""
    gate_sigma: float = 5.0
    """Innovations beyond this many standard deviations are rejected."""
    initial_bias_sd_um: float = 10.0
    """Prior spread of the bias before the first measurement."""

    def __post_init__(self) -> None:
        for name in ("bias_q_um2_per_s", "drift_q_um2_per_s3", "gate_sigma", "initial_bias_sd_um"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ModelError(f"observer {name} must be finite and >= 0, got {v}")
        if self.gate_sigma <= 0:
            raise ModelError("observer gate_sigma must be > 0")


@dataclass(frozen=True)
class ObserverState:
    """Disturbance estimate (bias [um], drift rate [um/s]) and its covariance."""

    bias_um: float
    drift_um_per_s: float
    cov: tuple[tuple[float, float], tuple[float, float]]

    @classmethod
    def prior(cls, cfg: ObserverConfig) -> ObserverState:
        v = cfg.initial_bias_sd_um ** 2
        return cls(0.0, 0.0, ((v, 0.0), (0.0, 0.0 if cfg.drift_q_um2_per_s3 == 0 else v / 3600.0**2)))


def time_update(cfg: ObserverConfig, z: ObserverState, dt_s: float) -> ObserverState:
    """The exact discretisation over ``dt_s`` of the integrated random walk."""
    dt = require_dt(dt_s)
    p = np.array(z.cov)
    f = np.array([[1.0, dt], [0.0, 1.0]])
    qb, qr = cfg.bias_q_um2_per_s, cfg.drift_q_um2_per_s3
    q = np.array([[qb * dt + qr * dt**3 / 3, qr * dt**2 / 2], [qr * dt**2 / 2, qr * dt]])
    p = f @ p @ f.T + q
    p = np.minimum(p, 1e12)  # a gap of years: the prior is forgotten, the numbers stay finite
    return ObserverState(z.bias_um + dt * z.drift_um_per_s, z.drift_um_per_s,
                         ((float(p[0, 0]), float(p[0, 1])), (float(p[1, 0]), float(p[1, 1]))))


@dataclass(frozen=True)
class Update:
    state: ObserverState
    accepted: bool
    innovation_um: float
    innovation_sd_um: float


def measurement_update(cfg: ObserverConfig, z: ObserverState, measured_um: float,
                       predicted_um: float, sigma_um: float) -> Update:
    """Fuse one measurement of the elongation taken now; refused beyond the gate."""
    y = require_finite("measured_um", measured_um)
    s_model = require_finite("predicted_um", predicted_um)
    sigma = require_finite("sigma_um", sigma_um)
    if sigma <= 0:
        raise ModelError(f"a measurement's sigma must be > 0, got {sigma}")
    p = np.array(z.cov)
    nu = y - (s_model + z.bias_um)
    s = float(p[0, 0]) + sigma * sigma
    sd = math.sqrt(s)
    if abs(nu) > cfg.gate_sigma * sd:
        return Update(z, False, nu, sd)
    k = p[:, 0] / s
    x = np.array([z.bias_um, z.drift_um_per_s]) + k * nu
    # Joseph form: stays symmetric and positive
    i_kh = np.eye(2) - np.outer(k, [1.0, 0.0])
    p = i_kh @ p @ i_kh.T + np.outer(k, k) * sigma * sigma
    return Update(ObserverState(float(x[0]), float(x[1]),
                                ((float(p[0, 0]), float(p[0, 1])), (float(p[1, 0]), float(p[1, 1])))),
                  True, nu, sd)


@dataclass(frozen=True)
class Fusion:
    fused_um: np.ndarray
    bias_um: np.ndarray
    accepted: int
    rejected: int


def fuse_series(cfg: ObserverConfig, time_s: np.ndarray, predicted_um: np.ndarray,
                probe_time_s: np.ndarray, probe_um: np.ndarray, probe_sigma_um: np.ndarray) -> Fusion:
    """The fused estimate at every sample of a log: the model's free run plus the bias
    estimated from the probes taken at or before each sample (causal). Probe times must lie in
    the log's span and increase."""
    t = np.asarray(time_s, float)
    s = np.asarray(predicted_um, float)
    pt, py, ps = (np.asarray(a, float) for a in (probe_time_s, probe_um, probe_sigma_um))
    if pt.size and (np.any(np.diff(pt) < 0)):
        raise ModelError("probe times must not go backwards")
    z = ObserverState.prior(cfg)
    t_z = float(t[0])
    bias = np.empty(t.size)
    j, acc, rej = 0, 0, 0
    for k in range(t.size):
        while j < pt.size and pt[j] <= t[k]:
            z = time_update(cfg, z, max(pt[j] - t_z, 0.0))
            t_z = max(t_z, float(pt[j]))
            # the model at the probe's instant: interpolated between samples
            s_at = float(np.interp(pt[j], t, s))
            up = measurement_update(cfg, z, float(py[j]), s_at, float(ps[j]))
            z = up.state
            acc += up.accepted
            rej += not up.accepted
            j += 1
        # the mean of the time update; its covariance is not needed between probes
        bias[k] = z.bias_um + max(t[k] - t_z, 0.0) * z.drift_um_per_s
    return Fusion(s + bias, bias, acc, rej)
