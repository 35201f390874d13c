"""``thermocomp wizard`` end to end against the virtual machine tool over OPC UA: unattended
by flags (killed mid-recording and resumed), interactively under a real terminal (pexpect),
and from imported DAQ logs. The model it saves then works in ``thermocomp replay`` and
``thermocomp run --check``."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from compensator.clock import SteppedClock
from compensator.io import read_run_log, write_run_log
from machine_sim import SpindlePlant, preset
from machine_sim.nc import parse_nc
from machine_sim.vcnc import (
    CYCLE_START_PATH,
    NAMESPACE_URI,
    SimClock,
    VirtualCNC,
    VirtualMachine,
    running,
    step,
)

# simulated seconds per wall second, where the wizard runs as its own process against a free-running
# virtual CNC (the bad-input test; nothing there depends on how far the simulated time got)
SCALE = 600.0
RATE_S = 20
THERMOCOMP = [sys.executable, "-m", "thermocomp"]


@pytest.fixture
def vcnc():
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=21), None, clock=SimClock(SCALE))
    with running(VirtualCNC(vm)) as cnc:
        yield vm, cnc


def press_cycle_start(url: str) -> None:
    """What the operator does: the CycleStart button, over OPC UA."""
    from asyncua import ua
    from asyncua.sync import Client

    with Client(url, timeout=10) as c:
        ns = c.get_namespace_index(NAMESPACE_URI)
        c.get_node(f"ns={ns};s={CYCLE_START_PATH}").write_value(
            ua.DataValue(ua.Variant(True, ua.VariantType.Boolean))
        )


class Killed(BaseException):
    """The wizard's process gone at once (as by SIGKILL): no handler of the wizard's catches it."""


class LockStep:
    """The wizard in this process, in lock-step with the virtual CNC, as ``make demo`` runs its
    recorder: the wizard's sleep moves the simulated clock on and steps the machine, so no stall
    of the computer changes what is recorded. Plays the operator too: on the wizard's 'waiting for
    the spindle' it loads the next NC program the wizard wrote and presses Cycle Start."""

    def __init__(self, seed: int = 21):
        self.clock = SteppedClock()
        self.vm = VirtualMachine(
            SpindlePlant(preset("motorized-27k"), seed=seed), None, clock=self.clock
        )
        self.cnc: VirtualCNC | None = None
        self.session_dir: Path | None = None
        self.pending = False  # the wizard waits for the spindle: load the next program
        self.kill_when = None  # (t_s, speed_rpm) of the last logged row -> True: kill now
        self.lines: list[str] = []

    def on_line(self, line: str) -> None:
        self.lines.append(line)
        if "waiting for the spindle" in line:
            self.pending = True

    def sleep(self, seconds: float) -> None:
        self.idle(seconds)
        if self.pending and (self.vm.program is None or self.vm.program_done):
            self.pending = False
            session = json.loads((self.session_dir / "session.json").read_text())
            runs = session["runs"]
            name = "validation" if runs.get("calibration", {}).get("complete") else "calibration"
            if self.vm.program is None or name == "validation":  # (resumed mid-program: it runs on)
                self.vm.load_pending(parse_nc(Path(session["programs"][name]).read_text()))
                press_cycle_start(self.cnc.url)
        if self.kill_when is not None:
            log = self.session_dir / "runs" / "calibration.csv"
            last = log.read_text().splitlines()[-1].split(",") if log.exists() else []
            if last and last[0] != "time_s" and self.kill_when(float(last[0]), float(last[1])):
                self.kill_when = None
                raise Killed

    def idle(self, seconds: float) -> None:
        """The machine goes on for ``seconds`` (the wizard asleep, or not running at all)."""
        self.clock.advance(seconds)
        step(self.cnc)

    def wizard(self, argv: list[str], *, stdin_tty: bool = False, out=None) -> int:
        """``thermocomp wizard ARGV`` in this process, on the lock-step clock; its exit code."""
        from rich.console import Console

        from calibration.wizard import Wizard
        from thermocomp.cli import build_parser

        args = build_parser().parse_args(["wizard", *argv])
        console = Console(
            file=LineTee(self.on_line, out),
            width=130,
            highlight=False,
            force_terminal=stdin_tty,
            color_system=None,
        )
        wiz = Wizard(args, console=console, clock=self.clock, sleep=self.sleep)
        return wiz.run()


