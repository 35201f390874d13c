"""FANUC, route FOCAS (issue 19): thermocomp's pure-socket FOCAS client against a loopback FOCAS
server built from the documented packet format (``machine_sim.focas_server``), and the
runtime with ``profile = "fanuc"`` in lock-step with the virtual machine behind the emulated
FANUC control (detection units, whole counts, the 9999-unit step alarm).

What this cannot show: that a real FANUC answers as the documented captures say, or that the
builder's ladder hands the variable to the THD signals; see docs/controls/fanuc.md.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
from controlrig import MAX_OFFSET_UM, control_runtime
from test_transients import assert_slow_while_cutting

from cnc_adapters import (
    AdapterTimeoutError,
    BadValueError,
    ConfigError,
    UnreachableError,
    WriteRejectedError,
    open_adapter,
)
from cnc_adapters.control_profiles import profile
from cnc_adapters.focas import FocasAdapter, command, decode_scaled, request_packet
from compensator.clock import SteppedClock
from compensator.io import read_run_log
from compensator.speed_programs import Program
from machine_sim import SpindlePlant, preset
from machine_sim.controls import EmulatedControl
from machine_sim.focas_server import FocasServer, PlainControl, encode_scaled
from machine_sim.vcnc import VirtualMachine

FANUC = profile("fanuc")
# a warm-up, two operations with a tool change, a run-down: half an hour of the thermal transient
PROGRAM = Program(
    "fanuc-day",
    ((5.0, 0.0), (600.0, 22500.0), (20.0, 0.0), (600.0, 9000.0), (300.0, 24000.0), (300.0, 0.0)),
)


def fanuc_machine(**kw) -> tuple[VirtualMachine, EmulatedControl]:
    vm = VirtualMachine(
        SpindlePlant(preset("motorized-27k"), seed=4), None, clock=kw.pop("clock", None)
    )
    return vm, EmulatedControl(vm, FANUC, **kw)


class Clock:
    """A settable clock for the link's back-off."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


# -- the wire format -------------------------------------------------------------------------


def test_the_client_sends_the_documented_packets_byte_for_byte():
    packet = pytest.importorskip("pyfocas.protocol.packet")
    PacketOrigin, PacketType, create_packet = (
        packet.PacketOrigin,
        packet.PacketType,
        packet.create_packet,
    )

    # the README's read of #502: 00 1c | 00 01 | 00 01 00 15 | 00 00 01 f6 | 00 00 01 f6 | 12 x 00
    readme = bytes.fromhex(
        "a0a0a0a0 0001 2101 001e 0001 001c 0001 00010015 000001f6 000001f6"
    ) + bytes(12)
    assert request_packet(command(0x15, 502, 502)) == readme
    # and what pyfocas sends for a write of 12.0 to #500 (its write_macro_double)
    cmd = struct.pack(">HHH", 1, 1, 0xA8)
    theirs = create_packet(
        PacketOrigin.CLIENT,
        PacketType.GENERIC_REQUEST,
        cmd + struct.pack(">iiiiid", 500, 0, 0, 0, 8, 12.0),
    )
    assert request_packet(command(0xA8, 500, 0, 0, 0, 8, payload=struct.pack(">d", 12.0))) == theirs
    # 38 bytes after the length field (the README's table says "00 38": decimal, not hex)
    assert struct.unpack(">H", theirs[8:10])[0] == 0x26


