"""LinuxCNC itself, headless: the example sim configuration (examples/linuxcnc) with thermocomp
started by LinuxCNC as a HAL userspace component, driven through linuxcncrsh (LinuxCNC's own
remote shell) on a free loopback port. LinuxCNC's rs274 interpreter checks the wizard's NC dialect.

LinuxCNC (Debian's linuxcnc-uspace) and the virtual environment it starts thermocomp from are
installed by scripts/system-deps.sh; rtapi refuses root, so as root LinuxCNC runs as the
``thermocomp-ci`` user that script creates."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from compensator.io import read_run_log

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "linuxcnc"
USER = "thermocomp-ci"
TIME_SCALE = 60.0
MAX_RATE = 0.5  # um per simulated second, as examples/linuxcnc/thermocomp.toml


def linuxcnc_venv() -> Path:
    env = os.environ.get("THERMOCOMP_LINUXCNC_VENV")
    if env:
        return Path(env)
    return Path("/opt/thermocomp/linuxcnc-venv") if os.geteuid() == 0 else ROOT / ".venv-linuxcnc"


def why_not() -> str | None:
    if shutil.which("linuxcnc") is None:
        return "LinuxCNC is not installed (scripts/system-deps.sh installs linuxcnc-uspace as root)"
    if not (linuxcnc_venv() / "bin" / "thermocomp").exists():
        return f"no LinuxCNC virtual environment at {linuxcnc_venv()} (scripts/system-deps.sh makes it)"
    if os.geteuid() == 0:
        try:
            import pwd

            pwd.getpwnam(USER)
        except KeyError:
            return f"running as root and no user {USER} to run LinuxCNC (scripts/system-deps.sh creates it)"
    return None


pytestmark = pytest.mark.skipif(why_not() is not None, reason=why_not() or "")


@contextlib.contextmanager
def hal_lock():
    """One HAL on this machine at a time: LinuxCNC and halrun share rtapi's shared memory, and the
    test workers (pytest-xdist) run in parallel."""
    with open(Path(tempfile.gettempdir()) / "thermocomp-tests-hal.lock", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def as_user(cmd: list[str]) -> list[str]:
    return ["runuser", "-u", USER, "--", *cmd] if os.geteuid() == 0 else cmd


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Rsh:
    """A linuxcncrsh session: one command, one reply line (verbose mode: ACK or NAK)."""

    def __init__(self, port: int):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.buf = b""
        assert self.cmd("hello EMC thermocomp-test 1.0").startswith("HELLO ACK")
        # verbose first: without it a `set` answers nothing but its echo
        assert self.cmd("set verbose on") == "SET VERBOSE ACK"
        assert self.cmd("set echo off").endswith("ACK")
        assert self.cmd("set enable EMCTOO").endswith("ACK")

    def _line(self) -> str:
        while b"\n" not in self.buf:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("linuxcncrsh closed the session")
            self.buf += chunk
        line, self.buf = self.buf.split(b"\n", 1)
        return line.decode().strip()

    def cmd(self, text: str) -> str:
        self.sock.sendall(text.encode() + b"\r\n")
        while True:
            line = self._line()
            if line and line.lower() != text.lower():  # skip an echo
                return line

    def set(self, what: str) -> None:
        reply = self.cmd(f"set {what}")
        assert reply.endswith("ACK") and "NAK" not in reply, f"set {what}: {reply}"

    def close(self) -> None:
        self.sock.close()


class LinuxCnc:
    def __init__(self, directory: Path, env: dict[str, str] | None = None):
        self.dir = directory
        self.port = free_port()
        ini = (directory / "thermocomp_sim.ini").read_text()
        ini = ini.replace("DISPLAY = axis", f"DISPLAY = linuxcncrsh --port {self.port}")
        (directory / "thermocomp_sim.ini").write_text(ini)
        env = {
            "PATH": f"{linuxcnc_venv() / 'bin'}:/usr/bin:/bin",
            "HOME": str(directory),
            "LANG": "C.UTF-8",
            **(env or {}),
        }
        self.proc = subprocess.Popen(
            as_user(
                ["env", *(f"{k}={v}" for k, v in env.items()), "linuxcnc", "thermocomp_sim.ini"]
            ),
            cwd=directory,
            stdout=open(directory / "linuxcnc.out", "w"),
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        end = time.monotonic() + 90
        while True:
            try:
                self.rsh = Rsh(self.port)
                break
            except OSError:
                if self.proc.poll() is not None or time.monotonic() > end:
                    raise RuntimeError("LinuxCNC did not start:\n" + self.log()) from None
                time.sleep(0.5)

    def log(self) -> str:
        out = (self.dir / "linuxcnc.out").read_text(errors="replace")[-3000:]
        for f in ("linuxcnc_debug.txt", "thermocomp.jsonl"):
            p = self.dir / f
            if p.exists():
                out += f"\n--- {f}\n" + p.read_text(errors="replace")[-3000:]
        return out

    def getps(self, pins: tuple[str, ...]) -> list[float | bool]:
        """Several pins read by one halcmd, microseconds apart."""
        r = subprocess.run(
            as_user(["halcmd", "-s", "-f"]),
            input="".join(f"getp {p}\n" for p in pins),
            capture_output=True,
            text=True,
            timeout=20,
        )
        assert r.returncode == 0, r.stderr
        values = r.stdout.split()
        assert len(values) == len(pins), r.stdout
        return [v == "TRUE" if v in ("TRUE", "FALSE") else float(v) for v in values]

    def getp(self, pin: str) -> float | bool:
        return self.getps((pin,))[0]

    def wait(self, what, timeout: float = 30.0, every: float = 0.1):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            value = what()
            if value:
                return value
            time.sleep(every)
        raise AssertionError(f"timed out waiting\n{self.log()}")

    def stop(self) -> None:
        try:
            self.rsh.cmd("shutdown")
        except Exception:
            pass
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, 9)
            self.proc.wait(10)


@contextlib.contextmanager
def linuxcnc_rig(adapter_options: str, hal_lines: str = ""):
    """The example configuration, ``adapter_options`` added to the adapter's table of
    thermocomp.toml and ``hal_lines`` to thermocomp.hal, started as LinuxCNC starts it."""
    directory = Path(tempfile.mkdtemp(prefix="thermocomp-linuxcnc-", dir="/tmp"))
    shutil.copytree(EXAMPLE, directory, dirs_exist_ok=True)
    toml = directory / "thermocomp.toml"
    toml.write_text(
        toml.read_text().replace('axis_units = "mm"', 'axis_units = "mm"\n' + adapter_options)
    )
    with open(directory / "thermocomp.hal", "a") as f:
        f.write(hal_lines)
    if os.geteuid() == 0:
        shutil.chown(directory, USER)
        for p in directory.rglob("*"):
            shutil.chown(p, USER)
    with hal_lock():
        # thermocomp from this tree (the environment's own copy is from its last install)
        rig = LinuxCnc(directory, env={"PYTHONPATH": str(ROOT)})
        try:
            yield rig
        finally:
            rig.stop()
            shutil.rmtree(directory, ignore_errors=True)


@pytest.fixture
def cnc():
    with linuxcnc_rig(
        'inputs = ["ambient_c"]'
    ) as rig:  # an extra input pin, as a model with inputs needs
        yield rig


def on_and_homed(cnc: LinuxCnc) -> None:
    """Out of E-stop, machine on, every joint homed, in MDI mode."""
    r = cnc.rsh
    r.set("estop off")
    r.set("machine on")
    r.set("mode manual")
    for joint in (0, 1, 2):
        r.set(f"home {joint}")
    assert cnc.wait(lambda: r.cmd("get joint_homed").startswith("JOINT_HOMED YES YES YES"))
    r.set("mode mdi")


def sample(cnc: LinuxCnc, seconds: float, pins: tuple[str, ...]) -> np.ndarray:
    rows = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rows.append([time.monotonic(), *(float(v) for v in cnc.getps(pins))])
    return np.array(rows)


def journal(cnc: LinuxCnc):
    files = sorted((cnc.dir / "state" / "journal").glob("sim-mill-*.csv"))
    logs = [read_run_log(f) for f in files]
    cat = {
        k: np.concatenate(
            [getattr(lg, k) if k in ("time_s", "speed_rpm") else lg.extras[k] for lg in logs]
        )
        for k in (
            "time_s",
            "speed_rpm",
            "offset_um",
            "alarms",
            "written",
            "dt_s",
            "cutting",
            "cutting_source",
            "slew_limit_um_per_s",
        )
    }
    return cat


def test_linuxcnc_compensates_z_through_external_offsets(cnc):
    r = cnc.rsh
    assert cnc.getp("thermocomp.ready") is False  # in E-stop at start: nothing applied
    subprocess.run(
        as_user(["halcmd", "setp", "thermocomp.input.ambient_c", "21.5"]), check=True, timeout=20
    )
    assert cnc.getp("thermocomp.input.ambient_c") == 21.5
    on_and_homed(cnc)
    r.set("mdi m3 s12000")

    # the component reads the actual spindle speed (spindle.0.speed-in, rps), not the command
    cnc.wait(lambda: abs(cnc.getp("thermocomp.speed-in") * 60 - 12000) < 120)
    assert cnc.wait(lambda: cnc.getp("thermocomp.ready"))
    cnc.wait(lambda: cnc.getp("thermocomp-plant.growth-um") > 3.0, timeout=60)
    pins = (
        "thermocomp.offset-um",
        "axis.z.eoffset",
        "axis.z.eoffset-request",
        "thermocomp-plant.growth-um",
        "thermocomp-plant.tip-error-um",
        "thermocomp.eoffset-counts",
    )
    data = sample(cnc, 6.0, pins)
    _t, offset, eoffset, request, growth, tip, _counts = data.T
    # axis.z.eoffset follows the model's offset: +Z by the growth (A = -S, offset_sign -1)
    # counts x scale at 0.01 um resolution; a read may fall between the component's pin writes
    # and the next servo period, so one cycle's step (0.5 um at most) now and then
    miss = np.abs(request * 1000 + offset)
    assert np.mean(miss < 0.011) > 0.9 and miss.max() <= MAX_RATE + 0.011, miss
    assert np.all(np.abs(eoffset * 1000 + offset) < 0.6)
    # (its slew limit is checked on the journal below: the runtime's own clock, not this one)
    # and it cancels the growth: what the part sees is a fraction of it (medians over the sample:
    # the plant runs on its own scaled clock, so one late read is no verdict)
    assert np.median(growth) > 3.0 and abs(np.median(tip)) < 0.2 * np.median(growth), (growth, tip)

    # machine off: counts to zero, the runtime told that the controller applies nothing
    r.set("machine off")
    cnc.wait(
        lambda: cnc.getp("thermocomp.ready") is False and cnc.getp("thermocomp.eoffset-counts") == 0
    )
    time.sleep(1.0)
    assert cnc.getp("thermocomp.eoffset-counts") == 0
    # machine on again: LinuxCNC zeroes the offset; thermocomp re-seeds it from zero (through
    # its slew limit: checked on the journal below)
    r.set("machine on")

    def back_on_the_model() -> bool:
        eo, ready, off = cnc.getps(("axis.z.eoffset", "thermocomp.ready", "thermocomp.offset-um"))
        return ready is True and eo > 0.0005 and abs(eo * 1000 + off) < 0.6

    assert cnc.wait(back_on_the_model)  # it comes back to the model
    # the spindle stopped with the machine: start it again, and let it settle
    r.set("mode mdi")
    r.set("mdi m3 s15000")
    cnc.wait(lambda: abs(cnc.getp("thermocomp.speed-in") * 60 - 15000) < 150)
    # a feed move at speed: motion.motion-type 2 with spindle-at-speed is a cut (cutting = "feed")
    assert cnc.wait(lambda: cnc.getp("thermocomp.at-speed") is True)
    r.set("mdi g1 x4 f120")
    assert cnc.wait(lambda: cnc.getp("thermocomp.motion-type") == 2, timeout=10)
    cnc.wait(lambda: cnc.getp("thermocomp.motion-type") != 2, timeout=10)

    # E-stop: the same
    r.set("estop on")
    cnc.wait(
        lambda: cnc.getp("thermocomp.ready") is False and cnc.getp("thermocomp.eoffset-counts") == 0
    )
    r.set("estop off")
    r.set("machine on")
    assert cnc.wait(lambda: cnc.getp("thermocomp.ready"))

    # the runtime's journal: speed read, alarms, and every written offset within clamp and slew

    def three_reseeds():
        try:
            j = journal(cnc)
        except Exception:
            return None
        not_ready = (j["alarms"].astype(int) & 128) != 0
        return j if (not_ready[:-1] & ~not_ready[1:]).sum() >= 3 else None

    j = cnc.wait(three_reseeds)
    assert np.max(j["speed_rpm"]) == pytest.approx(15000, rel=0.02)
    not_ready = (j["alarms"].astype(int) & 128) != 0
    assert not_ready[0] and not_ready.sum() > 3 and (~not_ready).sum() > 100
    off = j["offset_um"]
    assert np.all(np.isfinite(off)) and np.all(np.abs(off) <= 60.0)
    both = ~not_ready[1:] & ~not_ready[:-1]
    # dt_s: the step the shaper took, on the runtime's one clock (no wall-clock rounding); the
    # limit in force: MAX_RATE while cutting, the fast one in rapids, run-ups and at rest
    dt, limit, cutting = j["dt_s"], j["slew_limit_um_per_s"], j["cutting"] == 1
    assert set(j["cutting_source"]) == {"controller"}
    step = np.abs(np.diff(off))[both]
    allowed = limit[1:][both] * dt[1:][both] + 1e-6  # + the journal's 9 significant digits
    assert np.all(step <= allowed), (step - allowed).max()
    cut = both & cutting[1:] & cutting[:-1]
    assert cut.sum() >= 3  # the G1 move: a cut, by LinuxCNC's own pins
    assert np.all(np.abs(np.diff(off))[cut] <= MAX_RATE * dt[1:][cut] + 1e-6)
    assert (limit[cutting] == MAX_RATE).all() and (limit[~cutting] > MAX_RATE).all()
    # every re-seed starts from zero: the first ready cycle moves at most one slew step
    first = np.flatnonzero(not_ready[:-1] & ~not_ready[1:]) + 1
    assert first.size >= 3
    assert np.all(np.abs(off[first]) <= limit[first] * dt[first] + 1e-6)
    text = (cnc.dir / "thermocomp.jsonl").read_text()
    assert text.count("re-seeding from 0") >= 3 and "counts held at 0" in text


def test_linuxcnc_interpreter_accepts_the_wizards_programs(tmp_path):
    from calibration.nc_programs import calibration_profile, to_nc, validation_profile

    for prog in (calibration_profile(18000), validation_profile(18000, seed=4)):
        path = tmp_path / f"{prog.name}.ngc"
        path.write_text(to_nc(prog, "linuxcnc"))
        r = subprocess.run(
            ["rs274", "-g", str(path)],
            input="\n\n\n",
            capture_output=True,
            text=True,
            timeout=60,
            cwd=tmp_path,
        )
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr
        canon = r.stdout
        dwell = sum(float(x) for x in re.findall(r"DWELL\(([\d.]+)\)", canon))
        assert dwell == pytest.approx(prog.duration_s)
        speeds = [float(x) for x in re.findall(r"SET_SPINDLE_SPEED\(0, ([\d.]+)\)", canon)]
        assert speeds == [s for _, s in prog.segments if s > 0]
        assert canon.count("STOP_SPINDLE_TURNING") >= 1
        assert not re.search(r"STRAIGHT_(TRAVERSE|FEED)", canon)  # no axis moves
    bad = tmp_path / "bad.ngc"
    bad.write_text("%\nG1 X10 F100 Q\nM2\n%\n")
    r = subprocess.run(
        ["rs274", "-g", str(bad)], input="\n\n\n", capture_output=True, text=True, timeout=60
    )
    assert r.returncode != 0


# -- the closed loop: a probe cycle's measurement on HAL pins ---------------------------------

MEASURE_SCRIPT = """
import json
import hal
from cnc_adapters.linuxcnc import LinuxCncAdapter


