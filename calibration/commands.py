"""``thermocomp fit`` and ``thermocomp replay``: file I/O, progress and reports."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from compensator.expected import parse_expected
from compensator.io import load_any_model, read_run_log, save_model, write_run_log
from compensator.io.journal_export import NOT_INPUTS
from compensator.io.runlog import ELONGATION_COLUMN, SPARSE
from compensator.shaping import ShaperConfig

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
        return (
            f"{v:.{digits}g}" if abs(v) >= 1e4 or (v != 0 and abs(v) < 1e-2) else f"{v:.{digits}f}"
        )
    return str(v)


QUIET_S = 10.0
"""Without a terminal, progress lines start after this long, at most one per this long [s]."""


@contextmanager
def progress(enabled: bool, total: int | None = None) -> Iterator[Callable[[str], None]]:
    """A rich spinner on stderr; without a terminal, a plain line now and then once the work
    takes a while; silent in --json mode."""
    err = Console(stderr=True)
    if not enabled:
        yield lambda _msg: None
        return
    if not err.is_terminal:
        # a log file or a pipe: a plain line per stage, once the work has taken a while (a
        # quick run, or one refused at once, says nothing but its result)
        import time

        start = time.monotonic()
        last = [start]

        def line(msg: str) -> None:
            now = time.monotonic()
            if now - start >= QUIET_S and now - last[0] >= QUIET_S:
                last[0] = now
                print(f"thermocomp: {msg} ({now - start:.0f} s)", file=sys.stderr, flush=True)

        yield line
        return
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    with Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        TimeElapsedColumn(),
        console=err,
        transient=True,
    ) as bar:
        task = bar.add_task("starting", total=total)

        def say(msg: str) -> None:
            bar.update(task, description=msg, advance=1)

        yield say


def _meta(args: argparse.Namespace, logs) -> dict[str, Any]:
    meta: dict[str, Any] = {}
    spindle = args.spindle_id or next(
        (lg.metadata.get("spindle_id") for lg in logs if lg.metadata.get("spindle_id")), None
    )
    machine = args.machine_id or next(
        (lg.metadata.get("machine_id") for lg in logs if lg.metadata.get("machine_id")), None
    )
    if spindle:
        meta["spindle_id"] = spindle
    if machine:
        meta["machine_id"] = machine
    from datetime import datetime

    meta["created_utc"] = datetime.now(UTC).replace(microsecond=0).isoformat()
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
            names = [
                k for k, v in logs[0].extras.items() if v.dtype != object and k not in NOT_INPUTS
            ]
        if not names:
            raise CalibrationError(
                f"{logs[0].source}: --inputs all, but the log has no input column"
            )
    else:
        names = [n.strip() for n in spec.split(",") if n.strip()]
    for log in logs:
        for n in names:
            col = log.extras.get(n)
            if col is None:
                raise CalibrationError(
                    f"{log.source}: no column {n!r} for --inputs "
                    f"(columns: {', '.join(log.extras) or 'none'})"
                )
            if col.dtype == object or not np.isfinite(np.asarray(col, dtype=float)).all():
                bad = (
                    np.flatnonzero(~np.isfinite(np.asarray(col, dtype=float)))
                    if col.dtype != object
                    else [0]
                )
                line = log.line_of(int(bad[0])) if len(bad) else None
                raise CalibrationError(
                    f"{log.source}{f':{line}' if line else ''}: column {n} is not a "
                    "finite number on every row"
                )
    return names


def fit(args: argparse.Namespace) -> int:
    from compensator.errors import CalibrationError

    from .fit import fit_logs

    if not (math.isfinite(args.probe_target_um) and args.probe_target_um > 0):
        raise CalibrationError(f"--probe-target-um must be > 0, got {args.probe_target_um}")
    if args.probe_every is not None and not (
        math.isfinite(args.probe_every) and args.probe_every > 0
    ):
        raise CalibrationError(f"--probe-every must be > 0 s, got {args.probe_every}")
    with progress(not args.json) as say:
        logs = []
        for p in args.runs:
            say(f"reading {p}")
            logs.append(read_run_log(p))
        names = _input_names(args, logs)
        result = fit_logs(
            logs,
            names,
            labels=[str(p) for p in args.runs],
            progress=say,
            nested=not args.no_nested,
            physical=not args.no_physical,
            probe_target_um=args.probe_target_um,
            probe_every_s=args.probe_every,
            **_meta(args, logs),
        )
    model = result.model
    # validated before it is written: the same checks a load makes
    type(model).model_validate(model.model_dump(mode="json"))
    report = result.report()
    save_model(args.output, model)
    report["model_file"] = str(args.output)
    if args.plot:
        j = result.dataset
        pred = result.free_run_um()
        panels = [
            Panel(nm, j.time_s[a:b] - j.time_s[a], j.speed_rpm[a:b], pred[nm], j.elongation_um[a:b])
            for nm, (a, b) in zip(j.names, j.segments)
        ]
        plot_panels(
            args.plot,
            panels,
            f"fit: {result.chosen.name} (spindle {model.spindle_id}), in-sample free run",
            max_rpm=model.speed_range_rpm[1],
        )
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
    j = result.dataset
    out.print(
        f"[bold]thermocomp fit[/bold]  spindle {m.spindle_id}  {len(j.names)} log(s), "
        f"{j.time_s.size} rows, scored by {report['scored_by']}"
    )
    out.print(f"Cycle rule: {report['cycle_rule']}")
    for line in report["cycles"]:
        out.print(f"  {line}")
    t = Table(
        title="Candidates, free run (the model feeds on its own output; no measured elongation)"
    )
    for col in (
        "candidate",
        "CV RMS",
        "CV max",
        "nested RMS",
        "forward RMS",
        "in-sample RMS",
        "per fold RMS",
        "verdict",
    ):
        t.add_column(
            col, justify="left" if col in ("candidate", "verdict", "per fold RMS") else "right"
        )
    for c in report["candidates"]:
        name = c["name"] + (" [bold green]<- chosen[/]" if c["name"] == report["chosen"] else "")
        verdict = escape(
            "reference only"
            if c["family"] == "reference"
            else "accepted"
            if c["accepted"]
            else "refused: " + "; ".join(c["refusals"])
        )
        folds = " ".join(_fmt(v, 2) for v in c["folds_rms_um"])
        t.add_row(
            name,
            _fmt(c["cv_rms_um"]),
            _fmt(c["cv_max_abs_um"]),
            _fmt(c["nested_rms_um"]),
            _fmt(c.get("forward_rms_um")),
            _fmt(c["in_sample_rms_um"]),
            folds,
            verdict,
        )
    out.print(t)
    out.print(
        "CV: gains fitted without the held-out fold; nested: the fold also took no part in "
        "choosing alpha (the honest figure); forward: each fold from the third predicted by a model "
        "chosen and fitted on the folds before it only. "
        + (
            "The choice reads the worse of nested and forward."
            if report.get("forward_decides", True)
            else "The folds are blocks of one cycle, each at speeds the others do not run: forward there is "
            "extrapolation in speed, shown but not chosen by; the choice and the error to expect read "
            "the held-out figure."
        )
        + " One-step R² is not used."
    )
    out.print(f"Chosen: [bold]{report['chosen']}[/bold]: {escape(report['reason'])}")
    for c in report["candidates"]:
        if c["name"] == report["chosen"] and "alpha" in c:
            out.print(
                f"  grid {c['grid']}, alpha {c['alpha']:.3g}, {c['states']} state(s)", markup=False
            )
    if report["derived"]:
        dt = Table(title="Derived quantities, HAC (Newey-West) standard errors")
        for col in ("quantity", "value", "std. error", "unit"):
            dt.add_column(col)
        for d in report["derived"]:
            dt.add_row(d["quantity"], f"{d['value']:.3g}", f"{d['hac_stderr']:.2g}", d["unit"])
        out.print(dt)
    expected = parse_expected(m.fit)
    if expected is not None:
        out.print(
            "Error to expect (the next cycle's, measured predicting forward), by speed band:",
            markup=False,
        )
        for line in expected.describe():
            out.print(f"  {line}", markup=False, highlight=False)
    for line in m.describe():
        out.print(line, markup=False, highlight=False)
    for line in result.closed_loop.lines() if result.closed_loop is not None else ():
        out.print(line, markup=False, highlight=False)
    for w in report["warnings"]:
        out.print(f"[yellow]warning:[/yellow] {w}")


def _json_default(o: Any) -> Any:
    if hasattr(o, "item"):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def print_replay_report(rep: Replay, out: Console) -> None:
    r = rep.report
    t = Table(
        title=f"Replay of {r['samples']} samples, {r['duration_s'] / 3600:.2f} h, model {r['model_form']}"
    )
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
        (
            f"thermal equilibrium after [min] ({r['ste_source']})",
            None if r["equilibrium_time_s"] is None else r["equilibrium_time_s"] / 60,
        ),
        ("TEVR after equilibrium [um]", r["tevr_um"]),
    ]
    for k, v in rows:
        t.add_row(k, _fmt(v) if not isinstance(v, str) else v)
    out.print(t)
    sh = r["shaping"]
    out.print(
        f"Shaping: {sh['policy']}, {sh['max_rate_um_per_s']:g} um/s while cutting"
        + (
            f", {sh['not_cutting_rate_um_per_s']:g} um/s while not"
            if sh["policy"] == "dual-slew"
            else ""
        )
        + f"; cutting {100 * sh['cutting_fraction']:.0f} % of the samples, from {sh['cutting_source']}"
    )
    if r.get("policies"):
        pt = Table(title="Transient policies on this log (error of the offset each would write)")
        for col in (
            "policy",
            "RMS [um]",
            "max [um]",
            "cutting RMS",
            "cutting max",
            "max lag [um]",
            "max rate cutting [um/s]",
        ):
            pt.add_column(col, justify="left" if col == "policy" else "right")
        names = {
            "slow-slew": "slow slew only",
            "dual-slew": "dual slew",
            "longer-cycle": "longer cycle",
            "hold": "hold",
            "none": "no shaping (model bound)",
        }
        for row in r["policies"]:
            name = names[row["policy"]] + (" <- configured" if row["configured"] else "")
            pt.add_row(
                name,
                _fmt(row["rms_um"]),
                _fmt(row["max_abs_um"]),
                _fmt(row["cutting_rms_um"]),
                _fmt(row["cutting_max_abs_um"]),
                _fmt(row["max_lag_um"]),
                _fmt(row["max_cutting_rate_um_per_s"]),
            )
        out.print(pt)
    if r.get("expected_error"):
        et = Table(title="Error by speed band: what the fit expected, what this log shows")
        for col in (
            "speed band",
            "expected RMS [um]",
            "stated 95 % [um]",
            "RMS here [um]",
            "within 95 %",
            "within, where validated",
            "samples",
        ):
            et.add_column(col, justify="left" if col == "speed band" else "right")
        for b in r["expected_error"]:
            et.add_row(
                str(b["label"]),
                _fmt(b["expected_rms_um"]),
                _fmt(b["expected_p95_abs_um"]),
                _fmt(b["rms_um"]),
                f"{100 * b['within_p95']:.0f} %",
                # where the statement vouches for its figure (elsewhere it is a floor)
                "–"
                if b.get("within_p95_validated") is None
                else f"{100 * b['within_p95_validated']:.0f} %",
                str(b["samples"]),
            )
        out.print(et)
    for w in r["warnings"]:
        out.print(f"[yellow]warning:[/yellow] {w}")


def replay_cmd(
    args: argparse.Namespace,
    shaping: ShaperConfig | None = None,
    estimate_of: Callable[[Any], Any] | None = None,
) -> int:
    """``thermocomp replay``; ``shaping`` and ``estimate_of`` (the estimate a model runs with)
    from a runtime configuration (default: the runtime's defaults)."""
    from compensator.errors import CalibrationError

    model = load_any_model(args.model)
    estimate = None if estimate_of is None else estimate_of(model)
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
        rep = replay(
            model,
            log,
            args.initial_um,
            shaping or ShaperConfig(),
            probes,
            compare=not getattr(args, "no_compare", False),
            estimate=estimate,
        )
        if args.output:
            say("writing predictions")
            meta = {"model": args.model, "source": args.log}
            if log.sparse:  # its NaN cells are rows not measured, not faults
                meta[ELONGATION_COLUMN] = SPARSE
            write_run_log(args.output, rep.columns(), meta)
        if args.plot:
            say("plotting")
            applied = rep.applied_offset_um
            assert applied is not None  # replay() always shapes
            plot_panels(
                args.plot,
                [
                    Panel(
                        Path(args.log).name,
                        rep.time_s,
                        rep.speed_rpm,
                        rep.predicted_um,
                        rep.measured_um,
                        extra=(("applied (-offset written)", -applied),),
                    )
                ],
                f"replay: model {model.form} (spindle {model.spindle_id})",
                max_rpm=model.speed_range_rpm[1],
            )
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
