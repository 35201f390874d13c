"""One contract, written once, run against every backend over a real link; then the faults.

Backends: sim (in process), OPC UA against asyncua's server (the virtual CNC) and against
node-opcua's server, Haas Q/E and a generic line protocol over socat pseudo-terminals, and
Modbus RTU against pymodbus's own server over a pseudo-terminal; LinuxCNC's read-back against
a real HAL (halrun) where LinuxCNC is installed.
"""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

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
    ConfigError,
    Failure,
    FailureKind,
    Reading,
    UnreachableError,
    Wants,
    WriteRejectedError,
    WriteResult,
    backend,
    open_adapter,
)
from cnc_adapters.modbus import ModbusRtuAdapter
from cnc_adapters.opcua import OpcUaAdapter
from cnc_adapters.serial_link import HaasAdapter, LineAdapter
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import SimClock, VirtualCNC, VirtualMachine, free_port, running


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
    outside_write: Callable[[float], None]  # someone else sets the controller's offset (its unit)


BACKENDS = [
    "sim",
    "opcua-asyncua",
    "opcua-node",
    "haas",
    "line",
    "modbus",
    "focas",
    "plc-s7",
    "plc-modbus-tcp",
    "plc-ads",
]


def opcua_write(url: str, node_id: str, value: float) -> None:
    """Another OPC UA client (an operator's HMI, a fault test) writes a node."""
    from asyncua import ua
    from asyncua.sync import Client

    with Client(url, timeout=10) as c:
        node_id = (
            node_id.replace("{ns}", str(c.get_namespace_index("urn:thermocomp:virtual-cnc")))
            if "{ns}" in node_id
            else node_id
        )
        c.get_node(node_id).write_value(
            ua.DataValue(ua.Variant(float(value), ua.VariantType.Double))
        )


def line_handler_with_query(regs: Registers):
    """The generic line protocol with the optional read-back query ``?OFFSET``."""
    base = line_handler(regs)

    def handle(text: str, mode: str) -> str | None:
        if text == "?OFFSET":
            return "ERR locked" if mode == "reject" else f"OFFSET={regs.offset or 0.0:.6f}"
        return base(text, mode)

    return handle


VCNC_OFFSET = "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/ThermalOffset"


# One OPC UA server of each kind per module (starting one takes seconds); each test starts from
# a reset one: no speed forced, offset 0, and (node-opcua) no write reported yet.
@pytest.fixture(scope="module")
def _vcnc_server():
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    with running(VirtualCNC(vm)) as cnc:
        yield vm, cnc


@pytest.fixture
def vcnc(_vcnc_server):
    vm, cnc = _vcnc_server
    vm.override_speed(None)
    if vm.offset_um != 0.0:  # through its node: the server takes what its node holds each tick
        opcua_write(cnc.url, VCNC_OFFSET, 0.0)
        assert wait_for(lambda: vm.offset_um == 0.0)
    return vm, cnc


@pytest.fixture(scope="module")
def _node_opcua_server():
    srv = NodeOpcuaServer(free_port())
    try:
        yield srv
    finally:
        srv.close()


@pytest.fixture
def node_opcua(_node_opcua_server):
    _node_opcua_server.reset()
    return _node_opcua_server


