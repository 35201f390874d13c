"""The closed loop in the runtime (issue 17): probe and tool-setter measurements fused with the
model, cycle by cycle, on a fake clock (nothing sleeps). The virtual machine tool's tool setter
stops the spindle and measures; the runtime reads it through the adapter like a controller's
probe variables, or takes it from `thermocomp measure` (``SpindleRuntime.submit``)."""

from __future__ import annotations

import csv
import json
import logging
import math
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from test_runtime_statespace import InputSim, with_inputs

from cnc_adapters import AdapterError, AdapterTimeoutError
from cnc_adapters.opcua import OpcUaAdapter
from compensator import ConfigError
from compensator.io import load_state, read_run_log, save_model
from compensator.model import ThermalModel
from compensator.speed_programs import Program, job_shop_day
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import (
    NAMESPACE_URI,
    PROBE_METHOD_PATH,
    VirtualCNC,
    VirtualMachine,
    call,
    running,
)
from thermocomp.runtime import Alarm, SpindleRuntime
from thermocomp.runtime.config import load_config

EXAMPLES = Path(__file__).parents[1] / "examples"
RATE = 2.0
SPEED = 10000.0
WALL0 = 1.7e9


@pytest.fixture(scope="module")
def simple_model(tmp_path_factory) -> Path:
    # tau = 100 s, 2 um per krpm at steady state: 20 um at 10 000 rpm
    m = ThermalModel.from_discrete(0.99, (0.0, 0.02, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 27000.0))
    p = tmp_path_factory.mktemp("m") / "model.json"
    save_model(p, m)
    return p


def config(
    tmp_path: Path,
    model: Path,
    observer: str = "enabled = true",
    period_s: float = 1.0,
    shaping: str = f"max_offset_um = 60.0\nmax_rate_um_per_s = {RATE}\ndeadband_um = 0.0",
    extra: str = "",
) -> Path:
    lines = [
        f'state_dir = "{tmp_path / "state"}"',
        "watchdog = false",
        "journal_fsync_s = 3600.0",
        "[[spindle]]",
        'name = "s1"',
        f'model = "{model}"',
        f"period_s = {period_s}",
        "state_save_every_s = 600.0",
        'adapter = {url = "sim://"}',
        extra,
        "[spindle.shaping]",
        shaping,
        "[spindle.observer]",
        observer,
    ]
    tmp_path.mkdir(parents=True, exist_ok=True)
    p = tmp_path / "machine.toml"
    p.write_text("\n".join(lines) + "\n")
    return p


class Bench:
    """A runtime on the in-process virtual machine tool, one fake clock for both."""

    def __init__(self, tmp_path: Path, model: Path, *, make_vm=None, adapter_cls=SimAdapter, **kw):
        self.t = 0.0
        self.cfg = load_config(config(tmp_path, model, **kw))
        if make_vm is None:
            self.vm = VirtualMachine(
                SpindlePlant(preset("motorized-27k"), seed=1), None, clock=self.clock
            )
            self.vm.override_speed(SPEED)
        else:
            self.vm = make_vm(self.clock)
        self.adapter_cls = adapter_cls
        self.rt = self.start()
        self.rows: list[dict] = []

    def clock(self) -> float:
        return self.t

    def wall(self) -> float:
        return WALL0 + self.t

    def start(self, previous: SpindleRuntime | None = None) -> SpindleRuntime:
        sc = self.cfg.spindle[0]
        return SpindleRuntime(
            sc,
            self.cfg.state_dir,
            self.cfg.journal_path,
            clock=self.clock,
            wall=self.wall,
            adapter=self.adapter_cls(machine=self.vm),
            journal_fsync_s=self.cfg.journal_fsync_s,  # as the service passes it
            previous=previous,
        )

    def reload(self, tmp_path: Path, model: Path, **kw) -> None:
        """What SIGHUP does: a runtime from the new configuration goes on from the running one."""
        self.cfg = load_config(config(tmp_path, model, **kw))
        new = self.start(previous=self.rt)
        new.take_journal(self.rt)
        self.rt.close()
        self.rt = new

    def run(self, cycles: int) -> list[dict]:
        out = []
        period = self.cfg.spindle[0].period_s
        for _ in range(cycles):
            self.t += period
            out.append(self.rt.cycle())
        self.rows += out
        return out

    def measurements(self) -> list[dict[str, str]]:
        self.rt.measurements.flush(self.t)
        rows: list[dict[str, str]] = []
        for path in sorted((self.cfg.state_dir / "journal").glob("s1.measurements-*.csv")):
            with open(path, encoding="utf-8") as fh:
                rows += csv.DictReader(line for line in fh if not line.startswith("#"))
        return rows


