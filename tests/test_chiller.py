"""The chiller links (issue 20) against real peers: the ``modbus`` backend against pymodbus's own
server (:class:`~machine_sim.chiller_server.ChillerServer`) over loopback TCP and over RTU
on a pseudo-terminal pair, the ``opcua`` backend against asyncua's server, and the ``virtual``
backend in process; each backed by the plant's chiller. One contract for every backend, then
each backend's own faults, the server's register map and the settings.
"""

from __future__ import annotations

import math
import socket
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Self

import pytest
from devices import PtyPair

from cnc_adapters.chiller import (
    CHILLERS,
    Chiller,
    ModbusChiller,
    VirtualChiller,
    check_chiller,
    open_chiller,
)
from compensator.errors import (
    AdapterError,
    AdapterTimeoutError,
    BadValueError,
    ConfigError,
    UnreachableError,
    WriteRejectedError,
)
from machine_sim import SpindlePlant, preset
from machine_sim.chiller_server import HOLDING, INPUT, ChillerServer
from machine_sim.vcnc import free_port


class Clock:
    """A clock the test moves: the link's reconnect back-off passes when the test says so."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class CountingLock:
    """A lock that counts how often it was taken."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.taken = 0

    def __enter__(self) -> Self:
        self._lock.acquire()
        self.taken += 1
        return self

    def __exit__(self, *exc: object) -> None:
        self._lock.release()


def make_plant() -> SpindlePlant:
    # the chiller takes 5..35 degC and starts at 16 degC
    return SpindlePlant(preset("mechanical-cooled"))


class OpcUaChillerPlc:
    """asyncua's server with a chiller's nodes as a PLC publishes them: the set point an Int16
    in 0.1 degC (a write goes to the plant's chiller, which clamps it; a read shows what it
    holds), the supply temperature a Double in degC, read from the plant at each request."""

    NAMESPACE = "urn:thermocomp:test-chiller"
    SETPOINT = "ns={ns};s=Chiller.SetPoint"
    SUPPLY = "ns={ns};s=Chiller.Supply"

    def __init__(self, plant: SpindlePlant, lock: Any):
        self.plant = plant
        self.lock = lock
        self.url = f"opc.tcp://127.0.0.1:{free_port()}/chiller"
        self.refuse = False
        self.server: Any = None

    def start(self) -> OpcUaChillerPlc:
        from asyncua import ua
        from asyncua.sync import Server

        server = Server()
        server.set_endpoint(self.url)
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        ns = server.register_namespace(self.NAMESPACE)
        chiller = server.nodes.objects.add_object(f"ns={ns};s=Chiller", f"{ns}:Chiller")
        setpoint = chiller.add_variable(
            self.SETPOINT.format(ns=ns), f"{ns}:SetPoint", ua.Variant(0, ua.VariantType.Int16)
        )
        setpoint.set_writable()
        supply = chiller.add_variable(
            self.SUPPLY.format(ns=ns), f"{ns}:Supply", ua.Variant(0.0, ua.VariantType.Double)
        )

        def read_setpoint(_nodeid: Any, _attr: Any) -> Any:
            with self.lock:
                count = round(self.plant.chiller_setpoint_c * 10)
            return ua.DataValue(ua.Variant(count, ua.VariantType.Int16))

        def write_setpoint(_node: Any, _attr: Any, dv: Any) -> None:
            if self.refuse:  # the chiller in local (panel) mode
                raise ua.UaStatusCodeError(ua.StatusCodes.BadUserAccessDenied)
            with self.lock:
                self.plant.set_chiller_setpoint_c(dv.Value.Value / 10)

        def read_supply(_nodeid: Any, _attr: Any) -> Any:
            with self.lock:
                return ua.DataValue(ua.Variant(float(self.plant.supply_c), ua.VariantType.Double))

        server.start()
        iserver = server.aio_obj.iserver
        iserver.set_attribute_value_callback(setpoint.nodeid, read_setpoint)
        iserver.set_attribute_value_setter(setpoint.nodeid, write_setpoint)
        iserver.set_attribute_value_callback(supply.nodeid, read_supply)
        self.server = server
        return self

    def stop(self) -> None:
        server, self.server = self.server, None
        if server is not None:
            server.stop()


