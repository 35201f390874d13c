"""The control-side watchdog recipes in docs/controls against the code: each family's page has
one, names only sign-of-life options its backends really take and the defaults its profile
really has, and its NC code watches those very variables. The Structured Text watchdog block
(any PLC, Beckhoff) is parsed with an IEC 61131-3 grammar (blark, TwinCAT's dialect) and run as
written by a small interpreter of its syntax tree, scan by scan in simulated time (an injected
clock: nothing here waits): the timeout, the flag, the latch, the fade's first order and its cap,
the write-back, a PLC start."""

from __future__ import annotations

import dataclasses
import itertools
import math
import re
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from blark.parse import parse_source_code

from cnc_adapters import settings_model
from cnc_adapters.control_profiles import PROFILES

ROOT = Path(__file__).resolve().parents[1]
CONTROLS = ROOT / "docs" / "controls"
HEADING = "## Watchdog: when thermocomp stops"

# each page, the profile it documents (None: the generic PLC link) and the backends it configures
FAMILIES = {
    "sinumerik": ("sinumerik", ("opcua", "plc")),
    "fanuc": ("fanuc", ("focas",)),
    "heidenhain": ("heidenhain", ("plc",)),
    "haas": ("haas", ("haas-mdc", "haas")),
    "beckhoff": ("beckhoff", ("plc",)),
    "plc": (None, ("plc",)),
}


def watchdog_section(page: str) -> str:
    text = (CONTROLS / f"{page}.md").read_text()
    assert text.count(HEADING) == 1, f"{page}.md: no '{HEADING}' section"
    return text.split(HEADING, 1)[1].split("\n## ", 1)[0]


def code_blocks(text: str, lang: str = "") -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", text, re.S)


def life_options(kind: str) -> set[str]:
    model = settings_model(kind)
    assert model is not None, kind
    return {n for n in model.model_fields if n.startswith(("life_", "valid_"))}


def life_defaults(profile: str) -> dict[str, dict[str, Any]]:
    """Each route's default sign-of-life options."""
    return {
        name: {k: v for k, v in r.adapter.items() if k.startswith(("life_", "valid_"))}
        for name, r in PROFILES[profile].routes.items()
    }


@pytest.mark.parametrize("page", sorted(FAMILIES))
def test_each_family_page_has_a_watchdog_with_the_three_reactions_and_their_costs(page):
    s = watchdog_section(page)
    assert "../FAULTS.md#when-thermocomp-is-not-running" in s
    for words in ("alarm", "feed hold", "fade"):
        assert words in s.lower(), (page, words)
    assert "what it costs" in s, page
    # the fade follows cooling only at rest: every recipe says so, and says where tau comes from
    assert re.search(r"runs? (on|hot)|running hot", s), page
    assert "thermocomp model show" in s, page


@pytest.mark.parametrize("page", sorted(FAMILIES))
def test_the_pages_name_only_sign_of_life_options_the_backends_take(page):
    s = watchdog_section(page)
    _, kinds = FAMILIES[page]
    known = set().union(*(life_options(k) for k in kinds))
    named = set(re.findall(r"`((?:life|valid)_[a-z]+)", s))
    assert named, page
    assert named <= known, f"{page}.md names options no backend takes: {sorted(named - known)}"
    for kind in kinds:  # the counter and the flag of every backend the page configures
        options = life_options(kind)
        assert any(o.startswith("life_") and o in named for o in options), (page, kind)
        assert any(o.startswith("valid_") and o in named for o in options), (page, kind)


@pytest.mark.parametrize("page", sorted(p for p, (prof, _) in FAMILIES.items() if prof))
def test_the_profile_defaults_are_on_the_family_page_and_the_index(page):
    profile, _ = FAMILIES[page]
    s = watchdog_section(page)
    index = (CONTROLS / "index.md").read_text().split("## When thermocomp stops", 1)[1]
    label = {"sinumerik": "SINUMERIK", "fanuc": "FANUC", "heidenhain": "HEIDENHAIN"}.get(
        page, page.capitalize()
    )
    row = next(line for line in index.splitlines() if line.startswith(f"| {label} |"))
    defaults = life_defaults(profile)
    if page == "heidenhain":  # the gateway's addresses: no default, and the pages say so
        assert not any(defaults.values())
        assert "none" in row and "no default" in PROFILES[profile].life_sign
        return
    for route, values in defaults.items():
        assert {k.split("_")[0] for k in values} == {"life", "valid"}, (profile, route)
        for value in values.values():
            assert str(value) in s, (page, route, value)
            r_param = re.search(r"R\[u1,(\d+)\]", str(value))
            assert (f"R{r_param[1]}" if r_param else str(value)) in row, (page, value)


