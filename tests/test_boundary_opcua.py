"""The OPC UA boundary: whatever a server puts in a node, one cycle's ``read`` gives a checked
value or a Failure, in one request.

One real asyncua server for the module, its nodes written from the server's side between
examples (any variant type, any status: what a misconfigured or failing controller can send).
"""

from __future__ import annotations

import asyncio
import math
import threading
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import pytest
from asyncua import Server, ua
from asyncua.common.callback import CallbackType
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cnc_adapters import AdapterError, Failure, FailureKind, Reading, Wants, WriteResult
from cnc_adapters.base import Measurement
from cnc_adapters.opcua import OpcUaAdapter
from machine_sim.vcnc import free_port

ALL = Wants(cutting=True, held_offset=True, inputs=True, measurement=True)
NS_URI = "urn:thermocomp:boundary"

# the controller's values: node name and the good value it holds between examples
GOOD: dict[str, ua.Variant] = {
    "speed": ua.Variant(12000.0, ua.VariantType.Double),
    "cutting": ua.Variant(True, ua.VariantType.Boolean),
    "offset": ua.Variant(-4.0, ua.VariantType.Double),
    "input": ua.Variant(21.5, ua.VariantType.Double),
    "probe_value": ua.Variant(3.25, ua.VariantType.Double),
    "probe_sigma": ua.Variant(0.5, ua.VariantType.Double),
    "probe_sequence": ua.Variant(1, ua.VariantType.UInt32),
}

# what a node may hold instead: every variant type a controller can send where a number is due
VARIANTS: dict[str, ua.Variant] = {
    "string": ua.Variant("12", ua.VariantType.String),
    "string-nan": ua.Variant("nan", ua.VariantType.String),
    "string-empty": ua.Variant("", ua.VariantType.String),
    "true": ua.Variant(True, ua.VariantType.Boolean),
    "false": ua.Variant(False, ua.VariantType.Boolean),
    "double-array": ua.Variant([1.0, 2.0], ua.VariantType.Double),
    "string-array": ua.Variant(["1", "2"], ua.VariantType.String),
    "bytestring": ua.Variant(b"\x00\x01\xff", ua.VariantType.ByteString),
    "datetime": ua.Variant(datetime(2026, 1, 1, tzinfo=UTC), ua.VariantType.DateTime),
    "int64-min": ua.Variant(-(2**63), ua.VariantType.Int64),
    "int64-max": ua.Variant(2**63 - 1, ua.VariantType.Int64),
    "uint64-max": ua.Variant(2**64 - 1, ua.VariantType.UInt64),
    "uint64-zero": ua.Variant(0, ua.VariantType.UInt64),
    "nan": ua.Variant(math.nan, ua.VariantType.Double),
    "inf": ua.Variant(math.inf, ua.VariantType.Double),
    "-inf": ua.Variant(-math.inf, ua.VariantType.Double),
    "-0": ua.Variant(-0.0, ua.VariantType.Double),
    "1e308": ua.Variant(1e308, ua.VariantType.Double),
    "-1e308": ua.Variant(-1e308, ua.VariantType.Double),
    "float-2.5": ua.Variant(2.5, ua.VariantType.Float),
    "null": ua.Variant(),
}
NOT_A_NUMBER = {
    "string",
    "string-nan",
    "string-empty",
    "true",
    "false",
    "double-array",
    "string-array",
    "bytestring",
    "datetime",
    "null",
}

STATUSES = [
    ua.StatusCodes.Good,
    ua.StatusCodes.BadSensorFailure,
    ua.StatusCodes.UncertainLastUsableValue,
    ua.StatusCodes.BadNodeIdUnknown,
    ua.StatusCodes.BadOutOfService,
]


@dataclass
class Controller:
    """An asyncua server on a loop of its own, its nodes set from the server's side."""

    url: str
    loop: asyncio.AbstractEventLoop
    server: Server
    nodes: dict[str, Any]
    ns: int
    keep_offset: list[float] = field(default_factory=list)  # a value it reverts every write to

    def run(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(30)

    def set(self, name: str, variant: ua.Variant, status: int = ua.StatusCodes.Good) -> None:
        node_id = self.nodes[name].nodeid
        # the server keeps a node's variant type; a bad status empties it, and then a node of
        # the abstract type Number takes any variant
        empty = ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData))
        for dv in (empty, ua.DataValue(variant, StatusCode=ua.StatusCode(status))):
            space = self.server.iserver.aspace
            done = self.run(space.write_attribute_value(node_id, ua.AttributeIds.Value, dv))
            assert done.is_good(), (name, variant, done)

    def reset(self, sequence: int) -> None:
        for name, variant in GOOD.items():
            self.set(name, variant)
        self.set("probe_sequence", ua.Variant(sequence, ua.VariantType.UInt32))

    def node_id(self, name: str) -> str:
        return f"ns={self.ns};s=Boundary/{name}"


