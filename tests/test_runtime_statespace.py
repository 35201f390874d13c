"""The runtime with a state-space model (``thermocomp.state-space-model/1``): cold start at
equilibrium, its own state across a restart, the trained-range alarm and the spindle id.
In process, on a fake clock; nothing sleeps."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from compensator import ConfigError
from compensator.io import load_state, read_run_log, save_model
from compensator.statespace import InputChannel, StateSpaceModel
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import VirtualMachine
from thermocomp.runtime import Alarm, Service, SpindleRuntime
from thermocomp.runtime.config import load_config

WALL0 = 1.7e9
SPEED = 5000.0


def speed_only(**kw) -> StateSpaceModel:
    return StateSpaceModel(
        fitted_dt_s=15,
        speed_range_rpm=(0, 10000),
        taus_s=(600.0, 5400.0),
        drive_um=((0.5, 0.05), (2.0, 0.2)),
        feedthrough_um=(0.1, 0.0),
        offset_um=0.0,
        max_measured_um=40.0,
        **kw,
    )


def with_inputs(spindle_id: str = "sp-A") -> StateSpaceModel:
    temp = InputChannel(
        name="temp1_c",
        unit="degC",
        reference=25.0,
        trained_range=(20.0, 30.0),
        valid_range=(10.0, 40.0),
    )
    return StateSpaceModel(
        fitted_dt_s=15,
        speed_range_rpm=(0, 10000),
        taus_s=(600.0, 5400.0),
        drive_um=((0.5, 0.05, 0.2), (2.0, 0.2, 0.3)),
        feedthrough_um=(0.1, 0.0, 0.05),
        offset_um=0.5,
        max_measured_um=40.0,
        inputs=(temp,),
        fallback=speed_only(spindle_id=spindle_id),
        spindle_id=spindle_id,
    )


def write_config(
    tmp_path: Path, model: Path, extra: str = "", adapter: str = 'url = "sim://"'
) -> Path:
    p = tmp_path / "machine.toml"
    p.write_text(
        "\n".join(
            [
                f'state_dir = "{tmp_path / "state"}"',
                "watchdog = false",
                "[[spindle]]",
                'name = "s1"',
                f'model = "{model}"',
                "period_s = 1.0",
                "state_save_every_s = 10.0",
                extra,
                f"adapter = {{{adapter}}}",
                "[spindle.shaping]",
                "max_offset_um = 40.0",
                "max_rate_um_per_s = 2.0",
                "deadband_um = 0.0",
                "[spindle.shaping.transient]",
                "enabled = false",
                # constant test inputs must not go stale
                "[spindle.faults]",
                "input_stale_s = 86400.0",
                "input_recover_s = 5.0",
            ]
        )
        + "\n"
    )
    return p


class InputSim(SimAdapter):
    """The in-process virtual machine, with input values the test sets."""

    def __init__(self, machine: VirtualMachine, values: dict[str, float]):
        super().__init__(machine=machine)
        self.values = values

    def input_channels(self) -> tuple[str, ...]:
        return tuple(self.values)

    def _read_inputs_raw(self) -> dict[str, float]:
        return dict(self.values)


class Bench:
    def __init__(self, tmp_path: Path, model: StateSpaceModel, extra: str = ""):
        self.t = 0.0
        self.model_path = tmp_path / "model.json"
        save_model(self.model_path, model)
        self.cfg = load_config(write_config(tmp_path, self.model_path, extra))
        self.vm = VirtualMachine(
            SpindlePlant(preset("motorized-27k"), seed=1), None, clock=self.clock
        )
        self.vm.override_speed(SPEED)
        self.inputs = {"temp1_c": 27.0}
        self.rt = self.start()

    def clock(self) -> float:
        return self.t

    def wall(self) -> float:
        return WALL0 + self.t

    def start(self) -> SpindleRuntime:
        sc = self.cfg.spindle[0]
        return SpindleRuntime(
            sc,
            self.cfg.state_dir,
            self.cfg.journal_path,
            clock=self.clock,
            wall=self.wall,
            adapter=InputSim(self.vm, self.inputs),
        )

    def run(self, cycles: int) -> list[dict]:
        out = []
        for _ in range(cycles):
            self.t += 1.0
            out.append(self.rt.cycle())
        return out


def events(caplog, name: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if getattr(r, "event", None) == name]


def test_a_cold_start_puts_the_model_with_inputs_at_its_equilibrium(tmp_path):
    b = Bench(tmp_path, with_inputs())
    model = b.rt.estimate.with_inputs
    assert b.rt.alarms & Alarm.COLD_START
    first = b.run(1)[0]
    expected = model.steady_state_um(SPEED, {"temp1_c": 27.0})
    assert expected > 10.0  # far from the 0 um the fallback's cold state would hand on
    assert first["predicted_um"] == pytest.approx(expected, abs=1e-9)
    assert not first["alarms"] & Alarm.INPUT_FALLBACK
    assert b.rt.input_state.residual_um == 0.0  # nothing unexplained: no decay to come
    # the equilibrium holds: an hour later at the same speed and inputs, the same elongation
    last = b.run(3600)[-1]
    assert last["predicted_um"] == pytest.approx(expected, abs=1e-6)
    assert b.rt.est.references is None  # absolute references live in the model, not the state file
    b.rt.close()


def test_a_speed_only_state_space_model_cold_starts_at_its_rest_equilibrium(tmp_path):
    model = speed_only(spindle_id="sp-A").model_copy(update={"offset_um": 1.5})
    b = Bench(tmp_path, model)
    assert b.rt.estimate.with_inputs is None and b.rt.state.elongation_um == pytest.approx(1.5)
    b.rt.close()


def test_the_input_models_state_is_saved_and_restored_through_the_downtime(tmp_path):
    b = Bench(tmp_path, with_inputs())
    model = b.rt.estimate.with_inputs
    for temp in (22.0, 24.0, 28.0):  # move it off equilibrium
        b.inputs["temp1_c"] = temp
        b.run(600)
    b.rt.close()
    saved_input = b.rt.input_state
    body = load_state(b.rt.state_path)
    assert body["input_state"] == model.state_dict(saved_input)
    assert body["input_wall_s"] == pytest.approx(b.wall())
    assert "input_references" not in body
    # ten minutes down; the spindle stood still and the temperature moved to 26
    b.t += 600.0
    b.inputs["temp1_c"] = 26.0
    b.vm.override_speed(0.0)
    b.rt = b.start()
    assert not b.rt.alarms & Alarm.COLD_START
    row = b.run(1)[0]
    expected = model.step(saved_input, 0.0, 601.0, {"temp1_c": 26.0})  # + the first cycle's second
    assert b.rt.input_state == expected
    assert row["predicted_um"] == pytest.approx(expected.elongation_um, abs=1e-9)
    # not what a restart from the fallback's elongation, or at equilibrium, would give
    assert abs(row["predicted_um"] - model.steady_state_um(0.0, {"temp1_c": 26.0})) > 1.0
    b.rt.close()


def test_a_restored_input_state_not_yet_resumed_is_saved_again_as_it_was(tmp_path):
    b = Bench(tmp_path, with_inputs())
    b.run(300)
    b.rt.close()
    before = load_state(b.rt.state_path)
    b.t += 60.0
    b.rt = b.start()
    b.rt.close()  # stopped again before a single cycle
    after = load_state(b.rt.state_path)
    assert after["input_state"] == before["input_state"]
    assert after["input_wall_s"] == before["input_wall_s"]  # its own time, not the second save's
    assert after["saved_wall_s"] > before["saved_wall_s"]


def test_a_corrupt_saved_input_state_means_a_cold_start(tmp_path):
    from compensator.io import save_state

    b = Bench(tmp_path, with_inputs())
    b.run(30)
    b.rt.close()
    body = load_state(b.rt.state_path)
    body["input_state"] = {
        "states_um": [1.0],
        "residual_um": 0.0,
        "static_um": 0.0,
    }  # one state of two
    body.pop("format")
    save_state(b.rt.state_path, body)
    b.rt = b.start()
    assert b.rt.alarms & Alarm.STATE_CORRUPT and b.rt.alarms & Alarm.COLD_START
    b.rt.close()


def test_an_input_outside_the_trained_range_alarms_once_per_entry(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="thermocomp.runtime")
    b = Bench(tmp_path, with_inputs())
    rows = b.run(10)
    assert not any(r["alarms"] & Alarm.INPUTS_EXTRAPOLATED for r in rows)
    b.inputs["temp1_c"] = 35.0  # valid (10..40), but calibration saw 20..30
    rows = b.run(20)
    assert all(r["alarms"] & Alarm.INPUTS_EXTRAPOLATED for r in rows)
    assert not any(r["alarms"] & Alarm.INPUT_FALLBACK for r in rows)  # still the model with inputs
    entered = events(caplog, "inputs_extrapolated")
    assert len(entered) == 1 and "temp1_c" in entered[0].fields["reason"]
    b.inputs["temp1_c"] = 29.0
    rows = b.run(5)
    assert not any(r["alarms"] & Alarm.INPUTS_EXTRAPOLATED for r in rows)
    assert len(events(caplog, "inputs_within_training")) == 1
    b.inputs["temp1_c"] = 19.0  # a second entry: a second event
    assert b.run(1)[0]["alarms"] & Alarm.INPUTS_EXTRAPOLATED
    assert len(events(caplog, "inputs_extrapolated")) == 2
    b.inputs["temp1_c"] = 45.0  # beyond the valid range: a sensor fault, the fallback stands
    row = b.run(1)[0]
    assert row["alarms"] & Alarm.INPUT_FALLBACK and not row["alarms"] & Alarm.INPUTS_EXTRAPOLATED
    b.rt.close()
    journal = read_run_log(min((tmp_path / "state" / "journal").glob("s1-*.csv")))
    assert Alarm.INPUTS_EXTRAPOLATED == 131072
    assert (
        int(((journal.extras["alarms"].astype(int) & 131072) != 0).sum()) == 21
    )  # 20 at 35, 1 at 19


def test_after_an_input_fault_the_model_with_inputs_continues_from_the_fallback(tmp_path):
    b = Bench(tmp_path, with_inputs())
    b.run(100)
    b.inputs["temp1_c"] = float("nan")
    assert b.run(1)[0]["alarms"] & Alarm.INPUT_FALLBACK
    b.inputs["temp1_c"] = 27.0
    rows = b.run(6)  # input_recover_s = 5
    assert (
        rows[3]["alarms"] & Alarm.INPUT_FALLBACK and not rows[-1]["alarms"] & Alarm.INPUT_FALLBACK
    )
    # the fallback's elongation at the switch, not the input model's equilibrium
    assert rows[-1]["predicted_um"] == pytest.approx(b.rt.state.elongation_um, abs=1e-9)
    assert (
        abs(rows[-1]["predicted_um"] - b.rt.estimate.with_inputs.steady_state_um(SPEED, b.inputs))
        > 1.0
    )
    b.rt.close()


def test_inputs_faulty_at_a_cold_start_then_good_continue_from_the_fallback(tmp_path):
    b = Bench(tmp_path, with_inputs())
    b.inputs["temp1_c"] = float("nan")
    assert b.run(1)[0]["alarms"] & Alarm.INPUT_FALLBACK
    b.inputs["temp1_c"] = 27.0
    rows = b.run(6)
    assert not rows[-1]["alarms"] & Alarm.INPUT_FALLBACK
    # the fallback has been running: its estimate is the runtime's own now, not nothing
    assert rows[-1]["predicted_um"] == pytest.approx(b.rt.state.elongation_um, abs=1e-9)
    assert (
        abs(rows[-1]["predicted_um"] - b.rt.estimate.with_inputs.steady_state_um(SPEED, b.inputs))
        > 1.0
    )
    b.rt.close()


def test_a_model_for_another_spindle_is_refused(tmp_path):
    model = tmp_path / "model.json"
    save_model(model, with_inputs("sp-A"))
    cfg = load_config(write_config(tmp_path, model, 'spindle_id = "sp-B"'))
    with pytest.raises(ConfigError) as err:
        SpindleRuntime(
            cfg.spindle[0], cfg.state_dir, cfg.journal_path, clock=lambda: 0.0, wall=lambda: WALL0
        )
    msg = str(err.value)
    assert (
        msg == f"spindle \"s1\": spindle_id = 'sp-B': the model file {model} is for spindle 'sp-A'"
    )
    assert "\n" not in msg
    # a model that names no spindle does not prove it is this one's
    unnamed = tmp_path / "unnamed.json"
    save_model(unnamed, speed_only())
    cfg = load_config(write_config(tmp_path, unnamed, 'spindle_id = "sp-B"'))
    with pytest.raises(
        ConfigError, match="spindle_id = 'sp-B': the model file .* is for spindle 'unknown'"
    ):
        Service(tmp_path / "machine.toml", clock=lambda: 0.0, wall=lambda: WALL0, lock=False)


def test_spindle_id_checked_only_when_configured_and_at_reload(tmp_path, caplog):
    model = tmp_path / "model.json"
    save_model(model, speed_only(spindle_id="sp-A"))
    t = {"now": 0.0}
    path = write_config(tmp_path, model)  # no spindle_id: the name "s1" need not match "sp-A"
    svc = Service(path, clock=lambda: t["now"], wall=lambda: WALL0 + t["now"], lock=False)
    write_config(tmp_path, model, 'spindle_id = "sp-A"')
    svc.request_reload()
    t["now"] += 1.0
    svc.tick()
    assert not svc.reload_failed and svc.cfg.spindle[0].spindle_id == "sp-A"
    write_config(tmp_path, model, 'spindle_id = "sp-B"')
    svc.request_reload()
    t["now"] += 1.0
    svc.tick()
    assert svc.reload_failed and svc.spindles["s1"].alarms & Alarm.RELOAD_FAILED
    refused = [r for r in caplog.records if getattr(r, "event", None) == "reload_refused"]
    assert len(refused) == 1 and "spindle_id = 'sp-B': the model file" in refused[0].fields["error"]
    assert svc.cfg.spindle[0].spindle_id == "sp-A"  # the running configuration stays
    svc.close()


def test_spindle_id_in_the_configuration_is_validated(tmp_path):
    model = tmp_path / "model.json"
    save_model(model, speed_only())
    with pytest.raises(ConfigError, match="spindle_id"):
        load_config(write_config(tmp_path, model, 'spindle_id = ""'))
