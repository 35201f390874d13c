#!/usr/bin/env python3
"""Screenshots of the status page in its three telling states, for the docs:

- ``status-compensating.png``: the service on the virtual CNC (``thermocomp virtual-cnc``, a
  job-shop day, cycle start pressed once the service runs, so its cold start is at rest);
- ``status-link-down.png``: the service pointed at an OPC UA endpoint where nothing listens (a
  wrong URL): not writing, link down, and why;
- ``status-cold-start.png``: the virtual CNC turning at 18000 rpm for half an hour (simulated)
  before the service starts with no saved state: COLD_START_TURNING.

Each runs the real service (``thermocomp run``, 60x simulated time) and the virtual CNC on free
loopback ports in a temporary directory, waits until ``/status`` says what the picture is to
show, then has headless Chromium (Debian's /usr/bin/chromium) take the page at 1280x800.

Usage: python scripts/status-screenshots.py [--out docs] [--chromium /usr/bin/chromium]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "examples" / "linuxcnc" / "spindle-model.json"  # a model of the virtual spindle
TIME_SCALE = 60
WAIT_S = 180.0  # generous: a loaded machine; each state comes within seconds

WARM_UP = """%
(a spindle already warm and turning when the service starts)
S18000 M3
G4 P7200
M5
M2
%
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def thermocomp(args: list[str], log: Path) -> subprocess.Popen:
    with log.open("a") as out:  # a file, not a pipe nobody reads
        return subprocess.Popen(
            [sys.executable, "-m", "thermocomp", *args],
            cwd=ROOT,
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def wait(what: str, cond: Callable[[], object], procs: list[subprocess.Popen], log: Path) -> object:
    end = time.monotonic() + WAIT_S
    while time.monotonic() < end:
        for p in procs:
            if p.poll() is not None:
                sys.exit(
                    f"{what}: a process stopped (exit {p.returncode}):\n{log.read_text()[-3000:]}"
                )
        try:
            got = cond()
        except OSError:
            got = None
        if got:
            return got
        time.sleep(0.25)
    sys.exit(f"timed out waiting for {what}:\n{log.read_text()[-3000:]}")


def listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def status(url: str) -> dict:
    with urllib.request.urlopen(url + "status", timeout=5) as r:
        return json.loads(r.read())


def points(url: str) -> int:
    with urllib.request.urlopen(url + "history?spindle=s1", timeout=5) as r:
        return len(json.loads(r.read())["time_s"])


def service_config(d: Path, opc_port: int, status_port: int) -> Path:
    p = d / "machine.toml"
    p.write_text(
        f'state_dir = "{d / "state"}"\nwatchdog = false\ntime_scale = {TIME_SCALE}\n'
        f"[status]\nport = {status_port}\nhistory_every_s = 20\n"
        f'[[spindle]]\nname = "s1"\nmodel = "{MODEL}"\nperiod_s = 5.0\n'
        f'adapter = {{url = "opc.tcp://127.0.0.1:{opc_port}/thermocomp/virtual-cnc/", '
        'preset = "virtual-cnc", timeout_s = 2.0}\n'
        "[spindle.shaping]\nmax_offset_um = 60.0\nmax_rate_um_per_s = 2.0\n"
    )
    return p


def shoot(chromium: str, url: str, out: Path, d: Path) -> None:
    """The page as a browser shows it after a few polls (virtual time: no wall-clock wait), its
    plot over the last hour."""
    subprocess.run(
        [
            chromium,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--no-proxy-server",
            f"--user-data-dir={d / 'chromium'}",
            "--window-size=1280,800",
            "--virtual-time-budget=10000",
            f"--screenshot={out}",
            url + "?h=1",
        ],
        check=True,
        capture_output=True,
        timeout=120,
    )
    print(f"wrote {out}")


def scenario(
    name: str,
    out: Path,
    chromium: str,
    *,
    vcnc: list[str] | None,
    ready: Callable[[str], bool],
    before_service_s: float = 0.0,
) -> None:
    with tempfile.TemporaryDirectory(prefix=f"thermocomp-{name}-") as tmp:
        d = Path(tmp)
        log = d / "processes.log"
        (d / "warm-up.ngc").write_text(WARM_UP)
        opc_port, status_port = free_port(), free_port()
        procs: list[subprocess.Popen] = []
        try:
            if vcnc is not None:
                args = [a.replace("{dir}", str(d)) for a in vcnc]
                procs.append(
                    thermocomp(
                        [
                            "virtual-cnc",
                            "--port",
                            str(opc_port),
                            "--time-scale",
                            str(TIME_SCALE),
                            *args,
                        ],
                        log,
                    )
                )
                wait("the virtual CNC", lambda: listening(opc_port), procs, log)
                time.sleep(
                    before_service_s
                )  # the machine runs (and warms) before the service starts
            procs.append(
                thermocomp(["run", "--config", str(service_config(d, opc_port, status_port))], log)
            )
            url = f"http://127.0.0.1:{status_port}/"
            wait(f"{name}: the status to show it", lambda: ready(url), procs, log)
            shoot(chromium, url, out, d)
        finally:
            for p in reversed(procs):
                stop(p)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--out", type=Path, default=ROOT / "docs", help="folder for the PNGs (default docs/)"
    )
    ap.add_argument("--chromium", default="/usr/bin/chromium", help="the headless browser")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    def spindle(url: str) -> dict:
        return status(url)["spindles"][0]

    scenario(
        "compensating",
        args.out / "status-compensating.png",
        args.chromium,
        vcnc=["--program", "job-shop-day", "--seed", "3", "--wait-start", "--start-delay", "4"],
        ready=lambda url: (
            spindle(url)["state"] == "compensating"
            and not spindle(url)["alarms"]
            and (spindle(url)["speed_rpm"] or 0) > 1000
            and points(url) > 60
        ),
    )
    scenario(
        "link-down",
        args.out / "status-link-down.png",
        args.chromium,
        vcnc=None,
        ready=lambda url: (
            spindle(url)["state"] == "not writing"
            and spindle(url)["link"] != "connected"
            and points(url) > 10
        ),
    )
    scenario(
        "cold-start",
        args.out / "status-cold-start.png",
        args.chromium,
        vcnc=["--program", "{dir}/warm-up.ngc"],
        before_service_s=30.0,
        ready=lambda url: "COLD_START_TURNING" in spindle(url)["alarms"] and points(url) > 20,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
