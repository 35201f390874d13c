"""The ``thermocomp`` command.

Subcommands are declared here (arguments only); their handlers are named by
``"module:function"`` and imported on use, so ``thermocomp --help`` stays fast
and this module depends on no package but the standard library.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable, Sequence

Handler = Callable[[argparse.Namespace], int]


def _add_replay(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="free-run a model over a logged speed profile")
    p.add_argument("log", help="run log (CSV: time_s,speed_rpm[,elongation_um,...])")
    p.add_argument("--model", required=True, help="model file (JSON)")
    p.add_argument("--output", help="write predicted elongation and offset per row (CSV)")
    p.add_argument("--plot", help="write a PNG plot")
    p.add_argument("--initial-um", type=float, help="initial elongation (default: first measured, else 0)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.set_defaults(handler="calibration.commands:replay_cmd")


def _add_fit(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", help="fit and validate a model from calibration runs")
    p.add_argument("runs", nargs="+", help="calibration run logs (CSV)")
    p.add_argument("--output", required=True, help="model file to write (JSON)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.add_argument("--spindle-id", default=None, help="spindle id stored in the model")
    p.add_argument("--machine-id", default=None, help="machine id stored in the model")
    p.add_argument("--dt", type=float, default=None, help="resample runs to this period [s]")
    p.add_argument("--form", default="auto", help="force a model form (default: best in free run)")
    p.add_argument("--plot", help="write a PNG plot of the fit")
    p.set_defaults(handler="calibration.commands:fit")


def _add_simulate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="write a run log from the virtual spindle plant")
    p.add_argument("--preset", default="motorized-27k", help="plant preset")
    p.add_argument("--program", default="paper-calibration", help="speed program")
    p.add_argument("--dt", type=float, default=60.0, help="sample period [s]")
    p.add_argument("--seed", type=int, default=0, help="random seed (noise, ambient, program)")
    p.add_argument("--output", required=True, help="run log to write (CSV)")
    p.set_defaults(handler="cnc_adapters.sim.commands:simulate")


def _add_virtual_cnc(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("virtual-cnc", help="serve the virtual machine tool over OPC UA")
    p.add_argument("--preset", default="motorized-27k", help="plant preset")
    p.add_argument("--program", default="job-shop-day", help="speed program")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--time-scale", type=float, default=60.0, help="simulated seconds per second")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default loopback)")
    p.add_argument("--port", type=int, default=4840, help="TCP port")
    p.add_argument("--duration", type=float, default=None, help="stop after this many wall seconds")
    p.set_defaults(handler="cnc_adapters.sim.commands:virtual_cnc")


def _add_run(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the compensation service")
    p.add_argument("--config", required=True, help="runtime configuration (TOML)")
    p.add_argument("--check", action="store_true",
                   help="validate, connect, read one speed, and exit without writing")
    p.set_defaults(handler="compensator.service:main")


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the whole product on the embedded virtual machine tool")
    p.add_argument("--output-dir", default="demo-output", help="where to write logs and plots")
    p.set_defaults(handler="calibration.demo:main")


def _add_model(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("model", help="show or check a model file")
    p.add_argument("model", nargs="?", help="model file (JSON)")
    p.add_argument("--schema", action="store_true", help="print the model file's JSON schema")
    p.add_argument("--json", action="store_true", help="print as JSON")
    p.set_defaults(handler="compensator.commands:model")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="thermocomp",
        description="Cancel the thermal growth of machine-tool spindles from spindle speed.",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_demo, _add_fit, _add_replay, _add_run, _add_simulate, _add_virtual_cnc, _add_model):
        add(sub)
    return parser


def resolve(spec: str) -> Handler:
    module, _, func = spec.partition(":")
    return getattr(importlib.import_module(module), func)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        from . import __version__

        print(f"thermocomp {__version__}")
        return 0
    if not getattr(args, "handler", None):
        parser.print_help()
        return 2
    import logging

    from .errors import ThermocompError

    logging.basicConfig(level=logging.WARNING, format="thermocomp: %(levelname)s: %(name)s: %(message)s")
    # asyncua warns about every unsecured session; the adapters report what matters
    logging.getLogger("asyncua").setLevel(logging.ERROR)

    try:
        return int(resolve(args.handler)(args) or 0)
    except ThermocompError as err:
        print(f"thermocomp: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        name = f" {err.filename}" if getattr(err, "filename", None) else ""
        print(f"thermocomp: error:{name}: {err.strerror or err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("thermocomp: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
