"""Breaks a fault run found in the service, each with the test that shows it fixed: a link
planted in the journal or state directory, spindle names that read as another spindle's
journal, a state saved ahead of the clock, a held offset beyond the clamp in the journal, and
a probe's sigma of any type through the running service.

The runtime runs in lock-step on a clock the test moves; the controllers are real (the virtual
machine tool's adapter, an asyncua server).
"""

from __future__ import annotations

import csv
import logging
import math
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import ua
from test_boundary_opcua import VARIANTS, Controller, Sequence, controller

from compensator.errors import ConfigError
from compensator.io import Journal, MeasurementJournal, load_state, save_model, save_state
from compensator.io.journal import cut_torn_tail
from compensator.io.retention import day_start_s, utc_day
from compensator.model import ThermalModel
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import VirtualMachine, free_port
from thermocomp.runtime import Alarm, Service, SpindleRuntime
from thermocomp.runtime.config import load_config
from thermocomp.runtime.keeper import ScaledWall
from thermocomp.runtime.lock import LOCK_NAME, StateDirLock

__all__ = ["controller"]  # the asyncua server of test_boundary_opcua, one for this module

WALL0 = day_start_s("2026-03-02") + 8 * 3600.0
YEAR_S = 365.25 * 86400.0
CLAMP_UM = 40.0


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # tau 100 s, 2 um per 1000 rpm at steady state
    m = ThermalModel.from_discrete(0.99, (0.0, 0.02, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 27000.0))
    p = tmp_path_factory.mktemp("model") / "model.json"
    save_model(p, m)
    return p


def write_config(
    directory: Path, model: Path, adapter: str = '{url = "sim://"}', name: str = "s1"
) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "machine.toml"
    path.write_text(
        "\n".join(
            [
                f'state_dir = "{directory / "state"}"',
                "watchdog = false",
                "journal_fsync_s = 3600.0",
                "[status]",
                "enabled = false",
                "[[spindle]]",
                f'name = "{name}"',
                f'model = "{model}"',
                "period_s = 1.0",
                f"adapter = {adapter}",
                "[spindle.shaping]",
                f"max_offset_um = {CLAMP_UM}",
                "max_rate_um_per_s = 1.0",
                "deadband_um = 0.0",
                "[spindle.observer]",
                "enabled = true",
            ]
        )
        + "\n"
    )
    return path


class Rig:
    """One spindle's runtime on the virtual machine tool (or on the adapter its configuration
    names), on a clock the test moves; ``wall0`` is what the wall clock says at t = 0."""

    def __init__(self, directory: Path, model: Path, *, wall0: float = WALL0, adapter: str = ""):
        self.t = 0.0
        self.wall0 = wall0
        cfg = load_config(write_config(directory, model, *([adapter] if adapter else [])))
        self.vm: VirtualMachine | None = None
        link: Any = None
        if not adapter:
            self.vm = VirtualMachine(
                SpindlePlant(preset("motorized-27k"), seed=1), None, clock=lambda: self.t
            )
            link = SimAdapter(machine=self.vm)
        self.journal_dir = cfg.journal_path
        self.rt = SpindleRuntime(
            cfg.spindle[0],
            cfg.state_dir,
            cfg.journal_path,
            journal_fsync_s=cfg.journal_fsync_s,
            clock=lambda: self.t,
            wall=lambda: self.wall0 + self.t,
            **({"adapter": link} if link is not None else {}),
        )

    def cycles(self, n: int) -> list[Any]:
        out = []
        for _ in range(n):
            self.t += 1.0
            out.append(self.rt.cycle())
        return out


def events(caplog: pytest.LogCaptureFixture, name: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if getattr(r, "event", None) == name]


def journal_rows(path: Path) -> list[dict[str, str]]:
    lines = [ln for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]
    return list(csv.DictReader(lines))


# -- a link planted in the journal or state directory -----------------------------------------


TORN = b"# a run log\ntime_s,speed_rpm\n1.0,100\n2.0,1"  # its last row cut short


