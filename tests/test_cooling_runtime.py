"""``[cooling]`` in the runtime: the spindle's estimate drives a chiller over a real Modbus TCP
link (pymodbus's server on loopback, backed by the plant), in lock-step with a fake clock."""

from __future__ import annotations

import csv
import math
import threading

import numpy as np
import pytest

from calibration.cooling_studies import fit_cooling_model
from cnc_adapters.chiller import open_chiller
from compensator.errors import ConfigError
from compensator.io import save_model
from compensator.speed_programs import Program
from machine_sim.adapter import SimAdapter
from machine_sim.chiller_server import ChillerServer
from machine_sim.plant import SpindlePlant, preset
from machine_sim.vcnc import VirtualMachine
from thermocomp.runtime.config import load_config
from thermocomp.runtime.cooling import CHILLER_FAILED, CoolingRuntime
from thermocomp.runtime.spindle import SpindleRuntime

WALL0 = 1_800_000_000.0
PERIOD_S = 5.0


@pytest.fixture(scope="module")
def cooling_model(tmp_path_factory):
    path = tmp_path_factory.mktemp("cooling") / "model.json"
    save_model(path, fit_cooling_model(preset("mechanical-cooled")).model)
    return path


def config(
    tmp_path,
    model,
    mode="both",
    chiller='{ type = "modbus", host = "127.0.0.1", port = 1 }',
    extra="",
):
    p = tmp_path / "machine.toml"
    p.write_text(
        "\n".join(
            [
                f'state_dir = "{tmp_path / "state"}"',
                "watchdog = false",
                "[[spindle]]",
                'name = "s1"',
                f'model = "{model}"',
                f"period_s = {PERIOD_S}",
                'adapter = { url = "sim://mechanical-cooled" }',
                "[spindle.shaping]",
                "max_offset_um = 60.0",
                "max_rate_um_per_s = 2.0",
                "[spindle.faults]",
                "input_stale_s = 86400.0",
                "[cooling]",
                f'mode = "{mode}"',
                "rite_um = 17.0",
                "preheat_c = 16.0",
                "min_c = 8.0",
                "max_c = 26.0",
                "dew_point_c = 5.0",
                f"period_s = {PERIOD_S}",
                "hold_s = 120.0",
                f"chiller = {chiller}",
                extra,
            ]
        )
        + "\n"
    )
    return p


class Rig:
    """A spindle runtime on the virtual machine (3000 rpm, paper 000's preset) and the cooling
    runtime on a chiller, stepped together."""

    def __init__(self, tmp_path, model, chiller_table, mode="both"):
        self.t = 0.0
        self.plant = SpindlePlant(preset("mechanical-cooled"), seed=2)
        self.lock = threading.Lock()
        # the service runs before the spindle starts: a cold start at rest
        self.vm = VirtualMachine(
            self.plant,
            Program("wc1", ((60.0, 0.0), (8 * 3600.0, 3000.0))),
            clock=lambda: self.t,
            plant_dt_s=PERIOD_S,
        )
        self.cfg = load_config(config(tmp_path, model, mode, chiller_table))
        clock, wall = (lambda: self.t), (lambda: WALL0 + self.t)
        self.spindle = SpindleRuntime(
            self.cfg.spindle[0],
            self.cfg.state_dir,
            self.cfg.journal_path,
            clock=clock,
            wall=wall,
            adapter=SimAdapter(machine=self.vm, clock=clock),
        )
        self.spindle.writes_offset = mode != "cooling"
        self.clock, self.wall = clock, wall

    def cooling(self, chiller):
        self.rt = CoolingRuntime(
            self.cfg.cooling,
            self.spindle,
            self.cfg.journal_path,
            clock=self.clock,
            wall=self.wall,
            anchor_s=WALL0,
            chiller=chiller,
        )
        return self.rt

    def run(self, seconds):
        rows = []
        for _ in range(int(seconds / PERIOD_S)):
            self.t += PERIOD_S
            with self.lock:
                self.spindle.cycle()
            rows.append(self.rt.cycle())
        return rows