@pytest.fixture(params=BACKENDS)
def rig(request, tmp_path):
    kind = request.param
    if kind == "sim":
        vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
        yield Rig(
            lambda **kw: SimAdapter(machine=vm, **kw),
            vm.override_speed,
            lambda: vm.offset_um,
            vm.apply_offset,
        )
    elif kind == "opcua-asyncua":
        vm, cnc = request.getfixturevalue("vcnc")
        yield Rig(
            lambda **kw: OpcUaAdapter(cnc.url, preset="virtual-cnc", **kw),
            vm.override_speed,
            lambda: vm.offset_um,
            lambda v: opcua_write(cnc.url, VCNC_OFFSET, v),
        )
    elif kind == "opcua-node":
        srv = request.getfixturevalue("node_opcua")
        yield Rig(
            lambda **kw: OpcUaAdapter(
                srv.url,
                speed_node="ns=1;s=Spindle1.ActSpeed",
                offset_node="ns=1;s=Spindle1.ThermalOffset",
                **kw,
            ),
            srv.set_speed,
            srv.offset,
            lambda v: opcua_write(srv.url, "ns=1;s=Spindle1.ThermalOffset", v),
        )
    elif kind in ("haas", "line"):
        pty = PtyPair(tmp_path)
        regs = Registers()
        dev = LineDevice(
            pty.dev, haas_handler(regs) if kind == "haas" else line_handler_with_query(regs)
        )

        def make(**kw):
            if kind == "haas":
                return HaasAdapter(pty.ctl, **kw)
            return LineAdapter(pty.ctl, offset_query="?OFFSET", **kw)  # with its read-back query

        try:
            yield Rig(
                make,
                lambda v: setattr(regs, "speed_rpm", v),
                lambda: regs.offset,
                lambda v: setattr(regs, "offset", v),
            )
        finally:
            dev.stop()
            pty.close()
    elif kind == "focas":
        from cnc_adapters.focas import FocasAdapter
        from machine_sim.focas_server import FocasServer, PlainControl

        control = PlainControl()
        with FocasServer(control) as srv:
            yield Rig(
                lambda **kw: FocasAdapter("127.0.0.1", port=srv.port, **kw),
                lambda v: setattr(control, "speed_rpm", v),
                lambda: control.held_raw,
                lambda v: setattr(control, "held_raw", v),
            )
    elif kind.startswith("plc-"):
        from cnc_adapters.plc import PlcAdapter
        from machine_sim.plc_servers import AdsPlc, ModbusTcpPlc, S7Plc

        cls, addresses = {
            "plc-s7": (S7Plc, {"offset_address": "DB100.DBD0", "speed_address": "DB100.DBD4"}),
            "plc-modbus-tcp": (ModbusTcpPlc, {"offset_address": "hr:0", "speed_address": "hr:2"}),
            "plc-ads": (
                AdsPlc,
                {
                    "offset_address": "GVL.fOffset",
                    "offset_type": "REAL",
                    "speed_address": "GVL.fSpeed",
                },
            ),
        }[kind]
        plc = cls(
            None, held_address=None, cutting_address=None, **addresses
        ).start()  # its memory is the controller
        try:
            yield Rig(
                lambda **kw: PlcAdapter(
                    protocol=cls.protocol, host=plc.host, port=plc.port, **addresses, **kw
                ),
                lambda v: plc.put("speed", v),
                lambda: plc.get("offset"),
                lambda v: plc.put("offset", v),
            )
        finally:
            plc.close()
    else:
        from pymodbus.client import ModbusSerialClient as C

        pty = PtyPair(tmp_path)
        dev = ModbusDevice(pty.dev)

        def outside_write(v: float) -> None:  # the PLC's own program sets holding registers 0-1
            dev._run(
                dev.server.context.async_setValues(
                    1, 3, 0, C.convert_to_registers(v, C.DATATYPE.FLOAT32)
                )
            )

        try:
            yield Rig(
                lambda **kw: ModbusRtuAdapter(
                    pty.ctl, baudrate=115200, speed_register=0, offset_register=0, **kw
                ),
                dev.set_speed,
                dev.offset,
                outside_write,
            )
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


def test_reads_back_the_offset_the_controller_holds(rig):
    with rig.make() as link:
        assert link.can_read_offset
        link.write_offset_um(-7.5)
        assert wait_for(lambda: rig.held_offset() == pytest.approx(-7.5, abs=1e-4))
        assert link.read_offset_um() == pytest.approx(-7.5, abs=1e-4)
        link.write_offset_um(3.25)
        assert wait_for(lambda: link.read_offset_um() == pytest.approx(3.25, abs=1e-4))
        # what the controller holds, not what was written: someone else changed it
        rig.outside_write(999.0)
        assert wait_for(lambda: link.read_offset_um() == pytest.approx(999.0, abs=1e-3))
        assert link.offset_um_requested == 3.25


def test_read_back_is_in_um_whatever_the_controller_unit_and_sign(rig):
    # a controller that holds millimetres with the opposite sign convention
    with rig.make(offset_scale=0.001, offset_sign=-1) as link:
        link.write_offset_um(-12.0)
        assert wait_for(lambda: rig.held_offset() == pytest.approx(0.012, abs=1e-6))
        assert link.read_offset_um() == pytest.approx(-12.0, abs=1e-3)
        rig.outside_write(0.5)  # 0.5 mm, its sign
        assert wait_for(lambda: link.read_offset_um() == pytest.approx(-500.0, abs=1e-3))


def test_close_is_idempotent_and_final(rig):
    link = rig.make()
    with link:
        link.read_speed()
    link.close()
    link.close()
    with pytest.raises(AdapterError):
        link.read_speed()


# -- one cycle: read(wants) and write, typed ------------------------------------------

ALL = Wants(cutting=True, held_offset=True, inputs=True, measurement=True)


def assert_reading(r: Reading) -> None:
    """The Reading's contract: every value None, a Failure, or a finite value of its type."""

    def number(v: object) -> bool:
        return isinstance(v, Failure) or (type(v) is float and math.isfinite(v))

    assert number(r.speed_rpm), r.speed_rpm
    assert r.cutting is None or isinstance(r.cutting, (bool, Failure))
    assert r.held_offset_um is None or number(r.held_offset_um)
    assert r.not_ready_offset_um is None or number(r.not_ready_offset_um)
    assert r.write_refused_um is None or number(r.write_refused_um)
    assert r.inputs is None or isinstance(r.inputs, Failure) or all(map(number, r.inputs.values()))
    m = r.measurement
    assert (
        m is None
        or isinstance(m, Failure)
        or (
            number(m.elongation_um)
            and type(m.sequence) is int
            and (m.sigma_um is None or (number(m.sigma_um) and m.sigma_um > 0))
        )
    )
    assert type(r.reconnects) is int


