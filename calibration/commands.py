"""``thermocomp fit`` and ``thermocomp replay``: file I/O, progress and reports."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from compensator.io import load_any_model, read_run_log, save_model, write_run_log
from compensator.io.journal_export import NOT_INPUTS
from compensator.io.runlog import ELONGATION_COLUMN, SPARSE
from compensator.shaping import ShaperConfig

from .calibrate import Calibration, calibrate
from .data import bridge_gaps, run_from_log
from .plots import Panel, plot_panels
from .replay import Replay, replay


def _console() -> Console:
    """Readable tables also when piped: a fixed width instead of 80 columns."""
    c = Console()
    return c if c.is_terminal else Console(width=130)


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        if math.isinf(v) or math.isnan(v):
            return "-"
        return f"{v:.{digits}g}" if abs(v) >= 1e4 or (v != 0 and abs(v) < 1e-2) else f"{v:.{digits}f}"
    return str(v)


@contextmanager
def progress(enabled: bool, total: int | None = None) -> Iterator[Callable[[str], None]]:
    """A rich spinner on stderr; silent when not a terminal or in --json mode."""
    err = Console(stderr=True)
    if not enabled or not err.is_terminal:
        yield lambda _msg: None
        return
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                  console=err, transient=True) as bar:
        task = bar.add_task("starting", total=total)

        def say(msg: str) -> None:
            bar.update(task, description=msg, advance=1)

        yield say


def print_fit_report(cal: Calibration, report: dict[str, Any], out: Console) -> None:
    m = cal.model
    out.print(f"[bold]thermocomp fit[/bold]  spindle {m.spindle_id}  "
              f"{len(cal.runs)} run(s), fitted at {cal.fit_dt_s:g} s, scored by {report['scored_by']}")
    t = Table(title="Candidates (free run: the model feeds on its own output)")
    for col in ("form", "1-step R²", "free-run RMS", "free-run max", "held-out RMS", "held-out max", "note"):
        t.add_column(col, justify="left" if col in ("form", "note") else "right")
    for c in report["candidates"]:
        fr, cv = c["free_run"] or {}, c["cross_validation"] or {}
        name = c["form"] + (" [bold green]<- chosen[/]" if c["form"] == report["chosen"] else "")
        t.add_row(name, _fmt(c["one_step_r2"], 4), _fmt(fr.get("rms_um")), _fmt(fr.get("max_abs_um")),
                  _fmt(cv.get("rms_um")), _fmt(cv.get("max_abs_um")), c["note"])
    out.print(t)
    out.print(f"Chosen: [bold]{report['chosen']}[/bold]: {report['reason']}")
    ct = Table(title=f"Coefficients of {report['chosen']} (n in krpm)")
    for col in ("name", "value", "std. error", "unit"):
        ct.add_column(col)
    for c in report["coefficients"]:
        ct.add_row(c["name"], f"{c['value']:.6g}", _fmt(c["stderr"], 3), c["unit"])
    out.print(ct)
    if report["reference_one_step_r2"] is not None:
        out.print(f"Paper's OLS reference, one step ahead: R² = {report['reference_one_step_r2']:.5f} "
                  "(a one-step R² says little about free run)")
    rt = Table(title="Free-run residuals of the chosen model (um)")
    for col in ("run", "RMS", "max |r|", "mean |r|", "steady RMS", "steady max", "transient RMS", "transient max"):
        rt.add_column(col, justify="right" if col != "run" else "left")
    for r in report["residuals"]:
        st, tr = r["phases"]["steady"], r["phases"]["transient"]
        rt.add_row(Path(r["run"]).name, _fmt(r["rms_um"]), _fmt(r["max_abs_um"]), _fmt(r["mean_abs_um"]),
                   _fmt(st["rms_um"]), _fmt(st["max_abs_um"]), _fmt(tr["rms_um"]), _fmt(tr["max_abs_um"]))
    out.print(rt)
    for w in report["warnings"]:
        out.print(f"[yellow]warning:[/yellow] {w}")


def _meta(args: argparse.Namespace, logs) -> dict[str, Any]:
    meta: dict[str, Any] = {}
    spindle = args.spindle_id or next((lg.metadata.get("spindle_id") for lg in logs if lg.metadata.get("spindle_id")), None)
    machine = args.machine_id or next((lg.metadata.get("machine_id") for lg in logs if lg.metadata.get("machine_id")), None)
    if spindle:
        meta["spindle_id"] = spindle
    if machine:
        meta["machine_id"] = machine
    from datetime import datetime, timezone

    meta["created_utc"] = datetime.now(timezone.utc).replace(microsecond=0).isoformat()
    return meta


def _input_names(args: argparse.Namespace, logs) -> list[str]:
    """The input columns named by ``--inputs``. ``all``: those the first log's metadata lists
    (``# inputs:``, as a journal export writes), else its numeric extra columns but the
    journal's and the export's own (:data:`compensator.io.journal_export.NOT_INPUTS`: the
    runtime's prediction, offsets, flags, the chiller's commands...)."""
    from compensator.errors import CalibrationError

    spec = (args.inputs or "").strip()
    if spec == "all":
        listed = logs[0].metadata.get("inputs")
        if listed is not None:
            names = [n.strip() for n in listed.split(",") if n.strip()]
        else:
            names = [k for k, v in logs[0].extras.items() if v.dtype != object and k not in NOT_INPUTS]
        if not names:
            raise CalibrationError(f"{logs[0].source}: --inputs all, but the log has no input column")
    else:
        names = [n.strip() for n in spec.split(",") if n.strip()]
    for log in logs:
        for n in names:
            col = log.extras.get(n)
            if col is None:
                raise CalibrationError(f"{log.source}: no column {n!r} for --inputs "
                                       f"(columns: {', '.join(log.extras) or 'none'})")
            if col.dtype == object or not np.isfinite(np.asarray(col, dtype=float)).all():
                bad = np.flatnonzero(~np.isfinite(np.asarray(col, dtype=float))) if col.dtype != object else [0]
                line = log.line_of(int(bad[0])) if len(bad) else None
                raise CalibrationError(f"{log.source}{f':{line}' if line else ''}: column {n} is not a "
                                       "finite number on every row")
    return names


def fit(args: argparse.Namespace) -> int:
    if args.method == "forms":
        return fit_forms(args)
    from compensator.errors import CalibrationError

    from .identify import LogData, identify
    from .inputs import unit_of

    for flag, value in (("--dt", args.dt), ("--form", None if args.form == "auto" else args.form)):
        if value is not None:
            raise CalibrationError(f"{flag} applies to --method forms; the cycles method fits at the "
                                   "logs' own sample period")
    if not (math.isfinite(args.probe_target_um) and args.probe_target_um > 0):
        raise CalibrationError(f"--probe-target-um must be > 0, got {args.probe_target_um}")
    if args.probe_every is not None and not (math.isfinite(args.probe_every) and args.probe_every > 0):
        raise CalibrationError(f"--probe-every must be > 0 s, got {args.probe_every}")
    logs = [read_run_log(p) for p in args.runs]
    runs = [run_from_log(log, name=p, sparse=True) for log, p in zip(logs, args.runs)]
    sparse = any(lg.sparse for lg in logs)
    if sparse and args.probe_every is not None:
        raise CalibrationError("--probe-every plans the closed loop on an elongation measured on every "
                               f"row; {next(p for p, lg in zip(args.runs, logs) if lg.sparse)} has it on "
                               "some rows only (sparse)")
    names = _input_names(args, logs)
    data, gap_notes = [], []
    for p, r, lg in zip(args.runs, runs, logs):
        speed, gaps = bridge_gaps(r.time_s, r.speed_rpm)  # missing rows: the last logged speed
        if gaps:
            gap_notes.append(f"{Path(p).name}: {len(gaps)} gap(s) of up to {max(g for _, g in gaps) / 3600:.1f} h: "
                             "integrated at the last logged speed (a gap that begins at rest cools)")
        data.append(LogData(Path(p).name, r.time_s, speed, r.elongation_um,
                            {n: np.asarray(lg.extras[n], dtype=float) for n in names}))
    with progress(not args.json) as say:
        if sparse:  # fitted and scored on the measured rows: calibration.sparse
            from .sparse import identify_sparse

            result = identify_sparse(data, names, units={n: unit_of(n) for n in names}, progress=say,
                                     nested=not args.no_nested, **_meta(args, logs))
        else:
            result = identify(data, names, units={n: unit_of(n) for n in names}, progress=say,
                              nested=not args.no_nested, physical=not args.no_physical,
                              probe_target_um=args.probe_target_um, probe_every_s=args.probe_every,
                              **_meta(args, logs))
    result.warnings[:0] = gap_notes
    model = result.model
    # validated before it is written: the same checks a load makes
    type(model).model_validate(model.model_dump(mode="json"))
    report = result.report()
    save_model(args.output, model)
    report["model_file"] = str(args.output)
    if args.plot:
        j = result.joined
        pred = np.empty_like(j.time_s)
        for a, b in j.segments:
            inputs = {n: v[a:b] for n, v in j.inputs.items()} if model.input_names else None
            pred[a:b] = model.simulate_um(j.speed_rpm[a:b], j.time_s[a:b], inputs, None)
        panels = [Panel(Path(nm).name, j.time_s[a:b] - j.time_s[a], j.speed_rpm[a:b], pred[a:b],
                        j.elongation_um[a:b]) for nm, (a, b) in zip(j.names, j.segments)]
        plot_panels(args.plot, panels, f"fit: {result.chosen.name} (spindle {model.spindle_id}), "
                    "in-sample free run", max_rpm=model.speed_range_rpm[1])
        report["plot"] = str(args.plot)
    return _emit(args, report, lambda out: print_identification(result, report, out))


def _emit(args: argparse.Namespace, report: dict[str, Any], show: Callable[[Console], None]) -> int:
    """The fit report: one JSON object, or tables and where the model went."""
    if args.json:
        print(json.dumps(report, indent=2, allow_nan=False, default=_json_default))
    else:
        out = _console()
        show(out)
        out.print(f"Model written to {args.output}" + (f"; plot {args.plot}" if args.plot else ""))
    return 0


def print_identification(result, report: dict[str, Any], out: Console) -> None:
    m = result.model
    j = result.joined
    out.print(f"[bold]thermocomp fit[/bold]  spindle {m.spindle_id}  {len(j.names)} log(s), "
              f"{j.time_s.size} rows, scored by {report['scored_by']}")
    out.print(f"Cycle rule: {report['cycle_rule']}")
    for line in report["cycles"]:
        out.print(f"  {line}")
    t = Table(title="Candidates, free run (the model feeds on its own output; no measured elongation)")
    for col in ("candidate", "CV RMS", "CV max", "nested RMS", "in-sample RMS", "per fold RMS", "verdict"):
        t.add_column(col, justify="left" if col in ("candidate", "verdict", "per fold RMS") else "right")
    for c in report["candidates"]:
        name = c["name"] + (" [bold green]<- chosen[/]" if c["name"] == report["chosen"] else "")
        verdict = escape("reference only" if c["family"] == "reference" else
                         "accepted" if c["accepted"] else "refused: " + "; ".join(c["refusals"]))
        folds = " ".join(_fmt(v, 2) for v in c["folds_rms_um"])
        t.add_row(name, _fmt(c["cv_rms_um"]), _fmt(c["cv_max_abs_um"]), _fmt(c["nested_rms_um"]),
                  _fmt(c["in_sample_rms_um"]), folds, verdict)
    out.print(t)
    out.print("CV: gains fitted without the held-out fold; nested: the fold also took no part in "
              "choosing alpha (the honest figure). One-step R² is not used.")
    out.print(f"Chosen: [bold]{report['chosen']}[/bold]: {escape(report['reason'])}")
    for c in report["candidates"]:
        if c["name"] == report["chosen"] and "alpha" in c:
            out.print(f"  grid {c['grid']}, alpha {c['alpha']:.3g}, {c['states']} state(s)", markup=False)
    if report["derived"]:
        dt = Table(title="Derived quantities, HAC (Newey-West) standard errors")
        for col in ("quantity", "value", "std. error", "unit"):
            dt.add_column(col)
        for d in report["derived"]:
            dt.add_row(d["quantity"], f"{d['value']:.3g}", f"{d['hac_stderr']:.2g}", d["unit"])
        out.print(dt)
    for line in m.describe():
        out.print(line, markup=False, highlight=False)
    for line in result.closed_loop.lines() if result.closed_loop is not None else ():
        out.print(line, markup=False, highlight=False)
    for w in report["warnings"]:
        out.print(f"[yellow]warning:[/yellow] {w}")


def fit_forms(args: argparse.Namespace) -> int:
    """The earlier method: every output-error form on whole runs, inputs by forward selection."""
    from compensator.errors import CalibrationError

    logs = [read_run_log(p) for p in args.runs]
    for p, lg in zip(args.runs, logs):
        if lg.sparse:
            raise CalibrationError(f"{p}: the elongation is measured on {int(lg.measured.sum())} of {len(lg)} "
                                   "rows (sparse); --method forms needs it on every row: the default "
                                   "method (cycles) fits on the measured rows")
    runs = [run_from_log(log, name=p) for log, p in zip(logs, args.runs)]
    meta = _meta(args, logs)
    names = _input_names(args, logs) if args.inputs else []
    with progress(not args.json) as say:
        cal = calibrate(runs, dt_s=args.dt, form=args.form, progress=say, **meta)
        fitted = None
        if names:
            fitted = _fit_inputs(cal, logs, runs, names, args, say)
    report = cal.report()
    save_model(args.output, fitted.model if fitted else cal.model)
    report["model_file"] = str(args.output)
    if fitted:
        report["inputs"] = fitted.report()
    if args.plot:
        panels = [Panel(Path(r.name).name, r.time_s, r.speed_rpm, cal.predictions[r.name], r.elongation_um)
                  for r in cal.runs]
        plot_panels(args.plot, panels, f"fit: {cal.model.form} (spindle {cal.model.spindle_id})",
                    max_rpm=cal.model.speed_range_rpm[1])
        report["plot"] = str(args.plot)
    def show(out: Console) -> None:
        print_fit_report(cal, report, out)
        if fitted:
            print_input_report(fitted, out)

    return _emit(args, report, show)


def _fit_inputs(cal: Calibration, logs, runs, names: list[str], args: argparse.Namespace, say):
    from compensator.errors import CalibrationError

    from .inputs import InputRun, fit_with_inputs

    input_runs = []
    for log, run in zip(logs, runs):
        chans = {}
        for n in names:
            col = log.extras.get(n)
            if col is None:
                raise CalibrationError(f"{log.source}: no column {n!r} for --inputs "
                                       f"(columns: {', '.join(log.extras) or 'none'})")
            if col.dtype == object:
                raise CalibrationError(f"{log.source}: column {n} is not numeric")
            chans[n] = np.asarray(col, dtype=float)
        input_runs.append(InputRun(run, chans))
    fixed = {}
    for item in (args.input_reference_values or "").split(","):
        if item.strip():
            k, _, v = item.partition("=")
            try:
                fixed[k.strip()] = float(v)
            except ValueError as err:
                raise CalibrationError(f"--reference-values: {item!r} is not name=number") from err
    return fit_with_inputs(cal, input_runs, names, reference=args.input_reference, fixed=fixed,
                           max_inputs=args.max_inputs, progress=say)


def print_input_report(fitted, out: Console) -> None:
    t = Table(title="Inputs: forward selection judged on held-out runs (leave-one-run-out free run)")
    for col in ("step", "input", "dynamics", "held-out RMS [um]", "why"):
        t.add_column(col, justify="right" if "RMS" in col or col == "step" else "left")
    for s in fitted.steps:
        name = s.get("added") or (f"({s['best_next']})" if s.get("stopped") else
                                  "refined" if s.get("refined") else "speed only")
        tau = s.get("tau_s")
        dyn = "-" if tau is None else "static" if tau == 0 else f"lag {tau:g} s"
        t.add_row(str(s["step"]), name, dyn, _fmt(s["held_out_rms_um"]), s["note"])
    out.print(t)
    m = fitted.model
    kt = Table(title=f"Model with inputs (fallback: {m.fallback.form}, speed only)")
    for col in ("input", "unit", "reference", "gain", "tau [s]", "valid range"):
        kt.add_column(col)
    for term in m.inputs:
        ref = f"{term.reference:.3f}" + (" (run start)" if term.reference_mode == "start" else "")
        kt.add_row(term.name, term.unit, ref, f"{term.gain_um_per_unit:.4g} um/{term.unit}",
                   f"{term.tau_s:g}", f"{term.valid_range[0]:.3g}..{term.valid_range[1]:.3g}")
    out.print(kt)
    so, au = fitted.speed_only_cv["rms_um"], fitted.augmented_cv["rms_um"]
    out.print(f"Held-out free-run RMS: speed only {so:.3f} um, with inputs {au:.3f} um "
              f"({100 * (1 - au / so):.0f} % less)")
    for w in fitted.warnings:
        out.print(f"[yellow]warning:[/yellow] {w}")


def _json_default(o: Any) -> Any:
    if hasattr(o, "item"):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def print_replay_report(rep: Replay, out: Console) -> None:
    r = rep.report
    t = Table(title=f"Replay of {r['samples']} samples, {r['duration_s'] / 3600:.2f} h, model {r['model_form']}")
    t.add_column("figure")
    t.add_column("value", justify="right")
    rows = [
        ("initial elongation [um]", r["initial_um"]),
        ("predicted range [um]", f"{r['min_predicted_um']:.2f} .. {r['max_predicted_um']:.2f}"),
        ("max |residual| [um]", r["max_abs_residual_um"]),
        ("RMS residual [um]", r["rms_residual_um"]),
        ("mean |residual| [um]", r["mean_abs_residual_um"]),
        ("std uncompensated [um]", r["std_uncompensated_um"]),
        ("std compensated [um]", r["std_compensated_um"]),
        ("std reduction [%]", r["std_reduction_pct"]),
        ("RMS error of the applied offset [um]", r["applied_rms_residual_um"]),
        ("max |error| of the applied offset [um]", r["applied_max_abs_residual_um"]),
        ("  ... while cutting: RMS [um]", r["applied_cutting_rms_residual_um"]),
        ("  ... while cutting: max |error| [um]", r["applied_cutting_max_abs_residual_um"]),
        (f"thermal equilibrium after [min] ({r['ste_source']})",
         None if r["equilibrium_time_s"] is None else r["equilibrium_time_s"] / 60),
        ("TEVR after equilibrium [um]", r["tevr_um"]),
    ]
    for k, v in rows:
        t.add_row(k, _fmt(v) if not isinstance(v, str) else v)
    out.print(t)
    sh = r["shaping"]
    out.print(f"Shaping: {sh['policy']}, {sh['max_rate_um_per_s']:g} um/s while cutting"
              + (f", {sh['not_cutting_rate_um_per_s']:g} um/s while not" if sh["policy"] == "dual-slew" else "")
              + f"; cutting {100 * sh['cutting_fraction']:.0f} % of the samples, from {sh['cutting_source']}")
    if r.get("policies"):
        pt = Table(title="Transient policies on this log (error of the offset each would write)")
        for col in ("policy", "RMS [um]", "max [um]", "cutting RMS", "cutting max", "max lag [um]",
                    "max rate cutting [um/s]"):
            pt.add_column(col, justify="left" if col == "policy" else "right")
        names = {"slow-slew": "slow slew only", "dual-slew": "dual slew", "longer-cycle": "longer cycle",
                 "hold": "hold", "none": "no shaping (model bound)"}
        for row in r["policies"]:
            name = names[row["policy"]] + (" <- configured" if row["configured"] else "")
            pt.add_row(name, _fmt(row["rms_um"]), _fmt(row["max_abs_um"]), _fmt(row["cutting_rms_um"]),
                       _fmt(row["cutting_max_abs_um"]), _fmt(row["max_lag_um"]),
                       _fmt(row["max_cutting_rate_um_per_s"]))
        out.print(pt)
    for w in r["warnings"]:
        out.print(f"[yellow]warning:[/yellow] {w}")


def replay_cmd(args: argparse.Namespace, shaping: ShaperConfig | None = None) -> int:
    """``thermocomp replay``; ``shaping`` from a runtime configuration (default: the runtime's
    defaults)."""
    from compensator.errors import CalibrationError

    model = load_any_model(args.model)
    log = read_run_log(args.log)
    with progress(not args.json) as say:
        say("replaying")
        probes = None
        if args.probe_every is not None and args.measurements is not None:
            raise CalibrationError("--probe-every and --measurements exclude each other")
        if args.probe_every is not None:
            from .replay import probes_every

            probes = probes_every(log, args.probe_every, args.probe_noise_um, args.probe_seed)
        elif args.measurements is not None:
            from .replay import probes_from_file

            probes = probes_from_file(log, args.measurements, args.probe_noise_um)
        rep = replay(model, log, args.initial_um, shaping or ShaperConfig(), probes,
                     compare=not getattr(args, "no_compare", False))
        if args.output:
            say("writing predictions")
            meta = {"model": args.model, "source": args.log}
            if log.sparse:  # its NaN cells are rows not measured, not faults
                meta[ELONGATION_COLUMN] = SPARSE
            write_run_log(args.output, rep.columns(), meta)
        if args.plot:
            say("plotting")
            plot_panels(args.plot, [Panel(Path(args.log).name, rep.time_s, rep.speed_rpm,
                                          rep.predicted_um, rep.measured_um,
                                          extra=(("applied (-offset written)", -rep.applied_offset_um),))],
                        f"replay: model {model.form} (spindle {model.spindle_id})",
                        max_rpm=model.speed_range_rpm[1])
    report = dict(rep.report)
    if args.output:
        report["output"] = str(args.output)
    if args.plot:
        report["plot"] = str(args.plot)
    if args.json:
        print(json.dumps(report, indent=2, allow_nan=False, default=_json_default))
    else:
        out = _console()
        print_replay_report(rep, out)
        for key in ("output", "plot"):
            if key in report:
                out.print(f"{key}: {report[key]}")
    if args.json:
        for w in report["warnings"]:
            print(f"thermocomp: warning: {w}", file=sys.stderr)
    return 0
