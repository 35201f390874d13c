"""Bounds on what measurements can do: the observer's correction (the estimate minus the model's
free run) never leaves ``max_correction_um``, and one source moves it by at most
``max_source_move_um`` per ``source_window_s``. A client on the control socket (a real socket,
the whole service) and a probe cycle through the controller's nodes (a real OPC UA server) that
each send 300 measurements 3 um below the estimate, every one against the estimate the last one
left, cannot take the estimate further than the bound from the model; honest measurements of a
real drift are followed as before. Everything runs on fake clocks."""

from __future__ import annotations

import json
import logging
import socket
from pathlib import Path

import numpy as np
import pytest

from compensator.errors import ModelError
from compensator.estimate import Estimate
from compensator.fusion import FusedPredictor, observer_config_of
from compensator.io import save_model
from compensator.model import ThermalModel
from compensator.observer import ObserverConfig, ObserverState, measurement_update, time_update
from thermocomp.runtime import Alarm, Service, SpindleRuntime
from thermocomp.runtime.config import load_config
from thermocomp.runtime.control import SOCKET_NAME

WALL0 = 1.7e9
SPEED = 7500.0  # the model's steady state there: 15 um; at the top of its range (15 000): 30 um
ATTACKS = 300
BELOW_UM = 3.0


def thirty_um_model() -> ThermalModel:
    # tau 100 s, 2 um per krpm: 30 um at the top of the calibrated range, as in the report
    return ThermalModel.from_discrete(
        0.99, (0.0, 0.02, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 15000.0)
    )


