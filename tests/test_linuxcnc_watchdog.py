"""The sign of life against the real LinuxCNC: the example sim configuration with the shipped
watchdog recipe (examples/linuxcnc/thermocomp-watchdog.hal and its three reactions),
thermocomp's HAL component beating, then killed with SIGKILL, or stopped (SIGSTOP) past the
timeout and let go on; and the thermocomp service itself stopped cleanly, started again by hand
and killed.

Time is HAL's own: a few stock components appended for the test count servo-thread time
(``integ``) from the last flip of the life toggle HAL saw to the watchdog's ok falling, and
stamp the samples of the fade. The wall clock only bounds how long the test waits."""

from __future__ import annotations

import contextlib
import math
import os
import re
import shutil
import signal
import subprocess
import tempfile
from pathlib import Path

import pytest
from test_linuxcnc import (
    EXAMPLE,
    ROOT,
    USER,
    LinuxCnc,
    as_user,
    hal_lock,
    linuxcnc_venv,
    on_and_homed,
    why_not,
)

pytestmark = pytest.mark.skipif(why_not() is not None, reason=why_not() or "")

SERVO_PERIOD_S = 0.001  # [EMCMOT]SERVO_PERIOD of thermocomp_sim.ini
TIMEOUT_S = 2.0  # beats every 0.1 s: twenty missed before the watchdog speaks
FADE_TAU_S = 1.0  # the first-order fade's time constant ...
FADE_CAP = 500.0  # ... and its cap [counts/s]: 5 um/s at 0.01 um per count
OFFSET_UM = -10.0  # thermocomp's sign: +10 um on Z, 1000 counts
COUNTS = 1000

# the adapter as the service drives it: the offset and a beat each 0.1 s, valid once the
# machine is on and homed (before, the runtime confirms with valid false)
BEAT = """
import sys, time
from cnc_adapters import Life
from cnc_adapters.linuxcnc import LinuxCncAdapter

a = LinuxCncAdapter(component="thermocomp", cutting="feed")
a.open()
life = Life(0, False)
while True:
    ready = a.read().not_ready_offset_um is None
    life = life.next(ready)
    result = a.write(float(sys.argv[1]), life)
    assert result.taken, result.failure
    time.sleep(0.1)
"""

# HAL's clocks for the test: seconds of servo time since the last flip of the life toggle
# while the watchdog is ok (frozen once it falls), the largest such gap, the smallest ok seen,
# the time thermocomp-ok has been false, a plain clock, and a latch set when thermocomp-ok is
# false while the toggle still counts as fresh (ok fell on comp-valid, not on the timeout)
MEASURE = """
loadrt edge           names=tcw-beat
loadrt and2           names=tcw-early-and
loadrt flipflop       names=tcw-early
loadrt conv_bit_float names=tcw-ok-f,tcw-not-ok-f
loadrt integ          names=tcw-since-beat,tcw-since-fault,tcw-clock
loadrt minmax         names=tcw-gap,tcw-ok-min
addf tcw-beat       servo-thread
addf tcw-ok-f       servo-thread
addf tcw-not-ok-f   servo-thread
addf tcw-since-beat servo-thread
addf tcw-since-fault servo-thread
addf tcw-clock      servo-thread
addf tcw-gap        servo-thread
addf tcw-ok-min     servo-thread
addf tcw-early-and  servo-thread
addf tcw-early      servo-thread
setp tcw-beat.both 1
setp tcw-clock.in 1
net thermocomp-life                           => tcw-beat.in
net tcw-beat          tcw-beat.out            => tcw-since-beat.reset
net thermocomp-beating                        => tcw-ok-f.in
net tcw-ok-f          tcw-ok-f.out            => tcw-since-beat.in tcw-ok-min.in
net tcw-since-beat    tcw-since-beat.out      => tcw-gap.in
net thermocomp-not-ok                         => tcw-not-ok-f.in
net tcw-not-ok-f      tcw-not-ok-f.out        => tcw-since-fault.in
net thermocomp-beating                        => tcw-early-and.in0
net thermocomp-not-ok                         => tcw-early-and.in1
net tcw-early-set     tcw-early-and.out       => tcw-early.set
"""

RECIPE = (
    "thermocomp-watchdog.hal",
    "thermocomp-alarm.hal",
    "thermocomp-feedhold.hal",
    "thermocomp-fade.hal",
)

PROGRAM = """o<thermocomp_check> call
M68 E2 Q1
G1 X40 F60
M2
"""


