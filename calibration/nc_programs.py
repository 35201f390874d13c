"""Calibration speed profiles and the NC programs that run them. Pure: text in, text out.

The calibration profile is the paper's (paper 001, Fig. 3; ``docs/REFERENCES.md``), scaled to the
spindle's maximum speed: a staircase up, abrupt drops, a fluctuating phase, then a
cool-down at 0 rpm. The validation profile is a different, random one.

Dialects and the words they use (no axis ever moves):

=============  ==================================  =========================  ===========
dialect        speed / spindle on                  dwell [s]                  end
=============  ==================================  =========================  ===========
fanuc          ``S3000 M03``                       ``G04 X1200.0``            ``M30``
sinumerik      ``S3000 M3``                        ``G4 F1200`` (own block)   ``M30``
heidenhain     ``TOOL CALL Z S3000`` + ``M3``      ``CYCL DEF 9.0/9.1``       ``END PGM``
linuxcnc       ``S3000 M3``                        ``G4 P1200``               ``M2``
=============  ==================================  =========================  ===========

Dwells are split into blocks of at most ``MAX_DWELL_S`` (the TNC's cycle 9 takes at most
3600 s; the others accept it too).

Probe stops (calibration with the machine's tool setter alone, no eddy-current sensor): a
program with ``probe_at_s`` (:func:`with_probe_stops`) calls the tool-setter cycle that
``thermocomp probe-program`` writes (``calibration/probeprog.py``, ``docs/PROBING.md``) at each
of those program times. The cycle stops the spindle, measures and hands the value over; the
program then starts the spindle again. The cycle's own time is not in the program's time.

=============  ==========================  ============================================
dialect        call                        the cycle (as probeprog names it)
=============  ==========================  ============================================
fanuc          ``M98 P1100``               program ``O1100``
sinumerik      ``CALL "TCPROBE"``          ``TCPROBE.MPF`` (``--name``)
heidenhain     ``CALL PGM TCPROBE``        ``TCPROBE.H`` (``--name``)
linuxcnc       ``o<tcprobe> call``         ``tcprobe.ngc`` (lower case, on the subroutine path)
=============  ==========================  ============================================
"""

from __future__ import annotations

import math
from collections.abc import Iterator

from compensator.speed_programs import Program, paper_calibration, random_validation

DIALECTS = ("fanuc", "sinumerik", "heidenhain", "linuxcnc")
EXTENSIONS = {"fanuc": ".nc", "sinumerik": ".mpf", "heidenhain": ".h", "linuxcnc": ".ngc"}
MAX_DWELL_S = 3600.0
DEFAULT_REST_H = 8.0
PROBE_NAME = "TCPROBE"
"""The tool-setter cycle's program name: ``thermocomp probe-program``'s default ``--name``."""
FANUC_PROBE_NUMBER = 1100
"""The tool-setter cycle's program number on FANUC: probeprog writes it as ``O1100``."""


def calibration_profile(
    max_rpm: float,
    *,
    step_min: float = 20.0,
    cooldown_min: float = 60.0,
    round_rpm: float = 10.0,
    probe_every_s: float | None = None,
) -> Program:
    """The paper's profile at ``max_rpm``, speeds rounded to ``round_rpm``; with
    ``probe_every_s``, a tool-setter stop every that many seconds of program time
    (:func:`with_probe_stops`)."""
    _check_max(max_rpm)
    if not (step_min > 0 and cooldown_min >= 0):
        raise ValueError("step_min must be > 0 and cooldown_min >= 0")
    p = paper_calibration(max_rpm, cooldown_min=cooldown_min, step_min=step_min)
    prog = Program("calibration", _merged((round(d), _round(s, round_rpm)) for d, s in p.segments))
    return prog if probe_every_s is None else with_probe_stops(prog, probe_every_s)


