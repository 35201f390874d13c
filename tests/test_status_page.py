"""The status page (thermocomp/runtime/static/status.html) in a real headless Chromium, against
the real service (`python -m thermocomp run`, simulated machine, 60x time): it plots, updates
live, shows a real alarm by name, asks for the token, says when the service is gone and comes
back. tests/js/status_page.mjs drives the browser and prints one JSON line per phase; the test
acts on the service between phases and asserts on those lines. Every wait is for a condition."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from machine_sim.vcnc import free_port

CHROMIUM = Path("/usr/bin/chromium")
JS = Path(__file__).parent / "js"

pytestmark = [
    pytest.mark.skipif(
        not CHROMIUM.exists(),
        reason="Chromium (/usr/bin/chromium) is not installed: scripts/system-deps.sh installs it",
    ),
    pytest.mark.skipif(
        not (JS / "node_modules" / "playwright-core").is_dir(),
        reason="tests/js/node_modules/playwright-core is missing: scripts/system-deps.sh runs npm ci",
    ),
]

PHASE_TIMEOUT_S = 150.0  # generous: a loaded CI machine; a pass takes seconds


def write_config(tmp_path: Path, model: Path, port: int, access: str = "open") -> Path:
    p = tmp_path / "machine.toml"
    p.write_text(
        f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\ntime_scale = 60\n'
        f'[status]\nport = {port}\nhistory_every_s = 5\naccess = "{access}"\n'
        f'[[spindle]]\nname = "s1"\nmodel = "{model}"\n'
        'adapter = {url = "sim://motorized-27k?program=job-shop-day&seed=1"}\n'
    )
    return p


def start_service(
    cfg: Path, log: Path, env_extra: dict[str, str] | None = None
) -> subprocess.Popen:
    # output to a file, not a pipe nobody reads: a full pipe would stall the service
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env_extra or {})}
    with log.open("a") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "thermocomp", "run", "--config", str(cfg)],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
        )


def wait_url(path: Path, proc: subprocess.Popen, log: Path, timeout: float = 60.0) -> str:
    end = time.monotonic() + timeout
    while time.monotonic() < end and proc.poll() is None:
        if path.exists() and path.read_text().strip():
            return path.read_text().strip()
        time.sleep(0.05)
    pytest.fail(f"the service did not write {path.name}:\n{log.read_text()[-3000:]}")


class Page:
    """status_page.mjs in its own process: its phase lines, read as they come."""

    def __init__(
        self,
        url: str,
        shot: Path,
        scenario: str,
        log: Path,
        env_extra: dict[str, str] | None = None,
    ):
        self.log = log
        self.proc = subprocess.Popen(
            ["node", str(JS / "status_page.mjs"), url, str(shot), scenario],
            cwd=JS,
            stdout=subprocess.PIPE,
            stderr=log.open("w"),
            text=True,
            env={**os.environ, **(env_extra or {})},
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line)
        self.lines.put(None)

    def expect(self, phase: str) -> dict:
        try:
            line = self.lines.get(timeout=PHASE_TIMEOUT_S)
        except queue.Empty:
            pytest.fail(f"no {phase!r} from the browser in {PHASE_TIMEOUT_S:.0f} s")
        if line is None:
            pytest.fail(
                f"the browser script ended before {phase!r}:\n{self.log.read_text()[-3000:]}"
            )
        out = json.loads(line)
        assert out["phase"] == phase, out
        return out

    def finish(self) -> int:
        """The script's exit status, once it has closed its browser."""
        return self.proc.wait(60)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()  # its Chromium goes with it: playwright's pipe closes
        self.proc.wait(30)


def stop(proc: subprocess.Popen | None) -> None:
    if proc is not None and proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def test_page_plots_live_and_shows_a_refused_reload(tmp_path, calibrated_model):
    port = free_port()
    cfg = write_config(tmp_path, calibrated_model, port)
    log = tmp_path / "service.log"
    svc = start_service(cfg, log)
    page = None
    try:
        url = wait_url(tmp_path / "state" / "status.url", svc, log)
        assert url == f"http://127.0.0.1:{port}/"
        shot = tmp_path / "status.png"
        page = Page(url, shot, "alarm", tmp_path / "browser.log")

        live = page.expect("live")
        first, now = live["first"], live["now"]
        assert live["document_status"] == 200 and live["errors"] == []
        assert first["plotted"] > 10 and first["colored_pixels"] > 150  # drawn, not only counted
        assert now["updates"] > first["updates"] and now["points"] > first["points"]
        assert now["plotted"] >= first["plotted"] and now["spindle"] == "s1"
        assert now["state"] == "live" and now["offline"] is None and now["conn"] == "live"
        assert (
            now["spindle_state"] == "compensating"
        )  # the service's state for s1, as the page shows it
        assert "RELOAD_FAILED" not in now["alarms"]
        if not now["alarms"]:
            assert now["banner"] == "no alarms"

        # a real alarm: the service refuses an invalid configuration and says so
        cfg.write_text(cfg.read_text().replace("time_scale = 60", "time_scale = -60"))
        svc.send_signal(signal.SIGHUP)
        alarm = page.expect("alarm")
        assert "RELOAD_FAILED" in alarm["alarms"] and "RELOAD_FAILED" in alarm["banner"]
        assert alarm["banner_bg"] == "rgb(214, 40, 40)"  # the red banner, as rendered
        assert (
            alarm["banded"] > now["banded"] and alarm["red_pixels"] > 0
        )  # its band under the time axis
        assert (
            alarm["state"] == "live" and alarm["points"] > now["points"] and alarm["errors"] == []
        )
        assert png_size(shot) == (1280, 800)
        assert page.finish() == 0, (tmp_path / "browser.log").read_text()[-3000:]
        assert svc.poll() is None  # refused: still running on the old configuration
        assert "reload refused" in log.read_text()
    finally:
        if page is not None:
            page.close()
        stop(svc)