def test_the_nc_code_watches_the_profiles_variables():
    """The synchronized actions read the R parameters the OPC UA route writes; the FANUC and Haas
    macros the macro variables the profiles write; the Beckhoff call the profile's symbols."""
    s = watchdog_section("sinumerik")
    code = "\n".join(code_blocks(s))
    for value in life_defaults("sinumerik")["opcua"].values():
        n = re.search(r"R\[u1,(\d+)\]", value)
        assert n is not None and f"$R[{n[1]}]" in code, value
    assert "SETAL(" in code and "$AC_OVR=0" in code and "$AC_TIMER[1]=0" in code
    for page, program, route in (("fanuc", "O9020", "focas"), ("haas", "O08501", "mdc")):
        macro = next(c for c in code_blocks(watchdog_section(page)) if program in c)
        values = life_defaults(page)[route].values()
        for value in values:
            assert f"#{value}" in macro, (page, value)
        assert "#3000 =" in macro and "#3001" in macro
    beckhoff = watchdog_section("beckhoff")
    call = next(c for c in code_blocks(beckhoff, "iecst") if "fbWatch(" in c)
    for value in life_defaults("beckhoff")["ads"].values():
        assert f":= {value}" in call, value


# -- the Structured Text block: parsed, then run ------------------------------------------------


def st_blocks(page: str) -> list[str]:
    return code_blocks(watchdog_section(page), "iecst")


@pytest.mark.parametrize("page", ["plc", "beckhoff"])
def test_the_structured_text_parses_as_iec_61131_3(page):
    blocks = st_blocks(page)
    assert any("FUNCTION_BLOCK FB_ThermoWatchdog" in b for b in blocks)
    for block in blocks:
        source = block if "FUNCTION_BLOCK" in block else f"PROGRAM P\n{block}\nEND_PROGRAM\n"
        result = parse_source_code(source)
        assert result.exception is None, f"{page}.md:\n{block}\n{result.exception}"


def _float32(x: float) -> float:
    return struct.unpack("f", struct.pack("f", x))[0]


class Ton:
    """IEC 61131-3 TON on the interpreter's clock: ET counts from IN's rising edge up to PT, Q
    once ET reaches PT; IN false resets both."""

    def __init__(self, clock: Callable[[], int]) -> None:
        self.clock, self.IN, self.PT, self.Q, self.ET, self.start = clock, False, 0, False, 0, 0

    def call(self, IN: bool | None = None, PT: int | None = None) -> None:
        rising = IN is not None and IN and not self.IN
        if IN is not None:
            self.IN = IN
        if PT is not None:
            self.PT = PT
        if rising:
            self.start = self.clock()
        self.ET = min(self.clock() - self.start, self.PT) if self.IN else 0
        self.Q = self.IN and self.ET >= self.PT


Thunk = Callable[[], Any]

OPERATORS: dict[str, Callable[[Any, Any], Any]] = {
    "=": lambda a, b: a == b,
    "<>": lambda a, b: a != b,
    "<": lambda a, b: a < b,
    ">": lambda a, b: a > b,
    "<=": lambda a, b: a <= b,
    ">=": lambda a, b: a >= b,
    "+": lambda a, b: a + b,
    "-": lambda a, b: a - b,
    "*": lambda a, b: a * b,
    "/": lambda a, b: a / b,
}
FUNCTIONS: dict[str, Callable[..., Any]] = {
    "EXP": math.exp,
    "ABS": abs,
    "LIMIT": lambda lo, x, hi: min(max(x, lo), hi),
    "TIME_TO_REAL": float,  # a TIME counts ms
    "TIME_TO_LREAL": float,
    "DINT_TO_LREAL": float,
    "LREAL_TO_DINT": round,
}