# -- the rigs -------------------------------------------------------------------------------


@dataclass
class Rig:
    backend: str
    settings: dict[str, Any]
    plant: SpindlePlant
    lock: Any
    unplug: Callable[[Chiller], None]  # the device goes away (the virtual one: this chiller's)
    plug: Callable[[Chiller], None]
    refuse: Callable[[bool], None] | None  # the device refuses writes (None: it cannot)
    resolution_c: float  # the device's unit rounds the set point to this
    objects: dict[str, Any] = field(default_factory=dict)

    def make(self, clock: Clock | None = None, **settings: Any) -> Chiller:
        objects = dict(self.objects)
        if clock is not None:
            objects["clock"] = clock
        return open_chiller(self.backend, {**self.settings, **settings}, **objects)


BACKENDS = ["modbus-tcp", "modbus-tcp-float32", "modbus-rtu", "opcua", "virtual"]


@pytest.fixture(params=BACKENDS)
def rig(request, tmp_path) -> Iterator[Rig]:
    kind = request.param
    plant = make_plant()
    lock = threading.Lock()
    if kind.startswith("modbus-tcp"):
        f32 = kind.endswith("float32")
        with ChillerServer(plant, lock=lock) as srv:
            settings: dict[str, Any] = {"host": srv.host, "port": srv.port, "timeout_s": 2.0}
            if f32:
                settings.update(
                    data_type="float32",
                    setpoint_register=HOLDING["setpoint_f32"],
                    supply_register=INPUT["supply_f32"],
                )
            yield Rig(
                "modbus",
                settings,
                plant,
                lock,
                lambda _: srv.stop(),
                lambda _: srv.start(),
                lambda on: setattr(srv, "refuse_writes", on),
                1e-5 if f32 else 0.1,
            )
    elif kind == "modbus-rtu":
        pty = PtyPair(tmp_path)
        srv = ChillerServer(plant, lock=lock, serial_port=pty.dev, baudrate=115200).start()

        def unplug(_: Chiller) -> None:
            srv.stop()
            pty.unplug()

        def plug(_: Chiller) -> None:
            pty.plug()
            srv.start()

        try:
            yield Rig(
                "modbus",
                {"transport": "rtu", "port": pty.ctl, "baudrate": 115200, "timeout_s": 2.0},
                plant,
                lock,
                unplug,
                plug,
                lambda on: setattr(srv, "refuse_writes", on),
                0.1,
            )
        finally:
            srv.close()
            pty.close()
    elif kind == "opcua":
        plc = OpcUaChillerPlc(plant, lock).start()
        try:
            yield Rig(
                "opcua",
                {
                    "url": plc.url,
                    "namespace_uri": plc.NAMESPACE,
                    "setpoint_node": plc.SETPOINT,
                    "supply_node": plc.SUPPLY,
                    "scale_c": 0.1,
                    "supply_scale_c": 1.0,
                    "timeout_s": 4.0,
                },
                plant,
                lock,
                lambda _: plc.stop(),
                lambda _: plc.start(),
                lambda on: setattr(plc, "refuse", on),
                0.1,
            )
        finally:
            plc.stop()
    else:

        def reach(on: bool) -> Callable[[Chiller], None]:
            return lambda chiller: setattr(chiller, "reachable", on)

        yield Rig(
            "virtual",
            {},
            plant,
            lock,
            reach(False),
            reach(True),
            None,
            0.0,
            {"plant": plant, "lock": lock},
        )


# -- the contract ---------------------------------------------------------------------------


