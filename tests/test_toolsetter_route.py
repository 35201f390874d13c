"""Calibration with the machine's tool setter alone: the NC program's probe stops, the virtual
machine running them, the recorder's sparse log, the probe-interval plan, and the route compared
with the eddy-current sensor on the same virtual spindle.

Everything runs in lock-step on simulated clocks (the recorder's sleep moves the machine on), so
no figure depends on how fast the computer is.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from devices import LineDevice, PtyPair

from calibration.acquire import AcquireConfig, Recorder
from calibration.fit import fit_logs
from calibration.nc_programs import (
    DIALECTS,
    FANUC_PROBE_NUMBER,
    PROBE_NAME,
    calibration_profile,
    probe_call,
    to_nc,
    validation_profile,
)
from calibration.probeprog import probe_cycle, probe_program
from calibration.toolsetter_plan import ASSUMED_TAU_S, plan_probe_interval
from cnc_adapters import open_adapter
from cnc_adapters.sensors import AsciiSensor
from compensator.clock import SteppedClock
from compensator.errors import ConfigError
from compensator.io import read_run_log
from compensator.speed_programs import Program
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.nc import parse_nc
from machine_sim.vcnc import ToolSetter, VirtualCNC, VirtualMachine, running, step

PRESET = "motorized-27k"
MAX_RPM = 27000.0
SEED = 4
DWELL_S = 20.0


class FakeClock:
    """Wall and simulated time in one: the machine's clock is this minus the start."""

    def __init__(self, t0: float = 1.7e9):
        self.t0 = self.t = t0

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.t += dt

    def sim(self) -> float:
        return self.t - self.t0


# -- the NC program ----------------------------------------------------------------------------


@pytest.mark.parametrize("dialect", DIALECTS)
def test_the_probe_stops_survive_the_nc_text_in_every_dialect(dialect):
    prog = calibration_profile(MAX_RPM, step_min=3, cooldown_min=15, probe_every_s=600)
    assert prog.probe_at_s == (600.0, 1200.0, 1800.0, 2400.0, 3000.0, prog.duration_s)
    text = to_nc(prog, dialect)
    call = {
        "fanuc": "M98 P1100",
        "sinumerik": 'CALL "TCPROBE"',
        "heidenhain": "CALL PGM TCPROBE",
        "linuxcnc": "o<tcprobe> call",
    }[dialect]
    calls = [ln for ln in text.splitlines() if re.sub(r"^\d+ ", "", ln) == call]
    assert len(calls) == len(prog.probe_at_s)
    run = parse_nc(text)
    assert run.segments == prog.segments and run.probe_at_s == prog.probe_at_s
    # the program starts the spindle again after each cycle (the cycle leaves it stopped)
    blocks = [
        b
        for b in (re.sub(r"^\d+ ", "", ln) for ln in text.splitlines())
        if not b.startswith(("(", ";"))
    ]
    after = [blocks[k + 1] for k, b in enumerate(blocks) if b == call]
    for p, nxt in zip(prog.probe_at_s, after):
        if p < prog.duration_s and prog.speed_at(p + 1) > 0:
            assert re.match(r"(S\d+ M0?3|TOOL CALL Z S\d+)$", nxt), (p, nxt)
    # without stops the text is what it always was
    plain = calibration_profile(MAX_RPM, step_min=3, cooldown_min=15)
    assert call not in to_nc(plain, dialect) and "PROBE IN PLACE" in to_nc(plain, dialect)


