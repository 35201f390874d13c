"""The error a model can be expected to make where it runs now. Pure: no I/O.

The fit states it (``calibration.metrics.expected_error``) from residuals that took no part in
the fit, by operating region: the speed band and whether the inputs lie inside the range the
calibration saw. The service reads it every cycle (:meth:`ExpectedError.at`), publishes it and
raises an alarm when it exceeds a configured bound; replay sets a log's errors beside it.

The distance outside the trained range (:func:`distance_outside`) is measured in spans of that
range, the largest over the inputs: 0 inside, 1 one whole span beyond an end (where the model's
valid range ends and a value is taken for a sensor fault).

A band's 95 % half-width is calibrated on forward residuals (split conformal prediction, taken
per fold because the rows of one fold are not independent; ``calibration.metrics``). A band
states a validated figure only where forward residuals were measured: a speed above the fastest
the calibration measured at (a model fitted on measurements at rest, say) is "not validated at
speed", and its figure, if any, is a floor.

The thermal state remembers the speeds of the last hours: after running faster than any speed
in the memory of a forward residual (``history_rpm`` within ``memory_s``, :func:`memory_s_of`),
at rest too, the spindle is where validation never measured.

Formats: ``thermocomp.expected-error/2`` adds, per band and outside figure, the folds behind it,
the fastest speed the forward residuals were measured at and the speed history behind them;
``/1`` records read as they always did (every band validated by the statement's fold count, up
to its top band's speed).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar, Final, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, SerializerFunctionWrapHandler, model_serializer

from .units import RANGE_TOLERANCE

EXPECTED_FORMAT: Final = "thermocomp.expected-error/2"
EXPECTED_FORMAT_1: Final = "thermocomp.expected-error/1"
"""The first format: no folds per band, no measured speed (still read)."""

COVERAGE: Final = 0.95
"""The share of errors a band states to hold."""

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


MEMORY_TAUS = 3.0
"""A speed counts in the spindle's thermal state for this many of the model's slowest time
constants (its effect has then decayed to exp(-3), 5 %)."""


def memory_s_of(model: object) -> float | None:
    """How long a speed stays in the thermal state of ``model`` [s]: :data:`MEMORY_TAUS` times
    its slowest time constant, its input lags and its fallback's included; None where it states
    none."""
    taus: list[float] = []
    parts: tuple[Any, ...] = (model, getattr(model, "fallback", None))
    for m in parts:
        if m is None:
            continue
        own = getattr(m, "taus_s", None)
        if own is None and callable(getattr(m, "time_constants_s", None)):
            own = m.time_constants_s(0.0)
        taus += [float(t) for t in own or ()]
        taus += [float(getattr(c, "tau_s", 0.0)) for c in getattr(m, "inputs", None) or ()]
    taus = [t for t in taus if np.isfinite(t) and t > 0]
    return MEMORY_TAUS * max(taus) if taus else None


SAVED_LATELY = 256
"""Entries of the speeds lately a state file keeps at most (thinned on the safe side)."""


class RecentMax:
    """The fastest |speed| within ``span_s`` up to the newest time pushed, kept as it comes: a
    sliding-window maximum (the times, with their speeds decreasing; the first within a span is
    the fastest it remembers). O(1) per push, amortised, and no allocation per push.

    ``restart``: a time that runs backwards starts a new history (the next log of several);
    without it (a service's clock) what came before stays remembered, the safe side."""

    def __init__(self, span_s: float, restart: bool = False) -> None:
        self.span_s = span_s
        self.restart = restart
        self._times: deque[float] = deque()
        self._speeds: deque[float] = deque()

    def push(self, time_s: float, speed_rpm: float) -> None:
        """Add one |speed| [rpm] at ``time_s``; a NaN speed (unread) adds nothing."""
        n = abs(speed_rpm) if speed_rpm == speed_rpm else 0.0
        if self.restart and self._times and time_s < self._times[-1]:
            self._times.clear()
            self._speeds.clear()
        while self._speeds and self._speeds[-1] <= n:
            self._times.pop()
            self._speeds.pop()
        self._times.append(time_s)
        self._speeds.append(n)
        while self._times[0] < time_s - self.span_s:
            self._times.popleft()
            self._speeds.popleft()

    def to_wall(self, now: float, wall_now: float, most: int = SAVED_LATELY) -> list[list[float]]:
        """What a state file keeps: ``[wall time, |rpm|]`` pairs, oldest first, at most
        ``most``: consecutive entries merged, each group's fastest speed taking its latest time,
        so that a thinned history remembers a speed no shorter than the full one."""
        pairs, latest = [], -math.inf
        for t, v in zip(self._times, self._speeds):
            latest = max(latest, t)  # in order even after a clock that stepped back
            pairs.append((wall_now - max(0.0, now - latest), v))  # never after the save
        step = max(1, math.ceil(len(pairs) / most))
        # speeds decrease along the window: a group's first speed is its fastest
        return [
            [pairs[min(i + step, len(pairs)) - 1][0], pairs[i][1]]
            for i in range(0, len(pairs), step)
        ]

    def from_wall(self, pairs: Sequence[Sequence[float]], now: float, wall_now: float) -> None:
        """Take up a saved history (``[wall time, |rpm|]`` pairs, oldest first, checked by the
        reader) onto the clock read as ``now`` at ``wall_now``; what is older than the span
        drops out as it would have."""
        for wall_t, rpm in pairs:
            # a wall clock set back while the service was down: nothing later than now
            self.push(min(now, now - (wall_now - wall_t)), rpm)

    def fastest(self, time_s: float, span_s: float | None = None) -> float:
        """The fastest |speed| within ``span_s`` (default, and at most, :attr:`span_s`) up to
        ``time_s``, the newest pushed; 0 before any."""
        since = time_s - (self.span_s if span_s is None else min(span_s, self.span_s))
        for t, v in zip(self._times, self._speeds):
            if t >= since:
                return v
        return 0.0


def recent_rpm(time_s: np.ndarray, speed_rpm: np.ndarray, memory_s: float) -> np.ndarray:
    """Per row, the fastest |speed| within ``memory_s`` up to it, its own included. A time that
    runs backwards (the next log of several) starts a new history."""
    t = np.asarray(time_s, float).tolist()
    n = np.nan_to_num(np.asarray(speed_rpm, float)).tolist()
    window = RecentMax(memory_s, restart=True)
    out = np.empty(len(n))
    for i, (ti, ni) in enumerate(zip(t, n)):
        window.push(ti, ni)
        out[i] = window.fastest(ti)
    return out


class _Stored(BaseModel):
    """A part of the statement as stored: the fields added by a later format are left out where
    they are unset (None), so a record read from an older file writes back byte for byte (the
    model's checksum, which saved state names, stays the same)."""

    ADDED: ClassVar[tuple[str, ...]] = ()

    @model_serializer(mode="wrap")
    def _without_unset(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        data: dict[str, Any] = handler(self)
        for name in type(self).ADDED:
            if data.get(name, 0) is None:
                del data[name]
        return data


class Figure(_Stored):
    """RMS and 95th percentile of |error| [um] over ``samples`` residuals of ``source``."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    ADDED = ("folds",)

    source: str = Field(description="which residuals: forward (rolling origin) or held out")
    samples: int = Field(ge=1)
    rms_um: float = Field(ge=0)
    p95_abs_um: float = Field(ge=0)
    folds: int | None = Field(
        None,
        ge=0,
        description="folds predicted forward behind it (None: the statement's forward_folds)",
    )


class Band(_Stored):
    """One speed band: the error inside the trained input range and, where validation saw it,
    outside."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    ADDED = ("folds",)

    speed_rpm: tuple[float, float] = Field(
        description="(low, high] |speed| [rpm]; rest is (0, idle]"
    )
    source: str
    samples: int = Field(ge=1)
    rms_um: float = Field(ge=0)
    p95_abs_um: float = Field(ge=0)
    outside: Figure | None = Field(None, description="with the inputs outside the trained range")
    folds: int | None = Field(
        None,
        ge=0,
        description="folds predicted forward behind it (None: the statement's forward_folds)",
    )

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
    unvalidated: str | None = None
    """Where it is not validated, in a few words: ``at speed``, ``outside the trained range``."""

    @property
    def claim(self) -> str:
        """What a display says: the figure where validated, else that it is not validated (a
        floor is no promise)."""
        if self.validated:
            return f"expect ±{self.p95_abs_um:.1f} µm (95 %)"
        return "not validated" + (f" {self.unvalidated}" if self.unvalidated else "")


class ExpectedError(_Stored):
    """What the fit states, stored in the model's fit record under ``expected_error``."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    ADDED = ("measured_rpm", "history_rpm", "memory_s")

    format: Literal["thermocomp.expected-error/1", "thermocomp.expected-error/2"] = EXPECTED_FORMAT
    bands: tuple[Band, ...] = Field(min_length=1)
    outside_validated: float = Field(
        0.0,
        ge=0,
        description="largest distance outside the trained range that validation scored, in spans",
    )
    forward_folds: int = Field(0, ge=0, description="folds predicted forward behind the statement")
    measured_rpm: float | None = Field(
        None,
        ge=0,
        description="the fastest |speed| a forward residual was measured at; above it the "
        "statement is not validated (None: the top band's speed, as older records)",
    )
    history_rpm: float | None = Field(
        None,
        ge=0,
        description="the fastest |speed| within memory_s before any forward residual: after "
        "running faster, the spindle's heat lies where validation never measured",
    )
    memory_s: float | None = Field(
        None, gt=0, description="how long a speed counts in the thermal state (history_rpm)"
    )

    def recent_rpm(self, time_s: np.ndarray, speed_rpm: np.ndarray) -> np.ndarray | None:
        """Per row of a log, the fastest |speed| within :attr:`memory_s` up to it (None when
        the statement keeps no history): what :meth:`validated` takes as ``recent_rpm``."""
        if self.history_rpm is None or self.memory_s is None:
            return None
        return recent_rpm(time_s, speed_rpm, self.memory_s)

    def _ran_faster(self, recent: np.ndarray | None) -> np.ndarray | bool:
        if recent is None or self.history_rpm is None:
            return False
        hot: np.ndarray = np.asarray(recent, float) > max(self.history_rpm, 1.0) * (
            1 + RANGE_TOLERANCE
        )
        return hot

    def _folds(self, own: int | None) -> int:
        return self.forward_folds if own is None else own

    @property
    def measured_top_rpm(self) -> float:
        """The fastest speed validation measured at (older records: the top band's)."""
        return self.bands[-1].speed_rpm[1] if self.measured_rpm is None else self.measured_rpm

    def _above(self, n: np.ndarray) -> np.ndarray:
        """Faster than validation measured at (2 % over counts as in range)."""
        top = self.measured_top_rpm if self.measured_rpm is None else max(self.measured_rpm, 1.0)
        above: np.ndarray = n > top * (1 + RANGE_TOLERANCE)
        return above

    def validated(
        self,
        speed_rpm: np.ndarray,
        distance: np.ndarray | None = None,
        recent_rpm: np.ndarray | None = None,
    ) -> np.ndarray:
        """Per row, whether validation scored predictions like it: the row's band (and, with the
        inputs outside the trained range, its outside figure) rests on enough folds predicted
        forward (:data:`MIN_FORWARD_FOLDS`), the speed is no faster than validation measured at,
        the spindle ran no faster lately (``recent_rpm``, :meth:`recent_rpm`) than before any
        forward residual, and the inputs lie no farther out than validation reached. Elsewhere
        the stated figure is a floor."""
        n = np.abs(np.asarray(speed_rpm, float))
        which = self.band_index(n)
        ok = ~self._above(n) & self._in_band(n, which) & ~self._ran_faster(recent_rpm)
        ok &= np.array([self._folds(b.folds) >= MIN_FORWARD_FOLDS for b in self.bands])[which]
        if distance is not None:
            d = np.nan_to_num(np.asarray(distance, float))
            ok &= d <= self.outside_validated
            if self.format != EXPECTED_FORMAT_1:  # older records: the band's figure covers it
                out_ok = np.array(
                    [
                        b.outside is not None and self._folds(b.outside.folds) >= MIN_FORWARD_FOLDS
                        for b in self.bands
                    ]
                )[which]
                ok &= (d <= 0) | out_ok
        valid: np.ndarray = ok & (self.forward_folds >= MIN_FORWARD_FOLDS)
        return valid

    def _in_band(self, n: np.ndarray, which: np.ndarray) -> np.ndarray:
        """Whether each speed lies in the band it was given (not in a band left out, nor above
        the top one)."""
        if self.format == EXPECTED_FORMAT_1:  # older records: a gap took the top band's figure
            return np.ones(n.shape, bool)
        lo, hi = self._edges
        inside: np.ndarray = (n <= hi[which]) & ((n > lo[which]) | (lo[which] == 0.0))
        # above the top band only the speed check (measured_rpm, 2 % over) speaks
        out: np.ndarray = inside | (n > hi[-1])
        return out

    def unvalidated_where(
        self, speed_rpm: float, spans: float, recent: float | None = None
    ) -> str | None:
        """Where a prediction is not validated, in a few words (None: validated)."""
        n = np.array([speed_rpm])
        r = None if recent is None else np.array([recent])
        if bool(self.validated(n, np.array([spans]), r)[0]):
            return None
        if r is not None and bool(np.any(self._ran_faster(r))) and not self._above(np.abs(n))[0]:
            return "after running faster than calibrated"
        if (self.measured_rpm is not None and bool(self._above(np.abs(n))[0])) or not bool(
            self._in_band(np.abs(n), self.band_index(n))[0]
        ):
            return "at speed" if abs(speed_rpm) > 1.0 else "at rest"
        if spans > 0 and bool(self.validated(n, np.array([0.0]))[0]):
            return "outside the trained range"
        return None

    def why_unvalidated(
        self, speed_rpm: float, spans: float, recent: float | None = None
    ) -> list[str]:
        """Why validation scored no prediction like this one (:meth:`validated`), in words."""
        why = []
        if recent is not None and bool(np.any(self._ran_faster(np.array([recent])))):
            why.append(
                f"the spindle ran at {recent:.0f} rpm within the last "
                f"{(self.memory_s or 0.0) / 3600:.1f} h, faster than before any error the "
                f"calibration measured forward ({self.history_rpm or 0.0:.0f} rpm)"
            )
        if self.forward_folds < MIN_FORWARD_FOLDS:
            why.append(
                f"the fit predicted {self.forward_folds} fold(s) forward, fewer than {MIN_FORWARD_FOLDS}"
            )
        n = abs(speed_rpm)
        top = self.bands[-1].speed_rpm[1]
        if self.measured_rpm is None:
            if n > top * (1 + RANGE_TOLERANCE):
                why.append(f"{n:.0f} rpm is above the calibrated {top:.0f} rpm")
        elif bool(self._above(np.array([n]))[0]):
            where = (
                "at rest only" if self.measured_rpm <= 1.0 else f"up to {self.measured_rpm:.0f} rpm"
            )
            why.append(f"not validated at speed: the calibration measured the error {where}")
        else:
            b = self.band_of(speed_rpm)
            if not bool(self._in_band(np.array([n]), self.band_index(np.array([n])))[0]):
                why.append(f"no error was measured forward at {n:.0f} rpm")
            elif (
                self.forward_folds >= MIN_FORWARD_FOLDS and self._folds(b.folds) < MIN_FORWARD_FOLDS
            ):
                why.append(
                    f"{place(b.label)} the figure rests on {self._folds(b.folds)} fold(s) predicted "
                    f"forward ({b.source})"
                )
        if spans > self.outside_validated:
            why.append(
                f"inputs {spans:.2f} spans outside the trained range, further than validation "
                f"scored ({self.outside_validated:.2f})"
            )
        elif spans > 0 and self.format != EXPECTED_FORMAT_1:
            b = self.band_of(speed_rpm)
            if b.outside is None or self._folds(b.outside.folds) < MIN_FORWARD_FOLDS:
                why.append(
                    f"no forward fold measured the error {place(b.label)} with the inputs outside the trained range"
                )
        return why or ["validation scored no prediction like this one"]

    def describe(self) -> list[str]:
        """The statement in words, one line per band, and where it is not validated (what
        ``thermocomp fit`` prints)."""
        lines = []
        for b in self.bands:
            folds = min(self._folds(b.folds), self.forward_folds)
            far = (
                f"; inputs outside the trained range: RMS {b.outside.rms_um:.2f} um, 95 % within "
                f"{b.outside.p95_abs_um:.2f} um ({b.outside.source})"
                if b.outside is not None
                else ""
            )
            # with m folds as the exchangeable units, the next one's own 95 % half-width stays
            # within the worst of them with probability at least m / (m + 1)
            floor = (
                f"; 95 % of the next cycle within it with probability ≥ "
                f"{100 * folds / (folds + 1):.0f} %"
                if folds >= MIN_FORWARD_FOLDS
                else ", not validated: a floor"
            )
            lines.append(
                f"{b.label:>16}: RMS {b.rms_um:.2f} um, 95 % within {b.p95_abs_um:.2f} um "
                f"({b.source}, {b.samples} samples, {self._folds(b.folds)} fold(s){floor}){far}"
            )
        if self.measured_rpm is not None:
            lines.append(
                "validated at rest only: not validated at speed"
                if self.measured_rpm <= 1.0
                else f"validated up to {self.measured_rpm:.0f} rpm: not validated at speed above it"
            )
        return lines

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

    def at(
        self, speed_rpm: float, distance: float = 0.0, recent: float | None = None
    ) -> Expectation:
        """The error to expect at ``speed_rpm`` with the inputs ``distance`` spans outside the
        trained range (:func:`distance_outside`), the spindle having run at up to ``recent``
        rpm lately (:meth:`recent_rpm`; None: not known)."""
        b = self.band_of(speed_rpm)
        r = None if recent is None else np.array([recent])
        ok = bool(self.validated(np.array([speed_rpm]), np.array([distance]), r)[0])
        where = None if ok else self.unvalidated_where(speed_rpm, distance, recent)
        if distance > 0 and b.outside is not None and b.outside.p95_abs_um > b.p95_abs_um:
            fig = b.outside
            return Expectation(b.label, fig.rms_um, fig.p95_abs_um, fig.source, True, ok, where)
        return Expectation(b.label, b.rms_um, b.p95_abs_um, b.source, distance > 0, ok, where)


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