@pytest.fixture(scope="module")
def model_file(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("bounds") / "model.json"
    save_model(p, thirty_um_model())
    return p


def write_config(directory: Path, model: Path, adapter: str, observer: str = "") -> Path:
    lines = [
        f'state_dir = "{directory / "state"}"',
        "watchdog = false",
        "journal_fsync_s = 3600.0",
        "[[spindle]]",
        'name = "s1"',
        f'model = "{model}"',
        "period_s = 0.1",
        "state_save_every_s = 600.0",
        f"adapter = {adapter}",
        "[spindle.shaping]",
        "max_offset_um = 300.0\nmax_rate_um_per_s = 1000.0\ndeadband_um = 0.0",
        "[spindle.observer]",
        "enabled = true",
        observer,
    ]
    directory.mkdir(parents=True, exist_ok=True)
    p = directory / "machine.toml"
    p.write_text("\n".join(lines) + "\n")
    return p


def events(caplog, name: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if getattr(r, "event", None) == name]


def measurement_rows(state_dir: Path) -> list[list[str]]:
    rows: list[list[str]] = []
    for path in sorted((state_dir / "journal").glob("s1.measurements-*.csv")):
        lines = [x for x in path.read_text().splitlines() if x and not x.startswith("#")]
        rows += [x.split(",") for x in lines[1:]]
    return rows


# -- the attack through the control socket: the whole service, a real Unix socket ---------------


class SocketAttack:
    """The service on a fake clock with the virtual machine tool at ``SPEED``; a client sends
    each measurement 3 um below the estimate the answer to the last one gave."""

    def __init__(self, directory: Path, model: Path, observer: str = ""):
        self.t = 0.0
        cfg = write_config(directory, model, '{url = "sim://?program="}', observer)
        self.state_dir = directory / "state"
        self.svc = Service(cfg, clock=lambda: self.t, wall=lambda: WALL0 + self.t)
        self.rt: SpindleRuntime = self.svc.spindles["s1"]
        self.rt.adapter.machine.override_speed(SPEED)  # type: ignore[attr-defined]
        self.path = self.state_dir / SOCKET_NAME

    def tick(self) -> None:
        self.t += 0.1
        self.svc.tick()

    def ask(self, um: float) -> dict:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(30)  # a safety net only: the answer is there when tick() returns
            s.connect(str(self.path))
            s.sendall(json.dumps({"elongation_um": um, "sigma_um": 0.5}).encode() + b"\n")
            self.tick()
            return json.loads(s.makefile("rb").readline())

    def warm(self, seconds: float = 300.0) -> None:
        """300 s at speed: the estimate near the model's 15 um; shorter where any start will do
        (the attack is relative to the estimate)."""
        for _ in range(round(seconds / 0.1)):
            self.tick()

    def run(self, probe_too: bool = False) -> dict:
        """The attack: ``ATTACKS`` measurements through the socket, each 3 um below the estimate
        the last answer gave; with ``probe_too`` the controller's probe nodes (the sim link's)
        send the same at once, another source."""
        start, t0 = self.rt.estimate_um(), self.t
        estimates, biases, alarms = [start], [self.rt.est.bias_um], Alarm.NONE
        machine = self.rt.adapter.machine  # type: ignore[attr-defined]
        for _ in range(ATTACKS):  # ten a second: 30 s
            if probe_too:
                machine.probe_value_um = estimates[-1] - BELOW_UM
                machine.probe_sigma_um = 0.5
                machine.probe_sequence += 1
            answer = self.ask(estimates[-1] - BELOW_UM)
            assert answer["ok"], answer
            estimates.append(self.rt.estimate_um())
            biases.append(self.rt.est.bias_um)
            alarms |= self.rt.alarms
        self.rt.measurements.flush(self.t)
        c = self.rt.counters
        return {
            "start": start,
            "t0": t0,
            "model_um": self.rt.estimate_um() - self.rt.est.bias_um,
            "min": min(estimates),
            "end": estimates[-1],
            "min_correction": min(biases),
            "correction": biases[-1],
            "accepted": c["probes_accepted"],
            "restarted": c["probes_restarted"],
            "rejected": c["probes_rejected"],
            "limited": c.get("probes_limited", 0),
            "alarms": alarms,
            "offset": self.rt.offset.held_um,
        }

    def close(self) -> None:
        self.svc.close()


def test_a_client_on_the_control_socket_cannot_run_the_estimate_away(tmp_path, model_file, caplog):
    """Before the bounds: the estimate went from 14.3 to -387.5 um in the 30 s (100 accepted,
    101 restarts), the offset to its clamp. Now the socket moves the correction by its 7.5 um."""
    rig = SocketAttack(tmp_path, model_file)
    try:
        rig.warm()
        with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
            got = rig.run()
        cfg = rig.rt.estimate.fused.config  # type: ignore[union-attr]
        status = rig.rt.observer_status()
        line = rig.svc.status_text()
    finally:
        rig.close()
    print("socket attack:", got)
    assert got["start"] == pytest.approx(14.3, abs=0.5)
    # the defaults: half the model's 30 um steady growth; one source half of that per hour
    assert cfg.max_correction_um == pytest.approx(15.0) and cfg.source_move_um == pytest.approx(7.5)
    # 7.5 um at once, and 7.5 um per hour after: 0.0625 um in these 30 s
    drained = 7.5 * (rig.t - got["t0"]) / 3600.0
    assert got["min_correction"] >= -7.5 - drained - 1e-9  # was -401.96 um
    assert got["correction"] == pytest.approx(-7.5 - drained, abs=0.01)  # all it may
    assert got["min"] >= got["start"] - 7.5 - 1e-6 and got["min"] > 0  # was -387.5 um
    assert got["offset"] == pytest.approx(-got["end"], abs=1e-6)  # the offset followed, no further
    assert got["alarms"] & Alarm.OBSERVER_BOUND
    assert got["limited"] > 250 and got["accepted"] + got["restarted"] < 10
    assert got["accepted"] + got["restarted"] + got["limited"] + got["rejected"] == ATTACKS
    (raised,) = events(caplog, "observer_bound")  # once, on entry
    assert raised.fields["max_source_move_um"] == pytest.approx(7.5)
    cut = events(caplog, "probe_limited")
    assert len(cut) == got["limited"] and {r.fields["source"] for r in cut} == {"control"}
    assert all(r.fields["limited"] == "source" for r in cut)
    assert status is not None and status["bounded"] and not status["at_bound"]
    assert status["limited"] == {"control": got["limited"]}
    assert status["limited_sources"] == {"control": "source"}
    assert "OBSERVER_BOUND" in line
    outcomes = [r[5] for r in measurement_rows(rig.state_dir)]
    assert len(outcomes) == ATTACKS and outcomes.count("limited") == got["limited"]


def test_two_sources_together_stop_at_the_bound_of_the_correction(tmp_path, model_file, caplog):
    """The socket and the controller's probe nodes, each 7.5 um: together they reach the 15 um
    bound, and no further."""
    rig = SocketAttack(tmp_path, model_file)
    try:
        rig.warm(60.0)
        with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
            got = rig.run(probe_too=True)
        status = rig.rt.observer_status()
        moved = dict(rig.rt.est.core.observer.moved_um)
    finally:
        rig.close()
    print("two sources:", got)
    assert got["min_correction"] >= -15.0 - 1e-9
    assert got["correction"] == pytest.approx(-15.0)
    assert moved.keys() == {"control", "sim"} and sum(moved.values()) == pytest.approx(
        -15.0, abs=0.2
    )
    assert all(-7.5 - 1e-9 <= m < -7.0 for m in moved.values())
    assert (
        status is not None
        and status["at_bound"]
        and status["max_correction_um"] == pytest.approx(15.0)
    )
    (raised,) = events(caplog, "observer_bound")
    assert raised.fields["max_correction_um"] == pytest.approx(15.0)
    assert {r.fields["limited"] for r in events(caplog, "probe_limited")} == {"source", "bound"}


# -- the attack through the controller's probe nodes: a real OPC UA server --------------------


def test_a_probe_cycle_drifting_through_the_controllers_nodes_is_bounded_too(
    tmp_path, model_file, caplog
):
    from cnc_adapters.opcua import OpcUaAdapter
    from machine_sim import SpindlePlant, preset
    from machine_sim.vcnc import VirtualCNC, VirtualMachine, call, running

    t = [0.0]
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=1), None, clock=lambda: t[0])
    vm.override_speed(SPEED)
    cfg = load_config(write_config(tmp_path, model_file, '{url = "sim://"}'))
    with running(VirtualCNC(vm)) as cnc:
        link = OpcUaAdapter(cnc.url, preset="virtual-cnc", timeout_s=5.0)
        rt = SpindleRuntime(
            cfg.spindle[0],
            cfg.state_dir,
            cfg.journal_path,
            clock=lambda: t[0],
            wall=lambda: WALL0 + t[0],
            adapter=link,
        )
        try:

            def cycle() -> None:
                t[0] += 0.1
                call(cnc, cnc.tick)  # the virtual CNC publishes, then the runtime reads
                rt.cycle()

            for _ in range(600):  # a minute warm: any start will do, the attack is relative
                t[0] += 0.1
                rt.cycle()
            start = rt.estimate_um()
            model_um = start - rt.est.bias_um
            estimates, alarms = [start], Alarm.NONE
            with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
                for _ in range(ATTACKS):
                    # the NC program's probe cycle writes a value 3 um below the estimate
                    vm.probe_value_um = estimates[-1] - BELOW_UM
                    vm.probe_sigma_um = 0.5
                    vm.probe_sequence += 1
                    cycle()
                    estimates.append(rt.estimate_um())
                    alarms |= rt.alarms
            bound = getattr(rt.estimate.fused.config, "max_correction_um", None)  # type: ignore[union-attr]
            taken = rt.counters["probes_accepted"] + rt.counters["probes_restarted"]
            limited = rt.counters.get("probes_limited", 0)
        finally:
            rt.close()
    print("probe attack:", start, model_um, min(estimates), taken, limited, alarms)
    assert taken + limited + rt.counters["probes_rejected"] == ATTACKS  # each one read once
    assert min(estimates) >= model_um - bound - 1e-6
    assert alarms & Alarm.OBSERVER_BOUND
    sources = {r.fields["source"] for r in events(caplog, "probe_limited")}
    assert sources == {"opcua"}


