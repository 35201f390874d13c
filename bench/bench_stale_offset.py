"""The stale offset: thermocomp stopped in the middle of a day on the virtual machine tool, and
what the control's watch on its sign of life does about it, for each reaction.

The real service (``python -m thermocomp run``, a process of its own) compensates a job-shop day
over OPC UA against the virtual CNC (an asyncua server in this process, the day's program on a
spindle that starts cold), both in simulated time ``--time-scale`` times faster than the wall
clock. At 2 h 45 min, in a 21 500 rpm stretch that goes on for 6 min before a 45 min rest, the
service is stopped, once with SIGTERM and once with kill -9, and once left running (the
reference).

At the stop the machine's clock is paused until the service's process has gone (what it writes on
its way out lands at the stop, as it would at 1x: a shutdown is not stretched by the time
scale). From then on nothing reaches the control, so the machine is copied and each reaction
(``none``, ``alarm``, ``feed-hold``, ``fade``) runs on its own copy, in lock-step, for the next
simulated hour: when the watch tripped (machine time after the stop), what it did, the tool-tip
error (true growth + the offset the control applies) over every sample and while the tool cut,
and whether the operator's next cycle start is taken at the end of the hour.

The scored hour judges the watch with ``--timeout-s`` (default 3 s of machine time, a real
control's timeout: the copies run in lock-step, so the wall clock plays no part). The live runs
before the stop only record the watch (reaction ``none``) on the wall clock, with
``--live-timeout-s``: by default 3 s of wall time (3 s x the time scale), as ``thermocomp
virtual-cnc`` does; 3 s of machine time at 60x is 50 ms of wall time, and a late cycle of a
healthy service trips it.

Run: .venv/bin/python bench/bench_stale_offset.py [--time-scale 60] [--timeout-s 3]
[--live-timeout-s S] (about 10 min at 60x; not part of ``make test``). The published figures:
``--time-scale 60 --timeout-s 3 --live-timeout-s 3``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from plantdata import identify_runs, plant_run  # noqa: E402

from compensator.clock import ScaledClock, SteppedClock  # noqa: E402
from compensator.io import save_model  # noqa: E402
from compensator.speed_programs import Program, job_shop_day  # noqa: E402
from machine_sim import SpindlePlant, preset  # noqa: E402
from machine_sim.vcnc import VirtualCNC, VirtualMachine, running, step  # noqa: E402
from machine_sim.watchdog import REACTIONS, WatchSettings, default_timeout_s  # noqa: E402

PRESET = "motorized-27k"
SEED = 13  # the demo's job-shop day
STOP_S = 2.75 * 3600.0  # program time of the stop: 21 500 rpm until 2 h 51 min, then 45 min at rest
AFTER_S = 3600.0  # the hour after the stop that is scored
NEXT_JOB = Program("next-job", ((600.0, 15000.0),))
CONFIG = """state_dir = "{state}"
watchdog = false
time_scale = {scale}
log_file = "{log}"
[[spindle]]
name = "s1"
model = "{model}"
period_s = 1.0
adapter = {{url = "{url}", preset = "virtual-cnc"}}
[spindle.shaping]
max_offset_um = 80.0
max_rate_um_per_s = 1.0
not_cutting_rate_um_per_s = 50.0
deadband_um = 0.1
[spindle.shaping.transient]
mode = "dual-slew"
[spindle.shaping.cutting]
signal = "auto"
"""


class PausableClock:
    """The virtual CNC's simulated time, ``scale`` x the monotonic clock, until it is paused."""

    def __init__(self, scale: float) -> None:
        self._clock = ScaledClock(scale, time.monotonic)
        self._paused: float | None = None

    def __call__(self) -> float:
        return self._paused if self._paused is not None else self._clock()

    def pause(self) -> None:
        self._paused = self._clock()


@dataclass
class Outcome:
    stop: str
    reaction: str
    reacted_s: float | None  # machine time from the stop to the watch's trip; None: never
    since_beat_s: float | None  # ... from the last beat the control took
    did: str
    max_um: float
    rms_um: float
    cut_max_um: float
    cut_rms_um: float
    cut_rows: int
    rest_max_um: float
    rest_rms_um: float
    rest_rows: int
    offset_end_um: float
    next_start: str


