"""The sign of life (a counter the control watches and a "compensation valid" flag), written with
the offset by every controller backend, over a real link to the protocol's own server: an
asyncua server, pymodbus's RTU server on a pseudo-terminal, python-snap7's S7 server, pymodbus's
Modbus TCP server, pyads's ADS test server, the loopback FOCAS and Haas MDC servers, and line
devices on pseudo-terminals (Haas Q/E, a generic line protocol).

The contract, once for every backend: ``write(x, Life(n, True))`` leaves the offset, the counter
n and the flag true in the controller; ``write(None, Life(n + 1, False))`` leaves the offset,
moves the counter and clears the flag; a link configured without one ignores ``life``; a
refused counter or flag is a failed write, never an exception. Then what each protocol does
in one request, and the settings.
"""

from __future__ import annotations

import asyncio
import re
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from devices import LineDevice, ModbusDevice, PtyPair, Registers

from cnc_adapters import (
    LIFE_MODULUS,
    Adapter,
    ConfigError,
    FailureKind,
    Life,
    WriteResult,
    check_adapter,
    open_adapter,
)
from cnc_adapters.control_profiles import PROFILES, adapter_settings
from machine_sim.vcnc import free_port

NS_URI = "urn:thermocomp:virtual-cnc"
SPINDLE = "/CncInterface/CncSpindleList/Spindle1/"


def node(name: str) -> str:
    return f"ns={{ns}};s={SPINDLE}{name}"


@dataclass
class LifeRig:
    """A controller with its own server, and links to it."""

    make: Callable[..., Adapter]
    """A link whose sign of life is configured (keywords: more options)."""
    plain: Callable[[], Adapter]
    """The same link without a sign of life."""
    refusing: Callable[[], Adapter]
    """A link whose flag goes where the controller refuses a write."""
    offset: Callable[[], float | None]
    """The offset the controller holds, raw."""
    life: Callable[[], tuple[Any, Any]]
    """The counter and the flag the controller holds, as it holds them."""
    refused_offset: dict[str, Any]
    """Options that put the offset where the controller refuses a write."""


def counter_of(v: Any) -> int | None:
    return None if v is None else int(v)


def flag_of(v: Any) -> bool | None:
    return None if v is None else bool(v)


# -- an OPC UA controller: asyncua's server with the virtual CNC's node names ------------------


@dataclass
class UaController:
    url: str
    loop: asyncio.AbstractEventLoop
    server: Any
    ns: int
    nodes: dict[str, Any]
    writes: list[list[str]]
    """Every Write request the server served: the node ids it wrote, in order."""

    def value(self, name: str) -> Any:
        async def read() -> Any:
            return await self.nodes[name].read_value()

        return asyncio.run_coroutine_threadsafe(read(), self.loop).result(30)

    def put(self, name: str, value: Any, vtype: Any) -> None:
        from asyncua import ua

        async def write() -> None:
            await self.nodes[name].write_value(ua.DataValue(ua.Variant(value, vtype)))

        asyncio.run_coroutine_threadsafe(write(), self.loop).result(30)


@pytest.fixture(scope="module")
def ua_controller() -> Iterator[UaController]:
    from asyncua import Server, ua
    from asyncua.common.callback import CallbackType

    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    url = f"opc.tcp://127.0.0.1:{free_port()}/life"
    writes: list[list[str]] = []

    async def start() -> UaController:
        server = Server()
        await server.init()
        server.set_endpoint(url)
        ns = await server.register_namespace(NS_URI)
        objects = server.nodes.objects
        nodes: dict[str, Any] = {}
        for name, value, vtype, writable in (
            ("ActSpeed", 12000.0, ua.VariantType.Double, False),
            ("ThermalOffset", 0.0, ua.VariantType.Double, True),
            ("LifeCounter", 0, ua.VariantType.Int32, True),
            ("CompensationValid", False, ua.VariantType.Boolean, True),
            ("R98", 0.0, ua.VariantType.Double, True),  # a SINUMERIK R parameter: a REAL
            ("R99", 0.0, ua.VariantType.Double, True),
            ("Counter16", 0, ua.VariantType.Int16, True),
            ("Counter8", 0, ua.VariantType.Byte, True),
            ("Locked", False, ua.VariantType.Boolean, False),  # not writable
            ("Name", "x", ua.VariantType.String, True),
        ):
            var = await objects.add_variable(ua.NodeId(SPINDLE + name, ns), name, value, vtype)
            if writable:
                await var.set_writable()
            nodes[name] = var

        async def count(event: Any, _dispatcher: Any) -> None:
            ids = [w.NodeId for w in event.request_params.NodesToWrite]
            if any(i.NamespaceIndex == ns for i in ids):  # not the server's own status updates
                writes.append([i.to_string() for i in ids])

        server.subscribe_server_callback(CallbackType.PostWrite, count)
        await server.start()
        return UaController(url, loop, server, ns, nodes, writes)

    ctl = asyncio.run_coroutine_threadsafe(start(), loop).result(60)
    try:
        yield ctl
    finally:
        asyncio.run_coroutine_threadsafe(ctl.server.stop(), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)


def ua_reset(ctl: UaController) -> None:
    from asyncua import ua

    ctl.put("ThermalOffset", 0.0, ua.VariantType.Double)
    ctl.put("LifeCounter", 0, ua.VariantType.Int32)
    ctl.put("CompensationValid", False, ua.VariantType.Boolean)
    ctl.writes.clear()


def ua_link(ctl: UaController, **kw: Any) -> Adapter:
    """The virtual CNC's preset (its sign of life by default), its other channels off; a
    counter or flag given alone is paired with the preset's other one (both must be given)."""
    if ("life_node" in kw) != ("valid_node" in kw):
        kw = {"life_node": node("LifeCounter"), "valid_node": node("CompensationValid"), **kw}
    return open_adapter(
        {
            "type": "opcua",
            "url": ctl.url,
            "preset": "virtual-cnc",
            "input_nodes": {},
            "measurement_node": "",
            "measurement_sequence_node": "",
            "cutting_node": "",
            "verify_writes": False,
            **kw,
        }
    )


# -- the rigs ---------------------------------------------------------------------------------

RIGS = [
    "opcua",
    "modbus",
    "plc-s7",
    "plc-modbus-tcp",
    "plc-ads",
    "focas",
    "haas",
    "haas-mdc",
    "line",
]


