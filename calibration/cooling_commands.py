"""``thermocomp cooling compare|tune|rite`` and ``thermocomp simulate --cooling``: active cooling
from the command line (paper 000), with the plots."""

from __future__ import annotations

import argparse
import json
import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from compensator.cooling_law import PidGains
from compensator.errors import CalibrationError, ConfigError
from compensator.io import atomic_write, load_any_model, read_run_log, write_run_log
from machine_sim.plant import SpindlePlant, preset

from . import cooling_studies as cooling
from . import stability, tuning

MODES = ("constant", "pid", "pid+offset")


def _models(params, scenarios: Sequence[cooling.Scenario], say) -> dict[tuple[float, float], Any]:
    """One model per shop (air, constant coolant), fitted on that shop's excitation run."""
    out: dict[tuple[float, float], Any] = {}
    for sc in scenarios:
        key = (sc.air_c, sc.preheat_c)
        if key not in out:
            ident = cooling.fit_cooling_model(cooling.plant_for(params, *key))
            say(
                f"model for TA {key[0]:g} degC, TC {key[1]:g} degC: {ident.chosen.name} "
                f"({ident.model.form}); {ident.reason}"
            )
            out[key] = ident.model
    return out


def _gains(name: str, params, say) -> PidGains:
    if name == "paper":
        return PidGains.paper()
    if name == "simc":
        t = tune_plant(params)
        say(f"SIMC from the step run: {t['model'].describe()}; {t['tuning'].describe()}")
        return t["gains"]
    raise ConfigError(f"--gains is paper or simc, not {name!r}")


def compare(args: argparse.Namespace) -> int:
    """Paper 000's scenarios on the virtual plant: constant cooling, PID, PID plus the offset."""
    params = preset(args.preset)
    names = args.scenario or list(cooling.SCENARIOS)
    unknown = [n for n in names if n not in cooling.SCENARIOS]
    if unknown:
        raise ConfigError(
            f"unknown scenario {unknown[0]!r}; choose from {', '.join(cooling.SCENARIOS)}"
        )
    say = (lambda _m: None) if args.json else print
    scenarios = [cooling.SCENARIOS[n] for n in names]
    models = _models(params, scenarios, say)
    gain_sets = {g: _gains(g, params, say) for g in (args.gains or ["paper", "simc"])}
    rows, runs = [], {}
    for sc in scenarios:
        model = models[(sc.air_c, sc.preheat_c)]
        base = cooling.run_scenario(params, sc, model, "constant", dt_s=args.dt, seed=args.seed)
        fb = cooling.figures_of(base)
        runs[(sc.name, "constant")] = base
        rows.append({**fb.row(), "gains": "-"})
        for gname, g in gain_sets.items():
            for mode in ("pid", "pid+offset"):
                run = cooling.run_scenario(
                    params, sc, model, mode, gains=g, dt_s=args.dt, seed=args.seed
                )
                runs[(sc.name, f"{mode}/{gname}")] = run
                fr = cooling.figures_of(run)
                row = {**fr.row(), "gains": gname}
                if (
                    mode == "pid"
                    and fb.figures.equilibrium_s
                    and fr.figures.equilibrium_s is not None
                ):
                    row["sooner_pct"] = round(
                        100 * (1 - fr.figures.equilibrium_s / fb.figures.equilibrium_s), 1
                    )
                if mode == "pid" and fb.figures.tevr_um and fr.figures.tevr_um is not None:
                    row["tevr_ratio"] = round(fr.figures.tevr_um / fb.figures.tevr_um, 2)
                rows.append(row)
    if args.json:
        print(json.dumps({"preset": params.name, "dt_s": args.dt, "rows": rows}, indent=1))
    else:
        print(
            f"{'scenario':8} {'mode':11} {'gains':6} {'equilibrium':>12} {'sooner':>7} {'TEVR':>6} "
            f"{'ratio':>6} {'mean':>6} {'set point':>11}"
        )
        for r in rows:
            eq = "never" if r["equilibrium_min"] is None else f"{r['equilibrium_min']:.1f} min"
            tevr = "-" if r["tevr_um"] is None else f"{r['tevr_um']:.2f}"
            mean = "-" if r["mean_after_um"] is None else f"{r['mean_after_um']:.2f}"
            print(
                f"{r['scenario']:8} {r['mode']:11} {r['gains']:6} {eq:>12} "
                f"{(str(r['sooner_pct']) + ' %') if 'sooner_pct' in r else '':>7} {tevr:>6} "
                f"{r.get('tevr_ratio', ''):>6} {mean:>6} {r['setpoint_c'][0]:>5.1f}-{r['setpoint_c'][1]:<5.1f}"
            )
        print(
            "equilibrium: |STE| < 0.5e-3 um/s from then to the end (STE from a GCV smoothing spline); "
            "TEVR: max - min of the error after it; with +offset the error is the tool tip's"
        )
    if args.plot:
        plot_comparison(args.plot, runs, scenarios, list(gain_sets))
        say(f"wrote {args.plot}")
    return 0


