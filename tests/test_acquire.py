"""Displacement sensors over real serial links (socat pseudo-terminals, pymodbus's RTU server)
and the calibration recorder's fault handling, on the virtual spindle plant and a fake clock."""

from __future__ import annotations

import numpy as np
import pytest
from devices import LineDevice, ModbusDevice, PtyPair

from calibration.acquire import COLUMNS, AcquireConfig, Problem, Recorder
from calibration.nc_programs import calibration_profile
from cnc_adapters.base import AdapterTimeoutError, UnreachableError
from cnc_adapters.sensors import AsciiSensor, ModbusSensor, SensorOverRangeError, open_sensor
from compensator.errors import AcquisitionError
from compensator.io import RunLogAppender, read_run_log
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import VirtualMachine

MAX_RPM = 27000.0


class FakeClock:
    def __init__(self, t0: float = 1.7e9):
        self.t0 = self.t = t0

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.t += dt

    def sim(self) -> float:
        return self.t - self.t0


class Amplifier:
    """A virtual eddy-current amplifier: answers ``M`` with the plant's displacement, as
    ``+0012.345``; ``mode`` injects faults."""

    def __init__(self, vm: VirtualMachine):
        self.vm = vm
        self.mode = "ok"
        self.frozen: str | None = None
        self.bump_um = 0.0

    def __call__(self, text: str, _mode: str) -> str | None:
        if text != "M":
            return "ERR"
        if self.mode == "over":
            return "+OVER"
        reading = f"{self.vm.measured_um + self.bump_um:+09.3f}"
        if self.mode == "frozen":
            self.frozen = self.frozen or reading
            return self.frozen
        return reading


@pytest.fixture
def rig(tmp_path):
    clock = FakeClock()
    params = preset("motorized-27k")
    vm = VirtualMachine(SpindlePlant(params, seed=4), None, clock=clock.sim, plant_dt_s=1.0)
    pty = PtyPair(tmp_path)
    amp = Amplifier(vm)
    dev = LineDevice(pty.dev, amp)
    prog = calibration_profile(MAX_RPM, step_min=3, cooldown_min=15)
    vm.load_program(prog)
    yield clock, vm, pty, amp, prog, tmp_path
    dev.stop()
    pty.close()


def recorder(rig, *, on_sample=None, start_now=None, **cfg):
    clock, vm, pty, _amp, prog, tmp = rig
    ctl = SimAdapter(machine=vm)
    sensor = AsciiSensor(
        pty.ctl, request="M", timeout_s=0.5, range_um=(-500, 500), clock=clock, backoff_s=0.0
    )
    conf = AcquireConfig(rate_s=10.0, **cfg)
    return Recorder(
        ctl,
        sensor,
        tmp / "run.csv",
        prog,
        max_rpm=MAX_RPM,
        config=conf,
        clock=clock,
        sleep=clock.sleep,
        on_sample=on_sample,
        metadata={"spindle_id": "t"},
        wall=clock,
        start_now=start_now,
    )


def at(seconds: float, action):
    done = []

    def hook(sample, _rec):
        if not done and sample.time_s >= seconds:
            done.append(True)
            action()

    return hook


def test_clean_recording_matches_the_plant(rig):
    _clock, vm, *_ = rig
    rec = recorder(rig).run()
    assert rec.complete and rec.rows > 100 and not rec.flagged
    log = read_run_log(rec.path)
    assert list(log.extras)[:3] == list(COLUMNS[3:6])
    assert log.speed_rpm.max() == pytest.approx(MAX_RPM)
    # growth is counted from the cold start, and follows the plant's measurement
    assert log.elongation_um[0] == 0.0
    hist = vm.history()
    truth = np.interp(log.time_s, hist.time_s, hist.measured_um)  # one clock for both
    assert np.sqrt(np.mean((log.extras["sensor_um"] - truth) ** 2)) < 0.05
    assert log.elongation_um.max() > 10.0


def test_frozen_sensor_stops_with_a_clear_message_and_keeps_the_data(rig):
    _clock, _vm, _pty, amp, _prog, tmp = rig
    rec = recorder(rig, on_sample=at(1500, lambda: setattr(amp, "mode", "frozen")))
    with pytest.raises(
        AcquisitionError, match=r"sensor frozen at .* check the amplifier and cable"
    ):
        rec.run()
    log = read_run_log(tmp / "run.csv")
    assert log.time_s[-1] >= 1500 and np.all(np.diff(log.time_s) > 0)
    flags = log.extras["flags"].astype(int)
    assert (flags & Problem.FROZEN).any()
    assert not (flags[log.time_s < 1500] & Problem.FROZEN).any()
    kept = len(log)
    # fixed: the recording resumes into the same file and completes
    amp.mode = "ok"
    again = recorder(rig).run()
    assert again.complete and again.rows_before == kept
    full = read_run_log(tmp / "run.csv")
    assert len(full) == kept + again.rows and np.all(np.diff(full.time_s) > 0)
    assert full.elongation_um[0] == 0.0  # same cold reference after the resume


