"""The paper's one-step OLS, ``S_k = a*S_{k-1} + b0 + b1*n + b2*n^2 + b3*n^3`` (paper 001 eqs.
11-12, n in krpm), fitted one step ahead on the measured S[k-1] and scored in free run, for the
comparison only: it is never chosen. It regresses on the previous sample, so it needs the
elongation on every row: it is left out for sparse targets. Pure."""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from compensator.errors import CalibrationError
from compensator.filters import constant_decay, decaying_sum
from compensator.units import SPEED_SCALE_RPM

from .. import folds as fl
from ..candidate import Candidate
from ..checks import as_series, as_times
from ..dataset import Dataset
from ..metrics import fold_scores, pooled_stats

NAME = "paper-ols"


@dataclass(frozen=True)
class PaperFit:
    """``S_k = a*S_{k-1} + b0 + b1*n + b2*n^2 + b3*n^3`` (n in krpm) fitted at period ``dt_s``."""

    a: float
    b_um: tuple[float, float, float, float]
    dt_s: float
    one_step_r2: float

    def predict(self, time_s: Any, speed_rpm: Any, initial_um: float) -> np.ndarray:
        """Free run from ``initial_um`` (its own output fed back). At the fitted period the
        recursion itself; at another Δt its exact zero-order-hold equivalent (0 < a < 1 only)."""
        t = as_times(time_s)
        n = np.abs(as_series("speed_rpm", speed_rpm, t.size)) / SPEED_SCALE_RPM
        b0, b1, b2, b3 = self.b_um
        f = ((b3 * n + b2) * n + b1) * n + b0
        out = np.empty(t.size)
        if t.size == 0:
            return out
        out[0] = initial_um
        dt = np.diff(t)
        with np.errstate(over="ignore", invalid="ignore"):
            if np.allclose(dt, self.dt_s, rtol=1e-9, atol=0):
                out[1:] = constant_decay(self.a, f[1:], initial_um)
                return out
            if not 0 < self.a < 1:
                raise CalibrationError(
                    f"a = {self.a:.6g}: no continuous form to step at another dt"
                )
            lam = -math.log(self.a) / self.dt_s
            gk = -np.expm1(-lam * dt) / (1 - self.a)
            out[1:] = decaying_sum(gk * f[1:], initial_um, ld=lam * dt)
        return out


def fit_paper_ols(
    time_s: Any, speed_rpm: Any, elongation_um: Any, train: np.ndarray | None = None
) -> PaperFit:
    """The paper's eqs. 11-12 by OLS one step ahead on the measured S[k-1]; a row k is used when
    samples k-1 and k are both in ``train`` (default: all)."""
    t = as_times(time_s)
    n = np.abs(as_series("speed_rpm", speed_rpm, t.size)) / SPEED_SCALE_RPM
    s = as_series("elongation_um", elongation_um, t.size)
    use = np.ones(t.size, bool) if train is None else np.asarray(train, bool)
    rows = np.flatnonzero(use[1:] & use[:-1]) + 1
    if rows.size < 6:
        raise CalibrationError("too few rows for the paper's OLS")
    nk = n[rows]
    x = np.column_stack([s[rows - 1], np.ones_like(nk), nk, nk**2, nk**3])
    coef, *_ = np.linalg.lstsq(x, s[rows], rcond=None)
    r = s[rows] - x @ coef
    r2 = 1 - float(r @ r) / float(np.sum((s[rows] - s[rows].mean()) ** 2))
    dt = float(np.median(np.diff(t)[rows - 1]))
    return PaperFit(float(coef[0]), tuple(float(v) for v in coef[1:]), dt, r2)  # type: ignore[arg-type]


def fit(ds: Dataset, rows: np.ndarray | None = None) -> PaperFit:
    """The paper's OLS on ``rows`` (default: all); no regression row pairs the end of one
    segment with the start of the next."""
    use = np.ones(ds.time_s.size, bool) if rows is None else np.array(rows, dtype=bool)
    use[[a for a, _ in ds.segments[1:]]] = False
    return fit_paper_ols(ds.time_s, ds.speed_rpm, ds.elongation_um, use)