def haas_device(regs: Registers, refused: int):
    """A Haas control on a line: ``?Q600`` reads, ``?E`` writes any variable but ``refused``."""

    def handle(text: str, mode: str) -> str | None:
        m = re.match(r"^\?Q600 (\d+)$", text)
        if m:
            var = int(m.group(1))
            value = regs.speed_rpm if var == 3027 else regs.macros.get(var, 0.0)
            return f">MACRO, {var}, {value:.6f}"
        m = re.match(r"^\?E(\d+) (\S+)$", text)
        if m:
            if int(m.group(1)) == refused:
                return "?, INVALID"
            regs.macros[int(m.group(1))] = float(m.group(2))
            if int(m.group(1)) == 10500:
                regs.offset = float(m.group(2))
            return ">!"
        return "?, UNKNOWN COMMAND"

    return handle


def line_device(regs: Registers):
    """A generic line controller: ``OFFSET <x>`` and ``LIFE <counter> <valid>``, both ``OK``."""

    def handle(text: str, mode: str) -> str | None:
        if text == "?SPEED":
            return f"SPEED={regs.speed_rpm:.1f}"
        m = re.match(r"^OFFSET (\S+)$", text)
        if m:
            regs.offset = float(m.group(1))
            return "OK"
        m = re.match(r"^LIFE (\d+) ([01])$", text)
        if m:
            regs.macros[1] = float(m.group(1))
            regs.macros[2] = float(m.group(2))
            return "OK"
        return "ERR unknown"

    return handle


@pytest.fixture(params=RIGS)
def rig(request: pytest.FixtureRequest, tmp_path: Any) -> Iterator[LifeRig]:
    kind = request.param
    if kind == "opcua":
        ctl = request.getfixturevalue("ua_controller")
        ua_reset(ctl)
        yield LifeRig(
            lambda **kw: ua_link(ctl, **kw),
            lambda: ua_link(ctl, life_node="", valid_node=""),
            lambda: ua_link(ctl, valid_node=node("Locked")),
            lambda: ctl.value("ThermalOffset"),
            lambda: (ctl.value("LifeCounter"), ctl.value("CompensationValid")),
            {"offset_node": node("Locked")},
        )
    elif kind == "modbus":
        pty = PtyPair(tmp_path)
        dev = ModbusDevice(pty.dev)

        def held(address: int, count: int) -> list[int]:
            return list(dev._run(dev.server.context.async_getValues(1, 3, address, count)))

        def life() -> tuple[Any, Any]:
            counter, flag = held(2, 2)
            return counter, flag

        base = {"type": "modbus", "port": pty.ctl, "baudrate": 115200, "offset_register": 0}
        try:
            yield LifeRig(
                lambda **kw: open_adapter({**base, "life_register": 2, "valid_register": 3, **kw}),
                lambda: open_adapter(base),
                # the device has 16 holding registers: 40 is an illegal address
                lambda: open_adapter({**base, "life_register": 2, "valid_register": 40}),
                dev.offset,
                life,
                {"offset_register": 40},
            )
        finally:
            dev.close()
            pty.close()
    elif kind.startswith("plc-"):
        from machine_sim.plc_servers import AdsPlc, ModbusTcpPlc, S7Plc

        cls, addresses, life_at, refused, refused_offset = {
            # the counter and the flag next to the offset: one request for all three
            "plc-s7": (
                S7Plc,
                {"offset_address": "DB100.DBD0", "speed_address": "DB100.DBD8"},
                {"life_address": "DB100.DBW4", "valid_address": "DB100.DBW6"},
                "DB999.DBW0",  # no such DB on the PLC
                {"offset_address": "DB999.DBD0"},
            ),
            "plc-modbus-tcp": (
                ModbusTcpPlc,
                {"offset_address": "hr:0", "speed_address": "ir:0"},
                {"life_address": "hr:2", "valid_address": "hr:3"},
                "hr:200",  # past its 64 registers
                {"offset_address": "hr:200"},
            ),
            "plc-ads": (
                AdsPlc,
                {
                    "offset_address": "GVL_Thermo.nTempComp",
                    "offset_type": "DINT",
                    "speed_address": "GVL_Thermo.fSpeed",
                },
                {
                    "life_address": "GVL_Thermo.nLifeCounter",
                    "valid_address": "GVL_Thermo.bCompValid",
                },
                "GVL_Thermo.bNoSuchFlag",
                {"offset_address": "GVL_Thermo.nNoSuchComp"},
            ),
        }[kind]
        plc = cls(None, held_address=None, cutting_address=None, **addresses, **life_at).start()  # type: ignore[arg-type]
        base = {
            "type": "plc",
            "protocol": cls.protocol,
            "host": plc.host,
            "port": plc.port,
            **addresses,
        }
        try:
            yield LifeRig(
                lambda **kw: open_adapter({**base, **life_at, **kw}),
                lambda: open_adapter(base),
                lambda: open_adapter({**base, **life_at, "valid_address": refused}),
                lambda: plc.get("offset"),
                lambda: (plc.get("life"), plc.get("valid")),
                refused_offset,
            )
        finally:
            plc.close()
    elif kind == "focas":
        from machine_sim.focas_server import FocasServer, PlainControl

        control = PlainControl()
        with FocasServer(control, protected=(599,)) as srv:
            base = {"type": "focas", "host": "127.0.0.1", "port": srv.port}
            yield LifeRig(
                lambda **kw: open_adapter({**base, "life_macro": 502, "valid_macro": 503, **kw}),
                lambda: open_adapter(base),
                lambda: open_adapter({**base, "life_macro": 502, "valid_macro": 599}),
                lambda: control.held_raw,
                lambda: (srv.variables.get(502), srv.variables.get(503)),
                {"offset_macro": 599},
            )
    elif kind == "haas-mdc":
        from compensator.clock import SteppedClock
        from machine_sim import SpindlePlant, preset
        from machine_sim.controls import EmulatedControl
        from machine_sim.haas_server import HaasMdcServer
        from machine_sim.vcnc import VirtualMachine

        vm = VirtualMachine(
            SpindlePlant(preset("motorized-27k"), seed=4), None, clock=SteppedClock()
        )
        control = EmulatedControl(vm, PROFILES["haas"])
        with HaasMdcServer(control) as srv:
            base = {"profile": "haas", "route": "mdc", "host": "127.0.0.1", "port": srv.port}
            yield LifeRig(
                lambda **kw: open_adapter({**base, **kw}),  # the profile's #10501 and #10502
                lambda: open_adapter({**base, "life_var": "", "valid_var": ""}),
                # not writable over MDC (the counter: the profile's, given with it)
                lambda: open_adapter({**base, "life_var": 10501, "valid_var": 9999}),
                lambda: control.held_um,  # the profile's unit (mm) and sign, as um
                lambda: (srv.macros.get(10501), srv.macros.get(10502)),
                {"offset_var": 9999},
            )
    else:  # a line device: Haas Q/E, or the generic line protocol
        pty = PtyPair(tmp_path)
        regs = Registers()
        if kind == "haas":
            dev = LineDevice(pty.dev, haas_device(regs, refused=10999))
            base = {"type": "haas", "port": pty.ctl}
            life = {"life_var": 10501, "valid_var": 10502}
            refusing = {"life_var": 10501, "valid_var": 10999}
            refused_offset: dict[str, Any] = {"offset_var": 10999}
            held = (10501, 10502)
        else:
            dev = LineDevice(pty.dev, line_device(regs))
            base = {"type": "line", "port": pty.ctl}
            life = {"life_request": "LIFE {counter} {valid}"}
            refusing = {"life_request": "NOLIFE {counter} {valid}"}  # answered "ERR unknown"
            refused_offset = {"offset_request": "NOOFFSET {value:.4f}"}
            held = (1, 2)
        try:
            yield LifeRig(
                lambda **kw: open_adapter({**base, **life, **kw}),
                lambda: open_adapter(base),
                lambda: open_adapter({**base, **refusing}),
                lambda: regs.offset,
                lambda: (regs.macros.get(held[0]), regs.macros.get(held[1])),
                refused_offset,
            )
        finally:
            dev.stop()
            pty.close()