@contextlib.contextmanager
def watched_rig(beat: str | None = BEAT, tau_s: float = FADE_TAU_S, cap: float = FADE_CAP):
    """The example configuration with the whole recipe; thermocomp's component is the adapter
    driven by ``beat`` (None: the thermocomp service of the example, from this tree)."""
    directory = Path(tempfile.mkdtemp(prefix="thermocomp-watchdog-", dir="/tmp"))
    shutil.copytree(EXAMPLE, directory, dirs_exist_ok=True)
    hal = directory / "thermocomp.hal"
    if beat is not None:
        (directory / "beat.py").write_text(beat)
        text = hal.read_text()
        service = "loadusr -Wn thermocomp thermocomp run --config thermocomp.toml"
        assert service in text
        hal.write_text(text.replace(service, f"loadusr -Wn thermocomp python beat.py {OFFSET_UM}"))
    (directory / "measure.hal").write_text(MEASURE)
    (directory / "run.ngc").write_text(PROGRAM)
    ini = directory / "thermocomp_sim.ini"
    halfiles = "".join(f"HALFILE = {f}\n" for f in (*RECIPE, "measure.hal"))
    text = ini.read_text().replace(
        "HALFILE = thermocomp.hal\n", f"TWOPASS = on\nHALFILE = thermocomp.hal\n{halfiles}"
    )
    gain = 1 - math.exp(-SERVO_PERIOD_S / tau_s)
    text += (
        f"\n[THERMOCOMP]\nWATCHDOG_TIMEOUT_S = {TIMEOUT_S}\nFADE_GAIN = {gain!r}\n"
        f"FADE_MAX_COUNTS_PER_S = {cap}\n"
    )
    ini.write_text(text)
    if os.geteuid() == 0:
        shutil.chown(directory, USER)
        for p in directory.rglob("*"):
            shutil.chown(p, USER)
    with hal_lock():
        rig = LinuxCnc(directory, env={"PYTHONPATH": str(ROOT)})
        try:
            yield rig
        finally:
            rig.stop()
            shutil.rmtree(directory, ignore_errors=True)


def component_pid(name: str) -> int | None:
    """The process that owns HAL component ``name`` (halcmd's PID column); None: no such."""
    r = subprocess.run(
        as_user(["halcmd", "-s", "show", "comp", name]), capture_output=True, text=True, timeout=20
    )
    for line in r.stdout.splitlines():
        parts = line.split()
        if len(parts) >= 4 and parts[1] == "User" and parts[2] == name:
            return int(parts[3])
    return None


def kill(name: str, sig: signal.Signals) -> None:
    pid = component_pid(name)
    assert pid is not None, f"no user component {name}"
    os.kill(pid, sig)


def setp(pin: str, value: object) -> None:
    subprocess.run(as_user(["halcmd", "setp", pin, str(value)]), check=True, timeout=20)


def rsh_status(cnc: LinuxCnc) -> str:
    return cnc.rsh.cmd("get program_status")


def run_program(cnc: LinuxCnc) -> None:
    """run.ngc in auto mode, its marker (motion.analog-out-02) cleared first."""
    r = cnc.rsh
    r.set("mode mdi")
    r.set("mdi m68 e2 q0")
    assert cnc.wait(lambda: cnc.getp("motion.analog-out-02") == 0.0)
    r.set("mode auto")
    r.set(f"open {cnc.dir / 'run.ngc'}")
    r.set("run")


def fade_model(
    t_s: float, c0: float = COUNTS, tau_s: float = FADE_TAU_S, cap: float = FADE_CAP
) -> float:
    """The counts ``t_s`` seconds of HAL time after ok fell from ``c0`` (> 0): first order
    toward 0 with ``tau_s``, never faster than ``cap`` (whichever is slower at each instant)."""
    return max(c0 * math.exp(-t_s / tau_s), c0 - cap * t_s, 0.0)


