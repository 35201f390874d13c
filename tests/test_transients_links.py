"""Speed transients (issue 18) on every link that carries the controller's cutting signal: the
runtime takes it over the real protocol and, while the tool cuts, never moves the offset faster
than the cutting slew limit (checked on the journal's own dt: one clock). OPC UA against the
virtual CNC in lock-step; LinuxCNC's HAL pins in a real halrun; Modbus RTU against pymodbus's
server on a pseudo-terminal."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from devices import ModbusDevice, PtyPair
from test_linuxcnc import run_in_hal, why_not
from test_transients import (  # noqa: F401 - model_file is a fixture
    FAST_RATE,
    MAX_RATE,
    WALL0,
    assert_slow_while_cutting,
    lag_um,
    model_file,
)

from cnc_adapters import Wants, open_adapter
from compensator.clock import SteppedClock
from compensator.io import read_run_log
from compensator.speed_programs import Program
from machine_sim import SpindlePlant, preset
from machine_sim.vcnc import VirtualCNC, VirtualMachine, running, step
from thermocomp.runtime import Alarm, SpindleRuntime
from thermocomp.runtime.config import load_config

PROGRAM = Program(
    "two-ops", ((5.0, 0.0), (100.0, 22500.0), (15.0, 0.0), (100.0, 9000.0), (20.0, 0.0))
)
SHAPING = [
    "[spindle.shaping]",
    "max_offset_um = 60.0",
    f"max_rate_um_per_s = {MAX_RATE}",
    f"not_cutting_rate_um_per_s = {FAST_RATE}",
    "deadband_um = 0.1",
]


def runtime(tmp_path: Path, model: Path, adapter: str, clock, **kw) -> SpindleRuntime:
    lines = [
        f'state_dir = "{tmp_path / "state"}"',
        "watchdog = false",
        "journal_fsync_s = 3600.0",
        "[[spindle]]",
        'name = "s1"',
        f'model = "{model}"',
        "period_s = 1.0",
        "state_save_every_s = 600.0",
        f"adapter = {adapter}",
        *SHAPING,
    ]
    path = tmp_path / "machine.toml"
    path.write_text("\n".join(lines) + "\n")
    cfg = load_config(path)
    return SpindleRuntime(
        cfg.spindle[0],
        cfg.state_dir,
        cfg.journal_path,
        journal_fsync_s=cfg.journal_fsync_s,
        clock=clock,
        wall=lambda: WALL0 + clock(),
        **kw,
    )


def journal(tmp_path: Path):
    (path,) = sorted((tmp_path / "state" / "journal").glob("s1-*.csv"))
    return read_run_log(path)


def opcua_day(tmp_path: Path, model: Path, adapter_extra: str = "", program: Program = PROGRAM):
    """The runtime over OPC UA against the virtual CNC, in lock-step on one stepped clock: the
    simulated time moves on only once a cycle is done. Rows, and the machine's cutting state."""
    clock = SteppedClock()
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=4), None, clock=clock)
    rows, truth = [], []
    with running(VirtualCNC(vm, tick_s=None)) as cnc:
        rt = runtime(
            tmp_path, model, f'{{url = "{cnc.url}", preset = "virtual-cnc"{adapter_extra}}}', clock
        )
        step(cnc)
        rows.append(rt.cycle())
        truth.append(vm.cutting)
        vm.load_program(program)
        while not vm.program_done:
            clock.advance(rt.next_period_s())
            step(cnc)  # the CNC takes the last offset and moves on to now
            rows.append(rt.cycle())
            truth.append(vm.cutting)
        rt.close()
    return rows, np.array(truth), journal(tmp_path)


def test_opcua_the_controllers_cutting_node_keeps_the_offset_slow_in_the_cut(tmp_path, model_file):
    _rows, truth, log = opcua_day(tmp_path, model_file)
    assert set(log.extras["cutting_source"]) == {"controller"}
    journaled = np.asarray(log.extras["cutting"], float) == 1
    assert (journaled == truth).all()
    assert_slow_while_cutting(log, journaled)
    moved = np.abs(np.diff(log.extras["offset_um"]))
    assert moved[~journaled[1:]].max() > 3 * MAX_RATE  # the run-ups: fast
    assert lag_um(log)[journaled].max() < 0.25


def test_opcua_a_wrong_cutting_node_fails_the_signal_not_the_link(tmp_path, model_file):
    short = Program("short", ((30.0, 12000.0),))
    rows, _, log = opcua_day(
        tmp_path, model_file, ', cutting_node = "ns={ns};s=/No/Such/Node"', short
    )
    assert all(r["alarms"] & Alarm.CUTTING_SIGNAL_FAILED for r in rows)
    assert all(r["link"] == "connected" for r in rows)
    assert set(log.extras["cutting_source"]) == {"speed-fallback"}
    assert sum(r["written"] for r in rows) >= 3  # compensation went on, inferred


