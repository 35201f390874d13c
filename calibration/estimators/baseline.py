"""The exponential baseline: paper 001 eqs. 1-3 in dynamic form, one first-order state whose
time constant is chosen by cross-validation, with S∞ quadratic in n (the state's gains by OLS).
The bar every other candidate must clear. It is a ridge bank with one rung and no penalty
(:func:`.ridge_bank.fit_baseline`), chosen by the lowest held-out error. Pure."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from .. import folds as fl
from ..dataset import Dataset
from ..metrics import fold_scores, measured_stats
from .ridge_bank import BASELINE_TAUS_S, FilterBank, RidgeFit, fit_baseline, speed_terms

NAME = "exp-baseline"
DESCRIPTION = "paper 001 eqs. 1-3, dynamic: one time constant chosen by CV, S∞ quadratic in n"

__all__ = [
    "BASELINE_TAUS_S",
    "DESCRIPTION",
    "MONOTONE_DESCRIPTION",
    "MONOTONE_NAME",
    "NAME",
    "fit",
    "fit_monotone",
]


def fit(ds: Dataset, rows: np.ndarray | None = None, *, nested: bool = False) -> RidgeFit:
    """The baseline fitted on the measured rows of ``rows`` (default: all)."""
    return fit_baseline(ds, rows, nested=nested)


MONOTONE_NAME = "monotone-baseline"
MONOTONE_DESCRIPTION = (
    "one first-order state with its steady growth held to rise with speed in the measured "
    "direction (gains on n and n² of that sign, least squares; the time constant of the "
    "baseline's grid with the lowest held-out error that passes the physics check): the most "
    "conservative speed-only model"
)


def fit_monotone(
    ds: Dataset, base: RidgeFit, direction: int, splits: Sequence[fl.Split] = ()
) -> RidgeFit:
    """``base`` (a fitted baseline: one time constant) refitted with both gains of the sign of
    ``direction`` (non-negative least squares on the measured rows), so that its steady growth
    rises with speed whatever the data: the stand-in when every speed-only candidate fails the
    physics check. Its held-out residual is leave-one-fold-out on ``ds.folds`` and, on
    ``splits``, forward."""
    d = 1.0 if direction >= 0 else -1.0
    x = FilterBank(ds.time_s, speed_terms(ds.speed_rpm), ds.segments).design(base.grid, ())
    y = np.where(ds.measured, ds.elongation_um, 0.0)

    def solve(rows: np.ndarray) -> tuple[np.ndarray, float]:
        mx, my = x[rows].mean(axis=0), float(y[rows].mean())
        from scipy.optimize import nnls  # 1.5 s to import: only where it solves

        beta, _ = nnls(d * (x[rows] - mx), y[rows] - my)
        gains = d * beta
        return gains, my - float(mx @ gains)

    def predict(rows: np.ndarray) -> np.ndarray:
        g, c = solve(rows)
        return y - (c + x @ g)

    held = np.full(y.size, np.nan)
    for a, b in ds.folds:
        tr = fl.without(y.size, (a, b), ds.measured)
        if tr.sum() >= 2:
            held[a:b] = predict(tr)[a:b]
    held[~ds.measured] = np.nan
    ahead = np.full(y.size, np.nan) if splits else None
    for past, (a, b) in splits:
        tr = fl.rows_of(y.size, past, ds.measured)
        if tr.sum() >= 2 and ahead is not None:
            ahead[a:b] = predict(tr)[a:b]
    if ahead is not None:
        ahead[~ds.measured] = np.nan
    gains, intercept = solve(ds.measured)
    cv_rms, cv_max = measured_stats(held)
    fwd = measured_stats(ahead) if ahead is not None else (None, None)
    return replace(
        base,
        speed_gains_um=gains.reshape(2, 1),
        intercept_um=intercept,
        alpha=0.0,
        folds=fold_scores(held, ds.folds),
        cv_rms_um=cv_rms,
        cv_max_abs_um=cv_max,
        nested_folds=None,
        nested_rms_um=None,
        nested_max_abs_um=None,
        held_out_residual_um=held,
        forward_folds=fold_scores(ahead, [f for _, f in splits]) if ahead is not None else None,
        forward_rms_um=fwd[0],
        forward_max_abs_um=fwd[1],
        forward_residual_um=ahead,
        forward_rms_by_alpha_um=(),
        refusals=(),
        notes=(),
        accepted=True,
    )
