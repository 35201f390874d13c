"""The virtual machine tool's tool setter and the probe-measurement handshake over OPC UA.

In simulated time on a fake clock: the virtual CNC's OPC UA server (asyncua, loopback, a free
port) is made to publish with :func:`call` before each read, so nothing waits or sleeps.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cnc_adapters import AdapterError, BadValueError, ConfigError, open_adapter
from cnc_adapters.opcua import OpcUaAdapter
from compensator.speed_programs import Program
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import (
    NAMESPACE_URI,
    PROBE_METHOD_PATH,
    TOOL_SETTER_PATHS,
    ToolSetter,
    VirtualCNC,
    VirtualMachine,
    call,
    running,
)

SPEED = 20000.0


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def machine(clock: FakeClock, **setter) -> VirtualMachine:
    program = Program("steady", ((36000.0, SPEED),))
    return VirtualMachine(
        SpindlePlant(preset("motorized-27k"), seed=1),
        program,
        clock=clock,
        tool_setter=ToolSetter(**setter),
    )


def probe(vm: VirtualMachine, clock: FakeClock) -> float:
    """One probe cycle, run to its end; the value it published."""
    seq = vm.start_probe()
    assert seq == vm.probe_sequence + 1
    clock.t += vm.tool_setter.cycle_s
    vm.advance()
    assert vm.probe_sequence == seq and not vm.probing
    return vm.probe_value_um


def test_a_probe_cycle_stops_the_spindle_then_measures_the_true_elongation():
    clock = FakeClock()
    vm = machine(clock, dwell_s=20.0)
    clock.t = 1800.0
    vm.advance()
    assert vm.speed_rpm == SPEED
    seq = vm.start_probe()
    assert seq == 1 and vm.probing
    assert vm.start_probe() == 0  # one cycle at a time
    clock.t += 19.0
    vm.advance()
    assert vm.speed_rpm == 0.0 and vm.probe_sequence == 0  # still measuring
    clock.t += 1.0
    vm.advance()
    assert vm.probe_sequence == 1 and not vm.probing
    assert abs(vm.probe_value_um - vm.probe_true_um) < 5 * 0.5 + 0.05
    assert vm.probe_value_um == pytest.approx(
        round(vm.probe_value_um / 0.1) * 0.1, abs=1e-9
    )  # resolution
    assert vm.probe_true_um > 5.0  # 30 min at 20 000 rpm: a warm spindle
    h = vm.history()
    stopping = h.speed_rpm[(h.time_s > 1800.0) & (h.time_s <= 1820.0)]
    assert (np.diff(stopping) <= 0).all() and stopping[0] < SPEED  # it runs down at once ...
    assert (h.speed_rpm[(h.time_s >= 1804.0) & (h.time_s <= 1820.0)] == 0.0).all()  # ... in 4 s
    assert not h.cutting[(h.time_s > 1800.0) & (h.time_s <= 1820.0)].any()
    clock.t += 1.0
    vm.advance()
    assert 0.0 < vm.speed_rpm < SPEED  # the program goes on where it stopped: running up
    clock.t += 4.0
    vm.advance()
    assert vm.speed_rpm == SPEED
    assert vm.program.duration_s - (vm.plant.time_s - vm._program_start_s) == pytest.approx(
        36000.0 - 1805.0
    )


def test_the_tool_setters_noise_and_resolution_are_as_configured_and_seeded():
    def run(seed: int, n: int) -> list[float]:
        clock = FakeClock()
        vm = machine(clock, dwell_s=2.0, noise_um=0.5, resolution_um=0.0, seed=seed)
        return [probe(vm, clock) - vm.probe_true_um for _ in range(n)]

    errors = run(4, 400)
    assert abs(np.mean(errors)) < 0.1 and np.std(errors) == pytest.approx(0.5, rel=0.15)
    assert run(4, 5) == errors[:5]  # seeded
    assert run(5, 5) != errors[:5]
    with pytest.raises(ValueError, match="noise_um"):
        ToolSetter(noise_um=math.nan)


def test_a_cycle_of_several_touches_hands_on_their_mean():
    """Four touches: the cycle lasts three touch times longer, the value's noise halves (each
    touch read at the setter's resolution, then averaged), and the sigma published says so."""

    def run(touches: int, n: int) -> tuple[list[float], VirtualMachine]:
        clock = FakeClock()
        vm = machine(clock, dwell_s=2.0, noise_um=0.5, seed=4, touches=touches, touch_s=1.5)
        return [probe(vm, clock) - vm.probe_true_um for _ in range(n)], vm

    one, _ = run(1, 400)
    four, vm = run(4, 400)
    assert vm.tool_setter.cycle_s == pytest.approx(2.0 + 3 * 1.5)
    assert np.std(four) == pytest.approx(0.25, rel=0.15) and np.std(four) < 0.6 * np.std(one)
    assert vm.probe_sigma_um == pytest.approx(0.25)
    # a value is a mean of values at 0.1 um: a multiple of 0.025 um
    assert all(abs(v / 0.025 - round(v / 0.025)) < 1e-6 for v in (vm.probe_value_um,))
    for bad in (0, 11, 2.5):
        with pytest.raises(ValueError, match="touches"):
            ToolSetter(touches=bad)


