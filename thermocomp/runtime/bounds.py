"""The observer's bounds as the runtime shows them: which measurements they cut, and
``OBSERVER_BOUND``. The bounds themselves are the core's (:mod:`compensator.observer`): a
measurement the correction's bound or its source's move cuts is taken only in part there; here it
is counted (``probes_limited``, per source), evented (``probe_limited``), and ``OBSERVER_BOUND`` is
raised while the correction is at its bound or a source's last measurement was cut (until that
source's move has drained, or it sends one taken whole)."""

from __future__ import annotations

import logging
from typing import Any

from compensator.estimate import Estimate, EstimateState
from compensator.fusion import FusedPredictor, FusedState
from compensator.observer import Update, at_bound

from .alarms import Alarm
from .events import event


class BoundWatch:
    """One spindle's cut measurements and its ``OBSERVER_BOUND``; a reload with the same model
    goes on with it."""

    def __init__(self, name: str, counters: dict[str, int]):
        self.name = name
        self.counters = counters
        counters.setdefault("probes_limited", 0)
        # source -> why its last measurement was cut (bound or source), until one is taken whole
        self.limited: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self.bounded = False  # OBSERVER_BOUND raised (its event once on entry)
        self.at_bound = False  # the correction is at max_correction_um
        self.bound_um: float | None = None  # max_correction_um, as the last cycle had it

    def taken_whole(self, source: str) -> None:
        """A measurement from ``source`` taken whole: that source is within its bounds again."""
        self.limited.pop(source, None)

    def cut(
        self,
        fused: FusedPredictor,
        source: str,
        up: Update,
        y: float,
        before: float,
        fields: dict[str, Any],
    ) -> None:
        """A measurement the bounds cut: counted per source, evented (``probe_limited``)."""
        cfg = fused.config
        assert up.limited is not None
        self.limited[source] = up.limited
        self.counts[source] = self.counts.get(source, 0) + 1
        limit = (
            f"the correction's bound of {cfg.max_correction_um:g} um"
            if up.limited == "bound"
            else f"{source}'s move of {cfg.source_move_um:g} um per {cfg.window_s:g} s"
        )
        event(
            "probe_limited",
            self.name,
            "%s: measurement %.3f um from %s taken only in part: it would set the correction to "
            "%+.3f um, %s holds it at %+.3f um (estimate was %.3f um)",
            self.name,
            y,
            source,
            up.wanted_bias_um,
            limit,
            up.state.bias_um,
            before,
            level=logging.WARNING,
            limited=up.limited,
            wanted_bias_um=up.wanted_bias_um,
            max_correction_um=cfg.max_correction_um,
            max_source_move_um=cfg.source_move_um,
            source_window_s=cfg.window_s,
            **fields,
        )

    def alarm(self, estimate: Estimate, est: EstimateState) -> Alarm:
        """OBSERVER_BOUND while the correction is at its bound or a source's last measurement
        was cut; one event on entry, one on leaving."""
        fused = estimate.fused
        state = est.core
        assert fused is not None and isinstance(state, FusedState)
        cfg = fused.config
        bias = est.bias_um
        reached = at_bound(cfg, bias)
        # a cut is over once its source's move has drained, or the correction left the bound
        self.limited = {
            k: why
            for k, why in self.limited.items()
            if (why == "source" and state.observer.moved_by(k) != 0.0)
            or (why == "bound" and reached)
        }
        bounded = reached or bool(self.limited)
        if bounded and not self.bounded:
            event(
                "observer_bound",
                self.name,
                "%s: OBSERVER_BOUND: %s; measurements that pull further are taken only in part. "
                "Check the measurement sources (%s); if the spindle really has changed, "
                "re-run the cold reference or recalibrate (refit learns only from measurements "
                "taken whole)",
                self.name,
                f"the correction is at {bias:+.3f} um, its bound is {cfg.max_correction_um:g} um"
                if reached
                else f"a source moved the correction by its {cfg.source_move_um:g} um per "
                f"{cfg.window_s:g} s",
                ", ".join(f"{k}: {n} cut" for k, n in sorted(self.counts.items())) or "none cut",
                level=logging.WARNING,
                bias_um=bias,
                max_correction_um=cfg.max_correction_um,
                max_source_move_um=cfg.source_move_um,
                source_window_s=cfg.window_s,
                sources=dict(self.limited),
            )
        elif self.bounded and not bounded:
            event(
                "observer_bound_cleared",
                self.name,
                "%s: OBSERVER_BOUND cleared: the correction %+.3f um is within its bound and "
                "the measurements are taken whole",
                self.name,
                bias,
                bias_um=bias,
            )
        self.bounded, self.at_bound, self.bound_um = bounded, reached, cfg.max_correction_um
        return Alarm.OBSERVER_BOUND if bounded else Alarm.NONE

    def status(self) -> dict[str, Any]:
        """For the observer's status: the alarm, whether the correction is at its bound, the
        bound, the sources cut now and how many each had cut."""
        return {
            "bounded": self.bounded,
            "at_bound": self.at_bound,
            "max_correction_um": self.bound_um,
            "limited_sources": dict(self.limited),
            "limited": dict(self.counts),
        }
