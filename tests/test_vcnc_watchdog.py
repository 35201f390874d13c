"""The virtual CNC's watch on thermocomp's sign of life: a real asyncua server in lock-step with
a SteppedClock, the life counter and the valid flag written by a real OPC UA client (or the sim
link), each reaction asserted on the machine's own simulated time."""

from __future__ import annotations

import math

import pytest

from cnc_adapters.reading import LIFE_MODULUS, Life
from compensator.clock import SteppedClock
from compensator.speed_programs import Program
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import (
    CYCLE_START_PATH,
    LIFE_PATHS,
    NAMESPACE_URI,
    NODE_PATHS,
    RESET_PATH,
    STATE_PATHS,
    WATCH_PATHS,
    VirtualCNC,
    VirtualMachine,
    running,
    step,
)
from machine_sim.watchdog import ALARM_INVALID, Watch, WatchSettings

TICK_S = 0.5  # one lock-step tick: the plant's grid
DAY = Program("day", ((600.0, 20000.0), (600.0, 12000.0), (3600.0, 0.0)))


def machine(clock: SteppedClock, say=None, settings=None, **watch) -> VirtualMachine:
    return VirtualMachine(
        SpindlePlant(preset("motorized-27k"), seed=1),
        None,
        clock=clock,
        watch=settings or (WatchSettings(**watch) if watch else None),
        say=say,
    )


class Rig:
    """A virtual CNC in lock-step and an asyncua client that writes what thermocomp writes."""

    def __init__(self, cnc: VirtualCNC, clock: SteppedClock, client) -> None:
        self.cnc, self.clock, self.vm = cnc, clock, cnc.machine
        ns = client.get_namespace_index(NAMESPACE_URI)
        paths = {**NODE_PATHS, **STATE_PATHS, **LIFE_PATHS, **WATCH_PATHS}
        paths.update(cycle_start=CYCLE_START_PATH, reset=RESET_PATH)
        self.node = {k: client.get_node(f"ns={ns};s={p}") for k, p in paths.items()}
        self.life = Life(0, False)

    def tick(self, n: int = 1) -> None:
        for _ in range(n):
            self.clock.advance(TICK_S)
            step(self.cnc)

    def beat(self, valid: bool = True) -> None:
        """One beat as the service writes it (Int32 counter, Boolean flag), then one tick."""
        from asyncua import ua

        self.life = self.life.next(valid)
        self.node["life_counter"].write_value(ua.Variant(self.life.counter, ua.VariantType.Int32))
        self.node["compensation_valid"].write_value(ua.Variant(valid, ua.VariantType.Boolean))
        self.tick()

    def press(self, key: str) -> None:
        from asyncua import ua

        self.node[key].write_value(ua.Variant(True, ua.VariantType.Boolean))
        self.tick()

    def read(self, key: str):
        return self.node[key].read_value()

    def tick_until_tripped(self, limit_s: float = 30.0) -> float:
        """Ticks until the watch node leaves ok; the machine time it was first seen."""
        end = self.vm.plant.time_s + limit_s
        while self.read("compensation_watch") == "ok":
            assert self.vm.plant.time_s < end, "the watch never tripped"
            self.tick()
        return self.vm.plant.time_s


def rig(say=None, settings=None, **watch):
    from asyncua.sync import Client

    clock = SteppedClock()
    cnc = VirtualCNC(machine(clock, say, settings, **watch), tick_s=None)
    with running(cnc), Client(cnc.url, timeout=10) as client:
        r = Rig(cnc, clock, client)
        r.tick()
        yield r


@pytest.fixture
def alarm_rig():
    yield from rig(reaction="alarm")


@pytest.fixture
def hold_rig():
    yield from rig(reaction="feed-hold")


@pytest.fixture
def fade_rig():
    yield from rig(reaction="fade", fade_tau_s=60.0, fade_max_rate_um_per_s=0.2)


@pytest.fixture
def none_rig():
    yield from rig()


def beats_then_silence(r: Rig, beats: int = 10) -> tuple[float, float]:
    """Beats every tick, then none: (machine time of the last beat's tick, of the trip)."""
    for _ in range(beats):
        r.beat()
        assert r.read("compensation_watch") == "ok"
    last = r.vm.plant.time_s - TICK_S  # taken at the plant's time when the tick began
    tripped = r.tick_until_tripped()
    return last, tripped