@pytest.fixture(scope="module")
def controller() -> Iterator[Controller]:
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    url = f"opc.tcp://127.0.0.1:{free_port()}/boundary"

    async def start() -> Controller:
        server = Server()
        await server.init()
        server.set_endpoint(url)
        ns = await server.register_namespace(NS_URI)
        folder = await server.nodes.objects.add_folder(ns, "Boundary")
        nodes = {}
        for name, variant in GOOD.items():
            nodes[name] = await folder.add_variable(
                ua.NodeId(f"Boundary/{name}", ns),
                name,
                variant.Value,
                variant.VariantType,
                datatype=ua.NodeId(ua.ObjectIds.Number),
            )
        await nodes["offset"].set_writable()
        await server.start()
        ctl = Controller(url, loop, server, nodes, ns)

        async def revert(event: Any, _dispatcher: Any) -> None:  # a control that keeps its own
            if ctl.keep_offset:
                await server.write_attribute_value(
                    nodes["offset"].nodeid,
                    ua.DataValue(ua.Variant(ctl.keep_offset[0], ua.VariantType.Double)),
                )

        server.subscribe_server_callback(CallbackType.PostWrite, revert)
        return ctl

    ctl = asyncio.run_coroutine_threadsafe(start(), loop).result(60)
    try:
        yield ctl
    finally:
        ctl.run(ctl.server.stop())
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)


def adapter(ctl: Controller, **kw: Any) -> OpcUaAdapter:
    options: dict[str, Any] = {
        "speed_node": ctl.node_id("speed"),
        "offset_node": ctl.node_id("offset"),
        "cutting_node": ctl.node_id("cutting"),
        "input_nodes": {"bearing_temp_c": ctl.node_id("input")},
        "measurement_node": ctl.node_id("probe_value"),
        "measurement_sequence_node": ctl.node_id("probe_sequence"),
        "measurement_sigma_node": ctl.node_id("probe_sigma"),
        "timeout_s": 5.0,
        **kw,
    }
    return OpcUaAdapter(ctl.url, **options)


@pytest.fixture(scope="module")
def link(controller: Controller) -> Iterator[OpcUaAdapter]:
    with adapter(controller) as a:
        controller.reset(Sequence.next())
        assert a.read(ALL).measurement is None  # the counter found first is stale
        yield a


def assert_invariants(r: Reading) -> None:
    """Every field: None, a Failure, or a finite value of its type."""

    def number(v: Any) -> None:
        assert isinstance(v, Failure) or (type(v) is float and math.isfinite(v)), (
            f"not a finite float or a Failure: {v!r}"
        )

    number(r.speed_rpm)
    assert r.cutting is None or isinstance(r.cutting, (bool, Failure))
    for v in (r.held_offset_um, r.not_ready_offset_um):
        if v is not None:
            number(v)
    assert r.write_refused_um is None or (
        type(r.write_refused_um) is float and math.isfinite(r.write_refused_um)
    )
    if r.inputs is not None and not isinstance(r.inputs, Failure):
        for v in r.inputs.values():
            number(v)
    if isinstance(r.measurement, Measurement):
        m = r.measurement
        number(m.elongation_um)
        assert type(m.sequence) is int
        assert m.sigma_um is None or (
            type(m.sigma_um) is float and math.isfinite(m.sigma_um) and m.sigma_um > 0
        )
    else:
        assert r.measurement is None or isinstance(r.measurement, Failure)


class Sequence:
    """The probe cycle's counter: a new one for each example, so that each reads as a new
    measurement (the handshake takes a value only with a changed counter)."""

    value = 1

    @classmethod
    def next(cls) -> int:
        cls.value += 1
        return cls.value


@settings(
    max_examples=120,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    name=st.sampled_from(sorted(GOOD)),
    variant=st.sampled_from(sorted(VARIANTS)),
    status=st.sampled_from(STATUSES),
)
def test_whatever_a_node_holds_a_cycle_reads_a_checked_value_or_a_failure(
    controller: Controller, link: OpcUaAdapter, name: str, variant: str, status: int
) -> None:
    check_one(controller, link, name, variant, status)
    # the per-value reads (the wizard, run --check) refuse it as a link's error, nothing else
    for read in (
        link.read_speed,
        link.read_cutting,
        link.read_offset_um,
        link.read_inputs,
        link.read_measurement,
    ):
        try:
            read()
        except AdapterError:
            pass