def test_page_asks_for_the_token_and_survives_a_restart(tmp_path, calibrated_model):
    token = "page-test-token-0123456789"
    env = {"THERMOCOMP_STATUS_TOKEN": token}
    port = free_port()
    cfg = write_config(tmp_path, calibrated_model, port, access="token")
    log = tmp_path / "service.log"
    svc = start_service(cfg, log, env)
    page = None
    try:
        url = wait_url(tmp_path / "state" / "status.url", svc, log)
        page = Page(url, tmp_path / "token.png", "token", tmp_path / "browser.log", env)

        refused = page.expect("no_token")
        assert refused["document_status"] == 401  # the service gives nothing without the token
        assert refused["state"] == "unauthorised" and "Not authorised" in refused["offline"]
        assert (
            refused["plotted"] == 0 and refused["updates"] == 0 and refused["colored_pixels"] == 0
        )

        ok = page.expect("token")
        assert ok["document_status"] == 200 and ok["state"] == "live" and ok["offline"] is None
        assert ok["plotted"] > 10 and ok["colored_pixels"] > 150 and ok["errors"] == []

        stop(svc)
        gone = page.expect("unreachable")
        assert gone["conn"] == "not reachable" and "Service not reachable" in gone["offline"]
        assert gone["plotted"] >= ok["plotted"]  # the last data stays on screen
        assert png_size(tmp_path / "token.png") == (1280, 800)

        (tmp_path / "state" / "status.url").unlink(missing_ok=True)
        svc = start_service(cfg, log, env)
        wait_url(tmp_path / "state" / "status.url", svc, log)
        back = page.expect("recovered")
        assert back["state"] == "live" and back["offline"] is None and back["conn"] == "live"
        assert back["plotted"] > 0 and back["errors"] == []
        assert page.finish() == 0, (tmp_path / "browser.log").read_text()[-3000:]
    finally:
        if page is not None:
            page.close()
        stop(svc)


def test_page_says_a_spindle_whose_link_is_down_is_not_writing(tmp_path, calibrated_model):
    port, closed = free_port(), free_port()  # nothing listens on `closed`: a wrong URL
    cfg = write_config(tmp_path, calibrated_model, port)
    cfg.write_text(
        cfg.read_text().replace(
            'adapter = {url = "sim://motorized-27k?program=job-shop-day&seed=1"}',
            f'adapter = {{url = "opc.tcp://127.0.0.1:{closed}/thermocomp/virtual-cnc/", preset = "virtual-cnc", '
            "timeout_s = 1.0}",
        )
    )
    log = tmp_path / "service.log"
    svc = start_service(cfg, log)
    page = None
    try:
        url = wait_url(tmp_path / "state" / "status.url", svc, log)
        page = Page(url, tmp_path / "down.png", "not_writing", tmp_path / "browser.log")
        down = page.expect("not_writing")
        assert down["document_status"] == 200 and down["errors"] == []
        assert down["spindle_state"] == "not writing" and down["spindle_reason"].startswith(
            "link down since "
        )
        assert (
            down["state_bar"].startswith("S1 · NOT WRITING")
            and f"127.0.0.1:{closed}" in down["state_bar"]
        )
        assert down["state_border"] == "rgb(214, 40, 40)"  # red, as rendered
        # the header is the service's line: it counts no spindle that does not write
        assert down["header"].startswith(
            "NOT compensating (0 of 1 spindle(s)); s1 not writing: link down"
        )
        assert "LINK_DOWN" in down["alarms"] and png_size(tmp_path / "down.png") == (1280, 800)
        assert page.finish() == 0, (tmp_path / "browser.log").read_text()[-3000:]
    finally:
        if page is not None:
            page.close()
        stop(svc)
