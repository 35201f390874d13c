"""One contract, written once, run against every backend over a real link; then the faults.

Backends: sim (in process), OPC UA against asyncua's server (the virtual CNC) and against
node-opcua's server, Haas Q/E and a generic line protocol over socat pseudo-terminals, and
Modbus RTU against pymodbus's own server over a pseudo-terminal.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import pytest
from devices import (
    LineDevice,
    ModbusDevice,
    NodeOpcuaServer,
    PtyPair,
    Registers,
    haas_handler,
    line_handler,
)

from cnc_adapters import (
    Adapter,
    AdapterError,
    AdapterTimeoutError,
    BadValueError,
    UnreachableError,
    WriteRejectedError,
    backend,
    open_adapter,
)
from cnc_adapters.modbus import ModbusRtuAdapter
from cnc_adapters.opcua import OpcUaAdapter
from cnc_adapters.serial_link import HaasAdapter, LineAdapter
from cnc_adapters.sim import SpindlePlant, preset
from cnc_adapters.sim.adapter import SimAdapter
from cnc_adapters.sim.vcnc import SimClock, VirtualCNC, VirtualMachine, free_port, running


def wait_for(pred: Callable[[], bool], timeout: float = 15.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            if pred():
                return True
        except AdapterError:
            pass
        time.sleep(0.02)
    return False


@dataclass
class Rig:
    make: Callable[..., Adapter]  # builds an unopened adapter; kwargs: scaling
    set_speed: Callable[[float], None]
    held_offset: Callable[[], float | None]  # in the controller's unit


BACKENDS = ["sim", "opcua-asyncua", "opcua-node", "haas", "line", "modbus"]


@pytest.fixture(params=BACKENDS)
def rig(request, tmp_path):
    kind = request.param
    if kind == "sim":
        vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
        yield Rig(lambda **kw: SimAdapter(machine=vm, **kw), vm.override_speed, lambda: vm.offset_um)
    elif kind == "opcua-asyncua":
        vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
        with running(VirtualCNC(vm)) as cnc:
            yield Rig(lambda **kw: OpcUaAdapter(cnc.url, preset="virtual-cnc", **kw),
                      vm.override_speed, lambda: vm.offset_um)
    elif kind == "opcua-node":
        srv = NodeOpcuaServer(free_port())
        try:
            yield Rig(lambda **kw: OpcUaAdapter(srv.url, speed_node="ns=1;s=Spindle1.ActSpeed",
                                                offset_node="ns=1;s=Spindle1.ThermalOffset", **kw),
                      srv.set_speed, srv.offset)
        finally:
            srv.close()
    elif kind in ("haas", "line"):
        pty = PtyPair(tmp_path)
        regs = Registers()
        dev = LineDevice(pty.dev, haas_handler(regs) if kind == "haas" else line_handler(regs))
        cls = HaasAdapter if kind == "haas" else LineAdapter
        try:
            yield Rig(lambda **kw: cls(pty.ctl, **kw), lambda v: setattr(regs, "speed_rpm", v),
                      lambda: regs.offset)
        finally:
            dev.stop()
            pty.close()
    else:
        pty = PtyPair(tmp_path)
        dev = ModbusDevice(pty.dev)
        try:
            yield Rig(lambda **kw: ModbusRtuAdapter(pty.ctl, baudrate=115200, speed_register=0,
                                                    offset_register=0, **kw),
                      dev.set_speed, dev.offset)
        finally:
            dev.close()
            pty.close()


# -- the contract ------------------------------------------------------------------


def test_reads_the_actual_speed(rig):
    rig.set_speed(12345.0)
    with rig.make() as link:
        assert wait_for(lambda: link.read_speed() == pytest.approx(12345.0))


def test_reverse_rotation_reads_as_magnitude(rig):
    rig.set_speed(-9000.0)
    with rig.make() as link:
        assert wait_for(lambda: link.read_speed() == pytest.approx(9000.0))


def test_writes_the_offset(rig):
    with rig.make() as link:
        link.write_offset_um(-7.5)
        assert wait_for(lambda: rig.held_offset() == pytest.approx(-7.5, abs=1e-4))
        link.write_offset_um(3.25)
        assert wait_for(lambda: rig.held_offset() == pytest.approx(3.25, abs=1e-4))


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, None, "5"])
def test_never_writes_a_bad_value(rig, bad):
    with rig.make() as link:
        link.write_offset_um(1.5)
        assert wait_for(lambda: rig.held_offset() == pytest.approx(1.5, abs=1e-4))
        with pytest.raises(BadValueError):
            link.write_offset_um(bad)  # type: ignore[arg-type]
        time.sleep(0.1)
        assert rig.held_offset() == pytest.approx(1.5, abs=1e-4)


def test_unit_sign_and_scale(rig):
    # a controller that holds millimetres with the opposite sign convention
    with rig.make(offset_scale=0.001, offset_sign=-1) as link:
        link.write_offset_um(-12.0)
        assert wait_for(lambda: rig.held_offset() == pytest.approx(0.012, abs=1e-6))


def test_close_is_idempotent_and_final(rig):
    link = rig.make()
    with link:
        link.read_speed()
    link.close()
    link.close()
    with pytest.raises(AdapterError):
        link.read_speed()


# -- registry -----------------------------------------------------------------------


def test_registry_by_name_and_url(tmp_path):
    assert backend("haas") is HaasAdapter and backend("modbus") is ModbusRtuAdapter
    assert isinstance(open_adapter("sim://motorized-27k?program=job-shop-day&seed=2"), SimAdapter)
    assert isinstance(open_adapter("serial:///dev/ttyX?protocol=haas&offset_var=10600"), HaasAdapter)
    assert open_adapter("serial:///dev/ttyX?protocol=haas&offset_var=10600").offset_var == 10600
    m = open_adapter("serial:///dev/ttyX?protocol=modbus&device_id=3&speed_type=int16&speed_scale=10")
    assert isinstance(m, ModbusRtuAdapter) and m.device_id == 3 and m.speed_scale == 10
    o = open_adapter({"type": "opcua", "url": "opc.tcp://127.0.0.1:4840", "preset": "sinumerik", "r_parameter": 7})
    assert o.offset_node.endswith("R[u1,7]") and o.offset_scale == 0.001
    with pytest.raises(AdapterError, match="unknown adapter"):
        open_adapter({"type": "nope"})
    with pytest.raises(AdapterError, match="scheme"):
        open_adapter("ftp://x")


def test_exceptions_refine_builtins():
    assert issubclass(UnreachableError, ConnectionError)
    assert issubclass(AdapterTimeoutError, TimeoutError)
    assert issubclass(WriteRejectedError, PermissionError)
    assert issubclass(BadValueError, ValueError)
    assert len({UnreachableError, AdapterTimeoutError, WriteRejectedError, BadValueError}) == 4


# -- faults: OPC UA ---------------------------------------------------------------------


def test_opcua_server_killed_mid_session_and_restarted():
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    vm.override_speed(8000.0)
    port = free_port()
    events = []
    link = OpcUaAdapter(f"opc.tcp://127.0.0.1:{port}/thermocomp/virtual-cnc/", preset="virtual-cnc",
                        timeout_s=2, on_link_change=lambda up, why: events.append(up))
    with running(VirtualCNC(vm, port=port)):
        assert wait_for(lambda: link.read_speed() == 8000.0)
        link.write_offset_um(-2.0)
        assert wait_for(lambda: vm.offset_um == -2.0)
    # the server is gone: a distinct error, and no write gets through
    with pytest.raises((UnreachableError, AdapterTimeoutError)):
        link.read_speed()
    with pytest.raises((UnreachableError, AdapterTimeoutError)):
        link.write_offset_um(-3.0)
    assert vm.offset_um == -2.0
    with running(VirtualCNC(vm, port=port)):
        assert wait_for(lambda: link.read_speed() == 8000.0, timeout=30)  # recovered
        link.write_offset_um(-4.0)
        assert wait_for(lambda: vm.offset_um == -4.0)
    assert events == [False, True] and link.reconnects == 1
    link.close()


def test_opcua_wrong_node_id():
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    with running(VirtualCNC(vm)) as cnc:
        link = OpcUaAdapter(cnc.url, speed_node="ns=2;s=/No/Such/Node", offset_node="ns=2;s=/Nope")
        with pytest.raises(AdapterError, match="BadNodeIdUnknown"):
            link.read_speed()
        link.close()


def test_opcua_write_refused_by_node_opcua():
    srv = NodeOpcuaServer(free_port())
    try:
        locked = OpcUaAdapter(srv.url, speed_node="ns=1;s=Spindle1.ActSpeed",
                              offset_node="ns=1;s=Spindle1.LockedOffset")
        with pytest.raises(WriteRejectedError, match="BadNotWritable"):
            locked.write_offset_um(1.0)
        locked.close()
        link = OpcUaAdapter(srv.url, speed_node="ns=1;s=Spindle1.ActSpeed",
                            offset_node="ns=1;s=Spindle1.ThermalOffset")
        with pytest.raises(WriteRejectedError, match="BadOutOfRange"):
            link.write_offset_um(5000.0)  # beyond what this controller accepts
        link.close()
    finally:
        srv.close()


# -- faults: serial ---------------------------------------------------------------------


@pytest.fixture
def haas(tmp_path):
    pty = PtyPair(tmp_path)
    regs = Registers(speed_rpm=6000.0)
    dev = LineDevice(pty.dev, haas_handler(regs))
    link = HaasAdapter(pty.ctl, timeout_s=0.3)
    yield pty, regs, dev, link
    link.close()
    dev.stop()
    pty.close()


@pytest.mark.parametrize("mode,error", [("silent", AdapterTimeoutError), ("partial", AdapterTimeoutError),
                                        ("garbage", BadValueError)])
def test_serial_bad_replies(haas, mode, error):
    _, regs, dev, link = haas
    assert link.read_speed() == 6000.0
    dev.mode = mode
    with pytest.raises(error):
        link.read_speed()
    dev.mode = "ok"
    time.sleep(0.35)  # let a late reply arrive; it must not be taken for the next answer
    assert link.read_speed() == 6000.0


def test_serial_write_refused(haas):
    _, regs, dev, link = haas
    link.write_offset_um(-1.0)
    dev.mode = "reject"
    with pytest.raises(WriteRejectedError):
        link.write_offset_um(-2.0)
    assert regs.offset == -1.0


def test_serial_device_vanishes_and_returns(haas):
    pty, regs, dev, link = haas
    assert link.read_speed() == 6000.0
    pty.unplug()
    with pytest.raises(UnreachableError):
        link.read_speed()
    with pytest.raises(UnreachableError):  # still gone: reopening fails cleanly
        link.write_offset_um(-5.0)
    assert regs.offset is None  # nothing was written
    pty.plug()
    assert wait_for(lambda: link.read_speed() == 6000.0)
    link.write_offset_um(-5.0)
    assert regs.offset == -5.0


def test_modbus_crc_failure_is_a_timeout_not_a_value(tmp_path):
    import serial

    pty = PtyPair(tmp_path)
    try:
        link = ModbusRtuAdapter(pty.ctl, baudrate=115200, timeout_s=0.3)
        with serial.Serial(pty.dev, 115200, timeout=0.05) as dev:
            import threading

            def answer_with_bad_crc():
                req = b""
                end = time.monotonic() + 5
                while len(req) < 8 and time.monotonic() < end:
                    req += dev.read(8 - len(req))
                # device 1, fc 4, 4 bytes: a float32, then a CRC that is wrong
                dev.write(bytes([1, 4, 4, 0x46, 0x40, 0xE4, 0x00, 0x00, 0x00]))

            t = threading.Thread(target=answer_with_bad_crc, daemon=True)
            t.start()
            with pytest.raises(AdapterTimeoutError):
                link.read_speed()
            t.join(5)
        link.close()
    finally:
        pty.close()


def test_modbus_exception_reply_on_a_bad_address(tmp_path):
    pty = PtyPair(tmp_path)
    dev = ModbusDevice(pty.dev)
    try:
        link = ModbusRtuAdapter(pty.ctl, baudrate=115200, offset_register=200)
        with pytest.raises(WriteRejectedError):
            link.write_offset_um(1.0)
        link.close()
    finally:
        dev.close()
        pty.close()


# -- reading by subscription; reconnect back-off ------------------------------------------


def test_opcua_subscription_follows_the_speed():
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    vm.override_speed(3000.0)
    with running(VirtualCNC(vm)) as cnc:
        with OpcUaAdapter(cnc.url, preset="virtual-cnc", read_mode="subscribe") as link:
            assert wait_for(lambda: link.read_speed() == 3000.0)
            vm.override_speed(21000.0)
            assert wait_for(lambda: link.read_speed() == 21000.0)
            link.write_offset_um(-1.25)
            assert wait_for(lambda: vm.offset_um == -1.25)


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_reconnect_backs_off_exponentially_with_jitter_and_tells_the_runtime():
    import random

    clock = FakeClock()
    events = []
    link = OpcUaAdapter(f"opc.tcp://127.0.0.1:{free_port()}/x", preset="virtual-cnc", timeout_s=1,
                        backoff_s=1.0, max_backoff_s=8.0, jitter=0.2, clock=clock,
                        rng=random.Random(1), on_link_change=lambda up, why: events.append(up))
    attempts = []
    real = link._connect

    def counting():
        attempts.append(clock.t)
        real()

    link._connect = counting  # type: ignore[method-assign]
    delays = []
    for _ in range(6):
        with pytest.raises(UnreachableError):
            link.read_speed()
        wait = link._next_attempt - clock.t
        delays.append(wait)
        with pytest.raises(UnreachableError, match="next attempt"):
            link.read_speed()  # inside the back-off: fails at once, no network attempt
        clock.t += wait + 1e-6
    assert len(attempts) == 6
    nominal = [1, 2, 4, 8, 8, 8]
    assert all(0.8 * n <= d <= 1.2 * n for d, n in zip(delays, nominal)), delays
    assert len({round(d / n, 6) for d, n in zip(delays, nominal)}) > 1  # jittered
    assert events == [False]  # told once that the link is down
    link.close()


def test_opc40502_preset_finds_the_spindle_by_browse_path():
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    vm.override_speed(17000.0)
    with running(VirtualCNC(vm)) as cnc:
        path = "0:Objects/{ns}:CncInterface/{ns}:CncSpindleList/{ns}:Spindle1/{ns}:ThermalOffset"
        # the virtual CNC keeps the 40502 browse names in its own namespace
        with OpcUaAdapter(cnc.url, preset="opc40502", namespace_uri="urn:thermocomp:virtual-cnc",
                          offset_path=path) as link:
            assert wait_for(lambda: link.read_speed() == 17000.0)
            link.write_offset_um(-2.5)
            assert wait_for(lambda: vm.offset_um == -2.5)
        bad = OpcUaAdapter(cnc.url, preset="opc40502", namespace_uri="urn:thermocomp:virtual-cnc",
                           spindle="Spindle9", offset_path=path)
        with pytest.raises(AdapterError, match="BadNoMatch|browse"):
            bad.read_speed()
        bad.close()


def test_opcua_deferred_write_check_reports_a_write_the_controller_did_not_take():
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    vm.override_speed(9000.0)
    with running(VirtualCNC(vm)) as cnc:
        with OpcUaAdapter(cnc.url, preset="virtual-cnc", verify_writes="deferred") as link:
            link.write_offset_um(-3.0)  # taken
            assert wait_for(lambda: vm.offset_um == -3.0)
            assert link.read_speed() == 9000.0 and link.take_write_mismatch() is None
            link.write_offset_um(-5000.0)  # beyond what this CNC accepts: it reverts the variable
            assert wait_for(lambda: vm.rejected_writes >= 1)
            time.sleep(0.1)
            assert link.read_speed() == 9000.0
            assert link.take_write_mismatch() == -3.0  # what it holds, reported once
            assert link.take_write_mismatch() is None
    with pytest.raises(AdapterError, match="verify_writes"):
        OpcUaAdapter("opc.tcp://127.0.0.1:1", preset="virtual-cnc", verify_writes="sometimes")
