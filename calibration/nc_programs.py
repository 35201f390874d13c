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
"""

from __future__ import annotations

import math
from collections.abc import Iterator

from compensator.speed_programs import Program, paper_calibration, random_validation

DIALECTS = ("fanuc", "sinumerik", "heidenhain", "linuxcnc")
EXTENSIONS = {"fanuc": ".nc", "sinumerik": ".mpf", "heidenhain": ".h", "linuxcnc": ".ngc"}
MAX_DWELL_S = 3600.0
DEFAULT_REST_H = 8.0


def calibration_profile(max_rpm: float, *, step_min: float = 20.0, cooldown_min: float = 60.0,
                        round_rpm: float = 10.0) -> Program:
    """The paper's profile at ``max_rpm``, speeds rounded to ``round_rpm``."""
    _check_max(max_rpm)
    if not (step_min > 0 and cooldown_min >= 0):
        raise ValueError("step_min must be > 0 and cooldown_min >= 0")
    p = paper_calibration(max_rpm, cooldown_min=cooldown_min, step_min=step_min)
    return Program("calibration", _merged((round(d), _round(s, round_rpm)) for d, s in p.segments))


def validation_profile(max_rpm: float, *, seed: int = 1, duration_min: float = 240.0,
                       round_rpm: float = 10.0) -> Program:
    """Random speeds held 2-15 min with stops, then 30 min at rest: unlike calibration."""
    _check_max(max_rpm)
    p = random_validation(max_rpm, seed=seed, duration_min=duration_min)
    return Program(f"validation-{seed}", _merged((round(d), _round(s, round_rpm)) for d, s in p.segments))


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


def to_nc(program: Program, dialect: str, *, name: str = "THERMOCOMP", notes: tuple[str, ...] = ()) -> str:
    """The NC program text for ``program`` in ``dialect``."""
    if dialect not in DIALECTS:
        raise ValueError(f"unknown dialect {dialect!r}; choose from {', '.join(DIALECTS)}")
    pname = "".join(c for c in name.upper() if c.isalnum() or c == "_")[:24] or "THERMOCOMP"
    head = [f"THERMOCOMP {program.name.upper()} PROFILE",
            f"DURATION {program.duration_s / 3600:.2f} H, MAX {max(s for _, s in program.segments):.0f} RPM",
            "NO AXIS MOVES. SPINDLE CLEAR OF THE WORK, PROBE IN PLACE",
            *(n.upper() for n in notes)]
    out: list[str] = []
    comment = {"fanuc": lambda t: f"({t.replace('(', '[').replace(')', ']')})",
               "linuxcnc": lambda t: f"({t.replace('(', '[').replace(')', ']')})",
               "sinumerik": lambda t: f"; {t}", "heidenhain": lambda t: f"; {t}"}[dialect]
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
    for duration, rpm in program.segments:
        out.append(comment(f"T+{elapsed / 60:.0f} MIN: {rpm:.0f} RPM FOR {duration / 60:.1f} MIN"))
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
        for d in _dwells(duration):
            if dialect == "fanuc":
                out.append(f"G04 X{d:.1f}")
            elif dialect == "sinumerik":
                out.append(f"G4 F{_num(d)}")
            elif dialect == "linuxcnc":
                out.append(f"G4 P{_num(d)}")
            else:
                out += ["CYCL DEF 9.0 DWELL TIME", f"CYCL DEF 9.1 DWELL {_num(d)}"]
        elapsed += duration
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
