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

from __future__ import annotations

import collections
import hmac
import http.server
import json
import logging
import math
import socket
import threading
import time
from collections.abc import Iterable, Mapping
from importlib import resources
from typing import Any, Literal
from urllib.parse import parse_qs, urlsplit

from pydantic import BaseModel, ConfigDict, Field

from .events import event
from .spindle import Alarm

log = logging.getLogger("thermocomp.runtime")

ALARM_NAMES = {int(a): a.name for a in Alarm if a.name and a != Alarm.NONE}
"""Alarm bit -> name, as the page and the metrics show them."""


def alarm_names(bits: int) -> list[str]:
    return [name for bit, name in ALARM_NAMES.items() if bits & bit]


def finite(value: Any) -> float | None:
    """A JSON-safe number: None for a missing or non-finite one."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


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


def model_status(rt: Any) -> dict[str, Any]:
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


# -- the spindle's state: one derivation ------------------------------------------------------

STATES = ("compensating", "holding", "not writing")
"""Every state a spindle can be in, best first."""

StateWord = Literal["compensating", "holding", "not writing"]


class SpindleFacts(BaseModel):
    """What a spindle's state is judged on, at one instant; times are journal times [s]."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    now_s: float
    period_s: float = Field(gt=0)
    not_writing_cycles: int = Field(ge=1)
    cycles: int = Field(ge=0, description="cycles run since the runtime was built")
    writes_offset: bool = True
    link_up: bool
    link_state: str = "connected"
    link_down_since_s: float | None = None
    link_error: str | None = None
    last_in_step_s: float | None = Field(
        None,
        description="the last cycle the controller held the offset "
        "aimed at: a write went through, or none was due",
    )
    last_write_s: float | None = None
    since_s: float = Field(
        description="when the runtime began: a spindle never in step counts from here"
    )
    alarm_bits: int = 0
    offset_mode: str = "tracking"
    cold_settle_s: float | None = Field(
        None,
        description="COLD_START_TURNING: when the estimate settles (inf: only at a measurement)",
    )