def publish(comp, value, seq, sigma=None):
    # as a probe cycle does it: the value (and sigma) first, then the counter
    hal.set_p(comp + ".measurement.value", str(value))
    if sigma is not None:
        hal.set_p(comp + ".measurement.sigma", str(sigma))
    hal.set_p(comp + ".measurement.sequence", str(seq))


def read(a):
    try:
        m = a.read_measurement()
    except Exception as err:
        return type(err).__name__ + ": " + str(err)
    return None if m is None else [m.elongation_um, m.sigma_um, m.sequence]


out = {}
a = LinuxCncAdapter(component="tc-meas", machine_state="pins", held_pin="", measurement=True,
                    measurement_sigma=True)
a.open()
publish("tc-meas", 0.005, 7, 0.0005)  # a probe cycle ran before thermocomp started
out["stale"] = [read(a), read(a)]
publish("tc-meas", 0.0125, 8, 0.00075)
out["new"] = [read(a), read(a)]
publish("tc-meas", "nan", 9)
out["nan"] = [read(a), read(a)]
a._link_lost("linuxcnc: status poll failed (test)")  # what a failed linuxcnc.stat poll does
publish("tc-meas", -0.002, 10, 0.0005)  # while the link was down
out["after_reconnect"] = [read(a), read(a), a.reconnects]
publish("tc-meas", 0.001, 10.5)
out["fraction"] = read(a)

