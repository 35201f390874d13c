"""What one cycle did, as one frozen value: the journal, the status, the metrics and MQTT read it."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from .alarms import Alarm


@dataclass(frozen=True)
class CycleOutcome:
    """One cycle of one spindle. Times are the runtime's clock (monotonic seconds); the journal
    adds the anchor."""

    time_s: float
    dt_s: float
    speed_rpm: float
    """The speed every part of the cycle used (clamped to the calibrated range)."""
    predicted_um: float
    """The estimate the offset follows: the model in use plus the observer's bias."""
    target_um: float
    """The shaped offset this cycle aimed at."""
    offset_um: float
    """What the controller holds after this cycle (written, or kept)."""
    written: bool
    flags: int
    """The shaper's flags (:class:`compensator.shaping.Flag`)."""
    alarms: Alarm
    """The alarms journaled with this cycle."""
    read_to_write_ms: float
    offset_mode: str
    link: str
    cutting: bool
    cutting_source: str
    policy_state: str
    slew_limit_um_per_s: float
    estimate: str
    """Which estimate is in use: "fused", "inputs" or "speed"."""
    inputs: Mapping[str, float]
    """The input values read this cycle (journaled)."""
    observer: Mapping[str, Any] | None = None
    expected_error: Mapping[str, Any] | None = None
    drift: Mapping[str, Any] | None = None
    shadow: Mapping[str, Any] | None = None

    def __getitem__(self, key: str) -> Any:
        """A field by name, as scripts that read a cycle as a mapping do (``out["offset_um"]``)."""
        if key not in _FIELDS:
            raise KeyError(key)
        return getattr(self, key)

    def as_dict(self) -> dict[str, Any]:
        """Plain values, for status pages and messages."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["inputs"] = dict(self.inputs)
        return out


class Pace:
    """The cycle's own timing: since when it runs, the last cycle, a run-up that wants the fast
    period, and the alarms still to be journaled from the start."""

    def __init__(self, created_s: float):
        self.created_s = created_s
        self.first_s: float | None = None
        self.last_s: float | None = None
        self.run_up_until_s = -math.inf  # the speed was seen changing, the tool not cutting
        self.startup = Alarm.NONE  # journaled with the first cycle

    def follow(self, old: Pace) -> None:
        self.created_s, self.first_s, self.last_s = old.created_s, old.first_s, old.last_s
        self.run_up_until_s = old.run_up_until_s

    def tick(self, now: float) -> float:
        """This cycle's dt [s] on the monotonic clock."""
        if self.first_s is None:
            self.first_s = now
        dt = 0.0 if self.last_s is None else max(0.0, now - self.last_s)
        self.last_s = now
        return dt


_FIELDS = frozenset(f.name for f in dataclasses.fields(CycleOutcome))
