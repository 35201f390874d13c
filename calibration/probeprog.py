"""Tool-setter probe cycles for the closed loop. Settings in, NC text out; only the
command handler at the end writes a file.

A cycle measures the tool on the machine's tool setter, subtracts the reference taken cold at
calibration (``--reference`` writes the program that takes it) and hands the difference to the
thermocomp service: **value** = (trip position now − cold trip position) × 1000, in µm, positive
when the tool tip grew toward the workpiece (the trip comes earlier on the way down). The setter
is fixed, so this is the tool's length change. Handshake: the cycle writes the value, **then**
adds 1 to the counter (1..9999, then 1 again); a failed measurement (setter not tripped, no
cold reference, growth beyond ``max_um``) stops with an alarm and writes neither. The adapter
uses a value once, when the counter changed (see ``docs/PROBING.md``).

With ``touches`` > 1 the slow touch is repeated that many times and the trips are averaged: the
random part of the setter's repeatability falls as 1/sqrt(touches) (GUM, JCGM 100:2008, 4.2.3,
the experimental standard deviation of the mean). Every touch must lie within ``spread_um`` of
the first, else the cycle stops with an alarm (a chip or a coolant drop on the setter) and
writes nothing.

==========  =========================  ==================================  ===============
dialect     probing, result            trip in machine Z                   variables
==========  =========================  ==================================  ===============
fanuc       ``G31`` skip, ``#5063``    ``#5063 + #5023 - #5043``           ``#500-#999``
sinumerik   ``MEAS=1``, ``$AC_MEA``    ``$AA_MM[Z]``                       R parameters
heidenhain  ``TCH PROBE 481`` (TT)     tool table ``L`` + ``Q115``         QR parameters
linuxcnc    ``G38.2``, ``#5063``       ``#5063`` + G5x + G52/G92, ``G49``  ``#31-#5000``
==========  =========================  ==================================  ===============

Sources: LinuxCNC G-code overview (numbered parameters, persistence) and
``src/emc/rs274ngc/interp_parameter_def.hh``; LinuxCNC issue 4159 / PR 4163 (machine Z of a
probe); Fanuc Custom Macro B system variables (``#5021``, ``#5041``, ``#5061``; a reading of a
moving position waits for the move's end); SINUMERIK Job Planning, "Measurements with touch
trigger probe (MEAS, MEAW)"; HEIDENHAIN TNC user manuals (preassigned Q parameters: ``Q115``
length deviation after TT measurement, ``Q199`` TT status; QR parameters are non-volatile) and
the TNC 426/430 technical manual (``FN 17/18`` ID50: tool table). Details in ``docs/PROBING.md``.
"""

from __future__ import annotations

import argparse
import math
import re
from dataclasses import dataclass

from compensator.errors import ConfigError

from .nc_programs import DIALECTS, EXTENSIONS

COUNTER_WRAP = 9999
"""The counter runs 1..9999, then 1 again: it fits any register, and only a change counts."""

SPINDLE_MODES = ("stop", "low", "keep")
"""The spindle through the cycle: stopped (a contact setter), at a low measuring speed (a laser),
or kept at the speed the program runs (a laser measuring the turning tool: the measurement then
includes the growth that exists only while the spindle turns)."""
MAX_TOUCHES = 10
"""Slow touches averaged per cycle, at most."""
HEIDENHAIN_TT_S = 15.0
"""Nominal length of TCH PROBE 481 (its feeds are machine parameters): for the time estimate."""

# reference, value, counter: retained variables, so a power cycle repeats no counter value
DEFAULT_VARIABLES = {
    "fanuc": ("#520", "#521", "#522"),
    "sinumerik": ("R20", "R21", "R22"),
    "heidenhain": ("QR20", "QR21", "QR22"),
    "linuxcnc": ("#3020", "#3021", "#3022"),
}

# per dialect: prefix -> allowed number ranges; the first prefix is the one a bare number takes
_VARIABLES: dict[str, dict[str, tuple[tuple[int, int], ...]]] = {
    "fanuc": {"#": ((100, 199), (500, 999))},  # common variables; #100-#199 cleared at power off
    "sinumerik": {"R": ((0, 9999),)},  # how many exist: MD28050 MM_NUM_R_PARAM
    "heidenhain": {"QR": ((0, 499),), "Q": ((1600, 1999),)},  # QR non-volatile, Q1600+ free
    "linuxcnc": {"#": ((31, 5000),)},  # user parameters; persistent once listed in the .var file
}
_RETAINED: dict[str, tuple[tuple[int, int], ...] | None] = {
    "fanuc": ((500, 999),),
    "heidenhain": None,
}  # the cold reference must survive power off

