"""The ``thermocomp`` command.

Subcommands are declared here (arguments only); their handlers are named by
``"module:function"`` and imported on use, so ``thermocomp --help`` stays fast
and a command loads only the layers it needs.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import math
import signal
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn, overload

Handler = Callable[[argparse.Namespace], int]

ERROR_CHARS = 300
"""An error prints as one line of at most this many characters after ``thermocomp: error: ``."""

LOG_CHARS = 1000
"""A logged message is clipped to this many characters (warnings run longer than errors)."""


EXTRA_OF = {
    "scipy": "calibration",
    "statsmodels": "calibration",
    "pandas": "calibration",
    "matplotlib": "calibration",
    "rich": "calibration",
    "snap7": "plc",
    "pyads": "ads",
}
"""A library an optional extra brings -> that extra (pyproject.toml); the slim install has none."""


def fail(message: str) -> None:
    """Print ``thermocomp: error: <message>`` on stderr, clipped to one line: an error may
    echo a bad value, and one was found 50 MB long."""
    from compensator.errors import clip

    print(f"thermocomp: error: {clip(message, ERROR_CHARS)}", file=sys.stderr)


class _Parser(argparse.ArgumentParser):
    """argparse echoes a bad argument whole ("invalid float value: '...'"): clip it too.
    Subcommand parsers are made of this class as well."""

    def error(self, message: str) -> NoReturn:
        from compensator.errors import clip

        self.print_usage(sys.stderr)
        self.exit(2, f"{self.prog}: error: {clip(message, ERROR_CHARS)}\n")


class _IntermixedParser(_Parser):
    """Positionals may follow options (``model check --json FILE``): plain argparse takes a run
    of optional positionals once and calls a later one unrecognized."""

    _inside = False

    # one signature for argparse's overloads (a namespace passed in is the one returned)
    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        if self._inside:  # parse_known_intermixed_args calls back here
            return super().parse_known_args(args, namespace)
        self._inside = True
        try:
            return self.parse_known_intermixed_args(args, namespace)
        finally:
            self._inside = False


class _ModelParser(_Parser):
    """``model`` also takes its earlier forms, for one release: ``model FILE`` (now ``model show
    FILE``), ``model --schema`` (now ``model schema``), and options before the action
    (``model --json check FILE``), which a subcommand's own parser would not take."""

    # one signature for argparse's overloads (a namespace passed in is the one returned)
    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        return super().parse_known_args(self._current_form(list(args or ())), namespace)

    def _current_form(self, words: list[str]) -> list[str]:
        actions = next(a for a in self._actions if isinstance(a, argparse._SubParsersAction))
        valued = {
            o
            for sub in actions.choices.values()
            for a in sub._actions
            if a.nargs != 0
            for o in a.option_strings
        }
        if "--schema" in words:
            deprecated("thermocomp model --schema", use="thermocomp model schema")
            return ["schema", *(w for w in words if w != "--schema")]
        i = 0
        while i < len(words) and words[i].startswith("-"):
            i += 2 if words[i] in valued else 1
        if i >= len(words) or (i == 0 and words[0] in actions.choices):
            return words
        if words[i] in actions.choices:
            return [words[i], *words[:i], *words[i + 1 :]]
        deprecated("thermocomp model FILE", use="thermocomp model show FILE")
        return ["show", *words]


def deprecated(old: str, *, use: str | None = None, note: str | None = None) -> None:
    """The one line on stderr an old spelling prints; it still works until the next release."""
    instead = f", use '{use}'" if use else f" and {note}" if note else ""
    print(
        f"thermocomp: '{old}' is deprecated{instead}; it will be removed in the next release",
        file=sys.stderr,
    )


class _OldSpelling(argparse.Action):
    """An option's former spelling (``_old``): hidden from the help, it prints the deprecation
    line and then does what the current spelling does."""

    def __init__(
        self, option_strings: list[str], dest: str, current: argparse.Action, **_: object
    ) -> None:
        super().__init__(
            option_strings,
            current.dest,
            nargs=current.nargs,
            const=current.const,
            default=argparse.SUPPRESS,
            choices=current.choices,
            metavar=current.metavar,
            help=argparse.SUPPRESS,
        )
        # set as argparse's __init__ would: the type may be a registered type's name
        self.type = current.type
        self.current = current

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: str | Sequence[Any] | None,
        option_string: str | None = None,
    ) -> None:
        now = self.current.option_strings[-1]
        deprecated(str(option_string), use=now)
        self.current(parser, namespace, values, now)


class _NoLongerNeeded(argparse.Action):
    """A former option that does nothing now: hidden, accepted (with its value, if it took one)
    with the deprecation line and why, so that old scripts keep running for one release."""

    def __init__(
        self,
        option_strings: list[str],
        dest: str,
        why: str,
        nargs: int | str | None = 0,
        choices: Sequence[str] | None = None,
        **_: object,
    ) -> None:
        super().__init__(
            option_strings,
            argparse.SUPPRESS,
            nargs=nargs,
            choices=choices,
            metavar="VALUE",
            default=argparse.SUPPRESS,
            help=argparse.SUPPRESS,
        )
        self.why = why

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: str | Sequence[Any] | None,
        option_string: str | None = None,
    ) -> None:
        deprecated(str(option_string), note=f"does nothing ({self.why})")


def _old(
    p: argparse.ArgumentParser | argparse._ArgumentGroup, old: str, current: argparse.Action
) -> None:
    """Keep ``old``, the former spelling of ``current``, working for one release."""
    p.add_argument(old, action=_OldSpelling, current=current)