# -- the contract -----------------------------------------------------------------------------


def test_the_offset_the_counter_and_the_flag_reach_the_controller(rig: LifeRig) -> None:
    with rig.make() as link:
        assert link.writes_life and link.capabilities.life_sign
        assert link.write(-7.0, Life(41, True)) == WriteResult()
        assert rig.offset() == pytest.approx(-7.0)
        counter, flag = rig.life()
        assert (counter_of(counter), flag_of(flag)) == (41, True)


def test_a_confirmation_moves_the_counter_clears_the_flag_and_leaves_the_offset(
    rig: LifeRig,
) -> None:
    with rig.make() as link:
        assert link.write(-7.0, Life(41, True)).taken
        assert link.write(None, Life(42, False)) == WriteResult()
        assert rig.offset() == pytest.approx(-7.0)
        counter, flag = rig.life()
        assert (counter_of(counter), flag_of(flag)) == (42, False)
        # the counter's last value fits a signed 16-bit word of every control
        assert link.write(3.0, Life(LIFE_MODULUS, True)).taken
        counter, flag = rig.life()
        assert (counter_of(counter), flag_of(flag)) == (LIFE_MODULUS, True)
        assert rig.offset() == pytest.approx(3.0)


def test_a_link_without_a_sign_of_life_ignores_it(rig: LifeRig) -> None:
    before = rig.life()
    with rig.plain() as link:
        assert not link.writes_life and not link.capabilities.life_sign
        assert link.write(-5.0, Life(9, True)).taken
        assert rig.offset() == pytest.approx(-5.0)
        assert link.write(None, Life(10, True)) == WriteResult()  # nothing to write
    assert rig.life() == before


def test_a_refused_counter_or_flag_leaves_the_offset_taken(rig: LifeRig) -> None:
    # a control without the counter or the flag (or refusing them) still gets its offset: the
    # sign of life's failure is apart, never an exception
    with rig.refusing() as link:
        assert link.writes_life
        done = link.write(-6.0, Life(7, True))
        assert done.taken and done.failure is None
        assert done.life_failure is not None
        assert done.life_failure.kind in (FailureKind.REFUSED, FailureKind.FAILED), done
        assert rig.offset() == pytest.approx(-6.0)
        confirm = link.write(None, Life(8, False))
        assert confirm.failure is None  # a confirmation writes no offset
        assert confirm.life_failure is not None
        assert link.write(-4.0, Life(9, True)).life_failure is not None  # each time
        assert rig.offset() == pytest.approx(-4.0)
        assert link.read().speed_read  # the link itself is up


def test_a_refused_offset_sends_no_beat(rig: LifeRig) -> None:
    # the offset goes first: a control never sees a beat that says "valid" for an offset it
    # refused
    with rig.make() as link:
        assert link.write(-7.0, Life(41, True)).taken
    before = rig.life()
    with rig.make(**rig.refused_offset) as link:
        done = link.write(-6.0, Life(42, True))
        assert done.failure is not None, done
        assert done.failure.kind in (FailureKind.REFUSED, FailureKind.FAILED), done.failure
        assert done.life_failure is None  # the offset's failure, nothing said of the life
    assert rig.life() == before
    assert rig.offset() == pytest.approx(-7.0)


def test_a_bad_sign_of_life_never_leaves(rig: LifeRig) -> None:
    with rig.make() as link:
        assert link.write(-7.0, Life(41, True)).taken
        broken = Life(5, True)
        object.__setattr__(broken, "counter", 40000)  # past a 16-bit word
        for bad in (broken, (5, True), 5):
            done = link.write(1.0, bad)  # type: ignore[arg-type]
            assert done.failure is not None and done.failure.kind is FailureKind.VALUE
        assert rig.offset() == pytest.approx(-7.0)  # nothing was sent
        counter, flag = rig.life()
        assert (counter_of(counter), flag_of(flag)) == (41, True)


# -- one request where the protocol allows ----------------------------------------------------


def test_opcua_writes_the_offset_then_counter_and_flag_in_one_write_request(
    ua_controller: UaController,
) -> None:
    # a server takes each node of a Write on its own: the beat goes once the offset is Good
    ctl = ua_controller
    ua_reset(ctl)
    offset, life, valid = (
        f"ns={ctl.ns};s={SPINDLE}{n}" for n in ("ThermalOffset", "LifeCounter", "CompensationValid")
    )
    with ua_link(ctl) as link:
        for k in range(1, 4):
            assert link.write(-2.0 * k, Life(k, k % 2 == 1)).taken
        assert link.write(None, Life(4, False)).taken
    assert ctl.writes == [[offset], [life, valid]] * 3 + [[life, valid]]
    assert ctl.value("LifeCounter") == 4 and ctl.value("CompensationValid") is False
    assert ctl.value("ThermalOffset") == -6.0