def test_one_cycle_reads_checked_values_and_writes_without_raising(rig):
    rig.set_speed(12345.0)
    with rig.make() as link:
        caps = link.capabilities
        assert caps.held_offset == link.can_read_offset
        assert wait_for(lambda: link.read(ALL).speed_rpm == pytest.approx(12345.0))
        r = link.read(ALL)
        assert_reading(r)
        for wanted, got in (
            (caps.cutting, r.cutting),
            (caps.measurement, r.measurement if not isinstance(r.measurement, Failure) else 0),
            (bool(caps.inputs), r.inputs),
            (caps.held_offset, r.held_offset_um),
        ):
            if not wanted:
                assert got is None  # what the link cannot read is not read
        assert link.read(Wants()).held_offset_um is None  # nor what is not asked for
        done = link.write(-7.5)
        assert done.taken, done.failure
        assert wait_for(lambda: rig.held_offset() == pytest.approx(-7.5, abs=1e-4))
        if caps.held_offset:
            assert wait_for(lambda: link.read(ALL).held_offset_um == pytest.approx(-7.5, abs=1e-4))
        for bad in (math.nan, math.inf, "5", True):
            refused = link.write(bad).failure  # type: ignore[arg-type]
            assert refused is not None and refused.kind is FailureKind.VALUE
        assert link.write(None).taken  # a confirmation: no offset, no sign of life configured
        assert rig.held_offset() == pytest.approx(-7.5, abs=1e-4)
    closed = link.read(ALL)  # a closed link: failures, never an exception
    assert isinstance(closed.speed_rpm, Failure)
    assert_reading(closed)
    assert link.write(1.0).failure is not None


# the rigs whose controller holds the raw value it is given (the others run a plant)
RAW_VALUE_BACKENDS = ["haas", "line", "modbus", "plc-s7", "plc-modbus-tcp", "plc-ads"]


@pytest.mark.parametrize("rig", RAW_VALUE_BACKENDS, indirect=True)
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_speed_and_offset_that_are_not_finite_are_failures_of_their_own(rig, bad):
    """What a controller can hold that is no finite number, where a value is due: the cycle
    reads it as a Failure of that value, never an exception."""
    with rig.make() as link:
        rig.set_speed(bad)
        rig.outside_write(bad)
        r = link.read(ALL)
        assert_reading(r)
        assert wait_for(lambda: isinstance(link.read(ALL).speed_rpm, Failure))
        if link.capabilities.held_offset:
            assert wait_for(lambda: isinstance(link.read(ALL).held_offset_um, Failure))
        rig.set_speed(9000.0)
        assert wait_for(lambda: link.read(ALL).speed_rpm == pytest.approx(9000.0))


@pytest.mark.parametrize(
    "garbage",
    ["12", b"12", [1.0], True, None, math.nan, math.inf, 10**400, -(10**400), object()],
    ids=lambda g: type(g).__name__ + ":" + repr(g)[:12],
)
def test_whatever_the_controller_holds_a_cycle_gives_a_value_or_a_failure(garbage):
    """The virtual CNC made to hold garbage in every value it hands over."""
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    with SimAdapter(machine=vm) as link:
        link.read(ALL)  # the probe's counter found first is stale
        for name in ("offset_um", "probe_value_um", "probe_sigma_um"):
            setattr(vm, name, garbage)
        vm.probe_sequence = garbage if not isinstance(garbage, float) else vm.probe_sequence + 1
        vm.advance = lambda: None  # type: ignore[method-assign] - it holds what it holds
        r = link.read(ALL)
        assert_reading(r)
        assert isinstance(r.held_offset_um, Failure) and isinstance(r.measurement, Failure)
        assert r.held_offset_um.kind is FailureKind.VALUE


# -- registry -----------------------------------------------------------------------