def test_the_sim_adapter_reads_each_probe_once_and_ignores_the_one_found_at_start():
    clock = FakeClock()
    vm = machine(clock)
    clock.t = 600.0
    probe(vm, clock)  # before the link opened: stale
    link = SimAdapter(machine=vm, offset_scale=0.001)  # a controller in mm
    assert link.can_read_measurement
    assert link.read_measurement() is None
    value = probe(vm, clock)
    m = link.read_measurement()
    assert m is not None and m.sequence == 2 and m.source == "sim"
    assert m.elongation_um == pytest.approx(value) and m.sigma_um == pytest.approx(0.5)
    assert link.read_measurement() is None  # used once


# -- OPC UA --------------------------------------------------------------------------------

NODES = {
    "measurement_node": f"ns={{ns}};s={TOOL_SETTER_PATHS['probe_measurement']}",
    "measurement_sequence_node": f"ns={{ns}};s={TOOL_SETTER_PATHS['probe_sequence']}",
    "measurement_sigma_node": f"ns={{ns}};s={TOOL_SETTER_PATHS['probe_sigma']}",
}


def generic(url: str, **kw) -> OpcUaAdapter:
    """The virtual CNC as a generic OPC UA controller: every node id from configuration."""
    return OpcUaAdapter(
        url,
        namespace_uri=NAMESPACE_URI,
        timeout_s=5.0,
        speed_node="ns={ns};s=/CncInterface/CncSpindleList/Spindle1/ActSpeed",
        offset_node="ns={ns};s=/CncInterface/CncSpindleList/Spindle1/ThermalOffset",
        **{**NODES, **kw},
    )


def call_probe(url: str) -> int:
    """An operator's or NC program's client starts a probe cycle through the OPC UA method."""
    from asyncua.sync import Client

    with Client(url, timeout=10) as c:
        ns = c.get_namespace_index(NAMESPACE_URI)
        setter = c.get_node(f"ns={ns};s={PROBE_METHOD_PATH.rpartition('/')[0]}")
        return int(setter.call_method(f"{ns}:Probe"))


def test_opcua_each_probe_value_is_used_once_and_a_stale_one_is_ignored():
    clock = FakeClock()
    vm = machine(clock)
    clock.t = 900.0
    vm.advance()
    vm.probe_value_um, vm.probe_sequence = 12.3, 7  # left by a probe cycle before we connected
    with running(VirtualCNC(vm)) as cnc, generic(cnc.url) as link:
        assert link.can_read_measurement
        call(cnc, cnc.tick)
        assert link.read_measurement() is None  # the counter found at the first read is stale
        assert link.read_measurement() is None
        assert call_probe(cnc.url) == 8
        clock.t += vm.tool_setter.dwell_s
        call(cnc, cnc.tick)  # the cycle ends; the value is written, then the counter
        m = link.read_measurement()
        assert m is not None and (m.sequence, m.source) == (8, "opcua")
        assert m.elongation_um == pytest.approx(vm.probe_value_um) != 12.3
        assert abs(m.elongation_um - vm.probe_true_um) < 2.6 and m.sigma_um == pytest.approx(0.5)
        for _ in range(5):  # the spindle runs up again in 4 s (5000 rpm/s)
            clock.t += 1.0
            call(cnc, cnc.tick)
            assert link.read_measurement() is None  # each value once
        assert link.read_speed() == SPEED  # the program goes on after the probe cycle