def probe_stops(duration_s: float, every_s: float) -> tuple[float, ...]:
    """Program times of a tool-setter stop every ``every_s`` (whole seconds), and one at the
    end: the last cool-down reading pins the dissipation."""
    if not (math.isfinite(every_s) and every_s >= 1):
        raise ValueError(f"probe interval {every_s!r} s: give a number of seconds >= 1")
    every = float(round(every_s))
    stops = [every * k for k in range(1, int(duration_s // every) + 1) if every * k < duration_s]
    return (*stops, float(duration_s))


def with_probe_stops(program: Program, every_s: float) -> Program:
    """``program`` with a tool-setter stop every ``every_s`` of program time and at its end."""
    return Program(program.name, program.segments, probe_stops(program.duration_s, every_s))


def validation_profile(
    max_rpm: float, *, seed: int = 1, duration_min: float = 240.0, round_rpm: float = 10.0
) -> Program:
    """Random speeds held 2-15 min with stops, then 30 min at rest: unlike calibration."""
    _check_max(max_rpm)
    p = random_validation(max_rpm, seed=seed, duration_min=duration_min)
    return Program(
        f"validation-{seed}", _merged((round(d), _round(s, round_rpm)) for d, s in p.segments)
    )


def _merged(segments) -> tuple[tuple[float, float], ...]:
    """Whole seconds; neighbours at the same speed joined (an NC program cannot tell them apart)."""
    out: list[tuple[float, float]] = []
    for d, s in segments:
        if out and out[-1][1] == s:
            out[-1] = (out[-1][0] + d, s)
        elif d > 0:
            out.append((float(d), s))
    return tuple(out)


def _check_max(max_rpm: float) -> None:
    if not (math.isfinite(max_rpm) and 100 <= max_rpm <= 200_000):
        raise ValueError(f"maximum speed {max_rpm!r} rpm is not plausible (100 to 200000)")


def _round(speed: float, step: float) -> float:
    return float(round(speed / step) * step) if speed > 0 else 0.0


def rest_hours(time_constants_s: tuple[float, ...] | None = None) -> float:
    """How long the spindle must rest before a cold start: 5 of its slowest time constants
    (99 % cooled) when a former model gives them, else a night (8 h)."""
    if not time_constants_s:
        return DEFAULT_REST_H
    return max(1.0, math.ceil(5 * max(time_constants_s) / 3600.0))


def _dwells(seconds: float) -> Iterator[float]:
    left = round(seconds, 3)
    while left > 1e-9:
        chunk = min(left, MAX_DWELL_S)
        yield chunk
        left = round(left - chunk, 3)


def _num(x: float) -> str:
    return f"{x:.1f}" if x != int(x) else f"{int(x)}"


def probe_call(dialect: str, probe_name: str = PROBE_NAME) -> str:
    """The block that calls the tool-setter cycle in ``dialect`` (see the module's table)."""
    if dialect == "fanuc":
        return f"M98 P{FANUC_PROBE_NUMBER}"
    pname = _program_name(probe_name, PROBE_NAME)
    if dialect == "sinumerik":
        return f'CALL "{pname}"'
    if dialect == "heidenhain":
        return f"CALL PGM {pname}"
    if dialect == "linuxcnc":
        return f"o<{pname.lower()}> call"  # LinuxCNC finds the file by its lower-case name
    raise ValueError(f"unknown dialect {dialect!r}; choose from {', '.join(DIALECTS)}")


def _program_name(name: str, default: str) -> str:
    return "".join(c for c in name.upper() if c.isalnum() or c == "_")[:24] or default


def _check_stops(program: Program) -> tuple[float, ...]:
    stops = tuple(float(p) for p in program.probe_at_s)
    if any(not (math.isfinite(p) and 0 < p <= program.duration_s + 1e-9) for p in stops) or list(
        stops
    ) != sorted(stops):
        raise ValueError("probe stops must be ascending program times within the program")
    return stops


def to_nc(
    program: Program,
    dialect: str,
    *,
    name: str = "THERMOCOMP",
    notes: tuple[str, ...] = (),
    probe_name: str = PROBE_NAME,
) -> str:
    """The NC program text for ``program`` in ``dialect``; with ``program.probe_at_s``, a call of
    the tool-setter cycle (``probe_name``; FANUC: ``O1100``) at each of those program times."""
    if dialect not in DIALECTS:
        raise ValueError(f"unknown dialect {dialect!r}; choose from {', '.join(DIALECTS)}")
    pname = _program_name(name, "THERMOCOMP")
    stops = _check_stops(program)
    call = probe_call(dialect, probe_name) if stops else ""
    head = [
        f"THERMOCOMP {program.name.upper()} PROFILE",
        f"DURATION {program.duration_s / 3600:.2f} H, MAX {max(s for _, s in program.segments):.0f} RPM",
    ]
    if stops:
        head += [
            f"{len(stops)} TOOL-SETTER STOPS: {call.upper().replace(chr(34), '')}, THE CYCLE SETS THE SPINDLE",
            "NO AXIS MOVES BUT THE CYCLES. SPINDLE CLEAR OF THE WORK, GAUGE TOOL OF THE CYCLE IN THE SPINDLE",
            "PROGRAM TIMES BELOW DO NOT COUNT THE CYCLES",
        ]
    else:
        head += ["NO AXIS MOVES. SPINDLE CLEAR OF THE WORK, PROBE IN PLACE"]
    head += [n.upper() for n in notes]
    out: list[str] = []
    comment = {
        "fanuc": lambda t: f"({t.replace('(', '[').replace(')', ']')})",
        "linuxcnc": lambda t: f"({t.replace('(', '[').replace(')', ']')})",
        "sinumerik": lambda t: f"; {t}",
        "heidenhain": lambda t: f"; {t}",
    }[dialect]
    if dialect == "fanuc":
        out += ["%", f"O1000 ({pname[:16]})"]
    elif dialect == "linuxcnc":
        out += ["%"]
    elif dialect == "sinumerik":
        out += [f"%_N_{pname}_MPF", ";$PATH=/_N_MPF_DIR"]
    else:
        out += [f"BEGIN PGM {pname} MM"]
    out += [comment(t) for t in head]
    on, speed, elapsed = False, 0.0, 0.0

    def hold(rpm: float, seconds: float) -> None:
        nonlocal on, speed
        if rpm > 0 and (not on or rpm != speed):
            if dialect == "heidenhain":
                out.append(f"TOOL CALL Z S{rpm:.0f}")
                if not on:
                    out.append("M3")
            else:
                m3 = "M03" if dialect == "fanuc" else "M3"
                out.append(f"S{rpm:.0f} {m3}")
            on, speed = True, rpm
        elif rpm <= 0 and on:
            out.append("M05" if dialect == "fanuc" else "M5")
            on = False
        for d in _dwells(seconds):
            if dialect == "fanuc":
                out.append(f"G04 X{d:.1f}")
            elif dialect == "sinumerik":
                out.append(f"G4 F{_num(d)}")
            elif dialect == "linuxcnc":
                out.append(f"G4 P{_num(d)}")
            else:
                out.extend(["CYCL DEF 9.0 DWELL TIME", f"CYCL DEF 9.1 DWELL {_num(d)}"])

    k = 0
    for duration, rpm in program.segments:
        out.append(comment(f"T+{elapsed / 60:.0f} MIN: {rpm:.0f} RPM FOR {duration / 60:.1f} MIN"))
        t, end = elapsed, elapsed + duration
        while k < len(stops) and stops[k] <= end + 1e-9:
            if stops[k] > t:
                hold(rpm, stops[k] - t)
                t = stops[k]
            out += [comment(f"T+{t / 60:.1f} MIN: TOOL-SETTER CYCLE {k + 1}/{len(stops)}"), call]
            on = False  # the cycle leaves the spindle stopped: the next speed block starts it again
            k += 1
        if end > t:
            hold(rpm, end - t)
        elapsed = end
    if on:
        out.append("M05" if dialect == "fanuc" else "M5")
    if dialect == "fanuc":
        out += ["M30", "%"]
    elif dialect == "linuxcnc":
        out += ["M2", "%"]
    elif dialect == "sinumerik":
        out += ["M30"]
    else:
        out += [f"END PGM {pname} MM"]
        out = [f"{i} {line}" for i, line in enumerate(out)]  # the TNC numbers every block
    return "\n".join(out) + "\n"
