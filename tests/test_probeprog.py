"""Tool-setter probe cycles (issue 17): every line checked against the dialect's syntax, the
handshake order (value, then counter), the configured variables, refusals, and the LinuxCNC
cycle run by LinuxCNC's own interpreter (rs274) against a .var file, twice: reference, measure."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from calibration.probeprog import (
    COUNTER_WRAP,
    DEFAULT_VARIABLES,
    DIALECTS,
    ProbeCycle,
    measuring_time_s,
    probe_cycle,
    probe_program,
    var_file_lines,
)
from compensator.errors import ConfigError

NUM = r"-?\d+\.\d{3}"  # millimetres, always with the decimal point (Fanuc reads "10" as 10 um)

# What each control's manual allows for the blocks we write.
SYNTAX = {
    # Fanuc Custom Macro B: O number, (COMMENTS) in capitals, IF [..] THEN, #3000 alarms,
    # G31 skip, G53 machine moves, G04 X<s>, M30 between % tape marks
    "fanuc": [
        r"%",
        r"O\d{4} \([A-Z0-9_]+\)",
        r"\([^()a-z]*\)",
        r"G17 G21 G40 G80 G90 G94",
        r"IF \[#\d+ EQ #0\] THEN #3000 = 102 \(NO COLD REFERENCE\)",
        r"T\d+ M06",
        r"M05",
        r"S\d+ M03",
        rf"G53 G00 Z{NUM}",
        rf"G53 G00 X{NUM} Y{NUM}",
        r"G04 X\d+\.\d",
        r"#1 = #5043",
        rf"G91 G31 Z-{NUM} F\d+\.\d",
        r"G90",
        (
            rf"IF \[\[#5063 - #1 \+ {NUM}\] LT 0\.010\] THEN "
            r"#3000 = 101 \(SETTER NOT TRIPPED\)"
        ),
        r"#2 = #5063",
        rf"G91 G00 Z{NUM}",
        r"#3 = #5063 \+ #5023 - #5043",
        (
            rf"IF \[ABS\[#5063 - #2\] GT {NUM}\] THEN #3000 = 101 "
            r"\(SETTER NOT TRIPPED\)"
        ),
        r"#\d+ = #3",
        r"#4 = \[#3 - #\d+\] \* 1000",
        r"IF \[ABS\[#4\] GT \d+\.\d\] THEN #3000 = 103 \(GROWTH OUT OF RANGE\)",
        r"#\d+ = #4",
        r"(#\d+) = \1 \+ 1",
        rf"IF \[(#\d+) GT {COUNTER_WRAP}\] THEN \1 = 1",
        r"M30",
        # repeated touches: WHILE [..] DO1 .. END1, the mean in #3
        r"#[67] = 0",
        r"WHILE \[#7 LT \d+\] DO1",
        r"IF \[#7 EQ 0\] THEN #5 = #3",
        r"IF \[ABS\[#3 - #5\] \* 1000 GT \d+\.\d\] THEN #3000 = 104 \(TOUCHES DISAGREE\)",
        r"#6 = #6 \+ #3",
        r"END1",
        r"#3 = #6 / \d+",
    ],
    # SINUMERIK: archive header, ; comments, DEF first, MEAS=n G1 with STOPRE before $AC_MEA and
    # $AA_MM, SUPA (machine coordinates), G4 F<s> alone, IF .. GOTOF label, SETAL cycle alarms
    "sinumerik": [
        r"%_N_[A-Z0-9_]+_MPF",
        r";\$PATH=/_N_MPF_DIR",
        r"; [^a-z]*",
        r"DEF REAL TC_FAST, TC_TRIP, TC_UM(, TC_FIRST, TC_SUM)?",
        r"G17 G40 G71 G90 G94",
        r"IF R\d+==0 GOTOF TC_NOREF",
        r"T\d+ M6",
        r"M5",
        r"S\d+ M3",
        rf"SUPA G0 Z{NUM}",
        rf"SUPA G0 X{NUM} Y{NUM}",
        r"G4 F\d+(\.\d+)?",
        rf"MEAS=[12] G1 G91 Z-{NUM} F\d+(\.\d+)?",
        r"STOPRE",
        r"IF \$AC_MEA\[[12]\]==0 GOTOF TC_NOTRIP",
        r"TC_(FAST|TRIP)=\$AA_MM\[Z\]",
        rf"G0 G91 Z{NUM}",
        rf"IF ABS\(TC_TRIP-TC_FAST\)>{NUM} GOTOF TC_NOTRIP",
        r"G90",
        r"R\d+=TC_TRIP",
        r"TC_UM=\(TC_TRIP-R\d+\)\*1000",
        r"IF ABS\(TC_UM\)>\d+(\.\d+)? GOTOF TC_RANGE",
        r"R\d+=TC_UM",
        r"(R\d+)=\1\+1",
        rf"IF R\d+>{COUNTER_WRAP}",
        r"R\d+=1",
        r"ENDIF",
        r"M30",
        r"TC_(NOREF|NOTRIP|RANGE|SPREAD):",
        r"SETAL\(6500[1-4]\)",
        # repeated touches: a loop by label (GOTOB), IF .. ENDIF, the mean in TC_TRIP
        r"DEF INT TC_K",
        r"TC_(SUM|K)=0",
        r"TC_TOUCH:",
        r"IF TC_K==0",
        r"TC_FIRST=TC_TRIP",
        r"IF ABS\(TC_TRIP-TC_FIRST\)\*1000>\d+(\.\d+)? GOTOF TC_SPREAD",
        r"TC_SUM=TC_SUM\+TC_TRIP",
        r"TC_K=TC_K\+1",
        r"IF TC_K<\d+ GOTOB TC_TOUCH",
        r"TC_TRIP=TC_SUM/\d+",
    ],
    # TNC Klartext: numbered blocks (a "~" continues a block on unnumbered lines), BEGIN/END PGM,
    # FN 9/11/12 jumps to LBL, FN 14 errors, FN 17/18 ID50 tool table, TCH PROBE 481 with its Q
    # parameters, formulas, QL locals and QR non-volatile parameters
    "heidenhain": [
        r"\d+ BEGIN PGM \w+ MM",
        r"\d+ ; [^a-z]*",
        r"\d+ FN 9: IF \+(Q[RL]?\d+|0) EQU \+\d+ GOTO LBL \d+",
        r"\d+ TOOL CALL \d+ Z",
        r"\d+ M5",
        r"\d+ CYCL DEF 9\.0 DWELL TIME",
        r"\d+ CYCL DEF 9\.1 DWELL \d+",
        r"\d+ FN 18: SYSREAD QL[12] = ID50 NR[14] IDX\d+",
        r"\d+ TCH PROBE 481 TOOL LENGTH ~",
        r"  Q340=\+[01] ;CHECK ~",
        r"  Q260=[+-]\d+\.\d{3} ;CLEARANCE HEIGHT ~",
        r"  Q341=\+0 ;PROBING THE TEETH",
        r"\d+ FN 17: SYSWRITE ID50 NR4 IDX\d+ = QL2",
        r"\d+ FN 0: Q[RL]?\d+ = \+(QL\d+|\d+)",
        r"\d+ QL3 = \( QL1 \+ Q115 - QR\d+ \) \* 1000",
        r"\d+ FN 1[12]: IF \+Q[RL]?\d+ (GT|LT) [+-]\d+ GOTO LBL \d+",
        r"\d+ (QR?\d+) = \1 \+ 1",
        r"\d+ LBL \d+",
        r"\d+ FN 14: ERROR = 20[1-3]",
        r"\d+ END PGM \w+ MM",
    ],
    # RS274/NGC: % delimiters, (comments), o-word if/endif with (ABORT,), G38.2 probing, G53
    # machine moves, named and numbered parameters, M68 E<n> Q<value> to HAL, M2
    "linuxcnc": [
        r"%",
        r"\([^()]*\)",
        r"G17 G21 G40 G49 G90 G94",
        r"o10[0-5] (if \[.+\]|endif|repeat \[\d+\]|endrepeat)",
        r"T\d+ M6",
        r"M5",
        r"S\d+ M3",
        rf"G53 G0 Z{NUM}",
        rf"G53 G0 X{NUM} Y{NUM}",
        r"G4 P\d+(\.\d+)?",
        rf"(G91 )?G38\.2 Z-{NUM} F\d+\.\d",
        rf"(G91 )?G0 Z{NUM}",
        r"G90",
        r"#<trip_mm> = \[#5063 \+ #\[5203 \+ 20 \* #5220\] \+ #5213 \* #5210\]",
        r"#\d+ = #<trip_mm>",
        r"#<growth_um> = \[\[#<trip_mm> - #\d+\] \* 1000\]",
        r"#\d+ = #<growth_um>",
        r"(#\d+) = \[\1 \+ 1\]",
        r"#\d+ = 1",
        r"M68 E\d+ Q#\d+",
        r"M2",
        # repeated touches: named parameters, the mean in #<trip_mm>
        r"#<(sum_mm|k)> = 0",
        r"#<first_mm> = #<trip_mm>",
        r"#<sum_mm> = \[#<sum_mm> \+ #<trip_mm>\]",
        r"#<k> = \[#<k> \+ 1\]",
        r"#<trip_mm> = \[#<sum_mm> / \d+\]",
    ],
}

VALUE_WRITE = {
    "fanuc": r"{v} = #4",
    "sinumerik": r"{v}=TC_UM",
    "heidenhain": r"\d+ FN 0: {v} = \+QL3",
    "linuxcnc": r"{v} = #<growth_um>",
}
COUNTER_STEP = {
    "fanuc": r"{c} = {c} \+ 1",
    "sinumerik": r"{c}={c}\+1",
    "heidenhain": r"\d+ {c} = {c} \+ 1",
    "linuxcnc": r"{c} = \[{c} \+ 1\]",
}


def cycles(dialect: str):
    """The cycle in the shapes the options give it: defaults, at the setter, a laser setter."""
    if dialect == "heidenhain":
        yield probe_cycle(dialect, approach_z_mm=100)
        yield probe_cycle(
            dialect,
            tool=12,
            approach_z_mm=-25.5,
            settle_s=0,
            reference_var="QR7",
            value_var="Q1650",
            counter_var="QR9",
            max_um=150,
        )
        return
    yield probe_cycle(dialect)
    yield probe_cycle(
        dialect,
        tool=7,
        setter_x_mm=-412.5,
        setter_y_mm=-20,
        approach_z_mm=-5,
        travel_mm=25,
        backoff_mm=2,
        fast_feed_mm_min=500,
        slow_feed_mm_min=10,
        settle_s=3.5,
    )
    yield probe_cycle(dialect, spindle="low", low_rpm=800, approach_z_mm=-50, max_um=120)
    yield probe_cycle(dialect, spindle="keep", touches=4, spread_um=2.5)


def line_index(lines: list[str], pattern: str) -> int:
    hits = [k for k, ln in enumerate(lines) if re.fullmatch(pattern, ln)]
    assert len(hits) == 1, (pattern, hits)
    return hits[0]


@pytest.mark.parametrize("reference", [False, True], ids=["measure", "reference"])
@pytest.mark.parametrize("dialect", DIALECTS)
def test_every_line_follows_the_dialects_syntax(dialect, reference):
    for c in cycles(dialect):
        text = probe_program(c, reference=reference)
        lines = text.splitlines()
        for k, line in enumerate(lines, start=1):
            assert any(re.fullmatch(p, line) for p in SYNTAX[dialect]), (
                f"{dialect} line {k}: {line!r}"
            )
        assert text.endswith("\n") and "\t" not in text
        if dialect in ("fanuc", "linuxcnc"):
            assert (
                lines[0] == "%"
                and lines[-1] == "%"
                and lines[-2] == ("M30" if dialect == "fanuc" else "M2")
            )
            assert all(ln.count("[") == ln.count("]") for ln in lines)  # macro brackets balance
        if dialect == "fanuc":
            # Macro B groups with [ ]; ( ) only around a comment that ends the block
            assert all(re.fullmatch(r"[^()]*(\([^()]*\))?", ln) for ln in lines)
        if dialect == "sinumerik":
            first = next(ln for ln in lines if not ln.startswith((";", "%")))
            assert first.startswith("DEF ")  # definitions before the first executable block
            for label in set(re.findall(r"GOTO[FB] (\w+)", text)):
                assert lines.count(f"{label}:") == 1
            # a block IF (no jump on its line) closes with ENDIF
            assert sum(ln.startswith("IF ") and "GOTO" not in ln for ln in lines) == lines.count(
                "ENDIF"
            )
            for k, ln in enumerate(lines):  # GOTOB jumps back, GOTOF forward
                for way, label in re.findall(r"GOTO([FB]) (\w+)", ln):
                    assert (lines.index(f"{label}:") < k) == (way == "B"), ln
            for k, ln in enumerate(lines):  # a measurement's result is read after STOPRE
                if ln.startswith("MEAS="):
                    assert lines[k + 1] == "STOPRE" and "$AC_MEA" in lines[k + 2]
        if dialect == "heidenhain":
            numbers = [int(ln.split()[0]) for ln in lines if not ln.startswith(" ")]
            assert numbers == list(range(len(numbers)))
            assert (
                lines[0].split()[3] == lines[-1].split()[3]
            )  # BEGIN and END name the same program
            for n in set(re.findall(r"GOTO LBL (\d+)", text)):
                assert sum(bool(re.fullmatch(rf"\d+ LBL {n}", ln)) for ln in lines) == 1
            k = line_index(lines, r"\d+ TCH PROBE 481 TOOL LENGTH ~")
            assert [ln.split("=")[0].strip() for ln in lines[k + 1 : k + 4]] == [
                "Q340",
                "Q260",
                "Q341",
            ]
            assert f"Q340=+{0 if reference else 1} " in text  # 0 measures L, 1 checks against it
        if dialect == "linuxcnc":
            assert text.count(" if ") == text.count(" endif")


@pytest.mark.parametrize("dialect", DIALECTS)
def test_the_counter_is_incremented_after_the_value_is_written(dialect):
    for c in cycles(dialect):
        lines = probe_program(c).splitlines()
        v, n = re.escape(str(c.value_var)), re.escape(str(c.counter_var))
        value_at = line_index(lines, VALUE_WRITE[dialect].format(v=v))
        counter_at = line_index(lines, COUNTER_STEP[dialect].format(c=n))
        assert value_at < counter_at
        # nothing between them can fail, and every check and probing move comes before the value
        between = lines[value_at + 1 : counter_at]
        assert not any(re.search(r"GOTO|#3000|ABORT|G31|G38|MEAS=|TCH PROBE", ln) for ln in between)
        checks = [
            k
            for k, ln in enumerate(lines)
            if re.search(r"#3000|ABORT|GOTOF TC_|GOTO LBL 9[1-3]", ln)
        ]
        probing = [k for k, ln in enumerate(lines) if re.search(r"G31|G38\.2|MEAS=|TCH PROBE", ln)]
        assert checks and max(checks) < value_at and max(probing) < value_at
        # the counter wraps to 1, never 0 (0 means: never measured)
        wrap = "\n".join(lines[counter_at:])
        assert str(COUNTER_WRAP) in wrap or str(COUNTER_WRAP + 1) in wrap
        assert re.search(rf"{n} ?= ?\+?1\b", wrap)
        if dialect == "linuxcnc":  # HAL sees the value before the counter as well
            e_value = line_index(lines, rf"M68 E{c.value_aout} Q{v}")
            e_counter = line_index(lines, rf"M68 E{c.counter_aout} Q{n}")
            assert counter_at < e_value < e_counter


@pytest.mark.parametrize("dialect", DIALECTS)
def test_the_reference_program_writes_only_the_reference(dialect):
    for c in cycles(dialect):
        text = probe_program(c, reference=True)
        body = "\n".join(
            ln for ln in text.splitlines() if not re.match(r"(\d+ )?[(;]", ln)
        )  # no comments
        assert re.search(rf"{re.escape(str(c.reference_var))} ?= ?", body)
        assert not re.search(rf"{re.escape(str(c.value_var))}\b", body)
        assert not re.search(rf"{re.escape(str(c.counter_var))}\b", body)


@pytest.mark.parametrize("dialect", DIALECTS)
def test_the_configured_variables_and_tool_are_used(dialect):
    custom = {
        "fanuc": ("#600", "#150", "#151"),
        "sinumerik": ("R100", "R101", "R102"),
        "heidenhain": ("QR40", "QR41", "Q1700"),
        "linuxcnc": ("#1000", "#1001", "#1002"),
    }[dialect]
    extra = {"approach_z_mm": 50} if dialect == "heidenhain" else {}
    c = probe_cycle(
        dialect,
        tool=42,
        reference_var=custom[0],
        value_var=custom[1],
        counter_var=custom[2],
        **extra,
    )
    assert (str(c.reference_var), str(c.value_var), str(c.counter_var)) == custom
    text = probe_program(c)
    for var in custom:
        assert re.search(rf"{re.escape(var)}\b", text)
    for var in DEFAULT_VARIABLES[dialect]:
        assert not re.search(rf"{re.escape(var)}\b", text), var
    assert re.search(r"\bT(OOL CALL )?42\b", text)
    # a bare number takes the dialect's usual kind of variable
    bare = probe_cycle(
        dialect,
        value_var="150",
        counter_var="151",
        reference_var="600" if dialect == "fanuc" else "40",
        **extra,
    )
    assert str(bare.value_var).endswith("150") and str(bare.reference_var)[0] in "#RQ"


# per dialect: the slow touch, the loop's head and end, the mean and the spread alarm
LOOP = {
    "fanuc": (
        r"G91 G31 Z-{b} F",
        r"WHILE \[#7 LT {n}\] DO1",
        r"END1",
        r"#3 = #6 / {n}",
        r"GT {u}\] THEN #3000 = 104",
    ),
    "sinumerik": (
        r"MEAS=1 G1 G91 Z-{b} F",
        r"TC_TOUCH:",
        r"IF TC_K<{n} GOTOB TC_TOUCH",
        r"TC_TRIP=TC_SUM/{n}",
        r"\*1000>{u:g} GOTOF TC_SPREAD",
    ),
    "linuxcnc": (
        r"G38\.2 Z-{b} F",
        r"o103 repeat \[{n}\]",
        r"o103 endrepeat",
        r"#<trip_mm> = \[#<sum_mm> / {n}\]",
        r"\* 1000 GT {u:g}\]",
    ),
}


@pytest.mark.parametrize("dialect", sorted(LOOP))
@pytest.mark.parametrize("reference", [False, True], ids=["measure", "reference"])
def test_repeated_touches_are_averaged_and_must_agree(dialect, reference):
    """With --touches N the slow touch runs N times inside one loop, the trip used is their sum
    over N, and a touch farther than --spread-um from the first is an alarm before anything is
    written; the cold reference is averaged the same way. One touch writes no loop at all."""
    n, u = 4, 2.5
    c = probe_cycle(dialect, spindle="keep", touches=n, spread_um=u)
    lines = probe_program(c, reference=reference).splitlines()
    slow, head, end, mean, alarm = (p.format(b="0.400", n=n, u=u) for p in LOOP[dialect])
    at = {
        name: [k for k, ln in enumerate(lines) if re.search(p, ln)]
        for name, p in (
            ("slow", slow),
            ("head", head),
            ("end", end),
            ("mean", mean),
            ("alarm", alarm),
        )
    }
    assert all(len(v) == 1 for v in at.values()), (
        at
    )  # one slow touch, written once, inside one loop
    assert at["head"][0] < at["slow"][0] < at["alarm"][0] < at["end"][0] < at["mean"][0]
    written = [
        k for k, ln in enumerate(lines) if re.match(r"(#521|R21|#3021|#520|R20|#3020) ?=", ln)
    ]
    assert written and min(written) > at["mean"][0]  # nothing is written before the mean
    assert "MEAN OF 4 SLOW TOUCHES" in "\n".join(lines)
    single = probe_program(probe_cycle(dialect, spindle="keep"), reference=reference)
    assert not any(re.search(p.format(b="0.400", n=1, u=5), single) for p in LOOP[dialect][1:3])
    # the laser's back-off (0.2 mm at 20 mm/min): each further touch 1.2 s longer
    assert measuring_time_s(c) - measuring_time_s(
        probe_cycle(dialect, spindle="keep")
    ) == pytest.approx(3 * 1.2)


def test_measuring_time_and_spindle_words():
    c = probe_cycle(
        "fanuc", settle_s=2, travel_mm=10, fast_feed_mm_min=200, backoff_mm=1, slow_feed_mm_min=20
    )
    assert measuring_time_s(c) == pytest.approx(2 + 3 + 6)  # settle, 10 mm at 200, 2 mm at 20
    assert "ABOUT 11 S" in probe_program(c)
    low = probe_program(probe_cycle("sinumerik", spindle="low", low_rpm=600)).splitlines()
    assert (
        low.index("S600 M3")
        < next(k for k, ln in enumerate(low) if ln.startswith("MEAS="))
        < low.index("M5")
    )
    stop = probe_program(probe_cycle("linuxcnc")).splitlines()
    assert stop.index("M5") < next(k for k, ln in enumerate(stop) if "G38.2" in ln)
    assert not any(re.match(r"S\d+ M3", ln) for ln in stop)
    assert probe_program(probe_cycle("sinumerik", probe_input=2)).count("MEAS=2 ") == 2
    assert var_file_lines(probe_cycle("linuxcnc", value_var="40", counter_var="35")) == [
        "35 0",
        "40 0",
        "3020 0",
    ]


@pytest.mark.parametrize(
    "dialect,options,match",
    [
        ("mazak", {}, "choose from"),
        ("fanuc", {"spindle": "fast"}, "stop, low or keep"),
        ("heidenhain", {"spindle": "keep", "approach_z_mm": -5}, "keep is not for heidenhain"),
        ("fanuc", {"spindle": "low"}, "needs --low-rpm"),
        ("fanuc", {"low_rpm": 500}, "goes with --probe-spindle low"),
        ("fanuc", {"spindle": "low", "low_rpm": 0}, "--low-rpm"),
        ("fanuc", {"settle_s": "abc"}, "not a number"),
        ("fanuc", {"settle_s": float("nan")}, "--settle-s"),
        ("fanuc", {"settle_s": -1}, "--settle-s"),
        ("fanuc", {"tool": 0}, "--tool"),
        ("fanuc", {"tool": 2.5}, "whole number"),
        ("fanuc", {"value_var": "#50"}, "--value-var"),  # a local variable
        ("fanuc", {"counter_var": "#1000"}, "--counter-var"),  # a system variable
        ("fanuc", {"reference_var": "#150"}, "survive a power cycle"),  # cleared at power off
        ("fanuc", {"value_var": "R21"}, "--value-var"),
        ("fanuc", {"value_var": "#520"}, "three different"),
        ("fanuc", {"counter_var": "five"}, "--counter-var"),
        ("sinumerik", {"value_var": "#21"}, "--value-var"),
        (
            "heidenhain",
            {"approach_z_mm": 50, "value_var": "Q5"},
            "--value-var",
        ),  # Q0-Q99: cycles' own
        ("heidenhain", {"approach_z_mm": 50, "reference_var": "Q1600"}, "QR parameter"),
        ("heidenhain", {}, "--approach-z-mm"),
        (
            "heidenhain",
            {"approach_z_mm": 50, "spindle": "low", "low_rpm": 500},
            "not for heidenhain",
        ),
        (
            "heidenhain",
            {"approach_z_mm": 50, "setter_x_mm": 1, "setter_y_mm": 2},
            "not for heidenhain",
        ),
        ("heidenhain", {"approach_z_mm": 50, "travel_mm": 5}, "not for heidenhain"),
        ("linuxcnc", {"value_var": "#20"}, "--value-var"),  # a subroutine's local parameter
        ("linuxcnc", {"counter_var": "#5063"}, "--counter-var"),  # the probe result itself
        ("linuxcnc", {"probe_input": 2}, "not for linuxcnc"),
        ("linuxcnc", {"value_aout": 64}, "--value-aout"),
        ("fanuc", {"value_aout": 2}, "not for fanuc"),
        ("sinumerik", {"probe_input": 3}, "--probe-input"),
        ("fanuc", {"setter_x_mm": 10}, "go together"),
        ("fanuc", {"setter_x_mm": 10, "setter_y_mm": 10}, "need --approach-z-mm"),
        ("fanuc", {"travel_mm": 2, "backoff_mm": 1.5}, "more than half"),
        ("fanuc", {"slow_feed_mm_min": 300}, "--slow-feed-mm-min"),  # slower than the search
        ("fanuc", {"max_um": 0}, "--max-um"),
        ("fanuc", {"name": "9LIVES"}, "--name"),
        ("fanuc", {"touches": 0}, "--touches"),
        ("fanuc", {"touches": 11}, "--touches"),
        ("sinumerik", {"touches": 2.5}, "whole number"),
        ("linuxcnc", {"touches": 3, "spread_um": 0}, "--spread-um"),
        ("heidenhain", {"approach_z_mm": 50, "touches": 2}, "--touches is not for heidenhain"),
    ],
)
def test_bad_options_are_refused(dialect, options, match):
    with pytest.raises(ConfigError, match=match) as err:
        probe_cycle(dialect, **options)
    assert "\n" not in str(err.value)


def thermocomp(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "thermocomp", "probe-program", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_probe_program_command(tmp_path):
    out = tmp_path / "probe.nc"
    r = thermocomp(
        "--dialect",
        "fanuc",
        "--tool",
        "3",
        "--value-var",
        "#531",
        "--counter-var",
        "#532",
        "--reference-var",
        "#530",
        "--probe-spindle",
        "low",
        "--low-rpm",
        "400",
        "--settle-s",
        "1.5",
        "--output",
        str(out),
    )
    assert r.returncode == 0, r.stderr
    assert "#531" in r.stdout and "about" in r.stdout
    text = out.read_text()
    assert (
        "T3 M06" in text and "S400 M03" in text and "G04 X1.5" in text and "#532 = #532 + 1" in text
    )
    assert text == probe_program(
        probe_cycle(
            "fanuc",
            tool=3,
            value_var="#531",
            counter_var="#532",
            reference_var="#530",
            spindle="low",
            low_rpm=400,
            settle_s=1.5,
        )
    )
    # standard output by default; --reference writes the cold-reference program
    r = thermocomp("--dialect", "linuxcnc", "--reference")
    assert r.returncode == 0 and r.stdout.startswith("%\n") and "#3020 = #<trip_mm>" in r.stdout
    r = thermocomp("--dialect", "linuxcnc", "--output", str(tmp_path / "p.ngc"))
    assert "3020 0" in r.stdout  # the .var lines that make the parameters persistent
    # each spindle mode says what it does, the laser measuring the turning tool too
    for mode, said in (("stop", "spindle stopped"), ("keep", "spindle at the program's speed")):
        r = thermocomp(
            "--dialect",
            "linuxcnc",
            "--probe-spindle",
            mode,
            "--output",
            str(tmp_path / f"{mode}.ngc"),
        )
        assert r.returncode == 0 and said in r.stdout, r.stdout + r.stderr


@pytest.mark.parametrize(
    "args,match",
    [
        (["--dialect", "fanuc", "--settle-s", "soon"], "--settle-s"),
        (["--dialect", "fanuc", "--probe-spindle", "low"], "--low-rpm"),
        (["--dialect", "sinumerik", "--value-var", "#100"], "--value-var"),
        (["--dialect", "heidenhain", "--approach-z-mm", "50", "--value-aout", "3"], "heidenhain"),
    ],
)
def test_bad_command_input_is_one_line_and_writes_nothing(tmp_path, args, match):
    out = tmp_path / "x.nc"
    r = thermocomp(*args, "--output", str(out))
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and match in r.stderr, r.stderr
    assert r.stderr.startswith("thermocomp: error: ") and not out.exists()


# LinuxCNC's own interpreter, as tests/test_linuxcnc.py runs it for the wizard's programs; rs274
# alone needs no running LinuxCNC (scripts/system-deps.sh installs linuxcnc-uspace)
needs_rs274 = pytest.mark.skipif(
    shutil.which("rs274") is None,
    reason="LinuxCNC's rs274 is not installed (scripts/system-deps.sh installs "
    "linuxcnc-uspace as root)",
)


def rs274(program: Path, var_file: Path, tool_table: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        ["rs274", "-g", "-t", str(tool_table), "-v", str(var_file), str(program)],
        input="\n\n\n",
        capture_output=True,
        text=True,
        timeout=60,
        cwd=program.parent,
        check=False,
    )


def interpreter_files(
    tmp_path: Path, c: ProbeCycle, tool_line: str
) -> tuple[Path, Path, Path, Path]:
    """The tool table, a .var file listing the cycle's parameters, the reference program and the
    cycle, for :func:`rs274`."""
    tbl, var = tmp_path / "tool.tbl", tmp_path / "thermocomp.var"
    tbl.write_text(tool_line + "\n")
    var.write_text("\n".join(var_file_lines(c)) + "\n")
    ref_ngc, cyc_ngc = tmp_path / "tcref.ngc", tmp_path / "tcprobe.ngc"
    ref_ngc.write_text(probe_program(c, reference=True))
    cyc_ngc.write_text(probe_program(c))
    return tbl, var, ref_ngc, cyc_ngc


def read_var(var_file: Path) -> dict[int, float]:
    pairs = (line.split() for line in var_file.read_text().splitlines())
    return {int(p[0]): float(p[1]) for p in pairs if len(p) == 2}


@needs_rs274
def test_linuxcnc_interpreter_runs_reference_then_cycle(tmp_path):
    """The reference program stores the trip in the .var file, the cycle reads it back (LinuxCNC
    saves listed user parameters at exit), writes the value, then the counter, and hands both to
    HAL in that order; without a reference it aborts and writes nothing."""
    c: ProbeCycle = probe_cycle(
        "linuxcnc",
        tool=5,
        setter_x_mm=-400,
        setter_y_mm=-20,
        approach_z_mm=-50,
        spindle="low",
        low_rpm=300,
        value_aout=2,
        counter_aout=3,
    )
    tbl, var, ref_ngc, cyc_ngc = interpreter_files(tmp_path, c, "T5 P5 Z0 D10 ;gauge tool")

    r = rs274(ref_ngc, var, tbl)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr
    assert r.stdout.count("STRAIGHT_PROBE") == 2 and "SET_AUX_OUTPUT_VALUE" not in r.stdout
    probes = re.findall(r"STRAIGHT_PROBE\(([-\d.]+), ([-\d.]+), ([-\d.]+)", r.stdout)
    assert [float(x) for x in probes[0][:2]] == [-400.0, -20.0]  # at the setter
    trip_mm = read_var(var)[3020]
    assert trip_mm == pytest.approx(float(probes[1][2]), abs=1e-5)  # the slow touch, machine Z
    assert read_var(var)[3022] == 0

    var.write_text(var.read_text().replace(f"3020\t{trip_mm:f}", f"3020\t{trip_mm - 0.0123:f}"))
    for expected_counter in (1, 2):
        r = rs274(cyc_ngc, var, tbl)
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr
        canon = r.stdout
        assert "START_SPINDLE_CLOCKWISE" in canon and canon.index(
            "SET_SPINDLE_SPEED(0, 300"
        ) < canon.index("STRAIGHT_PROBE") < canon.rindex("STOP_SPINDLE_TURNING")
        aux = re.findall(r"SET_AUX_OUTPUT_VALUE\((\d+),([-\d.]+)\)", canon)
        assert [int(e) for e, _ in aux] == [2, 3]  # value first, then the counter
        assert (
            float(aux[0][1]) == pytest.approx(12.3, abs=1e-3)
            and float(aux[1][1]) == expected_counter
        )
        saved = read_var(var)
        assert saved[3021] == pytest.approx(12.3, abs=1e-3) and saved[3022] == expected_counter

    var.write_text(var.read_text().replace("3022\t2.000000", f"3022\t{COUNTER_WRAP}.000000"))
    assert rs274(cyc_ngc, var, tbl).returncode == 0
    assert read_var(var)[3022] == 1  # wraps to 1, never 0

    var.write_text("\n".join(var_file_lines(c)) + "\n")  # no cold reference
    r = rs274(cyc_ngc, var, tbl)
    assert r.returncode != 0 and "NO COLD REFERENCE" in r.stdout + r.stderr
    assert "STRAIGHT_PROBE" not in r.stdout and "SET_AUX_OUTPUT_VALUE" not in r.stdout
    assert read_var(var)[3021] == 0 and read_var(var)[3022] == 0

    bad = tmp_path / "bad.ngc"  # and the interpreter does refuse what it cannot run
    bad.write_text(probe_program(c).replace("G38.2 Z", "G38.9 Z", 1))
    assert rs274(bad, var, tbl).returncode != 0


@needs_rs274
def test_linuxcnc_interpreter_runs_repeated_touches(tmp_path):
    """LinuxCNC's interpreter runs the loop: the fast touch and three slow ones, for the cold
    reference and for the measurement alike, and hands HAL the growth between their means."""
    # the standalone interpreter's trips move from touch to touch by tens of um: a spread the
    # default tolerance (5 um) refuses, and 1 mm allows
    c = probe_cycle("linuxcnc", touches=3, spindle="keep", spread_um=1000)
    tbl, var, ref_ngc, cyc_ngc = interpreter_files(tmp_path, c, "T1 P1 Z0 D6 ;gauge tool")
    r = rs274(ref_ngc, var, tbl)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr
    assert r.stdout.count("STRAIGHT_PROBE") == 1 + 3
    trip_mm = read_var(var)[3020]
    var.write_text(var.read_text().replace(f"3020\t{trip_mm:f}", f"3020\t{trip_mm - 0.0123:f}"))
    r = rs274(cyc_ngc, var, tbl)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr
    assert r.stdout.count("STRAIGHT_PROBE") == 1 + 3
    assert read_var(var)[3021] == pytest.approx(12.3, abs=1e-3) and read_var(var)[3022] == 1
    cyc_ngc.write_text(probe_program(probe_cycle("linuxcnc", touches=3, spindle="keep")))
    r = rs274(cyc_ngc, var, tbl)
    assert r.returncode != 0 and "TOUCHES DISAGREE" in r.stdout + r.stderr
    assert read_var(var)[3022] == 1 and "SET_AUX_OUTPUT_VALUE" not in r.stdout


@needs_rs274
def test_linuxcnc_interpreter_refuses_a_growth_out_of_range(tmp_path):
    c = probe_cycle("linuxcnc", max_um=50)
    tbl = tmp_path / "tool.tbl"
    tbl.write_text("T1 P1 Z0 D6 ;gauge tool\n")
    var = tmp_path / "t.var"
    var.write_text("3020 -1000.0\n3021 0\n3022 7\n")  # a reference a metre away: not this tool
    prog = tmp_path / "p.ngc"
    prog.write_text(probe_program(c))
    r = rs274(prog, var, tbl)
    assert r.returncode != 0 and "GROWTH OUT OF RANGE" in r.stdout + r.stderr
    assert read_var(var)[3022] == 7 and "SET_AUX_OUTPUT_VALUE" not in r.stdout