def test_scaled_integers_decode_as_documented_and_encode_back():
    assert decode_scaled(bytes.fromhex("0bc77120 000a 0006")) == pytest.approx(197.62)
    assert decode_scaled(bytes.fromhex("297c1e00 000a 0006")) == pytest.approx(696.0)
    assert decode_scaled(bytes.fromhex("05f5e100 000a 0008")) == 1.0
    assert decode_scaled(bytes.fromhex("00000000 000a ffff")) is None  # vacant
    with pytest.raises(ValueError):
        decode_scaled(bytes.fromhex("00000001 0003 0001"))  # base 3
    assert encode_scaled(1.0) == bytes.fromhex("05f5e100 000a 0008")  # the README's form of 1.0
    assert encode_scaled(696.0) == bytes.fromhex("297c1e00 000a 0006")
    assert encode_scaled(None) == bytes.fromhex("00000000 000a ffff")
    rng = np.random.default_rng(1)
    for v in [0.0, -1.0, 9998.0, -32767.0, 12.3456789, *rng.uniform(-3e4, 3e4, 50)]:
        assert decode_scaled(encode_scaled(float(v))) == pytest.approx(v, rel=1e-8, abs=1e-8)


def test_pyfocas_talks_to_the_loopback_server():
    """An independent client (PyPI pyfocas) reads and writes through the server: the server
    follows the documented format, not only this repository's reading of it."""
    FOCAS = pytest.importorskip("pyfocas.protocol.protocol").FOCAS

    control = PlainControl(speed_rpm=12000.0)
    with FocasServer(control, offset_macro=500) as srv:
        client = FOCAS("127.0.0.1", srv.port)
        assert client.connect()
        client.write_macro_double(500, 12.5)
        client.write_macro_double(501, -3.25)
        assert control.held_raw == 12.5
        assert client.read_macro(500, 501) == {500: 12.5, 501: -3.25}
        client.socket.close()


# -- the client against the server -----------------------------------------------------------


def test_round_trip_speed_offset_and_read_back():
    control = PlainControl(speed_rpm=-9000.0)
    with FocasServer(control, offset_macro=500) as srv:
        with FocasAdapter("127.0.0.1", port=srv.port) as link:
            assert link.read_speed() == 9000.0  # cnc_acts, as a magnitude
            link.write_offset_um(-7.5)
            assert control.held_raw == -7.5
            assert link.read_offset_um() == -7.5
            control.held_raw = 999.0  # someone else wrote the variable
            assert link.read_offset_um() == 999.0
            link.write_macro(600, 0.125)
            assert link.read_macro(600) == 0.125 and link.read_macro(601) is None  # vacant
        # one session, ended with the close request (the control's FOCAS handle is freed)
        assert (srv.sessions, srv.closes, srv.received) == (1, 1, [-7.5])


def test_the_speed_from_a_macro_variable_and_the_read_back_from_the_ack():
    control = PlainControl(speed_rpm=15000.0)
    with FocasServer(control, offset_macro=500, ack_macro=501, speed_macro=502, acts=False) as srv:
        url = (
            f"focas://127.0.0.1:{srv.port}?offset_macro=500&ack_macro=501"
            "&speed_source=macro&speed_macro=502"
        )
        link = open_adapter(url)
        try:
            assert link.read_speed() == 15000.0
            link.write_offset_um(4.0)
            assert link.read_offset_um() == 4.0
        finally:
            link.close()
        assert srv.calls[0x25] == 0  # no cnc_acts


def test_a_control_without_cnc_acts_says_so_and_names_the_alternative():
    with (
        FocasServer(PlainControl(), acts=False) as srv,
        FocasAdapter("127.0.0.1", port=srv.port) as link,
    ):
        with pytest.raises(BadValueError, match=r"FOCAS error 1 .*speed_source = 'macro'"):
            link.read_speed()
        link.write_offset_um(1.0)  # the session is still good


def test_a_vacant_variable_is_a_bad_value_not_a_zero():
    with FocasServer(PlainControl(), speed_macro=None) as srv:
        with FocasAdapter(
            "127.0.0.1", port=srv.port, speed_source="macro", speed_macro=510
        ) as link:
            with pytest.raises(BadValueError, match="vacant"):
                link.read_speed()