# -- honest measurements of a real drift are followed as before -------------------------------


def test_honest_measurements_of_a_real_drift_are_followed_as_without_bounds(
    tmp_path, calibrated_model, computed_once
):
    """test_closed_loop's day: eight hours of a job shop while the hall warms 1 K/h (which the
    calibration never saw), the tool setter every 30 min; with the default bounds (the day
    test_closed_loop runs, made once) and without."""
    from test_closed_loop import drift_day, fused_day

    day, model = fused_day(computed_once, calibrated_model)
    t, est, rows = day.t, day.est, day.rows
    free = drift_day(
        tmp_path / "free",
        model,
        enabled=True,
        observer="max_correction_um = 1000.0\nmax_source_move_um = 1000.0",
    )
    assert day.max_correction_um is not None and day.source_move_um is not None
    assert free.max_correction_um == 1000.0  # the free day's bounds are out of reach
    bias = np.array([float(r["bias_um"]) for r in rows])
    hour = np.minimum((t // 3600).astype(int), 7)
    by_hour = [float(np.sqrt(np.mean(est[hour == k] ** 2))) for k in range(8)]
    late = t > 6 * 3600.0
    print(
        f"bound {day.max_correction_um:.2f} um, source {day.source_move_um:.2f} um/h; bias "
        f"{bias.min():+.2f}..{bias.max():+.2f} um; rms by hour {np.round(by_hour, 3).tolist()}; "
        f"max |est| after the first probe {np.abs(est[t > 1830.0]).max():.3f} um; "
        f"tip rms late {np.sqrt(np.mean(day.tip[late] ** 2)):.3f} um"
    )
    # the defaults leave the day's measurements alone: every one taken whole, the same estimate
    assert {r["outcome"] for r in rows} == {"accepted"} and len(rows) >= 15
    assert [r["outcome"] for r in free.rows] == [r["outcome"] for r in rows]
    assert np.array_equal(est, free.est)
    assert not any(a & Alarm.OBSERVER_BOUND for a in day.alarms)
    assert np.abs(bias).max() < day.max_correction_um / 2  # far from the bound
    # the closed loop's figures (test_closed_loop): 1.18 um worst hour, 2.63 um worst after
    assert max(by_hour) < 1.5 and np.abs(est[t > 1830.0]).max() < 3.0


# -- the pure core: the same bounds in replay, the service's state, the configuration ----------


def test_replay_runs_the_same_bounds():
    """Estimate.run (what `thermocomp replay` runs) over a source that says, every second for
    five minutes, that the spindle is 40 um shorter than the model: the correction stays within
    the source's move, two sources within the bound, and the outcomes say which were cut."""
    model = thirty_um_model()
    est = Estimate(model, observer_config_of(model))
    n = 400
    time_s = np.arange(n) * 1.0
    speed = np.full(n, SPEED)
    st = est.begin(model.steady_state_um(SPEED), SPEED)
    liar = model.steady_state_um(SPEED) - 40.0
    honest = [(50, model.steady_state_um(SPEED), 0.5, "probe")]  # the observer's first: whole
    probes = honest + [(k, liar, 0.5, "probe") for k in range(100, 400)]
    series = est.run(st, time_s, speed, probes=probes)
    correction = series.estimate_um - series.model_um
    assert correction.min() >= -7.5 - 7.5 * 300.0 / 3600.0 - 1e-9  # drained 7.5 um/h meanwhile
    assert correction[-1] < -7.5 and series.outcomes.count("limited") > 100
    wide = ObserverConfig(max_correction_um=1000.0, max_source_move_um=1000.0)
    free = Estimate(model, wide).run(st, time_s, speed, probes=probes)
    assert (free.estimate_um - free.model_um)[-1] == pytest.approx(-40.0, abs=0.5)
    # two sources: each its own move, together the bound
    both = [*probes, *((k, y, s, "socket") for k, y, s, _ in probes[1:])]
    series2 = est.run(st, time_s, speed, probes=sorted(both, key=lambda p: p[0]))
    assert (series2.estimate_um - series2.model_um).min() == pytest.approx(-15.0, abs=1e-9)


def bounded_cfg(**kw) -> ObserverConfig:
    return ObserverConfig(max_correction_um=10.0, **kw)


def test_a_sources_move_drains_at_its_rate_and_noise_costs_nothing():
    cfg = bounded_cfg(source_window_s=3600.0)  # 5 um per hour per source
    assert cfg.source_move_um == 5.0 and cfg.window_s == 3600.0
    z = ObserverState.prior(cfg)
    up = measurement_update(cfg, z, 20.0, 0.0, 0.5, "setter")
    assert up.limited == "source" and up.state.bias_um == pytest.approx(5.0)
    assert up.wanted_bias_um == pytest.approx(20.0, abs=0.1) and up.outcome == "limited"
    assert up.state.cov == z.cov  # its information not taken
    # another source has its own move, up to the bound
    up2 = measurement_update(cfg, up.state, 20.0, 0.0, 0.5, "socket")
    assert up2.state.bias_um == pytest.approx(10.0) and up2.limited == "source"
    up3 = measurement_update(cfg, up2.state, 20.0, 0.0, 0.5, "third")
    assert up3.state.bias_um == pytest.approx(10.0) and up3.limited == "bound"
    # half an hour later the setter may move 2.5 um again; an hour later 5
    half = time_update(cfg, up.state, 1800.0)
    assert half.moved_by("setter") == pytest.approx(2.5)
    again = measurement_update(cfg, half, 20.0, 0.0, 0.5, "setter")
    assert again.state.bias_um == pytest.approx(7.5)
    assert time_update(cfg, up.state, 3600.0).moved_um == ()  # drained: forgotten
    # moves that cancel cost nothing: +/- noise from one source is followed whole
    z = ObserverState.prior(cfg)
    for k in range(200):
        z = time_update(cfg, z, 1.0)
        up = measurement_update(cfg, z, 1.5 if k % 2 else -1.5, 0.0, 0.5, "setter")
        assert up.limited is None, k
        z = up.state
    assert abs(z.moved_by("setter")) < 5.0


def test_the_bound_holds_against_a_restart_and_a_drift_rate_and_lets_a_correction_back_in():
    cfg = bounded_cfg(max_source_move_um=100.0, drift_q_um2_per_s3=1e-6)
    z = ObserverState.prior(cfg)
    # two agreeing refusals far out restart the bias: at the bound only
    z = measurement_update(cfg, z, 5.0, 0.0, 0.5).state
    ups = []
    for _ in range(3):
        z = time_update(cfg, z, 1.0)
        ups.append(measurement_update(cfg, z, 60.0, 0.0, 0.5))
        z = ups[-1].state
    assert [u.outcome for u in ups] == ["rejected", "limited", "limited"]  # each a restart, cut
    assert ups[1].restarted and ups[1].limited == "bound" and z.bias_um == pytest.approx(10.0)
    # a drift rate carries it no further, and stops there
    pushed = ObserverState(9.0, 0.01, z.cov)
    later = time_update(cfg, pushed, 1000.0)
    assert later.bias_um == pytest.approx(10.0) and later.drift_um_per_s == 0.0
    # a correction beyond the bound already (a wider setting before) is not cut, only let back
    outside = ObserverState(25.0, 0.0, ((1.0, 0.0), (0.0, 0.0)))
    out = measurement_update(cfg, outside, 30.0, 0.0, 0.5)
    assert out.state.bias_um == pytest.approx(25.0) and out.limited == "bound"
    back = measurement_update(cfg, outside, 24.0, 0.0, 0.5)
    assert back.limited is None and back.state.bias_um < 25.0
    across = measurement_update(
        cfg, ObserverState(25.0, 0.0, ((1e4, 0.0), (0.0, 0.0))), -40.0, 0.0, 0.5
    )
    assert across.state.bias_um == pytest.approx(-10.0) and across.limited == "bound"
    # unbounded (None) as the calibration's own fits use it: the filter alone
    free = measurement_update(
        ObserverConfig(), ObserverState.prior(ObserverConfig()), 50.0, 0.0, 0.5
    )
    assert free.limited is None and free.state.bias_um == pytest.approx(50.0, abs=0.1)


def test_the_default_bound_comes_from_the_model_and_has_a_floor():
    fused = FusedPredictor(thirty_um_model(), ObserverConfig())
    assert fused.config.max_correction_um == pytest.approx(15.0)
    assert fused.config.source_move_um == pytest.approx(7.5)
    small = ThermalModel.from_discrete(
        0.99, (0.0, 0.001, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 15000.0)
    )
    assert FusedPredictor(small, ObserverConfig()).config.max_correction_um == 10.0
    given = FusedPredictor(thirty_um_model(), ObserverConfig(max_correction_um=4.0))
    assert given.config.max_correction_um == 4.0 and given.config.source_move_um == 2.0
    assert any("observer bounds" in line for line in fused.describe())


def test_the_sources_moves_are_saved_and_a_state_saved_before_them_loads():
    fused = FusedPredictor(thirty_um_model(), ObserverConfig())
    st = fused.start(0.0, 0.0)
    st, _ = fused.measure(st, 0.0, 0.5, source="control")  # the first, taken whole
    for _ in range(2):  # two agreeing refusals: the bias restarts, as far as the source may
        st, up = fused.measure(st, 20.0, 0.5, source="control")
    assert up.limited == "source"
    saved = json.loads(json.dumps(fused.state_dict(st)))
    back = fused.state_from_dict(saved)
    assert back.observer.moved_um == (("control", pytest.approx(7.5)),)
    del saved["observer"]["moved_um"]
    assert fused.state_from_dict(saved).observer.moved_um == ()
    saved["observer"]["moved_um"] = {"control": "a lot"}
    with pytest.raises(ModelError, match="observer"):
        fused.state_from_dict(saved)


def test_a_fit_record_written_before_the_bounds_dumps_as_it_was_read():
    from compensator.fitrecord import FitRecord

    stored = {"bias_q_um2_per_s": 0.1, "drift_q_um2_per_s3": 0.0, "model_sd_um": 0.2}
    stored |= {"gate_sigma": 5.0, "initial_bias_sd_um": 30.0, "reaccept_after": 2}
    assert FitRecord.of({"observer": stored}).as_dict() == {"observer": stored}
    with_bound = ObserverConfig(**stored, max_correction_um=12.0)
    assert with_bound.model_dump()["max_correction_um"] == 12.0


@pytest.mark.parametrize(
    "line,match",
    [
        ("max_correction_um = 0.0", "max_correction_um"),
        ("max_correction_um = 5000.0", "max_correction_um"),
        ("max_source_move_um = -1.0", "max_source_move_um"),
        ("source_window_s = 0", "source_window_s"),
        ("max_correction = 10.0", "max_correction"),
    ],
)
def test_bad_bounds_are_one_line_errors(tmp_path, model_file, line, match):
    from compensator import ConfigError

    cfg = write_config(tmp_path, model_file, '{url = "sim://?program="}', line)
    with pytest.raises(ConfigError, match=match) as err:
        load_config(cfg)
    assert "\n" not in str(err.value)


def test_the_bounds_configured_reach_the_estimate(tmp_path, model_file):
    cfg = write_config(
        tmp_path,
        model_file,
        '{url = "sim://?program="}',
        "max_correction_um = 6.0\nmax_source_move_um = 2.0\nsource_window_s = 600.0",
    )
    sc = load_config(cfg).spindle[0]
    from compensator.io import load_model

    fused = sc.estimate(load_model(model_file)).fused
    assert fused is not None
    c = fused.config
    assert (c.max_correction_um, c.source_move_um, c.window_s) == (6.0, 2.0, 600.0)


def test_the_alarm_clears_once_the_sources_move_has_drained(tmp_path, caplog):
    """A measurement cut by its source's move raises OBSERVER_BOUND until that move has drained
    (here a 60 s window); a measurement taken whole clears it too."""
    from test_closed_loop import Bench, answer_box

    model = tmp_path / "model.json"
    save_model(model, thirty_um_model())
    b = Bench(tmp_path, model, observer="enabled = true\nsource_window_s = 60.0")
    b.run(300)
    b.rt.submit(b.rows[-1]["predicted_um"], 0.5)  # the first: bounded by the correction only
    b.run(1)
    box, reply = answer_box()
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        b.rt.submit(b.rows[-1]["predicted_um"] + 12.0, 0.5, reply)  # beyond the gate
        b.run(1)
        b.rt.submit(b.rows[-1]["predicted_um"] + 12.0, 0.5, reply)  # agrees: restarts, cut
        rows = b.run(70)
    assert box[0]["outcome"] == "rejected"
    assert box[1]["outcome"] == "limited" and box[1]["limited"] == "source"
    assert b.rt.est.bias_um == pytest.approx(7.5, abs=0.2)  # 7.5 um, plus what drained since
    raised = [r["alarms"] & Alarm.OBSERVER_BOUND != 0 for r in rows]
    assert raised[:55] == [True] * 55 and raised[-5:] == [False] * 5
    (entered,) = events(caplog, "observer_bound")
    (cleared,) = events(caplog, "observer_bound_cleared")
    assert entered.fields["sources"] == {"control": "source"}
    assert cleared.fields["bias_um"] == pytest.approx(b.rt.est.bias_um)
    assert b.rt.counters["probes_limited"] == 1 and b.rt.observer_status()["limited"] == {
        "control": 1
    }
    b.rt.close()


def test_the_first_measurement_of_a_fresh_observer_is_held_to_the_bound_only():
    """A cold start on a warm spindle: the first measurement may move the correction up to the
    bound at once; the next ones from the same source are held to its move again."""
    fused = FusedPredictor(thirty_um_model(), ObserverConfig())
    st = fused.start(0.0, SPEED)
    st, up = fused.measure(st, 12.0, 0.5, source="setter")
    assert up.limited is None and st.bias_um == pytest.approx(12.0, abs=0.1)
    st, up = fused.measure(st, 14.0, 0.5, source="setter")  # its move (12 > 7.5) is used up
    assert up.limited == "source" and st.bias_um == pytest.approx(12.0, abs=0.1)
    st = fused.start(0.0, SPEED)
    st, up = fused.measure(st, 40.0, 0.5, source="setter")
    assert up.limited == "bound" and st.bias_um == pytest.approx(15.0)


def test_replay_of_the_services_journal_cuts_the_same_measurements(tmp_path, model_file):
    """`thermocomp replay --measurements` over the service's own journal of the two-source
    attack: each measurement's source is read from the journal, so replay cuts the same ones and
    gives the service's estimate, step for step."""
    from calibration.replay import probes_from_file, replay
    from compensator.io import load_any_model, read_run_log

    rig = SocketAttack(tmp_path, model_file)
    try:
        rig.warm(60.0)
        got = rig.run(probe_too=True)
        for _ in range(5):  # the cycle journal goes on past the last measurement
            rig.tick()
        sc = load_config(tmp_path / "machine.toml").spindle[0]
    finally:
        rig.close()
    journal_dir = rig.state_dir / "journal"
    (journal,) = sorted(journal_dir.glob("s1-*.csv"))
    (measurements,) = sorted(journal_dir.glob("s1.measurements-*.csv"))
    log = read_run_log(journal)
    probes = probes_from_file(log, str(measurements), 0.5)
    assert set(probes.sources) == {"control", "sim"}
    model = load_any_model(model_file)
    rep = replay(
        model, log, shaping=sc.shaping, probes=probes, estimate=sc.estimate(model), compare=False
    )
    service = np.asarray(log.extras["predicted_um"], dtype=float)
    np.testing.assert_allclose(rep.predicted_um, service, rtol=0, atol=1e-6)
    assert rep.report["probes_limited"] == got["limited"]
    assert float(np.min(rep.predicted_um)) == pytest.approx(got["min"], abs=1e-6)


def test_thermocomp_measure_says_limited_and_exits_1(tmp_path, model_file, capsys):
    """`thermocomp measure` against the running service: a value the bound cuts is answered
    `limited`, exit 1 (not taken whole), and the estimate moved only to the bound."""
    import threading

    from thermocomp.cli import main as cli

    rig = SocketAttack(tmp_path, model_file, observer="max_correction_um = 2.0")
    try:
        rig.warm(60.0)
        assert rig.svc.control is not None
        rig.svc.control.request_timeout_s = float("inf")  # the fake clock runs as we tick
        codes: list[int] = []
        um = rig.rt.estimate_um() + 5.0
        args = ["measure", "--um", f"{um:.3f}", "--state-dir", str(rig.state_dir)]
        client = threading.Thread(target=lambda: codes.append(cli(args)))
        client.start()
        while client.is_alive() and rig.t < 1e4:
            rig.tick()
        client.join()
        bias = rig.rt.est.bias_um
    finally:
        rig.close()
    assert codes == [1]
    assert capsys.readouterr().out.startswith("s1: limited: measured")
    assert bias == pytest.approx(2.0)


# -- a drift rate moves the correction on its source's account --------------------------------


def test_one_source_with_a_drift_state_stays_within_its_move_per_window() -> None:
    # With a drift state (drift_q_um2_per_s3 > 0, which calibration.closedloop.fit_noise(drift=
    # True) fits), one source's measurements teach the filter a drift rate, and the time update
    # carries the correction on: that move is charged to the source that taught it.
    cfg = ObserverConfig(max_correction_um=15.0, drift_q_um2_per_s3=1e-7)
    assert cfg.source_move_um == 7.5 and cfg.window_s == 3600.0
    z = ObserverState.prior(cfg)
    # an honest first measurement (exempt from the source's budget), on the model
    z = measurement_update(cfg, z, 0.0, 0.0, 0.5, "control", True).state
    t = 0
    for _ in range(20):  # 20 minutes, one measurement a minute from one source: a slow ramp
        for _ in range(60):
            z = time_update(cfg, z, 1.0)
            t += 1
            assert abs(z.moved_by("control")) <= cfg.source_move_um + 1e-9
        z = measurement_update(cfg, z, -0.02 * t, 0.0, 0.5, "control", False).state
    print(f"bias {z.bias_um:+.3f} um, charged {z.moved_by('control'):+.3f} um after {t} s")
    # within one window the source may move the correction its move, plus what drained
    # meanwhile (7.5 um per hour: 2.5 um in these 20 minutes), never the full bound
    assert abs(z.bias_um) <= cfg.source_move_um + cfg.source_move_um * t / cfg.window_s + 1e-9
    assert abs(z.bias_um) < cfg.max_correction_um - 4.0


def test_each_sources_share_of_the_drift_is_saved_and_a_state_saved_before_them_loads():
    fused = FusedPredictor(thirty_um_model(), ObserverConfig(drift_q_um2_per_s3=1e-7))
    st = fused.start(0.0, 0.0)
    st, _ = fused.measure(st, 0.0, 0.5, source="control")
    for k in range(1, 4):
        st = fused.step(st, 0.0, 60.0)
        st, up = fused.measure(st, -1.0 * k, 0.5, source="control")
        assert up.limited is None
    assert st.observer.drift_of("control") == pytest.approx(st.observer.drift_um_per_s)
    assert st.observer.drift_um_per_s < 0.0
    saved = json.loads(json.dumps(fused.state_dict(st)))
    back = fused.state_from_dict(saved)
    assert back.observer.drift_by_um_per_s == st.observer.drift_by_um_per_s
    # carried on, the drift is charged to the source that taught it
    before = back.observer.moved_by("control")
    later = fused.step(back, 0.0, 10.0)
    moved = later.observer.bias_um - back.observer.bias_um
    assert moved < 0.0
    drained = fused.config.source_move_um / fused.config.window_s * 10.0
    assert later.observer.moved_by("control") == pytest.approx(before + drained + moved)
    del saved["observer"]["drift_by_um_per_s"]
    assert fused.state_from_dict(saved).observer.drift_by_um_per_s == ()
    saved["observer"]["drift_by_um_per_s"] = {"control": "fast"}
    with pytest.raises(ModelError, match="observer"):
        fused.state_from_dict(saved)