b = LinuxCncAdapter(component="tc-meas-s32", machine_state="pins", held_pin="", measurement=True,
                    measurement_sequence_type="s32", measurement_scale=1)  # a cycle that hands over um
b.open()
publish("tc-meas-s32", 4.0, -3)
out["s32"] = [read(b), None]
publish("tc-meas-s32", 6.5, -2)
out["s32"][1] = read(b)
out["s32_pins"] = {p["NAME"]: p["TYPE"] for p in hal.get_info_pins() if p["NAME"].startswith("tc-meas-s32.measurement")}

c = LinuxCncAdapter(component="tc-meas-none", machine_state="pins", held_pin="")
c.open()
out["none"] = [c.can_read_measurement, read(c),
               sorted(p["NAME"] for p in hal.get_info_pins() if p["NAME"].startswith("tc-meas-none.measurement"))]
print("@@", json.dumps(out), flush=True)
"""


def run_in_hal(script: str, hal: str = "loadusr -w {python} {script}\n") -> dict:
    """``script`` as a HAL userspace component of a halrun session (no LinuxCNC), started by the
    HAL file ``hal`` ({python}: the LinuxCNC environment's, {script}: the script's path): what it
    prints after ``@@``, as JSON."""
    directory = Path(tempfile.mkdtemp(prefix="thermocomp-hal-", dir="/tmp"))
    try:
        (directory / "run.py").write_text(script)
        (directory / "run.hal").write_text(
            hal.format(python=linuxcnc_venv() / "bin" / "python", script=directory / "run.py")
        )
        if os.geteuid() == 0:
            shutil.chown(directory, USER)
            for f in directory.iterdir():
                shutil.chown(f, USER)
        env = ["env", f"PYTHONPATH={ROOT}", f"HOME={directory}"]
        with hal_lock():
            r = subprocess.run(
                as_user([*env, "halrun", "-f", str(directory / "run.hal")]),
                check=False,
                capture_output=True,
                text=True,
                timeout=120,
                cwd=directory,
            )
        lines = [x for x in r.stdout.splitlines() if x.startswith("@@ ")]
        assert lines, r.stdout[-2000:] + r.stderr[-2000:]
        return json.loads(lines[-1][3:])
    finally:
        shutil.rmtree(directory, ignore_errors=True)


def test_linuxcnc_measurement_pins_each_value_once_and_a_stale_one_ignored():
    out = run_in_hal(MEASURE_SCRIPT)
    assert out["stale"] == [None, None]
    # mm, the offset's unit (offset_sign -1 does not touch it): + = the tool grew
    (value, sigma, seq), again = out["new"]
    assert (value, sigma, seq, again) == (pytest.approx(12.5), pytest.approx(0.75), 8, None)
    assert re.match(r"BadValueError: linuxcnc: measurement nan \(sequence 9\)", out["nan"][0])
    assert out["nan"][1] is None  # refused once
    (value, sigma, seq), again, reconnects = out["after_reconnect"]
    assert (value, sigma, seq, again, reconnects) == (
        pytest.approx(-2.0),
        pytest.approx(0.5),
        10,
        None,
        1,
    )
    assert re.match(
        r"BadValueError: linuxcnc: measurement sequence 10\.5 is not a whole number",
        out["fraction"],
    )
    assert out["s32"] == [None, [6.5, None, -2]]
    assert out["s32_pins"] == {
        "tc-meas-s32.measurement.value": 2,
        "tc-meas-s32.measurement.sequence": 3,
    }
    assert out["none"] == [False, None, []]  # no measurement: no pins, nothing read


def test_linuxcnc_a_probe_programs_m68_reaches_the_measurement_pins():
    # the documented wiring: motion's analog outputs netted to the component's pins
    nets = (
        "net tc-meas     motion.analog-out-00 => thermocomp.measurement.value\n"
        "net tc-meas-seq motion.analog-out-01 => thermocomp.measurement.sequence\n"
    )
    with linuxcnc_rig("measurement = true", nets) as cnc:
        pins = ("thermocomp.measurement.value", "thermocomp.measurement.sequence")
        assert cnc.getps(pins) == [0.0, 0.0]
        on_and_homed(cnc)
        r = cnc.rsh
        r.set("mdi m68 e0 q0.0125")  # the value first ...
        r.set("mdi m68 e1 q1")  # ... then the counter
        assert cnc.wait(lambda: cnc.getps(pins) == [0.0125, 1.0])
        assert "Traceback" not in cnc.log()  # thermocomp run took measurement = true


# -- the sign of life and taking over: the component's pins in a real HAL ---------------------

LIFE_SCRIPT = """
import json
import hal
from cnc_adapters import Life
from cnc_adapters.linuxcnc import LinuxCncAdapter