# -- the pure watch ---------------------------------------------------------------------


def test_the_watch_waits_for_a_first_beat_and_trips_at_the_timeout_on_machine_time():
    w = Watch(WatchSettings(timeout_s=3.0, reaction="alarm"))
    assert w.summary().startswith("never written")
    for t in range(100):  # never written: thermocomp never ran here, nothing to react to
        assert w.beat(0, False, float(t)) == "waiting"
    assert w.refusal == "" and w.trips == 0
    w.beat(1, True, 100.0)
    assert w.update(102.9) == "ok"
    assert w.update(103.0) == "stale" and w.tripped_at_s == 103.0
    assert w.refusal.startswith("7001") and "3 s" in w.refusal
    assert not w.reset()  # the sign of life is still missing: the alarm stands
    w.beat(2, True, 104.0)
    assert w.state == "ok" and w.refusal  # latched until the operator's reset
    assert w.reset() and w.refusal == "" and w.trips == 1


def test_only_a_counter_that_moves_within_its_range_is_a_beat():
    w = Watch(WatchSettings(timeout_s=3.0))
    w.beat(7, True, 0.0)
    for t, counter in (
        (1, 7),
        (1.5, True),
        (2, 7.5),
        (2.5, 7.0),
        (2.7, LIFE_MODULUS + 1),
        (2.9, 0),
    ):
        w.beat(counter, True, t)
    assert w.update(3.0) == "stale" and w.last_beat_s == 0.0
    w.beat(LIFE_MODULUS, True, 3.5)  # a real move
    assert w.state == "ok" and w.last_beat_s == 3.5
    w.beat(1, "true", 4.0)  # only a Boolean true or the number 1 is true
    assert w.state == "invalid"
    w.beat(2.0, 1.0, 4.5)  # an R parameter: a whole Double moves, 1.0 is valid
    assert w.state == "ok" and (w.counter, w.last_beat_s) == (2, 4.5)
    w.beat(2.5, 1, 5.0)
    assert w.last_beat_s == 4.5 and w.state == "ok"


def test_a_fade_is_first_order_and_never_faster_than_its_rate():
    w = Watch(WatchSettings(reaction="fade", fade_tau_s=100.0, fade_max_rate_um_per_s=0.1))
    x, dt = -30.0, 0.5
    for _ in range(20000):
        y = w.fade(x, dt)
        assert abs(y - x) <= 0.1 * dt + 1e-12 and abs(y) <= abs(x) and y <= 0.0
        if abs(x) * (1 - math.exp(-dt / 100.0)) < 0.1 * dt:  # the cap does not bind: first order
            assert y == pytest.approx(x * math.exp(-dt / 100.0)) or y == 0.0
        x = y
    assert x == 0.0


@pytest.mark.parametrize(
    "bad",
    [{"timeout_s": 0.0}, {"timeout_s": math.nan}, {"reaction": "stop"}, {"fade_tau_s": -1.0}],
)
def test_watch_settings_refuse_what_no_control_could_run(bad):
    with pytest.raises(ValueError, match="watch"):
        WatchSettings(**bad)


# -- the virtual CNC over OPC UA, in lock-step ----------------------------------------------


def test_alarm_at_the_timeout_refuses_cycle_start_until_the_beats_are_back_and_reset(
    alarm_rig,
):
    r = alarm_rig
    r.vm.load_pending(DAY)
    last, tripped = beats_then_silence(r)
    assert tripped - last == pytest.approx(3.0, abs=TICK_S)
    assert r.read("compensation_tripped_at") == pytest.approx(last + 3.0, abs=TICK_S)
    assert r.read("compensation_watch") == "stale"
    assert r.read("compensation_alarm").startswith("7001 THERMAL COMPENSATION")
    assert "cycle start refused" in r.read("compensation_reaction")
    r.press("cycle_start")
    assert r.vm.program is None and r.vm.pending is DAY and r.vm.refused_starts == 1
    assert r.read("cycle_start") is False  # the press is spent
    r.press("reset")  # the sign of life still missing: the alarm stands
    assert r.read("compensation_alarm")
    r.beat()
    assert r.read("compensation_watch") == "ok" and r.read("compensation_alarm")
    r.press("cycle_start")
    assert r.vm.program is None and r.vm.refused_starts == 2
    r.press("reset")
    assert r.read("compensation_alarm") == "" and r.read("compensation_reaction") == ""
    r.beat()
    r.press("cycle_start")
    assert r.vm.program is DAY and r.vm.pending is None
    assert r.read("compensation_trips") == 1