def test_saturated_sensor_stops_and_says_to_reset_the_gap(rig):
    _clock, _vm, _pty, amp, _prog, tmp = rig
    rec = recorder(rig, on_sample=at(900, lambda: setattr(amp, "mode", "over")))
    with pytest.raises(AcquisitionError, match=r"saturated.*re-set the probe gap"):
        rec.run()
    assert [e for e in rec.events if e.problem == Problem.SATURATED and e.begins]
    log = read_run_log(tmp / "run.csv")
    assert 850 <= log.time_s[-1] < 1000  # every good row is there


def test_unplugged_sensor_stops_keeps_the_data_and_resumes_when_plugged_back(rig):
    clock, _vm, pty, _amp, _prog, tmp = rig
    rec = recorder(rig, on_sample=at(1200, pty.unplug))
    with pytest.raises(AcquisitionError, match=r"no reading from the sensor for \d+ s .*unplugged"):
        rec.run()
    faults = [e for e in rec.events if e.problem == Problem.SENSOR_FAULT]
    assert faults and ("vanished" in faults[0].message or "cannot open" in faults[0].message)
    before = read_run_log(tmp / "run.csv")
    assert before.time_s[-1] >= 1190
    clock.sleep(600)  # ten minutes to find the cable
    pty.plug()
    again = recorder(rig).run()
    assert again.complete
    full = read_run_log(tmp / "run.csv")
    assert len(full) == len(before) + again.rows
    assert any(g.duration_s >= 600 for g in full.gaps)  # the interruption shows as a gap


def test_a_knocked_probe_is_flagged_as_a_jump_and_the_recording_goes_on(rig):
    _clock, _vm, _pty, amp, _prog, _tmp = rig
    rec = recorder(rig, on_sample=at(2000, lambda: setattr(amp, "bump_um", 40.0))).run()
    assert rec.complete
    jumps = [e for e in rec.events if e.problem == Problem.JUMP]
    assert len(jumps) == 1 and "+40" in jumps[0].message
    assert rec.flagged == {"JUMP": 1}


def test_a_spindle_that_does_not_follow_the_program_is_reported(rig):
    _clock, vm, _pty, _amp, _prog, _tmp = rig

    def override(sample, _rec):  # the operator turns the override knob for ten minutes
        vm.override_speed(2000.0 if 1000 <= sample.time_s < 1600 else None)

    out = recorder(rig, on_sample=override).run()
    told = [e for e in out.events if e.problem == Problem.NOT_FOLLOWING]
    assert told[0].begins and "2000 rpm where" in told[0].message
    assert not told[-1].begins  # and it says when the spindle follows again
    assert 30 <= out.flagged["NOT_FOLLOWING"] <= 60


def test_no_spindle_start_times_out(rig):
    _clock, vm, _pty, _amp, _prog, _tmp = rig
    vm.load_program(None)
    with pytest.raises(AcquisitionError, match="did not start within 300 s"):
        recorder(rig, start_timeout_s=300).run()


def test_appender_cuts_a_half_written_line(tmp_path):
    path = tmp_path / "log.csv"
    with RunLogAppender(path, ("time_s", "speed_rpm", "elongation_um")) as app:
        app.append((0.0, 0.0, 0.0))
        app.append((1.0, 100.0, 0.5))
    with open(path, "a") as fh:
        fh.write("2.0,100,0.")  # killed mid-write
    with RunLogAppender(path, ("time_s", "speed_rpm", "elongation_um")) as app:
        assert app.rows_before == 2 and app.last_row == (1.0, 100.0, 0.5)
        app.append((2.0, 100.0, 0.75))
    log = read_run_log(path)
    assert log.time_s.tolist() == [0.0, 1.0, 2.0]
    from compensator.errors import RunLogError

    with pytest.raises(RunLogError, match="differs"):
        RunLogAppender(path, ("time_s", "speed_rpm", "other"))


# -- the sensor adapters on their own ------------------------------------------------------