def test_a_late_beat_holds_the_machine_until_the_beats_return_a_kill_stops_it():
    """One LinuxCNC for both (its start, homing and the cut under way are a third of each run).
    The watchdog does not latch: thermocomp stopped (SIGSTOP: a hang, a late cycle) past the
    timeout and let go on, nothing else done: ok falls after the timeout on HAL's clock and
    returns with the next beat; the feed hold releases and the fade gives the counts back. Then
    beats at 10 Hz keep it ok, and thermocomp killed (SIGKILL) stops the machine within the
    timeout: the fade, the feed hold and the refused cycle start."""
    with watched_rig() as cnc:
        r = cnc.rsh
        # in E-stop at start: it beats, but it is not valid: not ok, nothing applied
        pins = ("thermocomp.comp-valid", "thermocomp-ok.out")
        assert cnc.getps(pins) == [False, False]
        on_and_homed(cnc)
        # valid once on and homed: ok, the counts go through unchanged
        assert cnc.wait(lambda: cnc.getp("thermocomp-ok.out") is True)
        assert cnc.wait(lambda: cnc.getp("axis.z.eoffset-counts") == COUNTS)
        counts, life = cnc.getps(("thermocomp.eoffset-counts", "thermocomp.life-counter"))
        assert counts == COUNTS and life > 1

        # a cycle start is let through: the check passes, the marker is set, the cut begins
        run_program(cnc)
        assert cnc.wait(lambda: cnc.getp("motion.analog-out-02") == 1.0)
        assert cnc.wait(lambda: cnc.getp("motion.current-vel") > 0.5 / 60)

        # -- a late beat: stopped past the timeout, then let go on
        for tracker in ("tcw-since-fault", "tcw-early"):
            setp(f"{tracker}.reset", 1)
            setp(f"{tracker}.reset", 0)
        pid = component_pid("thermocomp")
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        try:
            assert cnc.wait(lambda: cnc.getp("thermocomp-ok.out") is False, timeout=60)
            since, valid, early = cnc.getps(
                ("tcw-since-beat.out", "thermocomp.comp-valid", "tcw-early.out")
            )
            # on the timeout, not on the flag: comp-valid still true, the toggle stale
            assert valid is True and early is False
            assert TIMEOUT_S - SERVO_PERIOD_S <= since <= TIMEOUT_S + 3 * SERVO_PERIOD_S
            # held: the feed stopped, the counts fading, the program still running
            assert cnc.wait(lambda: cnc.getp("motion.current-vel") == 0.0)
            assert cnc.wait(lambda: cnc.getp("axis.z.eoffset-counts") < COUNTS)
            assert rsh_status(cnc) == "PROGRAM_STATUS RUNNING"
        finally:
            os.kill(pid, signal.SIGCONT)

        # the beats again, nothing else: ok returns, the cut goes on, the counts are back
        assert cnc.wait(lambda: cnc.getp("thermocomp-ok.out") is True, timeout=60)
        late_gap = cnc.getp("tcw-since-fault.out")
        assert late_gap > 0.0  # ok was false for this long on HAL's clock, and now is true again
        assert cnc.wait(lambda: cnc.getp("motion.current-vel") > 0.5 / 60)
        assert cnc.wait(lambda: cnc.getp("axis.z.eoffset-counts") == COUNTS)
        assert rsh_status(cnc) == "PROGRAM_STATUS RUNNING"
        assert cnc.getp("thermocomp-beat.out") is True
        print(
            f"\nstopped past the timeout: ok fell {since:.3f} s after the last beat, was false "
            f"for {late_gap:.3f} s, true again with the next beat (timeout {TIMEOUT_S} s)"
        )

        # -- beats at 10 Hz with a 2 s timeout: ok all along, 3 s of HAL time
        for tracker in ("tcw-ok-min", "tcw-gap"):  # from here on
            setp(f"{tracker}.reset", 1)
            setp(f"{tracker}.reset", 0)
        t0 = cnc.getp("tcw-clock.out")
        assert cnc.wait(lambda: cnc.getp("tcw-clock.out") - t0 > 3.0, timeout=60)
        gap, ok_min, ok = cnc.getps(("tcw-gap.max", "tcw-ok-min.min", "thermocomp-ok.out"))
        assert ok_min == 1.0 and ok is True, gap
        assert cnc.getp("tcw-since-fault.out") == late_gap  # no fault since
        assert rsh_status(cnc) == "PROGRAM_STATUS RUNNING"
        assert cnc.getp("axis.z.eoffset-request") == pytest.approx(COUNTS * 1e-5)

        # -- SIGKILL of the process that owns the component: no last word, every pin stays
        setp("tcw-since-fault.reset", 1)
        setp("tcw-since-fault.reset", 0)
        kill("thermocomp", signal.SIGKILL)
        assert cnc.wait(lambda: cnc.getp("thermocomp-beat.out") is False, timeout=60)
        # the reaction time on HAL's clock: from the last flip HAL saw to ok falling
        since = cnc.getp("tcw-since-beat.out")
        # each sample between two readings of HAL's clock (halcmd reads one pin after the
        # other, and a loaded machine may deschedule it between them)
        samples = []
        watched = (
            "tcw-since-fault.out",
            "axis.z.eoffset-counts",
            "axis.z.eoffset-request",
            "motion.current-vel",
            "joint.0.pos-fb",
            "tcw-since-fault.out",
        )

        def faded() -> bool:
            samples.append([float(v) for v in cnc.getps(watched)])
            return samples[-1][1] == 0.0

        cnc.wait(faded, timeout=120, every=0.02)
        print(
            f"largest beat gap {gap:.3f} s; ok fell {since:.3f} s after the last beat "
            f"(timeout {TIMEOUT_S} s, servo period {SERVO_PERIOD_S * 1e3:g} ms); faded to 0 "
            f"{samples[-1][0]:.3f} s later ({len(samples)} samples)"
        )
        assert TIMEOUT_S - SERVO_PERIOD_S <= since <= TIMEOUT_S + 3 * SERVO_PERIOD_S
        # the dead component's pins: valid still true, only the watchdog tells
        assert cnc.getps(("thermocomp.comp-valid", "thermocomp-ok.out")) == [True, False]

        # (c) the fade: first order with tau, capped, on HAL's clock; the counts truncated
        t_a, counts, request, vel, x, t_b = (list(c) for c in zip(*samples, strict=True))
        assert len(counts) >= 5 and t_a[0] < 3.0  # seen while it fades
        for ta, ci, ri, tb in zip(t_a, counts, request, t_b, strict=True):
            assert fade_model(tb) - 1 <= ci <= fade_model(ta) + 1e-6, (ta, tb, ci)
            assert abs(ri * 1e5 - ci) <= FADE_CAP * (tb - ta) + 2  # motion holds the chain's
        for i in range(1, len(counts)):
            step = counts[i - 1] - counts[i]
            assert 0 <= step <= FADE_CAP * (t_b[i] - t_a[i - 1]) + 1, (i, step)
        # the request may still hold less than one count, which the counts truncate to none
        assert counts[-1] == 0 and abs(request[-1]) * 1e5 < 1 + 1e-6

        # (b) the feed hold: the cut stopped where it was, the program still running
        held = [i for i in range(len(t_a)) if t_a[i] > 0.05]
        assert held and all(vel[i] == 0.0 and x[i] == x[held[0]] for i in held)
        assert rsh_status(cnc) == "PROGRAM_STATUS RUNNING"

        # (a) the next cycle start is refused at the program's first line, with the message
        r.set("abort")
        assert cnc.wait(lambda: rsh_status(cnc) == "PROGRAM_STATUS IDLE")
        run_program(cnc)
        assert cnc.wait(lambda: rsh_status(cnc) == "PROGRAM_STATUS IDLE")
        assert "thermal compensation stopped - cycle start refused" in r.cmd("get error")
        assert cnc.getp("motion.analog-out-02") == 0.0  # its next line never ran


