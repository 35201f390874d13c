"""NC programs of the calibration and validation profiles, checked line by line against each
dialect's documented syntax, and run back through the virtual CNC's interpreter."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from calibration.nc_programs import (
    DIALECTS,
    MAX_DWELL_S,
    calibration_profile,
    rest_hours,
    to_nc,
    validation_profile,
)
from machine_sim.nc import NcSyntaxError, parse_nc

# What each control's manual allows for the blocks we write (no axis words anywhere).
SYNTAX = {
    # Fanuc: % tape marks, O number, (COMMENT) in capitals, S/M03/M05, G04 X<s> with a
    # decimal point (seconds), M30 end
    "fanuc": [
        r"%",
        r"O\d{4} \([A-Z0-9_ ]+\)",
        r"\([A-Z0-9 .,:+\[\]-]*\)",
        r"S\d+ M03",
        r"M05",
        r"G04 X\d+\.\d",
        r"M30",
    ],
    # SINUMERIK: %_N_<name>_MPF and ;$PATH archive header, ; comments, S M3/M5,
    # G4 F<s> alone in its block, M30
    "sinumerik": [
        r"%_N_[A-Z0-9_]+_MPF",
        r";\$PATH=/_N_MPF_DIR",
        r"; .*",
        r"S\d+ M3",
        r"M5",
        r"G4 F\d+(\.\d)?",
        r"M30",
    ],
    # TNC Klartext: numbered blocks, BEGIN/END PGM, ; comments, TOOL CALL Z S (speed only),
    # M3/M5 blocks, cycle 9 dwell (9.0 then 9.1, at most 3600 s)
    "heidenhain": [
        r"\d+ BEGIN PGM \w+ MM",
        r"\d+ ; .*",
        r"\d+ TOOL CALL Z S\d+",
        r"\d+ M3",
        r"\d+ M5",
        r"\d+ CYCL DEF 9\.0 DWELL TIME",
        r"\d+ CYCL DEF 9\.1 DWELL \d+(\.\d)?",
        r"\d+ END PGM \w+ MM",
    ],
    # RS274/NGC (LinuxCNC): % delimiters, (comments), S M3/M5, G4 P<s> (seconds), M2
    "linuxcnc": [r"%", r"\([^()]*\)", r"S\d+ M3", r"M5", r"G4 P\d+(\.\d)?", r"M2"],
}


def programs():
    for max_rpm in (8000.0, 24000.0, 42000.0):
        yield calibration_profile(max_rpm)
        yield validation_profile(max_rpm, seed=2)


@pytest.mark.parametrize("dialect", DIALECTS)
def test_every_line_follows_the_dialects_documented_syntax(dialect):
    for prog in programs():
        text = to_nc(prog, dialect, name="calib")
        lines = text.splitlines()
        for k, line in enumerate(lines, start=1):
            assert any(re.fullmatch(p, line) for p in SYNTAX[dialect]), (
                f"{dialect} line {k}: {line!r}"
            )
        dwell = {
            "fanuc": r"G04 X([\d.]+)",
            "sinumerik": r"G4 F([\d.]+)",
            "linuxcnc": r"G4 P([\d.]+)",
            "heidenhain": r"\d+ CYCL DEF 9\.1 DWELL ([\d.]+)",
        }[dialect]
        dwells = [float(m.group(1)) for m in (re.fullmatch(dwell, ln) for ln in lines) if m]
        assert sum(dwells) == pytest.approx(prog.duration_s)
        assert max(dwells) <= MAX_DWELL_S
        speeds = [int(x) for x in re.findall(r"S(\d+)", text)]
        assert max(speeds) == max(s for _, s in prog.segments)
        if dialect in ("fanuc", "linuxcnc"):
            assert lines[0] == "%" and lines[-1] == "%"
            assert lines[-2] == ("M30" if dialect == "fanuc" else "M2")
        if dialect == "heidenhain":
            assert [int(ln.split()[0]) for ln in lines] == list(range(len(lines)))
            assert (
                lines[0].split()[3] == lines[-1].split()[3]
            )  # BEGIN and END name the same program
            for k, ln in enumerate(lines):
                if ln.endswith("CYCL DEF 9.0 DWELL TIME"):
                    assert "CYCL DEF 9.1 DWELL" in lines[k + 1]
            # the first speed block is followed by M3 (TOOL CALL alone does not start the spindle)
            first = next(k for k, ln in enumerate(lines) if "TOOL CALL" in ln)
            assert lines[first + 1].endswith(" M3")
        assert not re.search(r"\b[XYZABC][-+]?\d", re.sub(r"\(.*?\)|;.*|G04 X[\d.]+", "", text)), (
            "an axis word: the program must not move an axis"
        )


@pytest.mark.parametrize("dialect", DIALECTS)
def test_the_virtual_cnc_runs_the_program_as_the_profile(dialect):
    for prog in programs():
        run = parse_nc(to_nc(prog, dialect))
        assert run.segments == prog.segments


def test_calibration_profile_has_the_papers_phases_scaled_to_the_spindle():
    p = calibration_profile(18000.0)
    speeds = [s for _, s in p.segments]
    assert speeds[:9] == [2000.0 * i for i in range(1, 10)]  # staircase up to the maximum
    assert speeds[9] == 8000.0 and speeds[10] == 12000.0 and speeds[11] == 0.0  # abrupt drops, stop
    assert speeds[12:16] == [4000.0, 14000.0, 6000.0, 16000.0]  # fluctuating
    assert speeds[-1] == 0.0 and p.segments[-1][0] == 3600.0  # cool-down
    assert p.duration_s == pytest.approx(350 * 60)
    short = calibration_profile(18000.0, step_min=10, cooldown_min=30)
    assert short.duration_s == pytest.approx((290 / 2 + 30) * 60)
    v = validation_profile(18000.0, seed=3)
    assert v.segments != p.segments and max(s for _, s in v.segments) <= 18000.0
    with pytest.raises(ValueError):
        calibration_profile(float("nan"))


def test_rest_time_before_a_cold_start():
    assert rest_hours(None) == 8.0
    assert rest_hours((1200.0, 9000.0)) == 13.0  # 5 x 2.5 h, rounded up


@pytest.mark.parametrize(
    "text,match",
    [
        ("%\nS1000 M3\nG1 X10 F100\nM2\n%\n", "only a dwell"),
        ("%\nS1000 M3\nG4 P10\n%\n", "no end of program"),
        ("O1000\nS1000 M03\nG04 X10\nM30\n", "decimal point"),
        ("0 BEGIN PGM A MM\n1 TOOL CALL Z S100\n2 M3\n3 CYCL DEF 9.0 DWELL TIME\n4 M5\n", "9.1"),
        ("; x\nS100 M3\nG4 F10 S200\nM30\n", "alone"),
    ],
)
def test_the_interpreter_refuses_what_a_control_would(text, match):
    with pytest.raises(NcSyntaxError, match=match):
        parse_nc(text)


def test_profile_command(tmp_path):
    out = tmp_path / "calib.h"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "thermocomp",
            "profile",
            "--max-rpm",
            "12000",
            "--dialect",
            "heidenhain",
            "--output",
            str(out),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert "5.83 h" in r.stdout and "rested for 8 h" in r.stdout
    assert parse_nc(out.read_text()).duration_s == pytest.approx(350 * 60)
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "thermocomp",
            "profile",
            "--max-rpm",
            "12000",
            "--dialect",
            "mazak",
            "--output",
            str(tmp_path / "x"),
        ],
        capture_output=True,
        text=True,
    )
    # argparse's refusal: the usage, then one error line
    assert (
        bad.returncode == 2
        and "error: argument --dialect: invalid choice: 'mazak'" in bad.stderr.splitlines()[-1]
    )
    assert not (tmp_path / "x").exists()
