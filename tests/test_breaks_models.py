"""Breaks a fault run found in the model commands and the model files, each with the test that
shows it fixed: a rollback of a model file two spindles share, a history that recorded a
rollback whose write failed, a calibrated range or sample period no calibration produces, and
a gain x 1e300 under a valid checksum.

The service runs in lock-step on a clock the test moves, on the virtual machine tool's adapter;
the commands run through the command line's ``main``, or as a process where what it prints on
its own (numpy's warnings) or the user it runs as matters.
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from compensator.inputs import AugmentedModel, InputTerm
from compensator.io import load_any_model, model_digest, save_model
from compensator.io.checksum import digest
from compensator.io.history import ModelHistory
from compensator.model import ThermalModel
from compensator.statespace import StateSpaceModel
from thermocomp.cli import main
from thermocomp.runtime import Alarm, Service

ROOT = Path(__file__).resolve().parent.parent
WALL0 = 1_772_438_400.0  # 2026-03-02 08:00 UTC


def old_model() -> ThermalModel:
    # tau 100 s, 2 um per 1000 rpm at steady state
    return ThermalModel.from_discrete(
        0.99, (0.0, 0.02, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 27000.0)
    )


def new_model() -> ThermalModel:
    # what a refit promoted: 3 um per 1000 rpm
    return ThermalModel.from_discrete(
        0.99, (0.0, 0.03, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 27000.0)
    )


def resealed(path: Path, edit: Callable[[dict[str, Any]], None]) -> None:
    """Edit a model file's content and give it a valid checksum again: a file signed after the
    edit, so that only the model's own checks can refuse it."""
    payload = json.loads(path.read_text())
    payload.pop("sha256")
    edit(payload)
    payload["sha256"] = digest(payload)
    path.write_text(json.dumps(payload))


def write_config(directory: Path, models: dict[str, Path], state_dir: Path | None = None) -> Path:
    """One ``[[spindle]]`` per name, each on its own virtual machine tool."""
    lines = [
        f'state_dir = "{state_dir or directory / "state"}"',
        "watchdog = false",
        "journal_fsync_s = 3600.0",
    ]
    for name, model in models.items():
        lines += [
            "[[spindle]]",
            f'name = "{name}"',
            f'model = "{model}"',
            "period_s = 1.0",
            'adapter = {url = "sim://"}',
        ]
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "machine.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def promoted_history(state_dir: Path, spindle: str, live: Path, scratch: Path) -> ModelHistory:
    """A spindle's history as a refit leaves it: the old model in use, then ``live`` promoted."""
    history = ModelHistory.of(state_dir, spindle)
    old = scratch / f"old-{spindle}.json"
    save_model(old, old_model())
    history.add("in_use", old, reason="the service started with it", at_wall_s=WALL0 - 7200.0)
    history.add("promoted", live, reason="a refit", at_wall_s=WALL0 - 3600.0)
    return history