class _Choices(Sequence[str]):
    """A fixed set of values, taken from the code that defines it ("module:NAME", a tuple or
    the keys of a dict) when first needed: building the parser imports none of them, so
    ``thermocomp --help`` stays fast. An argument using one names its ``metavar`` (argparse
    would otherwise list the values while building the parser)."""

    def __init__(self, *specs: str, extra: tuple[str, ...] = ()) -> None:
        self._specs, self._extra = specs, extra
        self._values: tuple[str, ...] | None = None

    def _all(self) -> tuple[str, ...]:
        if self._values is None:
            found: list[str] = []
            for spec in self._specs:
                module, _, name = spec.partition(":")
                found += [
                    v for v in getattr(importlib.import_module(module), name) if v not in found
                ]
            self._values = (*found, *self._extra)
        return self._values

    @overload
    def __getitem__(self, i: int) -> str: ...
    @overload
    def __getitem__(self, i: slice) -> Sequence[str]: ...
    def __getitem__(self, i: int | slice) -> str | Sequence[str]:
        return self._all()[i]

    def __len__(self) -> int:
        return len(self._all())

    def __contains__(self, value: object) -> bool:
        return value in self._all()


DIALECTS = _Choices("calibration.nc_programs:DIALECTS")
"""The NC dialects the program writers support (profile, probe-program, wizard)."""
PRESETS = _Choices("machine_sim.plant:PRESETS")
PROFILES = _Choices("cnc_adapters.control_profiles:PROFILES")
SCENARIOS = _Choices("calibration.cooling_studies:SCENARIOS")
GAINS = ("paper", "simc")
"""The PID gain sets of active cooling: paper 000's, or SIMC rules on the identified step."""