def check_one(
    controller: Controller, link: OpcUaAdapter, name: str, variant: str, status: int
) -> None:
    """One node holds ``variant`` with ``status``, the others good values: one cycle's read."""
    controller.reset(Sequence.next())
    controller.set(name, VARIANTS[variant], status)
    r = link.read(ALL)
    assert_invariants(r)
    good = status == ua.StatusCodes.Good
    target = {
        "speed": r.speed_rpm,
        "cutting": r.cutting,
        "offset": r.held_offset_um,
        "input": None if isinstance(r.inputs, Failure) else (r.inputs or {}).get("bearing_temp_c"),
    }
    if name in target:
        if not good or variant in NOT_A_NUMBER - (
            {"true", "false"} if name == "cutting" else set()
        ):
            assert isinstance(target[name], Failure), (name, variant, status, target[name])
    if name == "speed":
        assert not isinstance(r.speed_rpm, Failure) or not r.speed_rpm.link_lost
    else:  # one value's fault is its own: the speed is read
        assert r.speed_rpm == 12000.0
    if name == "probe_sigma" and (variant in NOT_A_NUMBER or not good):
        # a sigma that is not a number is never taken as 1 um, or as none
        assert isinstance(r.measurement, Failure), r.measurement
        if good:
            assert r.measurement.kind is FailureKind.VALUE
    if name in ("probe_value", "probe_sequence") and (variant in NOT_A_NUMBER or not good):
        assert isinstance(r.measurement, Failure), r.measurement
    if name not in ("probe_value", "probe_sigma", "probe_sequence"):
        assert r.measurement == Measurement(3.25, 0.5, Sequence.value, "opcua")


def test_every_variant_in_every_value_with_every_status(controller, link):
    """The property's whole space, each case once (7 values x 21 variants x 5 statuses)."""
    for name in GOOD:
        for variant in VARIANTS:
            for status in STATUSES:
                check_one(controller, link, name, variant, status)


def test_a_boolean_speed_is_a_failure_and_a_string_sigma_a_value_failure(controller, link):
    controller.reset(Sequence.next())
    controller.set("speed", ua.Variant(True, ua.VariantType.Boolean))
    controller.set("probe_sigma", ua.Variant("1", ua.VariantType.String))
    r = link.read(ALL)
    assert isinstance(r.speed_rpm, Failure) and r.speed_rpm.kind is FailureKind.VALUE
    assert isinstance(r.measurement, Failure) and r.measurement.kind is FailureKind.VALUE
    assert "sigma" in r.measurement.reason
    controller.reset(Sequence.next())
    r = link.read(ALL)
    assert r.speed_rpm == 12000.0 and r.cutting is True and r.held_offset_um == -4.0
    assert r.inputs == {"bearing_temp_c": 21.5}
    assert r.measurement == Measurement(3.25, 0.5, Sequence.value, "opcua")


def count_requests(link: OpcUaAdapter) -> list[int]:
    """The Read requests ``link`` sends from now on, by their number of nodes."""
    requests: list[int] = []
    assert link._client is not None
    real = link._client.read_attributes

    def counted(nodes: list[Any], *args: Any) -> Any:  # the real client's call, counted
        requests.append(len(nodes))
        return real(nodes, *args)

    link._client.read_attributes = counted  # type: ignore[method-assign]
    return requests


def test_a_cycle_is_one_request_from_the_first_on(controller):
    """The speed, the cutting signal, the held offset, the input and the probe's three
    handshake nodes: one Read a cycle, the first included (nodes resolved inside it)."""
    controller.reset(Sequence.next())
    with adapter(controller) as a:
        requests = count_requests(a)
        for k in range(3):
            r = a.read(ALL)
            assert r.speed_rpm == 12000.0 and r.cutting is True and r.held_offset_um == -4.0
            assert r.inputs == {"bearing_temp_c": 21.5} and r.measurement is None
            assert requests == [1 + 1 + 1 + 1 + 3] * (k + 1)
        controller.set("probe_value", ua.Variant(7.5, ua.VariantType.Double))
        controller.set("probe_sequence", ua.Variant(Sequence.next(), ua.VariantType.UInt32))
        assert a.read(ALL).measurement == Measurement(7.5, 0.5, Sequence.value, "opcua")
        assert a.read(ALL).measurement is None  # each value once
        assert a.read(Wants()).speed_rpm == 12000.0  # the speed alone: one node
        assert requests[-3:] == [7, 7, 1]
        # the per-value reads (the wizard, run --check): each its own request, no cache
        n = len(requests)
        assert a.read_offset_um() == -4.0 and a.read_offset_um() == -4.0
        assert a.read_inputs() == {"bearing_temp_c": 21.5}
        assert a.read_cutting() is True and a.read_speed() == 12000.0
        assert requests[n:] == [1, 1, 1, 1, 1]