class LineTee(io.TextIOBase):
    """A text stream that hands each complete line to ``on_line`` (and writes through to ``out``)."""

    def __init__(self, on_line, out=None):
        self.on_line, self.out, self.buf = on_line, out, ""

    def write(self, text: str) -> int:
        if self.out is not None:
            self.out.write(text)
            self.out.flush()
        self.buf += text
        *lines, self.buf = self.buf.split("\n")
        for line in lines:
            self.on_line(line + "\n")
        return len(text)

    def flush(self) -> None:
        if self.out is not None:
            self.out.flush()


@contextmanager
def at_a_terminal(monkeypatch):
    """A pseudo-terminal as the wizard's stdin and console: yields (the person's side, read and
    answered with pexpect; the stream the wizard's console writes to)."""
    from pexpect import fdpexpect

    master, slave = os.openpty()
    tty_in = open(slave, closefd=False)
    tty_out = open(slave, "w", closefd=False)
    monkeypatch.setattr(sys, "stdin", tty_in)
    try:
        yield fdpexpect.fdspawn(master, encoding="utf-8", timeout=180), tty_out
    finally:
        os.close(master)
        tty_in.close()
        tty_out.close()
        os.close(slave)


def in_thread(fn) -> tuple[threading.Thread, list[object]]:
    """``fn()`` on a thread; its result (or what it raised) lands in the list."""
    result: list[object] = []

    def run() -> None:
        try:
            result.append(fn())
        except BaseException as err:
            result.append(err)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th, result


@pytest.fixture
def lockstep():
    ls = LockStep()
    with running(VirtualCNC(ls.vm, tick_s=None)) as cnc:
        ls.cnc = cnc
        step(cnc)
        yield ls


def unattended_args(work: Path, cnc, *extra: str) -> list[str]:
    return [
        "--yes",
        "--workdir",
        str(work),
        "--machine-id",
        "vmc-7",
        "--model-spindle-id",
        "main",
        "--max-rpm",
        "27000",
        "--source",
        "sensor",
        "--controller",
        cnc.url + "?preset=virtual-cnc",
        "--sensor",
        cnc.url + "?preset=virtual-cnc&range_um=-250,250",
        "--rate-s",
        str(RATE_S),
        "--dialect",
        "linuxcnc",
        "--step-min",
        "10",
        *extra,
    ]