def test_a_valid_false_reacts_at_once(alarm_rig):
    r = alarm_rig
    r.vm.load_pending(DAY)
    for _ in range(4):
        r.beat()
    t = r.vm.plant.time_s
    r.beat(valid=False)  # a clean stop: one last beat, valid false
    assert r.read("compensation_watch") == "invalid"
    assert r.read("compensation_tripped_at") == t  # the tick that took it
    assert r.read("compensation_alarm") == ALARM_INVALID
    r.press("cycle_start")
    assert r.vm.program is None


def test_feed_hold_at_the_timeout_pauses_the_program_with_the_spindle_turning(hold_rig):
    r = hold_rig
    r.vm.load_program(DAY)
    r.tick(60)  # 30 s: at 20 000 rpm, cutting
    assert r.vm.cutting and r.read("act_speed") == 20000.0
    last, tripped = beats_then_silence(r)
    assert tripped - last == pytest.approx(3.0, abs=TICK_S)
    assert "feed hold" in r.read("compensation_reaction")
    r.tick(1400)  # 700 s: past the program's first segment, were it running
    assert r.read("cmd_speed") == 20000.0 and r.read("act_speed") == 20000.0  # spindle kept
    assert not r.vm.cutting and r.read("cutting") is False  # the axes stand
    h = r.vm.history()
    held = h.time_s > tripped
    assert not h.cutting[held].any() and (h.speed_rpm[held] == 20000.0).all()
    r.press("cycle_start")  # refused: the sign of life is missing
    assert r.vm.watch.held and r.vm.refused_starts == 1
    for _ in range(20):  # back: the machine still does not move on by itself
        r.beat()
    assert r.read("compensation_watch") == "ok"
    assert r.vm.watch.held and not r.vm.cutting
    r.press("cycle_start")
    assert not r.vm.watch.held
    for _ in range(20):
        r.beat()
    assert r.vm.cutting and r.read("cmd_speed") == 20000.0  # it cuts where it paused


def test_fade_at_the_timeout_takes_the_offset_to_zero_within_its_rate(fade_rig):
    r = fade_rig
    r.node["thermal_offset"].write_value(-20.0)
    r.tick()
    assert r.vm.offset_um == -20.0
    last, tripped = beats_then_silence(r)
    assert tripped - last == pytest.approx(3.0, abs=TICK_S)
    assert r.read("compensation_reaction") == "fade: offset to zero"
    r.tick(2400)  # 20 min: 20 time constants
    h = r.vm.history()
    after = h.time_s >= tripped - 1e-9
    off = h.offset_um
    assert (off[~after][-5:] == -20.0).all()  # nothing moved before the trip
    rate = (abs(off[1:] - off[:-1]) / TICK_S)[after[:-1]]  # each step from the trip on
    assert rate.max() <= 0.2 + 1e-9  # never faster than the cap ...
    assert rate[:10] == pytest.approx([0.2] * 10)  # ... which binds at first (20/60 > 0.2)
    assert off[after][1] > -20.0
    assert abs(off[after][-1]) == 0.0  # ~0: below the fade's floor
    assert r.read("thermal_offset") == 0.0  # the control's variable itself faded
    # the tool tip sees the faded offset
    assert h.tool_tip_error_um[-1] == pytest.approx(h.true_um[-1])
    r.beat()  # the sign of life is back: the fade ends, a write is taken as before
    assert r.read("compensation_watch") == "ok" and not r.vm.watch.fading
    r.node["thermal_offset"].write_value(-5.0)
    for _ in range(10):
        r.beat()
    assert r.vm.offset_um == -5.0
    r.tick(10)  # silent again: a second trip, a second fade
    assert r.read("compensation_trips") == 2 and r.vm.offset_um > -5.0