def test_ascii_sensor_polled_streaming_scaled_and_faults(tmp_path):
    import threading
    import time

    import serial

    pty = PtyPair(tmp_path)
    # a streaming amplifier: a reading in mm every 10 ms, no request
    halt = threading.Event()

    def stream():
        with serial.Serial(pty.dev, 115200, timeout=0.05) as ser:
            k = 0
            while not halt.is_set():
                ser.write(f"{0.012 + k * 1e-6:+.6f}\r\n".encode())
                k += 1
                time.sleep(0.01)

    th = threading.Thread(target=stream, daemon=True)
    th.start()
    try:
        # a gap probe reads less as the spindle grows: scale -1000 um/mm
        s = open_sensor(f"serial://{pty.ctl}?baudrate=115200&scale=-1000&offset_um=20")
        with s:
            a, b = s.read_um(), s.read_um()
        assert 7.0 < a < 8.1 and b <= a  # 20 - 12.0xx
        halt.set()
        th.join(2)
        quiet = AsciiSensor(pty.ctl, timeout_s=0.2)
        with quiet, pytest.raises(AdapterTimeoutError):
            quiet.read_um()
    finally:
        halt.set()
        pty.close()


def test_ascii_sensor_over_range_and_garbage(tmp_path):
    pty = PtyPair(tmp_path)
    replies = {"M": "+0012.500"}
    dev = LineDevice(pty.dev, lambda text, mode: replies.get(text, "ERR"))
    try:
        s = AsciiSensor(pty.ctl, request="M", range_um=(-100, 100))
        with s:
            assert s.read_um() == 12.5
            replies["M"] = "----"
            with pytest.raises(SensorOverRangeError):
                s.read_um()
            replies["M"] = "+0150.000"  # beyond the configured range
            with pytest.raises(SensorOverRangeError, match="outside its range"):
                s.read_um()
            replies["M"] = "hello"
            from cnc_adapters.base import BadValueError

            with pytest.raises(BadValueError, match="no reading"):
                s.read_um()
        pty.unplug()
        lost = AsciiSensor(pty.ctl, request="M")
        with pytest.raises(UnreachableError):
            lost.read_um()
    finally:
        dev.stop()
        pty.close()


def test_modbus_sensor_reads_an_input_register_and_its_overrange_code(tmp_path):
    pty = PtyPair(tmp_path)
    dev = ModbusDevice(pty.dev)
    try:
        dev.set_input(2, [-1234])  # int16 counts of 0.1 um
        s = open_sensor(
            f"serial://{pty.ctl}?protocol=modbus&baudrate=115200&register=2&type=int16"
            "&scale=0.1&saturated_raw=32767,-32768"
        )
        assert isinstance(s, ModbusSensor)
        with s:
            assert s.read_um() == pytest.approx(-123.4)
            dev.set_input(2, [32767])
            with pytest.raises(SensorOverRangeError, match="over-range code 32767"):
                s.read_um()
    finally:
        dev.close()
        pty.close()


def test_the_start_timeout_counts_wall_seconds_from_this_recording(rig):
    """A resumed recording waits its full time-out again (it used to count from the log's
    start and give up at once), and a simulated clock 100x faster than the wall does not
    shorten it."""
    clock, vm, pty, _amp, prog, tmp = rig
    vm.load_program(None)
    wall = lambda: (clock.t - clock.t0) / 100
    rows = []
    for _ in range(2):
        ctl = SimAdapter(machine=vm)
        sensor = AsciiSensor(
            pty.ctl, request="M", timeout_s=0.5, range_um=(-500, 500), clock=clock, backoff_s=0.0
        )
        rec = Recorder(
            ctl,
            sensor,
            tmp / "run.csv",
            prog,
            max_rpm=MAX_RPM,
            clock=clock,
            sleep=clock.sleep,
            config=AcquireConfig(rate_s=10.0, start_timeout_s=20),
            wall=wall,
            on_sample=lambda s, r: rows.append(s.time_s),
        )
        t0 = clock.t
        with pytest.raises(AcquisitionError, match="did not start within 20 s"):
            rec.run()
        assert clock.t - t0 == pytest.approx(2000, abs=20)  # 20 wall s = 2000 simulated s
    assert len(rows) >= 2 * 195


def test_a_start_by_hand_begins_the_program_clock(rig):
    """The operator's "start now" begins the program though the spindle has not turned yet
    (a program that opens with a rest); the event says so."""
    clock, vm, _pty, _amp, _prog, _tmp = rig
    vm.load_program(None)  # the spindle stays at rest: only the hand starts the clock
    t0 = clock.t
    pressed = lambda: clock.t - t0 >= 100
    rec = recorder(rig, start_now=pressed, start_timeout_s=1e6)
    events = []
    rec.on_event = events.append
    rec.should_stop = lambda: clock.t - t0 > 400
    with pytest.raises(KeyboardInterrupt):
        rec.run()
    started = [e for e in events if "started by hand" in e.message]
    assert len(started) == 1 and started[0].time_s == pytest.approx(100, abs=10)