class FunctionBlock:
    """One instance of a FUNCTION_BLOCK, its syntax tree compiled once into Python closures and
    run per scan. The subset the watchdog uses: BOOL, INT, DINT, REAL (kept at 32 bits), LREAL,
    TIME (ms), TON; assignments, IF/ELSIF/ELSE, calls of TON instances with named inputs, the
    operators, EXP, LIMIT, ABS and the conversions. Anything else raises, so that no statement
    of the page goes unrun."""

    def __init__(self, source: str) -> None:
        result = parse_source_code(source)
        assert result.exception is None, result.exception
        (self.fb,) = [i for i in result.transform().items if type(i).__name__ == "FunctionBlock"]
        self.now_ms = 0
        self.types: dict[str, str] = {}
        self.kinds: dict[str, str] = {}
        self.vars: dict[str, Any] = {}
        for decl in self.fb.declarations:
            kind = type(decl).__name__
            for item in decl.items:
                type_name = str(item.init.spec.type).upper()
                for v in item.variables:
                    name = str(v.variable.name).lower()
                    self.types[name], self.kinds[name] = type_name, kind
                    if type_name == "TON":
                        self.vars[name] = Ton(lambda: self.now_ms)
                    else:
                        init = item.init.value
                        default = {"BOOL": False, "TIME": 0}.get(type_name, 0)
                        self.store(name, default if init is None else self.expr(init)())
        self.body = self.block(self.fb.body.statements)

    def store(self, name: str, value: Any) -> None:
        t = self.types[name]
        if t == "BOOL":
            value = bool(value)
        elif t == "INT":
            value = (int(value) + 32768) % 65536 - 32768
        elif t in ("DINT", "TIME"):
            value = int(value)
        elif t == "REAL":
            value = _float32(float(value))
        elif t == "LREAL":
            value = float(value)
        else:
            raise NotImplementedError(t)
        self.vars[name] = value

    def scan(self, now_ms: int, **values: Any) -> dict[str, Any]:
        """One call at ``now_ms``: inputs and in-outs set, the body run; every output and in-out
        returned."""
        self.now_ms = now_ms
        for name, value in values.items():
            assert self.kinds[name.lower()] in ("InputDeclarations", "InputOutputDeclarations")
            self.store(name.lower(), value)
        self.body()
        return {
            n: v
            for n, v in self.vars.items()
            if self.kinds[n] in ("OutputDeclarations", "InputOutputDeclarations")
        }

    def block(self, statements: list[Any]) -> Thunk:
        steps = [self.statement(st) for st in statements]

        def run() -> None:
            for step in steps:
                step()

        return run

    def statement(self, st: Any) -> Thunk:
        kind = type(st).__name__
        if kind == "AssignmentStatement":
            (target,) = st.variables
            name, value = str(target.name).lower(), self.expr(st.expression)
            assert name in self.types, name
            return lambda: self.store(name, value())
        if kind == "IfStatement":
            branches = [(st.if_expression, st.statements)]
            branches += [(e.if_expression, e.statements) for e in st.else_ifs]
            compiled = [(self.expr(c), self.block(b.statements)) for c, b in branches]
            otherwise = (
                self.block(st.else_clause.statements.statements)
                if st.else_clause is not None
                else (lambda: None)
            )

            def run_if() -> None:
                for cond, body in compiled:
                    if cond():
                        body()
                        return
                otherwise()

            return run_if
        if kind == "FunctionCallStatement":
            ton = self.vars[str(st.name.name).lower()]
            assert isinstance(ton, Ton)
            params = {str(p.name.name).upper(): self.expr(p.value) for p in st.parameters}
            return lambda: ton.call(**{k: v() for k, v in params.items()})
        raise NotImplementedError(kind)

    def expr(self, e: Any) -> Thunk:
        kind = type(e).__name__
        if kind == "SimpleVariable":
            name = str(e.name).lower()
            assert name in self.vars, name
            return lambda: self.vars[name]
        if kind == "MultiElementVariable":
            (field,) = e.elements
            instance, attr = self.vars[str(e.name.name).lower()], str(field.field.name).upper()
            assert isinstance(instance, Ton) and attr in ("Q", "ET"), attr
            return lambda: getattr(instance, attr)
        if kind in ("Integer", "Real", "Boolean", "Duration"):
            value = self.literal(e)
            return lambda: value
        if kind == "ParenthesizedExpression":
            return self.expr(e.expr)
        if kind == "UnaryOperation":
            inner, op = self.expr(e.expr), str(e.op).upper()
            return (lambda: not inner()) if op == "NOT" else (lambda: -inner())
        if kind == "FunctionCall":
            f = FUNCTIONS[str(e.name.name).upper()]
            args = [self.expr(p.value) for p in e.parameters]
            return lambda: f(*(a() for a in args))
        if kind == "BinaryOperation":
            a, b, op = self.expr(e.left), self.expr(e.right), str(e.op).upper()
            if op == "AND":
                return lambda: a() and b()
            if op == "OR":
                return lambda: a() or b()
            f2 = OPERATORS[op]
            return lambda: f2(a(), b())
        raise NotImplementedError(kind)

    @staticmethod
    def literal(e: Any) -> Any:
        kind = type(e).__name__
        if kind == "Integer":
            return int(str(e.value))
        if kind == "Real":
            return float(str(e.value))
        if kind == "Boolean":
            return str(e.value).upper() == "TRUE"
        parts = (e.days, e.hours, e.minutes, e.seconds, e.milliseconds)  # a Duration
        scale = (86_400_000, 3_600_000, 60_000, 1000, 1)
        return sum(float(str(p)) * s for p, s in zip(parts, scale, strict=True) if p)


