"""Speed transients (issue 18): the elastic step is applied while the spindle runs up, with the
tool clear of the part, never while it cuts. In process, on one fake clock shared by the runtime
and the virtual machine (nothing sleeps, no second clock); replay applies the very same shaping.

The OPC UA, LinuxCNC and Modbus links carry the same signal: their tests are in
``test_transients_links.py``.
"""

from __future__ import annotations

import itertools
import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration.replay import replay
from cnc_adapters import AdapterError
from compensator import ConfigError
from compensator.io import read_run_log, save_model
from compensator.model import ThermalModel
from compensator.speed_programs import Program
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import VirtualMachine
from thermocomp.runtime import Alarm, SpindleRuntime
from thermocomp.runtime.config import load_config

MAX_RATE = 1.0  # um/s while cutting
FAST_RATE = 50.0  # um/s while the tool is clear of the part
WALL0 = 1.0e6  # small epoch seconds: the journal's millisecond stamps keep the exact dt

# two operations with a tool change between them, and a run-down to rest
PROGRAM = Program(
    "two-ops",
    ((5.0, 0.0), (240.0, 22500.0), (20.0, 0.0), (240.0, 9000.0), (120.0, 24000.0), (60.0, 0.0)),
)


@pytest.fixture(scope="module")
def model_file(tmp_path_factory) -> Path:
    # one thermal state (tau 100 s) plus the plant's own elastic growth: 10.4 um at 22 500 rpm
    m = ThermalModel.from_discrete(
        0.99, (0.0, 0.02, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 27000.0), elastic_um=(0.05, 0.0205)
    )
    p = tmp_path_factory.mktemp("m") / "model.json"
    save_model(p, m)
    return p


def config(
    tmp_path: Path, model: Path, signal: str = "auto", policy: str = "dual-slew", extra: str = ""
) -> Path:
    tmp_path.mkdir(parents=True, exist_ok=True)
    lines = [
        f'state_dir = "{tmp_path / "state"}"',
        "watchdog = false",
        "journal_fsync_s = 3600.0",
        "[[spindle]]",
        'name = "s1"',
        f'model = "{model}"',
        "period_s = 1.0",
        extra,
        "state_save_every_s = 600.0",
        'adapter = {url = "sim://"}',
        "[spindle.shaping]",
        "max_offset_um = 60.0",
        f"max_rate_um_per_s = {MAX_RATE}",
        f"not_cutting_rate_um_per_s = {FAST_RATE}",
        "deadband_um = 0.1",
        "[spindle.shaping.transient]",
        *(["enabled = false"] if policy == "slow-slew" else [f'mode = "{policy}"']),
        "[spindle.shaping.cutting]",
        f'signal = "{signal}"',
        "settle_s = 2.0",
    ]
    p = tmp_path / "machine.toml"
    p.write_text("\n".join(lines) + "\n")
    return p


class Bench:
    """The runtime on the in-process virtual machine (the sim adapter), one clock for both. The
    machine idles for the first cycle (both the runtime and replay start at rest), then runs
    ``program``."""

    def __init__(
        self,
        path: Path,
        program: Program = PROGRAM,
        adapter_cls=SimAdapter,
        jitter_seed: int | None = None,
    ):
        self.t = 0.0
        self.cfg = load_config(path)
        self.vm = VirtualMachine(
            SpindlePlant(preset("motorized-27k"), seed=3), None, clock=self.clock
        )
        self.rt = SpindleRuntime(
            self.cfg.spindle[0],
            self.cfg.state_dir,
            self.cfg.journal_path,
            journal_fsync_s=self.cfg.journal_fsync_s,
            clock=self.clock,
            wall=lambda: WALL0 + self.t,
            adapter=adapter_cls(machine=self.vm),
        )
        self.program = program
        self.rng = None if jitter_seed is None else np.random.default_rng(jitter_seed)
        self.truth: list[bool] = []  # the machine's own cutting state at each cycle

    def clock(self) -> float:
        return self.t

    def run(self) -> list[dict]:
        rows = [self.rt.cycle()]
        self.truth.append(self.vm.cutting)
        self.vm.load_program(self.program)
        while not self.vm.program_done:
            # the runtime's own schedule (run_up_period_s), or a jittered one on a 1-ms grid
            step = (
                self.rt.next_period_s()
                if self.rng is None
                else float(self.rng.integers(700, 1300)) / 1000
            )
            self.t = round(self.t + step, 3)
            rows.append(self.rt.cycle())
            self.truth.append(self.vm.cutting)
        self.rt.close()
        return rows

    def journal(self):
        (path,) = sorted(self.cfg.journal_path.glob("s1-*.csv"))
        return read_run_log(path)


