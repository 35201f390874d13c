"""The runtime: cycle compute time, read->write latency at 10 Hz over loopback OPC UA, and the
service's CPU and memory at 1 Hz. Targets (issue 6): p99 <= 10 ms; CPU <= 3 % of one core at
1 Hz; peak RSS <= 120 MB. Run: .venv/bin/python bench/bench_runtime.py
"""

from __future__ import annotations

import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from conftest import rich_form  # noqa: E402

from cnc_adapters import Adapter  # noqa: E402
from compensator.io import save_model  # noqa: E402
from machine_sim.vcnc import free_port  # noqa: E402
from thermocomp.runtime import SpindleRuntime  # noqa: E402
from thermocomp.runtime.config import load_config  # noqa: E402


class ConstantSpeed(Adapter):
    """An adapter with no I/O at all: isolates the compute part of a cycle."""

    name = "constant"

    def _connect(self) -> None:
        pass

    def _disconnect(self) -> None:
        pass

    def _read_speed_raw(self) -> float:
        return 15000.0

    def _write_offset_raw(self, value: float) -> None:
        pass


def config(tmp: Path, adapter: str, period: float) -> Path:
    save_model(tmp / "m.json", rich_form())
    p = tmp / "c.toml"
    p.write_text(
        f'state_dir = "{tmp / "state"}"\nwatchdog = false\n[[spindle]]\nname = "s"\n'
        f'model = "{tmp / "m.json"}"\nperiod_s = {period}\nadapter = {adapter}\n'
        "[spindle.shaping]\ndeadband_um = 0.0\nmax_rate_um_per_s = 100.0\n"
    )
    return p


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> dict:
    out: dict = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cfg = load_config(config(tmp, '{url = "sim://"}', 1.0))
        t = {"now": 0.0}
        rt = SpindleRuntime(
            cfg.spindle[0],
            cfg.state_dir,
            cfg.journal_path,
            clock=lambda: t["now"],
            adapter=ConstantSpeed(),
        )
        ms = []
        for _ in range(20000):
            t["now"] += 1.0
            t0 = time.perf_counter()
            rt.cycle()
            ms.append((time.perf_counter() - t0) * 1e3)
        rt.close()
        out["compute_ms_p50"], out["compute_ms_p99"] = np.percentile(ms, [50, 99])

        port = free_port()
        server = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "thermocomp",
                "virtual-cnc",
                "--port",
                str(port),
                "--time-scale",
                "1",
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        server.stdout.readline()
        url = f"opc.tcp://127.0.0.1:{port}/thermocomp/virtual-cnc/"
        try:
            cfg = load_config(
                config(
                    tmp,
                    f'{{url = "{url}", preset = "virtual-cnc", verify_writes = "deferred"}}',
                    0.1,
                )
            )
            rt = SpindleRuntime(cfg.spindle[0], cfg.state_dir, cfg.journal_path)
            lat, r2w = [], []
            next_t = time.monotonic()
            for _ in range(300):  # 30 s at 10 Hz; every cycle writes (deadband 0)
                t0 = time.perf_counter()
                rec = rt.cycle()
                lat.append((time.perf_counter() - t0) * 1e3)
                r2w.append(rec["read_to_write_ms"])
                next_t += 0.1
                time.sleep(max(0.0, next_t - time.monotonic()))
            rt.close()
            out["cycle_10hz_ms_p50"], out["cycle_10hz_ms_p99"] = np.percentile(lat, [50, 99])
            out["read_to_write_10hz_ms_p50"], out["read_to_write_10hz_ms_p99"] = np.percentile(
                r2w, [50, 99]
            )
            out["cycle_10hz_written"] = bool(rec["written"])

            svc_cfg = config(
                tmp, f'{{url = "{url}", preset = "virtual-cnc", verify_writes = "deferred"}}', 1.0
            )
            svc = subprocess.Popen(
                [sys.executable, "-m", "thermocomp", "run", "--config", str(svc_cfg)],
                stderr=subprocess.DEVNULL,
            )
            time.sleep(8)  # imports and connection
            c0, w0 = cpu_s(svc.pid), time.monotonic()
            time.sleep(60)
            c1, w1 = cpu_s(svc.pid), time.monotonic()
            svc.send_signal(signal.SIGTERM)
            _, _status, usage = os.wait4(svc.pid, 0)
            out["service_cpu_pct_1hz"] = 100 * (c1 - c0) / (w1 - w0)
            out["service_peak_rss_mb"] = usage.ru_maxrss / 1024
        finally:
            server.terminate()
            server.wait(10)
    return out


if __name__ == "__main__":
    r = main()
    print(f"# {platform.machine()}, Python {platform.python_version()}")
    for k, v in r.items():
        print(f"{k:24s} {v:.3f}" if isinstance(v, float) else f"{k:24s} {v}")
