"""The error a model can be expected to make where it runs now. Pure: no I/O.

The fit states it (``calibration.metrics.expected_error``) from residuals that took no part in
the fit, by operating region: the speed band and whether the inputs lie inside the range the
calibration saw. The service reads it every cycle (:meth:`ExpectedError.at`), publishes it and
raises an alarm when it exceeds a configured bound; replay sets a log's errors beside it.

The distance outside the trained range (:func:`distance_outside`) is measured in spans of that
range, the largest over the inputs: 0 inside, 1 one whole span beyond an end (where the model's
valid range ends and a value is taken for a sensor fault).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Final, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .units import RANGE_TOLERANCE

EXPECTED_FORMAT: Final = "thermocomp.expected-error/1"

MIN_FORWARD_FOLDS = 2
"""A statement from fewer folds predicted forward is not validated: held-out past cycles alone
understated the next cycle's error up to 50-fold on the real record."""

_MIN_SPAN = 1e-9
"""A span below this (an input that never moved in calibration) counts as this much."""


def distance_outside(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per row of ``values`` (rows, inputs), how far outside [``lo``, ``hi``] the inputs lie,
    in spans ``hi - lo`` of each input: the largest over the inputs, 0 inside. NaN stays NaN."""
    u = np.atleast_2d(np.asarray(values, float))
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    span = np.maximum(hi - lo, _MIN_SPAN * np.maximum(np.maximum(np.abs(lo), np.abs(hi)), 1.0))
    out = np.maximum(np.maximum(lo - u, u - hi), 0.0) / span
    return np.max(out, axis=1) if out.shape[1] else np.zeros(out.shape[0])


class Figure(BaseModel):
    """RMS and 95th percentile of |error| [um] over ``samples`` residuals of ``source``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    source: str = Field(description="which residuals: forward (rolling origin) or held out")
    samples: int = Field(ge=1)
    rms_um: float = Field(ge=0)
    p95_abs_um: float = Field(ge=0)


class Band(BaseModel):
    """One speed band: the error inside the trained input range and, where validation saw it,
    outside."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    speed_rpm: tuple[float, float] = Field(
        description="(low, high] |speed| [rpm]; rest is (0, idle]"
    )
    source: str
    samples: int = Field(ge=1)
    rms_um: float = Field(ge=0)
    p95_abs_um: float = Field(ge=0)
    outside: Figure | None = Field(None, description="with the inputs outside the trained range")

    @property
    def label(self) -> str:
        lo, hi = self.speed_rpm
        return "at rest" if hi <= 1.0 else f"{lo:.0f}-{hi:.0f} rpm"


@dataclass(frozen=True)
class Expectation:
    """The error to expect this cycle."""

    band: str
    rms_um: float
    p95_abs_um: float
    source: str
    outside: bool
    """The inputs lie outside the trained range."""
    validated: bool
    """Validation scored predictions like this one (:meth:`ExpectedError.validated`; False: the
    figure is a floor, not a measure)."""


class ExpectedError(BaseModel):
    """What the fit states, stored in the model's fit record under ``expected_error``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    format: Literal["thermocomp.expected-error/1"] = EXPECTED_FORMAT
    bands: tuple[Band, ...] = Field(min_length=1)
    outside_validated: float = Field(
        0.0,
        ge=0,
        description="largest distance outside the trained range that validation scored, in spans",
    )
    forward_folds: int = Field(0, ge=0, description="folds predicted forward behind the statement")

    def validated(self, speed_rpm: np.ndarray, distance: np.ndarray | None = None) -> np.ndarray:
        """Per row, whether validation scored predictions like it: enough folds predicted
        forward (:data:`MIN_FORWARD_FOLDS`), a speed within the calibrated range and inputs no
        farther out than validation reached. Elsewhere the stated figure is a floor."""
        n = np.abs(np.asarray(speed_rpm, float))
        ok = n <= self.bands[-1].speed_rpm[1] * (1 + RANGE_TOLERANCE)
        if distance is not None:
            ok &= np.nan_to_num(np.asarray(distance, float)) <= self.outside_validated
        valid: np.ndarray = ok & (self.forward_folds >= MIN_FORWARD_FOLDS)
        return valid

    def why_unvalidated(self, speed_rpm: float, spans: float) -> list[str]:
        """Why validation scored no prediction like this one (:meth:`validated`), in words."""
        why = []
        if self.forward_folds < MIN_FORWARD_FOLDS:
            why.append(
                f"the fit predicted {self.forward_folds} fold(s) forward, fewer than {MIN_FORWARD_FOLDS}"
            )
        top = self.bands[-1].speed_rpm[1]
        if abs(speed_rpm) > top * (1 + RANGE_TOLERANCE):
            why.append(f"{abs(speed_rpm):.0f} rpm is above the calibrated {top:.0f} rpm")
        if spans > self.outside_validated:
            why.append(
                f"inputs {spans:.2f} spans outside the trained range, further than validation "
                f"scored ({self.outside_validated:.2f})"
            )
        return why or ["validation scored no prediction like this one"]

    @cached_property
    def _edges(self) -> tuple[np.ndarray, np.ndarray]:
        # the statement is frozen and parsed once per model load; the service reads it every cycle
        return (
            np.array([b.speed_rpm[0] for b in self.bands], float),
            np.array([b.speed_rpm[1] for b in self.bands], float),
        )

    def band_index(self, speed_rpm: np.ndarray) -> np.ndarray:
        """For each speed, the index of its band; the top band above the calibrated range or in
        a band left out (no residual covered it)."""
        n = np.abs(np.asarray(speed_rpm, float))
        lo, hi = self._edges
        i = np.minimum(
            np.searchsorted(hi, n, side="left"), len(self.bands) - 1
        )  # first band reaching n
        inside = (n <= hi[i]) & ((n > lo[i]) | (lo[i] == 0.0))
        return np.where(inside, i, len(self.bands) - 1)

    def band_of(self, speed_rpm: float) -> Band:
        return self.bands[int(self.band_index(np.array([speed_rpm]))[0])]

    def p95_at(self, speed_rpm: np.ndarray, distance: np.ndarray | None = None) -> np.ndarray:
        """The stated 95 % bound [um] per row: the band's, its outside figure where the inputs
        lie outside (never below the inside one)."""
        which = self.band_index(speed_rpm)
        inside: np.ndarray = np.array([b.p95_abs_um for b in self.bands])[which]
        if distance is None:
            return inside
        out = np.array(
            [
                max(b.p95_abs_um, b.outside.p95_abs_um) if b.outside else b.p95_abs_um
                for b in self.bands
            ]
        )[which]
        bound: np.ndarray = np.where(np.asarray(distance, float) > 0, out, inside)
        return bound

    def at(self, speed_rpm: float, distance: float = 0.0) -> Expectation:
        """The error to expect at ``speed_rpm`` with the inputs ``distance`` spans outside the
        trained range (:func:`distance_outside`)."""
        b = self.band_of(speed_rpm)
        ok = bool(self.validated(np.array([speed_rpm]), np.array([distance]))[0])
        if distance > 0 and b.outside is not None and b.outside.p95_abs_um > b.p95_abs_um:
            fig = b.outside
            return Expectation(b.label, fig.rms_um, fig.p95_abs_um, fig.source, True, ok)
        return Expectation(b.label, b.rms_um, b.p95_abs_um, b.source, distance > 0, ok)


def place(label: str) -> str:
    """A band's label as a place in a sentence: ``at rest``, ``at 0-3333 rpm``."""
    return label if label == "at rest" else f"at {label}"


def parse_expected(fit: object) -> ExpectedError | None:
    """The statement in a model's fit record (None when it has none): the typed record's
    (``compensator.fitrecord.FitRecord.expected_error``, which new code reads directly) or a
    record's JSON form. An unreadable one is None too: it is advice, and the model runs
    without it."""
    typed = getattr(fit, "expected_error", None)
    if isinstance(typed, ExpectedError):
        return typed
    raw = fit.get("expected_error") if isinstance(fit, Mapping) else None
    if not isinstance(raw, Mapping):
        return None
    try:
        return ExpectedError.model_validate(raw)
    except ValueError:
        return None
