"""Structured events: every state transition of the runtime is one JSON log line.

An event is a log record with an ``event`` name, the ``spindle`` and its own fields; the
JSON formatter (:class:`JsonLines`) writes them as keys, so a shop's log collector can alarm on
``"event": "outage"`` without parsing prose. Messages are clipped to one short line.
"""

from __future__ import annotations

import json
import logging
from typing import Any

from cnc_adapters.reading import REASON_CHARS
from compensator.errors import clip

log = logging.getLogger("thermocomp.runtime")

EVENTS = (
    "started",
    "stopped",
    "cold_start",
    "state_restored",
    "state_corrupt",
    "link_down",
    "outage",
    "link_restored",
    "timeout",
    "idle_assumed",
    "speed_restored",
    "offset_mismatch",
    "write_rejected",
    "write_backoff",
    "input_fallback",
    "inputs_restored",
    "inputs_extrapolated",
    "inputs_within_training",
    "journal_failed",
    "journal_restored",
    "state_save_failed",
    "state_stale",
    "state_saved_again",
    "clock_step",
    "reload",
    "reload_refused",
    "lock_failed",
    "probe_accepted",
    "probe_rejected",
    "probe_restart",
    "probe_failed",
    "probe_limited",
    "observer_bound",
    "observer_bound_cleared",
    "observer_stale",
    "observer_fresh",
    "control_failed",
    "cutting_signal_failed",
    "cutting_signal_restored",
    "chiller_failed",
    "chiller_restored",
    "status_listening",
    "status_failed",
    "mqtt_connected",
    "mqtt_lost",
    "journal_swept",
    "estimate_refused",
    "cycle_failed",
    "downtime_corrected",
    "expected_error_high",
    "expected_error_within_bound",
    "model_drift",
    "model_drift_cleared",
    "model_switched",
    "history_failed",
    "shadow_started",
    "shadow_failed",
    "cold_start_turning",
    "cold_start_settled",
    "spindle_state",
    "cycles_late",
    "cycles_on_time",
    "sign_of_life_failed",
    "sign_of_life_restored",
)
"""Every event name the runtime emits (documented in docs/reference)."""


def event(
    name: str,
    spindle: str | None,
    message: str,
    *args: Any,
    level: int = logging.INFO,
    **fields: Any,
) -> None:
    """Log one transition: ``message % args`` for people, ``name`` and ``fields`` for machines."""
    assert name in EVENTS, name
    log.log(level, message, *args, extra={"event": name, "spindle": spindle, "fields": fields})


class JsonLines(logging.Formatter):
    """One JSON object per line: ts, level, logger, msg, and an event's name and fields."""

    MAX_MESSAGE = 500

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "ts": round(record.created, 3),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": clip(record.getMessage(), self.MAX_MESSAGE),
        }
        name = getattr(record, "event", None)
        if name is not None:
            out["event"] = name
            spindle = getattr(record, "spindle", None)
            if spindle is not None:
                out["spindle"] = spindle
            for k, v in (getattr(record, "fields", None) or {}).items():
                # a failure's reason whole: its status code and hint come last
                out.setdefault(k, clip(v, REASON_CHARS) if isinstance(v, str) else v)
        if record.exc_info:
            out["exc"] = clip(
                self.formatException(record.exc_info).splitlines()[-1], self.MAX_MESSAGE
            )
        return (
            json.dumps(out, default=str, allow_nan=False)
            if _finite(out)
            else json.dumps(
                {k: (v if _finite({k: v}) else str(v)) for k, v in out.items()}, default=str
            )
        )


def _finite(obj: dict[str, Any]) -> bool:
    return all(
        not ((isinstance(v, float) and v != v) or v in (float("inf"), float("-inf")))
        for v in obj.values()
        if isinstance(v, float)
    )