def _time_scale(text: str) -> float:
    """``--time-scale``: a finite number > 0 (a real machine runs at 1)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: give a number > 0 (1 on a real machine)")
    return value


class _OneLineFormatter(logging.Formatter):
    """A logged message (a warning may quote a bad value too) as one bounded line; a
    traceback, if any, still follows it."""

    def formatMessage(self, record: logging.LogRecord) -> str:
        from compensator.errors import clip

        record.message = clip(record.message, LOG_CHARS)
        return super().formatMessage(record)


SPINDLE_HELP = "the spindle: a [[spindle]] of the runtime configuration, by its name"
MODEL_SPINDLE_ID_HELP = (
    "the spindle id written into the model: a runtime configuration whose spindle sets "
    "spindle_id loads only a model that carries the same"
)
DIALECT_HELP = "NC dialect: %(choices)s"
PRESET_HELP = "plant preset: %(choices)s"


def _add_replay(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="free-run a model over a logged speed profile, and the offset "
        "the runtime's shaping would write",
    )
    p.add_argument("log", help="run log (CSV: time_s,speed_rpm[,elongation_um,cutting,...])")
    p.add_argument("--model", help="model file (JSON); default: the spindle's in --config")
    p.add_argument(
        "--config",
        metavar="RUNTIME.toml",
        help="take the shaping (limits, transient policy, cutting signal) from this runtime "
        "configuration (default: the runtime's own defaults)",
    )
    p.add_argument("--spindle", metavar="NAME", help=f"with --config: {SPINDLE_HELP}")
    p.add_argument(
        "--no-compare",
        action="store_true",
        help="skip the side-by-side of the transient policies (two more passes of "
        "the shaper with a dual-slew configuration: about 1.5 s per million rows)",
    )
    p.add_argument("--output", help="write predicted elongation and offset per row (CSV)")
    p.add_argument("--plot", help="write a PNG plot")
    p.add_argument(
        "--initial-um", type=float, help="initial elongation (default: first measured, else 0)"
    )
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.add_argument(
        "--probe-every",
        type=float,
        metavar="SECONDS",
        help="simulate the closed loop: a tool-setter measurement every SECONDS, drawn "
        "from the log's elongation_um plus noise, fused by the observer",
    )
    p.add_argument(
        "--measurements",
        metavar="FILE",
        help="fuse real measurements instead: CSV time_s,elongation_um[,sigma_um] on the "
        "log's clock (the runtime's measurement journal is one)",
    )
    p.add_argument(
        "--probe-noise-um",
        type=float,
        default=0.5,
        help="noise (sigma) of those measurements; with --measurements, the sigma of rows "
        "that state none",
    )
    p.add_argument("--probe-seed", type=int, default=0, help="random seed of that noise")
    p.add_argument(
        "--applied",
        action=_NoLongerNeeded,
        why="the offset the runtime would apply is in every report",
    )
    p.set_defaults(handler="thermocomp.commands.replay:replay")


def _add_fit(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "fit",
        help="fit and validate a model from calibration runs",
        description="Baseline, physical form and ridge filter banks, scored by "
        "leave-one-cycle-out free run; the best one is written.",
    )
    p.add_argument("runs", nargs="+", help="calibration run logs (CSV)")
    p.add_argument("--output", required=True, help="model file to write (JSON)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    _old(
        p,
        "--spindle-id",
        p.add_argument(
            "--model-spindle-id", dest="spindle_id", metavar="ID", help=MODEL_SPINDLE_ID_HELP
        ),
    )
    p.add_argument("--machine-id", default=None, help="machine id stored in the model")
    p.add_argument(
        "--method",
        action=_NoLongerNeeded,
        nargs=None,
        choices=("cycles",),
        why="cycles, the only method, is what fit does",
    )
    p.add_argument("--plot", help="write a PNG plot of the fit")
    p.add_argument(
        "--inputs",
        help="extra run-log columns to use as inputs, comma separated, or "
        "'all' (temperatures, spindle load, ambient); kept only if they help in "
        "cross-validation",
    )
    p.add_argument(
        "--no-nested",
        action="store_true",
        help="skip the nested cross-validation (faster; the choice then uses plain CV)",
    )
    p.add_argument(
        "--no-physical",
        action="store_true",
        help="leave the output-error physical form out of the candidates (faster)",
    )
    p.add_argument(
        "--probe-every",
        type=float,
        metavar="SECONDS",
        help="the spindle will run in closed loop with a probe every SECONDS: choose "
        "the model by its closed-loop error on held-out cycles instead of its free run",
    )
    p.add_argument(
        "--probe-target-um",
        type=float,
        default=2.0,
        help="closed loop: the RMS a recommended probe interval must meet in "
        "cross-validation [um] (the fit report tabulates interval -> RMS and max)",
    )
    p.set_defaults(handler="calibration.commands:fit")


def _add_simulate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="write a run log from the virtual spindle plant")
    p.add_argument(
        "--preset", default="motorized-27k", choices=PRESETS, metavar="PRESET", help=PRESET_HELP
    )
    p.add_argument(
        "--program",
        default="paper-calibration",
        metavar="PROGRAM",
        choices=_Choices(
            "compensator.speed_programs:PROGRAMS", "calibration.cooling_studies:SCENARIOS"
        ),
        help="speed program: %(choices)s (with --cooling one of paper 000's scenarios, wc1..wc4)",
    )
    p.add_argument("--dt", type=float, default=60.0, help="sample period [s]")
    p.add_argument("--seed", type=int, default=0, help="random seed (noise, ambient, program)")
    p.add_argument(
        "--accel-rpm-per-s",
        type=float,
        default=None,
        help="how fast the drive changes speed (default: the preset's, 5000 for motorized-27k)",
    )
    p.add_argument(
        "--output", required=True, help="run log to write (CSV, with a 0/1 cutting column)"
    )
    p.add_argument(
        "--cooling",
        choices=("constant", "pid"),
        default=None,
        help="active cooling (paper 000): run --program (wc1..wc4, default wc1) with the chiller "
        "constant or driven by the PID on a model's estimate; prints STE, equilibrium time, TEVR",
    )
    p.add_argument(
        "--offset", action="store_true", help="with --cooling: write the offset too (mode both)"
    )
    p.add_argument(
        "--rite",
        type=float,
        default=None,
        help="with --cooling pid: RITE [um] (default the scenario's)",
    )
    p.add_argument(
        "--model",
        default=None,
        help="with --cooling: the model file (default: fit one on an excitation run of the preset)",
    )
    p.add_argument(
        "--gains", default="paper", choices=GAINS, help="with --cooling pid: the gain set"
    )
    p.set_defaults(handler="thermocomp.commands.sim:simulate")


def _add_cooling(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "cooling", help="active cooling: compare on the virtual plant, tune, suggest RITE"
    )
    cs = p.add_subparsers(dest="cooling_command", metavar="ACTION", required=True)
    c = cs.add_parser(
        "compare", help="paper 000's scenarios: constant cooling, PID, PID plus the offset"
    )
    c.add_argument(
        "--preset", default="mechanical-cooled", choices=PRESETS, metavar="PRESET", help=PRESET_HELP
    )
    c.add_argument(
        "--scenario",
        action="append",
        choices=SCENARIOS,
        metavar="NAME",
        help="paper 000's scenario: %(choices)s (repeat; default all)",
    )
    c.add_argument("--gains", action="append", choices=GAINS, help="gain sets (default both)")
    c.add_argument("--dt", type=float, default=1.0, help="control period [s] (the paper: 1 s)")
    c.add_argument("--seed", type=int, default=0, help="random seed (noise, ambient)")
    c.add_argument("--plot", default=None, help="PNG to write")
    c.add_argument("--json", action="store_true", help="print the figures as JSON")
    c.set_defaults(handler="calibration.cooling_commands:compare")
    t = cs.add_parser(
        "tune", help="identify the chiller -> elongation step response and derive SIMC gains"
    )
    t.add_argument(
        "--preset", default="mechanical-cooled", choices=PRESETS, metavar="PRESET", help=PRESET_HELP
    )
    t.add_argument(
        "--log",
        default=None,
        help="a logged step run with chiller_setpoint_c and elongation_um (default: the plant's)",
    )
    t.add_argument("--write-step", default=None, help="write the plant's step run to this run log")
    t.add_argument("--tau-c-s", type=float, default=None, help="SIMC closed-loop time constant [s]")
    t.add_argument("--plot", default=None, help="PNG: the fit and the closed-loop step responses")
    t.set_defaults(handler="calibration.cooling_commands:tune")
    r = cs.add_parser(
        "rite", help="suggest RITE: the model's steady elongation at a journal's speed mix"
    )
    r.add_argument("--model", required=True, help="model file (JSON)")
    r.add_argument("--input", action="append", help="NAME=VALUE for a model with inputs")
    r.add_argument("journal", nargs="+", help="journal or run-log files (time_s, speed_rpm)")
    r.set_defaults(handler="calibration.cooling_commands:rite")


def _add_virtual_cnc(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("virtual-cnc", help="serve the virtual machine tool over OPC UA")
    p.add_argument(
        "--preset", default="motorized-27k", choices=PRESETS, metavar="PRESET", help=PRESET_HELP
    )
    p.add_argument(
        "--program",
        default="job-shop-day",
        help="speed program: a built-in name, or an NC program file (any of the four dialects)",
    )
    p.add_argument(
        "--wait-start",
        action="store_true",
        help="load the program and wait for a client to write true to CycleStart",
    )
    p.add_argument(
        "--start-delay",
        type=float,
        default=None,
        help="with --wait-start: press cycle start by itself after this many wall seconds",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument(
        "--time-scale", type=_time_scale, default=60.0, help="simulated seconds per wall second"
    )
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default loopback)")
    p.add_argument("--port", type=int, default=4840, help="TCP port")
    p.add_argument("--duration", type=float, default=None, help="stop after this many wall seconds")
    p.add_argument(
        "--tool-setter",
        choices=["rest", "speed"],
        default="rest",
        help="the machine's tool setter: a contact one, the spindle stopped for each cycle (default), "
        "or a laser measuring the turning tool at the program's speed",
    )
    p.add_argument(
        "--tool-setter-touches",
        type=int,
        default=1,
        choices=range(1, 11),
        metavar="N",
        help="touches each tool-setter cycle averages, 1 to 10 (default 1; as the probe program's "
        "--touches)",
    )
    p.add_argument(
        "--history",
        metavar="CSV",
        help="on stop, write the machine's record (true growth, the offset held, the tool tip's "
        "error) as a run log and print the error while cutting, with and without the offset",
    )
    p.add_argument(
        "--accel-rpm-per-s",
        type=float,
        default=None,
        help="how fast the drive changes speed (default: the preset's, 5000 for motorized-27k)",
    )
    p.add_argument(
        "--approach-s",
        type=float,
        default=None,
        help="seconds from at-speed to the first cut (default: the preset's, 3)",
    )
    p.add_argument(
        "--watch-reaction",
        choices=["none", "alarm", "feed-hold", "fade"],
        default="none",
        help="what the control does once thermocomp's sign of life is missing (LifeCounter "
        "still for --watch-timeout-s, or CompensationValid false): none (keep the offset; the "
        "state is shown), alarm (refuse the next cycle start until a reset), feed-hold (pause "
        "the program, the spindle turning), fade (the offset to zero, first-order)",
    )
    p.add_argument(
        "--watch-timeout-s",
        type=float,
        default=None,
        help="simulated seconds the life counter may stand still (default 3 s of wall time: "
        "3 x --time-scale, at least 3)",
    )
    p.add_argument(
        "--fade-tau-s",
        type=float,
        default=1200.0,
        help="with --watch-reaction fade: its time constant, simulated seconds (default 1200, "
        "the spindle's cooling)",
    )
    p.add_argument(
        "--fade-rate-um-per-s",
        type=float,
        default=1.0,
        help="with --watch-reaction fade: its fastest rate (default 1 um/s)",
    )
    p.set_defaults(handler="thermocomp.commands.sim:virtual_cnc")


def _add_hal_plant(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "hal-plant", help="the virtual spindle as a LinuxCNC HAL component (sim configs)"
    )
    p.add_argument("--name", default="thermocomp-plant", help="HAL component name")
    p.add_argument(
        "--preset", default="motorized-27k", choices=PRESETS, metavar="PRESET", help=PRESET_HELP
    )
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument(
        "--time-scale", type=_time_scale, default=1.0, help="simulated seconds per wall second"
    )
    p.add_argument("--step-s", type=float, default=0.5, help="plant step [simulated s]")
    p.set_defaults(handler="thermocomp.commands.halplant:hal_plant")


def _add_run(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the compensation service")
    p.add_argument(
        "--config", required=True, metavar="RUNTIME.toml", help="the runtime configuration"
    )
    p.add_argument(
        "--check",
        action="store_true",
        help="validate, connect, read one speed, and exit without writing",
    )
    p.set_defaults(handler="thermocomp.runtime.service:main")


def _add_measure(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "measure",
        help="send a tool-setter or probe measurement to the running service",
        description="The service fuses it at the spindle's next cycle and answers: "
        "accepted (exit 0), rejected by the innovation gate or taken only in part by the "
        "observer's bounds (exit 1); an error exits 2.",
    )
    p.add_argument(
        "--um",
        type=float,
        required=True,
        help="the measured elongation [um]: positive when the tool grew toward the workpiece",
    )
    p.add_argument(
        "--sigma-um",
        type=float,
        help="its standard deviation [um] (default: the spindle's [spindle.observer] sigma_um)",
    )
    p.add_argument(
        "--spindle", metavar="NAME", help=f"{SPINDLE_HELP} (default: the only one with an observer)"
    )
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--state-dir", help="the service's state directory (default /var/lib/thermocomp)"
    )
    g.add_argument(
        "--config", metavar="RUNTIME.toml", help="or the runtime configuration that names it"
    )
    p.add_argument("--timeout-s", type=float, help="wait this long for the answer (default 60)")
    p.add_argument("--json", action="store_true", help="print the service's answer as JSON")
    p.set_defaults(handler="thermocomp.runtime.service:measure")


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the whole product on the embedded virtual machine tool")
    p.add_argument("--output-dir", default="demo-output", help="where to write logs and plots")
    p.add_argument(
        "--hours",
        type=float,
        default=5.0,
        help="length of the job-shop days the service compensates, open and closed loop "
        "(1 to 24, default 5); the figures in docs/getting-started.md are for 5",
    )
    p.add_argument(
        "--profile",
        default="virtual",
        choices=PROFILES,
        metavar="NAME",
        help="the control the virtual CNC acts as, one of %(choices)s: its unit, resolution, "
        "limits and own rate limit (sinumerik: SD43900 with the SeaWrite right); default its own "
        "um node",
    )
    p.set_defaults(handler="thermocomp.demo:main")


def _add_controls(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "controls", help="controller profiles: what each control family does with the offset"
    )
    p.add_argument(
        "name",
        nargs="?",
        choices=PROFILES,
        metavar="NAME",
        help="a profile, one of %(choices)s: its routes, units, limits and the NC/PLC snippet",
    )
    p.add_argument("--json", action="store_true", help="print as JSON")
    p.set_defaults(handler="thermocomp.commands.controls:main")


def _add_profile(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "profile", help="write the NC program of the calibration (or validation) profile"
    )
    p.add_argument("--max-rpm", type=float, required=True, help="the spindle's maximum speed [rpm]")
    p.add_argument(
        "--dialect", required=True, choices=DIALECTS, metavar="DIALECT", help=DIALECT_HELP
    )
    p.add_argument("--output", required=True, help="NC program to write")
    p.add_argument(
        "--validation",
        action="store_true",
        help="the validation profile (random, unlike calibration)",
    )
    p.add_argument("--seed", type=int, default=1, help="seed of the validation profile")
    p.add_argument(
        "--step-min", type=float, default=20.0, help="minutes per staircase step (paper: 20)"
    )
    p.add_argument(
        "--cooldown-min", type=float, default=60.0, help="cool-down at 0 rpm at the end [min]"
    )
    p.add_argument("--name", default="THERMOCOMP", help="program name")
    p.add_argument(
        "--model", help="a former model of this spindle: sets the rest time before a cold start"
    )
    p.set_defaults(handler="calibration.wizard:profile_cmd")


def _add_probe_program(sub: argparse._SubParsersAction) -> None:
    # values stay text: the handler checks them per dialect, each refusal one line (docs/PROBING.md)
    p = sub.add_parser(
        "probe-program",
        help="write an NC tool-setter cycle that hands the tool's growth "
        "since the cold reference to the service (closed loop)",
        description="Measures the tool on the tool setter, writes (length now - cold "
        "reference) in um to --value-var, then adds 1 to --counter-var. See docs/PROBING.md.",
    )
    p.add_argument(
        "--dialect", required=True, choices=DIALECTS, metavar="DIALECT", help=DIALECT_HELP
    )
    p.add_argument("--output", help="NC program to write (default: standard output)")
    p.add_argument(
        "--reference",
        action="store_true",
        help="write the program that takes the cold reference instead (run it cold)",
    )
    p.add_argument(
        "--tool", default="1", metavar="N", help="tool measured (default 1; best a gauge tool)"
    )
    p.add_argument(
        "--value-var", metavar="VAR", help="the growth [um] (default #521, R21, QR21, #3021)"
    )
    p.add_argument(
        "--counter-var", metavar="VAR", help="the counter (default #522, R22, QR22, #3022)"
    )
    p.add_argument(
        "--reference-var",
        metavar="VAR",
        help="the cold reference [mm], kept through power cycles (default #520, R20, QR20, #3020)",
    )
    _old(
        p,
        "--spindle",
        p.add_argument(
            "--probe-spindle",
            dest="spindle",
            default="stop",
            choices=_Choices("calibration.probeprog:SPINDLE_MODES"),
            metavar="MODE",
            help="the spindle while the setter measures: stop, a contact setter (default); low, a laser "
            "setter, at --low-rpm; keep, a laser setter measuring the gauge tool in the spindle at the "
            "program's speed (sees the growth that exists only while it turns)",
        ),
    )
    p.add_argument("--low-rpm", metavar="RPM", help="spindle speed with --probe-spindle low")
    p.add_argument(
        "--settle-s", default="2", metavar="S", help="dwell before probing (spindle run-down) [s]"
    )
    p.add_argument(
        "--setter-x-mm", metavar="MM", help="setter centre, machine X (default: probe in place)"
    )
    p.add_argument("--setter-y-mm", metavar="MM", help="setter centre, machine Y")
    p.add_argument(
        "--approach-z-mm",
        metavar="MM",
        help="machine Z to rise to before moving across and after probing; heidenhain: "
        "the clearance height Q260",
    )
    p.add_argument(
        "--travel-mm", metavar="MM", help="longest search down from the approach (default 10)"
    )
    p.add_argument(
        "--backoff-mm",
        metavar="MM",
        help="back-off before each slow touch (default 1; 0.2 for a laser, --probe-spindle low or keep)",
    )
    p.add_argument("--fast-feed-mm-min", metavar="F", help="search feed (default 200)")
    p.add_argument("--slow-feed-mm-min", metavar="F", help="measuring feed (default 20)")
    p.add_argument(
        "--max-um", default="300", metavar="UM", help="a larger growth: alarm, nothing written"
    )
    p.add_argument(
        "--touches",
        default="1",
        metavar="N",
        help="slow touches averaged per measurement, 1 to 10 (default 1; not heidenhain)",
    )
    p.add_argument(
        "--spread-um",
        default="5",
        metavar="UM",
        help="with --touches: a touch farther than this from the first is an alarm, nothing written",
    )
    p.add_argument(
        "--probe-input", metavar="N", help="sinumerik: the setter's input, 1 or 2 (default 1)"
    )
    p.add_argument(
        "--value-aout", metavar="N", help="linuxcnc: M68 analog output, value (default 0)"
    )
    p.add_argument(
        "--counter-aout", metavar="N", help="linuxcnc: M68 analog output, counter (default 1)"
    )
    p.add_argument("--name", help="program name (default TCPROBE, or TCREF with --reference)")
    p.set_defaults(handler="calibration.probeprog:probe_program_cmd")


def _add_wizard(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "wizard",
        help="guided calibration of one spindle: program, record, fit, save",
        description="Every question has a flag; --yes runs unattended.",
    )
    p.add_argument(
        "--workdir", default="calibrations", help="sessions live in WORKDIR/<machine>/<spindle>/"
    )
    p.add_argument(
        "--yes", action="store_true", help="unattended: never ask; missing answers are errors"
    )
    p.add_argument(
        "--new", action="store_true", help="start a new session (the old one is kept aside)"
    )
    p.add_argument("--resume", action="store_true", help="resume the session without asking")
    g = p.add_argument_group("1 identify")
    g.add_argument(
        "--machine-id", metavar="ID", help="the machine, in the model and the session's path"
    )
    _old(
        g,
        "--spindle-id",
        g.add_argument(
            "--model-spindle-id", dest="spindle_id", metavar="ID", help=MODEL_SPINDLE_ID_HELP
        ),
    )
    g.add_argument("--max-rpm", type=float, help="the spindle's maximum speed [rpm]")
    g.add_argument(
        "--source",
        choices=["sensor", "tool-setter", "import"],
        help="live eddy-current sensor; the machine's tool setter alone (the program stops for it "
        "every few minutes, the controller link reads it); or import DAQ CSV logs",
    )
    g.add_argument("--controller", help="controller link URL (as in the runtime configuration)")
    g.add_argument(
        "--sensor",
        help="displacement sensor URL: serial:///dev/ttyUSB1?scale=-1&range_um=-500,500, "
        "serial:///dev/ttyUSB1?protocol=modbus&register=0&scale=0.1, opc.tcp://host:port/?node=...",
    )
    g.add_argument("--rate-s", type=float, help="sample period [s] (default 1)")
    g.add_argument("--no-connection-test", action="store_true", help="skip the connection test")
    g = p.add_argument_group("2 program")
    g.add_argument("--dialect", choices=DIALECTS, metavar="DIALECT", help=DIALECT_HELP)
    g.add_argument("--step-min", type=float, help="minutes per staircase step (paper: 20)")
    g.add_argument("--cooldown-min", type=float, help="cool-down at 0 rpm [min] (default 60)")
    g.add_argument(
        "--validation",
        dest="validation",
        action="store_true",
        default=None,
        help="also record a different validation profile",
    )
    g.add_argument(
        "--no-validation",
        dest="validation",
        action="store_false",
        help="calibration run only (the fit is judged by cross-validation)",
    )
    g.add_argument(
        "--validation-seed", type=int, default=1, help="seed of the random validation profile"
    )
    g.add_argument(
        "--probe-every-min",
        type=float,
        help="--source tool-setter: minutes between tool-setter stops (default: planned from the "
        "step and the fastest time constant)",
    )
    g.add_argument(
        "--probe-spindle",
        choices=["stop", "keep"],
        help="--source tool-setter: stop, the cycle measures at rest (a contact setter, default); "
        "keep, a laser setter measures the turning gauge tool at the program's speed, which also "
        "sees the growth that exists only while the spindle turns",
    )
    g.add_argument(
        "--probe-timeout-s",
        type=float,
        help="--source tool-setter: stop the recording when a stop's measurement has not come in "
        "this many wall seconds (default 900)",
    )
    g.add_argument(
        "--probe-dwell-s",
        type=float,
        help="--source tool-setter: seconds one tool-setter cycle keeps the spindle stopped, moves "
        "and every touch included (default: the cycle's measuring time + 10 s)",
    )
    g.add_argument(
        "--probe-touches",
        type=float,
        help="--source tool-setter: slow touches the cycle averages per stop, 1 to 10 (default: a laser "
        "at speed as many as keep the stops within a fifth of the program, at rest 1)",
    )
    g.add_argument(
        "--programs-only", action="store_true", help="stop after writing the NC programs"
    )
    g = p.add_argument_group("3 record")
    g.add_argument("--frozen-s", type=float, help="same reading this long: frozen (default 900)")
    g.add_argument(
        "--frozen-after-step-s",
        type=float,
        help="same reading this long across a speed step: frozen (default 120)",
    )
    g.add_argument("--abort-frozen-s", type=float, help="stop after frozen this long (default 300)")
    g.add_argument(
        "--abort-saturated-s", type=float, help="stop after saturated this long (default 30)"
    )
    g.add_argument(
        "--sensor-grace-s",
        type=float,
        help="stop after the sensor is silent this many wall seconds (default 30)",
    )
    g.add_argument(
        "--start-timeout-s",
        type=float,
        help="stop if the spindle has not started within this many wall seconds (default 3600)",
    )
    g.add_argument(
        "--start-now",
        action="store_true",
        help="start the program clock when the recording starts, not when the spindle first "
        "turns (a program that opens at rest); interactively: press Enter",
    )
    g.add_argument("--import-calibration", help="DAQ CSV of the calibration run (--source import)")
    g.add_argument("--import-validation", help="DAQ CSV of the validation run (--source import)")
    g.add_argument("--import-time-column", default="time_s", help="seconds or ISO date-times")
    g.add_argument(
        "--import-displacement-column",
        default="displacement_um",
        help="displacement column in the DAQ file",
    )
    g.add_argument("--import-speed-column", help="speed column in the DAQ file, if it has one")
    g.add_argument(
        "--import-speed-log", help="else a controller run log (time_s,speed_rpm) on the same clock"
    )
    g.add_argument(
        "--import-scale", type=float, default=1.0, help="um per DAQ unit (negative for a gap probe)"
    )
    g.add_argument(
        "--import-offset-um", type=float, default=0.0, help="added after --import-scale [um]"
    )
    g = p.add_argument_group("5 save")
    g.add_argument(
        "--report-format",
        choices=["html", "md"],
        default="html",
        help="the calibration report's format",
    )
    p.add_argument(
        "--time-scale",
        type=_time_scale,
        default=1.0,
        help="the virtual machine tool only, which runs faster than the wall clock: its simulated "
        "seconds per wall second, as given to `thermocomp virtual-cnc --time-scale` (durations are then "
        "shown in both, and the runtime configuration written runs at it). Keep 1, the default, on a "
        "real machine: any other value makes the recording's time and the service's wrong",
    )
    p.set_defaults(handler="calibration.wizard:main")


def _add_model(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "model",
        help="show or check a model file, print a format's schema; a spindle's model "
        "history and rollback",
    )
    p.__class__ = _ModelParser  # add_parser makes every subparser of one class
    # a positional that may follow the options (rollback --config X DIGEST) needs the intermixed parse
    ms = p.add_subparsers(
        dest="model_command", metavar="ACTION", required=True, parser_class=_IntermixedParser
    )
    s = ms.add_parser("show", help="describe a model file")
    s.add_argument("file", metavar="FILE", help="model file (JSON)")
    s.add_argument("--json", action="store_true", help="print the whole model as JSON")
    s.set_defaults(handler="thermocomp.commands.model:show")
    c = ms.add_parser(
        "check",
        help="verify a model file as the runtime would load it",
        description="Checksum, sanity, plausibility: exit 0 if the runtime would take the file, "
        "else 2 with a one-line reason.",
    )
    c.add_argument("file", metavar="FILE", help="model file (JSON)")
    c.add_argument(
        "--json", action="store_true", help="print {file, ok, reason, format, form, ...} as JSON"
    )
    c.set_defaults(handler="thermocomp.commands.model:check_cmd")
    f = ms.add_parser("schema", help="print a model format's JSON schema")
    f.add_argument(
        "--format",
        choices=_Choices("compensator.io:MODEL_TYPES", extra=("all",)),
        metavar="FORMAT",
        help="the format, one of %(choices)s (all: every format keyed by name; default: the "
        "speed-only model's)",
    )
    f.set_defaults(handler="thermocomp.commands.model:schema")
    h = ms.add_parser(
        "history",
        help="every model the service ran, every refit candidate and why it was "
        "promoted or rejected",
    )
    r = ms.add_parser(
        "rollback", help="put a kept model back; the service reloads it, its state carried over"
    )
    r.add_argument(
        "digest",
        nargs="?",
        metavar="DIGEST",
        help="the kept model (default: the one in use before the live one)",
    )
    for q in (h, r):
        q.add_argument(
            "--config", required=True, metavar="RUNTIME.toml", help="the runtime configuration"
        )
        q.add_argument("--spindle", metavar="NAME", help=f"{SPINDLE_HELP} (needed with several)")
    h.add_argument("--json", action="store_true", help="print the history as JSON")
    r.add_argument("--reason", help="why, for the history")
    h.set_defaults(handler="thermocomp.commands.learning:history_cmd")
    r.set_defaults(handler="thermocomp.commands.learning:rollback_cmd")


def _add_refit(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "refit",
        help="refit a spindle's model from its own tool-setter measurements; "
        "promote the candidate only if it beats the live model on the newest ones",
        description="Exports the journal since the live model went into use, fits a "
        "candidate on all but the newest measurements and judges both models on those "
        "(open loop and with the observer). A candidate the rule ([spindle.learning]) "
        "accepts replaces the configured model file and the service reloads it; every "
        "candidate is kept in the model history with its figures and the reason.",
    )
    p.add_argument(
        "--config", required=True, metavar="RUNTIME.toml", help="the runtime configuration"
    )
    p.add_argument("--spindle", metavar="NAME", help=f"{SPINDLE_HELP} (needed with several)")
    p.add_argument(
        "--from",
        dest="from_",
        metavar="WHEN",
        help="refit on the journal from this ISO date or date-time (UTC unless it names a zone; "
        "default: since the live model went into use)",
    )
    p.add_argument(
        "--dry-run",
        action="store_true",
        help="judge, keep the candidate in the history, change nothing",
    )
    p.add_argument("--json", action="store_true", help="print the decision and figures as JSON")
    p.set_defaults(handler="thermocomp.commands.learning:refit_cmd")


def _add_status(sub: argparse._SubParsersAction) -> None:
    from thermocomp.status_codes import DEFAULT_URL, EXIT_CODES  # constants only: no layer below

    p = sub.add_parser(
        "status",
        help="what a running service is doing: its status endpoint as a table",
        description="Reads the service's /status (docs/service.md, Live status). "
        "The token, where the service asks for one: THERMOCOMP_STATUS_TOKEN or --token-file.",
    )
    g = p.add_mutually_exclusive_group()
    g.add_argument("--url", help=f"the status endpoint (default {DEFAULT_URL})")
    g.add_argument(
        "--config", metavar="RUNTIME.toml", help="or the runtime configuration that names it"
    )
    p.add_argument("--token-file", help="a file holding the token")
    p.add_argument("--json", action="store_true", help="print the endpoint's JSON as it came")
    p.add_argument("--timeout-s", type=float, default=10.0, help="wait this long for the answer")
    p.add_argument(
        "--exit-code",
        action="store_true",
        help="exit status by what the service says, the worst that applies: "
        + "; ".join(f"{code} {what}" for code, what in sorted(EXIT_CODES.items())),
    )
    p.set_defaults(handler="thermocomp.commands.status:main")


def _add_journal(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("journal", help="the runtime's journal: export a time range as one run log")
    js = p.add_subparsers(dest="journal_command", metavar="ACTION", required=True)
    e = js.add_parser(
        "export",
        help="one run log (cycles, inputs, probe measurements, chiller commands) "
        "that fit and replay read directly",
    )
    g = e.add_mutually_exclusive_group()
    g.add_argument(
        "--config", metavar="RUNTIME.toml", help="the runtime configuration (its journal_dir)"
    )
    g.add_argument("--journal-dir", help="or the journal directory itself")
    e.add_argument(
        "--spindle", metavar="NAME", help=f"{SPINDLE_HELP} (default: the only one journaled)"
    )
    e.add_argument(
        "--from",
        dest="from_",
        metavar="WHEN",
        help="start, ISO date or date-time (UTC unless a zone is given), included",
    )
    e.add_argument("--to", metavar="WHEN", help="end, excluded")
    e.add_argument("--output", required=True, help="run log to write (CSV)")
    e.set_defaults(handler="thermocomp.commands.journal:export")


def _add_init(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "init",
        help="write the example configurations (runtime, cooling, systemd unit) to a directory",
    )
    p.add_argument("directory", nargs="?", default=".", help="where (default: here)")
    p.add_argument("--force", action="store_true", help="overwrite files that exist")
    p.set_defaults(handler="thermocomp.commands.init:main")


GROUPS = (
    ("edge box (beside the machine)", ("init", "run", "status", "measure", "journal", "refit")),
    (
        "workstation (calibration and models)",
        ("wizard", "profile", "probe-program", "fit", "replay", "model", "controls"),
    ),
    (
        "virtual machine tool (no machine needed)",
        ("demo", "simulate", "virtual-cnc", "hal-plant", "cooling"),
    ),
)
"""The commands by audience, as ``thermocomp --help`` lists them; each command is in one group."""


class _TopParser(_Parser):
    """``thermocomp --help`` lists the commands in their ``GROUPS`` instead of argparse's one
    flat list; parsing is argparse's own (``thermocomp COMMAND``)."""

    def format_help(self) -> str:
        formatter = self._get_formatter()
        formatter.add_usage(self.usage, self._actions, self._mutually_exclusive_groups)
        formatter.add_text(self.description)
        commands = next(a for a in self._actions if isinstance(a, argparse._SubParsersAction))
        listed = {a.dest: a for a in commands._choices_actions}
        for title, names in GROUPS:
            formatter.start_section(title)
            formatter.add_arguments([listed[n] for n in names])
            formatter.end_section()
        for group in self._action_groups:
            formatter.start_section(group.title)
            formatter.add_text(group.description)
            formatter.add_arguments([a for a in group._group_actions if a is not commands])
            formatter.end_section()
        formatter.add_text(self.epilog)
        return formatter.format_help()


