"""A spindle that changes over a month, compensated by a model kept fixed and by a service that
keeps learning from its own tool-setter measurements.

The virtual spindle (``motorized-27k``) ages: the heat its bearings and motor make rises
linearly by ``--heat-rise`` (default 20 %) over ``--days`` (30), and the shop's air follows a
seasonal swing (``--season-k`` kelvin, a quarter of a sine over the month). Day 0 it is
calibrated as the wizard does (the paper's calibration profile and a random validation run, the
eddy-current sensor, ``fit_logs``). Then every day: a shift of job-shop work (16 h) with a
tool-setter cycle every 30 min, and a night at rest. The service (``SpindleRuntime``, the observer
fusing every measurement) runs in lock-step on the machine's clock, at a 30 s cycle. The tool
setter in production is a laser measuring the turning tool (``--setter speed``), or a contact
setter at rest (``--setter rest``: what a refit cannot see at speed, it must leave alone).

- ``fixed``: the day-0 model all month;
- ``learning``: ``thermocomp refit`` every 7 days on the service's own journal (the same command
  a shop runs from its timer) with the default rule: a candidate that passes the held-out
  judgement runs in shadow, and the next refit promotes or rejects it on what it would have done
  there; the service then reloads (the promoted model, the candidate in shadow).

Per week: the tool tip's error while cutting in steady phases (the growth the offset did not
cancel), RMS and max, learning against kept; when ``MODEL_DRIFT`` fired; each refit's decisions
with their judgement figures. A PNG of the error over the month (``--plot``). The two runs go side
by side, one process each; ``--modes`` runs one; ``--keep DIR`` keeps each run's configuration,
journal, model history and the machine's history for a look afterwards.

Run: .venv/bin/python bench/bench_learning.py [--days 30] [--plot docs/learning.png] [--json out.json]
About 30 minutes on 2 cores shared with other work (the fits of the weekly refits dominate).
"""

from __future__ import annotations

import argparse
import io
import json
import logging
import math
import os
import platform
import sys
import tempfile
import time
from contextlib import redirect_stdout
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibration.fit import fit_logs
from calibration.nc_programs import with_probe_stops
from compensator.io import RunLog, save_model
from compensator.speed_programs import job_shop_day, paper_calibration, random_validation
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import ToolSetter, VirtualMachine
from thermocomp.cli import main as cli
from thermocomp.demo import after_speed_change
from thermocomp.runtime import SpindleRuntime
from thermocomp.runtime.config import load_config

DAY_S = 86400.0
WALL0 = 1.78e9
PERIOD_S = 30.0
SHIFT_H = 16.0
PROBE_EVERY_S = 1800.0
PLANT_DT_S = 2.0
DWELL_S = 60.0
"""One tool-setter cycle with its moves: longer than the service's cycle, so the service sees the
spindle at rest and compares the measurement with the estimate at rest."""


class AgingPlant(SpindlePlant):
    """The plant with its heat rising over the month and a seasonal swing of the air."""

    heat_rise: float = 0.2
    days: float = 30.0
    season_k: float = 3.0

    def age(self) -> None:
        """Scale the heat to this moment's age (called once a simulated hour)."""
        f = 1.0 + self.heat_rise * min(self.time_s / (self.days * DAY_S), 1.0)
        base = self._base

        def scaled(c):
            return tuple(f * v for v in c)

        self.params = replace(
            base,
            heat_shaft_w=scaled(base.heat_shaft_w),
            heat_nose_w=scaled(base.heat_nose_w),
            heat_housing_w=scaled(base.heat_housing_w),
        )
        self._cache.clear()  # the transitions were computed with the old heat

    def air_c(self, t_s: float) -> float:
        season = self.season_k * math.sin(0.5 * math.pi * t_s / (self.days * DAY_S))
        return super().air_c(t_s) + season


def aging(params, seed: int, heat_rise: float, days: float, season_k: float) -> AgingPlant:
    p = AgingPlant(params, seed=seed)
    p._base = params
    p.heat_rise, p.days, p.season_k = heat_rise, days, season_k
    return p