def test_writes_the_set_point_and_the_chiller_takes_it(rig):
    with rig.make() as chiller:
        sent = chiller.write_setpoint_c(21.3)
        assert sent == pytest.approx(21.3, abs=1e-5)
        assert rig.plant.chiller_setpoint_c == pytest.approx(21.3, abs=1e-5)
        assert chiller.read_setpoint_c() == pytest.approx(21.3, abs=1e-5)
        assert chiller.setpoint_c_requested == 21.3
        # the device's unit rounds: 0.1 degC counts take the nearest
        chiller.write_setpoint_c(18.04)
        assert rig.plant.chiller_setpoint_c == pytest.approx(18.04, abs=rig.resolution_c / 2 + 1e-9)


def test_reads_the_supply_temperature_as_it_moves(rig):
    with rig.make() as chiller:
        assert chiller.read_supply_c() == pytest.approx(16.0, abs=rig.resolution_c / 2 + 1e-9)
        chiller.write_setpoint_c(20.0)
        with rig.lock:  # the plant is stepped while the link may be serving
            rig.plant.advance(3000.0, 600.0)
            supply = rig.plant.supply_c
        assert supply > 19.0  # it moved toward the new set point
        assert chiller.read_supply_c() == pytest.approx(supply, abs=rig.resolution_c / 2 + 1e-6)


def test_a_set_point_the_chiller_clamps_is_a_refused_write(rig):
    # the configured guard is wider than the device's own range (5..35 degC): read back, the
    # device holds what it clamped to, not what was sent
    with rig.make(max_c=40.0) as chiller:
        with pytest.raises(WriteRejectedError, match="holds 35"):
            chiller.write_setpoint_c(38.0)
        assert rig.plant.chiller_setpoint_c == 35.0
        assert chiller.read_setpoint_c() == pytest.approx(35.0)


def test_without_the_read_back_a_clamped_set_point_passes(rig):
    with rig.make(max_c=40.0, setpoint_readback=False) as chiller:
        assert chiller.write_setpoint_c(38.0) == pytest.approx(38.0)
        assert rig.plant.chiller_setpoint_c == 35.0


def test_never_sends_a_bad_set_point(rig):
    with rig.make() as chiller:
        chiller.write_setpoint_c(17.0)
        for bad in (math.nan, math.inf, -math.inf, None, "20", True, 4.9, 35.1, -300.0):
            with pytest.raises(BadValueError):
                chiller.write_setpoint_c(bad)  # type: ignore[arg-type]
            assert rig.plant.chiller_setpoint_c == pytest.approx(17.0)
            assert chiller.setpoint_c_requested == 17.0


def test_a_refused_write_is_write_rejected(rig):
    if rig.refuse is None:
        pytest.skip("the virtual chiller refuses no finite set point")
    with rig.make() as chiller:
        rig.refuse(True)
        with pytest.raises(WriteRejectedError):
            chiller.write_setpoint_c(20.0)
        assert rig.plant.chiller_setpoint_c == 16.0
        rig.refuse(False)
        chiller.write_setpoint_c(20.0)  # the link itself is fine
        assert rig.plant.chiller_setpoint_c == pytest.approx(20.0)


def test_an_unreachable_chiller_and_its_return(rig):
    clock = Clock()
    changes: list[bool] = []
    chiller = rig.make(clock=clock, backoff_s=1.0)
    chiller.on_link_change = lambda up, _reason: changes.append(up)
    try:
        assert chiller.read_supply_c() == pytest.approx(16.0, abs=0.1)
        rig.unplug(chiller)
        with pytest.raises((UnreachableError, AdapterTimeoutError)):
            chiller.read_supply_c()
        with pytest.raises((UnreachableError, AdapterTimeoutError)):
            chiller.write_setpoint_c(20.0)
        assert rig.plant.chiller_setpoint_c == 16.0
        rig.plug(chiller)
        clock.t += 60.0  # past the back-off
        chiller.write_setpoint_c(20.0)
        assert rig.plant.chiller_setpoint_c == pytest.approx(20.0)
        assert changes == [False, True]
    finally:
        chiller.close()


# -- modbus ---------------------------------------------------------------------------------