def build_parser() -> argparse.ArgumentParser:
    """The whole command line, built without side effects (the docs build reads it too)."""
    parser = _TopParser(
        prog="thermocomp",
        description="Cancel the thermal growth of machine-tool spindles from spindle speed.",
        epilog="`thermocomp COMMAND --help` tells what a command takes.",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for add in (
        _add_init,
        _add_run,
        _add_status,
        _add_measure,
        _add_journal,
        _add_refit,
        _add_wizard,
        _add_profile,
        _add_probe_program,
        _add_fit,
        _add_replay,
        _add_model,
        _add_controls,
        _add_demo,
        _add_simulate,
        _add_virtual_cnc,
        _add_hal_plant,
        _add_cooling,
    ):
        add(sub)
    return parser


def resolve(spec: str) -> Handler:
    module, _, func = spec.partition(":")
    return getattr(importlib.import_module(module), func)


class _EarlySignals:
    """`run`: SIGHUP, SIGTERM and SIGINT recorded from the moment the command line is read, so
    that one arriving while the service starts neither kills it without a word (SIGHUP's default
    action) nor is lost; the service acts on them once it runs."""

    def __init__(self) -> None:
        self.stop = False
        self.reload = False
        for sig in ("SIGHUP", "SIGTERM", "SIGINT"):
            if hasattr(signal, sig):
                signal.signal(getattr(signal, sig), self)

    def __call__(self, signum: int, _frame: object) -> None:
        if signum == getattr(signal, "SIGHUP", None):
            self.reload = True
        else:
            self.stop = True


def _needs_extra(err: ModuleNotFoundError, command: str) -> int:
    """A library of an optional extra is missing: say which extra brings it, in one line."""
    extra = EXTRA_OF.get((err.name or "").partition(".")[0])
    if extra is None:
        raise err
    fail(
        f"thermocomp {command} needs {err.name}, which comes with the '{extra}' extra: "
        f"pip install 'thermocomp[{extra}]'"
    )
    return 2


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except (
        ModuleNotFoundError
    ) as err:  # a value set (_Choices) lives in a layer the slim install cannot load
        words = sys.argv[1:] if argv is None else argv
        return _needs_extra(err, next((w for w in words if not w.startswith("-")), ""))
    if getattr(args, "command", None) == "run" and not getattr(args, "check", False):
        args.early_signals = _EarlySignals()
    if args.version:
        from . import __version__

        print(f"thermocomp {__version__}")
        return 0
    if not getattr(args, "handler", None):
        parser.print_help()
        return 2
    from compensator.errors import ConfigError, ThermocompError

    handler = logging.StreamHandler()
    handler.setFormatter(_OneLineFormatter("thermocomp: %(levelname)s: %(name)s: %(message)s"))
    logging.basicConfig(level=logging.WARNING, handlers=[handler])
    # asyncua warns about every unsecured session; the adapters report what matters
    logging.getLogger("asyncua").setLevel(logging.ERROR)

    try:
        return int(resolve(args.handler)(args) or 0)
    except ThermocompError as err:
        # a configuration's problems come one a line: each printed (and clipped) on its own
        for line in str(err).splitlines() if isinstance(err, ConfigError) else [str(err)]:
            fail(line)
        return 2
    except OSError as err:
        name = f"{err.filename}: " if getattr(err, "filename", None) else ""
        fail(f"{name}{err.strerror or err}")
        return 2
    except KeyboardInterrupt:
        print("thermocomp: interrupted", file=sys.stderr)
        return 130
    except ModuleNotFoundError as err:
        return _needs_extra(err, args.command)
    except Exception as err:
        if not getattr(args, "json", False):
            raise
        # a machine reads --json output: one line, never a traceback, even for a bug of ours
        fail(f"internal error: {type(err).__name__}: {err}")
        return 1


if __name__ == "__main__":
    sys.exit(main())