@pytest.mark.parametrize("dialect", DIALECTS)
def test_the_call_names_the_cycle_probe_program_writes(dialect):
    cycle = probe_program(
        probe_cycle(dialect, approach_z_mm=-5 if dialect == "heidenhain" else None)
    )
    head = cycle.splitlines()[1 if dialect == "fanuc" else 0]
    if dialect == "fanuc":
        assert (
            head.startswith(f"O{FANUC_PROBE_NUMBER} ")
            and probe_call(dialect) == f"M98 P{FANUC_PROBE_NUMBER}"
        )
    elif dialect == "sinumerik":
        assert head == f"%_N_{PROBE_NAME}_MPF" and probe_call(dialect) == f'CALL "{PROBE_NAME}"'
    elif dialect == "heidenhain":
        assert (
            head == f"0 BEGIN PGM {PROBE_NAME} MM"
            and probe_call(dialect) == f"CALL PGM {PROBE_NAME}"
        )
    else:  # the file tcprobe.ngc on the subroutine path
        assert probe_call(dialect) == f"o<{PROBE_NAME.lower()}> call"
    assert probe_call(dialect, "TCPRB2").lower().count("tcprb2") == (0 if dialect == "fanuc" else 1)


# -- the virtual machine runs it ------------------------------------------------------------------


def test_a_parsed_program_with_probe_calls_measures_at_its_program_times_over_opcua():
    prog = Program("steps", ((120.0, 12000.0), (120.0, 24000.0), (60.0, 0.0)), (90.0, 240.0, 300.0))
    run = parse_nc(to_nc(prog, "linuxcnc"))
    clock = SteppedClock()
    vm = VirtualMachine(
        SpindlePlant(preset(PRESET), seed=SEED),
        None,
        clock=clock,
        tool_setter=ToolSetter(dwell_s=DWELL_S, seed=SEED),
    )
    got = []
    with running(VirtualCNC(vm, tick_s=None)) as cnc:
        link = open_adapter({"type": "opcua", "url": cnc.url, "preset": "virtual-cnc"})
        try:
            step(cnc)
            assert link.read_measurement() is None  # the counter found at the first read is stale
            vm.load_program(run)
            while not vm.program_done:
                clock.advance(1.0)
                step(cnc)
                m = link.read_measurement()
                if m is not None:
                    got.append((clock(), m.elongation_um, vm.probe_true_um, link.read_speed()))
        finally:
            link.close()
    # the k-th cycle ends DWELL_S after its program time, the earlier cycles' time later
    assert [t for t, *_ in got] == [p + (k + 1) * DWELL_S for k, p in enumerate(run.probe_at_s)]
    assert all(abs(v - true) < 5 * 0.5 + 0.05 for _, v, true, _ in got)
    assert got[1][2] > got[0][2] > 0.1  # the spindle warms between the stops
    h = vm.history()
    for k, p in enumerate(run.probe_at_s):  # at rest 4 s into each cycle, to its end
        t0 = p + k * DWELL_S
        assert (h.speed_rpm[(h.time_s >= t0 + 5) & (h.time_s <= t0 + DWELL_S)] == 0.0).all()
    assert vm.program_done and clock() == run.duration_s + len(run.probe_at_s) * DWELL_S


# -- the recorder takes the tool setter -----------------------------------------------------------


def setter_recording(
    tmp_path,
    prog: Program,
    *,
    rate_s: float = 10.0,
    should_stop=None,
    vm=None,
    clock=None,
    at_speed: bool = False,
    name: str = "setter.csv",
    touches: int = 1,
):
    clock = clock or FakeClock()
    if vm is None:
        vm = VirtualMachine(
            SpindlePlant(preset(PRESET), seed=SEED),
            None,
            clock=clock.sim,
            plant_dt_s=1.0,
            tool_setter=ToolSetter(dwell_s=DWELL_S, seed=SEED, at_speed=at_speed, touches=touches),
        )
        vm.load_program(prog)
    rec = Recorder(
        SimAdapter(machine=vm),
        None,
        tmp_path / name,
        prog,
        max_rpm=MAX_RPM,
        config=AcquireConfig(rate_s=rate_s),
        clock=clock,
        sleep=clock.sleep,
        wall=clock,
        should_stop=should_stop,
        metadata={"spindle_id": "t"},
        at_speed=at_speed,
    )
    return rec, vm, clock