def test_none_keeps_the_offset_and_shows_the_state(none_rig):
    r = none_rig
    r.node["thermal_offset"].write_value(-18.94)
    r.vm.load_pending(DAY)
    last, tripped = beats_then_silence(r)
    assert tripped - last == pytest.approx(3.0, abs=TICK_S)
    r.tick(600)
    assert r.read("compensation_watch") == "stale"
    assert r.read("compensation_reaction") == "none: offset kept"
    assert r.vm.offset_um == -18.94 and r.read("compensation_alarm") == ""
    r.press("cycle_start")
    assert r.vm.program is DAY


def test_without_thermocomp_the_virtual_cnc_never_reacts(alarm_rig):
    r = alarm_rig
    r.vm.load_pending(DAY)
    r.tick(200)  # 100 s, nothing ever written
    assert r.read("compensation_watch") == "waiting" and r.read("life_counter") == 0
    assert r.read("compensation_trips") == 0
    r.press("cycle_start")
    assert r.vm.program is DAY


def test_a_restarted_virtual_cnc_forgets_the_sign_of_life(alarm_rig):
    from machine_sim.vcnc import call

    r = alarm_rig
    r.beat()
    r.beat(valid=False)
    assert r.vm.watch.alarm
    call(r.cnc, r.cnc.stop)
    call(r.cnc, r.cnc.start)
    assert r.vm.watch.state == "waiting" and not r.vm.watch.alarm


# -- the sim link --------------------------------------------------------------------------


def test_the_sim_link_writes_the_sign_of_life_to_the_machines_watch():
    clock = SteppedClock()
    vm = machine(clock, reaction="fade")
    link = SimAdapter(machine=vm)
    assert link.writes_life and link.capabilities.life_sign
    life = Life(0, True)
    for _ in range(5):
        life = life.next(True)
        assert link.write(-10.0, life).failure is None
        clock.advance(1.0)
        link.read_speed()
    assert vm.watch.state == "ok" and vm.watch.counter == 5
    assert link.write(None, life.next(False)).failure is None  # a confirm: the sign only
    assert vm.watch.state == "invalid" and vm.watch.fading
    assert vm.watch.summary() == (
        "invalid (counter 6, valid false), tripped 1 times; fade: offset to zero"
    )
    clock.advance(10.0)
    link.read_speed()
    assert -10.0 < vm.offset_um < 0.0


# -- thermocomp virtual-cnc ------------------------------------------------------------------


@pytest.mark.parametrize(
    "flag, value",
    [("--watch-timeout-s", "0"), ("--fade-tau-s", "nan"), ("--fade-rate-um-per-s", "-1")],
)
def test_virtual_cnc_refuses_a_watch_it_cannot_run_in_one_line(flag, value):
    import subprocess
    import sys

    r = subprocess.run(
        [sys.executable, "-m", "thermocomp", "virtual-cnc", flag, value, "--port", "1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        f"thermocomp: error: virtual-cnc: {flag} must be a finite number > 0, got {float(value)!r}"
    ]


def test_virtual_cnc_process_raises_its_alarm_when_the_beats_stop(tmp_path):
    """``thermocomp virtual-cnc --watch-reaction alarm`` as a process: a client's beats arm it,
    their end trips it, and the alarm shows on its nodes (the timing is the lock-step tests')."""
    import subprocess
    import sys
    import time

    from asyncua import ua
    from asyncua.sync import Client

    from machine_sim.vcnc import free_port

    port = free_port()
    out = tmp_path / "vcnc.out"
    with open(out, "w") as fh:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "thermocomp",
                "virtual-cnc",
                "--port",
                str(port),
                "--time-scale",
                "60",
                "--watch-reaction",
                "alarm",
                "--watch-timeout-s",
                "60",  # 1 s of wall time: the default's 3 s is the lock-step tests'
            ],
            stdout=fh,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
        )
    try:
        end = time.monotonic() + 120
        while "virtual CNC (" not in out.read_text():
            assert proc.poll() is None and time.monotonic() < end, out.read_text()
            time.sleep(0.05)
        text = out.read_text()
        # said in wall time too (3 simulated seconds were 50 ms at 60x: a late cycle tripped it)
        assert (
            "sign of life: watched once LifeCounter moves; 60 s still (1 s of wall time at 60x)"
        ) in text
        nodes = next(line for line in text.splitlines() if line.startswith("nodes: "))
        for path in (*LIFE_PATHS.values(), *WATCH_PATHS.values(), RESET_PATH):
            assert f"ns=2;s={path}" in nodes, path
        url = f"opc.tcp://127.0.0.1:{port}/thermocomp/virtual-cnc/"
        with Client(url, timeout=10) as c:
            ns = c.get_namespace_index(NAMESPACE_URI)
            node = {
                k: c.get_node(f"ns={ns};s={p}") for k, p in {**LIFE_PATHS, **WATCH_PATHS}.items()
            }
            node["compensation_valid"].write_value(ua.Variant(True, ua.VariantType.Boolean))
            node["life_counter"].write_value(ua.Variant(1, ua.VariantType.Int32))
            end = time.monotonic() + 60
            while node["compensation_trips"].read_value() == 0:
                assert time.monotonic() < end, "the watch never tripped"
                time.sleep(0.02)
            assert node["compensation_watch"].read_value() == "stale"
            assert node["compensation_alarm"].read_value().startswith("7001")
        end = time.monotonic() + 30
        while "watch tripped" not in out.read_text():  # printed before the node is published
            assert time.monotonic() < end, out.read_text()
            time.sleep(0.05)
        assert "watch tripped (1): stale: the life counter still for 60 s" in out.read_text()
    finally:
        proc.terminate()
        proc.wait(30)