def test_registry_by_name_and_url(tmp_path):
    assert backend("haas") is HaasAdapter and backend("modbus") is ModbusRtuAdapter
    assert isinstance(open_adapter("sim://motorized-27k?program=job-shop-day&seed=2"), SimAdapter)
    assert isinstance(
        open_adapter("serial:///dev/ttyX?protocol=haas&offset_var=10600"), HaasAdapter
    )
    assert open_adapter("serial:///dev/ttyX?protocol=haas&offset_var=10600").offset_var == 10600
    m = open_adapter(
        "serial:///dev/ttyX?protocol=modbus&device_id=3&speed_type=int16&speed_scale=10"
    )
    assert isinstance(m, ModbusRtuAdapter) and m.device_id == 3 and m.speed_scale == 10
    o = open_adapter(
        {
            "type": "opcua",
            "url": "opc.tcp://127.0.0.1:4840",
            "preset": "sinumerik",
            "r_parameter": 7,
        }
    )
    assert o.offset_node.endswith("R[u1,7]") and o.offset_scale == 0.001
    with pytest.raises(ConfigError, match="unknown adapter"):
        open_adapter({"type": "nope"})
    with pytest.raises(ConfigError, match="scheme"):
        open_adapter("ftp://x")
    with pytest.raises(ConfigError, match="unknown serial protocol 'fanuc'"):
        open_adapter("serial:///dev/ttyX?protocol=fanuc")
    # a URL's query values are converted by the backend's settings model
    line = open_adapter("serial:///dev/ttyX?protocol=line&timeout_s=0.25&offset_query=%3FOFFSET")
    assert isinstance(line, LineAdapter) and line.timeout_s == 0.25 and line.can_read_offset


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
    link = OpcUaAdapter(
        f"opc.tcp://127.0.0.1:{port}/thermocomp/virtual-cnc/",
        preset="virtual-cnc",
        timeout_s=2,
        on_link_change=lambda up, why: events.append(up),
    )
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


def test_opcua_wrong_node_id(vcnc):
    _vm, cnc = vcnc
    link = OpcUaAdapter(cnc.url, speed_node="ns=2;s=/No/Such/Node", offset_node="ns=2;s=/Nope")
    with pytest.raises(AdapterError, match="BadNodeIdUnknown"):
        link.read_speed()
    link.close()


def test_opcua_write_refused_by_node_opcua(node_opcua):
    srv = node_opcua
    locked = OpcUaAdapter(
        srv.url, speed_node="ns=1;s=Spindle1.ActSpeed", offset_node="ns=1;s=Spindle1.LockedOffset"
    )
    with pytest.raises(WriteRejectedError, match="BadNotWritable"):
        locked.write_offset_um(1.0)
    locked.close()
    link = OpcUaAdapter(
        srv.url, speed_node="ns=1;s=Spindle1.ActSpeed", offset_node="ns=1;s=Spindle1.ThermalOffset"
    )
    with pytest.raises(WriteRejectedError, match="BadOutOfRange"):
        link.write_offset_um(5000.0)  # beyond what this controller accepts
    link.close()
    assert srv.offset() is None  # neither write was taken


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


@pytest.mark.parametrize(
    "mode,error",
    [("silent", AdapterTimeoutError), ("partial", AdapterTimeoutError), ("garbage", BadValueError)],
)
def test_serial_bad_replies(haas, mode, error):
    _, _regs, dev, link = haas
    assert link.read_speed() == 6000.0
    dev.mode = mode
    with pytest.raises(error):
        link.read_speed()
    dev.mode = "ok"
    time.sleep(0.35)  # let a late reply arrive; it must not be taken for the next answer
    assert link.read_speed() == 6000.0


@pytest.mark.parametrize(
    "reply",
    [
        ">MACRO, {var}, 1e999",
        ">MACRO, {var}, nan",
        ">MACRO, {var}, 99999999999999999999999999999999999999",
        ">MACRO, {var}, 1.5.5",
        ">MACRO, {var}, " + "9" * 400,
        ">MACRO, {var}",
        ">MACRO, {var}, \x00\x07",
        "?, UNKNOWN COMMAND",
        "",
    ],
)
def test_a_haas_line_that_is_no_number_is_a_failure_of_its_value(tmp_path, reply):
    """Every value a Haas control hands over, replaced by a malformed reply: the cycle reads
    a finite value or a Failure, and a write's check a Failure."""
    pty = PtyPair(tmp_path)

    def handle(text: str, mode: str) -> str | None:
        m = re.match(r"^\?Q600 (\d+)$", text)
        return reply.format(var=m.group(1)) if m else reply

    dev = LineDevice(pty.dev, handle)
    link = HaasAdapter(
        pty.ctl,
        timeout_s=0.3,
        measurement_var=10501,
        measurement_sequence_var=10502,
        measurement_sigma_var=10503,
    )
    try:
        r = link.read(ALL)
        assert_reading(r)
        assert isinstance(r.speed_rpm, Failure) or r.speed_rpm == 1e38  # the huge one is finite
        assert not link.write(-2.0).taken
    finally:
        link.close()
        dev.stop()
        pty.close()


def test_serial_write_refused(haas):
    _, regs, dev, link = haas
    link.write_offset_um(-1.0)
    dev.mode = "reject"
    with pytest.raises(WriteRejectedError):
        link.write_offset_um(-2.0)
    assert regs.offset == -1.0


