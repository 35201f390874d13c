"""Faults at the seams of one cycle's parts: one reading for the whole cycle, and the offset's
own bookkeeping between reads and writes."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from cnc_adapters import BadValueError, Failure, FailureKind, Reading, Wants, WriteResult
from cnc_adapters.base import RawMeasurement
from compensator.io import save_model
from compensator.model import ThermalModel
from compensator.shaping import ShaperConfig
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import VirtualMachine
from thermocomp.runtime import SpindleRuntime
from thermocomp.runtime.alarms import Alarm
from thermocomp.runtime.config import FaultPolicy, load_config
from thermocomp.runtime.link import Heard, LinkWatch
from thermocomp.runtime.offset import ControllerOffset

WALL0 = 1.77e9


def test_a_controller_that_keeps_a_foreign_value_gets_writes_again_once_it_takes_them() -> None:
    """A controller holds a value beyond the clamp and refuses every write for a while: the
    offset backs off, but the same foreign value read back again with nothing written since is
    no new refusal, so the back-off runs out and the writes go through once it takes them."""
    logging.disable(logging.CRITICAL)
    try:
        counters = dict.fromkeys(
            ("writes", "write_rejected", "mismatches", "readbacks", "link_down_cycles"), 0
        )
        faults = FaultPolicy()
        off = ControllerOffset(
            "s1", ShaperConfig(max_offset_um=50.0), faults, 1.0, counters, can_read_back=True
        )
        link = LinkWatch("s1", faults, counters, cutting_from_controller=False, reconnects=0)
        held = [80.0]  # beyond the 50 um clamp
        refusing = [True]

        def write(value: float | None, life: object = None) -> WriteResult:
            if refusing[0]:
                return WriteResult(Failure(FailureKind.REFUSED, "locked by the control"))
            held[0] = value
            return WriteResult()

        for t in range(400):
            refusing[0] = t < 10
            reading = Reading(1000.0, held_offset_um=held[0] if off.wants_readback(True) else None)
            heard = Heard(1000.0, Alarm.NONE, False, True, "controller", None, None)
            off.take(float(t), reading, heard, link)
            assert abs(off.held_um) <= 50.0  # the edge of the clamp, never the foreign value
            shaped = off.plan(-10.0, 1000.0, 1.0, True)
            off.apply(float(t), shaped, heard, link, write, lambda t=t: float(t))
    finally:
        logging.disable(logging.NOTSET)
    assert held[0] == 10.0 and counters["writes"] > 0  # it follows the model again


class ProbeWhileDown(SimAdapter):
    """A sim link whose speed is lost for a while, then a bad value (its status not Good yet),
    while the tool setter's cycle finishes during the outage."""

    mode = "ok"
    sequence = 0

    def _read_speed_raw(self) -> Any:
        if self.mode == "down":
            raise self._link_lost("the controller is gone")
        if self.mode == "bad":
            raise BadValueError("speed node BadWaitingForInitialData")
        return 5000.0

    def _read_measurement_raw(self) -> RawMeasurement:
        return RawMeasurement(self.sequence, 3.0, 0.5)


def test_a_measurement_taken_while_the_link_was_down_is_fused_not_lost(tmp_path: Path) -> None:
    model = tmp_path / "model.json"
    save_model(
        model,
        ThermalModel.from_discrete(0.99, (0.0, 0.002, 0.0, 0.0), 1.0, speed_range_rpm=(0, 24000)),
    )
    (tmp_path / "m.toml").write_text(
        f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\n[[spindle]]\nname = "s1"\n'
        f'model = "{model}"\nperiod_s = 1.0\nadapter = {{url = "sim://"}}\n'
        "[spindle.observer]\nenabled = true\n"
    )
    cfg = load_config(tmp_path / "m.toml")
    t = [0.0]
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=3), None, clock=lambda: t[0])
    link = ProbeWhileDown(machine=vm)
    rt = SpindleRuntime(
        cfg.spindle[0],
        cfg.state_dir,
        cfg.journal_path,
        clock=lambda: t[0],
        wall=lambda: WALL0 + t[0],
        adapter=link,
    )
    try:
        for k in range(12):
            t[0] += 1.0
            link.mode = "down" if 3 <= k < 6 else "bad" if k == 6 else "ok"
            if k == 5:
                link.sequence += 1  # the probe cycle finishes while the link is down
            rt.cycle()
    finally:
        rt.close()
    assert rt.counters["probes_accepted"] == 1  # read with the first answer after the outage


def test_a_session_lost_while_a_node_is_looked_up_ends_the_read_with_a_failure() -> None:
    """The OPC UA session times out while the cycle resolves a node given by its browse path
    (at the first read after a reconnect): the read ends there with the link's failure, never
    an exception. A stand-in client: a server that hangs on exactly one browse cannot be
    staged on loopback in lock-step."""
    from cnc_adapters.opcua import OpcUaAdapter

    class Root:
        def get_child(self, parts: Any) -> Any:
            raise TimeoutError("hung")

    class Nodes:
        root = Root()

    class Session:
        def disconnect_socket(self) -> None:
            pass

    class Client:
        nodes = Nodes()
        aio_obj = Session()
        close_tloop = False

        class tloop:
            @staticmethod
            def post(coroutine: Any) -> None:
                coroutine.close()

        def read_attributes(self, nodes: Any) -> Any:
            raise AssertionError("no request after the session was lost")

    link = OpcUaAdapter(
        "opc.tcp://127.0.0.1:1/",
        speed_node="ns=2;s=S",
        offset_node="ns=2;s=O",
        cutting_node="0:Objects/2:Cut",
    )
    link._client, link._open, link._speed, link._offset = Client(), True, "S", "O"
    reading = link.read(Wants(cutting=True))
    assert isinstance(reading.speed_rpm, Failure) and reading.speed_rpm.link_lost
    assert isinstance(reading.cutting, Failure) and reading.cutting.link_lost