def run(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t

    def wall(self) -> float:
        return WALL0 + self.t


def service(cfg: Path, clock: Clock) -> Service:
    # no lock: a rollback then finds no service to signal (it would SIGHUP this very process)
    return Service(cfg, clock=clock, wall=clock.wall, lock=False)


def reload(svc: Service, clock: Clock) -> None:
    """What SIGHUP does, in lock-step."""
    svc.request_reload()
    clock.t += 1.0
    svc.tick()


# -- shared model files ----------------------------------------------------------------------


@pytest.mark.parametrize("b_reads", ["the same path", "a link to it"])
def test_a_rollback_of_a_model_file_another_spindle_reads_is_refused_and_changes_neither(
    tmp_path, capsys, b_reads
):
    """Spindles a and b read one file. Rolling a back would rewrite it and b would take a's old
    model at its next reload, with nothing in b's history but "a reload found it": refused in
    one line, before anything is written or recorded; b runs the model it ran."""
    shared = tmp_path / "models" / "spindle.json"
    save_model(shared, new_model())
    b_model = shared
    if b_reads == "a link to it":
        b_model = tmp_path / "models" / "b.json"
        b_model.symlink_to(shared)
    cfg = write_config(tmp_path, {"a": shared, "b": b_model})
    state = tmp_path / "state"
    history = promoted_history(state, "a", shared, tmp_path)
    before = shared.read_bytes()
    clock = Clock()
    svc = service(cfg, clock)
    try:
        clock.t += 1.0
        svc.tick()
        b_digest = svc.spindles["b"].digest
        assert b_digest == model_digest(new_model())
        records_a = history.records()
        records_b = ModelHistory.of(state, "b").records()

        code, out, err = run(capsys, "model", "rollback", "--config", cfg, "--spindle", "a")
        assert code == 2 and out == "" and err.count("\n") == 1, (code, out, err)
        assert "also spindle b's" in err and "its own copy" in err

        assert shared.read_bytes() == before  # nothing written
        assert history.records() == records_a  # nothing recorded
        reload(svc, clock)
        assert not svc.reload_failed
        assert svc.spindles["b"].digest == b_digest  # b's model did not change
        assert svc.spindles["a"].digest == b_digest
        assert ModelHistory.of(state, "b").records() == records_b
        # a refit that may promote into the file is refused the same way, before any fit
        code, out, err = run(capsys, "refit", "--config", cfg, "--spindle", "a")
        assert code == 2 and "also spindle b's" in err and err.count("\n") == 1
        assert history.records() == records_a and shared.read_bytes() == before
    finally:
        svc.close()


@pytest.mark.parametrize("a_reads", ["its own copy", "a link to b's file"])
def test_a_rollback_that_leaves_the_other_spindle_alone_goes_ahead(tmp_path, capsys, a_reads):
    """The refusal is only for a file another spindle reads: with its own copy, or a link of its
    own (the write replaces the link, not the file behind it), a rolls back and b's file stays."""
    models = tmp_path / "models"
    b_model = models / "b.json"
    save_model(b_model, new_model())
    a_model = models / "a.json"
    if a_reads == "its own copy":
        shutil.copy(b_model, a_model)
    else:
        a_model.symlink_to(b_model)
    cfg = write_config(tmp_path, {"a": a_model, "b": b_model})
    history = promoted_history(tmp_path / "state", "a", a_model, tmp_path)
    b_before = b_model.read_bytes()
    code, out, err = run(capsys, "model", "rollback", "--config", cfg, "--spindle", "a")
    assert code == 0 and err == "" and out.startswith("a: rolled back to "), (code, out, err)
    assert model_digest(load_any_model(a_model)) == model_digest(old_model())
    assert b_model.read_bytes() == b_before
    assert [r.event for r in history.records()] == ["in_use", "promoted", "rollback"]


# -- the history records only what took effect -----------------------------------------------


PR_CAPBSET_DROP, CAP_DAC_OVERRIDE = 24, 1


def without_dac_override() -> None:
    """In the child before it runs thermocomp: root without the capability that writes past
    permission bits (a read-only directory is read-only to it then, as to any service user)."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_CAPBSET_DROP, CAP_DAC_OVERRIDE, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


def thermocomp(*argv: object, read_only_holds: bool = False) -> subprocess.CompletedProcess[str]:
    """``thermocomp ARGV`` in a process of its own (what it prints on its own is seen, and it
    configures no logging here); ``read_only_holds``: a read-only directory holds against it
    even when the tests run as root."""
    return subprocess.run(
        [sys.executable, "-m", "thermocomp", *map(str, argv)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        check=False,
        preexec_fn=without_dac_override if read_only_holds and os.geteuid() == 0 else None,
    )


def test_a_rollback_whose_model_write_fails_records_nothing(tmp_path):
    """The model file's directory is read-only: the rollback exits 2 in one line, the file and
    the history are as they were (the history does not end with a rollback that did not take
    effect). Writable again, the same rollback goes ahead and is recorded."""
    models = tmp_path / "models"
    live = models / "model.json"
    save_model(live, new_model())
    cfg = write_config(tmp_path, {"s1": live})
    history = promoted_history(tmp_path / "state", "s1", live, tmp_path)
    records = history.records()
    before = live.read_bytes()
    models.chmod(0o555)

    done = thermocomp("model", "rollback", "--config", cfg, read_only_holds=True)
    assert [r.event for r in history.records()] == ["in_use", "promoted"], done.stderr
    assert history.records() == records and live.read_bytes() == before
    assert done.returncode == 2 and done.stdout == "", done
    assert done.stderr.count("\n") == 1 and "cannot write" in done.stderr, done.stderr

    models.chmod(0o755)
    done = thermocomp("model", "rollback", "--config", cfg, read_only_holds=True)
    assert done.returncode == 0 and done.stderr == "", done
    after = history.records()
    assert [r.event for r in after] == ["in_use", "promoted", "rollback"]
    assert after[-1].digest == model_digest(load_any_model(live)) == model_digest(old_model())


# -- a calibrated range or sample period no calibration produces -------------------------------


def speed_only_state_space() -> StateSpaceModel:
    return StateSpaceModel(
        fitted_dt_s=15.0,
        speed_range_rpm=(0.0, 10000.0),
        taus_s=(600.0, 5400.0),
        drive_um=((0.5, 0.05), (2.0, 0.2)),
        feedthrough_um=(0.1, 0.0),
        max_measured_um=40.0,
    )


DEGENERATE = {
    "a top speed of 1e-9 rpm": (
        old_model,
        lambda d: d.update(speed_range_rpm=[0.0, 1e-9]),
        "speed_range_rpm tops at 1e-09 rpm",
    ),
    "a zero top speed": (
        old_model,
        lambda d: d.update(speed_range_rpm=[0.0, 0.0]),
        "speed_range_rpm tops at 0 rpm",
    ),
    "a sample period of 1e-300 s": (
        old_model,
        lambda d: d.update(fitted_dt_s=1e-300),
        "fitted_dt_s 1e-300 s is no calibration's sample period",
    ),
    "a state-space model's 1e-300 s": (
        speed_only_state_space,
        lambda d: d.update(fitted_dt_s=1e-300),
        "fitted_dt_s 1e-300 s is no calibration's sample period",
    ),
}


@pytest.mark.parametrize("make, edit, reason", DEGENERATE.values(), ids=DEGENERATE.keys())
def test_a_signed_model_with_a_range_no_calibration_produces_is_refused(
    tmp_path, capsys, caplog, make, edit, reason
):
    """``model check`` refuses it in one line; a reload refuses it and the spindle runs on with
    the model it had (which counted every real speed as impossible before: compensation off)."""
    bad = tmp_path / "bad.json"
    save_model(bad, make())
    resealed(bad, edit)
    code, out, err = run(capsys, "model", "check", bad)
    assert code == 2 and out == "" and err.count("\n") == 1, (code, out, err)
    assert err.startswith(f"thermocomp: error: {bad}: invalid model: ") and reason in err

    live = tmp_path / "model.json"
    save_model(live, old_model())
    clock = Clock()
    svc = service(write_config(tmp_path, {"s1": live}), clock)
    try:
        clock.t += 1.0
        svc.tick()
        running = svc.spindles["s1"].digest
        shutil.copy(bad, live)
        with caplog.at_level(logging.WARNING):
            reload(svc, clock)
        assert svc.reload_failed and svc.spindles["s1"].alarms & Alarm.RELOAD_FAILED
        assert svc.spindles["s1"].digest == running  # the running model kept
        refused = [r for r in caplog.records if getattr(r, "event", None) == "reload_refused"]
        assert len(refused) == 1 and reason in refused[0].fields["error"]
        cycles = svc.spindles["s1"].counters["cycles"]
        clock.t += 1.0
        svc.tick()
        assert svc.spindles["s1"].counters["cycles"] == cycles + 1  # compensating on
    finally:
        svc.close()


# -- a gain x 1e300 under a valid checksum ------------------------------------------------------


def times_1e300(path: Path) -> None:
    def edit(d: dict[str, Any]) -> None:
        d["states"][0]["generation_um_per_s"][1] *= 1e300

    resealed(path, edit)


@pytest.fixture
def huge_gain(tmp_path: Path) -> Path:
    p = tmp_path / "huge.json"
    save_model(p, old_model())
    times_1e300(p)
    return p


@pytest.fixture
def speed_log(tmp_path: Path) -> Path:
    """An hour of a spindle at 12 000 and 3 000 rpm in turn, with its measured growth and the
    hall's temperature (the input a model with inputs reads)."""
    p = tmp_path / "run.csv"
    rows = ["time_s,speed_rpm,elongation_um,amb_c"]
    for k in range(360):
        t = 10.0 * k
        speed = 12000.0 if (k // 60) % 2 == 0 else 3000.0
        rows.append(f"{t:g},{speed},{5.0 + t / 1000.0:.3f},{24.0 + t / 1800.0:.3f}")
    p.write_text("\n".join(rows) + "\n")
    return p


@pytest.mark.parametrize("as_json", [False, True], ids=["table", "json"])
def test_replay_refuses_a_gain_times_1e300_in_one_line(tmp_path, huge_gain, speed_log, as_json):
    """Before: two numpy overflow warnings and an internal error (or a table of 1e300 um).
    Now the model's own check refuses it at load, where every command loads a model."""
    done = thermocomp("replay", "--model", huge_gain, speed_log, *(["--json"] if as_json else []))
    assert done.returncode == 2 and done.stdout == "", done
    assert done.stderr.count("\n") == 1 and "Warning" not in done.stderr, done.stderr
    assert done.stderr.startswith(f"thermocomp: error: {huge_gain}: invalid model: state 1 holds ")
    assert "beyond 1e+06 um" in done.stderr


def augmented_model() -> AugmentedModel:
    term = InputTerm(
        name="amb_c",
        unit="degC",
        reference=25.0,
        gain_um_per_unit=0.5,
        tau_s=600.0,
        valid_range=(10.0, 40.0),
    )
    return AugmentedModel(speed_model=old_model(), inputs=(term,), fallback=old_model())


def _gains_and_measured(d: dict[str, Any]) -> None:
    # the state-space form's gains are held to 10 x the growth measured: both x 1e300
    d["drive_um"][0][0] *= 1e300
    d["max_measured_um"] *= 1e300


OTHER_FORMS = {
    "state space": (
        speed_only_state_space,
        _gains_and_measured,
        "max_measured_um 4e+301 um is more than any calibration measures",
    ),
    "augmented": (
        augmented_model,
        lambda d: d["inputs"][0].update(gain_um_per_unit=0.5e300),
        "input amb_c: its gain 5e+299 um per degC moves the elongation",
    ),
    "augmented's speed part": (
        augmented_model,
        lambda d: d["speed_model"]["states"][0]["generation_um_per_s"].__setitem__(1, 2e298),
        "state 1 holds",
    ),
}


@pytest.mark.parametrize("make, edit, reason", OTHER_FORMS.values(), ids=OTHER_FORMS.keys())
def test_every_form_refuses_a_gain_times_1e300_at_load(tmp_path, speed_log, make, edit, reason):
    """The same for the other forms: each form's gains held to what a calibration measures, so
    no form can carry a gain whose arithmetic overflows."""
    bad = tmp_path / "bad.json"
    save_model(bad, make())
    resealed(bad, edit)
    done = thermocomp("replay", "--model", bad, speed_log, "--json")
    assert done.returncode == 2 and done.stdout == "", done
    assert done.stderr.count("\n") == 1 and "Warning" not in done.stderr, done.stderr
    assert (
        done.stderr.startswith(f"thermocomp: error: {bad}: invalid model: ")
        and reason in done.stderr
    )


def test_the_service_refuses_a_gain_times_1e300_at_start_and_at_a_reload(
    tmp_path, caplog, huge_gain
):
    """The service refused it before too (its own plausibility check); now the model file's
    check does, the same words as replay and ``model check``: one line, exit 2 at a start; the
    running model kept at a reload."""
    started = thermocomp("run", "--config", write_config(tmp_path / "start", {"s1": huge_gain}))
    checked = thermocomp("model", "check", huge_gain)
    for done in (started, checked):
        assert done.returncode == 2 and done.stderr.count("\n") == 1, done
        assert "invalid model: state 1 holds" in done.stderr and "Warning" not in done.stderr

    live = tmp_path / "model.json"
    save_model(live, old_model())
    clock = Clock()
    svc = service(write_config(tmp_path, {"s1": live}), clock)
    try:
        clock.t += 1.0
        svc.tick()
        running = svc.spindles["s1"].digest
        shutil.copy(huge_gain, live)
        with caplog.at_level(logging.WARNING):
            reload(svc, clock)
        assert svc.reload_failed and svc.spindles["s1"].digest == running
        refused = [r for r in caplog.records if getattr(r, "event", None) == "reload_refused"]
        assert len(refused) == 1 and "state 1 holds" in refused[0].fields["error"]
    finally:
        svc.close()


# -- a calibrated range that is a sliver of the spindle's ------------------------------------


def ten_rpm_model() -> ThermalModel:
    # a range MIN_TOP_RPM lets through: on a 24 000 rpm spindle every real speed is clamped to it
    return ThermalModel.from_discrete(0.99, (0.0, 0.02, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 10.0))


def part_range_model() -> ThermalModel:
    # calibrated on the quarter of the range the shop runs: normal, taken
    return ThermalModel.from_discrete(
        0.99, (0.0, 0.02, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 6000.0)
    )


def with_max_speed(path: Path, max_speed_rpm: float) -> Path:
    path.write_text(path.read_text() + f"[spindle.faults]\nmax_speed_rpm = {max_speed_rpm!r}\n")
    return path


def test_a_model_covering_a_sliver_of_the_spindles_speeds_is_refused(tmp_path, capsys, caplog):
    """A model whose calibrated range tops at 10 rpm on a spindle rated 24 000 rpm: refused in
    one line by ``run --check`` and at the start, and a reload keeps the running model. Without
    a rated speed, and for a model calibrated on part of the range, nothing changes."""
    sliver = tmp_path / "sliver.json"
    save_model(sliver, ten_rpm_model())
    reason = (
        "the model's calibrated range tops at 10 rpm, under 5 % of the spindle's max_speed_rpm "
        "24000 (1200 rpm)"
    )
    cfg = with_max_speed(write_config(tmp_path / "sliver", {"s1": sliver}), 24000.0)
    code, out, err = run(capsys, "run", "--check", "--config", cfg)
    assert code == 2 and out == "" and err.count("\n") == 1, (code, out, err)
    assert reason in err
    started = thermocomp("run", "--config", cfg)
    assert started.returncode == 2 and started.stderr.count("\n") == 1, started
    assert reason in started.stderr

    # no rated speed configured: as before, it loads (the check needs the spindle's top)
    code, out, err = run(
        capsys, "run", "--check", "--config", write_config(tmp_path / "no-max", {"s1": sliver})
    )
    assert code == 0, (code, out, err)
    # a quarter of the range: taken
    part = tmp_path / "part.json"
    save_model(part, part_range_model())
    part_cfg = with_max_speed(write_config(tmp_path / "part", {"s1": part}), 24000.0)
    code, out, err = run(capsys, "run", "--check", "--config", part_cfg)
    assert code == 0, (code, out, err)

    # a reload to the sliver: refused, the running model kept, compensating on
    live = tmp_path / "model.json"
    save_model(live, old_model())
    clock = Clock()
    svc = service(with_max_speed(write_config(tmp_path, {"s1": live}), 24000.0), clock)
    try:
        clock.t += 1.0
        svc.tick()
        running = svc.spindles["s1"].digest
        shutil.copy(sliver, live)
        with caplog.at_level(logging.WARNING):
            reload(svc, clock)
        assert svc.reload_failed and svc.spindles["s1"].alarms & Alarm.RELOAD_FAILED
        assert svc.spindles["s1"].digest == running
        refused = [r for r in caplog.records if getattr(r, "event", None) == "reload_refused"]
        assert len(refused) == 1 and reason in refused[0].fields["error"]
        cycles = svc.spindles["s1"].counters["cycles"]
        clock.t += 1.0
        svc.tick()
        assert svc.spindles["s1"].counters["cycles"] == cycles + 1
    finally:
        svc.close()