def test_opcua_cutting_values_read_an_enumeration_or_an_inverted_bit():
    from cnc_adapters.opcua import OpcUaAdapter

    clock = SteppedClock()
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=4), None, clock=clock)
    vm.override_speed(9000.0)
    with running(VirtualCNC(vm, tick_s=None)) as cnc:
        clock.advance(20.0)
        step(cnc)
        assert vm.cutting
        node = "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/Cutting"
        inverted = OpcUaAdapter(
            cnc.url, preset="virtual-cnc", cutting_node=node, cutting_values=(False,)
        )
        plain = open_adapter({"url": cnc.url, "preset": "virtual-cnc"})
        off = open_adapter({"url": cnc.url, "preset": "virtual-cnc", "cutting_node": ""})
        try:
            assert (plain.read_cutting(), inverted.read_cutting(), off.read_cutting()) == (
                True,
                False,
                None,
            )
            assert plain.read(Wants(cutting=True)).cutting is True  # in the speed's request
        finally:
            for a in (inverted, plain, off):
                a.close()
    with pytest.raises(Exception, match="cutting_values"):
        open_adapter(
            {"url": "opc.tcp://127.0.0.1:9/", "preset": "virtual-cnc", "cutting_values": "maybe"}
        )


def test_modbus_the_plcs_cutting_register_keeps_the_offset_slow_in_the_cut(tmp_path, model_file):
    pty = PtyPair(tmp_path)
    dev = ModbusDevice(pty.dev)
    t = [0.0]
    try:
        rt = runtime(
            tmp_path,
            model_file,
            f'{{url = "serial://{pty.ctl}?protocol=modbus", baudrate = 115200, '
            "cutting_register = 8}",
            lambda: t[0],
        )
        # a run-up to 20 000 rpm, the approach, a cut; a run-down; a cut at 8000 (state 1 = cutting)
        profile = (
            [(0.0, 0)] * 2
            + [(5000.0 * k, 0) for k in (1, 2, 3, 4)]
            + [(20000.0, 0)] * 3
            + [(20000.0, 1)] * 60
            + [(20000.0 - 5000.0 * k, 0) for k in (1, 2, 3, 4)]
            + [(0.0, 0)] * 3
            + [(4000.0, 0), (8000.0, 0)]
            + [(8000.0, 0)] * 3
            + [(8000.0, 1)] * 60
        )
        rows = []
        for rpm, state in profile:
            dev.set_speed(rpm)
            dev.set_registers("holding", 8, [state])
            rows.append(rt.cycle())
            t[0] += 1.0
        rt.close()
    finally:
        dev.close()
        pty.close()
    log = journal(tmp_path)
    cutting = np.asarray(log.extras["cutting"], float) == 1
    assert set(log.extras["cutting_source"]) == {"controller"}
    assert (cutting == np.array([s == 1 for _, s in profile])).all()
    assert_slow_while_cutting(log, cutting)
    moved = np.abs(np.diff(log.extras["offset_um"]))
    assert moved[~cutting[1:]].max() > 3 * MAX_RATE