def restart_thermocomp(cnc: LinuxCnc) -> None:
    """examples/linuxcnc/thermocomp-restart.hal, run by hand as its comment says."""
    env = [
        "env",
        f"PATH={linuxcnc_venv() / 'bin'}:/usr/bin:/bin",
        f"PYTHONPATH={ROOT}",
        f"HOME={cnc.dir}",
    ]
    # to a file: the service started inherits halcmd's output, a pipe would stay open
    with open(cnc.dir / "restart.out", "w") as out:
        r = subprocess.run(
            as_user([*env, "halcmd", "-f", "thermocomp-restart.hal"]),
            stdout=out,
            stderr=subprocess.STDOUT,
            timeout=300,  # loadusr -Wn: until the component is ready
            cwd=cnc.dir,
        )
    assert r.returncode == 0, (cnc.dir / "restart.out").read_text() + cnc.log()


def gets(signal_name: str) -> str:
    """A signal's value (a component that exited cleanly has left its signals behind)."""
    r = subprocess.run(
        as_user(["halcmd", "-s", "gets", signal_name]), capture_output=True, text=True, timeout=20
    )
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


# a second thermocomp's link opened while the component's name is taken: what it says
OPEN = """
from cnc_adapters.linuxcnc import LinuxCncAdapter
from compensator.errors import UnreachableError
try:
    LinuxCncAdapter(component="thermocomp", machine_state="pins").open()
except UnreachableError as err:
    print(err)
"""