def test_a_subscription_gives_the_speed_and_the_rest_comes_in_one_request(controller):
    controller.reset(Sequence.next())
    with adapter(controller, read_mode="subscribe") as a:
        requests = count_requests(a)
        r = a.read(ALL)
        assert r.speed_rpm == 12000.0 and r.held_offset_um == -4.0 and r.cutting is True
        assert requests == [1 + 1 + 1 + 3]  # no speed node in it
        assert a.read(Wants()).speed_rpm == 12000.0 and requests == [6]  # no request at all


def test_nodes_that_do_not_resolve_fail_their_own_fields(controller):
    controller.reset(Sequence.next())
    nowhere = {
        "cutting_node": "0:Objects/9:Nowhere",  # a browse path that finds nothing
        "measurement_node": f"ns={controller.ns};s=Boundary/none",
        "measurement_sequence_node": f"ns={controller.ns};s=Boundary/nor",
        "measurement_sigma_node": None,
        "input_nodes": {"bearing_temp_c": f"ns={controller.ns};s=Boundary/gone"},
    }
    with adapter(controller, **nowhere) as a:
        r = a.read(ALL)
        assert_invariants(r)
        assert r.speed_rpm == 12000.0 and r.held_offset_um == -4.0
        assert isinstance(r.cutting, Failure) and not r.cutting.link_lost
        assert isinstance(r.measurement, Failure) and "BadNodeIdUnknown" in r.measurement.reason
        assert isinstance(r.inputs, Mapping) and isinstance(r.inputs["bearing_temp_c"], Failure)


def test_deferred_write_check_rides_in_the_next_read(controller):
    controller.reset(Sequence.next())
    with adapter(controller, verify_writes="deferred") as a:
        requests = count_requests(a)
        assert a.write(-6.0) == WriteResult(pending=True)
        r = a.read(Wants())  # the offset node comes in the speed's request
        assert r.speed_rpm == 12000.0 and r.write_refused_um is None and requests == [2]
        assert a.read(Wants()).write_refused_um is None and requests == [2, 1]
        controller.keep_offset.append(-6.0)  # the control keeps what it holds
        try:
            assert a.write(-8.0).pending
            assert a.read(Wants()).write_refused_um == -6.0  # reported once, in um
            assert a.read(Wants()).write_refused_um is None
        finally:
            controller.keep_offset.clear()


def test_immediate_write_check_refuses_a_write_the_control_did_not_take(controller):
    controller.reset(Sequence.next())
    with adapter(controller, verify_writes="immediate", offset_scale=0.001) as a:
        assert a.write(-6.0) == WriteResult()
        controller.keep_offset.append(-0.006)
        try:
            got = a.write(-8.0)
            assert isinstance(got.failure, Failure) and got.failure.kind is FailureKind.REFUSED
            assert not got.pending
        finally:
            controller.keep_offset.clear()
        for bad in (math.nan, math.inf):
            refused = a.write(bad).failure
            assert refused is not None and refused.kind is FailureKind.VALUE


def test_a_write_the_server_refuses_is_a_refused_failure(controller):
    controller.reset(Sequence.next())
    with adapter(controller, offset_node=controller.node_id("speed")) as a:  # not writable
        got = a.write(-1.0)
        assert got.failure is not None and got.failure.kind is FailureKind.REFUSED


def test_no_server_is_a_link_failure_of_the_cycle_and_of_the_write():
    a = OpcUaAdapter(
        f"opc.tcp://127.0.0.1:{free_port()}", speed_node="ns=2;s=S", offset_node="ns=2;s=O"
    )
    try:
        r = a.read(ALL)
        assert isinstance(r.speed_rpm, Failure) and r.speed_rpm.link_lost
        assert (r.cutting, r.held_offset_um, r.inputs, r.measurement) == (None,) * 4
        refused = a.write(-1.0).failure
        assert refused is not None and refused.link_lost  # in the back-off: not even tried
    finally:
        a.close()