def test_a_link_planted_in_the_journal_directory_is_never_followed(
    tmp_path: Path, model: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Today's journal file is a symbolic link to a run log with a torn last row: the repair
    and the appends never reach the target; the journal says why (JOURNAL_FAILED), keeps the
    rows in memory and writes them all once the link is gone; compensation goes on."""
    victim = tmp_path / "elsewhere" / "precious.csv"
    victim.parent.mkdir()
    victim.write_bytes(TORN)
    r = Rig(tmp_path / "m", model)
    assert r.vm is not None
    r.journal_dir.mkdir(parents=True)
    planted = r.journal_dir / f"s1-{utc_day(WALL0)}.csv"
    planted.symlink_to(victim)
    r.vm.override_speed(12000.0)
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        rows = r.cycles(20)
    assert victim.read_bytes() == TORN  # neither cut nor appended to
    assert planted.is_symlink() and not list(victim.parent.glob("*.torn-*"))
    assert all(o.alarms & Alarm.JOURNAL_FAILED for o in rows[1:])
    failed = events(caplog, "journal_failed")
    assert failed and "not a regular file" in failed[0].getMessage()
    assert str(planted) in failed[0].getMessage()
    assert r.rt.counters["writes"] > 5  # the offset still follows the model
    planted.unlink()
    r.cycles(1)
    r.rt.close()
    assert len(journal_rows(planted)) == 21  # no row lost


def test_the_torn_tail_is_never_written_through_a_link(tmp_path: Path) -> None:
    """The torn tail is kept beside the file it was cut from, in a file created for it: a link
    planted under that name is left alone, and so is its target."""
    jdir = tmp_path / "journal"
    jdir.mkdir()
    day = utc_day(WALL0)
    path = jdir / f"s1-{day}.csv"
    head = Journal(jdir, "s1", {"spindle": "s1"})
    head.write(WALL0, 1000.0, 1.0, 1.0, True, 0, 0)
    head.close()
    whole = path.read_bytes()
    path.write_bytes(whole + b"1772438401.000,10")  # a power loss mid-row
    victim = tmp_path / "precious.txt"
    victim.write_bytes(b"keep me\n")
    (jdir / f"{path.name}.torn-{len(whole)}").symlink_to(victim)
    kept = cut_torn_tail(path)
    assert victim.read_bytes() == b"keep me\n"
    assert kept is not None and not kept.is_symlink() and kept.read_bytes() == b"1772438401.000,10"
    assert path.read_bytes() == whole


def test_a_link_to_a_fifo_or_a_dangling_link_is_a_failed_write_not_a_hang(tmp_path: Path) -> None:
    jdir = tmp_path / "journal"
    jdir.mkdir()
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    path = jdir / f"s1-{utc_day(WALL0)}.csv"
    for target in (fifo, tmp_path / "nothing-here.csv"):
        path.symlink_to(target)
        j = Journal(jdir, "s1", {"spindle": "s1"})
        assert not j.write(WALL0, 1000.0, 1.0, 1.0, True, 0, 0)
        assert j.error is not None and "not a regular file" in j.error
        assert j.pending_rows == 1
        assert not (tmp_path / "nothing-here.csv").exists()  # not created through the link
        j.close()
        path.unlink()
    os.mkfifo(path)  # a FIFO in the journal's own place
    j = Journal(jdir, "s1", {"spindle": "s1"})
    assert not j.write(WALL0, 1000.0, 1.0, 1.0, True, 0, 0)
    assert j.error is not None and "not a regular file" in j.error
    j.close()


def test_a_link_planted_as_the_state_directorys_lock_file_is_not_written_through(
    tmp_path: Path,
) -> None:
    state = tmp_path / "state"
    state.mkdir()
    victim = tmp_path / "precious.txt"
    victim.write_bytes(b"keep me\n")
    (state / LOCK_NAME).symlink_to(victim)
    with StateDirLock(state):
        assert victim.read_bytes() == b"keep me\n"
        lock = state / LOCK_NAME
        assert not lock.is_symlink() and lock.read_text() == f"{os.getpid()}\n"


def test_links_planted_for_the_history_and_the_status_url_are_not_written_through(
    tmp_path: Path, model: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The model history's record file and ``status.url`` live in the state directory too: a
    link planted as either leaves its target as it was; the start goes on."""
    config = write_config(tmp_path, model)
    text = config.read_text().replace("[status]\nenabled = false", "[status]\nport = 0")
    config.write_text(text)
    victim = tmp_path / "precious.txt"
    victim.write_bytes(b"keep me\n")
    state = tmp_path / "state"
    (state / "history" / "s1").mkdir(parents=True)
    (state / "history" / "s1" / "history.jsonl").symlink_to(victim)
    (state / "status.url").symlink_to(victim)
    t = [0.0]
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        svc = Service(config, clock=lambda: t[0], wall=lambda: WALL0 + t[0])
        try:
            svc.start_status()
            t[0] += 1.0
            svc.tick()
            assert victim.read_bytes() == b"keep me\n"
            url = state / "status.url"
            assert not url.is_symlink() and url.read_text().startswith("http://127.0.0.1:")
            assert events(caplog, "history_failed")
            assert svc.spindles["s1"].counters["cycles"] == 1
        finally:
            svc.close()
    assert victim.read_bytes() == b"keep me\n"


# -- spindle names that end like a journal kind -----------------------------------------------


@pytest.mark.parametrize("name", ["a.measurements", "a.cooling", "x.y.cooling"])
def test_a_spindle_name_that_reads_as_another_spindles_journal_is_refused(
    tmp_path: Path, model: Path, name: str
) -> None:
    """``a.cooling-DAY.csv`` is spindle a's chiller journal: a spindle named ``a.cooling``
    would have its cycle journal read as that, and its export and refit fail."""
    with pytest.raises(ConfigError) as info:
        load_config(write_config(tmp_path, model, name=name))
    text = str(info.value)
    assert "\n" not in text
    assert f'spindle "{name}"' in text and "may not end in" in text
    with pytest.raises(ConfigError, match="may not end in"):
        Journal(tmp_path / "j", name, {})
    with pytest.raises(ConfigError, match="may not end in"):
        MeasurementJournal(tmp_path / "j", name, {})


@pytest.mark.parametrize("name", ["a", "a.measure", "a.cooling2", "a.cooling-line", "cooling"])
def test_other_spindle_names_and_their_journals_read_as_before(
    tmp_path: Path, model: Path, name: str
) -> None:
    from compensator.io import export_journal

    cfg = load_config(write_config(tmp_path, model, name=name))
    assert cfg.spindle[0].name == name
    d = tmp_path / "journal"
    cycles = Journal(d, name, {"spindle": name}, fsync_every_s=-1)
    probes = MeasurementJournal(d, name, {"spindle": name}, fsync_every_s=-1)
    for k in range(5):
        cycles.write(WALL0 + k, 1000.0, 1.0 + k, 1.0 + k, True, 0, 0, dt_s=1.0)
    probes.record(
        WALL0 + 2.5, elongation_um=3.0, sigma_um=0.5, source="probe", sequence=1, outcome="accepted"
    )
    cycles.close()
    probes.close()
    got = export_journal(d, tmp_path / "out.csv", spindle=name)
    assert got.rows == 5 and got.measured_rows == 1


# -- a state saved ahead of the clock ---------------------------------------------------------


def warm_state(directory: Path, model: Path, wall0: float) -> float:
    """A warm spindle's state saved at ``wall0`` + 600 s; its estimate."""
    warm = Rig(directory, model, wall0=wall0)
    assert warm.vm is not None
    warm.vm.override_speed(15000.0)
    warm.cycles(600)
    warm.rt.close()
    return warm.rt.estimate_um()


def test_a_state_saved_ten_years_ahead_of_the_clock_starts_cold_with_an_alarm(
    tmp_path: Path, model: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Its age cannot be known, so neither can whether it is younger than max_state_age_s:
    a cold start, CLOCK_STEP and COLD_START journaled, an event that says why."""
    hot = warm_state(tmp_path, model, WALL0 + 10 * YEAR_S)
    assert hot > 20.0
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        r = Rig(tmp_path, model)
        assert r.vm is not None
        r.vm.override_speed(0.0)
        first = r.cycles(1)[0]
    assert first.alarms & Alarm.CLOCK_STEP and first.alarms & Alarm.COLD_START
    assert abs(r.rt.estimate_um()) < 0.05 * hot  # not "advanced 0 s idle"
    assert not events(caplog, "state_restored")
    (step,) = events(caplog, "clock_step")
    assert "10.0 years ahead" in step.getMessage()
    assert step.levelno == logging.ERROR
    assert "ahead of the clock" in events(caplog, "cold_start")[0].getMessage()
    r.rt.close()
    assert load_state(r.rt.state_path)["saved_wall_s"] < WALL0 + 3600.0  # saved on the clock now


def test_a_state_saved_minutes_ahead_is_restored_with_an_alarm_and_measured_again(
    tmp_path: Path, model: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A box that boots with its clock where it stopped, 20 min behind its last save: the
    state is kept, the downtime taken as 0 s with CLOCK_STEP, and measured again when time
    synchronisation steps the clock (10 h later in truth)."""
    hot = warm_state(tmp_path, model, WALL0)
    saved = load_state(tmp_path / "state" / "s1.state.json")["saved_wall_s"]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        r = Rig(tmp_path, model, wall0=saved - 1200.0)
        assert r.vm is not None
        r.vm.override_speed(0.0)
        first = r.cycles(1)[0]
        assert first.alarms & Alarm.CLOCK_STEP and not first.alarms & Alarm.COLD_START
        assert r.rt.estimate_um() > 0.9 * hot  # restored, 0 s of downtime so far
        assert "1200 s ahead of the clock" in events(caplog, "clock_step")[0].getMessage()
        r.cycles(30)
        r.wall0 += 10 * 3600.0 + 1200.0  # the clock set right
        r.cycles(2)
    assert events(caplog, "downtime_corrected")
    assert r.rt.estimate_um() < 0.05 * hot
    r.rt.close()


def test_a_state_saved_a_second_ahead_is_restored_as_before(
    tmp_path: Path, model: Path, caplog: pytest.LogCaptureFixture
) -> None:
    hot = warm_state(tmp_path, model, WALL0)
    saved = load_state(tmp_path / "state" / "s1.state.json")["saved_wall_s"]
    r = Rig(tmp_path, model, wall0=saved - 1.0)
    assert r.vm is not None
    r.vm.override_speed(0.0)
    first = r.cycles(1)[0]
    assert not first.alarms & (Alarm.CLOCK_STEP | Alarm.COLD_START)
    assert r.rt.estimate_um() > 0.9 * hot
    r.rt.close()


# -- a state saved on a simulated clock (time_scale) ----------------------------------------

SCALE = 60.0


class ScaledRig(Rig):
    """A runtime on the virtual machine tool's simulated clock, ``SCALE`` times real time, as
    the service runs it with ``time_scale``; both clocks move only with the test (``real`` is
    the real wall clock)."""

    def __init__(self, directory: Path, model: Path, *, real0: float):
        self.real = real0
        cfg = load_config(write_config(directory, model))
        self.t = 0.0
        self.vm = VirtualMachine(
            SpindlePlant(preset("motorized-27k"), seed=1), None, clock=lambda: self.t
        )
        self.journal_dir = cfg.journal_path
        self.rt = SpindleRuntime(
            cfg.spindle[0],
            cfg.state_dir,
            cfg.journal_path,
            journal_fsync_s=cfg.journal_fsync_s,
            clock=lambda: self.t,
            wall=ScaledWall(lambda: self.t, lambda: self.real, SCALE),
            adapter=SimAdapter(machine=self.vm),
        )

    def cycles(self, n: int) -> list[Any]:
        out = []
        for _ in range(n):
            self.t += 1.0
            self.real += 1.0 / SCALE
            out.append(self.rt.cycle())
        return out


def test_a_time_scaled_restart_advances_the_real_downtime_times_the_scale(
    tmp_path: Path, model: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """10 real s of running (600 simulated) then 2 real s down: the restart advances the state
    120 simulated seconds idle and raises no CLOCK_STEP (the simulated save time is 590 s ahead
    of the real clock)."""
    warm = ScaledRig(tmp_path, model, real0=WALL0)
    assert warm.vm is not None
    warm.vm.override_speed(15000.0)
    warm.cycles(600)
    warm.rt.close()
    hot = warm.rt.state.elongation_um
    saved = load_state(tmp_path / "state" / "s1.state.json")
    assert saved["time_scale"] == SCALE
    assert saved["saved_real_wall_s"] == pytest.approx(WALL0 + 10.0)
    assert saved["saved_wall_s"] == pytest.approx(WALL0 + 600.0)  # simulated
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        r = ScaledRig(tmp_path, model, real0=warm.real + 2.0)
        assert r.vm is not None
        r.vm.override_speed(0.0)
        first = r.cycles(1)[0]
    assert not first.alarms & (Alarm.CLOCK_STEP | Alarm.COLD_START)
    assert not events(caplog, "clock_step")
    (restored,) = events(caplog, "state_restored")
    assert restored.__dict__["fields"]["downtime_s"] == pytest.approx(120.0)
    # the model's own cooling (0.99 per second) through 120 s, then one idle cycle
    assert restored.__dict__["fields"]["elongation_um"] == pytest.approx(hot * 0.99**120, rel=1e-6)
    r.rt.close()
    again = load_state(r.rt.state_path)
    assert again["saved_real_wall_s"] == pytest.approx(warm.real + 2.0 + 1.0 / SCALE)


def test_a_time_scaled_state_saved_ten_real_years_ahead_still_starts_cold(
    tmp_path: Path, model: Path, caplog: pytest.LogCaptureFixture
) -> None:
    warm = ScaledRig(tmp_path, model, real0=WALL0 + 10 * YEAR_S)
    assert warm.vm is not None
    warm.vm.override_speed(15000.0)
    warm.cycles(600)
    warm.rt.close()
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        r = ScaledRig(tmp_path, model, real0=WALL0)
        first = r.cycles(1)[0]
    assert first.alarms & Alarm.CLOCK_STEP and first.alarms & Alarm.COLD_START
    assert "10.0 years ahead" in events(caplog, "clock_step")[0].getMessage()
    assert not events(caplog, "state_restored")
    r.rt.close()


def test_a_state_without_the_real_time_is_read_as_before(
    tmp_path: Path, model: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A state file of an older version (no real time, no scale) under a time scale: its
    saved_wall_s is compared with the clock as before (1200 s ahead: CLOCK_STEP, 0 s)."""
    warm_state(tmp_path, model, WALL0)
    path = tmp_path / "state" / "s1.state.json"
    old = load_state(path)
    for k in ("saved_real_wall_s", "time_scale", "format"):
        old.pop(k)
    save_state(path, old)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        r = ScaledRig(tmp_path, model, real0=old["saved_wall_s"] - 1200.0)
        first = r.cycles(1)[0]
    assert first.alarms & Alarm.CLOCK_STEP and not first.alarms & Alarm.COLD_START
    assert "1200 s ahead of the clock" in events(caplog, "clock_step")[0].getMessage()
    r.rt.close()


# -- a held offset beyond the clamp -----------------------------------------------------------


def dead_link(directory: Path) -> str:
    """An OPC UA link to a port nobody listens on: the offset can be neither read nor written."""
    return (
        f'{{type = "opcua", url = "opc.tcp://127.0.0.1:{free_port()}", speed_node = "ns=2;s=a", '
        'offset_node = "ns=2;s=b", timeout_s = 0.5}'
    )


def test_a_held_offset_saved_beyond_the_clamp_is_journaled_at_the_clamps_edge(
    tmp_path: Path, model: Path
) -> None:
    """A state an older version saved with a foreign value (or a clamp lowered since), restored
    while the controller cannot be reached: nothing beyond the clamp was written, and the
    journal and status never say it was."""
    r = Rig(tmp_path, model, adapter=dead_link(tmp_path))
    r.cycles(1)
    r.rt.close()
    path = tmp_path / "state" / "s1.state.json"
    body = load_state(path)
    assert body is not None
    body.pop("format")
    for held in (9999.0, -9999.0):
        save_state(path, {**body, "offset_um": held})
        r = Rig(tmp_path, model, adapter=dead_link(tmp_path))
        rows = r.cycles(3)
        assert all(o.alarms & Alarm.LINK_DOWN and not o.written for o in rows)
        assert [o.offset_um for o in rows] == [math.copysign(CLAMP_UM, held)] * 3
        assert r.rt.offset.held_um == math.copysign(CLAMP_UM, held)
        r.rt.close()
    held_col = [
        float(row["offset_um"])
        for path in sorted(r.journal_dir.glob("s1-*.csv"))
        for row in journal_rows(path)
    ]
    assert len(held_col) == 7 and all(abs(v) <= CLAMP_UM for v in held_col)


@pytest.fixture
def opcua_config(controller: Controller, tmp_path: Path, model: Path) -> Path:
    node = controller.node_id
    adapter = (
        f'{{type = "opcua", url = "{controller.url}", speed_node = "{node("speed")}", '
        f'offset_node = "{node("offset")}", '
        f'measurement_node = "{node("probe_value")}", '
        f'measurement_sequence_node = "{node("probe_sequence")}", '
        f'measurement_sigma_node = "{node("probe_sigma")}", timeout_s = 5.0}}'
    )
    controller.keep_offset.clear()
    controller.reset(Sequence.next())
    return write_config(tmp_path, model, adapter)


@pytest.fixture
def service(opcua_config: Path, controller: Controller) -> Iterator[tuple[Service, list[float]]]:
    t = [0.0]
    svc = Service(opcua_config, clock=lambda: t[0], wall=lambda: WALL0 + t[0])
    try:
        yield svc, t
    finally:
        svc.close()
        controller.keep_offset.clear()
        controller.reset(Sequence.next())


def tick(svc: Service, t: list[float], n: int = 1) -> None:
    for _ in range(n):
        t[0] += 1.0
        svc.tick()  # raises nothing


def test_int64_max_held_by_the_controller_is_never_journaled_as_held(
    controller: Controller,
    service: tuple[Service, list[float]],
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A controller that keeps Int64 max in the offset, whatever is written: the journal's
    offset_um stays within the clamp on every row, written or held (the edge, where the foreign
    value was), and the offset_mismatch event names what the controller held."""
    svc, t = service
    tick(svc, t, 3)
    foreign = ua.Variant(2**63 - 1, ua.VariantType.Int64)
    controller.keep_offset[:] = [float(foreign.Value)]
    caplog.clear()
    rt = svc.spindles["s1"]
    seen = Alarm.NONE
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        controller.set("offset", foreign)
        for _ in range(6):
            tick(svc, t)
            seen |= rt.alarms
            assert abs(rt.offset.held_um) <= CLAMP_UM
    assert seen & Alarm.OFFSET_MISMATCH
    mismatch = events(caplog, "offset_mismatch")
    assert mismatch and getattr(mismatch[0], "fields", {}).get("held_um") == float(2**63 - 1)
    rt.journal.flush(t[0])
    held = [float(row["offset_um"]) for row in journal_rows(rt.journal.path)]
    assert len(held) == 9 and all(abs(v) <= CLAMP_UM for v in held)
    assert CLAMP_UM in map(abs, held)


# -- a probe's sigma of any type, through the running service ---------------------------------


SIGMA_NOT_A_NUMBER = [
    "string",
    "string-array",
    "double-array",
    "bytestring",
    "datetime",
    "true",
    "false",
]


def test_a_sigma_that_is_no_number_is_refused_and_the_service_runs_on(
    controller: Controller,
    service: tuple[Service, list[float]],
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A String, an array, a ByteString, a DateTime or a Boolean in the sigma node: the service
    keeps cycling and writing, each measurement is refused (journaled ``refused``, one line
    that names the sigma), none moves the estimate; a good one after them is taken."""
    svc, t = service
    tick(svc, t, 3)
    rt = svc.spindles["s1"]
    refused = 0
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        for kind in SIGMA_NOT_A_NUMBER:
            cycles, bias = rt.counters["cycles"], rt.observer_status()["bias_um"]
            y = ua.Variant(rt.estimate_um() + 2.0, ua.VariantType.Double)
            controller.set("probe_value", y)
            controller.set("probe_sigma", VARIANTS[kind])
            controller.set("probe_sequence", ua.Variant(Sequence.next(), ua.VariantType.UInt32))
            tick(svc, t, 2)  # the same counter the second time: no new measurement
            assert rt.counters["cycles"] == cycles + 2, kind
            assert rt.alarms & Alarm.PROBE_FAILED, kind
            assert rt.observer_status()["bias_um"] == bias, kind  # never taken as 1 um
            rt.measurements.flush(t[0])
            outcomes = [row["outcome"] for row in journal_rows(rt.measurements.path)]
            assert outcomes.count("refused") == refused + 1, kind
            refused += 1
    failed = events(caplog, "probe_failed")
    assert failed  # once per new reason
    assert all("sigma" in r.getMessage() and "\n" not in r.getMessage() for r in failed)
    rt.measurements.flush(t[0])
    outcomes = [row["outcome"] for row in journal_rows(rt.measurements.path)]
    assert outcomes.count("refused") == len(SIGMA_NOT_A_NUMBER)
    assert "accepted" not in outcomes and "rejected" not in outcomes
    assert not svc._stop and svc.exit_code == 0
    controller.set("probe_value", ua.Variant(rt.estimate_um() + 0.5, ua.VariantType.Double))
    controller.set("probe_sigma", ua.Variant(0.5, ua.VariantType.Double))
    controller.set("probe_sequence", ua.Variant(Sequence.next(), ua.VariantType.UInt32))
    tick(svc, t, 2)
    rt.measurements.flush(t[0])
    assert journal_rows(rt.measurements.path)[-1]["outcome"] == "accepted"


def test_a_fifo_planted_as_the_history_hangs_neither_the_start_nor_a_reload(
    tmp_path: Path, model: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A FIFO in the model history's record file: the start and a SIGHUP reload read and append
    the history; each says in one line that it could not, and the service compensates on."""
    config = write_config(tmp_path, model)
    fifo = tmp_path / "state" / "history" / "s1" / "history.jsonl"
    fifo.parent.mkdir(parents=True)
    os.mkfifo(fifo)
    t = [0.0]
    done: list[int] = []
    failed: list[BaseException] = []

    def run() -> None:
        try:
            svc = Service(config, clock=lambda: t[0], wall=lambda: WALL0 + t[0])
            try:
                t[0] += 1.0
                svc.tick()
                done.append(svc.spindles["s1"].counters["cycles"])
                svc.reload()
                for _ in range(3):
                    t[0] += 1.0
                    svc.tick()
                done.append(svc.spindles["s1"].counters["cycles"])
            finally:
                svc.close()
        except BaseException as err:  # handed to the test's thread
            failed.append(err)

    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        worker = threading.Thread(target=run, daemon=True)
        worker.start()
        worker.join(timeout=120.0)  # generous: a hang waits for a FIFO's writer forever
        if worker.is_alive():
            # a reader and a writer end whatever open still waits, so that the thread ends
            r = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
            w = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
            os.close(w)
            worker.join(timeout=10.0)
            os.close(r)
            pytest.fail("the service hung on the FIFO planted as its model history")
    assert not failed, failed
    assert done[0] == 1 and done[1] >= 2  # compensating after the start and after the reload
    said = events(caplog, "history_failed")
    assert len(said) >= 2  # the start and the reload
    for rec in said:
        text = rec.getMessage()
        assert "\n" not in text and "not a regular file" in text and str(fifo.parent) in text
    assert fifo.is_fifo()  # left alone