@dataclasses.dataclass(frozen=True)
class Names:
    """The block's variable names on a page, and its offset's unit."""

    counter: str
    valid: str
    fade: str
    rest: str
    ack: str
    offset: str
    ok: str
    lost: str
    apply: str
    tau: str
    per_um: float  # offset units per um


PAGES = {
    "plc": Names(
        "nLifeCounter",
        "xCompValid",
        "xFade",
        "xSpindleAtRest",
        "xAck",
        "rOffset",
        "xOk",
        "xLost",
        "rApply",
        "rTau_s",
        0.001,
    ),
    "beckhoff": Names(
        "nLifeCounter",
        "bCompValid",
        "bFade",
        "bSpindleAtRest",
        "bAck",
        "nTempComp",
        "bOk",
        "bLost",
        "nApply",
        "fTau_s",
        10.0,
    ),
}
SCAN_MS = 10


class Plc:
    """The block in a PLC task with a scan of ``scan_ms``, and thermocomp writing a beat every
    second while ``alive`` (with the offset ``writes_um``, or only the beat: a confirm)."""

    def __init__(
        self,
        page: str,
        offset_um: float,
        scan_ms: int = SCAN_MS,
        counter: int = 7,
        alive: bool = True,
        **inputs: Any,
    ) -> None:
        (source,) = [b for b in st_blocks(page) if "FUNCTION_BLOCK FB_ThermoWatchdog" in b]
        self.fb, self.n, self.scan_ms = FunctionBlock(source), PAGES[page], scan_ms
        self.t_ms, self.counter, self.valid, self.alive = 0, counter, True, alive
        self.offset = offset_um * self.n.per_um
        self.writes_um: float | None = None
        self.inputs: dict[str, Any] = {self.n.rest: True, self.n.ack: False, **inputs}
        self.out = self.step()

    def step(self) -> dict[str, Any]:
        n = self.n
        if self.alive and self.t_ms % 1000 == 0:
            self.counter = self.counter % 32767 + 1
            if self.writes_um is not None:
                self.offset = self.writes_um * n.per_um
        self.out = self.fb.scan(
            self.t_ms,
            **{n.counter: self.counter, n.valid: self.valid, n.offset: self.offset},
            **self.inputs,
        )
        self.offset = self.out[n.offset.lower()]  # the block may write it back
        self.t_ms += self.scan_ms
        return self.out

    def run_until(self, t_s: float) -> list[tuple[float, dict[str, Any]]]:
        trace = []
        while self.t_ms < t_s * 1000:
            trace.append((self.t_ms / 1000, self.step()))
        return trace

    def ok(self) -> bool:
        return bool(self.out[self.n.ok.lower()])

    def lost(self) -> bool:
        return bool(self.out[self.n.lost.lower()])

    def applied_um(self) -> float:
        return float(self.out[self.n.apply.lower()]) / self.n.per_um


@pytest.mark.parametrize("page", sorted(PAGES))
def test_the_block_sees_a_stopped_counter_after_the_timeout_and_a_false_flag_at_once(page):
    plc = Plc(page, offset_um=19.0)
    trace = plc.run_until(10.0)
    assert all(out[plc.n.ok.lower()] for _, out in trace), "alive, beating every second"
    assert plc.applied_um() == pytest.approx(19.0, abs=0.05)
    plc.alive = False  # kill -9: the last beat was at 9.0 s
    trace = plc.run_until(20.0)
    t_lost = next(t for t, out in trace if not out[plc.n.ok.lower()])
    assert 12.0 < t_lost <= 12.0 + 2 * SCAN_MS / 1000, t_lost  # 3 s after the last move
    assert plc.lost() and plc.applied_um() == pytest.approx(19.0, abs=0.05)  # held, no fade

    plc = Plc(page, offset_um=19.0)
    plc.run_until(5.0)
    plc.valid = False  # a clean stop: the flag false with one last beat
    plc.run_until(5.0 + SCAN_MS / 1000)
    assert not plc.ok() and plc.lost()

    plc = Plc(page, offset_um=19.0, counter=0, alive=False)  # never written
    assert not plc.ok()
    plc.run_until(1.0)
    assert not plc.ok()