# motion as a restarted thermocomp finds it: 0.0042 mm accumulated, its counts pin at 1000
# (the signal kept 580 counts through a machine-on)
motion = hal.component("fake-motion")
motion.newpin("eoffset-request", hal.HAL_FLOAT, hal.HAL_OUT)
motion.newpin("eoffset-counts", hal.HAL_S32, hal.HAL_OUT)
motion.ready()
motion["eoffset-request"] = 0.0042
motion["eoffset-counts"] = 1000

a = LinuxCncAdapter(component="tc-life", machine_state="pins", held_pin="fake-motion.eoffset-request")
a.open()
pins = ("life-counter", "life-toggle", "comp-valid", "eoffset-counts")


def state():
    return [hal.get_value("tc-life." + p) for p in pins]


out = {"exported": state(), "caps": a.capabilities.life_sign}
out["not_ready"] = [a.write(-1.0, Life(1, False)).taken, state()]  # counts held at 0
hal.set_p("tc-life.machine-on", "1")
hal.set_p("tc-life.homed", "1")
a.read()  # takes over: the counts start from what motion holds, 0.0042 mm
out["took_over"] = state()
out["confirm"] = [a.write(None, Life(2, True)).taken, state()]
out["same_beat"] = [a.write(None, Life(2, True)).taken, state()]
out["both"] = [a.write(-5.0, Life(3, True)).taken, state()]
out["refused"] = [a.write(-1e12, Life(4, True)).failure.reason, state()]
out["stop"] = [a.write(None, Life(4, False)).taken, state()]
print("@@", json.dumps(out), flush=True)
"""


def test_linuxcnc_life_pins_beat_with_the_offset_and_a_restart_takes_over_what_motion_holds():
    out = run_in_hal(LIFE_SCRIPT)
    assert out["exported"] == [0, False, False, 0] and out["caps"] is True
    # machine off: the beat goes out (valid false), the counts stay at 0
    assert out["not_ready"] == [True, [1, True, False, 0]]
    # ready: taken over as motion sees it (no move of its own): its pin's 1000 counts, of which
    # 0.0042 mm (420 counts of 1e-5 mm) are held
    assert out["took_over"] == [1, True, False, 1000]
    # a confirm: the counter moves, the toggle flips, valid; the offset untouched
    assert out["confirm"] == [True, [2, False, True, 1000]]
    # the same beat again is no new beat: the toggle stays
    assert out["same_beat"] == [True, [2, False, True, 1000]]
    # the offset and the beat in one call: -5 um is +500 counts on Z, on top of the 580
    assert out["both"] == [True, [3, True, True, 1080]]
    # an offset refused: no beat either (the watchdog must not see a write that did not happen)
    reason, pins = out["refused"]
    assert "does not fit the s32 counts" in reason and pins == [3, True, True, 1080]
    # a clean stop's last beat: valid false, the offset left
    assert out["stop"] == [True, [4, False, False, 1080]]