def test_opcua_writes_each_value_in_its_nodes_own_type(ua_controller: UaController) -> None:
    from asyncua import ua

    ctl = ua_controller
    ua_reset(ctl)
    ctl.put("R98", 0.0, ua.VariantType.Double)
    with ua_link(ctl, life_node=node("R98"), valid_node=node("R99")) as link:  # R parameters
        assert link.write(1.5, Life(300, True)).taken
        assert (ctl.value("R98"), ctl.value("R99")) == (300.0, 1.0)
        assert link.write(None, Life(301, False)).taken
        assert (ctl.value("R98"), ctl.value("R99")) == (301.0, 0.0)
    with ua_link(ctl, life_node=node("Counter16")) as link:  # an Int16 counter
        assert link.write(None, Life(LIFE_MODULUS, True)).taken
        assert ctl.value("Counter16") == LIFE_MODULUS
    with ua_link(ctl, life_node=node("Counter8")) as link:  # a Byte cannot hold 32767
        ctl.writes.clear()
        done = link.write(2.5, Life(300, True))
        assert done.taken  # the offset went
        assert done.life_failure is not None and done.life_failure.kind is FailureKind.FAILED
        # the counter runs to 32767: a Byte is refused from the first beat, not the 256th
        assert "32767 does not fit its Byte" in done.life_failure.reason
        assert ctl.writes == [[f"ns={ctl.ns};s={SPINDLE}ThermalOffset"]]  # no beat sent
        assert ctl.value("ThermalOffset") == 2.5
    with ua_link(ctl, life_node=node("Name")) as link:  # a String is no counter
        done = link.write(None, Life(5, True))
        assert done.failure is None and done.life_failure is not None
        assert "not a Boolean, an integer" in done.life_failure.reason


def test_opcua_a_node_that_does_not_exist_is_a_failed_write_that_names_it(
    ua_controller: UaController,
) -> None:
    ctl = ua_controller
    ua_reset(ctl)
    with ua_link(ctl, life_node=node("NoSuchCounter")) as link:
        done = link.write(-3.0, Life(1, True))
        assert done.taken and ctl.value("ThermalOffset") == -3.0
        failure = done.life_failure
        assert failure is not None and failure.kind is FailureKind.FAILED
        assert "NoSuchCounter" in failure.reason
        assert "BadNodeIdUnknown" in failure.reason
        assert 'life_node = ""' in failure.reason  # how to turn it off
        assert link.read().speed_read


def test_opcua_a_refused_flag_names_its_node_and_the_offset_still_counts(
    ua_controller: UaController,
) -> None:
    ctl = ua_controller
    ua_reset(ctl)
    with ua_link(ctl, valid_node=node("Locked")) as link:
        done = link.write(-4.0, Life(3, True))
        assert done.taken
        failure = done.life_failure
        assert failure is not None and failure.kind is FailureKind.REFUSED
        assert "Locked" in failure.reason and "valid flag" in failure.reason
    assert ctl.value("ThermalOffset") == -4.0


def test_focas_writes_the_offset_then_counter_and_flag_in_one_request() -> None:
    # the CNC takes each subpacket of a request on its own: the beat goes once the offset is
    # taken
    from machine_sim.focas_server import FocasServer, PlainControl

    control = PlainControl()
    with FocasServer(control) as srv:
        with open_adapter(
            {"profile": "fanuc", "host": "127.0.0.1", "port": srv.port}  # #502 and #503
        ) as link:
            before = srv.requests
            assert link.write(-12.0, Life(5, True)).taken
            assert srv.requests == before + 2
            assert link.write(None, Life(6, False)).taken
            assert srv.requests == before + 3
    assert control.held_raw == 12.0  # the profile's sign: +S
    assert (srv.variables[502], srv.variables[503]) == (6.0, 0.0)


@pytest.mark.parametrize(
    ("life", "writes"),
    [
        ({"life_register": 2, "valid_register": 3}, [(0, 4)]),  # one run: one request
        ({"life_register": 3, "valid_register": 2}, [(0, 4)]),  # in any order
        ({"life_register": 5, "valid_register": 6}, [(0, 2), (5, 2)]),  # a gap: two
    ],
)
def test_modbus_writes_adjacent_registers_in_one_request(
    tmp_path: Any, life: dict[str, int], writes: list[tuple[int, int]]
) -> None:
    pty = PtyPair(tmp_path)
    dev = ModbusDevice(pty.dev)
    try:
        link = open_adapter(
            {"type": "modbus", "port": pty.ctl, "baudrate": 115200, "offset_register": 0, **life}
        )
        with link:
            client = link._modbus.client  # type: ignore[attr-defined]
            sent: list[tuple[int, int]] = []
            real = client.write_registers

            def counted(address: int, values: list[int], **kw: Any) -> Any:  # the real call
                sent.append((address, len(values)))
                return real(address, values, **kw)

            client.write_registers = counted
            assert link.write(-7.5, Life(12, True)).taken
            assert sent == writes
        regs = dev._run(dev.server.context.async_getValues(1, 3, 0, 8))
        assert regs[life["life_register"]] == 12 and regs[life["valid_register"]] == 1
        assert dev.offset() == pytest.approx(-7.5)
    finally:
        dev.close()
        pty.close()


def test_plc_writes_adjacent_words_in_one_request() -> None:
    from machine_sim.plc_servers import S7Plc

    plc = S7Plc(
        None,
        held_address=None,
        cutting_address=None,
        life_address="DB100.DBW4",
        valid_address="DB100.DBW6",
        speed_address="DB100.DBD8",
    ).start()  # type: ignore[arg-type]
    try:
        link = open_adapter(
            {
                "type": "plc",
                "protocol": "s7",
                "host": plc.host,
                "port": plc.port,
                "offset_address": "DB100.DBD0",
                "speed_address": "DB100.DBD8",
                "life_address": "DB100.DBW4",
                "valid_address": "DB100.DBW6",
            }
        )
        with link:
            client = link._driver.client  # type: ignore[attr-defined]
            sent: list[tuple[int, int, int]] = []
            real = client.db_write

            def counted(db: int, start: int, data: bytearray) -> Any:  # the real call
                sent.append((db, start, len(data)))
                return real(db, start, data)

            client.db_write = counted
            assert link.write(-2.5, Life(77, True)).taken
            assert link.write(None, Life(78, False)).taken
        assert sent == [(100, 0, 8), (100, 4, 4)]
        assert (plc.get("offset"), plc.get("life"), plc.get("valid")) == (-2.5, 78, 0)
    finally:
        plc.close()


