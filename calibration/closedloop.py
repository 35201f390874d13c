"""Planning the closed loop: the observer's noise fitted from calibration residuals, and the
probe interval judged by cross-validation on cycles.

The input is the chosen model's held-out free-run residual r = y - S on every cycle (each cycle
predicted by a model fitted without it; :mod:`calibration.identify`). Fusing probes with a model
only moves the estimate by the bias the observer infers from ``r`` at the probe instants, so the
closed loop on a cycle can be simulated from ``r`` alone.

The noise model (``docs/PROBING.md``): between two instants ``lag`` apart, the residual changes
with variance ``q_b * lag + 2 * model_sd^2`` (a random walk the bias can follow, plus fast misses
minutes long that it cannot): a non-negative least-squares fit to the residual's variogram at
lags of 5 min to 2 h (Cressie, *Statistics for Spatial Data*, 1993, sec. 2.4). A drift-rate
variant adds ``q_r * lag^3 / 3``. Which variant is kept is decided by the closed loop's own
error on held-out cycles, each cycle's noise fitted without it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from compensator.filters import decay
from compensator.observer import ObserverConfig, fuse_series

INTERVALS_S = (900.0, 1800.0, 3600.0, 7200.0)
"""Probe intervals of the planning table [s]."""
LAGS_S = (300.0, 600.0, 900.0, 1200.0, 1800.0, 2700.0, 3600.0, 5400.0, 7200.0)
PROBE_SIGMA_UM = 0.5
"""The default probe's sigma (a contact or laser tool setter) [um]."""
SEEDS = (0, 1, 2)
"""Noise draws per cycle and interval; the figures are their mean."""
DRIFT_GAIN = 0.10
"""A drift state is kept only if it cuts the held-out closed-loop RMS by this fraction."""
DEFAULT_TARGET_UM = 2.0
"""The RMS a recommended interval must meet unless the user gives another [um]."""


def anchored(
    time_s: np.ndarray,
    residual_um: np.ndarray,
    cycles: Sequence[tuple[int, int]],
    slowest_tau_s: float,
) -> list[np.ndarray]:
    """Each cycle's residual as replay would see it on a fresh log: the model starts at the
    first measured value, its start error decaying with the slowest time constant."""
    out = []
    for a, b in cycles:
        r = np.asarray(residual_um[a:b], float)
        out.append(r - r[0] * decay(time_s[a:b], slowest_tau_s))
    return out