def test_a_fade_through_an_emulated_control_fades_its_held_value_too():
    """With a control profile (FANUC: +S in whole um counts) the control's own variable fades:
    the held value, the node a read-back sees and the applied offset move together."""
    from asyncua.sync import Client

    from cnc_adapters.control_profiles import profile
    from machine_sim.controls import EmulatedControl

    clock = SteppedClock()
    vm = machine(clock, reaction="fade", fade_tau_s=60.0, fade_max_rate_um_per_s=1.0)
    control = EmulatedControl(vm, profile("fanuc"))
    cnc = VirtualCNC(vm, tick_s=None, control=control)
    with running(cnc), Client(cnc.url, timeout=10) as client:
        r = Rig(cnc, clock, client)
        r.node["thermal_offset"].write_value(12.0)  # +S: the control applies -12 um
        r.tick()
        assert vm.offset_um == -12.0
        _, tripped = beats_then_silence(r)
        r.tick(120)  # 60 s: one time constant
        assert control.held_um == pytest.approx(vm.offset_um)
        assert r.read("thermal_offset") == pytest.approx(control.held_raw)
        elapsed = vm.plant.time_s - tripped
        assert vm.offset_um == pytest.approx(-12.0 * math.exp(-elapsed / 60.0), rel=1e-9)
        r.tick(1200)
        assert vm.offset_um == 0.0 and control.held_raw == 0.0


# -- the watch's timeout against the wall clock, and its message lines ----------------------


def vcnc_watch(*argv: str) -> tuple[WatchSettings, str]:
    from thermocomp.cli import build_parser
    from thermocomp.commands.sim import watch_settings

    return watch_settings(build_parser().parse_args(["virtual-cnc", *argv]))


def test_the_default_timeout_is_3_s_of_wall_time_at_the_time_scale():
    assert vcnc_watch("--time-scale", "60")[0].timeout_s == 180.0
    assert vcnc_watch("--time-scale", "5")[0].timeout_s == 15.0
    assert vcnc_watch("--time-scale", "1")[0].timeout_s == 3.0
    assert vcnc_watch("--time-scale", "0.5")[0].timeout_s == 3.0  # never under a real control's
    assert vcnc_watch()[0].timeout_s == 180.0  # the default scale: 60
    for argv in (("--time-scale", "60"), ("--time-scale", "0.5")):
        assert vcnc_watch(*argv)[1] == ""  # a default never warns
    # a value given is taken as given; under 1 s of wall time it is warned about
    watch, warning = vcnc_watch("--time-scale", "60", "--watch-timeout-s", "3")
    assert watch.timeout_s == 3.0
    assert warning == (
        "--watch-timeout-s 3 is 50 ms of wall time at --time-scale 60: a late cycle of a healthy "
        "service will trip the watch; give at least 60 (the default is 180)"
    )
    assert vcnc_watch("--time-scale", "60", "--watch-timeout-s", "60") == (
        WatchSettings(timeout_s=60.0),
        "",
    )
    assert vcnc_watch("--time-scale", "1", "--watch-timeout-s", "0.5")[1].startswith(
        "--watch-timeout-s 0.5 is 500 ms of wall time at --time-scale 1:"
    )