@pytest.fixture
def plant() -> SpindlePlant:
    return make_plant()


@pytest.fixture
def server(plant) -> Iterator[ChillerServer]:
    with ChillerServer(plant) as srv:
        yield srv


def modbus(srv: ChillerServer, **settings: Any) -> Chiller:
    return open_chiller(
        "modbus", {"host": srv.host, "port": srv.port, "timeout_s": 2.0, **settings}
    )


def test_modbus_nothing_is_sent_for_a_value_outside_the_guard(server, plant):
    with modbus(server) as chiller:
        for bad in (4.9, 35.1, math.nan):
            with pytest.raises(BadValueError):
                chiller.write_setpoint_c(bad)
    assert server.writes == 0
    assert plant.chiller_setpoint_c == 16.0


def test_modbus_an_integer_that_does_not_fit_int16_is_not_sent(server, plant):
    # 0.001 degC counts: 33 degC would be 33000, past int16's 32767
    with modbus(server, scale_c=0.001) as chiller, pytest.raises(BadValueError, match="32767"):
        chiller.write_setpoint_c(33.0)
    assert server.writes == 0
    assert plant.chiller_setpoint_c == 16.0


def test_modbus_a_wrong_scale_reads_as_an_implausible_temperature(server):
    # the supply register holds 160 counts of 0.1 degC; taken as whole degC it is no coolant
    with (
        modbus(server, scale_c=1.0) as chiller,
        pytest.raises(BadValueError, match="outside -50..150"),
    ):
        chiller.read_supply_c()


def test_modbus_float32_in_either_word_order(plant):
    with ChillerServer(plant, word_order="little") as srv:
        f32 = {
            "data_type": "float32",
            "setpoint_register": HOLDING["setpoint_f32"],
            "supply_register": INPUT["supply_f32"],
        }
        with modbus(srv, word_order="little", **f32) as chiller:
            assert chiller.write_setpoint_c(21.3) == 21.3
            assert plant.chiller_setpoint_c == pytest.approx(21.3, abs=1e-6)  # as a float32
            assert chiller.read_supply_c() == 16.0
        # 21.3 is 0x41AA 0x6666: the words swapped, 2.7e23, no coolant temperature
        with (
            modbus(srv, word_order="big", **f32) as chiller,
            pytest.raises(BadValueError, match="outside -50..150"),
        ):
            chiller.read_setpoint_c()


def test_modbus_reads_the_supply_from_a_holding_register(server, plant):
    # some controllers keep everything in holding registers: here the set point itself
    with modbus(
        server,
        supply_table="holding",
        supply_register=HOLDING["setpoint"],
        setpoint_register=HOLDING["setpoint_f32"],
        data_type="int16",
        setpoint_readback=False,
    ) as chiller:
        assert chiller.read_supply_c() == 16.0


def test_modbus_an_exception_reply_to_a_read_is_an_adapter_error(server):
    with modbus(server, supply_register=5) as chiller:  # no such register
        with pytest.raises(AdapterError) as err:
            chiller.read_supply_c()
        assert not isinstance(err.value, (WriteRejectedError, BadValueError))
        assert chiller.read_setpoint_c() == 16.0  # the link is still up


def test_modbus_a_closed_port_is_unreachable():
    chiller = open_chiller("modbus", {"host": "127.0.0.1", "port": free_port(), "timeout_s": 0.2})
    with pytest.raises(UnreachableError, match="cannot reach"):
        chiller.read_supply_c()
    chiller.close()


def test_modbus_a_peer_that_never_answers_is_a_timeout():
    # the kernel completes the connection, nobody ever reads the request
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        port = listener.getsockname()[1]
        changes: list[bool] = []
        chiller = open_chiller(
            "modbus",
            {"host": "127.0.0.1", "port": port, "timeout_s": 0.2},
            on_link_change=lambda up, _reason: changes.append(up),
        )
        with pytest.raises(AdapterTimeoutError, match="no valid reply"):
            chiller.read_supply_c()
        assert changes == [False]  # the hung connection was dropped: the next call reconnects
        chiller.close()