def test_ads_writes_the_offset_then_the_life_symbols_in_one_sum_request() -> None:
    # a sum-write takes each symbol on its own: the beat goes once the offset is taken
    from machine_sim.plc_servers import AdsPlc

    plc = AdsPlc(None).start()  # type: ignore[arg-type]  # the beckhoff profile's symbols
    requests: list[int] = []
    real = plc.handler.handle_request

    def counted(request: Any) -> Any:  # the server's own handler, each request counted
        requests.append(1)
        return real(request)

    plc.handler.handle_request = counted
    try:
        with open_adapter(
            {
                "profile": "beckhoff",
                "host": plc.host,
                "port": plc.port,
                "ams_net_id": "127.0.0.1.1.1",
                "offset_address": "GVL_Thermo.nTempComp",
                "speed_address": "GVL_Thermo.fSpeed",
            }
        ) as link:
            assert link.write(-1.0, Life(1, True)).taken  # asks each symbol's info once
            requests.clear()
            assert link.write(-1.5, Life(2, True)).taken
            assert len(requests) == 2  # the offset's, then the counter's and the flag's
            assert link.write(None, Life(3, False)).taken
            assert len(requests) == 3
        assert (plc.get("offset"), plc.get("life"), plc.get("valid")) == (15, 3, False)
    finally:
        plc.close()


# -- the settings -----------------------------------------------------------------------------


def test_profiles_default_the_sign_of_life_and_an_empty_value_turns_it_off() -> None:
    cases = {
        ("sinumerik", "opcua"): (
            {"url": "opc.tcp://h:4840", "offset_node": "ns=2;s=X"},
            "life_node",
        ),
        ("sinumerik", "s7"): (
            {"host": "h", "offset_address": "DB100.DBD0", "speed_address": "DB100.DBD4"},
            "life_address",
        ),
        ("fanuc", "focas"): ({"host": "h"}, "life_macro"),
        ("haas", "mdc"): ({"host": "h"}, "life_var"),
        ("haas", "serial"): ({"port": "/dev/null"}, "life_var"),
        ("beckhoff", "ads"): (
            {"host": "10.0.0.7", "offset_address": "G.a", "speed_address": "G.b"},
            "life_address",
        ),
        ("virtual", "opcua"): ({"url": "opc.tcp://h:4840"}, "life_node"),
    }
    for (name, route), (given, key) in cases.items():
        cfg = {"profile": name, "route": route, **given}
        merged = adapter_settings(cfg)
        valid_key = key.replace("life", "valid")
        if name != "virtual":  # the virtual CNC's preset names its nodes itself
            assert merged[key] and merged[valid_key], (name, route)
        link = open_adapter(cfg)
        assert link.writes_life, (name, route)
        off = open_adapter({**cfg, key: "", valid_key: ""})
        assert not off.writes_life, (name, route)
        with pytest.raises(ConfigError, match="needs both"):
            check_adapter({**cfg, key: ""})  # one alone
    # in a URL too: an empty value turns the preset's off
    assert open_adapter("opc.tcp://h:4840?preset=virtual-cnc").writes_life
    assert not open_adapter(
        "opc.tcp://h:4840?preset=virtual-cnc&life_node=&valid_node="
    ).writes_life
    # no default without a profile: a bare link writes no sign of life
    assert not open_adapter("focas://h:8193").writes_life
    assert not open_adapter(
        {
            "profile": "heidenhain",
            "protocol": "s7",
            "host": "h",
            "offset_address": "DB1.DBD0",
            "speed_address": "DB1.DBD4",
        }
    ).writes_life
    for p in PROFILES.values():
        assert p.life_sign and p.life_sign in p.describe()


@pytest.mark.parametrize(
    ("cfg", "says"),
    [
        (
            {"type": "focas", "host": "h", "life_macro": 501},
            "needs both life_macro and valid_macro",
        ),
        (
            {"type": "focas", "host": "h", "life_macro": 501, "valid_macro": 500},
            "offset_macro and valid_macro are both #500",
        ),
        ({"type": "focas", "host": "h", "life_macro": 50, "valid_macro": 502}, "life_macro"),
        (
            {"type": "haas", "port": "/dev/x", "life_var": 10500, "valid_var": 10502},
            "life_var and valid_var must be two macro variables of their own",
        ),
        (
            {"type": "haas", "port": "/dev/x", "life_request": "LIFE {counter} {valid}"},
            "not life_request",
        ),
        ({"type": "line", "port": "/dev/x", "life_request": "LIFE {counter}"}, "life_request"),
        (
            {"type": "modbus", "port": "/dev/x", "life_register": 1, "valid_register": 2},
            "offset_register 0 (float32) and life_register 1 (int16) overlap",
        ),
        (
            {
                "type": "plc",
                "protocol": "s7",
                "host": "h",
                "offset_address": "DB1.DBD0",
                "speed_address": "DB1.DBD4",
                "life_address": "DB1.DBW8",
                "valid_address": "DB1.DBX10.0",
            },
            "give a word",
        ),
        (
            {
                "type": "plc",
                "protocol": "modbus-tcp",
                "host": "h",
                "offset_address": "hr:0",
                "speed_address": "hr:2",
                "life_address": "ir:8",
                "valid_address": "hr:9",
            },
            "life_address = 'ir:8': expected a holding register",
        ),
        (
            {
                "type": "plc",
                "protocol": "modbus-tcp",
                "host": "h",
                "offset_address": "hr:0",
                "speed_address": "hr:4",
                "life_address": "hr:1",
                "valid_address": "hr:9",
            },
            "offset_address hr:0 and life_address hr:1 overlap",
        ),
        (
            {"type": "opcua", "url": "opc.tcp://h:4840", "preset": "virtual-cnc", "valid_node": ""},
            "needs both life_node (or life_path) and valid_node (or valid_path)",
        ),
    ],
)
def test_a_bad_sign_of_life_setting_is_one_clear_line(cfg: dict[str, Any], says: str) -> None:
    with pytest.raises(ConfigError) as err:
        check_adapter(cfg)
    assert says in str(err.value)
    assert "\n" not in str(err.value)


