"""The virtual CNC's NC interpreter: spindle words and dwells only, in four dialects.

It reads what an operator would load for a warm-up or calibration run: spindle on/off,
speed and dwell, with comments; anything else (an axis move, an unknown word) is refused
with the line number, like a control's syntax check. The result is a
:class:`~compensator.speed_programs.Program` the virtual machine runs.

Syntax accepted, per dialect:

- ``fanuc``: ``%`` lines, ``O<n>`` program number, ``( ... )`` comments, ``S<n>``, ``M03``/
  ``M04``/``M05``, ``G04 X<s>`` (with a decimal point: seconds) or ``G04 P<ms>``, ``M30``/``M02``;
- ``sinumerik``: ``%_N_..._MPF`` and ``;$PATH`` headers, ``;`` comments, ``S<n>``, ``M3``/``M4``/
  ``M5``, ``G4 F<s>`` alone in its block, ``M30``/``M2``/``M17``;
- ``heidenhain`` (Klartext): numbered blocks, ``BEGIN PGM <name> MM``, ``; comments``,
  ``TOOL CALL [<n>] Z S<n>``, ``M3``/``M4``/``M5``, ``CYCL DEF 9.0 DWELL TIME`` followed by
  ``CYCL DEF 9.1 DWELL <s>``, ``END PGM <name> MM``;
- ``linuxcnc`` (RS274/NGC): ``%`` lines, ``( ... )`` and ``;`` comments, ``S<n>``, ``M3``/``M4``/
  ``M5``, ``G4 P<s>``, ``M2``/``M30``.

A subprogram call, alone in its block, runs the machine's tool-setter cycle, the only
subprogram the virtual machine has: ``M98 P<n>`` (fanuc), ``CALL "<name>"`` (sinumerik),
``CALL PGM <name>`` (heidenhain), ``o<name> call`` (linuxcnc). It is kept as a probe stop at the
program time reached (:attr:`~compensator.speed_programs.Program.probe_at_s`); the cycle leaves
the spindle stopped, so the program must start it again.
"""

from __future__ import annotations

import re

from compensator.speed_programs import Program

NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)"
CALLS = {
    "fanuc": r"M98\s*P\d{1,5}",
    "sinumerik": r'CALL\s*"[A-Z_][A-Z0-9_]*"',
    "heidenhain": r"CALL PGM [A-Z_][A-Z0-9_]*(?:\.H)?",
    "linuxcnc": r"O<[A-Z0-9_-]+>\s*CALL",
}
"""A call of the tool-setter cycle, per dialect (matched on the upper-cased block)."""


class NcSyntaxError(ValueError):
    def __init__(self, message: str, line: int):
        super().__init__(f"line {line}: {message}")
        self.line = line


def detect_dialect(text: str) -> str:
    for raw in text.splitlines():
        s = raw.strip()
        if not s or s == "%":
            continue
        if re.match(r"^\d+\s+BEGIN PGM\b", s):
            return "heidenhain"
        if s.startswith(("%_N_", ";")):
            return "sinumerik"
        if re.match(r"^O\d+", s):
            return "fanuc"
        return "linuxcnc"
    raise NcSyntaxError("empty program", 1)


class _Machine:
    def __init__(self) -> None:
        self.on = False
        self.speed = 0.0
        self.segments: list[tuple[float, float]] = []
        self.probes: list[float] = []
        self.ended = False

    def probe(self) -> None:
        """The tool-setter cycle runs here; it leaves the spindle stopped."""
        self.probes.append(float(sum(d for d, _ in self.segments)))
        self.on = False

    def dwell(self, seconds: float, line: int) -> None:
        if not seconds >= 0:
            raise NcSyntaxError(f"negative dwell {seconds}", line)
        rpm = self.speed if self.on else 0.0
        if self.segments and self.segments[-1][1] == rpm:
            self.segments[-1] = (self.segments[-1][0] + seconds, rpm)
        elif seconds > 0:
            self.segments.append((seconds, rpm))

    def m(self, code: int, line: int) -> None:
        if code in (3, 4):
            self.on = True
        elif code == 5:
            self.on = False
        elif code in (2, 30, 17):
            self.on = False
            self.ended = True
        else:
            raise NcSyntaxError(f"M{code} is not allowed in a spindle program", line)


def _words(block: str, line: int) -> list[tuple[str, str]]:
    words = re.findall(rf"([A-Z])\s*({NUMBER})", block)
    rest = re.sub(rf"([A-Z])\s*({NUMBER})", "", block).strip()
    if rest:
        raise NcSyntaxError(f"cannot read {rest!r}", line)
    return words


