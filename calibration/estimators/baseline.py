"""The exponential baseline: paper 001 eqs. 1-3 in dynamic form, one first-order state whose
time constant is chosen by cross-validation, with S∞ quadratic in n (the state's gains by OLS).
The bar every other candidate must clear. It is a ridge bank with one rung and no penalty
(:func:`.ridge_bank.fit_baseline`), chosen by the lowest held-out error. Pure."""

from __future__ import annotations

import numpy as np

from ..dataset import Dataset
from .ridge_bank import BASELINE_TAUS_S, RidgeFit, fit_baseline

NAME = "exp-baseline"
DESCRIPTION = "paper 001 eqs. 1-3, dynamic: one time constant chosen by CV, S∞ quadratic in n"

__all__ = ["BASELINE_TAUS_S", "DESCRIPTION", "NAME", "fit"]


def fit(ds: Dataset, rows: np.ndarray | None = None, *, nested: bool = False) -> RidgeFit:
    """The baseline fitted on the measured rows of ``rows`` (default: all)."""
    return fit_baseline(ds, rows, nested=nested)