# -- the emulated controls hand the sign of life to their watch --------------------------------


class Watching:
    """A control's watch as the emulated servers feed it: the beats it was given."""

    def __init__(self) -> None:
        self.beats: list[tuple[Any, Any]] = []

    def life_beat(self, counter: object, valid: object) -> None:
        self.beats.append((counter, valid))


def test_the_emulated_controls_hand_the_sign_of_life_to_their_watch() -> None:
    from compensator.clock import SteppedClock
    from machine_sim import SpindlePlant, preset
    from machine_sim.controls import EmulatedControl
    from machine_sim.focas_server import FocasServer, PlainControl
    from machine_sim.haas_server import HaasMdcServer
    from machine_sim.plc_servers import S7Plc
    from machine_sim.vcnc import VirtualMachine

    class FocasControl(PlainControl, Watching):
        def __init__(self) -> None:
            PlainControl.__init__(self)
            Watching.__init__(self)

    class Control(EmulatedControl):
        def life_beat(self, counter: object, valid: object) -> None:
            self.__dict__.setdefault("beats", []).append((counter, valid))

    focas = FocasControl()
    with FocasServer(focas) as srv:
        with open_adapter({"profile": "fanuc", "host": "127.0.0.1", "port": srv.port}) as link:
            assert link.write(-3.0, Life(1, True)).taken
            assert link.write(None, Life(2, False)).taken
    assert focas.beats == [(1.0, 1.0), (2.0, 0.0)]

    def machine(name: str) -> Control:
        clock = SteppedClock()
        vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=4), None, clock=clock)
        return Control(vm, PROFILES[name])

    haas = machine("haas")
    with HaasMdcServer(haas) as srv:
        cfg = {"profile": "haas", "host": "127.0.0.1", "port": srv.port}
        with open_adapter(cfg) as link:
            assert link.write(-3.0, Life(7, True)).taken
    # each ?E is a beat: the counter first (the flag not yet written), then both
    assert haas.__dict__["beats"] == [(7.0, None), (7.0, 1.0)]

    s7 = machine("sinumerik")
    plc = S7Plc(s7).start()  # the sinumerik profile's DB100 layout
    try:
        cfg = {
            "profile": "sinumerik",
            "route": "s7",
            "host": plc.host,
            "port": plc.port,
            "offset_address": "DB100.DBD0",
            "speed_address": "DB100.DBD4",
        }
        with open_adapter(cfg) as link:
            assert link.write(-3.0, Life(9, True)).taken
            plc.sync()  # the PLC's scan
            assert link.write(None, Life(10, False)).taken
            plc.sync()
        assert s7.__dict__["beats"] == [(9, 1), (10, 0)]
    finally:
        plc.close()


@pytest.mark.parametrize("verify", [True, "deferred"])
def test_opcua_checks_the_offset_of_a_combined_write_as_configured(
    ua_controller: UaController, verify: Any
) -> None:
    ctl = ua_controller
    ua_reset(ctl)
    with ua_link(ctl, verify_writes=verify) as link:
        done = link.write(-8.0, Life(5, True))
        assert done.taken and done.pending == (verify == "deferred")
        assert link.read().write_refused_um is None  # the controller holds what was written
        assert link.write(None, Life(6, True)) == WriteResult()  # a confirmation: no check due
    assert len(ctl.writes) == 3 and ctl.value("ThermalOffset") == -8.0


# -- a sign of life that cannot be written never keeps the offset from the controller ----------
#
# The profiles and the virtual-cnc preset default a counter and a flag. A server that does not
# have them (any control commissioned before; a SINUMERIK whose user may not write R
# parameters; a Beckhoff project without GVL_Thermo) still gets its offset; the write says
# apart that the sign of life failed.


def test_a_missing_life_node_does_not_keep_the_offset_from_the_controller(
    ua_controller: UaController,
) -> None:
    ctl = ua_controller
    ua_reset(ctl)
    with ua_link(ctl, life_node=node("NoSuchCounter")) as link:
        done = link.write(-3.0, Life(1, True))
    assert done.life_failure is not None  # the sign of life failed, and says so
    assert done.failure is None
    assert ctl.value("ThermalOffset") == -3.0, "the offset never reached the controller"


def test_modbus_a_refused_run_of_offset_and_life_is_followed_by_the_offset_alone(
    tmp_path: Any,
) -> None:
    # the device has 16 holding registers: the offset (float32) in 14..15 and the counter and
    # flag at 16 and 17 make one run the device refuses whole; the offset then goes alone
    pty = PtyPair(tmp_path)
    dev = ModbusDevice(pty.dev)
    try:
        link = open_adapter(
            {
                "type": "modbus",
                "port": pty.ctl,
                "baudrate": 115200,
                "offset_register": 14,
                "life_register": 16,
                "valid_register": 17,
            }
        )
        with link:
            client = link._modbus.client  # type: ignore[attr-defined]
            sent: list[tuple[int, int]] = []
            real = client.write_registers

            def counted(address: int, values: list[int], **kw: Any) -> Any:  # the real call
                sent.append((address, len(values)))
                return real(address, values, **kw)

            client.write_registers = counted
            done = link.write(-7.5, Life(12, True))
            assert done.taken and done.life_failure is not None
            assert "life counter" in done.life_failure.reason
            assert sent == [(14, 4), (14, 2)]  # one more request, only for the refusal
            assert link.read_offset_um() == pytest.approx(-7.5)
            sent.clear()
            confirm = link.write(None, Life(13, True))
            assert confirm.failure is None and confirm.life_failure is not None
            assert sent == [(16, 2)]
    finally:
        dev.close()
        pty.close()


@pytest.mark.parametrize(
    ("life", "writes"),
    [
        ({"life_register": 12, "valid_register": 13}, [(8, 2), (12, 2)]),  # after the offset
        ({"life_register": 0, "valid_register": 1}, [(8, 2), (0, 2)]),  # before it: still 2nd
    ],
)
def test_modbus_the_offset_goes_first(
    tmp_path: Any, life: dict[str, int], writes: list[tuple[int, int]]
) -> None:
    pty = PtyPair(tmp_path)
    dev = ModbusDevice(pty.dev)
    try:
        link = open_adapter(
            {"type": "modbus", "port": pty.ctl, "baudrate": 115200, "offset_register": 8, **life}
        )
        with link:
            client = link._modbus.client  # type: ignore[attr-defined]
            sent: list[tuple[int, int]] = []
            real = client.write_registers

            def counted(address: int, values: list[int], **kw: Any) -> Any:  # the real call
                sent.append((address, len(values)))
                return real(address, values, **kw)

            client.write_registers = counted
            assert link.write(-7.5, Life(12, True)) == WriteResult()
            assert sent == writes
    finally:
        dev.close()
        pty.close()