LINUXCNC_SCRIPT = """
import json, pathlib, tempfile
import hal
from cnc_adapters.linuxcnc import LinuxCncAdapter
from compensator.io import read_run_log, save_model
from compensator.model import ThermalModel
from thermocomp.runtime import SpindleRuntime
from thermocomp.runtime.config import load_config

out = {}
def pins(comp):
    return sorted(p["NAME"][len(comp) + 1:] for p in hal.get_info_pins() if p["NAME"].startswith(comp + "."))

a = LinuxCncAdapter(component="tc-feed", machine_state="pins", held_pin="", cutting="feed")
a.open()
seen = []
for at, motion in ((False, 2), (True, 1), (True, 2), (True, 3), (True, 4), (True, 5)):
    hal.set_p("tc-feed.at-speed", "1" if at else "0")
    hal.set_p("tc-feed.motion-type", str(motion))
    seen.append(a.read_cutting())
out["feed"] = seen
b = LinuxCncAdapter(component="tc-pin", machine_state="pins", held_pin="", cutting="pin")
b.open()
hal.set_p("tc-pin.cutting", "1")
out["pin"] = [b.read_cutting()]
hal.set_p("tc-pin.cutting", "0")
out["pin"].append(b.read_cutting())
c = LinuxCncAdapter(component="tc-at", machine_state="pins", held_pin="", cutting="at-speed")
c.open()
hal.set_p("tc-at.at-speed", "1")
out["at_speed"] = c.read_cutting()
d = LinuxCncAdapter(component="tc-none", machine_state="pins", held_pin="")
d.open()
out["none"] = [d.can_read_cutting, d.read_cutting()]
out["pins"] = {k: pins(k) for k in ("tc-feed", "tc-pin", "tc-at", "tc-none")}

# the runtime on the feed pins: a run-up, the approach (traverse), a cut, a run-down, a cut in arcs
work = pathlib.Path(tempfile.mkdtemp())
m = ThermalModel.from_discrete(0.99, (0.0, 0.02, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 27000.0),
                               elastic_um=(0.05, 0.0205))
save_model(work / "model.json", m)
(work / "machine.toml").write_text("\\n".join([
    f'state_dir = "{work / "state"}"', "watchdog = false", "[[spindle]]", 'name = "s1"',
    f'model = "{work / "model.json"}"', "period_s = 1.0",
    'adapter = {type = "linuxcnc", component = "tc-rt", machine_state = "pins", held_pin = "", cutting = "feed"}',
    "[spindle.shaping]", "max_offset_um = 60.0", "max_rate_um_per_s = 1.0",
    "not_cutting_rate_um_per_s = 50.0", "deadband_um = 0.1"]) + "\\n")
cfg = load_config(work / "machine.toml")
t = [0.0]
rt = SpindleRuntime(cfg.spindle[0], cfg.state_dir, cfg.journal_path, clock=lambda: t[0],
                    wall=lambda: 1.0e6 + t[0])
rt.adapter.open()
hal.set_p("tc-rt.machine-on", "1")
hal.set_p("tc-rt.homed", "1")
profile = [(0, True, 0)] * 2 + [(5000 * k, False, 1) for k in (1, 2, 3, 4)] + [(20000, True, 1)] * 3 \\
    + [(20000, True, 2)] * 60 + [(20000, True, 1)] + [(20000 - 5000 * k, False, 0) for k in (1, 2, 3, 4)] \\
    + [(8000, True, 1)] * 3 + [(8000, True, 3)] * 60
for rpm, at, motion in profile:
    hal.set_p("tc-rt.speed-in", str(rpm / 60.0))
    hal.set_p("tc-rt.at-speed", "1" if at else "0")
    hal.set_p("tc-rt.motion-type", str(motion))
    rt.cycle()
    t[0] += 1.0
out["counts"] = hal.get_value("tc-rt.eoffset-counts")
rt.close()
(path,) = sorted((work / "state" / "journal").glob("s1-*.csv"))
log = read_run_log(path)
out["expected"] = [at and motion in (2, 3) for _, at, motion in profile]
for key in ("offset_um", "predicted_um", "dt_s", "cutting"):
    out[key] = [float(v) for v in log.extras[key]]
out["cutting_source"] = sorted(set(log.extras["cutting_source"]))
print("@@", json.dumps(out), flush=True)
"""


@pytest.mark.skipif(why_not() is not None, reason=why_not() or "")
def test_linuxcnc_at_speed_and_motion_type_pins_keep_the_offset_slow_in_feed_moves():
    out = run_in_hal(LINUXCNC_SCRIPT)
    # feed: at speed and a feed move (linear 2, arc 3); not in a traverse, tool change or probe
    assert out["feed"] == [False, False, True, True, False, False]
    assert out["pin"] == [True, False] and out["at_speed"] is True
    assert out["none"] == [False, None]
    assert {"at-speed", "motion-type"} <= set(out["pins"]["tc-feed"]) and "cutting" not in out[
        "pins"
    ]["tc-feed"]
    assert "cutting" in out["pins"]["tc-pin"] and "motion-type" not in out["pins"]["tc-at"]
    assert not {"cutting", "at-speed", "motion-type"} & set(out["pins"]["tc-none"])
    cutting = np.array(out["cutting"]) == 1
    assert out["cutting_source"] == ["controller"] and (cutting == np.array(out["expected"])).all()
    offset, dt = np.array(out["offset_um"]), np.array(out["dt_s"])[1:]
    moved = np.abs(np.diff(offset))
    both = cutting[1:] & cutting[:-1]
    assert both.sum() > 100 and (moved[both] <= MAX_RATE * dt[both] + 1e-9).all()
    assert moved[~cutting[1:]].max() > 3 * MAX_RATE  # the run-ups: fast
    # the counts motion applies: the last offset (0.01 um a count, Z's sign: +S)
    assert out["counts"] == round(-offset[-1] / 0.01)