def variogram(
    time_s: np.ndarray,
    residual_um: np.ndarray,
    cycles: Sequence[tuple[int, int]],
    lags_s: Sequence[float] = LAGS_S,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean squared change of the residual over each lag, pooled within ``cycles`` (lags with
    no pair are left out): (lags [s], E[(r(t+lag)-r(t))^2] [um^2])."""
    lags, values = [], []
    for lag in lags_s:
        sq, n = 0.0, 0
        for a, b in cycles:
            t, r = time_s[a:b], residual_um[a:b]
            j = np.searchsorted(t, t + lag)
            ok = j < t.size
            if ok.any():
                d = r[j[ok]] - r[ok]
                sq += float(np.sum(d * d))
                n += int(ok.sum())
        if n:
            lags.append(lag)
            values.append(sq / n)
    return np.array(lags), np.array(values)


def _nnls_variogram(
    time_s: np.ndarray, residual_um: np.ndarray, cycles: Sequence[tuple[int, int]], drift: bool
) -> np.ndarray | None:
    """(q_b, model_sd^2[, q_r]) fitted to the variogram pooled over ``cycles``; None if too short."""
    lags, v = variogram(time_s, residual_um, cycles)
    if lags.size < 2:
        return None
    cols = [lags, 2.0 * np.ones_like(lags)] + ([lags**3 / 3.0] if drift else [])
    a = np.column_stack(cols)
    scale = np.abs(a).max(axis=0)
    from scipy.optimize import (
        nnls,
    )  # scipy.optimize costs 1.5 s to import: only where a plan is made

    coef, _ = nnls(a / scale, v)
    return coef / scale


def fit_noise(
    time_s: np.ndarray,
    residual_um: np.ndarray,
    cycles: Sequence[tuple[int, int]],
    drift: bool = False,
) -> ObserverConfig:
    """The observer's noise from the residual's variogram (non-negative least squares).

    The bias intensity is the largest of the cycles' own (each cycle's variogram alone): a
    new operating point misses more than the pooled cycles suggest, and a filter that trusts
    its model too much lags far behind a real change while one that trusts the probes too much
    only loses a little of their averaging (on the real record, ch1 trained on two cycles:
    1800-s RMS 5.4 um with the pooled figure, 3.3 um with the largest)."""
    coef = _nnls_variogram(time_s, residual_um, cycles, drift)
    if coef is None:
        return ObserverConfig()
    qb, sd2 = float(coef[0]), float(coef[1])
    qr = float(coef[2]) if drift else 0.0
    for c in cycles:
        own = _nnls_variogram(time_s, residual_um, [c], False)
        if own is not None:
            qb = max(qb, float(own[0]))
    qb = max(qb, 1e-6 / 3600.0)  # never a frozen bias: (1 nm)^2 per hour at the least
    # the prior covers what the open loop missed on these cycles
    prior = max(10.0, 2.0 * float(np.max(np.abs(residual_um[cycles[0][0] : cycles[-1][1]]))))
    return ObserverConfig(
        bias_q_um2_per_s=qb,
        drift_q_um2_per_s3=qr,
        model_sd_um=math.sqrt(sd2),
        initial_bias_sd_um=min(prior, 1e3),
    )


def probe_rows(time_s: np.ndarray, every_s: float) -> np.ndarray:
    """Rows of the first samples at or after ``t0 + k * every_s``, k = 1, 2, ... (the probe
    instants of ``replay --probe-every`` and of the planning table)."""
    t = np.asarray(time_s, float)
    want = t[0] + every_s * np.arange(1, int((t[-1] - t[0]) // every_s) + 1)
    idx = np.unique(np.searchsorted(t, want))
    return idx[idx < t.size]


def closed_loop_error(
    cfg: ObserverConfig,
    time_s: np.ndarray,
    residual_um: np.ndarray,
    every_s: float,
    seed: int,
    sigma_um: float = PROBE_SIGMA_UM,
) -> tuple[np.ndarray, int]:
    """The fused estimate's error on one cycle with a probe every ``every_s`` from its start
    (as ``replay --probe-every``), and the number of probes rejected."""
    t = np.asarray(time_s, float)
    idx = probe_rows(t, every_s)
    rng = np.random.default_rng(seed)
    # the model predicts y - r and a probe reads y + noise: the observer sees r + noise, and
    # the fused estimate's error is its bias minus r
    probe = residual_um[idx] + rng.normal(0.0, sigma_um, idx.size)
    f = fuse_series(cfg, t, np.zeros(t.size), t[idx], probe, np.full(idx.size, sigma_um))
    return f.bias_um - residual_um, f.rejected


@dataclass
class Plan:
    """The observer chosen and the interval table, for the fit report and the model."""

    observer: ObserverConfig
    variant: str
    reason: str
    table: list[dict[str, Any]] = field(default_factory=list)
    variants: list[dict[str, Any]] = field(default_factory=list)
    target_um: float = DEFAULT_TARGET_UM
    recommended_s: float | None = None

    def rms_at(self, every_s: float) -> float:
        """The table's RMS for a probe every ``every_s`` (one of the intervals planned)."""
        for row in self.table[1:]:
            if row["interval_s"] == every_s:
                return float(row["rms_um"])
        raise KeyError(f"no closed-loop figure planned for {every_s:g} s")

    def report(self) -> dict[str, Any]:
        return {
            "observer": self.observer.model_dump(),
            "variant": self.variant,
            "reason": self.reason,
            "probe_sigma_um": PROBE_SIGMA_UM,
            "target_rms_um": self.target_um,
            "recommended_interval_s": self.recommended_s,
            "intervals": self.table,
            "variants": self.variants,
        }

    def lines(self) -> list[str]:
        out = [
            f"closed loop (probe sigma {PROBE_SIGMA_UM:g} um): {self.reason}",
            "  probe every      RMS um   max um   rejected",
        ]
        for row in self.table:
            name = "never" if row["interval_s"] is None else f"{row['interval_s']:.0f} s"
            rej = "" if row["rejected"] is None else f"{row['rejected']:.1f}"
            out.append(f"  {name:>11} {row['rms_um']:9.2f} {row['max_abs_um']:8.2f}   {rej}")
        if self.recommended_s is not None:
            out.append(
                f"  recommended: a probe every {self.recommended_s:.0f} s, the longest interval "
                f"whose RMS meets {self.target_um:g} um"
            )
        else:
            out.append(
                f"  no interval tried meets {self.target_um:g} um RMS: probe more often than "
                f"{min(r['interval_s'] for r in self.table[1:]):.0f} s, or add inputs to the model"
            )
        return out


def _scores(
    cfgs: Sequence[ObserverConfig],
    time_s: np.ndarray,
    pieces: Sequence[np.ndarray],
    starts: Sequence[int],
    every_s: float,
) -> tuple[float, float, float]:
    """Pooled RMS, mean per-cycle max |error| and mean rejections per cycle, over cycles and
    seeds; ``cfgs[i]`` serves cycle ``i``."""
    sq, n, mx, rej = 0.0, 0, [], 0
    for cfg, r, a in zip(cfgs, pieces, starts):
        t = time_s[a : a + r.size]
        for seed in SEEDS:
            e, k = closed_loop_error(cfg, t, r, every_s, seed)
            sq += float(np.sum(e * e))
            n += e.size
            mx.append(float(np.max(np.abs(e))))
            rej += k
    return math.sqrt(sq / n), float(np.mean(mx)), rej / (len(pieces) * len(SEEDS))


