"""The fault suite, generated: faults drawn by hypothesis rather than listed, the invariants of
docs/FAULTS.md checked on every case.

- a spindle's runtime in lock-step on the virtual machine tool, each cycle with a drawn fault:
  a speed read that is anything a link can deliver (NaN, infinities, 4.29e9, negative, a
  failure), an outside write of any finite value to the held offset, a measurement of any value
  and sigma, a wall-clock step, a late or a hung write, a cycle period that jitters;
- random bytes in the configuration, the state file and a journal day file;
- any status (Good, Bad, Uncertain) on the speed, the cutting signal and the input nodes of an
  OPC UA controller.

Invariants: the offset written is finite, within the clamp and within the slew limit in wall time
(from the last write that took effect); the estimate is finite and within 10 mm; a cycle never
raises; every cycle has its journal row; a bad file is one ``ConfigError`` line or a cold start,
never another exception.

``THERMOCOMP_FAULT_EXAMPLES`` (default 25) sets the number of generated cases per class; the
long run (``THERMOCOMP_FAULT_EXAMPLES=2000``) is the nightly size.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cnc_adapters import AdapterError, AdapterTimeoutError
from compensator.errors import ConfigError
from compensator.io import Journal, load_state, read_run_log, save_model
from compensator.model import ThermalModel
from compensator.speed_programs import job_shop_day
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import VirtualMachine
from thermocomp.runtime import SpindleRuntime
from thermocomp.runtime.config import load_config

EXAMPLES = int(os.environ.get("THERMOCOMP_FAULT_EXAMPLES", "25"))
WALL0 = 1.77e9
CLAMP_UM, RATE, FAST = 40.0, 0.5, 5.0
TOLERANCE_UM = 0.5  # faults.offset_tolerance_um
SETTINGS = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=False,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

anything = st.floats(allow_nan=True, allow_infinity=True, width=64)
fault = st.one_of(
    st.tuples(st.just("none")),
    st.tuples(st.just("speed"), st.one_of(anything, st.just(4.294967295e9), st.floats(-3e4, 3e4))),
    st.tuples(st.just("speed_fails")),
    st.tuples(st.just("outside_write"), st.floats(-1e308, 1e308)),
    st.tuples(st.just("measure"), anything, anything),
    st.tuples(st.just("clock_step"), st.floats(-1e6, 1e6)),
    st.tuples(st.just("hung_write"), st.floats(0.0, 60.0)),
    st.tuples(st.just("late"), st.floats(0.0, 120.0)),
)


def model_file(directory: Path) -> Path:
    # tau 100 s, 2 um per krpm at steady state; with an observer
    path = directory / "model.json"
    if not path.exists():
        save_model(
            path,
            ThermalModel.from_discrete(
                0.99, (0.0, 0.02, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 24000.0)
            ),
        )
    return path


def config_text(directory: Path) -> str:
    return (
        "\n".join(
            [
                f'state_dir = "{directory / "state"}"',
                "watchdog = false",
                "journal_fsync_s = 3600.0",
                "[[spindle]]",
                'name = "s1"',
                f'model = "{model_file(directory)}"',
                "period_s = 1.0",
                'adapter = {url = "sim://"}',
                "[spindle.shaping]",
                f"max_offset_um = {CLAMP_UM}",
                f"max_rate_um_per_s = {RATE}",
                f"not_cutting_rate_um_per_s = {FAST}",
                "deadband_um = 0.0",
                "[spindle.observer]",
                "enabled = true",
                "[spindle.faults]",
                "speed_hold_s = 5.0",
            ]
        )
        + "\n"
    )


class Runtime:
    """The runtime on the virtual machine tool, lock-step; faults enter at the link's raw reads
    and writes (the adapter's own checks run on what they return)."""

    def __init__(self, directory: Path):
        directory.mkdir(parents=True, exist_ok=True)
        cfg_path = directory / "machine.toml"
        cfg_path.write_text(config_text(directory))
        cfg = load_config(cfg_path)
        self.t, self.skew = 0.0, 0.0
        self.vm = VirtualMachine(
            SpindlePlant(preset("motorized-27k"), seed=2), None, clock=lambda: self.t
        )
        self.vm.load_program(job_shop_day(preset("motorized-27k").max_rpm, seed=2, hours=2))
        self.adapter = SimAdapter(machine=self.vm)
        self.rt = SpindleRuntime(
            cfg.spindle[0],
            cfg.state_dir,
            cfg.journal_path,
            journal_fsync_s=cfg.journal_fsync_s,
            clock=lambda: self.t,
            wall=lambda: WALL0 + self.t + self.skew,
            adapter=self.adapter,
        )
        self.speed: list = []  # a value (or an exception) the next speed read returns
        self.hang_s = 0.0
        # (clock when the value took effect, the value, how far the runtime may take it to be):
        # its own writes, and outside writes (which it sees only beyond the mismatch tolerance)
        self.writes: list[tuple[float, float, float]] = []
        read_speed, write = self.adapter._read_speed_raw, self.adapter._write_offset_raw

        def speed_raw():
            if self.speed:
                v = self.speed.pop()
                if isinstance(v, Exception):
                    raise v
                return v
            return read_speed()

        def write_raw(value: float) -> None:
            self.t += self.hang_s  # a controller that hangs inside the write
            self.hang_s = 0.0
            write(value)
            self.writes.append((self.t, value, 0.0))

        self.adapter._read_speed_raw = speed_raw  # type: ignore[method-assign]
        self.adapter._write_offset_raw = write_raw  # type: ignore[method-assign]


@SETTINGS
@given(
    faults=st.lists(fault, min_size=5, max_size=60),
    dts=st.lists(st.floats(0.05, 3.0), min_size=60, max_size=60),
)
def test_no_fault_breaks_the_offset_or_the_record(tmp_path_factory, faults, dts):
    r = Runtime(tmp_path_factory.mktemp("prop"))
    rt = r.rt
    limit_rate = rt.cfg.shaping.rate_limit_um_per_s
    rows = 0
    try:
        for (kind, *args), dt in zip(faults * 2, dts):
            if kind == "speed":
                r.speed.append(args[0])
            elif kind == "speed_fails":
                r.speed.append(AdapterTimeoutError("sim: no answer"))
            elif kind == "outside_write":
                r.vm.offset_um = args[0]
                # from here the offset may move at the limit from what it holds (clamped)
                r.writes.append((r.t, min(max(args[0], -CLAMP_UM), CLAMP_UM), TOLERANCE_UM))
            elif kind == "measure":
                rt.submit(args[0], args[1])
            elif kind == "clock_step":
                r.skew += args[0]
            elif kind == "hung_write":
                r.hang_s = args[0]
            elif kind == "late":
                r.t += args[0]
            r.t += dt
            out = rt.cycle()  # never raises
            rows += 1
            assert math.isfinite(out["offset_um"]) and math.isfinite(out["predicted_um"])
            assert abs(rt.estimate_um()) <= 1e4
            if out["written"]:
                assert abs(out["offset_um"]) <= CLAMP_UM
    finally:
        rt.close()
    for (t0, a0, tol), (t1, a1, outside) in zip(r.writes, r.writes[1:]):
        if outside:
            continue
        assert abs(a1) <= CLAMP_UM
        assert abs(a1 - a0) <= limit_rate * (t1 - t0) + tol + 1e-9, (t0, t1, a0, a1)
    days = sorted(rt.journal.directory.glob("s1-*.csv"))
    assert sum(read_run_log(p).time_s.size for p in days) == rows  # no row lost
    state = load_state(rt.state_path)
    assert state is None or math.isfinite(state["elongation_um"])


@SETTINGS
@given(data=st.binary(max_size=2000), where=st.integers(0, 10_000))
def test_random_bytes_in_a_configuration_are_one_line_a_problem(tmp_path_factory, data, where):
    d = tmp_path_factory.mktemp("cfg")
    good = config_text(d).encode()
    k = where % (len(good) + 1)
    path = d / "machine.toml"
    path.write_bytes(good[:k] + data + good[k:])
    try:
        load_config(path)
    except ConfigError as err:
        # one line a problem (several bytes can make several), each naming the file
        lines = str(err).split("\n")
        assert str(err) and all(
            line.startswith(f"{path}: ") and line.isprintable() for line in lines
        ), str(err)


@SETTINGS
@given(data=st.binary(max_size=4000))
def test_random_bytes_in_the_state_file_are_a_cold_start(tmp_path_factory, data):
    d = tmp_path_factory.mktemp("state")
    (d / "state").mkdir()
    (d / "state" / "s1.state.json").write_bytes(data)
    r = Runtime(d)
    try:
        out = r.rt.cycle()
        assert math.isfinite(out["predicted_um"])
    finally:
        r.rt.close()


@SETTINGS
@given(tail=st.binary(max_size=3000), cut=st.integers(0, 5000))
def test_random_bytes_at_the_end_of_a_journal_day_lose_no_complete_row(tmp_path_factory, tail, cut):
    d = tmp_path_factory.mktemp("journal")
    j = Journal(d, "s1", {"spindle": "s1"})
    for k in range(20):
        j.write(
            WALL0 + k, 1000.0, 1.0, -1.0, True, 0, 0, dt_s=1.0, wall_s=WALL0 + k, now_s=float(k)
        )
    j.close()
    (path,) = d.glob("s1-*.csv")
    whole = path.read_bytes()
    data = whole[: len(whole) - cut % 200] + tail  # a power loss, then garbage
    path.write_bytes(data)
    # the rows of the file as written that are still whole in it (the garbage may complete one)
    common = next(
        (i for i, (a, b) in enumerate(zip(data, whole)) if a != b), min(len(data), len(whole))
    )
    kept = read_rows(whole[:common])
    j = Journal(d, "s1", {"spindle": "s1"})
    j.write(WALL0 + 100, 1000.0, 1.0, -1.0, True, 0, 0, dt_s=1.0, wall_s=WALL0 + 100, now_s=100.0)
    j.close()
    log = read_run_log(path)  # whatever the tail was, the day reads, with every complete row
    assert log.time_s.size >= kept + 1 and log.time_s[-1] == pytest.approx(WALL0 + 100)
    assert set(log.time_s[:-1]) <= {WALL0 + k for k in range(20)}  # no garbage taken as a row


def read_rows(data: bytes) -> int:
    """Complete rows (a line ended by a newline, after the column line) in a journal's bytes."""
    lines = data.split(b"\n")[:-1]
    body = [ln for ln in lines if ln.strip() and not ln.startswith(b"#")]
    return max(0, len(body) - 1)


def test_a_link_that_fails_every_read_leaves_the_service_alive(tmp_path):
    r = Runtime(tmp_path)
    try:
        for _ in range(30):
            r.speed.append(AdapterError("sim: broken"))
            r.t += 1.0
            out = r.rt.cycle()
            assert math.isfinite(out["offset_um"])
        assert r.rt.counters["cycles"] == 30
    finally:
        r.rt.close()


STATUSES = (
    "Good",
    "BadSensorFailure",
    "BadCommunicationError",
    "BadOutOfService",
    "UncertainLastUsableValue",
    "BadWaitingForInitialData",
)
NODES = ("act_speed", "cutting", "bearing_temp_c", "motor_temp_c")


@pytest.fixture(scope="module")
def lockstep_cnc():
    from cnc_adapters.opcua import OpcUaAdapter
    from compensator.clock import SteppedClock
    from machine_sim.vcnc import VirtualCNC, running, step

    clock = SteppedClock()
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=clock)
    with running(VirtualCNC(vm, tick_s=None)) as cnc:
        link = OpcUaAdapter(
            cnc.url,
            preset="virtual-cnc",
            cutting_node="ns={ns};s=/CncInterface/CncSpindleList/Spindle1/Cutting",
        )
        try:
            yield vm, cnc, link, (lambda: (clock.advance(1.0), step(cnc)))
        finally:
            link.close()