def _iso_block(m: _Machine, block: str, line: int, dialect: str) -> None:
    words = _words(block, line)
    letters = [w for w, _ in words]
    for letter, value in words:
        if letter not in "GMSXPFNO":
            raise NcSyntaxError(f"word {letter}{value} is not allowed (no axis may move)", line)
    g = [float(v) for w, v in words if w == "G"]
    if g:
        if g != [4.0] or len(words) != 2:
            raise NcSyntaxError("only a dwell (G4) is allowed, alone in its block", line)
        arg, value = words[1]
        if dialect == "fanuc":
            if arg == "X" and "." in value:
                return m.dwell(float(value), line)
            if arg == "P" and "." not in value:
                return m.dwell(float(value) / 1000.0, line)
            raise NcSyntaxError(
                "Fanuc dwell is G04 X<seconds with a decimal point> or G04 P<ms>", line
            )
        want = {"sinumerik": "F", "linuxcnc": "P"}[dialect]
        if arg != want:
            raise NcSyntaxError(f"dwell is G4 {want}<seconds> in {dialect}", line)
        return m.dwell(float(value), line)
    if any(w in "XPF" for w in letters):
        raise NcSyntaxError("X, P or F outside a dwell", line)
    for letter, value in words:
        if letter == "S":
            if float(value) < 0:
                raise NcSyntaxError("negative speed", line)
            m.speed = float(value)
    for letter, value in words:
        if letter == "M":
            m.m(int(float(value)), line)


def parse_nc(text: str, name: str = "nc-program") -> Program:
    """The speed program an NC text commands; :class:`NcSyntaxError` on anything else."""
    dialect = detect_dialect(text)
    m = _Machine()
    pending_dwell: int | None = None
    for lineno, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip().upper()
        if not s:
            continue
        if m.ended and s != "%":
            raise NcSyntaxError("blocks after the end of the program", lineno)
        if dialect == "heidenhain":
            hm = re.match(r"^(\d+)\s+(.*)$", s)
            if not hm:
                raise NcSyntaxError("a Klartext block starts with its number", lineno)
            body = hm.group(2).strip()
            if body.startswith(";"):
                continue
            if pending_dwell is not None:
                dm = re.match(rf"^CYCL DEF 9\.1 DWELL\s*({NUMBER})$", body)
                if not dm:
                    raise NcSyntaxError(
                        "CYCL DEF 9.0 must be followed by CYCL DEF 9.1 DWELL <s>", lineno
                    )
                m.dwell(float(dm.group(1)), lineno)
                pending_dwell = None
                continue
            if re.fullmatch(CALLS[dialect], body):
                m.probe()
                continue
            if re.match(r"^BEGIN PGM \w+ (MM|INCH)$", body):
                continue
            if re.match(r"^END PGM \w+ (MM|INCH)$", body):
                m.on, m.ended = False, True
                continue
            if body == "CYCL DEF 9.0 DWELL TIME":
                pending_dwell = lineno
                continue
            tm = re.match(r"^TOOL CALL(?:\s+\d+)?\s+Z\s+S(\d+(?:\.\d*)?)$", body)
            if tm:
                m.speed = float(tm.group(1))
                continue
            mm = re.match(r"^M(\d+)$", body)
            if mm:
                m.m(int(mm.group(1)), lineno)
                continue
            raise NcSyntaxError(f"block {body!r} is not allowed", lineno)
        if s == "%":
            continue
        if dialect == "fanuc":
            if re.match(r"^O\d{1,5}\s*(\(.*\))?$", s):
                continue
        if dialect == "sinumerik" and (s.startswith(("%_N_", ";$PATH"))):
            continue
        body = s
        if dialect in ("fanuc", "linuxcnc"):
            if body.count("(") != body.count(")"):
                raise NcSyntaxError("unbalanced comment parentheses", lineno)
            body = re.sub(r"\([^()]*\)", "", body)
        if dialect in ("sinumerik", "linuxcnc"):
            body = body.split(";", 1)[0]
        body = body.strip()
        if re.fullmatch(CALLS[dialect], body):
            m.probe()
        elif body:
            _iso_block(m, body, lineno, dialect)
    if pending_dwell is not None:
        raise NcSyntaxError("CYCL DEF 9.0 without 9.1", pending_dwell)
    if not m.ended:
        raise NcSyntaxError(
            f"no end of program ({'END PGM' if dialect == 'heidenhain' else 'M30/M2'})",
            len(text.splitlines()),
        )
    if not m.segments:
        raise NcSyntaxError("the program has no dwell: it would take no time", 1)
    return Program(name, tuple(m.segments), tuple(m.probes))