def test_run_check_looks_up_the_life_nodes_and_says_each_missing_one(
    tmp_path: Any, calibrated_model: Any
) -> None:
    """`run --check` on the virtual CNC over OPC UA looks the sign of life's nodes up (nothing
    written): the preset's are there (no line); missing ones: one warning line each, naming
    the node and how to turn the sign of life off; the check still passes."""
    import subprocess
    import sys

    from machine_sim import SpindlePlant, preset
    from machine_sim.vcnc import VirtualCNC, VirtualMachine, running, step

    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=lambda: 0.0)
    missing = f', life_node = "{node("NoSuchCounter")}", valid_node = "{node("NoSuchFlag")}"'
    out = {}
    with running(VirtualCNC(vm, tick_s=None)) as cnc:
        step(cnc)
        for name, life in (("found", ""), ("missing", missing)):
            cfg = tmp_path / f"{name}.toml"
            cfg.write_text(
                f'state_dir = "{tmp_path / "state"}"\n[[spindle]]\nname = "s1"\n'
                f'model = "{calibrated_model}"\n'
                f'adapter = {{url = "{cnc.url}", preset = "virtual-cnc"{life}}}\n'
            )
            r = subprocess.run(
                [sys.executable, "-m", "thermocomp", "run", "--config", str(cfg), "--check"],
                capture_output=True,
                text=True,
                timeout=120,
            )
            assert r.returncode == 0, r.stderr
            out[name] = r.stdout
    head = "s1: warning: the sign of life cannot be written: "
    assert "link ok" in out["found"] and head not in out["found"]
    lines = [line for line in out["missing"].splitlines() if line.startswith(head)]
    assert len(lines) == 2, out["missing"]
    assert "NoSuchCounter" in lines[0] and "BadNodeIdUnknown" in lines[0]
    assert 'life_node = ""' in lines[0]
    assert "NoSuchFlag" in lines[1] and 'valid_node = ""' in lines[1]


def test_plc_a_refused_run_of_offset_and_life_is_followed_by_the_offset_alone() -> None:
    # the PLC's DB100 ends at byte 64: the offset's REAL in 60..63 and the counter and flag
    # words at 64 and 66 make one db_write the PLC refuses whole; the offset then goes alone
    from machine_sim.plc_servers import S7Plc

    plc = S7Plc(
        None,
        held_address=None,
        cutting_address=None,
        offset_address="DB100.DBD60",
        speed_address="DB100.DBD8",
    ).start()  # type: ignore[arg-type]
    try:
        link = open_adapter(
            {
                "type": "plc",
                "protocol": "s7",
                "host": plc.host,
                "port": plc.port,
                "offset_address": "DB100.DBD60",
                "speed_address": "DB100.DBD8",
                "life_address": "DB100.DBW64",
                "valid_address": "DB100.DBW66",
            }
        )
        with link:
            client = link._driver.client  # type: ignore[attr-defined]
            sent: list[tuple[int, int, int]] = []
            real = client.db_write

            def counted(db: int, start: int, data: bytearray) -> Any:  # the real call
                sent.append((db, start, len(data)))
                return real(db, start, data)

            client.db_write = counted
            done = link.write(-2.5, Life(77, True))
            assert done.taken and done.life_failure is not None
            assert "DB100.DBW64" in done.life_failure.reason
            assert sent == [(100, 60, 8), (100, 60, 4)]
        assert plc.get("offset") == -2.5
    finally:
        plc.close()


# -- what run --check says, and a half-given sign of life ------------------------------------

HALF_GIVEN = {
    "fanuc alone": {"profile": "fanuc", "host": "h", "life_macro": 600},
    "beckhoff alone": {
        "profile": "beckhoff",
        "host": "10.0.0.7",
        "offset_address": "G.a",
        "speed_address": "G.b",
        "life_address": "MAIN.nBeat",
    },
    "sinumerik opcua flag alone": {
        "profile": "sinumerik",
        "url": "opc.tcp://h:4840",
        "offset_node": "ns=2;s=X",
        "valid_node": "ns=2;s=/Channel/Parameter/R[u1,97]",
    },
    "sinumerik s7 flag alone": {
        "profile": "sinumerik",
        "route": "s7",
        "host": "h",
        "offset_address": "DB100.DBD0",
        "speed_address": "DB100.DBD4",
        "valid_address": "DB100.DBW20",
    },
    "haas mdc alone": {"profile": "haas", "host": "h", "life_var": 10601},
    "haas serial alone": {
        "profile": "haas",
        "route": "serial",
        "port": "/dev/null",
        "valid_var": 1,
    },
    "virtual by path alone": {"profile": "virtual", "url": "opc.tcp://h:4840", "life_path": "0:X"},
    "virtual-cnc preset alone": {
        "type": "opcua",
        "url": "opc.tcp://h:4840",
        "preset": "virtual-cnc",
        "life_node": "ns=2;s=X",
    },
    "preset in a URL": {"url": "opc.tcp://h:4840?preset=virtual-cnc&valid_node=ns=2;s=X"},
    "one empty": {"profile": "fanuc", "host": "h", "life_macro": ""},
}


@pytest.mark.parametrize("cfg", HALF_GIVEN.values(), ids=HALF_GIVEN.keys())
def test_a_sign_of_life_given_by_half_is_refused_where_a_profile_or_preset_has_the_other(
    cfg: dict[str, Any],
) -> None:
    """One alone never pairs with the profile's or preset's default for the other: one line."""
    with pytest.raises(ConfigError) as err:
        check_adapter(cfg)
    text = str(err.value)
    assert "\n" not in text and "the sign of life needs both" in text, text
    assert "or neither" in text and '= ""' in text, text


def test_both_given_or_both_empty_pass_with_a_profile() -> None:
    base = {"profile": "fanuc", "host": "h"}
    assert open_adapter({**base, "life_macro": 600, "valid_macro": 601}).life_macros == (600, 601)  # type: ignore[attr-defined]
    assert not open_adapter({**base, "life_macro": "", "valid_macro": ""}).writes_life
    assert open_adapter(base).life_macros == (502, 503)  # type: ignore[attr-defined]


