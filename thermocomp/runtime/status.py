"""Live status: what the running service is doing, for people, monitoring and the shop floor.

Each tick the service builds one immutable **snapshot** (:func:`snapshot`): per spindle the
elongation S, the offset aimed at, the one the controller holds and the one last read back, the
alarms by name, the age of the last write, the link and observer state, the model with its
ranges and the error to expect where the model states one; plus the chiller loop. A
:class:`History` keeps one point per ``history_every_s`` for the page's plot (the last values,
the alarms of the whole interval).

:class:`StatusServer` serves them read-only over HTTP from a thread of its own (stdlib
``http.server``): it only ever reads the latest snapshot and a copy of the history, so a slow
or hostile client cannot delay a cycle, and a server that cannot start is logged, never fatal.

- ``/status``: the snapshot as JSON;
- ``/history?spindle=NAME&since=T``: the plot's points after journal time ``T``;
- ``/metrics``: Prometheus text format (``prometheus_client``), from the same snapshot;
- ``/``: a self-contained page (no CDN) plotting speed, S, the offset and the alarms.

Each spindle's **state** is derived in one place, :func:`spindle_state`, a pure function of its
runtime facts (:class:`SpindleFacts`): ``compensating``, ``holding`` or ``not writing``, with one
reason. The snapshot carries it, and the page, ``thermocomp status``, ``/metrics``, MQTT and the
service's status line all show that one; none derives its own.

Times are the journal's (the service's monotonic clock anchored to the wall clock once), so
the page, the journal and the metrics agree, and nothing here reads a clock of its own.
"""

from collections.abc import Iterable, Mapping
from typing import Any

from .endpoint import StatusServer, page_html, start_server
from .history import History
from .metrics import metrics_text
from .spindle import SpindleRuntime
from .states import (
    ALARM_NAMES,
    STATES,
    SpindleFacts,
    SpindleState,
    StateWord,
    alarm_names,
    clock_time,
    finite,
    spindle_facts,
    spindle_state,
    state_of,
    stopped_state,
)

__all__ = [
    "ALARM_NAMES",
    "STATES",
    "History",
    "SpindleFacts",
    "SpindleState",
    "StateWord",
    "StatusServer",
    "alarm_names",
    "clock_time",
    "finite",
    "metrics_text",
    "model_status",
    "page_html",
    "snapshot",
    "spindle_facts",
    "spindle_state",
    "spindle_status",
    "start_server",
    "state_of",
    "stopped_state",
]


def _clean(value: Any) -> Any:
    """JSON-safe: non-finite numbers become null, tuples lists, keys strings."""
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, (int, float)):
        return value if isinstance(value, int) else finite(value)
    if isinstance(value, Mapping):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return str(value)


def _clean_dict(value: Mapping[str, Any]) -> dict[str, Any]:
    """A JSON-safe copy of a mapping (:func:`_clean` of each value)."""
    return {str(k): _clean(v) for k, v in value.items()}


def model_status(rt: SpindleRuntime) -> dict[str, Any]:
    """The model a spindle runs: file, digest, form, ids, speed range and input ranges."""
    model = rt.estimate.with_inputs or rt.estimate.core
    lo, hi = rt.estimate.speed_range_rpm
    ranges = {}
    for c in getattr(getattr(model, "model", model), "inputs", None) or ():
        rng = getattr(c, "trained_range", None)
        if rng is not None and getattr(c, "name", None):
            ranges[c.name] = [finite(rng[0]), finite(rng[1])]
    return {
        "file": str(rt.cfg.model),
        "digest": rt.digest,
        "format": getattr(model, "format", None),
        "form": getattr(model, "form", None),
        "spindle_id": getattr(model, "spindle_id", None),
        "machine_id": getattr(model, "machine_id", None),
        "speed_range_rpm": [finite(lo), finite(hi)],
        "inputs": list(getattr(model, "input_names", ()) or ()),
        "input_ranges": ranges,
    }


def spindle_status(
    rt: SpindleRuntime, now_s: float, state: SpindleState | None = None
) -> dict[str, Any]:
    """One spindle's status at clock time ``now_s`` (the service's clock); ``state`` as the
    service derived it this tick (derived here when not given)."""
    state = state if state is not None else state_of(rt, now_s)
    last = rt.last.as_dict() if rt.last is not None else {}
    alarms = int(rt.alarms)
    offset = rt.offset
    write_age = None if offset.last_write_s is None else max(0.0, now_s - offset.last_write_s)
    journal = rt.journal
    return _clean_dict(
        {
            "name": rt.cfg.name,
            "state": state.state,
            "state_reason": state.reason,
            "compensating": state.compensating,
            "time_s": None if not last else rt.anchor_s + last["time_s"],
            "speed_rpm": last.get("speed_rpm"),
            "elongation_um": last.get("predicted_um"),
            "estimate": last.get("estimate"),
            "offset_target_um": last.get("target_um"),
            "offset_held_um": rt.offset.held_um,
            "offset_read_back_um": offset.last_readback_um,
            "offset_mode": rt.offset.mode.value,
            "writes_offset": rt.writes_offset,
            "last_write_age_s": write_age,
            "last_in_step_age_s": None
            if offset.last_in_step_s is None
            else max(0.0, now_s - offset.last_in_step_s),
            "cold_start_settles_s": (
                None if rt.cold.settle_s is None else rt.anchor_s + rt.cold.settle_s
            ),
            "cutting": last.get("cutting"),
            "cutting_source": last.get("cutting_source"),
            "policy_state": last.get("policy_state"),
            "slew_limit_um_per_s": last.get("slew_limit_um_per_s"),
            "link": rt.link.state.value,
            "alarms": alarm_names(alarms),
            "alarm_bits": alarms,
            "observer": rt.observer_status(),
            "expected_error": last.get("expected_error"),
            "inputs": last.get("inputs", {}),
            "model": model_status(rt),
            "counters": dict(rt.counters),
            "journal": {
                "file": str(journal.path) if journal.path else None,
                "error": journal.error,
                "pending_rows": journal.pending_rows,
            },
        }
    )


def snapshot(
    *,
    version: str,
    pid: int,
    time_s: float,
    uptime_s: float,
    text: str,
    reload_failed: bool,
    spindles: Iterable[dict[str, Any]],
    cooling: dict[str, Any] | None,
) -> dict[str, Any]:
    """The whole service's status: ``time_s`` journal time (epoch seconds), ``text`` the line
    `systemctl status` shows."""
    return _clean_dict(
        {
            "service": "thermocomp",
            "version": version,
            "pid": pid,
            "time_s": time_s,
            "uptime_s": uptime_s,
            "status": text,
            "reload_failed": reload_failed,
            "spindles": list(spindles),
            "cooling": cooling,
            "alarm_names": ALARM_NAMES,
        }
    )
