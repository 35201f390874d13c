"""A spindle that keeps learning (``thermocomp refit``, ``model history``, ``model rollback``): the
service runs a job shop on the virtual machine tool with a tool-setter cycle every 30 min, in
lock-step on a fake clock; the refit reads its journal like any shop's. A poor model is replaced by
a better one; a good one is kept when the measurements it would learn from came from a faulty
setter, or when there are too few; a rollback goes back through the slew limit, the state carried
over."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from plantdata import identify_runs, plant_run
from test_closed_loop import Bench, simple_model  # noqa: F401 - the model file fixture

from calibration.learning import Rule, Score, decide
from calibration.nc_programs import with_probe_stops
from compensator.io import load_any_model, model_digest, read_run_log, save_model
from compensator.io.history import ModelHistory
from compensator.speed_programs import job_shop_day
from machine_sim import SpindlePlant, preset
from machine_sim.vcnc import ToolSetter, VirtualMachine
from thermocomp.cli import main as cli
from thermocomp.runtime.lock import holder

P = preset("motorized-27k")
PERIOD_S = 30.0
PROBE_EVERY_S = 1800.0
OBSERVER = "enabled = true\ngate_sigma = 1000.0"  # every measurement fused: the refit judges them
RULE = (
    "[spindle.learning]\nmin_train = 16\nmin_holdout = 6\nshadow_min = 12"  # 12 h: 24 measurements
)
AT_ONCE = "shadow_h = 0"  # promoted on the held-out judgement alone
KW = {
    "period_s": PERIOD_S,
    "observer": OBSERVER,
    "shaping": "max_offset_um = 80.0\nmax_rate_um_per_s = 2.0\ndeadband_um = 0.0",
}


def shop(
    tmp_path: Path,
    model: Path,
    hours: float,
    *,
    seed: int = 3,
    setter_bias_um=None,
    extra: str = "",
    at_speed: bool = True,
    kw: dict | None = None,
) -> Bench:
    """``hours`` of a job shop on the plant, the service compensating and journaling; the tool
    setter (a laser at the program's speed, or ``at_speed=False`` a contact one at rest) measures
    every 30 min (``setter_bias_um(t_s, machine)`` added to what it reads: a faulty one)."""
    prog = with_probe_stops(job_shop_day(P.max_rpm, seed=seed, hours=hours), PROBE_EVERY_S)

    def make_vm(clock):
        vm = VirtualMachine(
            SpindlePlant(P, seed=seed),
            prog,
            clock=clock,
            plant_dt_s=2.0,
            tool_setter=ToolSetter(dwell_s=60.0, noise_um=0.3, seed=seed, at_speed=at_speed),
        )
        if setter_bias_um is not None:
            finish = vm._finish_probe

            def biased() -> None:
                finish()
                vm.probe_value_um += setter_bias_um(vm.plant.time_s, vm)

            vm._finish_probe = biased
        return vm

    b = Bench(tmp_path, model, make_vm=make_vm, **(kw or KW), extra=RULE + "\n" + extra)
    while not b.vm.program_done:
        b.run(int(3600 / PERIOD_S))
    b.rt.journal.flush(b.t)
    b.rt.measurements.flush(b.t)
    return b


@pytest.fixture(scope="module")
def good_model(tmp_path_factory) -> Path:
    """The wizard's model of this plant: fitted on its calibration and validation runs."""
    fit = identify_runs(
        [plant_run("calibration", 20.0, 1), plant_run("validation", 20.0, 2)], spindle_id="s1"
    )
    p = tmp_path_factory.mktemp("good") / "model.json"
    save_model(p, fit.model)
    return p


def own_copy(model: Path, tmp_path: Path) -> Path:
    p = tmp_path / "model.json"
    shutil.copy(model, p)
    return p


def refit(b: Bench, capsys, *extra: str) -> dict:
    capsys.readouterr()
    assert cli(["refit", "--config", str(b.cfg_path), "--json", *extra]) == 0
    return json.loads(capsys.readouterr().out)


# -- the rule ----------------------------------------------------------------------------------


def test_the_promotion_rule_holds_back_unless_better_by_the_margin():
    rule = Rule(margin=0.10, observer_tolerance=0.05)
    live = Score(2.0, 1.0, 5.0)
    assert decide(rule, live, Score(1.7, 0.9, 4.0)).promote
    assert not decide(rule, live, Score(1.85, 0.9, 4.0)).promote  # better, by less than the margin
    worse_closed = decide(rule, live, Score(1.5, 1.1, 4.0))
    assert not worse_closed.promote and "observer" in worse_closed.reason
    assert decide(rule, Score(2.0, None, 5.0), Score(1.5, None, 3.0)).promote
    assert rule.holdout(20) == 8 and rule.holdout(100) == 25


# -- production --------------------------------------------------------------------------------


def test_a_poor_model_is_replaced_from_production_and_can_be_rolled_back(
    tmp_path, simple_model, capsys
):
    """The live model (2 um per krpm, tau 100 s) is far from the plant: a day of production with a
    measurement every 30 min gives a candidate that misses less on the newest measurements, open
    loop and with the observer; it is promoted. Rolled back during the run, the offset walks back
    at the slew limit and the estimate does not jump."""
    model = own_copy(simple_model, tmp_path)
    b = shop(tmp_path, model, hours=12, extra=AT_ONCE)
    b.cfg_path = tmp_path / "machine.toml"
    old = load_any_model(model)
    old_digest = model_digest(old)
    out = refit(b, capsys)
    assert out["outcome"] == "promoted", out
    assert out["measurements"] >= 22 and out["holdout"] >= 6
    assert out["candidate"]["open_loop_rms_um"] < 0.9 * out["live"]["open_loop_rms_um"]
    assert isinstance(out["live_model"], str) and out["live_model"]  # named beside its figures
    new = load_any_model(model)
    assert (
        model_digest(new) != old_digest and new.spindle_id == old.spindle_id
    )  # the same spindle's
    history = ModelHistory.of(b.cfg.state_dir, "s1")
    events = [r.event for r in history.records()]
    assert events == ["in_use", "promoted"]
    assert history.live().digest == model_digest(new)
    assert "no service runs" in out["written"]  # this rig holds no lock: the next start takes it
    # the service takes it (what SIGHUP does), from the old estimate
    before = b.rt.estimate_um()
    b.reload(tmp_path, model, **KW, extra=RULE + "\n" + AT_ONCE)
    assert b.rt.digest == model_digest(new) and abs(b.rt.estimate_um() - before) < 1e-9
    # rollback during the run, while the spindle turns
    b.vm.override_speed(15000.0)
    b.run(60)
    capsys.readouterr()
    assert cli(["model", "rollback", "--config", str(b.cfg_path), "--reason", "test"]) == 0
    said = capsys.readouterr().out
    assert f"rolled back to {old_digest[:16]}" in said
    assert model_digest(load_any_model(model)) == old_digest
    held_before = b.rt.offset.held_um
    est_before = b.rt.estimate_um()
    b.reload(tmp_path, model, **KW, extra=RULE + "\n" + AT_ONCE)
    assert abs(b.rt.estimate_um() - est_before) < 1e-9  # the state carried over
    rows = b.run(120)
    held = np.array([held_before] + [r["offset_um"] for r in rows])
    assert (
        np.max(np.abs(np.diff(held))) <= 2.0 * PERIOD_S + 1e-9
    )  # never faster than the slew limit
    records = ModelHistory.of(b.cfg.state_dir, "s1").records()
    assert [r.event for r in records] == ["in_use", "promoted", "rollback"] and records[
        -1
    ].reason == "test"
    capsys.readouterr()
    assert cli(["model", "history", "--config", str(b.cfg_path)]) == 0
    listing = capsys.readouterr().out
    assert listing.count("\n") == 4 and "* " in listing and "rollback" in listing


def test_a_candidate_from_a_faulty_setter_is_rejected_and_the_live_model_untouched(
    tmp_path, good_model, capsys
):
    """A chip on the tool setter for the first 8 h reads 4 um too much; it is cleaned for the
    last hours, whose measurements judge. The candidate learned the chip: it misses more than the
    live model there, and is rejected; the model file is the same to the byte."""
    model = own_copy(good_model, tmp_path)
    first = model.read_bytes()
    b = shop(
        tmp_path,
        model,
        hours=12,
        setter_bias_um=lambda t, _vm: 4.0 if t < 8 * 3600 else 0.0,
        extra=AT_ONCE,
    )
    b.cfg_path = tmp_path / "machine.toml"
    out = refit(b, capsys)
    assert out["outcome"] == "rejected", out
    assert out["candidate"]["open_loop_rms_um"] > out["live"]["open_loop_rms_um"]
    assert model.read_bytes() == first
    records = ModelHistory.of(b.cfg.state_dir, "s1").records()
    assert [r.event for r in records] == ["in_use", "rejected"]
    assert (
        records[-1].reason
        and ModelHistory.of(b.cfg.state_dir, "s1").live().digest == records[0].digest
    )


def test_a_candidate_runs_in_shadow_before_it_is_promoted(tmp_path, simple_model, capsys):
    """With ``shadow_h``, a candidate the rule accepts first runs beside the live model: stepped
    every cycle and journaled, never written to the controller. The next refit holds it while it
    has run too short, then promotes it on its own misses at the measurements taken meanwhile."""
    model = own_copy(simple_model, tmp_path)
    first = model.read_bytes()
    learning = "shadow_h = 6.0"
    # the observer free to follow the poor model's misses: a promotion starts at the live
    # estimate, and this keeps it near the spindle
    kw = {**KW, "observer": OBSERVER + "\nmax_correction_um = 200.0\nmax_source_move_um = 200.0"}
    b = shop(tmp_path, model, hours=12, extra=learning, kw=kw)
    b.cfg_path = tmp_path / "machine.toml"
    out = refit(b, capsys)
    assert out["outcome"] == "shadow", out
    assert model.read_bytes() == first  # the live model is untouched
    history = ModelHistory.of(b.cfg.state_dir, "s1")
    assert history.shadow_path.is_file() and history.shadow() is not None
    # the service takes it in shadow (what SIGHUP does)
    b.reload(tmp_path, model, **kw, extra=RULE + "\n" + learning)
    assert b.rt.shadow is not None and b.rt.digest == model_digest(load_any_model(model))
    b.vm.load_program(with_probe_stops(job_shop_day(P.max_rpm, seed=4, hours=3), PROBE_EVERY_S))
    rows = b.run(int(3 * 3600 / PERIOD_S))
    # never written: the offset follows the live estimate, the shadow's is journaled beside it
    b.rt.journal.flush(b.t)
    b.rt.measurements.flush(b.t)
    part = read_run_log(b.rt.journal.path)
    shadow = part.extras["shadow_um"]
    live, held = part.extras["predicted_um"], part.extras["offset_um"]
    assert np.isfinite(shadow).all() and np.sqrt(np.mean((shadow - live) ** 2)) > 1.0  # two models
    assert np.median(np.abs(held + live)) < 0.5 < np.median(np.abs(held + shadow))
    assert rows[-1]["shadow"]["digest"] == history.shadow().digest
    held = refit(b, capsys)
    assert held["outcome"] == "held back" and "of 6 h" in held["reason"], held
    b.vm.load_program(with_probe_stops(job_shop_day(P.max_rpm, seed=5, hours=8), PROBE_EVERY_S))
    while not b.vm.program_done:
        b.run(int(3600 / PERIOD_S))
    b.rt.journal.flush(b.t)
    b.rt.measurements.flush(b.t)
    done = refit(b, capsys)
    judged = done.get("shadow_judged", done)
    assert judged["outcome"] == "promoted" and judged["reason"].startswith("in shadow:"), judged
    # judged as the service runs it: with the observer, beyond the measurements' noise
    assert judged["candidate"]["observer_rms_um"] < 0.9 * judged["live"]["observer_rms_um"]
    assert judged["paired_t"] <= -2.0 and judged["measurements"] >= 12
    assert model.read_bytes() != first
    assert model_digest(load_any_model(model)).startswith(judged["shadow"])
    records = history.records()
    assert [r.event for r in records][:3] == ["in_use", "shadow", "promoted"]
    assert history.live().digest == records[2].digest
    # then a new candidate, fitted on the newest journal, is judged against the promoted model
    assert [r.event for r in records[3:]] in ([], ["shadow"], ["rejected"]), records


def test_measurements_at_rest_cannot_take_away_the_growth_at_speed(tmp_path, simple_model, capsys):
    """A contact setter measures at rest: a candidate fitted on that misses less at rest than the
    poor live model, but nothing there vouches for the growth while the spindle turns, and the
    candidate changes it: it is rejected for that, and the live model stays."""
    model = own_copy(simple_model, tmp_path)
    first = model.read_bytes()
    b = shop(tmp_path, model, hours=12, at_speed=False, extra=AT_ONCE)
    b.cfg_path = tmp_path / "machine.toml"
    out = refit(b, capsys)
    assert out["outcome"] == "rejected" and "taken at rest" in out["reason"], out
    assert (
        out["candidate"]["open_loop_rms_um"] < 0.9 * out["live"]["open_loop_rms_um"]
    )  # better at rest
    assert model.read_bytes() == first


def test_too_few_measurements_hold_the_refit_back(tmp_path, simple_model, capsys):
    model = own_copy(simple_model, tmp_path)
    b = shop(tmp_path, model, hours=4)  # 8 measurements: fewer than 16 + 6
    b.cfg_path = tmp_path / "machine.toml"
    first = model.read_bytes()
    out = refit(b, capsys)
    assert out["outcome"] == "held back" and "nothing fitted" in out["reason"], out
    assert model.read_bytes() == first
    assert [r.event for r in ModelHistory.of(b.cfg.state_dir, "s1").records()] == ["in_use"]


def test_measurements_taken_during_a_fault_are_left_out(tmp_path):
    from calibration.learning import usable_measurements
    from compensator.io import RunLog

    t = np.arange(6.0)
    log = RunLog(
        t,
        np.zeros(6),
        np.array([1.0, np.nan, 2.0, 3.0, np.nan, 4.0]),
        extras={"alarms": np.array([0, 0, 8, 0, 64, 1 << 20], dtype=float)},
    )
    rows, faulted = usable_measurements(log)
    # LINK_DOWN on row 2 leaves its measurement out; PROBE_FAILED (row 5) is no fault of the row
    assert rows.tolist() == [True, False, False, True, False, True] and faulted == 1


def test_the_fault_bits_are_the_runtimes_alarms():
    from compensator.io.journal import FAULT_ALARM_BITS
    from thermocomp.runtime import Alarm

    assert all(int(Alarm[name]) == bit for name, bit in FAULT_ALARM_BITS.items())


def test_holder_sees_a_running_service(tmp_path):
    import os

    from thermocomp.runtime.lock import StateDirLock

    assert holder(tmp_path) == (False, None)
    with StateDirLock(tmp_path):
        assert holder(tmp_path) == (True, os.getpid())
    assert holder(tmp_path) == (False, None)


def test_a_candidate_better_on_the_held_out_past_but_worse_in_shadow_is_not_promoted(
    tmp_path, simple_model, capsys
):
    """The poor live model is beaten on the held-out measurements of a day's first 12 h, open
    loop and with the observer, so a candidate goes into shadow. Then the spindle comes to
    behave as the live model says (the tool setter reads the live estimate, with its noise): in
    shadow, run as the service runs it, the candidate misses those measurements more than the
    live model does, and it is rejected; the model file is the same to the byte."""
    model = own_copy(simple_model, tmp_path)
    first = model.read_bytes()
    learning = "shadow_h = 4.0"
    changed: list = []  # the bench, once the spindle behaves as the live model says

    def as_the_live_model_says(_t: float, vm) -> float:
        return changed[0].rt.estimate_um() - vm.plant.true_elongation_um() if changed else 0.0

    b = shop(tmp_path, model, hours=12, extra=learning, setter_bias_um=as_the_live_model_says)
    b.cfg_path = tmp_path / "machine.toml"
    out = refit(b, capsys)
    assert out["outcome"] == "shadow", out  # judged better on the held-out past
    assert out["candidate"]["observer_rms_um"] < out["live"]["observer_rms_um"]
    b.reload(tmp_path, model, **KW, extra=RULE + "\n" + learning)
    assert b.rt.shadow is not None
    changed.append(b)
    b.vm.load_program(with_probe_stops(job_shop_day(P.max_rpm, seed=6, hours=8), PROBE_EVERY_S))
    while not b.vm.program_done:
        b.run(int(3600 / PERIOD_S))
    b.rt.journal.flush(b.t)
    b.rt.measurements.flush(b.t)
    done = refit(b, capsys)
    judged = done.get("shadow_judged", done)
    assert judged["outcome"] == "rejected" and judged["reason"].startswith("in shadow:"), judged
    assert judged["candidate"]["observer_rms_um"] > judged["live"]["observer_rms_um"]
    assert judged["measurements"] >= 12
    assert model.read_bytes() == first
    events = [r.event for r in ModelHistory.of(b.cfg.state_dir, "s1").records()]
    assert events[:3] == ["in_use", "shadow", "rejected"], events