def test_the_profile_line_says_what_the_configured_link_writes() -> None:
    """``describe`` with the link's settings: its own addresses, or off; never the profile's
    defaults the configuration replaced or turned off."""
    p = PROFILES["beckhoff"]
    base = {"profile": "beckhoff", "host": "h", "offset_address": "G.a", "speed_address": "G.b"}
    default = p.describe(None, adapter_settings(base), True)
    assert "GVL_Thermo.nLifeCounter" in default and "GVL_Thermo.bCompValid" in default
    own = adapter_settings({**base, "life_address": "MAIN.nBeat", "valid_address": "MAIN.bOk"})
    text = p.describe(None, own, True)
    assert "life_address = 'MAIN.nBeat', valid_address = 'MAIN.bOk'" in text
    assert "GVL_Thermo" not in text
    off = adapter_settings({**base, "life_address": "", "valid_address": ""})
    text = p.describe(None, off, False)
    assert "sign of life: off" in text and "GVL_Thermo" not in text
    # without settings (thermocomp controls): the route's defaults
    assert "CompensationValid" in PROFILES["virtual"].describe()
    assert "valid_macro = 503" in PROFILES["fanuc"].describe()


def test_the_virtual_profile_names_its_presets_own_sign_of_life() -> None:
    from cnc_adapters.opcua import PRESETS

    route = PROFILES["virtual"].route()
    for key in ("life_node", "valid_node"):
        assert route.adapter[key] == PRESETS[route.adapter["preset"]][key]


def test_run_check_prints_the_sign_of_life_the_link_writes_and_names_the_options_when_off(
    tmp_path: Any, calibrated_model: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    """`run --check` with the virtual profile on the virtual CNC: the preset's nodes; the
    configured ones; off, with a warning naming the two options and the virtual CNC's page."""
    from machine_sim import SpindlePlant, preset
    from machine_sim.vcnc import VirtualCNC, VirtualMachine, running, step
    from thermocomp.runtime.checks import check

    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=lambda: 0.0)
    variants = {
        "default": "",
        "own": f', life_node = "{node("OtherCounter")}", valid_node = "{node("OtherFlag")}"',
        "off": ', life_node = "", valid_node = ""',
    }
    out = {}
    with running(VirtualCNC(vm, tick_s=None)) as cnc:
        step(cnc)
        for name, life in variants.items():
            cfg = tmp_path / f"{name}.toml"
            cfg.write_text(
                f'state_dir = "{tmp_path / "state"}"\n[[spindle]]\nname = "s1"\n'
                f'model = "{calibrated_model}"\n'
                f'adapter = {{profile = "virtual", url = "{cnc.url}"{life}}}\n'
            )
            assert check(str(cfg)) == 0
            out[name] = capsys.readouterr().out
    profile_line = {
        k: next(x for x in v.splitlines() if x.startswith("s1: profile virtual"))
        for k, v in out.items()
    }
    assert "LifeCounter" in profile_line["default"], profile_line["default"]
    assert "OtherCounter" in profile_line["own"] and "OtherFlag" in profile_line["own"]
    assert "/Spindle1/LifeCounter" not in profile_line["own"]
    assert "sign of life: off" in profile_line["off"]
    assert "LifeCounter" not in profile_line["off"]
    warning = (
        "s1: warning: the control cannot tell when thermocomp stops: set life_node and "
        "valid_node (docs/reference/virtual-machine-tool.md)"
    )
    assert warning in out["off"].splitlines()
    assert warning not in out["default"] and warning not in out["own"]


@pytest.mark.parametrize(
    ("cfg", "says"),
    [
        ({"type": "focas", "host": "h"}, "set life_macro and valid_macro (docs/controls/fanuc.md)"),
        (
            {
                "type": "plc",
                "protocol": "s7",
                "host": "h",
                "offset_address": "DB1.DBD0",
                "speed_address": "DB1.DBD4",
            },
            "set life_address and valid_address (docs/controls/plc.md)",
        ),
        ({"type": "haas-mdc", "host": "h"}, "set life_var and valid_var (docs/controls/haas.md)"),
        (
            {
                "type": "opcua",
                "url": "opc.tcp://h:4840",
                "offset_node": "ns=2;s=A",
                "speed_node": "ns=2;s=B",
            },
            "set life_node and valid_node (docs/controls/index.md)",
        ),
    ],
)
def test_the_no_sign_of_life_warning_names_the_backends_two_options(
    cfg: dict[str, Any], says: str, calibrated_model: Any, tmp_path: Any
) -> None:
    from thermocomp.runtime.checks import life_check
    from thermocomp.runtime.config import SpindleConfig

    sc = SpindleConfig.model_validate(
        {"name": "s1", "model": str(calibrated_model), "adapter": cfg}
    )
    link = open_adapter(cfg)  # not connected: the warning needs none
    assert (
        life_check(sc, link)
        == f"s1: warning: the control cannot tell when thermocomp stops: {says}"
    )


def test_a_long_sign_of_life_refusal_keeps_its_status_code_and_hint_in_the_event() -> None:
    """A long URL and node id before the status code: the failure's reason, the event's msg and
    its error field keep the code and the hint after it whole."""
    import json
    import logging

    from cnc_adapters import Failure, WriteRejectedError
    from thermocomp.runtime.events import JsonLines, event

    reason = (
        f"opcua write life counter node ns=2;s={SPINDLE}LifeCounter at "
        "opc.tcp://cnc-hall2-machine17.example.com:4840/freeopcua/server/: BadUserAccessDenied "
        '(check life_node; life_node = "" turns the sign of life off)'
    )
    assert len(reason) > 200
    failure = Failure.of(WriteRejectedError(reason))
    assert failure.reason == reason
    records: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    log = logging.getLogger("thermocomp.runtime")
    keep = Keep()
    log.addHandler(keep)
    try:
        event(
            "sign_of_life_failed",
            "s1",
            "%s: SIGN_OF_LIFE: the sign of life is not written (%s); the offset is, but "
            "the control's watch sees the counter stop at %d",
            "s1",
            failure.reason,
            7,
            level=logging.ERROR,
            error=failure.reason,
        )
    finally:
        log.removeHandler(keep)
    out = json.loads(JsonLines().format(records[-1]))
    assert out["error"] == reason
    assert f"({reason})" in out["msg"] and "characters cut" not in out["msg"]