def steps(log) -> tuple[np.ndarray, np.ndarray]:
    """|offset change| and dt of each journal row after the first."""
    return np.abs(np.diff(log.extras["offset_um"])), np.asarray(log.extras["dt_s"], float)[1:]


def assert_slow_while_cutting(log, cutting: np.ndarray, rate: float = MAX_RATE) -> int:
    """Between two cycles taken as cutting the offset moved at most ``rate`` * dt; the number
    of such steps."""
    moved, dt = steps(log)
    both = cutting[1:] & cutting[:-1]
    assert both.sum() > 100
    excess = moved[both] - rate * dt[both]
    assert excess.max() <= 1e-9, f"{excess.max():.4f} um over the cutting slew limit"
    return int(both.sum())


def lag_um(log) -> np.ndarray:
    """How far the offset held is from the model's -S."""
    return np.abs(np.asarray(log.extras["offset_um"]) + np.asarray(log.extras["predicted_um"]))


def test_with_the_controllers_signal_the_step_lands_in_the_run_up_and_never_while_cutting(
    tmp_path, model_file
):
    b = Bench(config(tmp_path, model_file))
    rows = b.run()
    log = b.journal()
    truth = np.array(b.truth)
    assert set(log.extras["cutting_source"]) == {"controller"}
    journaled = np.asarray(log.extras["cutting"], float) == 1
    assert (journaled == truth).all()  # the runtime took the machine's word, every cycle
    assert_slow_while_cutting(log, journaled)
    # the elastic step (10 um and more) went on as the spindle ran up, the tool clear of the part
    moved, dt = steps(log)
    fast = moved > MAX_RATE * dt + 1e-9
    assert moved.max() > 3 * MAX_RATE and not journaled[1:][fast].any()  # a run-up: ~5 um/s
    assert set(log.extras["policy_state"][journaled]) == {"cutting"}
    assert set(log.extras["policy_state"][~journaled]) == {"clear"}
    assert set(np.asarray(log.extras["slew_limit_um_per_s"])[~journaled]) == {FAST_RATE}
    # so whenever the tool cuts, the offset is where the model says (within the deadband and a
    # second of thermal drift)
    assert lag_um(log)[journaled].max() < 0.25
    assert all(r["cutting"] == t for r, t in zip(rows, truth))


def test_slow_slew_only_lags_the_elastic_step_into_the_cut(tmp_path, model_file):
    """The old behaviour, still selectable: one slow limit; the cut starts 10 um off."""
    b = Bench(config(tmp_path, model_file, policy="slow-slew"))
    b.run()
    log = b.journal()
    truth = np.array(b.truth)
    assert lag_um(log)[truth].max() > 5.0
    assert set(log.extras["policy_state"]) == {"tracking"}


def test_with_the_signal_inferred_from_the_speed_the_machine_never_sees_a_fast_move_in_the_cut(
    tmp_path, model_file
):
    b = Bench(config(tmp_path, model_file, signal="speed"))
    b.run()
    log = b.journal()
    truth = np.array(b.truth)
    assert set(log.extras["cutting_source"]) == {"speed"}
    inferred = np.asarray(log.extras["cutting"], float) == 1
    assert_slow_while_cutting(log, inferred)  # the runtime's own view
    assert_slow_while_cutting(log, truth)  # and the machine's: the tool in the part
    # it agrees with the machine but for the settling after a run-up and the cycle before the
    # runtime sees a new speed (the tool already retracted): then it errs on the slow side
    assert (inferred == truth).mean() > 0.97
    assert lag_um(log)[truth].max() < 0.25


def test_replay_writes_what_the_runtime_wrote_step_for_step(tmp_path, model_file):
    """The journal replayed with the same configuration: the applied offset equals the offset
    the runtime wrote, cycle for cycle, on an irregular clock; with the controller's signal (the
    journal's cutting column) and inferred."""
    for signal in ("auto", "speed"):
        path = config(tmp_path / signal, model_file, signal=signal)
        b = Bench(path, jitter_seed=7)
        b.run()
        log = b.journal()
        rep = replay(load_model_of(path), log, shaping=b.cfg.spindle[0].shaping)
        written = np.asarray(log.extras["offset_um"], float)
        assert np.abs(rep.applied_offset_um - written).max() < 1e-6, signal
        assert np.abs(rep.predicted_um - np.asarray(log.extras["predicted_um"])).max() < 1e-6
        assert (rep.cutting == (np.asarray(log.extras["cutting"], float) == 1)).all()
        assert rep.report["shaping"]["cutting_source"] == (
            "the journal's cutting column where the controller gave it"
            if signal == "auto"
            else "inferred from the speed"
        )