def events(caplog, name: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if getattr(r, "event", None) == name]


def answer_box() -> tuple[list[dict], Callable[[dict], None]]:
    """Where the runtime's answer to a submitted measurement lands."""
    box: list[dict] = []
    return box, box.append


# -- the test: an unmodelled ambient drift -----------------------------------------------


@pytest.fixture
def fitted_model(calibrated_model) -> Path:
    """A speed-only model fitted on the plant in a hall at constant temperature."""
    return calibrated_model


@dataclass(frozen=True)
class Day:
    """What a drift day left: each cycle's time, estimate error, tool-tip error and alarms, the
    measurement journal's rows, the runtime's and the machine's probe counts, and the observer's
    bounds (None: no observer)."""

    t: np.ndarray
    est: np.ndarray
    tip: np.ndarray
    alarms: list[int]
    rows: list[dict[str, str]]
    accepted: int
    probes: int
    max_correction_um: float | None
    source_move_um: float | None

    def save(self, d: Path) -> None:
        np.savez(d / "day.npz", t=self.t, est=self.est, tip=self.tip)
        rest = {k: v for k, v in vars(self).items() if k not in ("t", "est", "tip")}
        (d / "day.json").write_text(json.dumps(rest))

    @classmethod
    def load(cls, d: Path) -> Day:
        with np.load(d / "day.npz") as a:
            arrays = {k: a[k] for k in ("t", "est", "tip")}
        return cls(**arrays, **json.loads((d / "day.json").read_text()))


def drift_day(tmp_path: Path, model: Path, enabled: bool, observer: str = "") -> Day:
    """Eight hours of a job shop while the hall warms by 1 K/h, a probe cycle every 30 min
    (the spindle stops for the tool setter either way); ``observer``: more observer settings."""
    p = preset("motorized-27k")

    def warming_hall(clock) -> VirtualMachine:
        vm = VirtualMachine(
            SpindlePlant(p, seed=5).with_params(ambient_drift_k_per_h=1.0),
            None,
            clock=clock,
            plant_dt_s=2.0,
        )
        vm.load_program(job_shop_day(p.max_rpm, seed=5, hours=8))
        return vm

    # the hall warms 1 K/h, which a calibration at constant temperature never saw: its fitted bias
    # random walk is far too small for that, so the shop states the one it sees (5 um per sqrt(h))
    b = Bench(
        tmp_path,
        model,
        make_vm=warming_hall,
        observer=f"enabled = {str(enabled).lower()}\n"
        f"bias_q_um2_per_s = {25.0 / 3600.0!r}\n{observer}",
        period_s=10.0,
        shaping="max_offset_um = 60.0\nmax_rate_um_per_s = 1.0\ndeadband_um = 0.0",
    )
    vm = b.vm
    next_probe = 1800.0
    while not vm.program_done:
        if b.t >= next_probe:
            vm.start_probe()  # the NC program's probe cycle
            next_probe += 1800.0
        b.run(1)
    rows = b.measurements()
    b.rt.close()
    fused = b.rt.estimate.fused
    h = vm.history()
    t = np.array([r["time_s"] for r in b.rows])
    return Day(
        t=t,
        est=np.interp(t, h.time_s, h.true_um) - np.array([r["predicted_um"] for r in b.rows]),
        tip=np.interp(t, h.time_s, h.tool_tip_error_um),
        alarms=[int(r["alarms"]) for r in b.rows],
        rows=rows,
        accepted=b.rt.counters["probes_accepted"],
        probes=vm.probe_sequence,
        max_correction_um=None if fused is None else fused.config.max_correction_um,
        source_move_um=None if fused is None else fused.config.source_move_um,
    )