def test_the_tool_setter_recording_is_a_sparse_log_measured_at_rest(tmp_path):
    prog = parse_nc(
        to_nc(
            calibration_profile(MAX_RPM, step_min=3, cooldown_min=15, probe_every_s=300),
            "sinumerik",
        )
    )
    rec, vm, _clock = setter_recording(tmp_path, prog)
    result = rec.run()
    assert result.complete and result.measurements == len(prog.probe_at_s) == 12
    assert not result.flagged, result.events  # no "not following" while the program waits
    log = read_run_log(result.path)
    assert log.sparse and log.metadata["elongation_um"] == "sparse"
    assert int(log.measured.sum()) == 12
    assert (log.speed_rpm[log.measured] == 0.0).all()  # the cycle measures at rest
    assert (log.extras["commanded_rpm"][log.measured] == 0.0).all()
    # each value is the cycle's, taken at the end of its stop
    sim_t = log.time_s[log.measured]
    seqs = [e.message for e in result.events if e.message.startswith("tool setter")]
    assert len(seqs) == 12 and all("stop" in s for s in seqs)
    h = vm.history()
    at_rest = [h.true_um[np.flatnonzero((h.time_s <= t) & (h.speed_rpm == 0.0))[-1]] for t in sim_t]
    assert (
        np.max(np.abs(log.elongation_um[log.measured] - at_rest)) < 5 * 0.5 + 0.05
    )  # the setter's noise
    assert log.elongation_um[log.measured].max() > 5.0
    # the rest of every row as before: the speed followed, the controller's sensors beside
    assert np.isfinite(log.extras["bearing_temp_c"]).all()
    assert log.time_s[-1] == pytest.approx(prog.duration_s + 12 * DWELL_S, abs=10.0)


def test_a_laser_value_at_speed_keeps_the_speed_it_was_taken_at(tmp_path):
    """Four touches make a 23.6 s cycle, which ends between two 10 s polls: where the program
    has moved on to another speed by the poll that reads the value, the value goes on a row
    between the two at the speed held through the cycle, not on the new speed's row (whose
    growth at speed differs by up to 16 um)."""
    prog = parse_nc(
        to_nc(calibration_profile(MAX_RPM, step_min=6, cooldown_min=15, probe_every_s=120), "fanuc")
    )
    rec, vm, _clock = setter_recording(tmp_path, prog, at_speed=True, touches=4)
    assert vm.tool_setter.cycle_s == pytest.approx(23.6)
    held = []
    finish = vm._finish_probe

    def finish_and_note() -> None:  # the speed the cycle measured at, as it ends
        held.append(vm.speed_rpm)
        finish()

    vm._finish_probe = finish_and_note
    result = rec.run()
    assert result.complete and result.measurements == len(prog.probe_at_s) == len(held)
    log = read_run_log(result.path)
    np.testing.assert_allclose(log.speed_rpm[log.measured], held, atol=1.0)
    between = np.flatnonzero(
        log.measured & (np.abs(log.time_s - np.round(log.time_s / 10) * 10) > 1e-6)
    )
    assert (
        between.size >= 3
    )  # stops at a step's end, whose value came in after the program moved on
    assert (log.speed_rpm[between + 1] != log.speed_rpm[between]).all()


@pytest.mark.parametrize("stall_s", [250.0, 650.0], ids=["one-stop-late", "two-stops-in-one-stall"])
def test_a_recording_that_stalls_keeps_counting_the_stops_by_the_cycles_counter(tmp_path, stall_s):
    """The recording's computer stalls (an overloaded workstation, a virtual machine at 600x):
    the machine goes on through a stop, and perhaps the next, unobserved. The value that comes
    in late is still the stop's, and a counter that moved by two says a stop's value was missed:
    the recording goes on to the end instead of waiting forever for a stop already done."""
    prog = calibration_profile(MAX_RPM, step_min=3, cooldown_min=15, probe_every_s=300)
    clock = FakeClock()
    stalled = []

    def sleep(dt: float) -> None:  # once, past the third stop: a stall of stall_s
        if not stalled and clock.sim() > 3 * 300.0 + 100.0:
            stalled.append(clock.sim())
            dt += stall_s
        clock.sleep(dt)

    rec, vm, _ = setter_recording(tmp_path, prog, clock=clock)
    rec.sleep = sleep
    rec.cfg = rec.cfg.model_copy(update={"probe_timeout_s": 600.0})
    result = rec.run()
    assert stalled and result.complete, result.events
    missed = 1 if stall_s > 2 * (300.0 + DWELL_S) else 0
    assert rec.stops_done == len(prog.probe_at_s) == vm.probe_sequence
    assert result.measurements == len(prog.probe_at_s) - missed
    said = " / ".join(e.message for e in result.events)
    assert ("went by while the recording did not read" in said) == bool(missed), said


