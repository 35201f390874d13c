"""The runtime trusts the controller's offset and survives its disk: in process, on a fake clock.

The same faults with real processes (the service, the OPC UA virtual CNC) are in
``tests/faults/``; these cases pin the decisions cycle by cycle.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np
import pytest

from cnc_adapters.reading import REASON_CHARS
from compensator import ConfigError
from compensator.io import read_run_log, save_model
from compensator.model import ThermalModel
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import VirtualMachine
from thermocomp.runtime import Alarm, SpindleRuntime
from thermocomp.runtime.config import load_config
from thermocomp.runtime.events import JsonLines
from thermocomp.runtime.lock import AlreadyRunningError, StateDirLock

RATE = 2.0
CLAMP = 40.0


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    # tau = 100 s, 2 um per krpm at steady state: 20 um at 10 000 rpm
    m = ThermalModel.from_discrete(0.99, (0.0, 0.02, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 27000.0))
    p = tmp_path_factory.mktemp("m") / "model.json"
    save_model(p, m)
    return p


def config(tmp_path: Path, model: Path, faults: str = "", **top) -> Path:
    lines = [f'state_dir = "{tmp_path / "state"}"', "watchdog = false"]
    lines += [f"{k} = {json.dumps(v)}" for k, v in top.items()]
    lines += [
        "[[spindle]]",
        'name = "s1"',
        f'model = "{model}"',
        "period_s = 1.0",
        "state_save_every_s = 10.0",
        'adapter = {url = "sim://"}',
        "[spindle.shaping]",
        f"max_offset_um = {CLAMP}",
        f"max_rate_um_per_s = {RATE}",
        "deadband_um = 0.0",
        "[spindle.shaping.transient]",
        "enabled = false",
        "[spindle.faults]",
        faults,
    ]
    p = tmp_path / "machine.toml"
    p.write_text("\n".join(lines) + "\n")
    return p


class Bench:
    """A runtime on the in-process virtual machine, one clock for both."""

    def __init__(self, tmp_path: Path, model: Path, faults: str = "", wall0: float = 1.7e9, **top):
        self.t = 0.0
        self.wall_offset = wall0
        self.cfg = load_config(config(tmp_path, model, faults, **top))
        self.vm = VirtualMachine(
            SpindlePlant(preset("motorized-27k"), seed=1), None, clock=self.clock
        )
        self.vm.override_speed(10000.0)
        sc = self.cfg.spindle[0]
        self.rt = SpindleRuntime(
            sc,
            self.cfg.state_dir,
            self.cfg.journal_path,
            clock=self.clock,
            wall=self.wall,
            adapter=SimAdapter(machine=self.vm),
        )
        self.rows: list[dict] = []

    def clock(self) -> float:
        return self.t

    def wall(self) -> float:
        return self.wall_offset + self.t

    def run(self, cycles: int) -> list[dict]:
        out = []
        for _ in range(cycles):
            self.t += 1.0
            out.append(self.rt.cycle())
        self.rows += out
        return out


def assert_slew(rows: list[dict], held_um: dict[int, float] | None = None) -> None:
    """Each row within one slew step of the one before; ``held_um``: row index -> the value
    the controller was found to hold in that cycle (the step starts there)."""
    off = np.array([r["offset_um"] for r in rows])
    dt = np.array([r["dt_s"] for r in rows])
    before = np.r_[np.nan, off[:-1]]
    for k, v in (held_um or {}).items():
        before[k] = v
    assert np.all(np.abs(off - before)[1:] <= RATE * dt[1:] + 1e-9)


def test_a_reset_controller_is_read_back_and_written_again_within_one_cycle(tmp_path, model_file):
    b = Bench(tmp_path, model_file)
    first = b.run(1)[0]
    assert first["alarms"] & Alarm.COLD_START and not first["alarms"] & Alarm.OFFSET_MISMATCH
    b.run(300)
    assert b.vm.offset_um == pytest.approx(-b.rows[-1]["predicted_um"], abs=1e-9)
    assert b.vm.offset_um < -10
    b.vm.offset_um = 0.0  # an NC reset clears the variable; the link stays up
    rows = b.run(5)  # read back every cycle (the default): found before the next write
    hit = [r for r in rows if r["alarms"] & Alarm.OFFSET_MISMATCH]
    assert len(hit) == 1 and hit[0] is rows[0] and hit[0]["written"]  # and written in that cycle
    assert hit[0]["offset_um"] == pytest.approx(-RATE)  # one slew step from 0: no jump back
    assert b.vm.offset_um == rows[-1]["offset_um"]
    b.run(30)
    assert b.vm.offset_um == pytest.approx(-b.rows[-1]["predicted_um"], abs=1e-9)
    assert_slew(b.rows[1:], {b.rows[1:].index(hit[0]): 0.0})
    assert b.rt.counters["mismatches"] == 1


def test_an_outside_write_beyond_the_clamp_is_never_written_back(tmp_path, model_file, caplog):
    b = Bench(tmp_path, model_file)
    b.run(100)
    b.vm.offset_um = 90.0  # someone wrote 90 um; the clamp is 40
    with caplog.at_level(logging.ERROR, logger="thermocomp.runtime"):
        rows = b.run(100)
    mismatch = [r for r in caplog.records if getattr(r, "event", None) == "offset_mismatch"]
    assert len(mismatch) == 1 and "outside write" in mismatch[0].fields["cause"]
    assert mismatch[0].fields["held_um"] == 90.0
    off = np.array([r["offset_um"] for r in rows])
    (k,) = [i for i, r in enumerate(rows) if r["alarms"] & Alarm.OFFSET_MISMATCH]
    assert rows[k]["written"] and off[k] == CLAMP  # the clamp in the cycle that saw it
    assert np.all(np.abs(off) <= CLAMP)
    assert np.all(np.diff(off[k : k + 60]) <= 0)  # then only ever towards the model
    assert (off[k:] > -CLAMP).sum() > 20  # at the slew limit, not in a jump
    assert_slew(b.rows[1:], {99 + k: CLAMP})
    assert b.vm.offset_um == pytest.approx(-b.rows[-1]["predicted_um"], abs=1e-9)


def test_a_controller_that_keeps_refusing_is_not_fought(tmp_path, model_file, monkeypatch):
    b = Bench(tmp_path, model_file, faults="max_mismatches = 2")
    b.run(20)
    # the controller acknowledges every write but keeps its own value (a locked variable)
    monkeypatch.setattr(b.vm, "apply_offset", lambda value: True)
    b.vm.offset_um = 0.0
    rows = b.run(40)
    backoff = [r for r in rows if r["alarms"] & Alarm.WRITE_BACKOFF]
    assert backoff, "no back-off"
    writes = sum(r["written"] for r in rows)
    assert writes < 20  # it did not write every cycle against a controller that ignores it
    assert all(np.isfinite(r["offset_um"]) for r in rows)


def test_a_failing_journal_loses_no_row_and_never_stops_the_writes(tmp_path, model_file, caplog):
    b = Bench(tmp_path, model_file)
    b.run(10)
    jdir = b.cfg.journal_path
    b.rt.journal.close()  # as at midnight: the next row opens a file (RLIMIT_FSIZE: tests/faults)
    for f in jdir.iterdir():
        f.rename(tmp_path / f.name)  # keep what was written so far
    jdir.rmdir()
    jdir.write_text("not a directory")  # mkdir and open now fail: like a dead disk
    with caplog.at_level(logging.ERROR, logger="thermocomp.runtime"):
        rows = b.run(30)
    assert all(r["alarms"] & Alarm.JOURNAL_FAILED for r in rows)
    assert sum(r["written"] for r in rows) >= 15  # compensation went on
    failed = [r for r in caplog.records if getattr(r, "event", None) == "journal_failed"]
    assert len(failed) == 1 and str(jdir) in failed[0].fields["error"]
    jdir.unlink()
    b.run(5)
    later = sorted(jdir.glob("s1-*.csv"))
    assert len(later) == 1
    log = read_run_log(later[0])
    # the 30 rows kept in memory are there, in order, before the 5 that followed
    assert len(log) == 35
    assert np.all(np.diff(log.time_s) > 0)
    alarms = log.extras["alarms"].astype(int)
    assert np.all(alarms[1:30] & int(Alarm.JOURNAL_FAILED))
    assert not alarms[-1] & int(Alarm.JOURNAL_FAILED)


def test_a_state_that_cannot_be_saved_alarms_escalates_and_recovers(tmp_path, model_file, caplog):
    b = Bench(tmp_path, model_file, faults="state_retry_s = 2.0\nstate_stale_s = 60.0")
    b.run(5)
    path = b.rt.state_path
    path.unlink()
    path.mkdir()  # os.replace onto a directory fails: IsADirectoryError
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        rows = b.run(90)
        assert all(r["alarms"] & Alarm.STATE_SAVE_FAILED for r in rows[12:])
        assert not rows[40]["alarms"] & Alarm.STATE_STALE and rows[-1]["alarms"] & Alarm.STATE_STALE
        assert sum(r["written"] for r in rows) > 40
        path.rmdir()
        rows = b.run(70)  # the back-off is at most max_write_backoff_s
    assert not rows[-1]["alarms"] & (Alarm.STATE_SAVE_FAILED | Alarm.STATE_STALE)
    events = [getattr(r, "event", None) for r in caplog.records]
    assert events.count("state_save_failed") == 1 and events.count("state_stale") == 1
    assert events.count("state_saved_again") == 1
    assert path.is_file()


@pytest.mark.parametrize(
    "text",
    [
        '{"format": "thermocomp.state/1", "thermal_um": [NaN]}',
        "[" * 100000 + "]" * 100000,
        "{",
        '{"format": "thermocomp.state/1"}',
        "\x00\xff garbage",
    ],
)
def test_a_corrupt_state_file_is_kept_aside_and_means_a_cold_start(tmp_path, model_file, text):
    b = Bench(tmp_path, model_file)
    b.run(3)
    b.rt.close()
    b.rt.state_path.write_text(text, encoding="utf-8", errors="surrogateescape")
    again = Bench(tmp_path, model_file)
    assert again.rt.alarms & Alarm.STATE_CORRUPT and again.rt.alarms & Alarm.COLD_START
    kept = list(b.rt.state_path.parent.glob("s1.state.json.corrupt-*"))
    assert len(kept) == 1 and kept[0].read_text(encoding="utf-8", errors="surrogateescape") == text
    assert again.run(1)[0]["alarms"] & Alarm.STATE_CORRUPT


def test_a_wall_clock_step_is_flagged_and_the_journal_stays_increasing(tmp_path, model_file):
    b = Bench(tmp_path, model_file, wall0=1.7e9 + 40000)  # 09:20 UTC: one day file
    b.run(10)
    b.wall_offset -= 3600.0  # NTP or an operator sets the clock back an hour
    rows = b.run(10)
    assert rows[0]["alarms"] & Alarm.CLOCK_STEP and not rows[1]["alarms"] & Alarm.CLOCK_STEP
    b.rt.close()
    log = read_run_log(next(b.cfg.journal_path.glob("s1-*.csv")))
    assert len(log) == 20 and np.all(np.diff(log.time_s) == pytest.approx(1.0))
    wall = log.extras["wall_s"]
    assert wall[10] - wall[9] == pytest.approx(1.0 - 3600.0)  # the wall clock as read
    # a restart behind the last row continues in a second part, itself increasing
    c = Bench(tmp_path, model_file, wall0=1.7e9 + 40000 - 1800)
    c.run(5)
    c.rt.close()
    parts = sorted(b.cfg.journal_path.glob("s1-*.csv"))
    assert [p.name.count(".p2.") for p in parts] == [0, 1]
    assert len(read_run_log(parts[1])) == 5


def test_one_instance_per_state_directory(tmp_path):
    with StateDirLock(tmp_path):
        with pytest.raises(AlreadyRunningError, match=f"pid {os.getpid()}"):
            StateDirLock(tmp_path).acquire()
    with StateDirLock(tmp_path):  # released: free again
        pass


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        ("period_s = inf", "period_s"),
        ("period_s = nan", "period_s"),
        ("state_save_every_s = 1e400", "state_save_every_s"),
    ],
)
def test_config_values_are_finite_and_bounded(tmp_path, model_file, extra, match):
    p = config(tmp_path, model_file)
    key = extra.split(" =")[0]
    p.write_text(
        "\n".join(
            extra if line.startswith(f"{key} =") else line for line in p.read_text().splitlines()
        )
        + "\n"
    )
    with pytest.raises(ConfigError, match=match) as exc:
        load_config(p)
    assert "\n" not in str(exc.value)


def test_time_scale_inf_and_a_password_in_the_url_are_refused(tmp_path, model_file):
    with pytest.raises(ConfigError, match="time_scale"):
        load_config(config(tmp_path, model_file, time_scale=1e309))
    p = config(tmp_path, model_file)
    p.write_text(
        p.read_text().replace('url = "sim://"', 'url = "opc.tcp://op:Hunter2@127.0.0.1:4840"')
    )
    with pytest.raises(ConfigError, match="password_file") as exc:
        load_config(p)
    assert "Hunter2" not in str(exc.value)


def test_events_are_json_lines_with_their_fields_and_short_messages():
    fmt = JsonLines()
    rec = logging.LogRecord(
        "thermocomp.runtime", logging.ERROR, __file__, 1, "x" * 100000, None, None
    )
    rec.event, rec.spindle, rec.fields = "outage", "s1", {"down_s": 12.5, "error": "e" * 5000}
    out = json.loads(fmt.format(rec))
    assert out["event"] == "outage" and out["spindle"] == "s1" and out["down_s"] == 12.5
    assert len(out["msg"]) <= JsonLines.MAX_MESSAGE and len(out["error"]) <= REASON_CHARS