def second_thermocomp(cnc: LinuxCnc) -> str:
    """The error of a second thermocomp's link opened now (stdout only: HAL's own message on
    stderr is not ours)."""
    env = ["env", f"PATH={linuxcnc_venv() / 'bin'}:/usr/bin:/bin", f"PYTHONPATH={ROOT}"]
    r = subprocess.run(
        as_user([*env, "python", "-c", OPEN]),
        capture_output=True,
        text=True,
        timeout=60,
        cwd=cnc.dir,
    )
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_the_service_stopped_says_so_restarted_takes_over_killed_is_caught():
    slow = {"tau_s": 20.0, "cap": 100.0}  # a restart comes while the offset still fades
    with watched_rig(beat=None, **slow) as cnc:
        r = cnc.rsh
        on_and_homed(cnc)
        r.set("mdi m3 s12000")  # the spindle grows: thermocomp writes counts on Z
        assert cnc.wait(lambda: cnc.getp("thermocomp-ok.out") is True, timeout=60)
        assert cnc.wait(lambda: cnc.getp("thermocomp.eoffset-counts") > 300, timeout=120)

        # a clean stop: the last beat says "not valid", ok falls at once, before the timeout
        # could run out; the offset starts to fade
        setp("tcw-early.reset", 1)
        setp("tcw-early.reset", 0)
        kill("thermocomp", signal.SIGTERM)
        assert cnc.wait(lambda: cnc.getp("thermocomp-ok.out") is False)
        assert cnc.getp("tcw-early.out") is True  # ok fell while the toggle was still fresh
        assert cnc.wait(lambda: component_pid("thermocomp") is None, timeout=60)  # exited
        assert gets("thermocomp-valid") == "FALSE"  # what its pin said last
        stopped_at = float(gets("thermocomp-counts"))
        assert cnc.wait(lambda: 0 < cnc.getp("axis.z.eoffset-counts") < stopped_at - 20)

        # started again by hand: it takes over what motion holds, ok comes back
        restart_thermocomp(cnc)
        assert cnc.wait(lambda: cnc.getp("thermocomp-ok.out") is True, timeout=120)
        took = re.findall(r"re-seeding from the (\d+) counts motion holds", cnc.log())
        assert took and 0 < int(took[-1]) < stopped_at, (took, stopped_at)

        # killed: ok falls once the timeout has run out on HAL's clock, and the
        # offset fades from where the dead component left it
        pid = component_pid("thermocomp")
        said = second_thermocomp(cnc)  # the name taken by a live one: it says so
        assert said == (
            f"linuxcnc: HAL component 'thermocomp' belongs to process {pid}, which runs: stop "
            "it first, or give this thermocomp another component name\n"
        ), said
        setp("tcw-since-fault.reset", 1)
        setp("tcw-since-fault.reset", 0)
        kill("thermocomp", signal.SIGKILL)
        assert cnc.wait(lambda: cnc.getp("thermocomp-beat.out") is False, timeout=60)
        since, c0 = cnc.getps(("tcw-since-beat.out", "thermocomp.eoffset-counts"))
        print(f"\nthe service killed: ok fell {since:.3f} s after its last beat; fading from {c0}")
        assert TIMEOUT_S - SERVO_PERIOD_S <= since <= TIMEOUT_S + 3 * SERVO_PERIOD_S
        assert c0 > 0  # the spindle grew toward the part: +Z
        samples = []
        watched = ("tcw-since-fault.out", "axis.z.eoffset-counts", "tcw-since-fault.out")

        def faded() -> bool:
            samples.append([float(v) for v in cnc.getps(watched)])
            return samples[-1][0] > 5.0

        cnc.wait(faded, timeout=120, every=0.05)
        assert len(samples) >= 5 and samples[0][0] < 3.0
        for ta, ci, tb in samples:
            lo = fade_model(tb, c0, **slow) - 1
            assert lo <= ci <= fade_model(ta, c0, **slow) + 1e-6, (ta, tb, ci)

        # started again now, it cannot have the dead one's name: one line that says why
        assert component_pid("thermocomp") == pid  # HAL keeps it
        said = second_thermocomp(cnc)
        assert said.count("\n") == 1 and f"left from process {pid}, which ended" in said, said
        assert said.rstrip().endswith("restart LinuxCNC"), said