def _table(
    pieces: Sequence[np.ndarray],
    intervals_s: Sequence[float],
    scores: Sequence[tuple[float, float, float]],
    target_um: float,
) -> tuple[list[dict[str, Any]], float | None]:
    """The interval table (open loop first) and the longest interval meeting ``target_um``."""
    joined = np.concatenate(pieces)
    table: list[dict[str, Any]] = [
        {
            "interval_s": None,
            "rms_um": float(np.sqrt(np.mean(joined**2))),
            "max_abs_um": float(np.mean([np.max(np.abs(p)) for p in pieces])),
            "rejected": None,
        }
    ]
    table += [
        {"interval_s": e, "rms_um": sc[0], "max_abs_um": sc[1], "rejected": sc[2]}
        for e, sc in zip(intervals_s, scores)
    ]
    ok = [row["interval_s"] for row in table[1:] if row["rms_um"] <= target_um]
    return table, (max(ok) if ok else None)


def plan(
    time_s: Any,
    residual_um: Any,
    cycles: Sequence[tuple[int, int]],
    slowest_tau_s: float,
    target_um: float = DEFAULT_TARGET_UM,
    intervals_s: Sequence[float] = INTERVALS_S,
) -> Plan:
    """Fit the observer's noise, choose the variant by held-out cycles, and tabulate interval →
    expected RMS and max (the mean over cycles of each cycle's max)."""
    t = np.asarray(time_s, float)
    r = np.asarray(residual_um, float)
    pieces = anchored(t, r, cycles, slowest_tau_s)
    starts = [a for a, _ in cycles]
    joined = np.concatenate(pieces)
    variants = {"bias": False, "bias+drift": True}
    rows, best = [], None
    for name, drift in variants.items():
        # each cycle's observer is fitted without that cycle
        per = []
        for i in range(len(cycles)):
            rest = [c for j, c in enumerate(cycles) if j != i] or list(cycles)
            per.append(fit_noise(t, joined, rest, drift))
        scores = [_scores(per, t, pieces, starts, every) for every in intervals_s]
        mean_rms = float(np.mean([s[0] for s in scores]))
        rows.append(
            {
                "variant": name,
                "mean_rms_um": mean_rms,
                "rms_um": {f"{e:.0f}": s[0] for e, s in zip(intervals_s, scores)},
            }
        )
        # a drift state extrapolates: only when clearly better, on enough cycles to tell
        if best is None or (mean_rms < best[1] * (1 - DRIFT_GAIN) and len(cycles) >= 4):
            best = (name, mean_rms, per, scores)
    assert best is not None
    name, mean_rms, per, scores = best
    cfg = fit_noise(t, joined, cycles, variants[name])
    never = [float(np.sqrt(np.mean(p * p))) for p in pieces]
    table, recommended = _table(pieces, intervals_s, scores, target_um)
    other = [row for row in rows if row["variant"] != name]
    reason = (
        f"{name} observer (bias random walk {math.sqrt(cfg.bias_q_um2_per_s * 3600):.2f} um/sqrt(h), "
        f"model sd {cfg.model_sd_um:.2f} um"
        + (
            f", drift {math.sqrt(cfg.drift_q_um2_per_s3) * 3600**1.5:.2g} um/h/sqrt(h)"
            if cfg.drift_q_um2_per_s3 > 0
            else ""
        )
        + f") has mean RMS {mean_rms:.2f} um over the intervals"
        + "".join(f"; {o['variant']} {o['mean_rms_um']:.2f} um" for o in other)
        + f"; open loop {np.mean(never):.2f} um"
    )
    return Plan(cfg, name, reason, table, rows, target_um, recommended)


def plan_on_run(
    fit_time_s: Any,
    fit_residual_um: Any,
    time_s: Any,
    residual_um: Any,
    slowest_tau_s: float,
    target_um: float = DEFAULT_TARGET_UM,
    intervals_s: Sequence[float] = INTERVALS_S,
) -> Plan:
    """The wizard's plan: the observer's noise from the calibration run's residual, the table on
    a validation run the fit never saw (one held-out run; no variant choice)."""
    tf, rf = np.asarray(fit_time_s, float), np.asarray(fit_residual_um, float)
    t, r = np.asarray(time_s, float), np.asarray(residual_um, float)
    cfg = fit_noise(tf, anchored(tf, rf, [(0, tf.size)], slowest_tau_s)[0], [(0, tf.size)])
    (piece,) = anchored(t, r, [(0, t.size)], slowest_tau_s)
    scores = [_scores([cfg], t, [piece], [0], every) for every in intervals_s]
    table, recommended = _table([piece], intervals_s, scores, target_um)
    reason = (
        f"bias observer fitted on the calibration run (random walk "
        f"{math.sqrt(cfg.bias_q_um2_per_s * 3600):.2f} um/sqrt(h), model sd {cfg.model_sd_um:.2f} um), "
        "scored on the validation run"
    )
    return Plan(cfg, "bias", reason, table, [], target_um, recommended)