def test_opcua_a_cycles_reads_ride_in_the_speeds_request():
    """A cycle's read is one request from the first cycle on: the speed, the offset read-back,
    the inputs and the probe's handshake. Each is the cycle's own (a later read asks again), and
    a write in between makes the next read-back the controller's own value."""
    from cnc_adapters import Wants
    from machine_sim.vcnc import NODE_PATHS

    every = Wants(cutting=True, held_offset=True, inputs=True, measurement=True)
    clock = FakeClock()
    vm = machine(clock)
    inputs = {"bearing_temp_c": f"ns={{ns}};s={NODE_PATHS['bearing_temp_c']}"}
    with running(VirtualCNC(vm)) as cnc, generic(cnc.url, input_nodes=inputs) as link:
        call(cnc, cnc.tick)
        link.open()
        requests = []
        real = link._client.read_attributes

        def counted(nodes):  # the real client's call, counted
            requests.append(len(nodes))
            return real(nodes)

        link._client.read_attributes = counted
        for k in range(3):
            clock.t += 1.0
            call(cnc, cnc.tick)
            r = link.read(every)
            assert r.speed_rpm == pytest.approx(vm.speed_rpm)
            assert r.measurement is None
            assert r.inputs["bearing_temp_c"] == pytest.approx(
                vm.sensor_values()["bearing_temp_c"], abs=1.0
            )
            assert r.held_offset_um == pytest.approx(vm.offset_um)
            # speed, offset, input, the handshake's three
            assert requests == [1 + 1 + 1 + 3] * (k + 1)
        value = probe(vm, clock)  # a cycle of the tool setter, read in the same request
        call(cnc, cnc.tick)
        assert link.read(every).measurement.elongation_um == pytest.approx(value)
        assert len(requests) == 4
        link.read_inputs()
        link.read_inputs()  # a read of its own asks the controller, each time
        assert len(requests) == 6
        link.write_offset_um(-3.0)
        call(cnc, cnc.tick)
        assert link.read(every).held_offset_um == pytest.approx(-3.0)  # not a value from before


def test_opcua_a_non_finite_measurement_is_refused_once():
    clock = FakeClock()
    vm = machine(clock)
    # a controller whose offset is in mm, whose probe cycle hands over um
    with (
        running(VirtualCNC(vm)) as cnc,
        generic(cnc.url, offset_scale=0.001, measurement_scale=1.0) as link,
    ):
        call(cnc, cnc.tick)
        assert link.read_measurement() is None
        vm.probe_value_um, vm.probe_sequence = math.nan, vm.probe_sequence + 1
        call(cnc, cnc.tick)
        with pytest.raises(BadValueError, match="not a finite number"):  # refused once
            link.read_measurement()
        assert link.read_measurement() is None  # its counter is taken as seen
        value = probe(vm, clock)
        call(cnc, cnc.tick)
        m = link.read_measurement()
        assert (
            m is not None
            and m.elongation_um == pytest.approx(value)
            and m.sigma_um == pytest.approx(0.5)
        )


def test_opcua_a_wrong_measurement_node_fails_the_measurement_not_the_link():
    clock = FakeClock()
    vm = machine(clock)
    nowhere = {
        "measurement_node": "ns={ns};s=/Nowhere",
        "measurement_sequence_node": "ns={ns};s=/Nor",
    }
    with running(VirtualCNC(vm)) as cnc, generic(cnc.url, **nowhere) as link:
        clock.t = 60.0
        call(cnc, cnc.tick)
        with pytest.raises(AdapterError, match="BadNodeIdUnknown") as exc:
            link.read_measurement()
        assert not isinstance(exc.value, (ConnectionError, TimeoutError))
        assert link.read_speed() == SPEED  # the link is up


def test_opcua_measurement_settings_need_the_handshake():
    base = {
        "type": "opcua",
        "url": "opc.tcp://127.0.0.1:4840",
        "speed_node": "ns=2;s=S",
        "offset_node": "ns=2;s=O",
    }
    with pytest.raises(ConfigError, match="measurement_sequence_node"):
        open_adapter({**base, "measurement_node": "ns=2;s=M"})
    with pytest.raises(ConfigError, match="measurement_sigma_node only with"):
        open_adapter({**base, "measurement_sigma_node": "ns=2;s=E"})
    link = open_adapter(
        {
            **base,
            "measurement_node": "ns=2;s=M",
            "measurement_sequence_node": "ns=2;s=N",
            "measurement_scale": 1,
        }
    )
    assert link.can_read_measurement and link.measurement_refs == ("ns=2;s=N", "ns=2;s=M")
    assert link.measurement_scale == 1.0
    with pytest.raises(ConfigError, match="measurement_scale"):
        open_adapter({**base, "measurement_scale": 0})
    assert not open_adapter(base).can_read_measurement
    assert open_adapter(
        {"type": "opcua", "url": "opc.tcp://127.0.0.1:4840", "preset": "virtual-cnc"}
    ).can_read_measurement