def free_run(model: PaperFit, ds: Dataset) -> np.ndarray:
    """Each segment from its first measured elongation, its own output fed back."""
    out = np.empty(ds.time_s.size)
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        for a, b in ds.segments:
            out[a:b] = model.predict(ds.time_s[a:b], ds.speed_rpm[a:b], float(ds.elongation_um[a]))
    return out


def paper_ols_cv(
    time_s: Any,
    speed_rpm: Any,
    elongation_um: Any,
    cycles: Sequence[tuple[int, int]],
    restart: bool = False,
) -> dict[str, Any]:
    """Leave-one-cycle-out free run of the paper's OLS over one log. The free run starts from the
    log's first measured elongation and runs over the whole log; with ``restart`` it starts again
    from the held-out cycle's first measured value (the most favourable reading of the paper)."""
    t = as_times(time_s)
    y = as_series("elongation_um", elongation_um, t.size)
    res = np.empty(t.size)
    fits = []
    for a, b in cycles:
        f = fit_paper_ols(t, speed_rpm, y, fl.without(t.size, (a, b)))
        fits.append(f)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if restart:
                pred = f.predict(t[a:b], np.asarray(speed_rpm, float)[a:b], float(y[a]))
            else:
                pred = f.predict(t, speed_rpm, float(y[0]))[a:b]
        res[a:b] = y[a:b] - pred
    rms, mx = pooled_stats(res)
    return {
        "folds": fold_scores(res, cycles),
        "cv_rms_um": rms,
        "cv_max_abs_um": mx,
        "a": [f.a for f in fits],
        "one_step_r2": [f.one_step_r2 for f in fits],
    }


def candidate(ds: Dataset, ctx: Mapping[str, Any]) -> tuple[Candidate, Any]:
    """The paper's OLS refitted without each fold and free-run over every segment; scored on the
    held-out fold, for the comparison."""
    cpu0 = time.process_time()
    c = Candidate(
        NAME,
        "reference",
        "paper 001 eqs. 11-12: OLS one step ahead on the measured "
        "S[k-1], scored in free run (for comparison; never chosen)",
    )
    res = np.empty(ds.time_s.size)
    per_fold = []
    try:
        for a, b in ds.folds:
            f = fit(ds, fl.without(ds.time_s.size, (a, b)))
            per_fold.append(f.a)
            res[a:b] = (ds.elongation_um - free_run(f, ds))[a:b]
        splits = fl.forward_of(ds.time_s, ds.speed_rpm, ds.folds, ds.unit == "cycle", ds.measured)
        ahead = np.full(ds.time_s.size, np.nan)
        for past, (a, b) in splits:
            ahead[a:b] = (
                ds.elongation_um - free_run(fit(ds, fl.rows_of(ds.time_s.size, past)), ds)
            )[a:b]
        full = fit(ds)
    except CalibrationError as err:
        c.refusals.append(str(err))
        return c, None
    c.cv_rms_um, c.cv_max_abs_um = pooled_stats(res)
    c.folds_rms_um = [f.rms_um for f in fold_scores(res, ds.folds)]
    if splits:
        c.forward_rms_um, c.forward_max_abs_um = pooled_stats(
            ahead, fl.rows_of(ahead.size, [f for _, f in splits])
        )
        c.forward_folds_rms_um = [f.rms_um for f in fold_scores(ahead, [f for _, f in splits])]
        c.forward_residual_um = ahead
    c.in_sample_rms_um, c.in_sample_max_abs_um = pooled_stats(ds.elongation_um - free_run(full, ds))
    c.details = {"a": full.a, "one_step_r2": full.one_step_r2, "a_per_fold": per_fold}
    if full.a >= 1:
        c.notes.append(f"pole a = {full.a:.6f} >= 1: its free run diverges")
    c.fit_cpu_s = time.process_time() - cpu0
    return c, full
