"""The virtual CNC over a real OPC UA server on loopback: asyncua and node-opcua clients."""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from cnc_adapters import BadValueError, UnreachableError, open_adapter
from cnc_adapters.opcua import OpcUaAdapter
from compensator.speed_programs import Program
from machine_sim import SpindlePlant, preset
from machine_sim.vcnc import (
    NAMESPACE_URI,
    NODE_PATHS,
    SimClock,
    VirtualCNC,
    VirtualMachine,
    free_port,
    running,
)

JS = Path(__file__).parent / "js"


def machine(scale=600.0, program=None):
    p = preset("motorized-27k")
    # ten simulated hours: a slow client start (a loaded machine) must not outlive the program
    prog = program or Program("steady", ((36000.0, 20000.0),))
    return VirtualMachine(SpindlePlant(p, seed=1), prog, clock=SimClock(scale))


def wait_for(pred, timeout=20.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return False


def test_asyncua_client_reads_speed_and_writes_the_offset():
    from asyncua.sync import Client

    vm = machine()
    with running(VirtualCNC(vm)) as cnc, Client(cnc.url, timeout=10) as c:
        ns = c.get_namespace_index(NAMESPACE_URI)
        node = {k: c.get_node(f"ns={ns};s={p}") for k, p in NODE_PATHS.items()}
        assert wait_for(lambda: node["act_speed"].read_value() == 20000.0)
        node["thermal_offset"].write_value(-7.25)
        assert wait_for(lambda: vm.offset_um == -7.25)
        assert wait_for(
            lambda: (
                abs(
                    node["tool_tip_error"].read_value()
                    - (node["true_elongation"].read_value() - 7.25)
                )
                < 1e-9
            )
        )
        t0 = node["sim_time"].read_value()
        assert wait_for(lambda: node["sim_time"].read_value() > t0)  # accelerated time runs
    h = vm.history()
    assert (h.offset_um[-5:] == -7.25).all()
    np.testing.assert_allclose(h.tool_tip_error_um, h.true_um + h.offset_um)


def test_virtual_cnc_ignores_a_non_finite_or_huge_offset():
    from asyncua.sync import Client

    vm = machine()
    with running(VirtualCNC(vm)) as cnc, Client(cnc.url, timeout=10) as c:
        ns = c.get_namespace_index(NAMESPACE_URI)
        off = c.get_node(f"ns={ns};s={NODE_PATHS['thermal_offset']}")
        off.write_value(5e6)
        assert wait_for(lambda: vm.rejected_writes >= 1)
        assert wait_for(lambda: off.read_value() == 0.0)
    assert vm.offset_um == 0.0


@pytest.mark.skipif(
    shutil.which("node") is None, reason="Node.js is not installed (make test installs it)"
)
def test_independent_node_opcua_client_reads_and_writes():
    assert (JS / "node_modules" / "node-opcua-client").is_dir(), "run scripts/system-deps.sh"
    vm = machine()
    with running(VirtualCNC(vm)) as cnc:
        r = subprocess.run(
            ["node", str(JS / "vcnc_client.mjs"), cnc.url, "-4.5"],
            capture_output=True,
            text=True,
            timeout=120,
        )
        out = json.loads(r.stdout.strip().splitlines()[-1])
        assert r.returncode == 0, (out, r.stderr[-2000:])
        assert out["browse_status"] == "Good"
        assert out["act_speed_rpm"] == 20000
        assert out["write_status"] == "Good" and out["offset_readback_um"] == -4.5
        # both read in one request; the server may publish between the two nodes (one tick)
        assert out["tool_tip_error_um"] == pytest.approx(out["true_elongation_um"] - 4.5, abs=0.3)
        assert out["true_elongation_um"] > 1.0
        # at 20 000 rpm for over 7 simulated seconds: at speed, the tool in the part (Boolean nodes)
        assert (out["at_speed"], out["cutting"], out["cutting_type"]) == (True, True, "Boolean")
        assert wait_for(lambda: vm.offset_um == -4.5)


def test_opcua_adapter_against_the_virtual_cnc():
    vm = machine()
    with running(VirtualCNC(vm)) as cnc:
        with open_adapter(cnc.url + "?preset=virtual-cnc") as link:
            assert isinstance(link, OpcUaAdapter)
            assert wait_for(lambda: link.read_speed() == 20000.0)
            link.write_offset_um(-3.0)
            with pytest.raises(BadValueError):
                link.write_offset_um(float("nan"))
            assert wait_for(lambda: vm.offset_um == -3.0)
        link.close()  # idempotent


def test_opcua_adapter_unreachable():
    link = OpcUaAdapter(
        f"opc.tcp://127.0.0.1:{free_port()}/nothing", preset="virtual-cnc", timeout_s=2
    )
    with pytest.raises(UnreachableError):
        link.read_speed()
    with pytest.raises(ConnectionError):  # also the builtin it refines
        link.open()


def test_any_client_can_write_the_offset_and_the_adapter_reads_it_back():
    from asyncua.sync import Client

    vm = machine()
    with running(VirtualCNC(vm)) as cnc, open_adapter(cnc.url + "?preset=virtual-cnc") as link:
        link.write_offset_um(-3.0)
        assert link.read_offset_um() == -3.0
        # an operator's HMI (another client) writes 999 um: the controller takes it
        with Client(cnc.url, timeout=10) as other:
            ns = other.get_namespace_index(NAMESPACE_URI)
            other.get_node(f"ns={ns};s={NODE_PATHS['thermal_offset']}").write_value(999.0)
        assert wait_for(lambda: vm.offset_um == 999.0)
        assert link.read_offset_um() == 999.0


def test_a_restarted_virtual_cnc_starts_with_offset_zero():
    vm = machine()
    port = free_port()
    url = f"opc.tcp://127.0.0.1:{port}/thermocomp/virtual-cnc/"
    link = OpcUaAdapter(url, preset="virtual-cnc", timeout_s=2)
    with running(VirtualCNC(vm, port=port)):
        link.write_offset_um(-6.0)
        assert wait_for(lambda: vm.offset_um == -6.0)
    assert vm.offset_um == -6.0  # stopped: the machine still holds it
    with running(VirtualCNC(vm, port=port)):
        assert vm.offset_um == 0.0  # a controller restart clears the variable
        assert wait_for(lambda: _read_back(link) == 0.0)  # after the adapter reconnects
    link.close()


def _read_back(link):
    try:
        return link.read_offset_um()
    except UnreachableError:
        return None


def test_virtual_cnc_writes_the_machines_record_on_sigterm(tmp_path):
    """`thermocomp virtual-cnc --history`: stopped by SIGTERM (as systemd or a shell stops it), it
    writes the machine's record with the tool tip's error and says it in one line; with no
    service writing an offset, the error is the growth itself."""
    import signal
    import socket
    import sys

    from asyncua.sync import Client

    from compensator.io import read_run_log
    from machine_sim.vcnc import NAMESPACE_URI, NODE_PATHS

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    out = tmp_path / "machine.csv"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "thermocomp",
            "virtual-cnc",
            "--program",
            "job-shop-day",
            "--time-scale",
            "3000",
            "--port",
            str(port),
            "--history",
            str(out),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        head = []
        for line in proc.stdout:  # the server is up once it prints its nodes
            head.append(line)
            if line.startswith("nodes:"):
                break
        with Client(f"opc.tcp://127.0.0.1:{port}/thermocomp/virtual-cnc/", timeout=10) as c:
            node = c.get_node(
                f"ns={c.get_namespace_index(NAMESPACE_URI)};s={NODE_PATHS['sim_time']}"
            )
            for _ in range(600):  # until the machine has a record of a few simulated minutes
                if node.read_value() > 300.0:
                    break
                time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        rest = proc.communicate(timeout=60)[0]
    finally:
        proc.kill()
    assert proc.returncode == 0, "".join(head) + rest
    assert "tool-tip error over" in rest and f"to {out}" in rest
    log = read_run_log(out)
    assert log.time_s[-1] > 300.0
    assert np.allclose(log.extras["error_um"], log.elongation_um + log.extras["offset_um"])
    assert np.allclose(log.extras["offset_um"], 0.0)  # nothing wrote an offset