def test_a_refused_write_is_write_rejected_and_the_control_keeps_its_value():
    _vm, control = fanuc_machine()
    with FocasServer(control) as srv:
        link = open_adapter({"profile": "fanuc", "host": "127.0.0.1", "port": srv.port})
        try:
            link.write_offset_um(-25.0)  # a growth of 25 detection units
            assert control.held_raw == 25.0
            with pytest.raises(WriteRejectedError, match="EW_DATA"):
                link.write_offset_um(-10025.0)  # a step of 10 000 units: the control's alarm
            assert control.held_raw == 25.0 and control.refused == 1
            assert "step" in control.last_refusal
            assert link.read_offset_um() == -25.0
            link.write_offset_um(-30.0)  # the session goes on
            assert control.held_raw == 30.0
        finally:
            link.close()


def test_the_ladder_refusing_shows_in_the_ack_not_in_focas():
    """On a real control the macro variable takes any number: the refusal is the ladder's, so
    only ``ack_macro`` (the value the control took) reveals it."""
    _vm, control = fanuc_machine()
    with FocasServer(control, ack_macro=501, refuse_in="ladder") as srv:
        plain = open_adapter({"profile": "fanuc", "host": "127.0.0.1", "port": srv.port})
        acked = open_adapter(
            {"profile": "fanuc", "host": "127.0.0.1", "port": srv.port, "ack_macro": 501}
        )
        try:
            plain.write_offset_um(-20.0)
            plain.write_offset_um(-10020.0)  # FOCAS takes it; the ladder refuses the step
            assert control.held_raw == 20.0 and control.refused == 1
            assert plain.read_offset_um() == -10020.0  # the variable: what was written
            assert acked.read_offset_um() == -20.0  # the ack: what the control applies
        finally:
            plain.close()
            acked.close()


def test_the_control_gone_is_unreachable_then_the_link_recovers():
    control = PlainControl(speed_rpm=8000.0)
    clock = Clock()
    changes = []
    srv = FocasServer(control).start()
    try:
        link = FocasAdapter(
            "127.0.0.1",
            port=srv.port,
            clock=clock,
            on_link_change=lambda up, why: changes.append(up),
        )
        link.write_offset_um(2.0)
        srv.stop()
        with pytest.raises(UnreachableError):
            link.write_offset_um(3.0)
        with pytest.raises(UnreachableError):  # refused now, or in the back-off
            link.read_speed()
        srv.start()  # the same port
        clock.t += 60.0  # past the back-off
        assert link.read_speed() == 8000.0
        link.write_offset_um(3.0)
        assert control.held_raw == 3.0
        assert link.reconnects == 1 and changes == [False, True]
        link.close()
    finally:
        srv.stop()


def test_a_hung_control_times_out_and_the_next_call_opens_a_new_session():
    control = PlainControl(speed_rpm=8000.0)
    with FocasServer(control) as srv:
        link = FocasAdapter("127.0.0.1", port=srv.port, timeout_s=0.2)
        try:
            assert link.read_speed() == 8000.0
            srv.fault = "hang"
            with pytest.raises(AdapterTimeoutError):
                link.write_offset_um(5.0)
            srv.fault = ""
            assert link.read_speed() == 8000.0  # a fresh session: no late reply taken
            assert srv.sessions == 2
        finally:
            link.close()


def test_settings_are_checked_in_one_line():
    a = open_adapter("focas://10.0.0.7?offset_macro=510&ack_macro=511")
    assert (a.host, a.port, a.offset_macro, a.ack_macro, a.speed_source) == (
        "10.0.0.7",
        8193,
        510,
        511,
        "acts",
    )
    p = open_adapter({"profile": "fanuc", "route": "focas", "host": "h"})
    assert (p.offset_scale, p.offset_sign, p.units.resolution, p.offset_macro) == (
        1.0,
        -1,
        1.0,
        500,
    )
    for bad, words in [
        ({"offset_macro": 1000}, "common macro variable"),
        ({"offset_macro": 33}, "common macro variable"),
        ({"ack_macro": 500}, "both #500"),
        ({"speed_source": "macro"}, "speed_macro goes with"),
        ({"speed_macro": 502}, "speed_macro goes with"),
        ({"speed_source": "plc"}, "speed_source"),
        ({"port": 70000}, "port"),
    ]:
        with pytest.raises(ConfigError, match=words):
            open_adapter({"type": "focas", "host": "h", **bad})
    with pytest.raises(ConfigError, match="host: required key missing"):
        open_adapter({"type": "focas"})