class SpindleState(BaseModel):
    """One state word and one reason ("" for a plain ``compensating``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    state: StateWord
    reason: str = ""

    @property
    def compensating(self) -> bool:
        return self.state == "compensating"

    @property
    def line(self) -> str:
        return self.state + (f": {self.reason}" if self.reason else "")


def clock_time(t_s: float | None) -> str:
    """A journal time as a person reads it on the shop floor: ``12:03:10 UTC``."""
    if t_s is None or not math.isfinite(t_s):
        return "never"
    return time.strftime("%H:%M:%S UTC", time.gmtime(t_s))


def spindle_state(f: SpindleFacts) -> SpindleState:
    """The spindle's state: the one rule every view shows.

    - ``not writing``: no cycle has run yet (starting); the link is down (refused, lost, timing out); or the
      controller has not held the offset aimed at for more than ``not_writing_cycles`` cycles
      (no write went through while one was due: refused, backed off, cycles failing);
    - ``holding``: the link is up and writes reach the controller, but the offset does not follow
      the estimate now: the machine is not ready (the controller applies its own), the estimate
      step was refused, the speed cannot be read (a sensor fault: last speed held, or idle
      assumed), or a write is pending (refused, backed off) for fewer cycles than that;
    - ``compensating``: otherwise; the reason then names what the estimate rests on when it is
      not the model as calibrated (an unsettled cold start, the speed-only fallback), or the
      chiller where it compensates instead of the offset.
    """
    bits = Alarm(f.alarm_bits)
    if f.cycles == 0 and f.now_s - f.since_s <= f.not_writing_cycles * f.period_s:
        return SpindleState(state="not writing", reason="starting: no cycle has run yet")
    if not f.link_up:
        word = "link down (outage)" if f.link_state == "outage" else "link down"
        since = "" if f.link_down_since_s is None else f" since {clock_time(f.link_down_since_s)}"
        why = f" ({f.link_error})" if f.link_error else ""
        return SpindleState(state="not writing", reason=f"{word}{since}{why}")
    if not f.writes_offset:
        return SpindleState(
            state="compensating",
            reason="by the chiller ([cooling] mode = cooling): no offset is written",
        )
    if bits & Alarm.NOT_READY:
        return SpindleState(
            state="holding",
            reason="machine not ready (off, E-stop or not homed): the "
            "controller applies its own offset",
        )
    ref = f.last_in_step_s if f.last_in_step_s is not None else f.since_s
    behind_s = f.now_s - ref
    if behind_s > f.not_writing_cycles * f.period_s:
        last = (
            "never written"
            if f.last_write_s is None
            else f"last write {clock_time(f.last_write_s)}"
        )
        if bits & Alarm.WRITE_BACKOFF:
            cause = "the controller keeps refusing the offset: writes paused"
        elif bits & Alarm.WRITE_REJECTED:
            cause = "the controller refuses the offset"
        else:
            # a time, not a duration: the line stays the same while nothing changes
            cause = f"no write has gone through since {clock_time(ref)}"
        return SpindleState(state="not writing", reason=f"{cause}; {last}")
    if bits & Alarm.ESTIMATE_REFUSED:
        return SpindleState(
            state="holding", reason="estimate step refused: offset held at its last value"
        )
    if bits & Alarm.IDLE_ASSUMED:
        return SpindleState(state="holding", reason="sensor fault: speed not read, idle assumed")
    if bits & Alarm.SPEED_READ_FAILED:
        return SpindleState(state="holding", reason="sensor fault: speed not read, last speed held")
    if bits & Alarm.WRITE_BACKOFF:
        return SpindleState(
            state="holding",
            reason="the controller refused the offset: writes paused, "
            "offset held at its last value",
        )
    if f.offset_mode == "holding":
        return SpindleState(
            state="holding", reason="offset held at its last value: the write is pending"
        )
    notes = []
    if bits & Alarm.COLD_START_TURNING:
        until = (
            "a measurement is accepted"
            if f.cold_settle_s is None or not math.isfinite(f.cold_settle_s)
            else f"{clock_time(f.cold_settle_s)} or a measurement accepted"
        )
        notes.append(f"estimate unsettled after a cold start on a turning spindle (until {until})")
    if bits & Alarm.INPUT_FALLBACK:
        notes.append("on the speed-only fallback (input fault)")
    return SpindleState(state="compensating", reason="; ".join(notes))


def spindle_facts(rt: Any, now_s: float) -> SpindleFacts:
    """The facts of runtime ``rt`` at clock time ``now_s`` (the service's clock)."""
    a = rt.anchor_s
    at = lambda t: None if t is None else a + t  # noqa: E731 - clock time -> journal time
    cfg = rt.cfg
    return SpindleFacts(
        now_s=a + now_s,
        period_s=cfg.period_s,
        not_writing_cycles=cfg.faults.not_writing_cycles,
        cycles=int(rt.counters.get("cycles", 0)),
        writes_offset=bool(rt.writes_offset),
        link_up=rt.link.up,
        link_state=rt.link.state.value,
        link_down_since_s=at(rt.link.down_since),
        link_error=rt.link.error,
        last_in_step_s=at(rt.offset.last_in_step_s),
        last_write_s=at(rt.offset.last_write_s),
        since_s=a + rt.pace.created_s,
        alarm_bits=int(rt.alarms),
        offset_mode=rt.offset.mode.value,
        cold_settle_s=at(rt.cold.settle_s),
    )


def state_of(rt: Any, now_s: float) -> SpindleState:
    """Runtime ``rt``'s state at clock time ``now_s``."""
    return spindle_state(spindle_facts(rt, now_s))


def spindle_status(rt: Any, now_s: float, state: SpindleState | None = None) -> dict[str, Any]:
    """One spindle's status at clock time ``now_s`` (the service's clock); ``state`` as the
    service derived it this tick (derived here when not given)."""
    state = state if state is not None else state_of(rt, now_s)
    last = rt.last.as_dict() if rt.last is not None else {}
    alarms = int(rt.alarms)
    offset = rt.offset
    write_age = None if offset.last_write_s is None else max(0.0, now_s - offset.last_write_s)
    journal = rt.journal
    return _clean(
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
    return _clean(
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


class History:
    """Per spindle, one point per ``every_s`` over the last ``hours``: time (journal time),
    speed, elongation, offset held (the last values of the interval) and the alarms of the
    whole interval. Written by the service's thread, read (copied) by the server's."""

    FIELDS = ("time_s", "speed_rpm", "elongation_um", "offset_um", "alarm_bits")

    def __init__(self, hours: float, every_s: float):
        self.every_s = every_s
        self._n = max(2, math.ceil(hours * 3600.0 / every_s))
        self._points: dict[str, collections.deque[tuple]] = {}
        self._open: dict[str, list] = {}  # the interval being gathered: [start, point, alarm bits]
        self._lock = threading.Lock()

    def add(
        self,
        name: str,
        time_s: float,
        speed_rpm: float | None,
        elongation_um: float | None,
        offset_um: float | None,
        alarm_bits: int,
    ) -> None:
        acc = self._open.get(name)
        if acc is None or time_s - acc[0] >= self.every_s:
            if acc is not None:
                self._commit(name, acc)
            self._open[name] = acc = [time_s, None, 0]
        acc[1] = (time_s, finite(speed_rpm), finite(elongation_um), finite(offset_um))
        acc[2] |= int(alarm_bits)

    def _commit(self, name: str, acc: list) -> None:
        with self._lock:
            q = self._points.setdefault(name, collections.deque(maxlen=self._n))
            q.append((*acc[1], acc[2]))

    def series(self, name: str, since_s: float | None = None) -> dict[str, list] | None:
        """The points after ``since_s`` (all without), column by column, the open interval's
        latest values last; None for an unknown spindle."""
        with self._lock:
            if name not in self._points and name not in self._open:
                return None
            rows = list(self._points.get(name, ()))
        acc = self._open.get(name)
        if acc is not None and acc[1] is not None:
            rows.append((*acc[1], acc[2]))
        if since_s is not None:
            rows = [r for r in rows if r[0] > since_s]
        return {f: [r[i] for r in rows] for i, f in enumerate(self.FIELDS)}

    def names(self) -> list[str]:
        with self._lock:
            return sorted(set(self._points) | set(self._open))


# -- Prometheus -------------------------------------------------------------------------------


def metrics_text(snap: Mapping[str, Any] | None) -> bytes:
    """The snapshot in Prometheus' text format, through ``prometheus_client``'s own exposition
    (a registry of one collector that reads this snapshot)."""
    from prometheus_client import CollectorRegistry, generate_latest
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, InfoMetricFamily

    class _Snapshot:
        def collect(self):
            up = GaugeMetricFamily("thermocomp_up", "1 while the service runs and has a snapshot")
            up.add_metric([], 0.0 if snap is None else 1.0)
            yield up
            if snap is None:
                return
            info = InfoMetricFamily("thermocomp_build", "the service's version")
            info.add_metric([], {"version": str(snap.get("version"))})
            yield info
            yield _gauge(
                "thermocomp_uptime_seconds",
                "seconds since the service started",
                [],
                [([], snap.get("uptime_s"))],
            )
            yield _gauge(
                "thermocomp_reload_failed",
                "1 while a refused reload keeps the old configuration",
                [],
                [([], 1.0 if snap.get("reload_failed") else 0.0)],
            )
            sp = snap.get("spindles") or []
            gauges = {
                "speed_rpm": ("thermocomp_spindle_speed_rpm", "spindle speed read [rpm]"),
                "elongation_um": (
                    "thermocomp_elongation_micrometres",
                    "estimated thermal elongation S [um]",
                ),
                "offset_target_um": (
                    "thermocomp_offset_target_micrometres",
                    "offset the shaper aims at [um]",
                ),
                "offset_held_um": (
                    "thermocomp_offset_held_micrometres",
                    "offset the controller holds [um]",
                ),
                "last_write_age_s": (
                    "thermocomp_last_write_age_seconds",
                    "seconds since an offset was written",
                ),
            }
            for key, (name, doc) in gauges.items():
                yield _gauge(name, doc, ["spindle"], [([s["name"]], s.get(key)) for s in sp])
            yield _gauge(
                "thermocomp_compensating",
                "1 while the spindle's state is compensating (0: holding "
                "or not writing; the reason is in /status)",
                ["spindle"],
                [([s["name"]], 1.0 if s.get("state") == "compensating" else 0.0) for s in sp],
            )
            state = GaugeMetricFamily(
                "thermocomp_spindle_state",
                "1 for the spindle's state, 0 for the others (every state is listed)",
                labels=["spindle", "state"],
            )
            for s in sp:
                for word in STATES:
                    state.add_metric([s["name"], word], 1.0 if s.get("state") == word else 0.0)
            yield state
            yield _gauge(
                "thermocomp_link_up",
                "1 while the controller link is up",
                ["spindle"],
                [([s["name"]], 1.0 if s.get("link") == "connected" else 0.0) for s in sp],
            )
            yield _gauge(
                "thermocomp_cutting",
                "1 while the tool is taken to cut",
                ["spindle"],
                [([s["name"]], 1.0 if s.get("cutting") else 0.0) for s in sp],
            )
            alarm = GaugeMetricFamily(
                "thermocomp_alarm",
                "1 while the alarm is raised (every alarm is listed, so a 0 means clear)",
                labels=["spindle", "alarm"],
            )
            for s in sp:
                bits = int(s.get("alarm_bits") or 0)
                for bit, aname in ALARM_NAMES.items():
                    alarm.add_metric([s["name"], aname], 1.0 if bits & bit else 0.0)
            yield alarm
            yield _gauge(
                "thermocomp_observer_bias_micrometres",
                "the probe observer's bias [um]",
                ["spindle"],
                [
                    ([s["name"]], (s.get("observer") or {}).get("bias_um"))
                    for s in sp
                    if s.get("observer")
                ],
            )
            # absent for a spindle whose model states no expected error
            stated = [(s["name"], s["expected_error"]) for s in sp if s.get("expected_error")]
            yield _gauge(
                "thermocomp_expected_error_p95_micrometres",
                "the error to expect now, as the fit stated it: 95th percentile of |error| [um]",
                ["spindle"],
                [([name], e.get("p95_abs_um")) for name, e in stated],
            )
            yield _gauge(
                "thermocomp_expected_error_rms_micrometres",
                "the error to expect now, as the fit stated it: RMS [um]",
                ["spindle"],
                [([name], e.get("rms_um")) for name, e in stated],
            )
            yield _gauge(
                "thermocomp_expected_error_bound_micrometres",
                "max_expected_error_um: above it EXPECTED_ERROR_HIGH [um]",
                ["spindle"],
                [([name], e.get("bound_um")) for name, e in stated],
            )
            yield _gauge(
                "thermocomp_input_value",
                "the link's extra inputs (temperatures, load)",
                ["spindle", "input"],
                [([s["name"], k], v) for s in sp for k, v in (s.get("inputs") or {}).items()],
            )
            names = sorted({k for s in sp for k in (s.get("counters") or {})})
            for key in names:
                c = CounterMetricFamily(
                    f"thermocomp_{key}", f"count of {key.replace('_', ' ')}", labels=["spindle"]
                )
                for s in sp:
                    if key in (s.get("counters") or {}):
                        c.add_metric([s["name"]], float(s["counters"][key]))
                yield c
            cool = snap.get("cooling")
            if cool:
                yield _gauge(
                    "thermocomp_chiller_setpoint_celsius",
                    "set point sent to the chiller [degC]",
                    [],
                    [([], cool.get("setpoint_c"))],
                )
                yield _gauge(
                    "thermocomp_chiller_supply_celsius",
                    "chiller supply temperature read [degC]",
                    [],
                    [([], cool.get("supply_c"))],
                )
                yield _gauge(
                    "thermocomp_chiller_alarm",
                    "1 while the chiller loop has an alarm",
                    [],
                    [([], 1.0 if cool.get("alarm") else 0.0)],
                )

    registry = CollectorRegistry(auto_describe=False)
    registry.register(_Snapshot())
    return generate_latest(registry)


def _gauge(name: str, doc: str, labels: list[str], values: Iterable[tuple[list[str], Any]]):
    from prometheus_client.core import GaugeMetricFamily

    g = GaugeMetricFamily(name, doc, labels=labels)
    for lab, v in values:
        x = finite(v)
        if x is not None:  # an unknown value is absent, not 0
            g.add_metric(lab, x)
    return g


# -- HTTP ---------------------------------------------------------------------------------------


def page_html() -> bytes:
    """The status page: one self-contained HTML file shipped with the package."""
    return resources.files("thermocomp.runtime").joinpath("static/status.html").read_bytes()


class StatusServer:
    """The read-only HTTP endpoint, on a thread of its own. ``publish`` hands it the latest
    snapshot; nothing it does can block or stop the service."""

    def __init__(self, bind: str, port: int, *, token: str | None, history: History):
        self.token = token
        self.history = history
        self._snapshot: dict[str, Any] | None = None
        self._httpd: http.server.ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None
        self.bind, self.port = bind, port

    @property
    def url(self) -> str:
        host = self.bind if ":" not in self.bind else f"[{self.bind}]"
        if self.bind in ("0.0.0.0", "::", ""):
            host = "127.0.0.1"
        return f"http://{host}:{self.port}/"

    def publish(self, snap: dict[str, Any]) -> None:
        self._snapshot = snap  # one reference swap: the server's thread sees this one or the last

    def start(self) -> StatusServer:
        server = self

        class Handler(_Handler):
            owner = server

        cls = _V6Server if ":" in self.bind else _Server
        self._httpd = cls((self.bind, self.port), Handler)
        self.port = self._httpd.server_address[1]
        self._thread = threading.Thread(
            target=self._httpd.serve_forever,
            name="thermocomp-status",
            kwargs={"poll_interval": 0.5},
            daemon=True,
        )
        self._thread.start()
        return self

    def close(self) -> None:
        httpd, self._httpd = self._httpd, None
        if httpd is not None:
            httpd.shutdown()
            httpd.server_close()
        if self._thread is not None:
            self._thread.join(5.0)


class _Server(http.server.ThreadingHTTPServer):
    daemon_threads = True

    def server_bind(self) -> None:
        # HTTPServer's own looks the host name up (getfqdn): a bind to a LAN address with no
        # DNS would hold the service's start
        socketserver_bind = http.server.socketserver.TCPServer.server_bind
        socketserver_bind(self)
        self.server_name, self.server_port = (
            str(self.server_address[0]),
            int(self.server_address[1]),
        )

    def handle_error(self, request: Any, client_address: Any) -> None:
        # a broken client is one debug line, never a traceback on stderr
        log.debug("status: request from %s failed", client_address, exc_info=True)  # noqa: LOG014 - socketserver calls this inside its handler


class _V6Server(_Server):
    address_family = socket.AF_INET6


class _Handler(http.server.BaseHTTPRequestHandler):
    owner: StatusServer
    server_version = "thermocomp"
    sys_version = ""
    timeout = 10.0  # a client that stalls holds one thread of the server, never the service

    def log_message(self, format: str, *args: Any) -> None:
        # the request line may carry ?token=: never log a query
        path = urlsplit(getattr(self, "path", "") or "").path[:100]  # unset on a malformed request
        log.debug("status: %s: %s %s", self.address_string(), getattr(self, "command", None), path)

    def _allowed(self, query: dict[str, list[str]]) -> bool:
        token = self.owner.token
        if token is None:
            return True
        given = self.headers.get("Authorization", "")
        given = given[7:].strip() if given.lower().startswith("bearer ") else ""
        given = given or (query.get("token") or [""])[0]
        return hmac.compare_digest(given.encode(), token.encode())

    def _send(self, code: int, body: bytes, ctype: str) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, code: int, data: Any) -> None:
        self._send(code, json.dumps(data, allow_nan=False).encode(), "application/json")

    def do_HEAD(self) -> None:
        self.do_GET()

    def do_GET(self) -> None:
        try:
            url = urlsplit(self.path)
            query = parse_qs(url.query)
            if not self._allowed(query):
                # a body, so that a browser shows what to do rather than an empty error page
                body = b"thermocomp status: a token is needed (Authorization: Bearer, or ?token= for the page)\n"
                self.send_response(401)
                self.send_header("WWW-Authenticate", 'Bearer realm="thermocomp"')
                self.send_header("Content-Type", "text/plain; charset=utf-8")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                if self.command != "HEAD":
                    self.wfile.write(body)
                return
            snap = self.owner._snapshot
            if url.path in ("/", "/index.html"):
                self._send(200, page_html(), "text/html; charset=utf-8")
            elif url.path == "/status":
                if snap is None:
                    self._json(503, {"error": "no cycle run yet"})
                else:
                    self._json(200, snap)
            elif url.path == "/history":
                self._history(query, snap)
            elif url.path == "/metrics":
                self._send(200, metrics_text(snap), "text/plain; version=0.0.4; charset=utf-8")
            else:
                self._json(404, {"error": f"no such page: {url.path[:100]}"})
        except (BrokenPipeError, ConnectionResetError):
            pass  # the client went away
        except Exception as err:  # noqa: BLE001 - a status page never takes anything down
            log.warning("status: %s failed: %s", urlsplit(self.path).path[:100], err)
            try:
                self._json(500, {"error": type(err).__name__})
            except OSError:
                pass

    def _history(self, query: dict[str, list[str]], snap: dict[str, Any] | None) -> None:
        hist = self.owner.history
        names = hist.names()
        name = (query.get("spindle") or [""])[0] or (names[0] if len(names) == 1 else "")
        since = None
        if query.get("since"):
            since = finite(query["since"][0])
            if since is None:
                self._json(400, {"error": "since: a number (journal time, s)"})
                return
        series = hist.series(name, since) if name else None
        if series is None:
            self._json(404, {"error": f"no spindle {name[:50]!r}; spindles: {', '.join(names)}"})
            return
        # the snapshot's time as latest_s: the series' own time_s column follows
        self._json(
            200,
            {
                "spindle": name,
                "every_s": hist.every_s,
                "latest_s": None if snap is None else snap.get("time_s"),
                "alarm_names": ALARM_NAMES,
                **series,
            },
        )


def start_server(cfg: Any, history: History, url_file: Any) -> StatusServer | None:
    """The endpoint of ``[status]``, or None: disabled, or it cannot start (logged as
    ``status_failed``; compensation does not need it). Its URL goes to ``url_file``."""
    if not cfg.enabled:
        return None
    token = cfg.token()  # a missing token is a configuration error, said at start
    if token is None and cfg.bind not in ("127.0.0.1", "::1", "localhost"):
        log.warning(
            "status: serving %s:%d without a token: anyone on the network can read it",
            cfg.bind,
            cfg.port,
        )
    try:
        server = StatusServer(cfg.bind, cfg.port, token=token, history=history).start()
    except OSError as err:
        event(
            "status_failed",
            None,
            "status endpoint %s:%d not started: %s; compensation goes on",
            cfg.bind,
            cfg.port,
            err.strerror or err,
            level=logging.ERROR,
            error=str(err)[:200],
        )
        return None
    try:
        url_file.write_text(server.url + "\n", encoding="utf-8")
    except OSError as err:
        log.warning("status: cannot write %s: %s", url_file, err.strerror or err)
    event("status_listening", None, "status on %s", server.url, url=server.url)
    return server