def test_at_60x_the_virtual_cnc_trips_180_s_of_machine_time_after_the_last_beat():
    """The settings ``thermocomp virtual-cnc --time-scale 60`` runs with, in lock-step: beats
    1 s apart in machine time (a 1 s period) never trip it, and silence trips it at 180 s."""
    settings, _ = vcnc_watch("--time-scale", "60", "--watch-reaction", "alarm")
    for r in rig(settings=settings):
        for _ in range(60):
            r.beat()
            r.tick()  # 1 s of machine time between beats
        assert r.read("compensation_trips") == 0
        last = r.vm.plant.time_s - 2 * TICK_S  # the beat's tick began a tick before the last
        r.tick(int((179.0 - (r.vm.plant.time_s - last)) / TICK_S))
        assert r.vm.plant.time_s - last == 179.0
        assert r.read("compensation_watch") == "ok"  # 179 s still: 2.98 s of wall time at 60x
        tripped = r.tick_until_tripped(limit_s=5.0)
        assert tripped - last == pytest.approx(180.0, abs=TICK_S)
        assert r.read("compensation_alarm").startswith(
            "7001 THERMAL COMPENSATION: no sign of life from thermocomp for 180 s"
        )


def test_the_virtual_cnc_says_each_trip_refused_start_reset_and_resume():
    said: list[tuple[float, str]] = []
    for r in rig(say=lambda t, text: said.append((t, text)), reaction="alarm"):
        r.vm.load_pending(DAY)
        last, tripped = beats_then_silence(r)
        assert said == [
            (
                pytest.approx(tripped - TICK_S, abs=TICK_S),
                f"watch tripped (1): stale: the life counter still for 3 s (last beat at "
                f"{last:.1f} s); reaction alarm: alarm {r.read('compensation_alarm')}; the next "
                "cycle start is refused until a reset",
            )
        ]
        said.clear()
        r.press("cycle_start")
        r.press("reset")
        r.beat()
        r.press("reset")
        r.press("reset")
        texts = [text for _, text in said]
        assert texts == [
            "cycle start refused: 7001 THERMAL COMPENSATION: no sign of life from thermocomp "
            "for 3 s",
            "reset: alarm 7001 stands, the sign of life is still missing (stale)",
            f"watch ok: the sign of life is back (counter {r.life.counter}); the alarm stands "
            "until a reset",
            "reset: alarm cleared (7001)",
            "reset: no alarm to clear",
        ]
        times = [t for t, _ in said]  # machine time, one tick apart: the five ticks above
        assert times == sorted(times) and r.vm.plant.time_s - 5 * TICK_S <= times[0]
    said.clear()
    for r in rig(say=lambda t, text: said.append((t, text)), reaction="feed-hold"):
        r.vm.load_program(DAY)
        for _ in range(4):
            r.beat()
        r.beat(valid=False)
        r.press("cycle_start")
        r.beat()
        r.press("cycle_start")
        assert [text for _, text in said] == [
            "watch tripped (1): invalid: the valid flag is false; reaction feed-hold: feed hold, "
            "the program paused (the spindle turns)",
            "cycle start refused: feed hold: the sign of life from thermocomp is missing",
            f"watch ok: the sign of life is back (counter {r.life.counter}); the feed hold "
            "waits for cycle start",
            "cycle start: the program resumes after the feed hold",
        ]


def test_a_fork_of_the_machine_says_nothing():
    """The bench's what-ifs run on copies: their trips are not the machine's to report."""
    said: list[str] = []
    clock = SteppedClock()
    vm = machine(clock, lambda t, text: said.append(text), reaction="fade")
    vm.life_beat(1, True)
    twin = vm.fork(SteppedClock(clock()))
    assert twin.watch.say is None and vm.watch.say is not None
    twin.life_beat(2, False)
    assert twin.watch.state == "invalid" and said == []
    vm.life_beat(2, False)
    assert said and said[0].startswith("watch tripped (1): invalid")