def test_a_tool_setter_recording_resumes_into_its_log_and_keeps_the_stops(tmp_path):
    prog = calibration_profile(MAX_RPM, step_min=3, cooldown_min=15, probe_every_s=300)
    clock = FakeClock()
    stop_at = clock.t + 1500.0
    rec, vm, clock = setter_recording(
        tmp_path, prog, clock=clock, should_stop=lambda: clock() > stop_at
    )
    with pytest.raises(KeyboardInterrupt):
        rec.run()
    kept = read_run_log(tmp_path / "setter.csv")
    done = int(kept.measured.sum())
    assert done == rec.stops_done >= 4
    again, *_ = setter_recording(tmp_path, prog, vm=vm, clock=clock)
    result = again.run()
    assert result.complete and not result.flagged, result.events
    assert result.measurements == len(prog.probe_at_s) - done
    assert int(read_run_log(tmp_path / "setter.csv").measured.sum()) == len(prog.probe_at_s)


def test_the_tool_setter_route_refuses_what_cannot_work(tmp_path):
    prog = calibration_profile(MAX_RPM, step_min=3, cooldown_min=15)
    vm = VirtualMachine(SpindlePlant(preset(PRESET), seed=SEED), prog, clock=lambda: 0.0)
    with pytest.raises(ConfigError, match="needs a program with probe stops"):
        Recorder(SimAdapter(machine=vm), None, tmp_path / "x.csv", prog, max_rpm=MAX_RPM)

    class Blind(SimAdapter):
        can_read_measurement = False

    stops = calibration_profile(MAX_RPM, step_min=3, cooldown_min=15, probe_every_s=300)
    with pytest.raises(ConfigError, match="reads no measurement"):
        Recorder(Blind(machine=vm), None, tmp_path / "x.csv", stops, max_rpm=MAX_RPM)


def test_a_stop_without_a_measurement_times_out_in_wall_seconds(tmp_path):
    prog = Program("one", ((120.0, 12000.0), (60.0, 0.0)), (60.0, 180.0))
    rec, vm, _clock = setter_recording(tmp_path, prog)
    vm.tool_setter = ToolSetter(dwell_s=10_000.0)  # a cycle that never ends: the setter alarmed
    with pytest.raises(Exception, match=r"no tool-setter measurement .* after probe stop 1/2"):
        rec.run()


# -- the plan -----------------------------------------------------------------------------------


