"""``thermocomp simulate`` and ``thermocomp virtual-cnc``: the virtual machine tool from the
command line."""

from __future__ import annotations

import argparse
import dataclasses
import math
import signal
import sys
import time
from pathlib import Path

from compensator.errors import ConfigError
from compensator.io import read_text, write_run_log
from compensator.speed_programs import program
from machine_sim.nc import NcSyntaxError, parse_nc
from machine_sim.plant import PlantParams, SpindlePlant, preset
from machine_sim.vcnc import (
    CYCLE_START_PATH,
    LIFE_PATHS,
    NODE_PATHS,
    PROBE_METHOD_PATH,
    RESET_PATH,
    STATE_PATHS,
    TOOL_SETTER_PATHS,
    WATCH_PATHS,
    SimClock,
    ToolSetter,
    VirtualCNC,
    VirtualMachine,
    running,
)
from machine_sim.watchdog import WatchSettings, default_timeout_s, timeout_warning


def drive_params(params: PlantParams, args: argparse.Namespace) -> PlantParams:
    """The preset with the drive options given on the command line."""
    changes = {}
    for key in ("accel_rpm_per_s", "approach_s"):
        value = getattr(args, key, None)
        if value is None:
            continue
        if not (math.isfinite(value) and (value > 0 if key == "accel_rpm_per_s" else value >= 0)):
            flag = "--" + key.replace("_", "-")
            raise ConfigError(
                f"{flag} must be a number {'> 0' if key == 'accel_rpm_per_s' else '>= 0'}, "
                f"got {value}"
            )
        changes[key] = value
    return dataclasses.replace(params, **changes) if changes else params


def simulate(args: argparse.Namespace) -> int:
    if getattr(args, "cooling", None) is not None:
        from calibration.cooling_commands import simulate_cooling  # fits a model: only when asked

        if args.program == "paper-calibration":
            args.program = "wc1"
        if args.preset == "motorized-27k":
            args.preset = "mechanical-cooled"
        return simulate_cooling(args)
    try:
        params = drive_params(preset(args.preset), args)
        prog = program(args.program, params.max_rpm, seed=args.seed)
    except KeyError as err:
        raise ConfigError(str(err.args[0])) from err
    if not args.dt > 0:
        raise ConfigError(f"--dt must be > 0, got {args.dt}")
    t, n = prog.sample(args.dt)
    run = SpindlePlant(params, seed=args.seed).run(t, n)
    meta = {
        "source": "thermocomp virtual spindle plant",
        "preset": params.name,
        "program": prog.name,
        "seed": args.seed,
        "accel_rpm_per_s": params.accel_rpm_per_s,
        "spindle_id": f"sim-{params.name}",
        "machine_id": "virtual",
    }
    write_run_log(args.output, run.columns(), meta)
    print(
        f"wrote {t.size} rows, {prog.duration_s / 3600:.2f} h of {prog.name} on {params.name} to {args.output}"
    )
    return 0


def virtual_cnc(args: argparse.Namespace) -> int:
    try:
        params = drive_params(preset(args.preset), args)
        if Path(args.program).is_file():
            prog = parse_nc(read_text(args.program), name=Path(args.program).name)
        else:
            prog = program(args.program, params.max_rpm, seed=args.seed)
    except KeyError as err:
        raise ConfigError(str(err.args[0])) from err
    except NcSyntaxError as err:
        raise ConfigError(f"{args.program}: {err}") from err
    watch, warning = watch_settings(args)
    if warning:
        print(f"thermocomp: warning: {warning}", file=sys.stderr, flush=True)
    vm = VirtualMachine(
        SpindlePlant(params, seed=args.seed),
        None if args.wait_start else prog,
        clock=SimClock(args.time_scale),
        tool_setter=ToolSetter(
            at_speed=getattr(args, "tool_setter", "rest") == "speed",
            touches=getattr(args, "tool_setter_touches", 1),
        ),
        watch=watch,
        say=_say,
    )
    if args.wait_start:
        vm.load_pending(prog)
    history = getattr(args, "history", None)
    # SIGTERM (systemd, kill, a test) ends the loop like Ctrl-C, so the history is still written
    signal.signal(signal.SIGTERM, _interrupt)
    with running(VirtualCNC(vm, host=args.host, port=args.port)) as cnc:
        print(
            f"virtual CNC ({params.name}, {prog.name}, {args.time_scale:g}x) at {cnc.url}",
            flush=True,
        )
        if args.wait_start:
            print(
                f"program loaded; write true to ns={cnc.ns};s={CYCLE_START_PATH} to start it",
                flush=True,
            )
        paths = (*NODE_PATHS.values(), *STATE_PATHS.values(), CYCLE_START_PATH, RESET_PATH)
        paths += (*TOOL_SETTER_PATHS.values(), PROBE_METHOD_PATH)
        paths += (*LIFE_PATHS.values(), *WATCH_PATHS.values())
        print("nodes: " + ", ".join(f"ns={cnc.ns};s={p}" for p in paths), flush=True)
        wall = watch.timeout_s / args.time_scale
        print(
            f"sign of life: watched once LifeCounter moves; {watch.timeout_s:g} s still "
            f"({wall:.3g} s of wall time at {args.time_scale:g}x) or CompensationValid false: "
            f"{watch.reaction}",
            flush=True,
        )
        if args.wait_start and args.start_delay is not None:
            print(f"... or it starts by itself in {args.start_delay:g} s", flush=True)
        t0 = time.monotonic()
        end = None if args.duration is None else t0 + args.duration
        pressed = False  # the delayed press is made once, as an operator's: a refusal spends it
        try:
            while end is None or time.monotonic() < end:
                time.sleep(0.2)
                if (
                    not pressed
                    and vm.pending is not None
                    and args.start_delay is not None
                    and time.monotonic() - t0 >= args.start_delay
                ):
                    pressed = True
                    vm.advance()
                    if vm.cycle_start():  # a refusal says why on its own line
                        print("cycle start", flush=True)
                if vm.program is not None and vm.pending is None and vm.program_done:
                    print("program finished; the spindle idles", flush=True)
                    if history:
                        print(error_line(vm), flush=True)
                    vm.load_program(None)
        except KeyboardInterrupt:
            print("stopped", flush=True)
    if history:
        write_history(history, vm, params.name, prog.name)
    return 0