def test_unattended_wizard_survives_a_kill_resumes_and_its_model_works(lockstep, tmp_path):
    ls = lockstep
    work = tmp_path / "cal"
    ls.session_dir = sdir = work / "vmc-7" / "main"
    argv = unattended_args(work, ls.cnc, "--validation", "--cooldown-min", "120")
    log = sdir / "runs" / "calibration.csv"
    # killed 10 min into the cool-down, and away for 15 min while the machine cools on: the
    # recording must show the gap and carry on into the same log
    ls.kill_when = lambda t_s, speed_rpm: t_s > 145 * 60 + 600 and speed_rpm == 0
    with pytest.raises(Killed):
        ls.wizard(argv)
    kept = read_run_log(log)  # readable, and nothing recorded is lost
    # lock-step: one row per 20 s sample, none lost to a slow computer
    assert np.allclose(np.diff(kept.time_s), RATE_S) and kept.speed_rpm.max() == 27000
    assert kept.time_s[-1] > 145 * 60 + 600
    ls.idle(15 * 60)

    assert ls.wizard(argv) == 0
    out = "".join(ls.lines)
    assert "resuming the session" in out and "resuming into" in out
    full = read_run_log(log)
    assert len(full) > len(kept) and np.array_equal(full.time_s[: len(kept)], kept.time_s)
    # the interruption is visible, not papered over: 15 min and one sample period
    assert [round(g.duration_s) for g in full.gaps if g.duration_s > 60] == [15 * 60 + RATE_S]
    # the controller's own sensor channels are logged beside, ready for `fit --inputs`
    assert (
        np.isfinite(full.extras["bearing_temp_c"]).all()
        and np.ptp(full.extras["bearing_temp_c"]) > 3
    )
    assert "validation run, free run on data the fit never saw" in out
    session = json.loads((sdir / "session.json").read_text())
    saved = session["saved"]
    model, report, config = Path(saved["model"]), Path(saved["report"]), Path(saved["config"])
    assert model.name.startswith("vmc-7_main_") and model.suffix == ".json"
    html = report.read_text()
    assert "data:image/png;base64," in html and "validation (held out)" in html

    # the model works in replay, on the held-out validation run
    r = subprocess.run(
        [
            *THERMOCOMP,
            "replay",
            str(sdir / "runs" / "validation.csv"),
            "--model",
            str(model),
            "--json",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    peak = float(np.abs(read_run_log(sdir / "runs" / "validation.csv").elongation_um).max())
    assert peak > 15 and rep["rms_residual_um"] < 0.15 * peak
    # the runtime configuration is valid and reaches the controller
    r = subprocess.run(
        [*THERMOCOMP, "run", "--config", str(config), "--check"], capture_output=True, text=True
    )
    assert r.returncode == 0, r.stdout + r.stderr

    # a second save never overwrites the first model
    first = model.read_bytes()
    ls.lines.clear()
    assert ls.wizard(argv) == 0
    second = Path(json.loads((sdir / "session.json").read_text())["saved"]["model"])
    assert second != model and second.name.endswith(".v2.json") and model.read_bytes() == first
    assert "earlier models kept" in "".join(ls.lines)


def test_the_wizard_killed_by_sigkill_mid_recording_keeps_every_row_and_resumes(vcnc, tmp_path):
    """The real signal, on the wizard's own process: what it had recorded is on disk and readable,
    and a second process resumes into the same log. (How far the free-running machine got in the
    meantime does not matter here: the lock-step test above checks the recording itself.)"""
    vm, cnc = vcnc
    work = tmp_path / "cal"
    sdir = work / "vmc-7" / "main"
    cmd = [
        *THERMOCOMP,
        "wizard",
        *unattended_args(work, cnc, "--no-validation", "--programs-only"),
        "--time-scale",
        str(SCALE),
    ]
    assert subprocess.run(cmd, capture_output=True, text=True, timeout=120).returncode == 0
    vm.load_pending(
        parse_nc(
            Path(
                json.loads((sdir / "session.json").read_text())["programs"]["calibration"]
            ).read_text()
        )
    )
    press_cycle_start(cnc.url)
    cmd.remove("--programs-only")
    log = sdir / "runs" / "calibration.csv"
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    try:
        end = time.monotonic() + 120
        while (
            time.monotonic() < end
            and proc.poll() is None
            and not (log.exists() and _rows_in(log) >= 20)
        ):
            time.sleep(0.05)
        assert proc.poll() is None, "the wizard ended before it was killed"
        proc.send_signal(signal.SIGKILL)  # the worst case: no clean-up at all
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    kept = read_run_log(log)
    assert len(kept) >= 20 and len(kept) == _rows_in(log)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        end = time.monotonic() + 120
        while time.monotonic() < end and proc.poll() is None and _rows_in(log) <= len(kept):
            time.sleep(0.05)
    finally:
        proc.kill()
        out = proc.communicate(timeout=10)[0]
    assert "resuming into" in out, out
    full = read_run_log(log)
    assert len(full) > len(kept) and np.array_equal(full.time_s[: len(kept)], kept.time_s)


def _rows_in(path: Path) -> int:
    return sum(1 for x in path.read_text().splitlines() if x and x[0].isdigit())


def test_interactive_wizard_under_a_real_terminal(lockstep, tmp_path, monkeypatch):
    """Every question asked at a real terminal (a pseudo-terminal, read and answered as a person
    would), the recording in lock-step with the virtual CNC."""
    pytest.importorskip("pexpect")
    ls = lockstep
    work = tmp_path / "cal"
    ls.session_dir = sdir = work / "vmc-9" / "sp1"
    with at_a_terminal(monkeypatch) as (child, tty_out):
        th, result = in_thread(
            lambda: ls.wizard(
                ["--workdir", str(work), "--step-min", "10"], stdin_tty=True, out=tty_out
            )
        )
        answers = [
            ("Machine id", "vmc-9"),
            ("Spindle id", "sp1"),
            ("Maximum spindle speed", "27000"),
            ("Displacement from", "sensor"),
            ("Controller link", ls.cnc.url + "?preset=virtual-cnc"),
            ("Sensor", ls.cnc.url + "?preset=virtual-cnc&range_um=-250,250"),
            ("Sample period", str(RATE_S)),
            ("Test the connections now", "y"),
        ]
        for prompt, answer in answers:
            child.expect(prompt)
            child.sendline(answer)
        child.expect("controller: .*ok")
        child.expect("sensor: .*ok")
        child.expect("NC dialect")
        child.sendline("sinumerik")
        child.expect("validation profile")
        child.sendline("n")
        child.expect("start recording")
        child.sendline("y")
        child.expect("waiting for the spindle")
        child.expect("Chosen", timeout=240)
        child.expect("Written", timeout=120)
        th.join(120)
    assert result == [0], result
    session = json.loads((sdir / "session.json").read_text())
    assert session["programs"]["calibration"].endswith(".mpf")
    saved = session["saved"]
    assert Path(saved["model"]).exists() and Path(saved["config"]).exists()
    r = subprocess.run(
        [
            *THERMOCOMP,
            "replay",
            str(sdir / "runs" / "calibration.csv"),
            "--model",
            saved["model"],
            "--json",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0 and json.loads(r.stdout)["rms_residual_um"] < 1.5


def test_wizard_imports_daq_logs(tmp_path):
    from compensator.speed_programs import paper_calibration, random_validation

    params = preset("motorized-27k")
    epoch = 1.78e9
    speed_t, speed_n = [], []
    for name, prog, seed, day in (
        ("cal", paper_calibration(params.max_rpm), 1, 0),
        ("val", random_validation(params.max_rpm, seed=5), 2, 1),
        ("late", random_validation(params.max_rpm, seed=5), 2, 30),
    ):
        t, n = prog.sample(1.0)
        run = SpindlePlant(params, seed=seed).run(t, n)
        t0 = epoch + day * 86400.0
        if name != "late":  # the controller's own speed log, 1 s, epoch seconds, both days
            speed_t.append(t0 + t)
            speed_n.append(n)
        # the DAQ: a gap probe in mm every 5 s, with ISO time stamps
        k = slice(0, None, 5)
        stamps = np.datetime64("1970-01-01T00:00:00", "ms") + ((t0 + t[k]) * 1000).astype(
            "int64"
        ).astype("timedelta64[ms]")
        gap_mm = 1.0 - run.measured_um[k] / 1000.0
        with open(tmp_path / f"{name}-daq.csv", "w") as fh:
            fh.write("timestamp;gap_mm;temp\n")
            fh.writelines(f"{s}Z;{g:.6f};21.0\n" for s, g in zip(stamps.astype(str), gap_mm))
    write_run_log(
        tmp_path / "speed.csv",
        {"time_s": np.concatenate(speed_t), "speed_rpm": np.concatenate(speed_n)},
    )
    sdir = tmp_path / "w" / "m1" / "s1"
    base = [
        *THERMOCOMP,
        "wizard",
        "--yes",
        "--workdir",
        str(tmp_path / "w"),
        "--machine-id",
        "m1",
        "--model-spindle-id",
        "s1",
        "--max-rpm",
        "27000",
        "--source",
        "import",
        "--dialect",
        "fanuc",
        "--import-time-column",
        "timestamp",
        "--import-displacement-column",
        "gap_mm",
        "--import-scale",
        "-1000",
        "--validation",
        "--import-speed-log",
        str(tmp_path / "speed.csv"),
        "--report-format",
        "md",
        "--import-calibration",
        str(tmp_path / "cal-daq.csv"),
    ]
    # a DAQ file from another day than the speed log: refused in one line, what was imported kept
    r = subprocess.run(
        [*base, "--import-validation", str(tmp_path / "late-daq.csv")],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "same clock" in r.stderr and r.stderr.count("\n") == 1, (
        r.stdout + r.stderr
    )
    assert json.loads((sdir / "session.json").read_text())["runs"]["calibration"]["complete"]
    r = subprocess.run(
        [*base, "--import-validation", str(tmp_path / "val-daq.csv")],
        capture_output=True,
        text=True,
        umask=0o022,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "imported" in r.stdout and "calibration: already recorded" in r.stdout
    # the probe-interval table, judged on the validation run, and its observer kept in the model
    assert "probe every" in r.stdout and (
        "recommended: a probe every" in r.stdout or "no interval" in r.stdout
    )
    saved = json.loads((sdir / "session.json").read_text())["saved"]
    assert "bias_q_um2_per_s" in json.loads(Path(saved["model"]).read_text())["fit"]["observer"]
    # the model, its report and config are readable by all (no secret in them); the session,
    # which keeps the links as typed, by its owner only
    modes = {k: Path(saved[k]).stat().st_mode & 0o777 for k in ("model", "report", "config")}
    assert modes == {"model": 0o644, "report": 0o644, "config": 0o644}
    assert (sdir / "session.json").stat().st_mode & 0o777 == 0o600
    md = Path(saved["report"]).read_text()
    assert saved["report"].endswith(".md") and "![fit](data:image/png;base64," in md
    assert "## Closed loop with a tool setter" in md and "| 1800 s |" in md
    cal = read_run_log(sdir / "runs" / "calibration.csv")
    assert cal.elongation_um.max() > 20  # the gap probe's sign was turned into growth
    r = subprocess.run(
        [
            *THERMOCOMP,
            "replay",
            str(sdir / "runs" / "validation.csv"),
            "--model",
            saved["model"],
            "--json",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["rms_residual_um"] < 2.0
    # the wizard fits as `thermocomp fit` does: the same log gives the same model (the wizard
    # then plans its observer on the validation run, which `fit` has not seen)
    r = subprocess.run(
        [
            *THERMOCOMP,
            "fit",
            str(sdir / "runs" / "calibration.csv"),
            "--output",
            str(tmp_path / "fit.json"),
            "--json",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    wiz, fit = (json.loads(Path(p).read_text()) for p in (saved["model"], tmp_path / "fit.json"))
    for m in (wiz, fit):
        for key in ("created_utc", "sha256"):
            m.pop(key, None)
        m["fit"].pop("observer")
    assert wiz == fit


def test_wizard_bad_input_gives_one_line_and_exit_2(tmp_path, vcnc):
    _vm, cnc = vcnc
    cases = [
        (["--workdir", str(tmp_path), "--model-spindle-id", "s"], "--machine-id is needed"),
        (
            ["--workdir", str(tmp_path), "--machine-id", "m/x", "--model-spindle-id", "s"],
            "--machine-id 'm/x'",
        ),
        (
            ["--workdir", str(tmp_path), "--machine-id", "m", "--model-spindle-id", ".."],
            "--model-spindle-id '..'",
        ),
        (
            ["--workdir", str(tmp_path), "--machine-id", "../../up", "--model-spindle-id", "s"],
            "--machine-id '../../up'",
        ),
        (
            [
                "--workdir",
                str(tmp_path),
                "--machine-id",
                "m",
                "--model-spindle-id",
                "s",
                "--max-rpm",
                "5",
                "--source",
                "sensor",
            ],
            "not a plausible spindle speed",
        ),
        (
            [
                "--workdir",
                str(tmp_path),
                "--machine-id",
                "m",
                "--model-spindle-id",
                "s",
                "--max-rpm",
                "9000",
                "--source",
                "sensor",
                "--controller",
                "opc.tcp://127.0.0.1:1/x?preset=virtual-cnc",
                "--sensor",
                cnc.url + "?preset=virtual-cnc",
            ],
            "controller opc.tcp://127.0.0.1:1",
        ),
        (
            [
                "--workdir",
                str(tmp_path),
                "--machine-id",
                "m",
                "--model-spindle-id",
                "s",
                "--max-rpm",
                "9000",
                "--source",
                "sensor",
                "--controller",
                cnc.url + "?preset=virtual-cnc",
                "--sensor",
                "serial:///dev/nonexistent-probe",
            ],
            "sensor serial:///dev/nonexistent-probe",
        ),
    ]
    for k, (dialect, touches, message) in enumerate(
        (
            ("fanuc", "11", "--probe-touches 11: a whole number from 1 to 10"),
            ("fanuc", "nan", "--probe-touches nan"),
            ("heidenhain", "2", "--probe-touches is not for heidenhain"),
        )
    ):
        cases.append(
            (
                [
                    "--workdir",
                    str(tmp_path),
                    "--machine-id",
                    f"t{k}",
                    "--model-spindle-id",
                    "s",
                    "--max-rpm",
                    "9000",
                    "--source",
                    "tool-setter",
                    "--controller",
                    cnc.url + "?preset=virtual-cnc",
                    "--no-connection-test",
                    "--programs-only",
                    "--dialect",
                    dialect,
                    "--probe-touches",
                    touches,
                ],
                message,
            )
        )
    for args, message in cases:
        r = subprocess.run(
            [*THERMOCOMP, "wizard", "--yes", *args], capture_output=True, text=True, timeout=60
        )
        assert r.returncode == 2, (args, r.stdout, r.stderr)
        assert message in r.stderr and r.stderr.count("\n") == 1, r.stderr


# -- ids and paths: nothing outside the work directory ------------------------------------


def wizard_args(work: Path, *extra: str):
    from thermocomp.cli import build_parser

    return build_parser().parse_args(["wizard", "--yes", "--workdir", str(work), *extra])


def quiet_wizard(args):
    import io

    from rich.console import Console

    from calibration.wizard import Wizard

    return Wizard(args, console=Console(file=io.StringIO()))


BAD_IDS = [
    "..",
    ".",
    "../x",
    "x/..",
    "a/b",
    "/etc",
    "a\\b",
    "a\x00b",
    "a b",
    " ",
    "",
    "a\nb",
    "-rf",
    "_x",
    ".hidden",
    "a..b",
    "x" * 65,
    "ä",
    "a;b",
    "$(id)",
    "a*",
    "x" * 1_000_000,
]


@pytest.mark.parametrize("bad", BAD_IDS, ids=[repr(b[:8]) for b in BAD_IDS])
@pytest.mark.parametrize("flag", ["--machine-id", "--model-spindle-id"])
def test_an_unsafe_id_is_refused_in_one_line_and_nothing_is_written(tmp_path, flag, bad):
    from compensator.errors import ConfigError

    work = tmp_path / "w" / "calibrations"
    ids = {"--machine-id": "m1", "--model-spindle-id": "s1", flag: bad}
    wiz = quiet_wizard(
        wizard_args(work, *(f"{k}={v}" for k, v in ids.items()), "--max-rpm", "9000")
    )
    with pytest.raises(ConfigError) as info:
        wiz.step_identify()
    msg = str(info.value)
    assert msg.startswith(f"{flag} ") and "A-Z a-z 0-9 '_' '.' '-'" in msg and "'..'" in msg, msg
    assert repr(bad.strip())[:20] in msg and "\n" not in msg and len(msg) < 300
    assert list(tmp_path.rglob("*")) == []  # not even the work directory


@pytest.mark.parametrize("good", ["vmc-7", "A.b_c-9", "0", "x" * 64, "  padded  "])
def test_a_safe_id_names_the_session_directory(tmp_path, good):
    work = tmp_path / "w"
    wiz = quiet_wizard(
        wizard_args(
            work,
            "--machine-id",
            good,
            "--model-spindle-id",
            "s1",
            "--max-rpm",
            "9000",
            "--source",
            "import",
        )
    )
    wiz.step_identify()
    assert wiz.dir == work.resolve() / good.strip() / "s1"
    assert (wiz.dir / "session.json").is_file()


def test_a_symlink_out_of_the_work_directory_is_refused(tmp_path):
    from compensator.errors import ConfigError

    work, outside = tmp_path / "w", tmp_path / "outside"
    work.mkdir()
    outside.mkdir()
    (work / "m1").symlink_to(outside)
    wiz = quiet_wizard(
        wizard_args(work, "--machine-id", "m1", "--model-spindle-id", "s1", "--max-rpm", "9000")
    )
    with pytest.raises(ConfigError, match="the session directory .* is outside the work directory"):
        wiz.step_identify()
    assert list(outside.iterdir()) == []


def test_an_edited_session_cannot_send_a_run_log_outside(tmp_path):
    from calibration.wizard import SESSION_FORMAT
    from compensator.errors import ConfigError

    work, outside = tmp_path / "w", tmp_path / "outside.csv"
    sdir = work / "m1" / "s1"
    sdir.mkdir(parents=True)
    (sdir / "session.json").write_text(
        json.dumps(
            {
                "format": SESSION_FORMAT,
                "runs": {
                    "calibration": {
                        "log": str(sdir / ".." / ".." / ".." / "outside.csv"),
                        "complete": False,
                    }
                },
            }
        )
    )
    (tmp_path / "daq.csv").write_text("time_s,displacement_um,speed_rpm\n0,0,0\n1,0,0\n")
    wiz = quiet_wizard(
        wizard_args(
            work,
            "--machine-id",
            "m1",
            "--model-spindle-id",
            "s1",
            "--max-rpm",
            "9000",
            "--source",
            "import",
            "--dialect",
            "fanuc",
            "--no-validation",
            "--import-calibration",
            str(tmp_path / "daq.csv"),
            "--import-speed-column",
            "speed_rpm",
        )
    )
    wiz.step_identify()
    wiz.step_programs()
    with pytest.raises(
        ConfigError, match=f"the calibration run log {outside} is outside the work directory"
    ):
        wiz.step_acquire()
    assert not outside.exists()
