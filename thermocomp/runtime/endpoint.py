"""The status endpoint: :class:`StatusServer` serves the snapshot, the history, the metrics and
the page read-only over HTTP from a thread of its own (stdlib ``http.server``); it only ever
reads the latest snapshot and a copy of the history, so a slow or hostile client cannot delay a
cycle, and a server that cannot start is logged, never fatal."""

from __future__ import annotations

import hmac
import http.server
import json
import logging
import socket
import socketserver
import threading
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from compensator.io.atomic import write_text

from .config import StatusConfig
from .events import event
from .history import History
from .metrics import metrics_text
from .states import ALARM_NAMES, finite

log = logging.getLogger("thermocomp.runtime")


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
        socketserver_bind = socketserver.TCPServer.server_bind
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


def start_server(cfg: StatusConfig, history: History, url_file: Path) -> StatusServer | None:
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
        write_text(url_file, server.url + "\n")  # replaces a link planted there, never follows it
    except OSError as err:
        log.warning("status: cannot write %s: %s", url_file, err.strerror or err)
    event("status_listening", None, "status on %s", server.url, url=server.url)
    return server