# options a dialect's cycle has no use for: refused, not silently dropped
_AOUT = dict.fromkeys(("value_aout", "counter_aout"), "analog outputs (M68) are LinuxCNC's")
_NOT_FOR = {
    "fanuc": {"probe_input": "the skip signal has no input number here", **_AOUT},
    "sinumerik": dict(_AOUT),
    "linuxcnc": {"probe_input": "LinuxCNC has one probe input (motion.probe-input)"},
    "heidenhain": dict.fromkeys(
        (
            "setter_x_mm",
            "setter_y_mm",
            "travel_mm",
            "backoff_mm",
            "fast_feed_mm_min",
            "slow_feed_mm_min",
        ),
        "TCH PROBE 481 takes the setter's position, travel and feeds from the TT machine parameters",
    )
    | {"probe_input": "the TT has its own input", **_AOUT},
}


@dataclass(frozen=True)
class Variable:
    """A controller variable: ``#521``, ``R21``, ``QR21``, ``Q1621``."""

    prefix: str
    number: int

    def __str__(self) -> str:
        return f"{self.prefix}{self.number}"


@dataclass(frozen=True)
class ProbeCycle:
    """Validated settings of one dialect's cycle (build it with :func:`probe_cycle`)."""

    dialect: str
    tool: int
    reference_var: Variable
    value_var: Variable
    counter_var: Variable
    spindle: str
    low_rpm: float | None
    settle_s: float
    travel_mm: float
    backoff_mm: float
    fast_feed_mm_min: float
    slow_feed_mm_min: float
    setter_xy_mm: tuple[float, float] | None
    approach_z_mm: float | None
    max_um: float
    touches: int
    spread_um: float
    probe_input: int
    value_aout: int
    counter_aout: int
    name: str


def _option(name: str) -> str:
    return "--" + name.replace("_", "-")