def calibrate(params, seed: int, workdir: Path) -> Path:
    """Day 0, as the wizard calibrates: the calibration profile and a validation run, dense."""
    logs = []
    for prog, s in (
        (paper_calibration(params.max_rpm), seed),
        (random_validation(params.max_rpm, seed=seed + 1), seed + 1),
    ):
        t, n = prog.sample(10.0)
        run = SpindlePlant(params, seed=s).run(t, n)
        logs.append(RunLog(t, n, run.measured_um))
    fit = fit_logs(logs, spindle_id="aging", labels=["calibration", "validation"])
    path = workdir / "model.json"
    save_model(path, fit.model)
    return path


CONFIG = """state_dir = "{state}"
watchdog = false
journal_fsync_s = 3600.0

[[spindle]]
name = "aging"
model = "{model}"
period_s = {period}
state_save_every_s = 3600.0
adapter = {{url = "sim://"}}

[spindle.observer]
enabled = true
"""


class Drifts(logging.Handler):
    def __init__(self):
        super().__init__()
        self.seen: list[tuple[float, dict]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if getattr(record, "event", None) == "model_drift":
            self.seen.append((record.fields.get("since_s", 0.0), dict(record.fields)))


def run(mode: str, args, params, model0: Path, workdir: Path) -> dict:
    d = workdir / mode
    d.mkdir()
    model = d / "model.json"
    model.write_bytes(model0.read_bytes())
    config = d / "machine.toml"
    config.write_text(CONFIG.format(state=d / "state", model=model, period=PERIOD_S))
    t = [0.0]
    clock = lambda: t[0]  # noqa: E731
    wall = lambda: WALL0 + t[0]  # noqa: E731
    plant = aging(params, args.seed, args.heat_rise, args.days, args.season_k)
    vm = VirtualMachine(
        plant,
        None,
        clock=clock,
        plant_dt_s=PLANT_DT_S,
        tool_setter=ToolSetter(
            dwell_s=DWELL_S, noise_um=0.3, seed=args.seed, at_speed=args.setter == "speed"
        ),
    )

    def start(previous=None):
        cfg = load_config(config)
        return SpindleRuntime(
            cfg.spindle[0],
            cfg.state_dir,
            cfg.journal_path,
            clock=clock,
            wall=wall,
            adapter=SimAdapter(machine=vm),
            previous=previous,
        )

    rt = start()
    drifts = Drifts()
    logging.getLogger("thermocomp.runtime").addHandler(drifts)
    logging.getLogger("thermocomp.runtime").setLevel(logging.INFO)
    refits = []
    next_age = 0.0
    try:
        for day in range(int(args.days)):
            prog = with_probe_stops(
                job_shop_day(params.max_rpm, seed=1000 + day, hours=SHIFT_H), PROBE_EVERY_S
            )
            vm.load_program(prog)
            end = (day + 1) * DAY_S
            while t[0] < end:
                t[0] += PERIOD_S
                if t[0] >= next_age:
                    plant.age()
                    next_age += 3600.0
                if vm.program is not None and vm.program_done:
                    vm.load_program(None)  # the night: at rest
                rt.cycle()
            if mode == "learning" and (day + 1) % 7 == 0:
                rt.journal.flush(t[0])
                rt.measurements.flush(t[0])
                buf = io.StringIO()
                with redirect_stdout(buf):
                    cli(["refit", "--config", str(config), "--json"])
                out = json.loads(buf.getvalue())
                out["day"] = day + 1
                refits.append(out)
                print(
                    f"  day {day + 1}: refit {out.get('outcome')}: {out.get('reason', '')}",
                    flush=True,
                )
                judged = out.get("shadow_judged") or {}
                if (
                    "promoted" in (out.get("outcome"), judged.get("outcome"))
                    or out.get("outcome") == "shadow"
                ):
                    # what SIGHUP does: the promoted model, or the candidate in shadow, taken up
                    new = start(previous=rt)
                    new.take_journal(rt)
                    rt.close()
                    rt = new
    finally:
        logging.getLogger("thermocomp.runtime").removeHandler(drifts)
        rt.close()
    h = vm.history()
    if args.keep:
        np.savez_compressed(
            d / "history.npz",
            time_s=h.time_s,
            speed_rpm=h.speed_rpm,
            true_um=h.true_um,
            offset_um=h.offset_um,
            cutting=h.cutting,
        )
    err = h.tool_tip_error_um
    # steady: 5 min or more after the spindle last changed speed (a 30 s service cycle lags a
    # speed change's elastic step by up to one cycle, the same for both models)
    steady = h.cutting & ~after_speed_change(h.time_s, h.speed_rpm)
    weeks = []

    def rms(e):
        return float(np.sqrt(np.mean(e**2))) if e.size else None

    for w in range(math.ceil(args.days / 7)):
        span = (h.time_s >= w * 7 * DAY_S) & (h.time_s < min((w + 1) * 7, args.days) * DAY_S)
        e, es = err[span & h.cutting], err[span & steady]
        weeks.append(
            {
                "week": w + 1,
                "cutting_rms_um": rms(e),
                "cutting_max_um": float(np.max(np.abs(e))) if e.size else None,
                "steady_rms_um": rms(es),
                "steady_max_um": float(np.max(np.abs(es))) if es.size else None,
                "uncompensated_rms_um": rms(h.true_um[span & h.cutting]),
            }
        )
    # the error while cutting in steady phases, daily RMS, for the plot
    days = np.floor(h.time_s / DAY_S)
    daily = {}
    for d in np.unique(days[steady]):
        daily[float(d)] = rms(err[(days == d) & steady])
    return {
        "mode": mode,
        "weeks": weeks,
        "refits": refits,
        "drifts": [{"day": (s - WALL0) / DAY_S, **f} for s, f in drifts.seen],
        "daily": daily,
    }


def plot(results: dict, args, path: str) -> None:
    """The error while cutting over the month, daily, with each refit's decision."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4))
    for mode, color in (("fixed", "tab:red"), ("learning", "tab:blue")):
        dd = {float(k): v for k, v in results[mode]["daily"].items()}  # a JSON key is text
        x = np.array(sorted(dd))
        ax.plot(
            x + 0.5,
            [dd[k] for k in sorted(dd)],
            "o-",
            ms=3,
            color=color,
            label="day-0 model kept" if mode == "fixed" else "learning service",
        )
    for r in results["learning"]["refits"]:
        judged = r.get("shadow_judged") or {}
        promoted = "promoted" in (r["outcome"], judged.get("outcome"))
        label = (
            "promoted"
            if promoted
            else "rejected in shadow"
            if judged.get("outcome") == "rejected"
            else "into shadow"
            if r["outcome"] == "shadow"
            else r["outcome"]
        )
        ax.axvline(r["day"], color="tab:green" if promoted else "0.6", lw=1, ls="--")
        ax.text(
            r["day"],
            ax.get_ylim()[1] * 0.97,
            " " + label,
            fontsize=8,
            va="top",
            color="tab:green" if promoted else "0.4",
        )
    for mode, marker in (("fixed", "v"), ("learning", "^")):
        ds = [d["day"] for d in results[mode]["drifts"]]
        ax.plot(
            ds,
            [0.02] * len(ds),
            marker,
            color="tab:orange",
            ms=6,
            ls="none",
            label="MODEL_DRIFT (" + ("day-0 model" if mode == "fixed" else "refit") + ")",
        )
    ax.set_xlabel("day")
    ax.set_ylabel("tool-tip error while cutting,\nsteady phases, daily RMS [um]")
    ax.set_title(
        f"Spindle heat +{100 * args.heat_rise:.0f} % over {args.days:g} days, air +/-{args.season_k:g} K; "
        f"tool setter at {args.setter}, every 30 min",
        fontsize=10,
    )
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"plot: {path}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=float, default=30.0)
    ap.add_argument("--heat-rise", type=float, default=0.2)
    ap.add_argument("--season-k", type=float, default=3.0)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument(
        "--setter",
        choices=["speed", "rest"],
        default="speed",
        help="the production tool setter: a laser measuring the turning tool (default), or a "
        "contact setter at rest",
    )
    ap.add_argument(
        "--modes",
        default="fixed,learning",
        help="the runs, comma-separated (fixed, learning): one alone for a quicker look",
    )
    ap.add_argument("--plot", help="PNG of the error while cutting over the month")
    ap.add_argument("--json", help="write every figure here")
    ap.add_argument(
        "--keep",
        help="keep each run's configuration, journal, model history and the machine's history "
        "(history.npz: the true growth and the offset held, every plant step) in this directory",
    )
    args = ap.parse_args()
    params = preset("motorized-27k")
    started = time.monotonic()
    print(
        f"bench_learning: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}; {args.days:g} days, heat +{100 * args.heat_rise:.0f} %, "
        f"season {args.season_k:g} K, tool setter at {args.setter}"
    )
    with tempfile.TemporaryDirectory(prefix="bench-learning-") as tmp:
        work = Path(args.keep or tmp)
        work.mkdir(parents=True, exist_ok=True)
        model0 = calibrate(params, args.seed, work)
        modes = args.modes.split(",")
        if len(modes) > 1:  # the runs are independent: side by side, one process each
            from concurrent.futures import ProcessPoolExecutor

            with ProcessPoolExecutor(len(modes)) as pool:
                futures = {m: pool.submit(run, m, args, params, model0, work) for m in modes}
                results = {m: f.result() for m, f in futures.items()}
        else:
            results = {m: run(m, args, params, model0, work) for m in modes}
    print(
        "\nweek | uncompensated RMS | fixed model: RMS / max while cutting, steady RMS / max | "
        "learning: RMS / max while cutting, steady RMS / max"
    )
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))
    if set(results) != {"fixed", "learning"}:
        return 0
    print(
        "\nweek | uncompensated RMS | day-0 model kept: steady RMS / max | learning service: "
        "steady RMS / max | learning against kept"
    )
    for a, b in zip(results["fixed"]["weeks"], results["learning"]["weeks"]):
        print(
            f"{a['week']:4d} | {a['uncompensated_rms_um']:6.2f} um | "
            f"{a['steady_rms_um']:5.2f} / {a['steady_max_um']:5.2f} um | "
            f"{b['steady_rms_um']:5.2f} / {b['steady_max_um']:5.2f} um | "
            f"{100 * (b['steady_rms_um'] / a['steady_rms_um'] - 1):+5.1f} %"
        )
    for mode in ("fixed", "learning"):
        for dft in results[mode]["drifts"]:
            print(
                f"{mode}: MODEL_DRIFT from day {dft['day']:.2f}: {dft['size_um']:+.2f} um over "
                f"{dft['measurements']} measurements"
            )
    print("\nrefits (judged with the observer, as the service runs it):")
    for r in results["learning"]["refits"]:
        for what in (r.get("shadow_judged"), r):
            if what is None:
                continue
            figs = ""
            if "candidate" in what and "live" in what:
                c, lv = what["candidate"], what["live"]
                if c.get("observer_rms_um") is not None:
                    figs = (
                        f" [observer {c['observer_rms_um']:.2f} vs {lv['observer_rms_um']:.2f} um"
                    )
                    figs += f", open loop {c['open_loop_rms_um']:.2f} vs {lv['open_loop_rms_um']:.2f} um"
                    figs += "" if "paired_t" not in what else f", paired t {what['paired_t']:+.1f}"
                    figs += f", {what.get('measurements', '?')} measurements]"
            print(f"day {r['day']}: {what.get('outcome')}{figs}: {what.get('reason', '')}")
    print(f"{time.monotonic() - started:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))
    if args.plot:
        plot(results, args, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