# -- the runtime, lock-step with the virtual machine --------------------------------------------


def fanuc_day(tmp_path: Path, model: Path, program: Program = PROGRAM):
    """The runtime over FOCAS to the emulated FANUC control, one stepped clock for all: the
    rows, the machine, the control, what the server received (clock time, raw) and the journal."""
    clock = SteppedClock()
    vm, control = fanuc_machine(clock=clock)
    received: list[tuple[float, float]] = []
    with FocasServer(control) as srv:
        adapter = f'{{profile = "fanuc", route = "focas", host = "127.0.0.1", port = {srv.port}}}'
        rt = control_runtime(tmp_path, model, adapter, clock)

        def cycle() -> dict:
            vm.advance()
            control.sync()  # the control applies what it holds, at its rate, to the axis
            n = len(srv.received)
            row = rt.cycle()
            received.extend((clock(), v) for v in srv.received[n:])
            return row

        rows = [cycle()]
        vm.load_program(program)
        while not vm.program_done:
            clock.advance(rt.next_period_s())
            rows.append(cycle())
        rt.close()
    (path,) = sorted((tmp_path / "state" / "journal").glob("s1-*.csv"))
    return rows, vm, control, received, read_run_log(path)


def test_fanuc_end_to_end_the_offset_reaches_the_axis_in_detection_units(
    tmp_path, calibrated_model
):
    rows, vm, control, received, log = fanuc_day(tmp_path, calibrated_model)

    # the service wrote, the control took every value, and the axis carries it
    assert sum(r["written"] for r in rows) >= 20
    assert control.refused == 0 and all(w.taken for w in control.writes)
    assert [v for _, v in received] == [w.raw for w in control.writes]
    assert vm.offset_um == pytest.approx(control.held_um) and abs(control.held_um) > 5.0

    # in the control's units: whole detection units, the growth's sign (+S), inside the clamp
    raw = np.array([v for _, v in received])
    assert (raw == np.round(raw)).all()
    assert raw.max() > 5 and raw.min() >= 0  # the spindle grows: S > 0, written as +S
    assert np.abs(raw).max() <= MAX_OFFSET_UM * FANUC.scale <= FANUC.limit
    # each change within the slew limit in force since the last change (clock time)
    t = np.array([s for s, _ in received])
    times = np.asarray(log.time_s, float) - float(log.time_s[0])
    limit = np.asarray(log.extras["slew_limit_um_per_s"], float)
    prev_t, prev_raw, worst_um = 0.0, 0.0, -math.inf
    for ti, ri in zip(t, raw):
        rate = limit[(times > prev_t - 1e-9) & (times <= ti + 1e-9)].max()
        worst_um = max(worst_um, abs(ri - prev_raw) - rate * FANUC.scale * (ti - prev_t))
        prev_t, prev_raw = ti, ri
    assert worst_um <= 1e-9
    assert np.abs(np.diff(np.concatenate([[0.0], raw]))).max() <= FANUC.max_step
    cutting = np.asarray(log.extras["cutting"], float) == 1
    assert_slow_while_cutting(log, cutting)

    # the virtual workpiece: the error shrinks as with the OPC UA route
    h = vm.history()
    rms_off = float(np.sqrt(np.mean(h.true_um**2)))
    rms_on = float(np.sqrt(np.mean(h.tool_tip_error_um**2)))
    assert rms_on < 0.1 * rms_off  # measured: 13.1 um -> 0.58 um
    assert np.abs(h.tool_tip_error_um).max() < 0.5 * np.abs(h.true_um).max()