def test_serial_device_vanishes_and_returns(haas):
    pty, regs, _dev, link = haas
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
        # the operation, the register, the port and the device address on the bus
        where = rf"modbus write offset holding register 200( \(\+\d\))? at {re.escape(pty.ctl)} \(device 1\)"
        with pytest.raises(WriteRejectedError, match=f"^{where}: exception reply"):
            link.write_offset_um(1.0)
        link.close()
    finally:
        dev.close()
        pty.close()


# -- reading by subscription; reconnect back-off ------------------------------------------


def test_opcua_subscription_follows_the_speed(vcnc):
    vm, cnc = vcnc
    vm.override_speed(3000.0)
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
    link = OpcUaAdapter(
        f"opc.tcp://127.0.0.1:{free_port()}/x",
        preset="virtual-cnc",
        timeout_s=1,
        backoff_s=1.0,
        max_backoff_s=8.0,
        jitter=0.2,
        clock=clock,
        rng=random.Random(1),
        on_link_change=lambda up, why: events.append(up),
    )
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


def test_opc40502_preset_finds_the_spindle_by_browse_path(vcnc):
    vm, cnc = vcnc
    vm.override_speed(17000.0)
    path = "0:Objects/{ns}:CncInterface/{ns}:CncSpindleList/{ns}:Spindle1/{ns}:ThermalOffset"
    # the virtual CNC keeps the 40502 browse names in its own namespace
    with OpcUaAdapter(
        cnc.url, preset="opc40502", namespace_uri="urn:thermocomp:virtual-cnc", offset_path=path
    ) as link:
        assert wait_for(lambda: link.read_speed() == 17000.0)
        link.write_offset_um(-2.5)
        assert wait_for(lambda: vm.offset_um == -2.5)
    bad = OpcUaAdapter(
        cnc.url,
        preset="opc40502",
        namespace_uri="urn:thermocomp:virtual-cnc",
        spindle="Spindle9",
        offset_path=path,
    )
    with pytest.raises(AdapterError, match="BadNoMatch|browse"):
        bad.read_speed()
    bad.close()


def test_opcua_deferred_write_check_reports_a_write_the_controller_did_not_take():
    from compensator.clock import SteppedClock
    from machine_sim.vcnc import step

    # lock-step: each server tick (take the write or refuse and revert it) is done when step returns
    clock = SteppedClock()
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=clock)
    vm.override_speed(9000.0)
    with running(VirtualCNC(vm, tick_s=None)) as cnc:
        clock.advance(60.0)  # up to speed
        step(cnc)
        with OpcUaAdapter(cnc.url, preset="virtual-cnc", verify_writes="deferred") as link:
            assert link.write(-3.0) == WriteResult(pending=True)  # taken, checked by the next read
            step(cnc)
            assert vm.offset_um == -3.0
            got = link.read(Wants())
            assert got.speed_rpm == 9000.0 and got.write_refused_um is None
            assert link.write(-5000.0).pending  # beyond what this CNC accepts: it reverts it
            step(cnc)
            assert vm.rejected_writes == 1
            got = link.read(Wants())
            assert got.speed_rpm == 9000.0
            assert got.write_refused_um == -3.0  # what it holds, reported once
            assert link.read(Wants()).write_refused_um is None
    with pytest.raises(AdapterError, match="verify_writes"):
        OpcUaAdapter("opc.tcp://127.0.0.1:1", preset="virtual-cnc", verify_writes="sometimes")


# -- reading the offset back: what cannot, and what is not a number -------------------------


def test_a_link_without_a_read_command_says_so_and_opens_nothing(tmp_path):
    link = LineAdapter(str(tmp_path / "no-such-port"))  # the generic protocol, no offset_query
    assert not link.can_read_offset and HaasAdapter.can_read_offset
    with pytest.raises(AdapterError, match="cannot read back") as info:
        link.read_offset_um()
    assert not isinstance(info.value, UnreachableError)  # it did not even try the port
    link.close()


@pytest.mark.parametrize("held", [math.nan, math.inf, True, "12"])
def test_a_held_offset_that_is_not_a_finite_number_is_a_bad_value(held):
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    vm.offset_um = held  # type: ignore[assignment] - a controller that holds garbage
    with SimAdapter(machine=vm) as link, pytest.raises(BadValueError):
        link.read_offset_um()


def test_a_refused_read_query_is_an_adapter_error(tmp_path):
    pty = PtyPair(tmp_path)
    regs = Registers()
    dev = LineDevice(pty.dev, line_handler_with_query(regs))
    try:
        with LineAdapter(pty.ctl, offset_query="?OFFSET") as link:
            dev.mode = "reject"
            with pytest.raises(
                AdapterError, match="line read offset '\\?OFFSET' at .*: controller refused it"
            ):
                link.read_offset_um()
            dev.mode = "ok"
            regs.offset = -2.5
            assert link.read_offset_um() == -2.5
    finally:
        dev.stop()
        pty.close()