def test_the_probe_interval_plan():
    p = plan_probe_interval(1200.0, 3600.0, 20.0)
    assert p.tau_assumed and p.fastest_tau_s == ASSUMED_TAU_S
    assert p.interval_s == 300.0 and p.bound == "tau"  # 10 min / 2 < 20 min / 3
    assert p.stops == 70 and p.added_s == 1400.0  # 350 min: 69 on the way, one at the end
    assert p.loss_per_stop == pytest.approx(1 - np.exp(-20 / 600))
    assert "assumed" in p.lines()[0] and len(p.lines()) == 3
    q = plan_probe_interval(360.0, 1800.0, 20.0, fastest_tau_s=1800.0)
    assert q.interval_s == 120.0 and q.bound == "step" and "former model" in q.lines()[0]
    assert plan_probe_interval(60.0, 0.0, 20.0).interval_s == 60.0  # never below a minute
    with pytest.raises(ValueError):
        plan_probe_interval(0.0, 0.0, 20.0)
    # a laser at speed loses nothing at a stop: as often as 20 s cycles add at most 20 %
    r = plan_probe_interval(1200.0, 3600.0, 20.0, at_speed=True)
    assert (
        r.interval_s == 120.0
        and r.bound == "overhead"
        and r.loss_per_stop == 0.0
        and r.stopped_share == 0.0
    )
    assert r.added_s / r.program_s <= 0.2
    assert "laser at speed" in r.lines()[0]
    assert plan_probe_interval(180.0, 0.0, 20.0, at_speed=True).bound == "step"  # already shorter
    assert (
        plan_probe_interval(1200.0, 3600.0, 90.0, at_speed=True).interval_s == 300.0
    )  # long cycles: tau
    # touches: a laser at speed fills its stops up to that 20 % (4 x 1.2 s more than one touch's
    # 20 s would pass it at 2 min: 3 more), and says what their mean gains
    t = plan_probe_interval(1200.0, 3600.0, 20.0, at_speed=True, touch_s=1.2)
    assert (
        t.interval_s == 120.0
        and t.touches == 4
        and t.touches_planned
        and t.cycle_s == pytest.approx(23.6)
    )
    assert t.added_s == pytest.approx(t.stops * 23.6) and t.added_s / t.program_s <= 0.2
    assert "4 touches averaged" in t.lines()[-1] and "0.50 of one touch's noise" in t.lines()[-1]
    # at rest one touch unless asked; asked, each touch lengthens the stop and its decay
    assert plan_probe_interval(1200.0, 3600.0, 20.0, touch_s=6.0).touches == 1
    a = plan_probe_interval(1200.0, 3600.0, 20.0, touches=3, touch_s=6.0)
    assert (
        a.touches == 3
        and not a.touches_planned
        and a.loss_per_stop == pytest.approx(1 - np.exp(-32 / 600))
    )
    assert "as asked" in a.lines()[-1]
    with pytest.raises(ValueError, match="touches"):
        plan_probe_interval(1200.0, 3600.0, 20.0, touches=11)


# -- the two routes on the same virtual spindle ---------------------------------------------------

STEP_MIN, COOLDOWN_MIN, RATE_S = 6.0, 30.0, 10.0


