"""``[mqtt]``: the service's status on a broker, for the shop floor's dashboards (paho-mqtt).

Topics under the configured prefix, JSON payloads, all retained so a dashboard that connects
later sees the latest at once:

- ``<topic>/status``: the whole snapshot (:func:`.status.snapshot`);
- ``<topic>/spindle/<name>``: each spindle's part of it (S, the offsets, the alarms, the error
  to expect, ...);
- ``<topic>/availability``: ``online`` once connected, ``offline`` at a clean stop, and
  ``offline`` from the broker itself (the last will) when the service dies or goes silent for
  1.5 ``keepalive_s``.

A clean stop publishes one last status before ``offline``: each spindle ``stopped``, with the
offset the control holds ("stopped: the control holds X µm"), retained. After a kill the
spindle topics keep the last status sent while it ran; ``offline`` (the will) says it is stale.

Publishing never waits on the network: paho's own thread connects, reconnects with an
exponential back-off (1 s doubling to :data:`RECONNECT_MAX_S`) and sends what :meth:`publish`
hands it. While disconnected nothing is queued (a stale status is worth nothing later); the
snapshots skipped are counted. A broker that is down, a name that does not resolve or refused
credentials are one ``mqtt_lost`` event per outage; compensation never notices.
"""

from __future__ import annotations

import json
import logging
import socket
import sys
import threading
from typing import Any

import paho.mqtt.client as paho
from paho.mqtt.properties import Properties
from paho.mqtt.reasoncodes import ReasonCode

from compensator.errors import ConfigError

from .config import MqttConfig
from .events import event

log = logging.getLogger("thermocomp.runtime")
paho_log = logging.getLogger("thermocomp.runtime.paho")  # paho's own lines, in our log
# ...but not the error paho logs on each reconnection attempt: an outage is one event here
paho_log.addFilter(lambda r: not str(r.msg).startswith("Client is not connected"))

RECONNECT_MAX_S = 30
"""Longest wait between two connection attempts [s]: a broker back up is found within this."""
MAX_QUEUED = 256
"""Messages paho may hold unsent or unacknowledged (a slow broker); more are dropped, counted."""
CLOSE_WAIT_S = 2.0
"""How long :meth:`MqttPublisher.close` waits for ``offline`` to be acknowledged [s]."""
WARN_EVERY_S = 600.0
"""At most one warning per this many seconds of the service's clock for a failed publish [s]."""


