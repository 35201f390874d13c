"""The service's status, published each tick: each spindle's state (derived once), the snapshot,
the history, the HTTP endpoint and the MQTT broker. Nothing here is needed to compensate: a part
that cannot start is logged and left out, and a failure to publish never stops a cycle."""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from compensator.errors import ConfigError

from .config import RuntimeConfig
from .events import event
from .spindle import SpindleRuntime
from .status import (
    History,
    SpindleState,
    StatusServer,
    snapshot,
    spindle_status,
    start_server,
    state_of,
    stopped_state,
)

if TYPE_CHECKING:  # paho is imported only where MQTT is configured
    from .mqtt import MqttPublisher

log = logging.getLogger("thermocomp.runtime")

PUBLISH_WARN_EVERY_S = 600.0
"""A status that keeps failing to publish: one traceback per this many seconds, not per tick."""


class Publisher:
    """Each spindle's state, the snapshot built from it, and where it goes."""

    def __init__(self) -> None:
        self.history: History | None = None
        self.server: StatusServer | None = None
        self.mqtt: MqttPublisher | None = None
        self.snapshot: dict[str, Any] | None = None
        self.states: dict[str, SpindleState] = {}  # each spindle's state, derived once per tick
        self.not_started: list[str] = []  # optional parts that could not start (status, mqtt)
        self._warned = -math.inf

    def start(self, cfg: RuntimeConfig) -> None:
        """The history, the status endpoint and the MQTT publisher of the configuration."""
        st = cfg.status
        self.history = History(st.history_h, st.history_every_s)
        try:
            self.server = start_server(st, self.history, cfg.state_dir / "status.url")
        except ConfigError as err:  # a token missing: no endpoint (never an open one instead)
            self.not_started.append("status endpoint")
            event(
                "status_failed",
                None,
                "status endpoint not started: %s; compensation goes on",
                err,
                level=logging.ERROR,
                error=str(err)[:200],
            )
        if cfg.mqtt is not None and cfg.mqtt.enabled:
            from .mqtt import MqttPublisher

            try:
                self.mqtt = MqttPublisher(cfg.mqtt).start()
            except ConfigError as err:
                self.not_started.append("mqtt")
                event(
                    "mqtt_lost",
                    None,
                    "mqtt not started: %s; compensation goes on",
                    err,
                    level=logging.ERROR,
                    reason=str(err)[:200],
                )

    def derive(
        self, spindles: Mapping[str, SpindleRuntime], now: float, *, stopped: bool = False
    ) -> dict[str, SpindleState]:
        """Each spindle's state at ``now`` (:func:`.states.spindle_state`, the one derivation;
        ``stopped``: what a clean stop leaves, :func:`.states.stopped_state`); a change is one
        ``spindle_state`` event."""
        states = {
            name: stopped_state(rt) if stopped else state_of(rt, now)
            for name, rt in spindles.items()
        }
        for name, st in states.items():
            before = self.states.get(name)
            if before is None or before.state != st.state:
                event(
                    "spindle_state",
                    name,
                    "%s: %s",
                    name,
                    st.line,
                    level=logging.INFO
                    if st.compensating or before is None or st.state == "stopped"
                    else logging.WARNING,
                    state=st.state,
                    reason=st.reason,
                    was=None if before is None else before.state,
                )
        self.states = states
        return states

    def publish(
        self,
        spindles: Mapping[str, SpindleRuntime],
        now: float,
        *,
        text: Callable[[], str],
        time_s: float,
        uptime_s: float,
        reload_failed: bool,
        cooling: dict[str, Any] | None,
        stopped: bool = False,
    ) -> None:
        """Derive the states, build the snapshot and hand it to the endpoint, the history and
        the broker. ``text``: the status line, read once the states are derived. ``stopped``:
        the last one, as the service stops cleanly (each spindle ``stopped``, with the offset
        the control holds; retained on the broker)."""
        states = self.derive(spindles, now, stopped=stopped)
        if self.server is None and self.mqtt is None and self.history is None:
            return
        sp = [spindle_status(rt, now, states[name]) for name, rt in spindles.items()]
        snap = snapshot(
            version=_version(),
            pid=os.getpid(),
            time_s=time_s,
            uptime_s=uptime_s,
            text=text(),
            reload_failed=reload_failed,
            spindles=sp,
            cooling=cooling,
        )
        self.snapshot = snap
        if self.history is not None:
            for s in sp:
                if s["time_s"] is not None:
                    self.history.add(
                        s["name"],
                        s["time_s"],
                        s["speed_rpm"],
                        s["elongation_um"],
                        s["offset_held_um"],
                        s["alarm_bits"],
                    )
        if self.server is not None:
            self.server.publish(snap)
        if self.mqtt is not None:
            self.mqtt.publish(snap, now)

    def failed(self, now: float, err: Exception) -> None:
        """A publish that failed: one traceback per ``PUBLISH_WARN_EVERY_S``, not per tick."""
        if now - self._warned >= PUBLISH_WARN_EVERY_S:
            self._warned = now
            log.error("status not published: %s", err, exc_info=err)

    def close(self, url_file: Path) -> None:
        """Stop the endpoint (its URL file goes with it: `status --config` must not find a port
        that is free now) and the MQTT publisher."""
        if self.server is not None:
            self.server.close()
            self.server = None
            try:
                url_file.unlink(missing_ok=True)
            except OSError:
                pass
        if self.mqtt is not None:
            self.mqtt.close()
            self.mqtt = None


def _version() -> str:
    from thermocomp import __version__

    return __version__
