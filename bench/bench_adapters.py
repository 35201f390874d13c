"""Read + write round-trip latency of the controller links, on loopback and pseudo-terminals.

OPC UA against the asyncua virtual CNC (polling, polling without write read-back, and
subscription), Haas Q/E and Modbus RTU at 115 200 baud over socat pty pairs.
Target (issue 5): OPC UA p99 <= 10 ms. Run: .venv/bin/python bench/bench_adapters.py
"""

from __future__ import annotations

import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from devices import LineDevice, ModbusDevice, PtyPair, Registers, haas_handler

from cnc_adapters.modbus import ModbusRtuAdapter
from cnc_adapters.opcua import OpcUaAdapter
from cnc_adapters.serial_link import HaasAdapter
from machine_sim import SpindlePlant, preset
from machine_sim.vcnc import SimClock, VirtualCNC, VirtualMachine, running

N = 1000


def cycle_latency(link, n: int = N) -> np.ndarray:
    out = np.empty(n)
    link.read_speed()
    for k in range(n):
        t0 = time.perf_counter()
        link.read_speed()
        link.write_offset_um(-1.0 - (k % 7) * 0.5)  # always a new value: a real write each time
        out[k] = time.perf_counter() - t0
    return out * 1e3


def row(name: str, ms: np.ndarray) -> dict:
    return {
        "link": name,
        "p50_ms": float(np.percentile(ms, 50)),
        "p99_ms": float(np.percentile(ms, 99)),
        "max_ms": float(ms.max()),
        "n": int(ms.size),
    }


def main() -> list[dict]:
    rows = []
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    vm.override_speed(12000.0)
    with running(VirtualCNC(vm)) as cnc:
        for name, kw in (
            ("OPC UA poll, write + read-back", {}),
            ("OPC UA poll, write only", {"verify_writes": False}),
            ("OPC UA subscription, write only", {"read_mode": "subscribe", "verify_writes": False}),
        ):
            with OpcUaAdapter(cnc.url, preset="virtual-cnc", **kw) as link:
                rows.append(row(name, cycle_latency(link)))
    with tempfile.TemporaryDirectory() as tmp:
        pty = PtyPair(Path(tmp))
        regs = Registers(12000.0)
        dev = LineDevice(pty.dev, haas_handler(regs))
        with HaasAdapter(pty.ctl, baudrate=115200) as link:
            rows.append(row("Haas Q/E serial 115200 (pty)", cycle_latency(link)))
        dev.stop()
        pty.close()
    with tempfile.TemporaryDirectory() as tmp:
        pty = PtyPair(Path(tmp))
        dev = ModbusDevice(pty.dev)
        with ModbusRtuAdapter(pty.ctl, baudrate=115200) as link:
            rows.append(row("Modbus RTU 115200 (pty)", cycle_latency(link, 300)))
        dev.close()
        pty.close()
    return rows


if __name__ == "__main__":
    import logging

    logging.getLogger("asyncua").setLevel(logging.ERROR)
    logging.getLogger("pymodbus").setLevel(logging.ERROR)
    res = main()
    print(f"# {platform.machine()}, Python {platform.python_version()}; read + write per cycle")
    for r in res:
        print(
            f"{r['link']:36s} p50 {r['p50_ms']:6.2f} ms  p99 {r['p99_ms']:6.2f} ms  max {r['max_ms']:6.2f} ms  (n={r['n']})"
        )
