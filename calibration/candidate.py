"""One candidate of the identification and how it scored: the type every estimator's
``candidate`` returns and the choice (:mod:`calibration.identify`) reads. Pure."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# a forward figure from one predicted fold is too noisy to decide by (on the real record it
# swapped a better speed-only candidate for a worse one); the error statement uses the same
from compensator.expected import MIN_FORWARD_FOLDS


@dataclass
class Candidate:
    """One candidate and how it scored. ``honest_rms_um`` decides (nested when available)."""

    name: str
    family: str  # "speed", "inputs" or "reference"
    description: str
    cv_rms_um: float = math.inf
    cv_max_abs_um: float = math.inf
    nested_rms_um: float | None = None
    nested_max_abs_um: float | None = None
    folds_rms_um: list[float] = field(default_factory=list)
    in_sample_rms_um: float | None = None
    in_sample_max_abs_um: float | None = None
    accepted: bool = False
    refusals: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    model: Any = None
    details: dict[str, Any] = field(default_factory=dict)
    fit_cpu_s: float = 0.0
    held_out_residual_um: np.ndarray | None = None
    slowest_tau_s: float = 0.0
    forward_rms_um: float | None = None
    forward_max_abs_um: float | None = None
    forward_folds_rms_um: list[float] = field(default_factory=list)
    forward_residual_um: np.ndarray | None = None
    forward_clipped_residual_um: np.ndarray | None = None
    """The forward residual with the inputs held to the range their past saw."""
    forward_distance: np.ndarray | None = None
    """How far the inputs of each row predicted forward lay outside the range their past saw."""
    forward_decides: bool = True
    """False when the folds are blocks of one cycle: each block of a calibration program holds
    other speeds, so "forward" there is extrapolation in speed, which the error statement and the
    extrapolation policy judge, not the choice."""

    @property
    def honest_rms_um(self) -> float:
        """Leave-one-fold-out: nested when available."""
        return self.nested_rms_um if self.nested_rms_um is not None else self.cv_rms_um

    @property
    def decisive_rms_um(self) -> float:
        """What the choice reads: the worse of the honest backward figure and the forward one
        (rolling origin), so that a candidate must hold on the future too; the backward one
        alone while fewer than :data:`MIN_FORWARD_FOLDS` folds were predicted forward, or when
        the forward figure does not decide (``forward_decides``)."""
        if (
            self.forward_rms_um is None
            or not self.forward_decides
            or len(self.forward_folds_rms_um) < MIN_FORWARD_FOLDS
        ):
            return self.honest_rms_um
        return max(self.honest_rms_um, self.forward_rms_um)

    def row(self) -> dict[str, Any]:
        def num(v: float | None) -> float | None:
            return None if v is None or not math.isfinite(v) else float(v)

        return {
            "name": self.name,
            "family": self.family,
            "description": self.description,
            "cv_rms_um": num(self.cv_rms_um),
            "cv_max_abs_um": num(self.cv_max_abs_um),
            "nested_rms_um": num(self.nested_rms_um),
            "nested_max_abs_um": num(self.nested_max_abs_um),
            "honest_rms_um": num(self.honest_rms_um),
            "folds_rms_um": [num(v) for v in self.folds_rms_um],
            "forward_rms_um": num(self.forward_rms_um),
            "forward_max_abs_um": num(self.forward_max_abs_um),
            "forward_folds_rms_um": [num(v) for v in self.forward_folds_rms_um],
            "forward_median_rms_um": num(
                float(np.median(self.forward_folds_rms_um)) if self.forward_folds_rms_um else None
            ),
            "forward_worst_rms_um": num(
                max(self.forward_folds_rms_um) if self.forward_folds_rms_um else None
            ),
            "decisive_rms_um": num(self.decisive_rms_um),
            "in_sample_rms_um": num(self.in_sample_rms_um),
            "in_sample_max_abs_um": num(self.in_sample_max_abs_um),
            "accepted": self.accepted,
            "refusals": list(self.refusals),
            "notes": list(self.notes),
            **self.details,
            "fit_cpu_s": round(self.fit_cpu_s, 3),
        }