def test_modbus_reads_back_an_integer_register_in_its_unit(tmp_path):
    pty = PtyPair(tmp_path)
    dev = ModbusDevice(pty.dev)
    try:
        # 0.1 um counts in an int16: -7.46 um is written as -75 counts and read back as -7.5 um
        with ModbusRtuAdapter(
            pty.ctl, baudrate=115200, offset_register=4, offset_type="int16", offset_scale=10
        ) as link:
            link.write_offset_um(-7.46)
            assert link.read_offset_um() == pytest.approx(-7.5)
    finally:
        dev.close()
        pty.close()


# -- a hung controller (its process stopped) ------------------------------------------------

SERVE_VCNC = """
import sys
from machine_sim import SpindlePlant, preset
from machine_sim.vcnc import SimClock, VirtualCNC, VirtualMachine, running
vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
vm.override_speed(float(sys.argv[2]))
with running(VirtualCNC(vm, port=int(sys.argv[1]))):
    print("ready", flush=True)
    sys.stdin.read()
"""


@pytest.fixture
def vcnc_process():
    """The virtual CNC in a process of its own, so that it can be stopped (SIGSTOP) like a
    controller that hangs: its socket stays open, nothing answers."""
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-c", SERVE_VCNC, str(port), "7000"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().strip() == "ready"  # type: ignore[union-attr]
        yield proc, f"opc.tcp://127.0.0.1:{port}/thermocomp/virtual-cnc/"
    finally:
        os.kill(proc.pid, signal.SIGCONT)
        proc.stdin.close()  # type: ignore[union-attr]
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def _proc_state(pid: int) -> str:
    """The process state letter from /proc (R running, S sleeping, T stopped, ...)."""
    stat = Path(f"/proc/{pid}/stat").read_text()
    return stat[stat.rindex(")") + 2]


def test_a_hung_controller_times_out_drops_the_session_and_reconnects(vcnc_process):
    proc, url = vcnc_process
    clock = FakeClock()
    events = []
    timeout_s = 0.5
    link = OpcUaAdapter(
        url,
        preset="virtual-cnc",
        timeout_s=timeout_s,
        clock=clock,
        backoff_s=1.0,
        on_link_change=lambda up, why: events.append((up, why)),
    )
    assert link.read_speed() == 7000.0
    link.write_offset_um(-4.0)
    os.kill(proc.pid, signal.SIGSTOP)
    # kill() returns before the signal lands: under load the server could still answer one
    # request, so wait until the kernel reports it stopped
    assert wait_for(lambda: _proc_state(proc.pid) in ("T", "t"))
    # the call times out, and says so (the runtime counts it as a link failure) ...
    start = time.monotonic()
    with pytest.raises(AdapterTimeoutError, match="no answer"):
        link.read_speed()
    # ... within about timeout_s: nothing waits for a goodbye the server will never answer
    assert time.monotonic() - start < timeout_s + 5.0
    assert (
        events == [(False, events[0][1])] and "no answer" in events[0][1]
    )  # the session is dropped
    # the next call reconnects, and connecting to the stopped server honours timeout_s too
    start = time.monotonic()
    with pytest.raises(AdapterTimeoutError, match="opcua connect at opc.tcp://.*: no answer"):
        link.read_offset_um()
    assert time.monotonic() - start < timeout_s + 5.0
    with pytest.raises(UnreachableError, match="next attempt"):
        link.read_offset_um()  # during the back-off after a failed connect: at once, no network
    os.kill(proc.pid, signal.SIGCONT)
    clock.t += 10.0
    assert wait_for(lambda: link.read_speed() == 7000.0)  # back, on a new session
    assert link.read_offset_um() == -4.0 and link.reconnects == 1 and events[-1][0] is True
    link.close()


# -- LinuxCNC: the offset motion holds, read from a real HAL ---------------------------------

from test_linuxcnc import run_in_hal  # noqa: E402 - one HAL at a time, as LinuxCNC starts it
from test_linuxcnc import why_not as _no_hal  # noqa: E402