@pytest.fixture(scope="module")
def routes(tmp_path_factory):
    """The calibration program recorded on the same virtual spindle (preset, seed, cold start)
    with the eddy-current sensor (dense) and with the tool setter alone at the plan's interval
    (sparse); both fitted by ``fit_logs`` and run free over a held-out validation run."""
    tmp = tmp_path_factory.mktemp("routes")
    params = preset(PRESET)
    # (a) the eddy-current sensor, over a serial line, as in test_acquire
    clock = FakeClock()
    vm = VirtualMachine(SpindlePlant(params, seed=SEED), None, clock=clock.sim, plant_dt_s=1.0)
    prog = calibration_profile(MAX_RPM, step_min=STEP_MIN, cooldown_min=COOLDOWN_MIN)
    vm.load_program(prog)
    pty = PtyPair(tmp)
    dev = LineDevice(
        pty.dev, lambda text, _mode: f"{vm.measured_um:+09.3f}" if text == "M" else "ERR"
    )
    try:
        sensor = AsciiSensor(
            pty.ctl, request="M", timeout_s=0.5, range_um=(-500, 500), clock=clock, backoff_s=0.0
        )
        eddy = Recorder(
            SimAdapter(machine=vm),
            sensor,
            tmp / "eddy.csv",
            prog,
            max_rpm=MAX_RPM,
            config=AcquireConfig(rate_s=RATE_S),
            clock=clock,
            sleep=clock.sleep,
            wall=clock,
        ).run()
    finally:
        dev.stop()
        pty.close()
    eddy_fit = fit_logs([read_run_log(eddy.path)])
    # (b) the tool setter alone, every N from the plan (the eddy model is the "former model")
    plan = plan_probe_interval(
        STEP_MIN * 60, COOLDOWN_MIN * 60, DWELL_S, min(eddy_fit.model.time_constants_s())
    )
    probed = calibration_profile(
        MAX_RPM, step_min=STEP_MIN, cooldown_min=COOLDOWN_MIN, probe_every_s=plan.interval_s
    )
    nc = parse_nc(to_nc(probed, "fanuc"))
    rec, _vm, _clock = setter_recording(tmp, nc, rate_s=RATE_S)
    setter = rec.run()
    setter_fit = fit_logs([read_run_log(setter.path)])
    # (c) a laser setter measuring the turning gauge tool at the program's speed, at its own plan
    # it averages as many touches per stop as the plan fits in (the virtual setter's touch time)
    laser_plan = plan_probe_interval(
        STEP_MIN * 60,
        COOLDOWN_MIN * 60,
        DWELL_S,
        min(eddy_fit.model.time_constants_s()),
        at_speed=True,
        touch_s=ToolSetter().touch_s,
    )
    laser_nc = parse_nc(
        to_nc(
            calibration_profile(
                MAX_RPM,
                step_min=STEP_MIN,
                cooldown_min=COOLDOWN_MIN,
                probe_every_s=laser_plan.interval_s,
            ),
            "fanuc",
        )
    )
    laser_rec, _vm, _clock = setter_recording(
        tmp, laser_nc, rate_s=RATE_S, at_speed=True, name="laser.csv", touches=laser_plan.touches
    )
    laser = laser_rec.run()
    laser_log = read_run_log(laser.path)
    laser_fit = fit_logs([laser_log])
    # held out: the validation profile, free run, against the plant's true elongation
    t, cmd = validation_profile(MAX_RPM, seed=1).sample(RATE_S)
    plant = SpindlePlant(params, seed=SEED)
    truth = plant.run(t, cmd)
    elastic = np.array([plant.elastic_um(s) for s in truth.speed_rpm])

    def rms(e):
        return float(np.sqrt(np.mean(np.square(e))))

    pe = eddy_fit.model.simulate_um(truth.speed_rpm, t)
    ps = setter_fit.model.simulate_um(truth.speed_rpm, t)
    pl = laser_fit.model.simulate_um(truth.speed_rpm, t)
    rest = truth.speed_rpm < 1.0
    fig = {
        "eddy_rms_um": rms(pe - truth.true_um),
        "setter_rms_um": rms(ps - truth.true_um),
        "eddy_rest_rms_um": rms((pe - truth.true_um)[rest]),
        "setter_rest_rms_um": rms((ps - truth.true_um)[rest]),
        "setter_plus_elastic_rms_um": rms(ps + elastic - truth.true_um),
        "max_elastic_um": float(elastic.max()),
        "interval_min": plan.interval_s / 60,
        "stops": setter.measurements,
        "added_min": plan.added_s / 60,
        "eddy_model": eddy_fit.chosen.name,
        "setter_model": setter_fit.chosen.name,
        "setter_rows": setter.rows,
        "eddy_rows": eddy.rows,
        "plan": plan.lines(),
    }
    fig["ratio"] = fig["setter_rms_um"] / fig["eddy_rms_um"]
    fig["laser_rms_um"] = rms(pl - truth.true_um)
    fig["laser_ratio"] = fig["laser_rms_um"] / fig["eddy_rms_um"]
    fig["laser_model"] = laser_fit.chosen.name
    fig["laser_at_speed"] = int((laser_log.speed_rpm[laser_log.measured] > 1.0).sum())
    fig["laser_stops"], fig["laser_plan_stops"] = laser.measurements, laser_plan.stops
    fig["laser_touches"] = laser_plan.touches
    fig["thermal_ratio"] = fig["setter_plus_elastic_rms_um"] / fig["eddy_rms_um"]
    fig["eddy_report"], fig["eddy_expected"] = (
        eddy_fit.report(),
        eddy_fit.model.fit.get("expected_error"),
    )
    assert eddy.complete and setter.complete and not eddy.flagged and not setter.flagged
    assert setter.measurements == plan.stops
    return fig