def _number(name: str, value: float | str, lo: float, hi: float, *, whole: bool = False) -> float:
    """``value`` (a number or the CLI's text) within [lo, hi]; a one-line ConfigError otherwise."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{_option(name)} {value!r} is not a number") from None
    if not (math.isfinite(x) and lo <= x <= hi) or (whole and x != int(x)):
        kind = "a whole number" if whole else "a number"
        raise ConfigError(f"{_option(name)} {value!r}: give {kind} from {lo:g} to {hi:g}")
    return x


def parse_variable(dialect: str, text: str | int, role: str) -> Variable:
    """``text`` (``521``, ``#521``, ``R21``, ``QR21``, ``Q1621``) as a variable ``dialect`` allows.
    ``role``: ``reference``, ``value`` or ``counter`` (for the message, and the reference must be
    one the controller keeps through a power cycle)."""
    rules = _VARIABLES[dialect]
    m = re.fullmatch(r"\s*(QR|Q|R|#)?\s*(\d{1,6})\s*", str(text), re.IGNORECASE)
    prefix = (m.group(1) or next(iter(rules))).upper() if m else ""
    ranges = rules.get(prefix)
    what = ", ".join(f"{p}{lo}-{p}{hi}" for p, rs in rules.items() for lo, hi in rs)
    if not m or ranges is None or not any(lo <= int(m.group(2)) <= hi for lo, hi in ranges):
        raise ConfigError(f"--{role}-var {text!r}: {dialect} takes {what}")
    var = Variable(prefix, int(m.group(2)))
    if role == "reference" and dialect in _RETAINED:
        kept = _RETAINED[dialect]
        if (kept is None and prefix != "QR") or (
            kept and not any(lo <= var.number <= hi for lo, hi in kept)
        ):
            need = "a QR parameter" if kept is None else "#500-#999"
            raise ConfigError(
                f"--reference-var {text!r}: the cold reference must survive a power cycle: "
                f"use {need}"
            )
    return var


def probe_cycle(
    dialect: str,
    *,
    tool: int | str = 1,
    reference_var: str | None = None,
    value_var: str | None = None,
    counter_var: str | None = None,
    spindle: str = "stop",
    low_rpm: float | str | None = None,
    settle_s: float | str = 2.0,
    travel_mm: float | str | None = None,
    backoff_mm: float | str | None = None,
    fast_feed_mm_min: float | str | None = None,
    slow_feed_mm_min: float | str | None = None,
    setter_x_mm: float | str | None = None,
    setter_y_mm: float | str | None = None,
    approach_z_mm: float | str | None = None,
    max_um: float | str = 300.0,
    touches: int | str = 1,
    spread_um: float | str = 5.0,
    probe_input: int | str | None = None,
    value_aout: int | str | None = None,
    counter_aout: int | str | None = None,
    name: str = "TCPROBE",
) -> ProbeCycle:
    """Check every option for ``dialect`` and fill in its defaults; :class:`ConfigError` (one
    line, naming the option) on anything a control would refuse or that could not be safe."""
    if dialect not in DIALECTS:
        raise ConfigError(f"--dialect {dialect!r}: choose from {', '.join(DIALECTS)}")
    given = {
        "setter_x_mm": setter_x_mm,
        "setter_y_mm": setter_y_mm,
        "travel_mm": travel_mm,
        "backoff_mm": backoff_mm,
        "fast_feed_mm_min": fast_feed_mm_min,
        "slow_feed_mm_min": slow_feed_mm_min,
        "probe_input": probe_input,
        "value_aout": value_aout,
        "counter_aout": counter_aout,
    }
    for key, why in _NOT_FOR[dialect].items():
        if given.get(key) is not None:
            raise ConfigError(f"{_option(key)} is not for {dialect}: {why}")
    n_touches = int(_number("touches", touches, 1, MAX_TOUCHES, whole=True))
    if n_touches > 1 and dialect == "heidenhain":
        raise ConfigError(
            "--touches is not for heidenhain: TCH PROBE 481 measures once per call; use --touches 1"
        )
    if spindle not in SPINDLE_MODES:
        raise ConfigError(f"--probe-spindle {spindle!r}: choose stop, low or keep")
    if spindle == "keep" and dialect == "heidenhain":
        raise ConfigError(
            "--probe-spindle keep is not for heidenhain: TCH PROBE 481 turns the spindle itself; "
            "use --probe-spindle stop"
        )
    if spindle == "low":
        if dialect == "heidenhain":
            raise ConfigError(
                "--probe-spindle low is not for heidenhain: TCH PROBE 481 turns the spindle itself "
                "(tool table R-OFFS); use --probe-spindle stop"
            )
        if low_rpm is None:
            raise ConfigError(
                "--probe-spindle low needs --low-rpm (the laser setter's measuring speed)"
            )
        rpm: float | None = _number("low_rpm", low_rpm, 1, 5000)
    elif low_rpm is not None:
        raise ConfigError("--low-rpm goes with --probe-spindle low")
    else:
        rpm = None
    defaults = DEFAULT_VARIABLES[dialect]
    variables = [
        parse_variable(dialect, text if text is not None else default, role)
        for text, default, role in zip(
            (reference_var, value_var, counter_var), defaults, ("reference", "value", "counter")
        )
    ]
    if len(set(variables)) < 3:
        raise ConfigError(
            f"reference, value and counter need three different variables, not "
            f"{', '.join(map(str, variables))}"
        )
    travel = _number("travel_mm", 10.0 if travel_mm is None else travel_mm, 0.5, 100)
    # a laser's beam has no stylus to clear: a short back-off keeps repeated touches cheap
    default_backoff = 0.2 if spindle in ("low", "keep") else 1.0
    backoff = _number("backoff_mm", default_backoff if backoff_mm is None else backoff_mm, 0.1, 10)
    if backoff * 2 > travel:
        raise ConfigError(f"--backoff-mm {backoff:g} is more than half of --travel-mm {travel:g}")
    fast = _number(
        "fast_feed_mm_min", 200.0 if fast_feed_mm_min is None else fast_feed_mm_min, 1, 5000
    )
    slow = _number(
        "slow_feed_mm_min", 20.0 if slow_feed_mm_min is None else slow_feed_mm_min, 0.1, fast
    )
    if (setter_x_mm is None) != (setter_y_mm is None):
        raise ConfigError(
            "--setter-x-mm and --setter-y-mm go together (the setter's centre, machine X and Y)"
        )
    xy = None
    if setter_x_mm is not None and setter_y_mm is not None:
        xy = (
            _number("setter_x_mm", setter_x_mm, -1e5, 1e5),
            _number("setter_y_mm", setter_y_mm, -1e5, 1e5),
        )
        if approach_z_mm is None:
            raise ConfigError(
                "--setter-x-mm/--setter-y-mm need --approach-z-mm: the cycle rises to it "
                "before it moves across"
            )
    if dialect == "heidenhain" and approach_z_mm is None:
        raise ConfigError(
            "heidenhain needs --approach-z-mm: the clearance height Q260 of TCH PROBE 481"
        )
    z = None if approach_z_mm is None else _number("approach_z_mm", approach_z_mm, -1e5, 1e5)
    pname = "".join(ch for ch in name.upper() if ch.isalnum() or ch == "_")[:24]
    if not pname or not pname[0].isalpha():
        raise ConfigError(f"--name {name!r}: letters, digits and _, starting with a letter")
    return ProbeCycle(
        dialect=dialect,
        tool=int(_number("tool", tool, 1, 9999, whole=True)),
        reference_var=variables[0],
        value_var=variables[1],
        counter_var=variables[2],
        spindle=spindle,
        low_rpm=rpm,
        settle_s=_number("settle_s", settle_s, 0, 600),
        travel_mm=travel,
        backoff_mm=backoff,
        fast_feed_mm_min=fast,
        slow_feed_mm_min=slow,
        setter_xy_mm=xy,
        approach_z_mm=z,
        max_um=_number("max_um", max_um, 1, 5000),
        touches=n_touches,
        spread_um=_number("spread_um", spread_um, 0.1, 1000),
        probe_input=int(
            _number("probe_input", 1 if probe_input is None else probe_input, 1, 2, whole=True)
        ),
        value_aout=int(
            _number("value_aout", 0 if value_aout is None else value_aout, 0, 63, whole=True)
        ),
        counter_aout=int(
            _number("counter_aout", 1 if counter_aout is None else counter_aout, 0, 63, whole=True)
        ),
        name=pname,
    )


def measuring_time_s(cycle: ProbeCycle) -> float:
    """Seconds from the spindle's stop (or slow-down) to the end of probing, at worst (the fast
    touch over the whole travel); rapid moves to and from the setter come on top."""
    if cycle.dialect == "heidenhain":
        return cycle.settle_s + HEIDENHAIN_TT_S
    fast_s = 60.0 * cycle.travel_mm / cycle.fast_feed_mm_min
    return cycle.settle_s + fast_s + cycle.touches * touch_time_s(cycle)


def touch_time_s(cycle: ProbeCycle) -> float:
    """One slow touch: off the setter by the back-off and onto it again at the slow feed [s]."""
    return 60.0 * 2 * cycle.backoff_mm / cycle.slow_feed_mm_min


def _mm(x: float) -> str:
    return f"{x:.3f}"


def _feed(x: float) -> str:
    return f"{x:.1f}"


def _header(c: ProbeCycle, reference: bool) -> list[str]:
    ref, val, cnt = c.reference_var, c.value_var, c.counter_var
    spindle = (
        "SPINDLE STOPPED"
        if c.spindle == "stop"
        else "SPINDLE KEEPS THE PROGRAM SPEED [LASER SETTER, GAUGE TOOL IN THE SPINDLE]"
        if c.spindle == "keep"
        else f"SPINDLE AT {c.low_rpm:g} RPM [LASER SETTER]"
    )
    if reference:
        lines = [
            f"THERMOCOMP TOOL-SETTER COLD REFERENCE, T{c.tool}",
            "RUN IT COLD: AFTER THE REST, BEFORE THE FIRST SPINDLE START",
            f"STORES THE COLD TRIP POSITION [MM] IN {ref}",
        ]
    else:
        lines = [
            f"THERMOCOMP TOOL-SETTER CYCLE, T{c.tool}",
            f"{val} = [TRIP NOW - COLD TRIP {ref}] X 1000: UM, + = TIP GREW TOWARD THE WORK",
            f"THEN {cnt} + 1 [1..{COUNTER_WRAP}]. A FAILED MEASUREMENT WRITES NEITHER",
        ]
    if c.touches > 1:
        lines.append(
            f"MEAN OF {c.touches} SLOW TOUCHES, EACH WITHIN {c.spread_um:g} UM OF THE FIRST"
        )
    return [*lines, f"{spindle}, ABOUT {measuring_time_s(c):.0f} S. SEE DOCS/PROBING.MD"]


# the words the ISO-style dialects spell differently around the probing itself
_WORDS = {
    "fanuc": {
        "tool": "T{} M06",
        "stop": "M05",
        "run": "S{:g} M03",
        "machine": "G53 G00",
        "dwell": "G04 X{:.1f}",
        "up": "G91 G00 Z{}",
    },
    "sinumerik": {
        "tool": "T{} M6",
        "stop": "M5",
        "run": "S{:g} M3",
        "machine": "SUPA G0",
        "dwell": "G4 F{:g}",
        "up": "G0 G91 Z{}",
    },
    "linuxcnc": {
        "tool": "T{} M6",
        "stop": "M5",
        "run": "S{:g} M3",
        "machine": "G53 G0",
        "dwell": "G4 P{:g}",
        "up": "G91 G0 Z{}",
    },
}


def _to_setter(c: ProbeCycle) -> list[str]:
    """Tool change, spindle stopped (contact setter) or slow (laser), up to the approach height
    and across to the setter in machine coordinates, then the settling dwell."""
    w = _WORDS[c.dialect]
    # keep: no tool change (it stops the spindle) and no speed word: the gauge tool in the
    # spindle is measured turning at the program's speed
    out = (
        []
        if c.spindle == "keep"
        else [
            w["tool"].format(c.tool),
            w["stop"] if c.low_rpm is None else w["run"].format(c.low_rpm),
        ]
    )
    if c.approach_z_mm is not None:
        out.append(f"{w['machine']} Z{_mm(c.approach_z_mm)}")
    if c.setter_xy_mm:
        out.append(f"{w['machine']} X{_mm(c.setter_xy_mm[0])} Y{_mm(c.setter_xy_mm[1])}")
    return out + ([w["dwell"].format(c.settle_s)] if c.settle_s > 0 else [])


def _from_setter(c: ProbeCycle) -> list[str]:
    """Off the setter by the back-off, back to absolute, up to the approach height, spindle off."""
    w = _WORDS[c.dialect]
    return (
        [w["up"].format(_mm(c.backoff_mm)), "G90"]
        + ([f"{w['machine']} Z{_mm(c.approach_z_mm)}"] if c.approach_z_mm is not None else [])
        + ([w["stop"]] if c.low_rpm is not None else [])
    )


def _fanuc(c: ProbeCycle, reference: bool) -> list[str]:
    ref, val, cnt = c.reference_var, c.value_var, c.counter_var
    out = ["%", f"O{1101 if reference else 1100} ({c.name[:16]})"]
    out += [f"({t})" for t in _header(c, reference)]
    out.append("G17 G21 G40 G80 G90 G94")
    if not reference:  # fail before anything moves
        out.append(f"IF [{ref} EQ #0] THEN #3000 = 102 (NO COLD REFERENCE)")
    out += _to_setter(c)
    b = c.backoff_mm
    out += [
        "#1 = #5043",  # read once the move has ended: start of the fast touch, workpiece Z
        f"G91 G31 Z-{_mm(c.travel_mm)} F{_feed(c.fast_feed_mm_min)}",
        "G90",
        f"IF [[#5063 - #1 + {_mm(c.travel_mm)}] LT 0.010] THEN #3000 = 101 (SETTER NOT TRIPPED)",
        "#2 = #5063",
    ]
    touch = [
        f"G91 G00 Z{_mm(b)}",
        f"G91 G31 Z-{_mm(2 * b)} F{_feed(c.slow_feed_mm_min)}",
        "#3 = #5063 + #5023 - #5043",  # the slow trip in machine Z: work offsets and TLO drop out
        "G90",
        f"IF [ABS[#5063 - #2] GT {_mm(b / 2)}] THEN #3000 = 101 (SETTER NOT TRIPPED)",
    ]
    if c.touches == 1:
        out += touch
    else:  # #5 the first trip, #6 the sum, #7 the touches done
        out += [
            "#6 = 0",
            "#7 = 0",
            f"WHILE [#7 LT {c.touches}] DO1",
            *touch,
            "IF [#7 EQ 0] THEN #5 = #3",
            f"IF [ABS[#3 - #5] * 1000 GT {c.spread_um:.1f}] THEN #3000 = 104 (TOUCHES DISAGREE)",
            "#6 = #6 + #3",
            "#7 = #7 + 1",
            "END1",
            f"#3 = #6 / {c.touches}",
        ]
    out += _from_setter(c)
    if reference:
        out.append(f"{ref} = #3")
    else:
        out += [
            f"#4 = [#3 - {ref}] * 1000",
            f"IF [ABS[#4] GT {c.max_um:.1f}] THEN #3000 = 103 (GROWTH OUT OF RANGE)",
            f"{val} = #4",  # the value first ...
            f"{cnt} = {cnt} + 1",  # ... then the counter that releases it
            f"IF [{cnt} GT {COUNTER_WRAP}] THEN {cnt} = 1",
        ]
    return [*out, "M30", "%"]


def _sinumerik(c: ProbeCycle, reference: bool) -> list[str]:
    ref, val, cnt, n = c.reference_var, c.value_var, c.counter_var, c.probe_input
    out = [
        f"%_N_{c.name}_MPF",
        ";$PATH=/_N_MPF_DIR",
        *(f"; {t}" for t in _header(c, reference)),
        "DEF REAL TC_FAST, TC_TRIP, TC_UM" + (", TC_FIRST, TC_SUM" if c.touches > 1 else ""),
    ]
    if c.touches > 1:
        out.append("DEF INT TC_K")
    out.append("G17 G40 G71 G90 G94")
    if not reference:
        out.append(f"IF {ref}==0 GOTOF TC_NOREF")
    out += _to_setter(c)  # SUPA: machine coordinates, no frame, no offset
    b = c.backoff_mm
    out += [
        f"MEAS={n} G1 G91 Z-{_mm(c.travel_mm)} F{c.fast_feed_mm_min:g}",
        "STOPRE",  # the result is the main run's: read it after the block has run
        f"IF $AC_MEA[{n}]==0 GOTOF TC_NOTRIP",
        "TC_FAST=$AA_MM[Z]",
    ]
    touch = [
        f"G0 G91 Z{_mm(b)}",
        f"MEAS={n} G1 G91 Z-{_mm(2 * b)} F{c.slow_feed_mm_min:g}",
        "STOPRE",
        f"IF $AC_MEA[{n}]==0 GOTOF TC_NOTRIP",
        "TC_TRIP=$AA_MM[Z]",
        f"IF ABS(TC_TRIP-TC_FAST)>{_mm(b / 2)} GOTOF TC_NOTRIP",
    ]
    if c.touches == 1:
        out += touch
    else:  # a loop by label: the jumps out of it to the alarms stay plain GOTOF
        out += [
            "TC_SUM=0",
            "TC_K=0",
            "TC_TOUCH:",
            *touch,
            "IF TC_K==0",
            "TC_FIRST=TC_TRIP",
            "ENDIF",
            f"IF ABS(TC_TRIP-TC_FIRST)*1000>{c.spread_um:g} GOTOF TC_SPREAD",
            "TC_SUM=TC_SUM+TC_TRIP",
            "TC_K=TC_K+1",
            f"IF TC_K<{c.touches} GOTOB TC_TOUCH",
            f"TC_TRIP=TC_SUM/{c.touches}",
        ]
    out += _from_setter(c)
    if reference:
        out += [f"{ref}=TC_TRIP", "M30"]
    else:
        out += [
            f"TC_UM=(TC_TRIP-{ref})*1000",
            f"IF ABS(TC_UM)>{c.max_um:g} GOTOF TC_RANGE",
            f"{val}=TC_UM",
            f"{cnt}={cnt}+1",
            f"IF {cnt}>{COUNTER_WRAP}",
            f"{cnt}=1",
            "ENDIF",
            "M30",
            "TC_NOREF:",
            "SETAL(65002)",
            "M30",
            "TC_RANGE:",
            "SETAL(65003)",
            "M30",
        ]
    if c.touches > 1:
        out += ["TC_SPREAD:", "SETAL(65004)", "M30"]
    return [*out, "TC_NOTRIP:", "SETAL(65001)", "M30"]


def _heidenhain(c: ProbeCycle, reference: bool) -> list[str]:
    ref, val, cnt, t = c.reference_var, c.value_var, c.counter_var, c.tool
    out = [f"BEGIN PGM {c.name} MM", *(f"; {h}" for h in _header(c, reference))]
    if not reference:
        out.append(f"FN 9: IF +{ref} EQU +0 GOTO LBL 91")
    out += [f"TOOL CALL {t} Z", "M5"]
    if c.settle_s > 0:
        out += ["CYCL DEF 9.0 DWELL TIME", f"CYCL DEF 9.1 DWELL {c.settle_s:g}"]
    if not reference:  # keep L and DL: the check writes the deviation into DL, put back below
        out += [f"FN 18: SYSREAD QL1 = ID50 NR1 IDX{t}", f"FN 18: SYSREAD QL2 = ID50 NR4 IDX{t}"]
    # one block over four lines: "~" continues it, the parameter lines take no number
    out += [
        "TCH PROBE 481 TOOL LENGTH ~",
        f"  Q340=+{0 if reference else 1} ;CHECK ~",
        f"  Q260={c.approach_z_mm:+.3f} ;CLEARANCE HEIGHT ~",
        "  Q341=+0 ;PROBING THE TEETH",
    ]
    if reference:  # 481 measured: L = the cold length, DL = 0
        out += [f"FN 18: SYSREAD QL1 = ID50 NR1 IDX{t}", f"FN 0: {ref} = +QL1"]
    else:
        out += [
            f"FN 17: SYSWRITE ID50 NR4 IDX{t} = QL2",  # the length compensation stays cold
            "FN 9: IF +Q199 EQU +2 GOTO LBL 92",
            f"QL3 = ( QL1 + Q115 - {ref} ) * 1000",
            f"FN 11: IF +QL3 GT +{c.max_um:g} GOTO LBL 93",
            f"FN 12: IF +QL3 LT -{c.max_um:g} GOTO LBL 93",
            f"FN 0: {val} = +QL3",
            f"{cnt} = {cnt} + 1",
            f"FN 12: IF +{cnt} LT +{COUNTER_WRAP + 1} GOTO LBL 1",
            f"FN 0: {cnt} = +1",
            "LBL 1",
            "FN 9: IF +0 EQU +0 GOTO LBL 99",
            "LBL 91",
            "FN 14: ERROR = 202",  # no cold reference
            "LBL 92",
            "FN 14: ERROR = 201",  # the TT found the tool broken (LBREAK)
            "LBL 93",
            "FN 14: ERROR = 203",  # growth beyond max_um
            "LBL 99",
        ]
    out.append(f"END PGM {c.name} MM")
    numbered, n = [], 0
    for k, line in enumerate(out):  # the TNC numbers every block
        if k and out[k - 1].endswith(" ~"):
            numbered.append(line)
        else:
            numbered.append(f"{n} {line}")
            n += 1
    return numbered


def _linuxcnc(c: ProbeCycle, reference: bool) -> list[str]:
    ref, val, cnt = c.reference_var, c.value_var, c.counter_var
    out = ["%", *(f"({t})" for t in _header(c, reference)), "G17 G21 G40 G49 G90 G94"]
    if not reference:
        out += [
            f"o100 if [{ref} EQ 0]",
            "(ABORT, NO COLD REFERENCE: RUN THE REFERENCE PROGRAM)",
            "o100 endif",
        ]
    out += _to_setter(c)
    b = c.backoff_mm
    out += [
        f"G91 G38.2 Z-{_mm(c.travel_mm)} F{_feed(c.fast_feed_mm_min)}",  # G38.2: no trip is an error
    ]
    touch = [
        # G91 again each time round: the touch ends in G90
        f"{'G91 ' if c.touches > 1 else ''}G0 Z{_mm(b)}",
        f"G38.2 Z-{_mm(2 * b)} F{_feed(c.slow_feed_mm_min)}",
        "G90",
        # the trip in machine Z: #5063 is in the probing frame; G49 is on, so G5x + G52/G92 only
        "#<trip_mm> = [#5063 + #[5203 + 20 * #5220] + #5213 * #5210]",
    ]
    if c.touches == 1:
        out += touch
    else:
        out += [
            "#<sum_mm> = 0",
            "#<k> = 0",
            f"o103 repeat [{c.touches}]",
            *touch,
            "o104 if [#<k> EQ 0]",
            "#<first_mm> = #<trip_mm>",
            "o104 endif",
            f"o105 if [ABS[#<trip_mm> - #<first_mm>] * 1000 GT {c.spread_um:g}]",
            "(ABORT, TOUCHES DISAGREE)",
            "o105 endif",
            "#<sum_mm> = [#<sum_mm> + #<trip_mm>]",
            "#<k> = [#<k> + 1]",
            "o103 endrepeat",
            f"#<trip_mm> = [#<sum_mm> / {c.touches}]",
        ]
    out += _from_setter(c)
    if reference:
        out.append(f"{ref} = #<trip_mm>")
    else:
        out += [
            f"#<growth_um> = [[#<trip_mm> - {ref}] * 1000]",
            f"o101 if [ABS[#<growth_um>] GT {c.max_um:g}]",
            "(ABORT, GROWTH OUT OF RANGE)",
            "o101 endif",
            f"{val} = #<growth_um>",
            f"{cnt} = [{cnt} + 1]",
            f"o102 if [{cnt} GT {COUNTER_WRAP}]",
            f"{cnt} = 1",
            "o102 endif",
            f"M68 E{c.value_aout} Q{val}",  # HAL sees them in this order too
            f"M68 E{c.counter_aout} Q{cnt}",
        ]
    return [*out, "M2", "%"]


_WRITERS = {
    "fanuc": _fanuc,
    "sinumerik": _sinumerik,
    "heidenhain": _heidenhain,
    "linuxcnc": _linuxcnc,
}


def probe_program(cycle: ProbeCycle, *, reference: bool = False) -> str:
    """The NC text of ``cycle``: the measuring cycle, or with ``reference`` the program that
    takes the cold reference."""
    return "\n".join(_WRITERS[cycle.dialect](cycle, reference)) + "\n"


def var_file_lines(cycle: ProbeCycle) -> list[str]:
    """LinuxCNC keeps a user parameter across restarts only when its number is in the .var file
    (the interpreter rewrites the file's own lines at exit): the lines to add, in order."""
    return [
        f"{v.number} 0"
        for v in sorted(
            (cycle.reference_var, cycle.value_var, cycle.counter_var), key=lambda v: v.number
        )
    ]


def probe_program_cmd(args: argparse.Namespace) -> int:
    """``thermocomp probe-program``: write a tool-setter cycle (or its cold-reference program)."""
    cycle = probe_cycle(
        args.dialect,
        tool=args.tool,
        reference_var=args.reference_var,
        value_var=args.value_var,
        counter_var=args.counter_var,
        spindle=args.spindle,
        low_rpm=args.low_rpm,
        settle_s=args.settle_s,
        travel_mm=args.travel_mm,
        backoff_mm=args.backoff_mm,
        fast_feed_mm_min=args.fast_feed_mm_min,
        slow_feed_mm_min=args.slow_feed_mm_min,
        setter_x_mm=args.setter_x_mm,
        setter_y_mm=args.setter_y_mm,
        approach_z_mm=args.approach_z_mm,
        max_um=args.max_um,
        touches=args.touches,
        spread_um=args.spread_um,
        probe_input=args.probe_input,
        value_aout=args.value_aout,
        counter_aout=args.counter_aout,
        name=args.name or ("TCREF" if args.reference else "TCPROBE"),
    )
    text = probe_program(cycle, reference=args.reference)
    if not args.output or args.output == "-":
        print(text, end="")
        return 0
    from compensator.io import write_text  # files only here: the generator stays pure

    write_text(args.output, text)
    c = cycle
    what = "cold-reference program" if args.reference else "tool-setter cycle"
    print(
        f"wrote {args.output}: {c.dialect} {what} for T{c.tool}; cold reference {c.reference_var}, "
        f"value {c.value_var} [um], counter {c.counter_var}"
    )
    turning = {"stop": "stopped", "keep": "at the program's speed"}.get(
        c.spindle
    ) or f"at {c.low_rpm:g} rpm"
    touches = f", {c.touches} slow touches averaged" if c.touches > 1 else ""
    print(
        f"spindle {turning} for about "
        f"{measuring_time_s(c):.0f} s per measurement (settle {c.settle_s:g} s + probing{touches})"
    )
    if args.reference:
        print("run it cold: after the rest, before the calibration run's first spindle start")
    if c.dialect == "linuxcnc":
        print(
            "to keep them through a restart, add to the .var file (sorted by number; LinuxCNC saves it "
            "at a clean shutdown): " + ", ".join(f"'{line}'" for line in var_file_lines(c))
        )
    if not args.output.lower().endswith(EXTENSIONS[c.dialect]):
        print(f"note: {c.dialect} programs usually end in {EXTENSIONS[c.dialect]}")
    return 0