# the adapter in a HAL of its own (halrun), as LinuxCNC starts it; motion's
# axis.z.eoffset-request (accumulated counts x scale) stood in for by conv_s32_float and mult2
HAL_SCRIPT = """
import json, sys, time
import hal
from cnc_adapters.linuxcnc import LinuxCncAdapter

out = {}
a = LinuxCncAdapter(component="tc-readback", machine_state="pins", held_pin="mult2.0.out")
a.open()
for sig, kind, pins in (("tc-counts", hal.HAL_S32, ("tc-readback.eoffset-counts", "conv-s32-float.0.in")),
                        ("tc-countsf", hal.HAL_FLOAT, ("conv-s32-float.0.out", "mult2.0.in0")),
                        ("tc-scale", hal.HAL_FLOAT, ("tc-readback.eoffset-scale", "mult2.0.in1"))):
    hal.new_sig(sig, kind)
    for pin in pins:
        hal.connect(pin, sig)


def settle(want):
    end = time.monotonic() + 10  # the servo thread runs every millisecond
    while time.monotonic() < end:
        got = a.read_offset_um()
        if abs(got - want) < 1e-6:
            return got
        time.sleep(0.005)
    return a.read_offset_um()


out["not_ready"] = a.read_offset_um()  # machine off: motion applies none
hal.set_p("tc-readback.machine-on", "1")
hal.set_p("tc-readback.homed", "1")
a.read_speed()  # the runtime's cycle: notices the machine is ready
a.write_offset_um(-12.0)
out["counts"] = hal.get_value("tc-readback.eoffset-counts")
out["held"] = settle(-12.0)
a.write_offset_um(3.5)
out["held2"] = settle(3.5)
b = LinuxCncAdapter(component="tc-readback2", machine_state="pins", held_pin="no.such.pin")
b.open()
hal.set_p("tc-readback2.machine-on", "1")
hal.set_p("tc-readback2.homed", "1")
try:
    b.read_offset_um()
except Exception as err:
    out["missing_pin"] = f"{type(err).__name__}: {err}"
print("@@", json.dumps(out), flush=True)
"""

HAL_FILE = """
loadrt threads name1=servo-thread period1=1000000
loadrt conv_s32_float
loadrt mult2
addf conv-s32-float.0 servo-thread
addf mult2.0 servo-thread
start
loadusr -w {python} {script}
"""


@pytest.mark.skipif(_no_hal() is not None, reason=_no_hal() or "")
def test_linuxcnc_reads_back_what_motion_holds_not_what_it_wrote():
    out = run_in_hal(HAL_SCRIPT, HAL_FILE)
    assert out["not_ready"] == 0.0
    # -12 um: +0.012 mm on Z (offset_sign -1), 1200 counts of 0.01 um; read back through HAL
    assert out["counts"] == 1200
    assert out["held"] == pytest.approx(-12.0, abs=1e-6)
    assert out["held2"] == pytest.approx(3.5, abs=1e-6)
    assert re.match(r"AdapterError: linuxcnc read offset pin no\.such\.pin: ", out["missing_pin"])


# -- the closed loop: a probe cycle's measurement, each value once ---------------------------

MEASURING = ["haas", "modbus"]  # LinuxCNC's pins: tests/test_linuxcnc.py, in a real HAL


@dataclass
class ProbeRig:
    make: Callable[..., Adapter]  # an unopened adapter with a measurement source; kwargs: scaling
    publish: Callable[
        ..., None
    ]  # (value, sequence, sigma=None), the controller's unit: value first
    unplug: Callable[[], None]  # the controller goes away ...
    plug: Callable[[], None]  # ... and comes back


@pytest.fixture(params=MEASURING)
def probe_rig(request, tmp_path):
    pty = PtyPair(tmp_path)
    if request.param == "haas":
        regs = Registers()
        dev = LineDevice(pty.dev, haas_handler(regs))

        def publish(value: float, seq: int, sigma: float | None = None) -> None:
            regs.macros[10501] = value
            if sigma is not None:
                regs.macros[10503] = sigma
            regs.macros[10502] = seq

        try:
            yield ProbeRig(
                lambda **kw: HaasAdapter(
                    pty.ctl,
                    timeout_s=0.3,
                    measurement_var=10501,
                    measurement_sequence_var=10502,
                    measurement_sigma_var=10503,
                    **kw,
                ),
                publish,
                pty.unplug,
                pty.plug,
            )
        finally:
            dev.stop()
            pty.close()
    else:
        from pymodbus.client import ModbusSerialClient as C

        mdev = ModbusDevice(pty.dev)

        def publish(value: float, seq: int, sigma: float | None = None) -> None:
            mdev.set_registers(
                "holding", 8, C.convert_to_registers(float(value), C.DATATYPE.FLOAT32)
            )
            if sigma is not None:
                mdev.set_registers(
                    "holding", 12, C.convert_to_registers(float(sigma), C.DATATYPE.FLOAT32)
                )
            mdev.set_registers("holding", 10, [seq])

        def unplug() -> None:
            pty.unplug()
            mdev.stop_server()

        def plug() -> None:
            pty.plug()
            mdev.start()

        try:
            yield ProbeRig(
                lambda **kw: ModbusRtuAdapter(
                    pty.ctl,
                    baudrate=115200,
                    timeout_s=0.3,
                    measurement_register=8,
                    measurement_sequence_register=10,
                    measurement_sigma_register=12,
                    **kw,
                ),
                publish,
                unplug,
                plug,
            )
        finally:
            mdev.close()
            pty.close()


