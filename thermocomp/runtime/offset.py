"""The offset, one small state machine: tracking, ramping, holding.

It owns the shaper and knows what the controller holds (``held_um``), which is what the
journal records. Each cycle :meth:`OffsetTracker.plan` shapes the model's elongation; the runtime
then reports the outcome: :meth:`written`, or :meth:`kept` when nothing reached the controller.
:meth:`controller_holds` is for a controller whose value is known to differ (a deferred
write check, a machine that is off and applies 0), :meth:`rewrite` for a link that came back.

- ``TRACKING``: the controller holds the shaped offset, which follows the model;
- ``RAMPING``: the controller holds a value on its way to the model's, slowed by the slew limit
  or the transient policy;
- ``HOLDING``: the controller keeps an older value because a write was not possible; the
  shaper moves on from that value, so when writes resume the offset ramps, never jumps.
"""

from __future__ import annotations

import enum
import math

from compensator.shaping import Flag, OffsetShaper, ShapedOffset, ShaperConfig

_SLOWED = Flag.SLEW_LIMITED | Flag.TRANSIENT | Flag.RELEASING


class OffsetMode(enum.Enum):
    TRACKING = "tracking"
    RAMPING = "ramping"
    HOLDING = "holding"


class OffsetTracker:
    def __init__(self, config: ShaperConfig, held_um: float = 0.0):
        self.shaper = OffsetShaper(config, held_um)
        self.held_um = self.shaper.output_um
        self.pending = False
        self.mode = OffsetMode.TRACKING

    def plan(
        self, elongation_um: float, speed_rpm: float, dt_s: float, cutting: bool | None = None
    ) -> ShapedOffset:
        """The shaped offset for this cycle (not yet written); ``cutting`` the controller's
        signal, or None for the shaper to infer it from the speed."""
        return self.shaper.update(elongation_um, speed_rpm, dt_s, cutting)

    def wants_write(self, shaped: ShapedOffset) -> bool:
        return shaped.write or self.pending

    def written(self, shaped: ShapedOffset) -> None:
        self.held_um = shaped.offset_um
        self.pending = False
        self.mode = OffsetMode.RAMPING if shaped.flags & _SLOWED else OffsetMode.TRACKING

    def kept(self, wanted: bool) -> None:
        """Nothing was written this cycle; ``wanted`` says whether a write was due."""
        if wanted:
            self.pending = True
        if self.shaper.output_um != self.held_um:
            self.shaper.hold(self.held_um)  # the controller still holds the old value
        if self.pending:
            self.mode = OffsetMode.HOLDING

    def controller_holds(self, offset_um: float) -> None:
        """The controller holds ``offset_um``: move on from there and write again. A value that
        is not a finite number is not moved on from: the offset is only written again."""
        self.pending = True
        if math.isfinite(offset_um):
            self.shaper.hold(float(offset_um))
            self.held_um = float(offset_um)
        self.mode = OffsetMode.HOLDING

    def observe(self, held_um: float, tolerance_um: float) -> float | None:
        """The controller was read back and holds ``held_um``. Within ``tolerance_um`` of what
        it should hold: None. Otherwise the difference (held - expected); the offset then
        moves on from the held value through the slew limit, and is written again."""
        expected = self.held_um
        if not math.isfinite(held_um) or abs(held_um - expected) <= tolerance_um:
            return None
        self.controller_holds(held_um)
        return held_um - expected

    def rewrite(self) -> None:
        """Write the offset again at the next chance (the controller may have lost it)."""
        self.pending = True
