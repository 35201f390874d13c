"""The error to expect, each cycle: the figure the model in use states for the speed and for how
far the inputs lie outside the trained range (``fit.expected_error``).

Above ``max_expected_error_um``, or where validation scored nothing like it (the figure a
floor) while a bound is set: ``EXPECTED_ERROR_HIGH``, one event on entry and one on leaving.
Advice only: the offset is the same.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from compensator.estimate import Estimate, EstimateState
from compensator.expected import MIN_FORWARD_FOLDS, ExpectedError, RecentMax, place
from compensator.fitrecord import fit_of

from .alarms import Alarm
from .config import SpindleConfig
from .events import event

log = logging.getLogger("thermocomp.runtime")


@dataclass(frozen=True)
class ExpectedNow:
    """The error to expect this cycle, from the statement of the model in use."""

    band: str
    rms_um: float
    p95_abs_um: float
    source: str
    outside: bool
    outside_spans: float
    validated: bool
    bound_um: float | None
    claim: str = ""
    """What a display shows: ``expect ±X µm (95 %)``, or ``not validated at speed`` where
    validation never measured (the figure is then a floor, not shown as a promise)."""

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


class ExpectedWatch:
    """The statements of the model with inputs and of its speed-only fallback, read once per
    load, and the bound."""

    def __init__(self, cfg: SpindleConfig, model: Any):
        self.name = cfg.name
        self.bound_um = cfg.max_expected_error_um
        fallback = getattr(model, "fallback", None)
        self.expected: ExpectedError | None = fit_of(model).expected_error
        self.fallback: ExpectedError | None = (
            None if fallback is None else fit_of(fallback).expected_error
        )
        self.high: str | None = None  # why EXPECTED_ERROR_HIGH is raised, while it is
        self.memory_s = max(
            (e.memory_s or 0.0 for e in (self.expected, self.fallback) if e is not None),
            default=0.0,
        )
        # the speeds lately: a spindle cooling from a speed faster than validation saw is where
        # validation never measured, at rest too
        self.lately = RecentMax(self.memory_s)
        if self.bound_um is None:
            return
        if self.expected is None and self.fallback is None:
            log.warning(
                "%s: max_expected_error_um = %g, but model %s states no expected error (fit it "
                "again to have one): the bound is not checked",
                cfg.name,
                self.bound_um,
                cfg.model,
            )
        folds = min(
            (e.forward_folds for e in (self.expected, self.fallback) if e is not None),
            default=MIN_FORWARD_FOLDS,
        )
        if folds < MIN_FORWARD_FOLDS:
            log.warning(
                "%s: the expected error of model %s rests on %d fold(s) predicted forward (fewer "
                "than %d): it is only a floor, so EXPECTED_ERROR_HIGH stands while "
                "max_expected_error_um is set; fit on more cycles",
                cfg.name,
                cfg.model,
                folds,
                MIN_FORWARD_FOLDS,
            )

    def saved_fields(self, now: float, wall_now: float) -> dict[str, Any]:
        """What the state file keeps of the speeds lately (wall times): a restart within the
        memory still knows the spindle ran faster than validation saw."""
        if self.memory_s <= 0:
            return {}
        pairs = self.lately.to_wall(now, wall_now)
        return {"speeds_lately": pairs} if pairs else {}

    def restored(self, pairs: Sequence[Sequence[float]], now: float, wall_now: float) -> None:
        """The speeds lately a state file kept (checked where it was read)."""
        if self.memory_s > 0:
            self.lately.from_wall(pairs, now, wall_now)

    def follow(self, old: ExpectedWatch) -> None:
        self.high = old.high  # raised still: no second entry event
        self.lately = old.lately
        self.lately.span_s = self.memory_s  # this model's memory from now on

    def _recent(self, stated: ExpectedError, speed_rpm: float, now: float | None) -> float | None:
        """The fastest |speed| within ``stated``'s memory up to ``now`` (None: no history)."""
        if now is None or self.memory_s <= 0:
            return None
        self.lately.push(now, speed_rpm)
        if stated.memory_s is None or stated.history_rpm is None:
            return None
        return self.lately.fastest(now, stated.memory_s)

    def stated(self, estimate: Estimate, est: EstimateState) -> tuple[ExpectedError | None, bool]:
        """The statement of the model in use (the fallback's while it stands in), and whether
        the model with inputs is in use."""
        on_inputs = estimate.with_inputs is not None and est.inputs is not None
        use_main = on_inputs or estimate.with_inputs is None
        return (self.expected if use_main else self.fallback), on_inputs

    def at(
        self, estimate: Estimate, est: EstimateState, speed_rpm: float, now: float | None = None
    ) -> tuple[ExpectedNow | None, Alarm]:
        """The error to expect at ``speed_rpm`` (None where the model in use states none), and
        ``EXPECTED_ERROR_HIGH`` while a bound is set and the figure (95 % of |error|) exceeds it
        or validation scored no prediction like this one (too few folds predicted forward, a
        speed above the calibrated range, a speed faster than validation saw within the
        statement's memory before ``now``, inputs further out than it reached: the figure is
        then a floor). Advice only: the offset is never changed for it."""
        stated, on_inputs = self.stated(estimate, est)
        bound = self.bound_um
        out: ExpectedNow | None = None
        why: str | None = None
        if stated is not None:
            spans = float(est.outside_spans) if on_inputs else 0.0
            recent = self._recent(stated, speed_rpm, now)
            e = stated.at(speed_rpm, spans, recent)
            out = ExpectedNow(
                e.band,
                e.rms_um,
                e.p95_abs_um,
                e.source,
                e.outside,
                spans,
                e.validated,
                bound,
                e.claim,
            )
            if bound is not None and (e.p95_abs_um > bound or not e.validated):
                where = place(e.band)
                over = e.p95_abs_um > bound
                why = (
                    f"expected error {'' if e.validated else 'at least '}{e.p95_abs_um:.1f} um (95 %)"
                    + (
                        f" over the bound {bound:g} um {where}"
                        if over
                        else f" {where} (bound {bound:g} um)"
                    )
                )
                if not e.validated:  # the figure is a floor: the bound cannot be vouched for
                    why += ", not validated here: " + "; ".join(
                        stated.why_unvalidated(speed_rpm, spans, recent)
                    )
                elif e.outside:
                    why += ", inputs outside the trained range"
                why += ": probe or recalibrate"
        fields = out.as_dict() if out is not None else {}
        if why is not None and self.high is None:
            event(
                "expected_error_high",
                self.name,
                "%s: EXPECTED_ERROR_HIGH: %s",
                self.name,
                why,
                level=logging.WARNING,
                reason=why,
                **fields,
            )
        elif why is None and self.high is not None:
            now_is = (
                "the model in use states no expected error"
                if out is None
                else "no bound is set"
                if bound is None
                else f"expected error {out.p95_abs_um:.1f} um (95 %) {place(out.band)}, within "
                f"the bound {bound:g} um"
            )
            event(
                "expected_error_within_bound",
                self.name,
                "%s: EXPECTED_ERROR_HIGH cleared: %s",
                self.name,
                now_is,
                reason=now_is,
                **fields,
            )
        self.high = why
        return out, Alarm.EXPECTED_ERROR_HIGH if why is not None else Alarm.NONE