def plot_comparison(
    path: str | os.PathLike[str],
    runs: dict[tuple[str, str], cooling.CoolingRun],
    scenarios: Sequence[cooling.Scenario],
    gain_names: Sequence[str],
) -> None:
    """Per scenario: the error under constant cooling, PID cooling and PID plus the offset
    (top), the coolant set points (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        2, len(scenarios), figsize=(4.2 * len(scenarios), 6.4), sharex=True, squeeze=False
    )
    for i, sc in enumerate(scenarios):
        top, bottom = axes[0][i], axes[1][i]
        base = runs[(sc.name, "constant")]
        tm = base.time_s / 60
        top.plot(tm, base.error_um, color="tab:grey", lw=1.2, label="constant cooling")
        bottom.plot(tm, base.setpoint_c, color="tab:grey", lw=1.0)
        for g, color in zip(gain_names, ("tab:blue", "tab:green", "tab:purple")):
            pid, both = runs[(sc.name, f"pid/{g}")], runs[(sc.name, f"pid+offset/{g}")]
            top.plot(tm, pid.error_um, color=color, lw=1.2, label=f"PID ({g})")
            top.plot(tm, both.error_um, color=color, lw=1.0, ls="--", label=f"PID ({g}) + offset")
            bottom.plot(tm, pid.setpoint_c, color=color, lw=1.0)
            eq = stability.stability(pid.time_s, pid.error_um).equilibrium_s
            if eq is not None:
                top.axvline(eq / 60, color=color, lw=0.6, ls=":")
        eq0 = stability.stability(base.time_s, base.error_um).equilibrium_s
        if eq0 is not None:
            top.axvline(eq0 / 60, color="tab:grey", lw=0.6, ls=":")
        top.axhline(sc.rite_um, color="k", lw=0.5, ls="-.")
        top.set_title(f"{sc.name}: {sc.title}", fontsize=8)
        bottom.set_xlabel("time [min]")
        if i == 0:
            top.set_ylabel("thermal error [um]")
            bottom.set_ylabel("chiller set point [degC]")
            top.legend(fontsize=7, loc="lower right")
    fig.suptitle(
        "Active cooling on the virtual plant (paper 000's work conditions); dotted: equilibrium",
        fontsize=10,
    )
    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=80)
    plt.close(fig)


def step_run(
    params,
    *,
    speed_rpm: float | None = None,
    step_k: float = -3.0,
    seed: int = 4,
    dt_s: float = 30.0,
) -> dict[str, np.ndarray]:
    """The chiller step test on the plant: hold a speed until steady (6 h), step the chiller
    set point by ``step_k`` and hold 6 h more. Columns for a run log."""
    n0 = speed_rpm if speed_rpm is not None else params.max_rpm / 2
    t = np.arange(0.0, 12 * 3600.0 + dt_s / 2, dt_s)
    sp = np.where(t <= 6 * 3600.0, params.chiller_c, params.chiller_c + step_k)
    plant = SpindlePlant(params, seed=seed)
    run = plant.run(t, np.full(t.size, n0), sp)
    sensors = plant.sensor_channels(run)
    return {**run.columns(), "coolant_temp_c": sensors["coolant_temp_c"]}


def _step_window(time_s: np.ndarray, setpoint_c: np.ndarray) -> tuple[int, int]:
    """(first row, the row of the first set-point change): the hour before the step on."""
    changes = np.flatnonzero(np.diff(setpoint_c) != 0)
    if changes.size == 0:
        raise CalibrationError("the log's chiller_setpoint_c never changes: nothing to identify")
    k0 = int(changes[0])
    return max(0, int(np.searchsorted(time_s, time_s[k0] - 3600.0))), k0


def identify_step(
    time_s: np.ndarray, setpoint_c: np.ndarray, elongation_um: np.ndarray, order: int = 2
):
    """The set point -> elongation transfer from the part of a log after its first set-point
    change (from the last steady hour before it)."""
    start, _ = _step_window(time_s, setpoint_c)
    t = time_s[start:] - time_s[start]
    return tuning.fit_step_model(t, setpoint_c[start:], elongation_um[start:], order=order)


def tune_plant(
    params, log: dict[str, np.ndarray] | None = None, tau_c_s: float | None = None
) -> dict[str, Any]:
    cols = log if log is not None else step_run(params)
    model = identify_step(
        np.asarray(cols["time_s"]),
        np.asarray(cols["chiller_setpoint_c"]),
        np.asarray(cols["elongation_um"]),
    )
    tun = tuning.simc(model, tau_c_s=tau_c_s)
    gains = tun.parallel()
    return {"model": model, "tuning": tun, "gains": gains, "log": cols}


def tune(args: argparse.Namespace) -> int:
    """Identify the chiller -> elongation transfer from a step run (the plant's, or a log with a
    ``chiller_setpoint_c`` column) and derive SIMC gains; compare with the paper's."""
    params = preset(args.preset)
    log = None
    if args.log:
        rl = read_run_log(args.log)
        if "chiller_setpoint_c" not in rl.extras or rl.elongation_um is None:
            raise ConfigError(
                f"{args.log}: a step run needs elongation_um and chiller_setpoint_c columns"
            )
        log = {
            "time_s": rl.time_s,
            "elongation_um": rl.elongation_um,
            "chiller_setpoint_c": np.asarray(rl.extras["chiller_setpoint_c"], dtype=float),
        }
    elif args.write_step:
        cols = step_run(params)
        write_run_log(
            args.write_step,
            cols,
            {
                "source": "thermocomp cooling tune",
                "preset": params.name,
                "spindle_id": f"sim-{params.name}",
                "machine_id": "virtual",
            },
        )
        print(f"wrote the step run to {args.write_step}")
        log = cols
    t = tune_plant(params, log, args.tau_c_s)
    model, tun, gains = t["model"], t["tuning"], t["gains"]
    print(f"step model (set point -> elongation): {model.describe()}")
    print(f"SIMC: {tun.describe()}")
    print(f"  parallel gains: {gains.describe()}")
    print(f"paper 000: {PidGains.paper().describe()}")
    for name, g in (("simc", gains), ("paper", PidGains.paper())):
        tt, y = tuning.closed_loop_step(
            model, g, dt_s=1.0, duration_s=4 * 3600.0, u_limits=(-8.0, 8.0)
        )
        m = tuning.step_metrics(tt, y, 1.0)
        settle = "not within 4 h" if m.settling_s is None else f"{m.settling_s / 60:.1f} min"
        print(
            f"  {name:5}: unit step in RITE, overshoot {m.overshoot_pct:.1f} %, settling (2 %) "
            f"{settle}, IAE {m.iae:.0f}"
        )
    if args.plot:
        plot_step(args.plot, t["log"], model, {"simc": gains, "paper": PidGains.paper()})
        print(f"wrote {args.plot}")
    return 0