def test_pid_over_modbus_holds_the_error_and_the_offset_cancels_the_rest(tmp_path, cooling_model):
    rig = Rig(tmp_path, cooling_model, '{ type = "modbus", host = "127.0.0.1", port = 1 }')
    with ChillerServer(rig.plant, lock=rig.lock) as server:
        chiller = open_chiller(
            "modbus", {"host": "127.0.0.1", "port": server.port, "timeout_s": 2.0}, clock=rig.clock
        )
        rt = rig.cooling(chiller)
        rows = rig.run(6 * 3600)
        assert server.writes > 0
    phases = [r["phase"] for r in rows]
    closed_at = phases.index("closed")
    # preheat at the constant until the estimate reached RITE (the paper: ~1.5 h at 3000 rpm)
    assert all(r["setpoint_c"] == 16.0 for r in rows[:closed_at])
    assert rows[closed_at - 1]["estimate_um"] < 17.0 <= rows[closed_at]["estimate_um"]
    # the set point went where the law sent it, within the limits, and the plant's chiller took it
    sp = np.array([r["setpoint_c"] for r in rows])
    assert sp.min() >= 8.0 and sp.max() <= 26.0 and sp.min() < 15.0
    assert rig.plant.chiller_setpoint_c == pytest.approx(sp[-1], abs=0.05)
    assert np.max(np.abs(np.diff(sp))) <= 1.0 / 60 * PERIOD_S + 0.1 + 1e-9
    # the growth is held near RITE (constant cooling reaches ~28 um by 6 h on this preset)
    h = rig.vm.history()
    true = h.true_um
    assert abs(true[-1] - 17.0) < 2.5
    # `both`: the offset cancels what the cooling leaves
    assert np.abs(h.tool_tip_error_um[-720:]).max() < 1.0
    # every command journaled, with what came back from the chiller
    rt.close()
    path = next(rig.cfg.journal_path.glob("s1.cooling-*.csv"))
    with open(path) as fh:
        body = list(csv.DictReader(x for x in fh if not x.startswith("#")))
    assert len(body) == len(rows)
    assert {r["phase"] for r in body} == {"preheat", "closed"}
    assert all(r["supply_c"] != "" for r in body)
    rig.spindle.close()


def test_chiller_fault_holds_then_goes_to_the_constant_then_resumes_bumplessly(
    tmp_path, cooling_model
):
    rig = Rig(tmp_path, cooling_model, '{ type = "virtual" }', mode="cooling")
    chiller = open_chiller("virtual", {}, plant=rig.plant, lock=rig.lock, clock=rig.clock)
    rt = rig.cooling(chiller)
    rows = rig.run(3 * 3600)
    assert rows[-1]["phase"] == "closed" and rows[-1]["setpoint_c"] < 16.0
    last_taken = rig.plant.chiller_setpoint_c
    chiller.reachable = False
    down = rig.run(600)
    assert all(r["alarm"] == CHILLER_FAILED and not r["sent"] for r in down)
    # the chiller keeps what it took; the law holds it for hold_s, then goes to the constant
    assert rig.plant.chiller_setpoint_c == last_taken
    assert [r["setpoint_c"] for r in down[: int(110 / PERIOD_S)]] == [last_taken] * int(
        110 / PERIOD_S
    )
    assert down[-1]["setpoint_c"] == pytest.approx(16.0)
    chiller.reachable = True
    back = rig.run(120)
    # the link's back-off (30 s at most, on the same clock) ends, and the constant is written first
    first = next(k for k, r in enumerate(back) if r["sent"])
    assert first * PERIOD_S <= 35.0
    assert back[first]["alarm"] == "" and back[first]["setpoint_c"] == pytest.approx(16.0)
    assert all(r["alarm"] == CHILLER_FAILED for r in back[:first])
    # the loop closes again from the constant without a bump
    steps = np.abs(np.diff([16.0] + [r["setpoint_c"] for r in back]))
    assert steps.max() <= 1.0 / 60 * PERIOD_S + 0.1 + 1e-9
    assert back[-1]["phase"] == "closed"
    # mode "cooling": the offset is never written
    assert rig.spindle.counters["writes"] == 0 and rig.vm.offset_um == 0.0
    rt.close()
    rig.spindle.close()


def test_cooling_configuration_is_checked_in_one_line(tmp_path, cooling_model):
    cfg = load_config(config(tmp_path, cooling_model))
    assert cfg.cooling_spindle == "s1" and cfg.cooling.law().rite_um == 17.0
    for extra, msg in (
        ("min_c = 20.0", "outside the limits"),
        ("surprise = 1", "surprise"),
        ("gains = { kp = -1.0 }", "kp"),
    ):
        p = config(tmp_path, cooling_model, extra=extra)
        text = (
            p.read_text().replace("min_c = 8.0\n", "")
            if extra.startswith("min_c")
            else p.read_text()
        )
        p.write_text(text)
        with pytest.raises(ConfigError, match=msg) as err:
            load_config(p)
        assert "\n" not in str(err.value)
    p = config(tmp_path, cooling_model, chiller='{ type = "nope" }')
    with pytest.raises(ConfigError, match="unknown chiller backend"):
        load_config(p)
    p = config(tmp_path, cooling_model)
    p.write_text(p.read_text().replace("rite_um = 17.0\n", ""))
    with pytest.raises(ConfigError, match="rite_um"):
        load_config(p)
    assert math.isfinite(cfg.cooling.preheat_c)