def fused_day(computed_once, model: Path) -> tuple[Day, Path]:
    """drift_day with the observer's default bounds, run once per test session (it takes a
    while): test_observer_bounds checks the bounds on the same day. With the model it ran."""

    def make(d: Path) -> None:
        shutil.copyfile(model, d / "model.json")
        drift_day(d, d / "model.json", enabled=True).save(d)

    d = computed_once("fused-drift-day", make)
    return Day.load(d), d / "model.json"


def test_observer_on_the_virtual_plant_with_unmodelled_ambient_drift(
    tmp_path, fitted_model, computed_once
):
    opened = drift_day(tmp_path / "open", fitted_model, enabled=False)
    fused, _ = fused_day(computed_once, fitted_model)
    t, open_est, open_tip = opened.t, opened.est, opened.tip
    fused_est, fused_tip = fused.est, fused.tip
    assert np.array_equal(t, fused.t)
    hour = np.minimum((t // 3600).astype(int), 7)
    rms = lambda e, k: float(np.sqrt(np.mean(e[hour == k] ** 2)))
    open_by_hour = [rms(open_est, k) for k in range(8)]
    fused_by_hour = [rms(fused_est, k) for k in range(8)]
    # open loop: the error grows with the hall's temperature
    assert open_by_hour[7] > 5.0 and open_by_hour[7] > 5 * open_by_hour[0]
    assert np.all(np.diff(open_by_hour[3:]) > -1.0)
    # fused: bounded from the first probe on, whatever the hour
    after = t > 1800.0 + 30.0
    assert max(fused_by_hour) < 1.5
    assert np.abs(fused_est[after]).max() < 3.0
    assert fused_by_hour[7] < open_by_hour[7] / 4
    # what the part sees, shaper and all: better too
    late = t > 6 * 3600.0
    assert np.sqrt(np.mean(fused_tip[late] ** 2)) < 0.6 * np.sqrt(np.mean(open_tip[late] ** 2))
    rows = fused.rows
    assert len(rows) == fused.accepted == fused.probes >= 15
    assert {r["outcome"] for r in rows} == {"accepted"} and {r["source"] for r in rows} == {"sim"}
    assert [int(r["sequence"]) for r in rows] == list(range(1, len(rows) + 1))
    assert not any(
        a & (Alarm.PROBE_REJECTED | Alarm.PROBE_FAILED | Alarm.OBSERVER_STALE) for a in fused.alarms
    )


def test_a_probe_seen_once_the_spindle_runs_again_is_compared_at_rest(tmp_path, fitted_model):
    """The tool setter measures at rest; the runtime may see the new counter only once the program
    has restarted the spindle (here at 22 500 rpm, ~11 um of elastic growth the model knows)."""

    def steady(clock) -> VirtualMachine:
        return VirtualMachine(
            SpindlePlant(preset("motorized-27k"), seed=1),
            Program("steady", ((20000.0, 22500.0),)),
            clock=clock,
        )

    b = Bench(tmp_path, fitted_model, make_vm=steady, period_s=3.0)
    b.run(600)
    b.vm.start_probe()
    rows = b.run(20)
    seen = next(r for r in rows if r["observer"]["since_measurement_s"] == 0.0)
    assert seen["speed_rpm"] > 0.0  # read after the restart (the spindle running up again)
    (m,) = b.measurements()
    assert abs(float(m["innovation_um"])) < 1.5  # met the estimate at rest, not the one at speed
    assert abs(b.rt.state.bias_um) < 1.5
    h = b.vm.history()
    assert (
        abs(np.interp(b.rows[-1]["time_s"], h.time_s, h.true_um) - b.rows[-1]["predicted_um"]) < 1.5
    )
    b.rt.close()


# -- safety: slew limit, outliers, failing sources, staleness ------------------------------------


WIDE = "enabled = true\nmax_correction_um = 100.0\nmax_source_move_um = 100.0"
"""Bounds wide enough for the one large correction these tests make (test_observer_bounds)."""


def test_slew_limits_respected_after_a_large_correction(tmp_path, simple_model):
    b = Bench(tmp_path, simple_model, observer=WIDE)
    b.run(600)
    s = b.rows[-1]["predicted_um"]
    assert b.vm.offset_um == pytest.approx(-s, abs=1e-6)
    box, reply = answer_box()
    b.rt.submit(s + 30.0, 0.5, reply)  # the tool grew 30 um more than the model says
    rows = b.run(40)
    assert box[0]["outcome"] == "accepted" and box[0]["innovation_um"] == pytest.approx(
        30.0, abs=0.2
    )
    assert rows[0]["predicted_um"] > s + 29.0  # the estimate takes the correction at once...
    off = np.array([r["offset_um"] for r in b.rows])
    assert np.all(np.abs(np.diff(off)) <= RATE * 1.0 + 1e-9)  # ...the controller never jumps
    assert rows[0]["offset_um"] == pytest.approx(b.rows[-41]["offset_um"] - RATE)
    assert rows[-1]["offset_um"] == pytest.approx(
        -rows[-1]["predicted_um"], abs=1e-6
    )  # and arrives
    h = b.vm.history()  # what the controller held, every 0.5 s of the plant
    held = h.offset_um[h.time_s >= 590.0]
    assert np.abs(np.diff(held)).max() <= RATE + 1e-9
    b.rt.close()


def test_an_outlier_raises_probe_rejected_and_leaves_the_estimate_unchanged(
    tmp_path, simple_model, caplog
):
    b = Bench(tmp_path, simple_model, observer=WIDE)
    b.run(300)
    b.rt.submit(b.rows[-1]["predicted_um"] + 1.0, 0.5)
    b.run(10)
    bias = b.rt.state.bias_um
    assert bias == pytest.approx(1.0, abs=0.05)
    box, reply = answer_box()
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        b.rt.submit(b.rows[-1]["predicted_um"] + 40.0, 0.5, reply)
        rows = b.run(5)
    assert box[0]["outcome"] == "rejected" and not box[0]["accepted"]
    assert (
        box[0]["innovation_um"] == pytest.approx(40.0, abs=0.2) and box[0]["innovation_sd_um"] < 2.0
    )
    assert b.rt.state.bias_um == bias  # unchanged
    for r in rows:  # the estimate is the model's plus the same bias
        assert r["alarms"] & Alarm.PROBE_REJECTED  # held until a measurement is taken again
    assert rows[-1]["predicted_um"] == pytest.approx(
        b.rt.est.speed_only.elongation_um + bias, abs=1e-12
    )
    (rejected,) = events(caplog, "probe_rejected")
    assert (
        rejected.fields["innovation_um"] == pytest.approx(40.0, abs=0.2)
        and rejected.levelno == logging.WARNING
    )
    b.rt.submit(b.rows[-1]["predicted_um"] + 0.3, 0.5)
    assert not b.run(1)[0]["alarms"] & Alarm.PROBE_REJECTED  # taken: cleared
    # two refusals that agree are a real change (a new tool holder): the bias restarts
    for _ in range(2):
        b.rt.submit(b.rows[-1]["predicted_um"] + 40.0, 0.5)
        b.run(1)
    assert b.rt.state.bias_um == pytest.approx(bias + 40.0, abs=1.0)
    assert [r["outcome"] for r in b.measurements()] == [
        "accepted",
        "rejected",
        "accepted",
        "rejected",
        "restarted",
    ]
    row = b.measurements()[1]
    assert (
        float(row["innovation_um"]) == pytest.approx(40.0, abs=0.2)
        and float(row["innovation_sd_um"]) > 0
    )
    assert row["source"] == "control" and row["sequence"] == ""
    b.rt.close()


class FlakySource(SimAdapter):
    """The virtual machine with a measurement read that fails while ``broken`` is an error."""

    broken: AdapterError | None = None

    def _read_measurement_raw(self):
        if self.broken is not None:
            raise self.broken
        return super()._read_measurement_raw()


def test_a_failing_measurement_source_alarms_and_compensation_goes_on(
    tmp_path, simple_model, caplog
):
    b = Bench(tmp_path, simple_model, adapter_cls=FlakySource)
    b.run(100)
    b.vm.probe_value_um, b.vm.probe_sequence = (
        math.nan,
        b.vm.probe_sequence + 1,
    )  # a probe cycle's NaN
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        rows = b.run(3)
    assert all(r["alarms"] & Alarm.PROBE_FAILED for r in rows)  # held: the value was refused
    assert all(r["written"] for r in rows)  # compensation goes on (still warming up)
    assert len(events(caplog, "probe_failed")) == 1
    assert b.measurements()[-1]["outcome"] == "refused"
    b.vm.start_probe()
    rows = b.run(25)
    assert not rows[-1]["alarms"] & Alarm.PROBE_FAILED and b.rt.counters["probes_accepted"] == 1
    b.vm.override_speed(12000.0)
    for error in (
        AdapterError("sim: measurement variable unreadable"),
        AdapterTimeoutError("sim: the probe's variables do not answer"),
    ):
        b.rt.adapter.broken = error
        rows = b.run(3)
        assert all(r["alarms"] & Alarm.PROBE_FAILED and r["offset_mode"] != "holding" for r in rows)
        assert b.vm.offset_um == rows[-1]["offset_um"]  # written on
        assert not any(r["alarms"] & Alarm.LINK_DOWN for r in rows)  # the speed says the link is up
        b.rt.adapter.broken = None
        assert not b.run(1)[0]["alarms"] & Alarm.PROBE_FAILED  # it reads again
    b.rt.close()


def test_a_stale_observer_says_so_in_the_alarms_the_events_and_the_status(
    tmp_path, simple_model, caplog
):
    b = Bench(tmp_path, simple_model, observer="enabled = true\nstale_after_s = 60.0")
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        rows = b.run(70)
    # a new installation: counted from the start, not stale at once
    assert (
        not rows[58]["alarms"] & Alarm.OBSERVER_STALE and rows[-1]["alarms"] & Alarm.OBSERVER_STALE
    )
    assert rows[-1]["observer"]["stale"] and len(events(caplog, "observer_stale")) == 1
    b.rt.submit(rows[-1]["predicted_um"], 0.5)
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        rows = b.run(62)
    assert (
        not rows[0]["alarms"] & Alarm.OBSERVER_STALE and len(events(caplog, "observer_fresh")) == 1
    )
    assert rows[0]["observer"]["since_measurement_s"] == 0.0
    assert not rows[-2]["alarms"] & Alarm.OBSERVER_STALE  # 60 s: not yet
    assert rows[-1]["alarms"] & Alarm.OBSERVER_STALE and len(events(caplog, "observer_stale")) == 2
    b.rt.close()
    journal = read_run_log(min((tmp_path / "state" / "journal").glob("s1-*.csv")))
    stale = (journal.extras["alarms"].astype(int) & int(Alarm.OBSERVER_STALE)) != 0
    assert stale.sum() == sum(bool(r["alarms"] & Alarm.OBSERVER_STALE) for r in b.rows) == 9 + 1


# -- state, switches, configuration ---------------------------------------------------------


def test_the_observer_state_is_saved_and_restored_through_the_downtime(tmp_path, simple_model):
    b = Bench(tmp_path, simple_model)
    b.run(300)
    b.rt.submit(b.rows[-1]["predicted_um"] + 3.0, 0.5)
    b.run(5)
    bias, sd = b.rt.state.bias_um, b.rt.state.observer.bias_sd_um
    b.rt.close()
    saved = load_state(tmp_path / "state" / "s1.state.json")
    assert saved["observer"]["bias_um"] == bias and saved["observer"]["since_measurement_s"] == 4.0
    b.t += 3600.0  # an hour down
    rt = b.start()
    assert rt.state.bias_um == bias  # a random walk keeps its mean...
    assert rt.state.observer.bias_sd_um > sd  # ...and grows less certain
    assert rt.state.since_measurement_s == pytest.approx(3604.0)
    rt.close()


def test_one_observer_serves_the_model_in_use_and_a_switch_does_not_jump(tmp_path):
    model = tmp_path / "inputs.json"
    save_model(model, with_inputs())
    values = {"temp1_c": 27.0}
    b = Bench(
        tmp_path,
        model,
        adapter_cls=lambda machine: InputSim(machine, values),
        shaping="max_offset_um = 60.0\nmax_rate_um_per_s = 2.0\ndeadband_um = 0.0",
        extra="[spindle.faults]\ninput_stale_s = 86400.0\ninput_recover_s = 5.0",
    )
    b.vm.override_speed(5000.0)
    b.run(200)
    assert b.rt.input_state is not None
    b.rt.submit(b.rows[-1]["predicted_um"] + 4.0, 0.5)  # measured against the model with inputs
    b.run(5)
    fused = b.rows[-1]["predicted_um"]
    assert fused == pytest.approx(b.rt.input_state.elongation_um + b.rt.state.bias_um)
    values["temp1_c"] = math.nan  # the sensor fails: the speed-only fallback takes over
    rows = b.run(10)
    assert rows[0]["alarms"] & Alarm.INPUT_FALLBACK
    steps = np.abs(np.diff([fused] + [r["predicted_um"] for r in rows]))
    assert steps.max() < 0.05  # no jump at the switch (the spindle's own change only)
    values["temp1_c"] = 27.0
    rows = b.run(10)
    assert not rows[-1]["alarms"] & Alarm.INPUT_FALLBACK
    steps = np.abs(np.diff([r["predicted_um"] for r in b.rows[-11:]]))
    assert steps.max() < 0.05
    # saved on the speed-only model's footing: a restart starts from the same estimate
    b.rt.save_state()
    saved = load_state(tmp_path / "state" / "s1.state.json")
    assert saved["elongation_um"] == pytest.approx(b.rows[-1]["predicted_um"], abs=1e-9)
    b.rt.close()


def test_a_reload_carries_the_observer_and_its_waiting_measurements_on(tmp_path, simple_model):
    b = Bench(tmp_path, simple_model)
    b.run(100)
    b.rt.submit(b.rows[-1]["predicted_um"] + 2.0, 0.5)
    b.run(2)
    bias = b.rt.state.bias_um
    box, reply = answer_box()
    b.rt.submit(b.rows[-1]["predicted_um"] + 0.1, 0.5, reply)  # waits for the next cycle
    b.reload(tmp_path, simple_model, observer="enabled = true\ngate_sigma = 4.0")
    assert b.rt.state.bias_um == bias and b.rt.estimate.fused.config.gate_sigma == 4.0
    b.run(1)
    assert box[0]["outcome"] == "accepted"
    b.reload(tmp_path, simple_model, observer="enabled = false")  # the model alone again
    rows = b.run(5)
    assert (
        rows[-1]["predicted_um"] == pytest.approx(b.rt.state.elongation_um)
        and rows[-1]["observer"] is None
    )
    off = np.array([r["offset_um"] for r in b.rows])
    assert np.all(np.abs(np.diff(off)) <= RATE + 1e-9)  # the bias leaves through the slew limit
    b.reload(tmp_path, simple_model)  # and on again: from the prior
    assert b.rt.state.bias_um == 0.0 and b.rt.state.since_measurement_s is None
    b.run(1)
    b.rt.close()
    assert [r["outcome"] for r in b.measurements()] == ["accepted", "accepted"]


def test_observer_settings_are_validated_and_override_the_fitted_ones(tmp_path, simple_model):
    cfg = load_config(EXAMPLES / "closed-loop.toml")
    obs = cfg.spindle[0].observer
    assert obs.enabled and obs.sigma_um == 0.5 and obs.overrides() == {"gate_sigma": 5.0}
    b = Bench(
        tmp_path, simple_model, observer="enabled = true\ngate_sigma = 3.0\nreaccept_after = 0"
    )
    assert (
        b.rt.estimate.fused.config.gate_sigma == 3.0
        and b.rt.estimate.fused.config.reaccept_after == 0
    )
    b.rt.close()
    for bad, match in (
        ("gate_sigma = 0.0", "gate_sigma"),
        ("bogus = 1", "bogus"),
        ("sigma_um = -1", "sigma_um"),
        ("stale_after_s = nan", "stale_after_s"),
    ):
        with pytest.raises(ConfigError, match=match) as exc:
            load_config(config(tmp_path, simple_model, f"enabled = true\n{bad}"))
        assert "\n" not in str(exc.value)
    off = Bench(tmp_path / "off", simple_model, observer="enabled = false")
    assert off.rt.estimate.fused is None
    box, reply = answer_box()
    off.rt.submit(1.0, 0.5, reply)
    assert box[0]["ok"] is False and "observer" in box[0]["error"]
    off.rt.close()


# -- over OPC UA, the virtual CNC's tool setter ------------------------------------------------


def test_the_runtime_takes_the_controllers_probe_once_over_opcua_and_refuses_a_nan(
    tmp_path, simple_model, caplog
):
    t = [0.0]
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=1), None, clock=lambda: t[0])
    vm.override_speed(SPEED)
    cfg = load_config(config(tmp_path, simple_model))
    with running(VirtualCNC(vm)) as cnc:
        link = OpcUaAdapter(cnc.url, preset="virtual-cnc", timeout_s=5.0)
        rt = SpindleRuntime(
            cfg.spindle[0],
            cfg.state_dir,
            cfg.journal_path,
            clock=lambda: t[0],
            wall=lambda: WALL0 + t[0],
            adapter=link,
            journal_fsync_s=cfg.journal_fsync_s,
        )
        try:
            opcua_probe_cycles(cnc, vm, rt, t, caplog)
        finally:
            rt.close()  # and the link: its client thread would outlive the test