def plot_step(path, log: dict[str, np.ndarray], model, gains: dict[str, PidGains]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    t = np.asarray(log["time_s"])
    sp = np.asarray(log["chiller_setpoint_c"])
    y = np.asarray(log["elongation_um"])
    start, k0 = _step_window(t, sp)
    tt = t[start:] - t[start]
    fit = model.response(tt, sp[start:] - sp[start]) + float(np.mean(y[start : k0 + 1]))
    a.plot(tt / 60, y[start:], color="tab:grey", lw=1, label="measured")
    a.plot(tt / 60, fit, color="tab:red", lw=1.2, label="fitted step model")
    a.set_xlabel("time [min]")
    a.set_ylabel("elongation [um]")
    a.set_title("chiller step: identification", fontsize=9)
    a.legend(fontsize=8)
    for name, g in gains.items():
        ts, ys = tuning.closed_loop_step(
            model, g, dt_s=1.0, duration_s=4 * 3600.0, u_limits=(-8.0, 8.0)
        )
        b.plot(ts / 60, ys, lw=1.2, label=f"{name}: {g.describe()}")
    b.axhline(1.0, color="k", lw=0.5, ls="--")
    b.set_xlabel("time [min]")
    b.set_ylabel("error / RITE step [-]")
    b.set_title("closed loop: a unit step in RITE", fontsize=9)
    b.legend(fontsize=6)
    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=80)
    plt.close(fig)