class MqttPublisher:
    """The service's status on ``cfg``'s broker; :meth:`start`, then :meth:`publish` each tick."""

    def __init__(self, cfg: MqttConfig):
        self.cfg = cfg
        self.client: paho.Client | None = None
        self.connected = False  # set by paho's thread, read by the service's
        self.published = 0  # snapshots handed to paho
        self.skipped = 0  # snapshots due while disconnected
        self.dropped = 0  # messages paho refused (queue full, bad payload)
        self._outage: str | None = None  # why we are not connected, once logged
        self._connects = 0  # connections made (paho's thread): each wants a publish at once
        self._due_conn = -1  # the connection count at the last publish (or skip)
        self._down_since: float | None = None  # service clock of the first publish not connected
        self.silent_after_s = 1.5 * cfg.keepalive_s
        """Not connected this long without a word from paho: an outage all the same."""
        self._next_s = 0.0  # the service clock's time of the next periodic publish [s]
        self._alarms: Any = None  # the alarms last published
        self._warn_s: float | None = None
        self._closing = False

    @property
    def availability(self) -> str:
        return f"{self.cfg.topic}/availability"

    def start(self) -> MqttPublisher:
        """Configure the client and let paho's thread connect. Raises ConfigError for an
        unreadable password or CA file (said at start, like the status token); never for the
        network: a broker that is down or not found is retried in the background."""
        cfg = self.cfg
        client_id = cfg.client_id or f"thermocomp-{socket.gethostname()}"
        c = paho.Client(
            paho.CallbackAPIVersion.VERSION2, client_id=client_id, protocol=paho.MQTTv311
        )
        c.enable_logger(paho_log)
        c.will_set(self.availability, "offline", qos=cfg.qos, retain=True)
        if cfg.username is not None:
            c.username_pw_set(cfg.username, cfg.password())
        if cfg.tls:
            try:
                c.tls_set(ca_certs=None if cfg.ca_file is None else str(cfg.ca_file))
            except (OSError, ValueError) as err:  # ssl.SSLError is an OSError
                raise ConfigError(f"mqtt.ca_file {cfg.ca_file}: {err}") from err
        c.reconnect_delay_set(min_delay=1, max_delay=RECONNECT_MAX_S)
        c.max_queued_messages_set(MAX_QUEUED)
        c.on_connect, c.on_disconnect = self._on_connect, self._on_disconnect
        c.on_connect_fail = self._on_fail
        c.connect_async(cfg.host, cfg.port, keepalive=cfg.keepalive_s)  # no I/O here
        log.info("mqtt: connecting to %s:%d as %s", cfg.host, cfg.port, client_id)
        self.client = c
        c.loop_start()
        return self

    # -- paho's thread ------------------------------------------------------------------------

    def _on_connect(
        self,
        client: paho.Client,
        userdata: Any,
        flags: paho.ConnectFlags,
        reason: ReasonCode,
        properties: Properties | None,
    ) -> None:
        if reason.is_failure:  # e.g. "Not authorized": paho retries, we say it once
            self._lost(f"refused: {reason}")
            return
        self.connected, self._outage = True, None
        self._connects += 1  # after `connected`: a publish that sees the new count can send
        client.publish(self.availability, "online", qos=self.cfg.qos, retain=True)
        event(
            "mqtt_connected",
            None,
            "mqtt: connected to %s:%d",
            self.cfg.host,
            self.cfg.port,
            host=self.cfg.host,
            port=self.cfg.port,
        )

    def _on_disconnect(
        self,
        client: paho.Client,
        userdata: Any,
        flags: paho.DisconnectFlags,
        reason: ReasonCode,
        properties: Properties | None,
    ) -> None:
        was, self.connected = self.connected, False
        if was and not self._closing:
            self._lost(f"connection lost: {reason}")

    def _on_fail(self, client: paho.Client, userdata: Any) -> None:
        err = sys.exc_info()[1]  # paho calls this inside its `except OSError`: the cause
        self._lost(f"cannot connect: {err or 'unreachable'}")

    def _lost(self, why: str) -> None:
        """One event per outage (the first reason); a different reason later only at debug."""
        if self._closing:
            return
        if self._outage is None:
            cfg = self.cfg
            event(
                "mqtt_lost",
                None,
                "mqtt: %s:%d %s; retrying, compensation goes on",
                cfg.host,
                cfg.port,
                why,
                level=logging.WARNING,
                host=cfg.host,
                port=cfg.port,
                reason=why[:200],
            )
        elif why != self._outage:
            log.debug("mqtt: %s", why)
        self._outage = why

    # -- the service's thread -----------------------------------------------------------------

    def publish(self, snapshot: dict[str, Any], now_s: float) -> None:
        """Hand ``snapshot`` to paho if it is due: the first call, every ``publish_every_s`` of
        the service clock ``now_s`` [s], just after a (re)connection, or when the alarms or a
        spindle's state change.
        Never blocks, never raises."""
        if self.client is None:
            return
        try:
            # a new alarm or a new state (compensating, holding, not writing) goes out at once
            alarms = (
                [
                    (s.get("name"), s.get("alarms"), s.get("state"))
                    for s in snapshot.get("spindles") or ()
                ],
                (snapshot.get("cooling") or {}).get("alarm"),
            )
            conn = self._connects
            if conn == self._due_conn and now_s < self._next_s and alarms == self._alarms:
                return
            self._due_conn, self._alarms = conn, alarms
            self._next_s = now_s + self.cfg.publish_every_s
            if not self.connected:  # paho would queue it for later, when it is stale
                self.skipped += 1
                if self._down_since is None:
                    self._down_since = now_s
                elif self._outage is None and now_s - self._down_since > self.silent_after_s:
                    # a broker that took the TCP connection and never answers calls no callback
                    self._lost(f"no answer within {now_s - self._down_since:.0f} s")
                return
            self._down_since = None
            self._send("status", snapshot, now_s)
            for sp in snapshot.get("spindles") or ():
                self._send(f"spindle/{sp['name']}", sp, now_s)
            self.published += 1
        except Exception as err:  # noqa: BLE001 - the status never stops the offset
            self._warn(now_s, "mqtt: status not published: %s", err)

    def _send(self, sub: str, payload: Any, now_s: float) -> None:
        assert self.client is not None
        body = json.dumps(payload, allow_nan=False, separators=(",", ":"))
        info = self.client.publish(f"{self.cfg.topic}/{sub}", body, qos=self.cfg.qos, retain=True)
        # NO_CONN: the connection dropped just now; at qos 1 paho sends it again on reconnect
        if info.rc not in (paho.MQTT_ERR_SUCCESS, paho.MQTT_ERR_NO_CONN):
            self.dropped += 1
            self._warn(
                now_s,
                "mqtt: %s not queued: %s (%d dropped so far)",
                sub,
                paho.error_string(info.rc),
                self.dropped,
            )

    def _warn(self, now_s: float, msg: str, *args: Any) -> None:
        if self._warn_s is None or now_s - self._warn_s >= WARN_EVERY_S:
            self._warn_s = now_s
            log.warning(msg, *args)
        else:
            log.debug(msg, *args)

    def close(self) -> None:
        """``offline`` on availability (waiting up to :data:`CLOSE_WAIT_S` for it), then a clean
        disconnect (the broker drops the last will). Never raises."""
        c, self.client = self.client, None
        if c is None:
            return
        self._closing = True
        try:
            if self.connected:
                info = c.publish(self.availability, "offline", qos=self.cfg.qos, retain=True)
                info.wait_for_publish(CLOSE_WAIT_S)
            c.disconnect()
        except Exception as err:  # noqa: BLE001 - stopping goes on; the will says offline
            log.debug("mqtt: offline not sent: %s", err)
        # paho's thread may sit in a connect attempt (up to its 5 s timeout, or a slow name
        # lookup): stop it without waiting for more than a moment
        stop = threading.Thread(target=c.loop_stop, name="thermocomp-mqtt-stop", daemon=True)
        stop.start()
        stop.join(CLOSE_WAIT_S)
        self.connected = False