def watch_settings(args: argparse.Namespace) -> tuple[WatchSettings, str]:
    """The watch the options ask for, and a warning line ('' when none). Without
    ``--watch-timeout-s`` the timeout is 3 s of wall time (3 s x the time scale, never under 3 s
    of machine time), as generous against the wall clock as a real control's; a value given is
    taken as it is, with a warning when it is under 1 s of wall time."""
    scale = float(getattr(args, "time_scale", 1.0))
    given = getattr(args, "watch_timeout_s", None)
    try:
        watch = WatchSettings(
            timeout_s=default_timeout_s(scale) if given is None else given,
            reaction=getattr(args, "watch_reaction", "none"),
            fade_tau_s=getattr(args, "fade_tau_s", 1200.0),
            fade_max_rate_um_per_s=getattr(args, "fade_rate_um_per_s", 1.0),
        )
    except ValueError as err:
        text = str(err)
        for name, flag in (
            ("timeout_s", "--watch-timeout-s"),
            ("fade_tau_s", "--fade-tau-s"),
            ("fade_max_rate_um_per_s", "--fade-rate-um-per-s"),
        ):
            text = text.replace(f"watch {name} ", f"{flag} ")
        raise ConfigError(f"virtual-cnc: {text}") from err
    return watch, "" if given is None else timeout_warning(watch.timeout_s, scale)


def _say(now_s: float, text: str) -> None:
    """The control's message line: the watch's trips, resets and refused cycle starts."""
    print(f"[{now_s:9.1f} s] {text}", flush=True)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def tool_tip_error(vm: VirtualMachine):
    """The machine's record (time, speed, the true growth, the offset the controller held,
    whether the tool cut) and the tool tip's error (growth plus offset, A = -S)."""
    h = vm.history()
    return h, h.tool_tip_error_um


def error_line(vm: VirtualMachine) -> str:
    """One line: the tool tip's error over the record and while cutting, without and with the
    offset the controller held."""
    h, err = tool_tip_error(vm)
    if h.time_s.size == 0:
        return "tool-tip error: no record yet"

    def figs(e) -> str:
        return (
            f"RMS {math.sqrt(float((e**2).mean())):.2f} um, max {float(abs(e).max()):.2f} um"
            if e.size
            else "-"
        )

    cut = h.cutting
    return (
        f"tool-tip error over {h.time_s[-1] - h.time_s[0]:.0f} s: uncompensated {figs(h.true_um)}; "
        f"with the offset {figs(err)}; while cutting ({int(cut.sum())} rows): uncompensated "
        f"{figs(h.true_um[cut])}, with the offset {figs(err[cut])}"
    )


def write_history(path: str, vm: VirtualMachine, preset_name: str, program_name: str) -> None:
    h, err = tool_tip_error(vm)
    write_run_log(
        path,
        {
            "time_s": h.time_s,
            "speed_rpm": h.speed_rpm,
            "elongation_um": h.true_um,
            "offset_um": h.offset_um,
            "error_um": err,
            "cutting": h.cutting.astype(int),
        },
        {
            "source": "thermocomp virtual-cnc",
            "preset": preset_name,
            "program": program_name,
            "elongation_um": "the plant's true growth; error_um = growth + offset",
        },
    )
    print(error_line(vm), flush=True)
    print(f"wrote the machine's record, {h.time_s.size} rows, to {path}", flush=True)