def suggest_rite(
    model: Any, speed_rpm: np.ndarray, time_s: np.ndarray, inputs: dict[str, float] | None = None
) -> tuple[float, list[tuple[float, float, float]]]:
    """RITE for a shop: the model's steady elongation at the speed mix of a journal, each speed
    band's steady elongation weighted by the share of running time it took. The model is linear
    in its states, so the mean state under a repeating mix is its equilibrium under the mean
    drive: the time-weighted mean of the steady elongations. Rests are left out (the loop
    releases at rest). Returns RITE and the bands (speed, share, steady elongation)."""
    t = np.asarray(time_s, dtype=float)
    n = np.abs(np.asarray(speed_rpm, dtype=float))
    dt = np.diff(t, prepend=t[0])
    run = n > 1.0
    if not run.any() or dt[run].sum() <= 0:
        raise CalibrationError("the journal holds no running time: no speed mix to take RITE from")
    bands = np.round(n[run] / 250.0) * 250.0
    total = float(dt[run].sum())
    rows = []
    for b in np.unique(bands):
        share = float(dt[run][bands == b].sum()) / total
        ss = model.start(None, float(b), inputs).elongation_um
        rows.append((float(b), share, float(ss)))
    rite = float(sum(share * ss for _, share, ss in rows))
    return rite, rows


def rite(args: argparse.Namespace) -> int:
    model = load_any_model(args.model)
    t_parts, n_parts = [], []
    for path in args.journal:
        rl = read_run_log(path)
        t_parts.append(rl.time_s)
        n_parts.append(rl.speed_rpm)
    inputs = None
    if model.input_names:
        if not args.input:
            raise ConfigError(
                f"the model reads {', '.join(model.input_names)}: give each as --input NAME=VALUE "
                "(the shop's typical values with the coolant at its constant)"
            )
        inputs = {}
        for item in args.input:
            name, _, value = item.partition("=")
            try:
                inputs[name] = float(value)
            except ValueError as err:
                raise ConfigError(f"--input {item!r}: NAME=VALUE with a number") from err
        missing = sorted(set(model.input_names) - set(inputs))
        if missing:
            raise ConfigError(f"--input: the model also needs {', '.join(missing)}")
    value, rows = suggest_rite(model, np.concatenate(n_parts), np.concatenate(t_parts), inputs)
    for speed, share, ss in rows:
        if share >= 0.01:
            print(f"  {speed:7.0f} rpm  {100 * share:5.1f} % of running time  steady {ss:6.2f} um")
    print(f"suggested rite_um = {value:.1f}  (the model's steady elongation at this speed mix)")
    return 0


def simulate_cooling(args: argparse.Namespace) -> int:
    """``thermocomp simulate --cooling constant|pid``: one scenario on the plant, the run log
    with the coolant columns, and the stability figures."""
    params = preset(args.preset)
    sc = cooling.SCENARIOS.get(args.program)
    if sc is None:
        raise ConfigError(
            f"with --cooling, --program is one of paper 000's scenarios: {', '.join(cooling.SCENARIOS)}"
        )
    if args.rite is not None:
        if not math.isfinite(args.rite):
            raise ConfigError(f"--rite must be a number, got {args.rite}")
        sc = cooling.Scenario(sc.name, sc.title, sc.segments, args.rite, sc.air_c, sc.preheat_c)
    if args.model:
        model = load_any_model(args.model)
    else:
        model = _models(params, [sc], print)[(sc.air_c, sc.preheat_c)]
    mode = args.cooling + ("+offset" if args.offset else "")
    run = cooling.run_scenario(
        params,
        sc,
        model,
        mode,
        gains=_gains(args.gains, params, print),
        dt_s=1.0,
        seed=args.seed,
        sample_s=max(1.0, args.dt),
    )
    meta = {
        "source": "thermocomp virtual spindle plant, active cooling",
        "preset": params.name,
        "program": sc.name,
        "cooling": mode,
        "rite_um": sc.rite_um,
        "seed": args.seed,
        "spindle_id": f"sim-{params.name}",
        "machine_id": "virtual",
    }
    write_run_log(args.output, run.columns(), meta)
    f = stability.stability(run.time_s, run.error_um)
    print(
        f"wrote {run.time_s.size} rows of {sc.name} ({sc.title}), cooling {mode}, to {args.output}"
    )
    if run.switch_s is not None:
        print(
            f"the loop closed at {run.switch_s / 60:.1f} min (the estimate reached RITE {sc.rite_um:g} um)"
        )
    for line in f.describe():
        print(line)
    return 0