# -- the loopback server on its own: pymodbus's client against its register map ------------


def test_the_server_holds_what_the_chiller_took(server, plant):
    from pymodbus.client import ModbusTcpClient as C

    client = C(server.host, port=server.port, timeout=2, retries=0)
    assert client.connect()
    try:
        assert not client.write_register(HOLDING["setpoint"], 380, device_id=1).isError()  # 38.0
        assert plant.chiller_setpoint_c == 35.0
        assert client.read_holding_registers(
            HOLDING["setpoint"], count=1, device_id=1
        ).registers == [350]
        f32 = client.read_holding_registers(HOLDING["setpoint_f32"], count=2, device_id=1).registers
        assert C.convert_from_registers(f32, C.DATATYPE.FLOAT32) == 35.0
        # a negative count is a signed int16; the chiller clamps it to its minimum
        client.write_register(HOLDING["setpoint"], (-20) & 0xFFFF, device_id=1)
        assert plant.chiller_setpoint_c == 5.0
        # a float32 NaN is a value the chiller cannot take
        rr = client.write_registers(
            HOLDING["setpoint_f32"],
            C.convert_to_registers(math.nan, C.DATATYPE.FLOAT32),
            device_id=1,
        )
        assert rr.isError() and rr.exception_code == 3  # ILLEGAL_VALUE
        assert plant.chiller_setpoint_c == 5.0
        # half a float32, and an address the map does not have
        assert client.write_register(HOLDING["setpoint_f32"], 0, device_id=1).isError()
        assert client.read_holding_registers(5, count=1, device_id=1).isError()
        regs = client.read_input_registers(0, count=2, device_id=1).registers
        assert regs == [round(plant.supply_c * 10), round(plant.coolant_c * 10)]
        regs = client.read_input_registers(INPUT["coolant_f32"], count=2, device_id=1).registers
        assert C.convert_from_registers(regs, C.DATATYPE.FLOAT32) == pytest.approx(plant.coolant_c)
        assert server.writes == 4
    finally:
        client.close()


def test_the_server_takes_the_plant_only_under_its_lock(plant):
    lock = CountingLock()
    with ChillerServer(plant, lock=lock) as srv, modbus(srv) as chiller:
        chiller.read_supply_c()
        assert lock.taken == 1
        chiller.write_setpoint_c(20.0)  # the write, then its read-back
        assert lock.taken == 3


# -- virtual --------------------------------------------------------------------------------


def test_virtual_needs_a_plant_and_uses_its_lock(plant):
    with pytest.raises(ConfigError, match="plant="):
        open_chiller("virtual", {})
    lock = CountingLock()
    chiller = open_chiller("virtual", {"min_c": 10.0}, plant=plant, lock=lock)
    assert isinstance(chiller, VirtualChiller)
    with chiller:
        assert chiller.write_setpoint_c(22.5) == 22.5
        assert plant.chiller_setpoint_c == 22.5
        assert chiller.read_supply_c() == 16.0
        with pytest.raises(BadValueError):
            chiller.write_setpoint_c(9.0)
    assert lock.taken == 3


def test_virtual_unreachable_from_the_start(plant):
    chiller = open_chiller("virtual", {}, plant=plant, clock=Clock())
    chiller.reachable = False  # type: ignore[attr-defined]
    with pytest.raises(UnreachableError):
        chiller.read_supply_c()
    chiller.reachable = True  # type: ignore[attr-defined]
    with pytest.raises(UnreachableError, match="next attempt"):  # the back-off still runs
        chiller.read_supply_c()


# -- settings -------------------------------------------------------------------------------


def test_every_backend_declares_its_settings():
    for name, cls in CHILLERS.items():
        assert issubclass(cls, Chiller) and cls.name == name
        assert cls.Settings.model_config["extra"] == "forbid"