@pytest.mark.parametrize("page", sorted(PAGES))
def test_the_loss_is_latched_until_acknowledged_and_the_value_is_taken_again(page):
    plc = Plc(page, offset_um=19.0)
    plc.run_until(5.0)
    plc.alive = False
    plc.run_until(10.0)
    plc.inputs[plc.n.ack] = True  # an acknowledgement while still lost clears nothing
    plc.run_until(10.5)
    assert plc.lost()
    plc.inputs[plc.n.ack] = False
    plc.alive = True  # thermocomp returns: it reads back the held value and ramps from it
    plc.writes_um = 21.0
    plc.run_until(12.0)
    assert plc.ok() and plc.lost(), "back, but nobody has looked yet"
    assert plc.applied_um() == pytest.approx(21.0, abs=0.05)
    plc.inputs[plc.n.ack] = True
    plc.run_until(12.1)
    assert plc.ok() and not plc.lost()


@pytest.mark.parametrize("page", sorted(PAGES))
def test_the_fade_follows_cooling_at_rest_and_holds_while_the_spindle_turns(page):
    tau_s = 60.0  # a short time constant: the first order shows within two minutes
    plc = Plc(page, offset_um=19.0, scan_ms=20, **{PAGES[page].fade: True, PAGES[page].tau: tau_s})
    plc.run_until(3.0)
    plc.alive = False  # last beat at 2.0 s: lost from 5.0 s
    plc.inputs[plc.n.rest] = False  # the spindle runs on: the offset must hold
    plc.run_until(30.0)
    assert plc.applied_um() == pytest.approx(19.0, abs=0.05)
    plc.inputs[plc.n.rest] = True  # it stops at 30 s: the offset decays with tau from there
    trace = plc.run_until(150.0)
    written = [float(out[plc.n.offset.lower()]) / plc.n.per_um for _, out in trace]
    applied = [float(out[plc.n.apply.lower()]) / plc.n.per_um for _, out in trace]
    counts = 1 / plc.n.per_um if plc.n.per_um > 1 else 0.0  # a DINT's rounding
    for (t, _), a, w in zip(trace, applied, written, strict=True):
        expected = 19.0 * math.exp(-(t - 30.0) / tau_s)
        assert a == pytest.approx(expected, rel=0.01, abs=counts + 0.02), t
        assert w == pytest.approx(a, abs=counts), "written back for thermocomp's read-back"
    steps = [a - b for a, b in itertools.pairwise(applied)]
    assert all(s >= -1e-9 for s in steps), "toward zero only"


@pytest.mark.parametrize("page", sorted(PAGES))
def test_the_fade_is_capped_at_its_rate(page):
    """With a time constant entered far too short (2 s), the first-order rate (19 um / 2 s) would
    be 9.5 um/s: the cap holds it at 1 um/s until |offset| <= cap x tau (2 um)."""
    plc = Plc(page, offset_um=19.0, **{PAGES[page].fade: True, PAGES[page].tau: 2.0})
    plc.run_until(1.0)
    plc.alive = False  # last beat at 0 s: lost from 3.0 s
    plc.run_until(3.2)
    start = plc.applied_um()
    trace = plc.run_until(13.2)
    assert plc.applied_um() == pytest.approx(start - 10.0, abs=0.15)  # 1 um/s for 10 s
    applied = [float(out[plc.n.apply.lower()]) / plc.n.per_um for _, out in trace]
    fastest = max(a - b for a, b in itertools.pairwise(applied))
    assert fastest <= 0.1 + (0.1 if plc.n.per_um > 1 else 1e-6)  # one step: 1 um/s x 0.1 s
    plc.run_until(40.0)
    assert abs(plc.applied_um()) < 0.2  # then first order to zero


@pytest.mark.parametrize("page", sorted(PAGES))
def test_after_a_plc_start_the_value_is_held_and_a_kept_counter_is_no_sign_of_life(page):
    plc = Plc(page, offset_um=19.0, alive=False)  # the variables kept theirs; thermocomp is gone
    assert plc.applied_um() == pytest.approx(19.0, abs=0.05), "no step to zero at the start"
    trace = plc.run_until(5.0)
    t_lost = next(t for t, out in trace if not out[plc.n.ok.lower()])
    assert 3.0 <= t_lost <= 3.0 + 2 * SCAN_MS / 1000