def load_model_of(path: Path):
    from compensator.io import load_any_model

    return load_any_model(load_config(path).spindle[0].model)


def test_replay_cli_takes_the_shaping_from_the_runtime_configuration(tmp_path, model_file):
    path = config(tmp_path, model_file)
    b = Bench(path)
    b.run()
    (journal,) = sorted(b.cfg.journal_path.glob("s1-*.csv"))
    out = tmp_path / "replayed.csv"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "thermocomp",
            "replay",
            str(journal),
            "--config",
            str(path),
            "--json",
            "--output",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert (
        rep["shaping"]["policy"] == "dual-slew" and rep["shaping"]["max_rate_um_per_s"] == MAX_RATE
    )
    cols = read_run_log(out).extras
    assert np.abs(cols["applied_offset_um"] - b.journal().extras["offset_um"]).max() < 1e-6
    # a configuration with two spindles needs --spindle; an unknown one is named
    two = tmp_path / "two.toml"
    two.write_text(
        path.read_text()
        + path.read_text()
        .split("[[spindle]]", 1)[1]
        .join(["[[spindle]]", ""])
        .replace('name = "s1"', 'name = "s2"')
    )
    for extra, msg in (([], "name one with --spindle"), (["--spindle", "s9"], "no spindle 's9'")):
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "thermocomp",
                "replay",
                str(journal),
                "--config",
                str(two),
                *extra,
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert r.returncode == 2 and msg in r.stderr and len(r.stderr.strip().splitlines()) == 1, (
            r.stderr
        )


class FlakyCutting(SimAdapter):
    """The sim adapter whose cutting signal fails while ``failing`` is set (a wrong node, a
    broken wire)."""

    failing = False

    def _read_cutting_raw(self) -> bool:
        if self.failing:
            raise AdapterError("sim: cutting signal unreadable (test)")
        return super()._read_cutting_raw()


def test_a_failing_cutting_signal_alarms_and_the_speed_decides_meanwhile(
    tmp_path, model_file, caplog
):
    b = Bench(config(tmp_path, model_file), adapter_cls=FlakyCutting)
    adapter = b.rt.adapter
    rows = []
    b.vm.load_program(PROGRAM)
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        for k in range(240):
            adapter.failing = 60 <= k < 120
            b.t += 1.0
            rows.append(b.rt.cycle())
    sources = [r["cutting_source"] for r in rows]
    assert sources[:60] == ["controller"] * 60 and sources[120:] == ["controller"] * 120
    assert sources[60:120] == ["speed-fallback"] * 60
    assert all(r["alarms"] & Alarm.CUTTING_SIGNAL_FAILED for r in rows[60:120])
    assert not any(r["alarms"] & Alarm.CUTTING_SIGNAL_FAILED for r in rows[:60] + rows[120:])
    assert all(
        r["written"] or r["offset_um"] == rows[k - 1]["offset_um"] for k, r in enumerate(rows) if k
    )  # compensation went on
    names = [getattr(r, "event", None) for r in caplog.records]
    assert names.count("cutting_signal_failed") == 1 and names.count("cutting_signal_restored") == 1


def test_run_up_period_follows_the_run_up_in_finer_steps(tmp_path, model_file):
    b = Bench(config(tmp_path, model_file, extra="run_up_period_s = 0.25"))
    b.run()
    log = b.journal()
    dt = np.asarray(log.extras["dt_s"], float)[1:]
    cut = np.asarray(log.extras["cutting"], float)[1:] == 1
    assert set(np.round(dt, 6)) == {0.25, 1.0}
    assert (dt[cut] == 1.0).all()  # while cutting: the normal period
    assert (dt == 0.25).sum() >= 4 * 4  # each of the four speed changes in quarter seconds


def test_cutting_settings_are_checked_at_load(tmp_path, model_file):
    bad = config(tmp_path / "a", model_file, extra="")
    good = bad.read_text()
    for old, wrong, key in (
        ("settle_s = 2.0", "settle_s = -1.0", "settle_s"),
        ("settle_s = 2.0", "settle_s = 2.0\nspeed_tolerance_pct = 90", "speed_tolerance_pct"),
        ('signal = "auto"', 'signal = "sometimes"', "signal"),
        ("settle_s = 2.0", "settle_s = 2.0\nspeed_tolerance_rpm = nan", "speed_tolerance_rpm"),
    ):
        bad.write_text(good.replace(old, wrong))
        with pytest.raises(ConfigError, match=key):
            load_config(bad)
    bad.write_text(
        good.replace(f"not_cutting_rate_um_per_s = {FAST_RATE}", "not_cutting_rate_um_per_s = 0.5")
    )
    with pytest.raises(ConfigError, match="not_cutting_rate_um_per_s must not be below"):
        load_config(bad)
    # the controller's signal required where the link has none: refused at start
    need = config(tmp_path / "b", model_file, signal="controller")
    need.write_text(
        need.read_text().replace(
            'adapter = {url = "sim://"}',
            'adapter = {url = "opc.tcp://127.0.0.1:9/", speed_node = '
            '"ns=2;s=a", offset_node = "ns=2;s=b"}',
        )
    )
    cfg = load_config(need)
    with pytest.raises(ConfigError, match="no cutting signal configured"):
        SpindleRuntime(cfg.spindle[0], cfg.state_dir, cfg.journal_path)