@pytest.mark.parametrize(
    ("backend", "settings", "message"),
    [
        ("ammonia", {}, "unknown chiller backend 'ammonia'; known: modbus, opcua, virtual"),
        ("modbus", {"host": "h", "setpoint_regster": 3}, "did you mean 'setpoint_register'?"),
        ("modbus", {}, "transport tcp needs host"),
        (
            "modbus",
            {"host": "h", "port": "/dev/ttyUSB0"},
            "port = '/dev/ttyUSB0': expected a TCP port 1..65535 (transport tcp)",
        ),
        ("modbus", {"transport": "rtu"}, "transport rtu needs port"),
        ("modbus", {"transport": "rtu", "port": "/dev/ttyUSB0", "host": "h"}, "takes no host"),
        (
            "modbus",
            {"host": "h", "transport": "udp"},
            "transport = 'udp': expected one of 'tcp', 'rtu'",
        ),
        (
            "modbus",
            {"host": "h", "data_type": "int32"},
            "data_type = 'int32': expected one of 'int16', 'float32'",
        ),
        (
            "modbus",
            {"host": "h", "scale_c": 0},
            "scale_c = 0: expected a finite number other than 0",
        ),
        ("modbus", {"host": "h", "timeout_s": math.nan}, "timeout_s = nan: expected a number > 0"),
        ("modbus", {"host": "h", "min_c": 30, "max_c": 20}, "min_c < max_c"),
        ("modbus", {"host": "h", "max_c": 400}, "within -50..150"),
        (
            "modbus",
            {
                "host": "h",
                "supply_table": "holding",
                "data_type": "float32",
                "setpoint_register": 10,
                "supply_register": 11,
            },
            "overlap",
        ),
        (
            "modbus",
            {"host": "h", "plant": "p"},
            "plant = 'p': unknown key; allowed: transport, host, ",
        ),
        (
            "opcua",
            {"url": "opc.tcp://h:4840", "setpoint_node": "ns=2;s=S"},
            "supply_node: required key missing; expected a non-empty string",
        ),
        (
            "opcua",
            {"url": "opc.tcp://u:secret@h:4840", "setpoint_node": "a", "supply_node": "b"},
            "carries a password",
        ),
        ("virtual", {"min_c": "cold"}, "min_c = 'cold': expected a finite number"),
        ("virtual", [1, 2], "settings must be a table"),
    ],
)
def test_a_bad_setting_is_one_config_error_line(backend, settings, message):
    with pytest.raises(ConfigError) as err:
        open_chiller(backend, settings)
    text = str(err.value)
    assert message in text and "\n" not in text
    assert "secret" not in text


def test_objects_never_come_in_the_settings(plant):
    with pytest.raises(ConfigError, match="clock = 1: no configuration option"):
        open_chiller("virtual", {"clock": 1}, plant=plant)
    with pytest.raises(ConfigError, match="both as settings and as objects"):
        open_chiller("virtual", {"min_c": 6.0}, plant=plant, min_c=7.0)


def test_modbus_defaults():
    tcp = open_chiller("modbus", {"host": "chiller.local"})
    assert isinstance(tcp, ModbusChiller)
    assert (tcp.port, tcp.device_id, tcp.scale_c, tcp.raw_range) == (502, 1, 0.1, (-32768, 32767))
    assert (tcp.min_c, tcp.max_c, tcp.setpoint_readback) == (5.0, 35.0, True)
    rtu = open_chiller(
        "modbus",
        {
            "transport": "rtu",
            "port": "/dev/ttyUSB0",
            "data_type": "float32",
            "parity": "E",
            "stopbits": 2,
        },
    )
    assert (rtu.port, rtu.scale_c, rtu.raw_range, rtu.parity, rtu.stopbits) == (
        "/dev/ttyUSB0",
        1.0,
        None,
        "E",
        2,
    )
    checked = check_chiller(
        "opcua", {"url": "opc.tcp://h:4840", "setpoint_node": "a", "supply_node": "b"}
    )
    assert checked.scale_c == 1.0 and checked.setpoint_readback is True