def figures(f) -> str:
    return (
        f"held-out RMS: eddy {f['eddy_rms_um']:.2f} um ({f['eddy_model']}), tool setter "
        f"{f['setter_rms_um']:.2f} um ({f['setter_model']}), ratio {f['ratio']:.2f}; at rest "
        f"{f['eddy_rest_rms_um']:.2f} vs {f['setter_rest_rms_um']:.2f} um; tool setter + the plant's elastic "
        f"term {f['setter_plus_elastic_rms_um']:.2f} um (ratio {f['thermal_ratio']:.2f}, elastic up to "
        f"{f['max_elastic_um']:.1f} um); every {f['interval_min']:.0f} min, {f['stops']} stops, "
        f"+{f['added_min']:.1f} min; " + " / ".join(f["plan"])
    )


def test_the_tool_setter_route_identifies_the_thermal_growth_as_well_as_the_eddy_sensor(routes):
    f = routes
    # what a standstill measurement can see, it learns: with the elastic growth it cannot see
    # put back, its held-out error is within 1.5x of the eddy-current model's, or within the
    # setter's repeatability when the eddy-current model is better than a sparse measurement can judge
    print(figures(f))
    assert f["setter_plus_elastic_rms_um"] <= max(1.5 * f["eddy_rms_um"], ToolSetter().noise_um), (
        figures(f)
    )
    assert f["setter_rest_rms_um"] < 1.0, figures(f)
    assert f["stops"] >= 3 * 9, figures(f)  # at least 3 per staircase step


def test_a_laser_setter_at_speed_sees_the_growth_at_speed(routes):
    """Measured turning at the program's speed, the tool setter sees the growth that exists only
    while the spindle turns: with the same stops, its model's full held-out error is under half
    the contact setter's at rest, and within 1.5x of the eddy-current model's or within the
    setter's own repeatability, whichever is larger (an eddy-current model under the setter's
    noise is a bar no sparse measurement can reach). docs/benchmarks.md has the figures over seeds
    and step lengths."""
    f = routes
    print(
        figures(f)
        + f"; laser at speed {f['laser_rms_um']:.2f} um ({f['laser_model']}), ratio {f['laser_ratio']:.2f}"
    )
    assert (
        f["laser_stops"] == f["laser_plan_stops"] >= f["stops"]
        and f["laser_at_speed"] >= 0.5 * f["laser_stops"]
    )
    assert f["laser_touches"] > 1  # its stops average several touches
    assert f["laser_rms_um"] < 0.5 * f["setter_rms_um"], (f["laser_rms_um"], f["setter_rms_um"])
    assert f["laser_rms_um"] <= max(1.5 * f["eddy_rms_um"], ToolSetter().noise_um), figures(f)


def test_within_one_cycle_the_error_to_expect_is_the_held_out_figure(routes):
    """One calibration cycle is scored on blocks of it, each at speeds the others do not run: a
    block predicted forward is an extrapolation in speed that the model, fitted on every block,
    never makes. The forward figure is shown, but neither the choice nor the error to expect reads it."""
    rep, expected = routes["eddy_report"], routes["eddy_expected"]
    assert rep["forward_decides"] is False and rep["scored_by"].startswith("blocked")
    chosen = next(c for c in rep["candidates"] if c["name"] == rep["chosen"])
    assert (
        chosen["forward_rms_um"] is not None
        and chosen["decisive_rms_um"] == chosen["honest_rms_um"]
    )
    bands = expected["bands"]
    assert bands and {b["source"] for b in bands} == {"held out"} and expected["forward_folds"] == 0
    assert max(b["rms_um"] for b in bands) < 5 * chosen["honest_rms_um"]


@pytest.mark.xfail(
    strict=True,
    reason="a tool setter measures at rest and never sees the elastic "
    "(centrifugal, preload) growth the spindle shows at speed: up to 16 um at 27 000 rpm "
    "on this plant; docs/PROBING.md, 'Assumptions of every cycle'",
)
def test_the_tool_setter_models_full_error_is_within_1_5x_of_the_eddy_models(routes):
    assert routes["ratio"] <= 1.5, figures(routes)