def model_file(tmp: Path) -> Path:
    """A model identified on the virtual plant's calibration and validation runs (as the
    end-to-end tests do): the error shows what the control does, not a model that misfits."""
    path = tmp / "model.json"
    save_model(
        path,
        identify_runs([plant_run("calibration", 60.0, 0), plant_run("validation", 60.0, 1)]).model,
    )
    return path


def day() -> Program:
    """The job-shop day to an hour past the stop (the rest of the day is never reached)."""
    prog = job_shop_day(preset(PRESET).max_rpm, seed=SEED, hours=5)
    segs, t = [], 0.0
    for d, rpm in prog.segments:
        take = min(d, STOP_S + AFTER_S + 600.0 - t)
        if take <= 0:
            break
        segs.append((take, rpm))
        t += take
    return Program(f"{prog.name} (seed {SEED})", tuple(segs))


def events(log: Path) -> list[dict]:
    if not log.exists():
        return []
    out = []
    for line in log.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            continue
    return out


def wait(pred, timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > end:
            raise SystemExit(f"bench: timed out waiting for {what}")
        time.sleep(0.05)


def live(
    case: str, model: Path, tmp: Path, scale: float, live_timeout_s: float
) -> tuple[VirtualMachine, float, int, str]:
    """One live run to the stop (or an hour past it, ``running``): the machine (a copy of it
    at the stop, its clock stepped from there), the program's start in machine time, the watch's
    trips before the stop, and what the service said about the sign of life."""
    clock = PausableClock(scale)
    vm = VirtualMachine(
        SpindlePlant(preset(PRESET), seed=SEED),
        None,
        clock=clock,
        watch=WatchSettings(timeout_s=live_timeout_s),  # live: the state only
    )
    root = tmp / case.replace(" ", "")
    root.mkdir()
    log = root / "log.jsonl"
    with running(VirtualCNC(vm, tick_s=0.005)) as cnc:
        config = root / "machine.toml"
        config.write_text(
            CONFIG.format(state=root / "state", scale=scale, log=log, model=model, url=cnc.url)
        )
        with open(root / "stderr", "w") as err:
            proc = subprocess.Popen(
                [sys.executable, "-m", "thermocomp", "run", "--config", str(config)],
                stdout=subprocess.DEVNULL,
                stderr=err,
                stdin=subprocess.DEVNULL,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
        try:
            wait(
                lambda: (
                    proc.poll() is None and any(e.get("event") == "started" for e in events(log))
                ),
                120,
                "the service to start",
            )
            vm.advance()
            vm.load_program(day())
            t0 = vm.plant.time_s
            end = t0 + STOP_S + (AFTER_S if case == "running" else 0.0)
            last_report = t0
            while vm.plant.time_s < end:
                if proc.poll() is not None:
                    raise SystemExit(f"bench: the service exited {proc.returncode}, see {root}")
                if vm.plant.time_s - last_report >= 1800.0:
                    last_report = vm.plant.time_s
                    print(
                        f"   {case}: {(vm.plant.time_s - t0) / 3600:4.2f} h, offset "
                        f"{vm.offset_um:7.2f} um, watch {vm.watch.state}",
                        flush=True,
                    )
                time.sleep(0.05)
            if case != "running":
                clock.pause()
            vm.advance()
            trips = vm.watch.trips
            stop_s = vm.plant.time_s
            proc.send_signal(signal.SIGTERM if case == "SIGTERM" else signal.SIGKILL)
            proc.wait(60)
            step(cnc)  # what it wrote until it went, taken at the stop
            last_beat_s = vm.watch.last_beat_s
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(30)
    said = [
        str(e.get("msg") or e.get("message") or e)
        for e in events(log)
        if "sign of life" in json.dumps(e)
    ]
    twin = vm.fork(SteppedClock(stop_s)) if case != "running" else vm
    before = [(t, s) for t, s in vm.watch.changes if t < stop_s]
    stale = sum(s == "stale" for _, s in before)
    invalid = [round(t - t0, 1) for t, s in before if s == "invalid"]
    gap = "-" if last_beat_s is None else f"{stop_s - last_beat_s:.1f} s"
    late = sum(e.get("event") == "cycles_late" for e in events(log))
    note = (
        f"{case}: before the stop the watch went stale {stale} times, invalid {len(invalid)} "
        f"times (program time s: {invalid[:8]}), the service logged {late} 'cycles late'; the "
        f"last beat the control took came {gap} before the stop; the service said: "
        f"{said[-1] if said else '-'}"
    )
    return twin, t0, trips, note


def score(
    stop: str, reaction: str, vm: VirtualMachine, stop_s: float, trips_before: int
) -> Outcome:
    h = vm.history()
    span = (h.time_s > stop_s + 1e-9) & (h.time_s <= stop_s + AFTER_S + 1e-9)
    err = h.tool_tip_error_um[span]
    cut = err[h.cutting[span]]
    rest = err[h.speed_rpm[span] == 0.0]
    w = vm.watch
    tripped = w.trips > trips_before and w.tripped_at_s is not None
    reacted = (w.tripped_at_s - stop_s) if tripped and w.tripped_at_s is not None else None
    did = {
        "none": "offset kept",
        "alarm": "alarm; the program runs to its end",
        "feed-hold": "program paused, spindle on",
        "fade": f"offset faded (tau {w.settings.fade_tau_s:g} s)",
    }.get(reaction, "-")
    if reacted is None:
        did = "nothing: the watch never tripped" + (
            " (never armed: no sign of life)" if not w.armed else ""
        )
    vm.load_pending(NEXT_JOB)
    started = vm.cycle_start()
    since = (
        None
        if reacted is None or w.last_beat_s is None or w.tripped_at_s is None or not w.valid
        else w.tripped_at_s - w.last_beat_s
    )
    return Outcome(
        stop,
        reaction,
        reacted,
        since,
        did,
        float(np.max(np.abs(err))),
        float(np.sqrt(np.mean(err**2))),
        float(np.max(np.abs(cut))) if cut.size else math.nan,
        float(np.sqrt(np.mean(cut**2))) if cut.size else math.nan,
        int(cut.size),
        float(np.max(np.abs(rest))) if rest.size else math.nan,
        float(np.sqrt(np.mean(rest**2))) if rest.size else math.nan,
        int(rest.size),
        float(vm.offset_um),
        "taken" if started else f"refused: {w.refusal or 'nothing loaded'}",
    )


def after_the_stop(
    vm: VirtualMachine, stop_s: float, reaction: str, settings: WatchSettings, trips: int
) -> Outcome:
    """A copy of the machine at the stop, the watch set to ``reaction``, an hour in lock-step."""
    clock = SteppedClock(stop_s)
    twin = vm.fork(clock)
    twin.watch.settings = WatchSettings(
        timeout_s=settings.timeout_s,
        fade_tau_s=settings.fade_tau_s,
        fade_max_rate_um_per_s=settings.fade_max_rate_um_per_s,
    )
    twin.watch.with_reaction(reaction)  # type: ignore[arg-type]
    h = twin.plant_dt_s
    for _ in range(int(round(AFTER_S / h))):
        clock.advance(h)
        twin.advance()
    return score("", reaction, twin, stop_s, trips)


def table(rows: list[Outcome]) -> str:
    def f(x: float) -> str:
        return "-" if math.isnan(x) else f"{x:.2f}"

    head = (
        "| stop | reaction | the control reacted (after the stop) | what it did | tool-tip error "
        "over the hour, max / RMS [µm] | while cutting (rows) | at rest (rows) | offset at +1 h "
        "[µm] | next cycle start |\n|---|---|---|---|---|---|---|---|---|"
    )
    lines = [head]
    for o in rows:
        when = "-" if o.reacted_s is None else f"{o.reacted_s:+.1f} s"
        if o.reacted_s is not None:
            when += (
                " (the last beat: valid false)"
                if o.since_beat_s is None
                else f" ({o.since_beat_s:.1f} s after the last beat)"
            )
        lines.append(
            f"| {o.stop} | {o.reaction} | {when} | {o.did} | {o.max_um:.2f} / {o.rms_um:.2f} | "
            f"{f(o.cut_max_um)} / {f(o.cut_rms_um)} ({o.cut_rows}) | "
            f"{f(o.rest_max_um)} / {f(o.rest_rms_um)} ({o.rest_rows}) | {o.offset_end_um:.2f} | "
            f"{o.next_start} |"
        )
    return "\n".join(lines)


def main() -> int:
    global STOP_S
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--time-scale", type=float, default=60.0, help="simulated s per wall s")
    ap.add_argument(
        "--stop-h", type=float, default=STOP_S / 3600, help="program time of the stop [h]"
    )
    ap.add_argument(
        "--timeout-s",
        type=float,
        default=3.0,
        help="the watch's timeout over the scored hour, machine s (lock-step)",
    )
    ap.add_argument(
        "--live-timeout-s",
        type=float,
        default=None,
        help="the watch's timeout in the live runs, machine s (default 3 s of wall time: "
        "3 x --time-scale)",
    )
    ap.add_argument("--fade-tau-s", type=float, default=WatchSettings().fade_tau_s)
    ap.add_argument(
        "--fade-rate-um-per-s", type=float, default=WatchSettings().fade_max_rate_um_per_s
    )
    args = ap.parse_args()
    STOP_S = args.stop_h * 3600.0
    settings = WatchSettings(
        timeout_s=args.timeout_s,
        fade_tau_s=args.fade_tau_s,
        fade_max_rate_um_per_s=args.fade_rate_um_per_s,
    )
    live_timeout_s = (
        default_timeout_s(args.time_scale) if args.live_timeout_s is None else args.live_timeout_s
    )
    WatchSettings(timeout_s=live_timeout_s)  # refused here, not after the model's fit
    logging.getLogger("asyncua").setLevel(logging.ERROR)
    started = time.monotonic()
    rows: list[Outcome] = []
    notes: list[str] = []
    with tempfile.TemporaryDirectory(prefix="bench-stale-") as d:
        tmp = Path(d)
        print("identifying a model on the virtual plant ...", flush=True)
        model = model_file(tmp)
        for case in ("running", "SIGTERM", "kill -9"):
            print(f"{case}: the service on a job-shop day at {args.time_scale:g}x ...", flush=True)
            vm, t0, trips, note = live(case, model, tmp, args.time_scale, live_timeout_s)
            notes.append(note)
            stop_s = t0 + STOP_S
            if case == "running":
                o = score("none: the service runs on", "-", vm, stop_s, vm.watch.trips)
                o.did, o.next_start = "-", "-"
                rows.append(o)
                continue
            stop_s = vm.plant.time_s
            notes.append(
                f"{case}: stop at {(stop_s - t0) / 3600:.3f} h, offset held {vm.offset_um:.2f} um, "
                f"watch {vm.watch.state} (counter {vm.watch.counter}, valid {vm.watch.valid}), "
                f"trips before the stop {trips}"
            )
            for reaction in REACTIONS:
                o = after_the_stop(vm, stop_s, reaction, settings, trips)
                o.stop = case
                rows.append(o)
    print()
    print(
        f"Stale offset on the virtual machine tool ({PRESET}, job-shop day seed {SEED}, stop "
        f"at {STOP_S / 3600:.2f} h; watch timeout {settings.timeout_s:g} s (live runs "
        f"{live_timeout_s:g} s), fade tau "
        f"{settings.fade_tau_s:g} s capped at {settings.fade_max_rate_um_per_s:g} um/s; the "
        f"hour after the stop)"
    )
    print(table(rows))
    for n in notes:
        print(n)
    print(f"({time.monotonic() - started:.0f} s at {args.time_scale:g}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