@SETTINGS
@given(
    statuses=st.tuples(*(st.sampled_from(STATUSES) for _ in NODES)), speed=st.floats(0.0, 24000.0)
)
def test_no_value_with_a_status_other_than_good_is_used(lockstep_cnc, statuses, speed):
    vm, cnc, link, tick = lockstep_cnc
    vm.override_speed(speed)
    cnc.failed.clear()
    cnc.failed.update({k: s for k, s in zip(NODES, statuses) if s != "Good"})
    tick()
    bad = set(cnc.failed)
    for _ in range(2):  # the first read of the cutting signal goes alone; then with the speed
        try:
            read = link.read_speed()
        except AdapterError as err:
            assert "act_speed" in bad, err
        else:
            assert "act_speed" not in bad and read == pytest.approx(
                abs(vm.speed_rpm)
            )  # as published
        try:
            link.read_cutting()
        except AdapterError:
            assert "cutting" in bad or "act_speed" in bad
    inputs = link.read_inputs()
    for name in ("bearing_temp_c", "motor_temp_c"):
        assert math.isfinite(inputs[name]) == (name not in bad)


@settings(
    max_examples=max(3, EXAMPLES // 8),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(hup=st.one_of(st.none(), st.floats(0.0, 0.5)), term=st.floats(0.0, 0.6))
def test_signals_at_any_moment_after_the_command_line_is_read(tmp_path_factory, hup, term):
    """`thermocomp run` in this process; another thread sends SIGHUP and SIGTERM at drawn
    moments from the instant `run` has read its command line (nothing in Python can come
    earlier). Whatever the moments: it stops with status 0, never killed by the signal, and
    reloads at most once."""
    import json
    import logging
    import signal
    import threading
    import time

    from thermocomp.cli import main

    d = tmp_path_factory.mktemp("signals")
    log_file = d / "log.jsonl"
    cfg = d / "machine.toml"
    cfg.write_text(
        f'log_file = "{log_file}"\n' + config_text(d).replace("period_s = 1.0", "period_s = 0.05")
    )
    root = logging.getLogger()
    saved_logging = (root.handlers[:], root.level, logging.raiseExceptions)
    sigs = (signal.SIGHUP, signal.SIGTERM, signal.SIGINT)
    saved = {s: signal.getsignal(s) for s in sigs}
    plan = sorted(([(hup, signal.SIGHUP)] if hup is not None else []) + [(term, signal.SIGTERM)])

    def sender() -> None:
        while signal.getsignal(signal.SIGHUP) is saved[signal.SIGHUP]:  # `run` not yet reading
            time.sleep(0.0005)
        t0 = time.monotonic()
        for at, sig in plan:
            time.sleep(max(0.0, t0 + at - time.monotonic()))
            os.kill(os.getpid(), sig)

    th = threading.Thread(target=sender, daemon=True)
    th.start()
    try:
        rc = main(["run", "--config", str(cfg)])
    finally:
        th.join(30)
        for s, h in saved.items():
            signal.signal(s, h)
        for h in root.handlers[:]:
            root.removeHandler(h)
            h.close()
        for h in saved_logging[0]:
            root.addHandler(h)
        root.setLevel(saved_logging[1])
        logging.raiseExceptions = saved_logging[2]
    assert rc == 0
    names = [
        json.loads(line).get("event") for line in log_file.read_text().splitlines() if line.strip()
    ]
    assert names.count("started") == 1 and names.count("reload") <= 1
    assert not any(n in ("reload_refused", "cycle_failed") for n in names)