def test_each_measurement_is_used_once_and_one_left_from_before_is_stale(probe_rig):
    from cnc_adapters.base import Measurement

    probe_rig.publish(5.0, 7, 0.5)  # a probe cycle ran before thermocomp started
    with probe_rig.make() as link:
        assert link.can_read_measurement
        assert link.read_measurement() is None  # stale: the counter found at the first read
        assert link.read_measurement() is None
        probe_rig.publish(12.5, 8, 0.75)
        assert link.read_measurement() == Measurement(12.5, 0.75, 8, link.name)
        assert link.read_measurement() is None  # once
        # a value that is not a finite number: refused, once
        probe_rig.publish(math.nan, 9)
        with pytest.raises(BadValueError, match="sequence 9"):
            link.read_measurement()
        assert link.read_measurement() is None
        probe_rig.publish(-3.25, 10)
        assert link.read_measurement() == Measurement(-3.25, 0.75, 10, link.name)
        # the controller goes away; a probe cycle runs meanwhile; it is taken after the reconnect
        probe_rig.unplug()
        with pytest.raises(UnreachableError):
            link.read_measurement()
        probe_rig.publish(2.0, 11, 0.25)
        probe_rig.plug()
        got: list = []
        assert wait_for(lambda: got.append(link.read_measurement()) or got[-1] is not None)
        assert got[-1] == Measurement(2.0, 0.25, 11, link.name) and link.reconnects == 1
        assert link.read_measurement() is None


def test_a_measurement_is_in_the_controllers_unit_whatever_the_offsets_sign(probe_rig):
    # millimetres, the offset's sign flipped: a measurement keeps its own sign (+ = grown)
    with probe_rig.make(offset_scale=0.001, offset_sign=-1) as link:
        assert link.read_measurement() is None
        probe_rig.publish(0.0125, 1, 0.0005)
        m = link.read_measurement()
        assert m.elongation_um == pytest.approx(12.5) and m.sigma_um == pytest.approx(0.5)
    # a cycle that hands over um while the offset is in mm
    with probe_rig.make(offset_scale=0.001, measurement_scale=1) as link:
        assert link.read_measurement() is None
        probe_rig.publish(12.5, 2, 0.5)
        m = link.read_measurement()
        assert m.elongation_um == pytest.approx(12.5) and m.sigma_um == pytest.approx(0.5)


def test_a_link_without_a_measurement_source_says_so_and_reads_nothing(tmp_path):
    port = str(tmp_path / "no-such-port")
    for link in (HaasAdapter(port), ModbusRtuAdapter(port)):
        assert type(link).can_read_measurement and not link.can_read_measurement
        assert link.read_measurement() is None  # without even opening the port
        assert not link._open
        link.close()
    assert not LineAdapter(port).can_read_measurement  # the generic protocol has no source
    for bad, match in (
        ({"measurement_var": 10501}, "needs both"),
        ({"measurement_var": 10500, "measurement_sequence_var": 10502}, "different"),
    ):
        with pytest.raises(ConfigError, match=match):
            open_adapter({"type": "haas", "port": port, **bad})
    for bad, match in (
        ({"measurement_sequence_register": 3}, "needs both"),
        ({"measurement_register": 2, "measurement_sequence_register": 3}, "overlap"),
    ):
        with pytest.raises(ConfigError, match=match):
            open_adapter({"type": "modbus", "port": port, **bad})


def test_modbus_measurement_in_integer_registers_of_the_input_table(tmp_path):
    from pymodbus.client import ModbusSerialClient as C

    pty = PtyPair(tmp_path)
    dev = ModbusDevice(pty.dev)
    try:
        # 0.1 um counts in an int32, low word first, in input registers; the counter a uint16
        with ModbusRtuAdapter(
            pty.ctl,
            baudrate=115200,
            word_order="little",
            measurement_table="input",
            measurement_register=4,
            measurement_type="int32",
            measurement_sequence_register=6,
            measurement_scale=10,
        ) as link:
            dev.set_registers("input", 6, [65535])
            assert link.read_measurement() is None
            dev.set_registers(
                "input", 4, C.convert_to_registers(-125, C.DATATYPE.INT32, word_order="little")
            )
            dev.set_registers("input", 6, [0])  # wrapped
            m = link.read_measurement()
            assert (
                m.elongation_um == pytest.approx(-12.5) and m.sequence == 0 and m.sigma_um is None
            )
            assert link.read_measurement() is None
    finally:
        dev.close()
        pty.close()


def test_a_counter_that_moves_while_the_value_is_read_waits_for_the_next_read():
    from cnc_adapters.base import RawMeasurement, read_handshake

    counter = iter([4, 5, 5, 5])  # the cycle changed the counter between its two reads
    assert read_handshake("x", lambda: next(counter), lambda: 1.5) is None
    assert read_handshake("x", lambda: next(counter), lambda: 1.5, lambda: 0.5) == RawMeasurement(
        5, 1.5, 0.5
    )
    with pytest.raises(BadValueError, match="whole number"):
        read_handshake("x", lambda: 2.5, lambda: 1.5)