def test_a_day_file_with_the_older_columns_is_continued_in_a_new_part(tmp_path):
    """An upgrade mid-day: the journal never appends the new columns under the old header."""
    from compensator.io import Journal

    old_header = "time_s,speed_rpm,predicted_um,offset_um,written,flags,alarms,dt_s,wall_s\n"
    old = tmp_path / "s1-1970-01-12.csv"  # 1e6 s after the epoch
    old.write_text(old_header + "5.000,0,0,0,0,0,0,0,5.000\n")
    j = Journal(tmp_path, "s1", {"source": "test"})
    assert j.write(
        WALL0,
        9000.0,
        3.5,
        -3.4,
        True,
        2,
        0,
        dt_s=1.0,
        cutting=True,
        cutting_source="controller",
        policy_state="cutting",
        slew_limit_um_per_s=1.0,
    )
    j.close()
    assert old.read_text() == old_header + "5.000,0,0,0,0,0,0,0,5.000\n"
    log = read_run_log(tmp_path / "s1-1970-01-12.p2.csv")
    assert list(log.extras)[-4:] == [
        "cutting",
        "cutting_source",
        "policy_state",
        "slew_limit_um_per_s",
    ]
    assert (
        log.extras["cutting"][0],
        log.extras["cutting_source"][0],
        log.extras["policy_state"][0],
        log.extras["slew_limit_um_per_s"][0],
    ) == (1, "controller", "cutting", 1.0)


def test_cutting_values_match_bits_numbers_and_state_codes():
    from cnc_adapters.base import cutting_of
    from compensator.errors import BadValueError

    assert [cutting_of("x", r, (True,)) for r in (True, False, 1, 0, 1.0)] == [
        True,
        False,
        True,
        False,
        True,
    ]
    assert [cutting_of("x", r, (False,)) for r in (True, False, 0)] == [
        False,
        True,
        True,
    ]  # feed hold
    assert [cutting_of("x", r, (2, 3)) for r in (2, 3.0, 1, 5, True)] == [
        True,
        True,
        False,
        False,
        False,
    ]
    for bad in (1.5, "yes", None, float("nan")):
        with pytest.raises(BadValueError, match="cutting signal"):
            cutting_of("x", bad, (True,))


class FlakySpeed(SimAdapter):
    """The sim adapter whose speed cannot be read while ``failing`` is set (a bad speed node)."""

    failing = False

    def _read_speed_raw(self) -> float:
        if self.failing:
            raise AdapterError("sim: speed unreadable (test)")
        return super()._read_speed_raw()


def test_a_speed_not_read_never_opens_the_fast_limit(tmp_path, model_file):
    """Held, then assumed idle: the model cools as at rest, but nothing is known of the tool, so
    the offset moves at the cutting limit; when reads come back at the same speed it goes on
    slowly (the inference kept the last speed read, not the assumed 0)."""
    path = config(tmp_path, model_file, signal="speed")
    path.write_text(path.read_text() + "[spindle.faults]\nspeed_hold_s = 5.0\n")
    b = Bench(path, program=Program("steady", ((3600.0, 22500.0),)), adapter_cls=FlakySpeed)
    b.vm.load_program(b.program)
    rows = []
    for k in range(200):
        b.rt.adapter.failing = 100 <= k < 140
        b.t += 1.0
        rows.append(b.rt.cycle())
    unread = list(rows[100:140])
    assert all(r["alarms"] & Alarm.SPEED_READ_FAILED for r in unread)
    assert any(r["alarms"] & Alarm.IDLE_ASSUMED for r in unread)  # the model took it as at rest ...
    assert all(r["cutting"] and r["cutting_source"] == "unread" for r in unread)
    moved = [abs(b2["offset_um"] - a["offset_um"]) for a, b2 in itertools.pairwise(rows[99:])]
    assert max(moved) <= MAX_RATE * 1.0 + 1e-9  # ... but the offset crept, through and after it
    assert rows[140]["cutting"] and rows[140]["cutting_source"] == "speed"