def opcua_probe_cycles(
    cnc: VirtualCNC, vm: VirtualMachine, rt: SpindleRuntime, t: list[float], caplog
) -> None:
    from asyncua.sync import Client

    def cycles(n: int) -> list[dict]:
        out = []
        for _ in range(n):
            t[0] += 1.0
            call(cnc, cnc.tick)  # the virtual CNC publishes, then the runtime reads
            out.append(rt.cycle())
        return out

    cycles(120)
    with Client(cnc.url, timeout=10) as c:
        ns = c.get_namespace_index(NAMESPACE_URI)
        setter = c.get_node(f"ns={ns};s={PROBE_METHOD_PATH.rpartition('/')[0]}")
        assert setter.call_method(f"{ns}:Probe") == 1
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        rows = cycles(30)
    (accepted,) = events(caplog, "probe_accepted")
    assert accepted.fields["sequence"] == 1 and accepted.fields["source"] == "opcua"
    assert accepted.fields["measured_um"] == vm.probe_value_um
    assert rt.counters["probes_accepted"] == 1  # once, though read every cycle
    vm.probe_value_um, vm.probe_sequence = math.nan, vm.probe_sequence + 1
    rows = cycles(3)
    assert all(r["alarms"] & Alarm.PROBE_FAILED for r in rows)
    assert not any(r["alarms"] & Alarm.LINK_DOWN for r in rows)
    assert rt.counters["probes_failed"] == 1 and rt.counters["probes_accepted"] == 1
    call(cnc, cnc.tick)  # the virtual CNC takes the last write
    assert vm.offset_um == pytest.approx(rows[-1]["offset_um"])  # still compensating
