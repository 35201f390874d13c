"""Forward splits of the real 40 h record: fit on cycles 1..k, predict cycle k+1 in free run, for
every k >= 2 and every channel. A model must hold on the future, not only on held-out past cycles.

Methods, each scored on cycle k+1 only (RMS and mean |e| [um]):

- thermocomp with the 16 temperatures offered: ``fit_data(..., nested=True)`` on the rows of
  cycles 1..k, then the chosen model's free run from the log's first elongation over rows
  0..end of cycle k+1 (the runtime carries its state through the day);
- thermocomp, speed only: the same without inputs;
- plain ridge: S ~ c + b1*n + b2*n^2 + sum g_i*T_i (n = |speed| in krpm, temperatures static, no
  filters), standardised columns, alpha by leave-one-cycle-out on the training cycles; static, so
  it predicts cycle k+1 directly;
- the paper's one-step OLS (``fit_paper_ols``), free run from the log's first elongation.

Then, per channel, thermocomp with inputs on the whole 40 h: in-sample free-run RMS of the chosen
model against its honest (nested) CV RMS from the report, and the fit's CPU time.

Run: .venv/bin/python bench/bench_forward.py [--data DIR] [--channels ch1,ch3] [--json out.json]
(DIR holds ch1_train.csv .. ch5_train.csv; it is skipped with a message when absent). It prints
the code that ran: the package's folder, its commit and any uncommitted product files.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import runpy
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_real_spindle import ENV, cand

# one BLAS thread, as the real-spindle bench; it must be set before numpy loads
os.environ.update(
    {k: ENV[k] for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
)

import numpy as np

import calibration
from calibration.dataset import LogData, log_data
from calibration.estimators.paper_ols import fit_paper_ols
from calibration.fit import fit_data
from calibration.folds import split_cycles
from calibration.metrics import residual_stats
from compensator.expected import distance_outside, parse_expected
from compensator.io import read_run_log
from compensator.units import SPEED_SCALE_RPM

ROOT = Path(__file__).resolve().parents[1]
CHANNELS = ("ch1", "ch2", "ch3", "ch4", "ch5")
TEMPS = tuple(f"temp{i}_c" for i in range(1, 17))
ALPHAS = np.logspace(-6, 3, 28)
"""The plain ridge's penalties: 1e-6 to 1e3, three per decade."""
METHODS = (
    ("thermocomp_inputs", "thermocomp, 16 temps offered"),
    ("thermocomp_speed", "thermocomp, speed only"),
    ("plain_ridge", "plain ridge (static)"),
    ("paper_ols", "paper's OLS"),
)


def head(d: LogData, stop: int) -> LogData:
    """The log's rows 0..stop-1."""
    return LogData(
        d.name,
        d.time_s[:stop],
        d.speed_rpm[:stop],
        d.elongation_um[:stop],
        {k: v[:stop] for k, v in d.inputs.items()},
    )


def scores(y_um: np.ndarray, pred_um: np.ndarray) -> dict:
    s = residual_stats(y_um - pred_um)
    return {"rms_um": s["rms_um"], "mean_abs_um": s["mean_abs_um"], "max_abs_um": s["max_abs_um"]}


def free_run_um(model, d: LogData, stop: int) -> np.ndarray:
    """The model's free run over rows 0..stop-1 from the first measured elongation."""
    inputs = {n: d.inputs[n][:stop] for n in model.input_names} if model.input_names else None
    with np.errstate(all="ignore"):
        return model.simulate_um(
            d.speed_rpm[:stop], d.time_s[:stop], inputs, float(d.elongation_um[0])
        )


def thermocomp(d: LogData, cycles: list, k: int, names: tuple[str, ...]) -> dict:
    train_stop = cycles[k - 1][1]
    a, b = cycles[k]
    cpu0 = time.process_time()
    ident = fit_data([head(d, train_stop)], names, nested=True, probe_target_um=None)
    cpu = time.process_time() - cpu0
    pred = free_run_um(ident.model, d, b)
    c = ident.chosen
    with_inputs = next((x for x in ident.candidates if x.family == "inputs"), None)
    return {
        **scores(d.elongation_um[a:b], pred[a:b]),
        **coverage(ident.model, d, pred, a, b),
        "chosen": c.name,
        "inputs_kept": bool(ident.model.input_names),
        "train_honest_rms_um": c.honest_rms_um,
        "train_nested": c.nested_rms_um is not None,
        "fit_cpu_s": cpu,
        "inputs_refused": list(with_inputs.refusals) if with_inputs is not None else None,
    }


def coverage(model, d: LogData, pred: np.ndarray, a: int, b: int) -> dict:
    """How many of the predicted cycle's errors lie within the 95 % band the fit stated for
    their speed (the model's ``fit["expected_error"]``): about 95 % if the statement is honest."""
    expected = parse_expected(model.fit)
    if expected is None:
        return {"within_p95": None}
    err = np.abs(d.elongation_um[a:b] - pred[a:b])
    dist = None
    if model.input_names:
        ch = model.inputs
        dist = distance_outside(
            np.column_stack([d.inputs[c.name][a:b] for c in ch]),
            np.array([c.trained_range[0] for c in ch]),
            np.array([c.trained_range[1] for c in ch]),
        )
    bound = expected.p95_at(d.speed_rpm[a:b], dist)
    ok = expected.validated(d.speed_rpm[a:b], dist)
    out = {
        "within_p95": float(np.mean(err <= bound)),
        "covered_rows": int(err.size),
        "validated_rows": int(ok.sum()),
        "within_p95_validated": float(np.mean(err[ok] <= bound[ok])) if ok.any() else None,
        "within_p95_unvalidated": float(np.mean(err[~ok] <= bound[~ok])) if (~ok).any() else None,
    }
    if dist is not None:
        o = dist > 0
        out["outside_rows"] = int(o.sum())
        out["within_p95_outside"] = float(np.mean(err[o] <= bound[o])) if o.any() else None
        out["within_p95_inside"] = float(np.mean(err[~o] <= bound[~o])) if (~o).any() else None
    return out


# -- the plain static ridge: the comparison, not product code ----------------------------------


def static_columns(d: LogData) -> np.ndarray:
    n = np.abs(d.speed_rpm) / SPEED_SCALE_RPM
    return np.column_stack([n, n * n, *(d.inputs[t] for t in TEMPS)])


def ridge_path(x: np.ndarray, y: np.ndarray, alphas: np.ndarray) -> list[tuple]:
    """Ridge on standardised columns with an unpenalised intercept, one fit per alpha from one
    SVD: minimises ||y - c - Zb||^2/m + alpha*||b||^2. Returns (mean, std, c, b) per alpha."""
    mu, sd = x.mean(axis=0), x.std(axis=0)
    sd[sd == 0] = 1.0
    u, s, vt = np.linalg.svd((x - mu) / sd, full_matrices=False)
    uy = u.T @ (y - y.mean())
    return [(mu, sd, float(y.mean()), vt.T @ (s / (s * s + y.size * a) * uy)) for a in alphas]


def ridge_predict(fit: tuple, x: np.ndarray) -> np.ndarray:
    mu, sd, c, b = fit
    return c + ((x - mu) / sd) @ b


def plain_ridge(d: LogData, cycles: list, k: int) -> dict:
    x, y = static_columns(d), d.elongation_um
    train = cycles[:k]
    sq = np.zeros(ALPHAS.size)
    for a, b in train:
        rows = np.zeros(y.size, bool)
        for a2, b2 in train:
            rows[a2:b2] = (a2, b2) != (a, b)
        for i, f in enumerate(ridge_path(x[rows], y[rows], ALPHAS)):
            sq[i] += float(np.sum((y[a:b] - ridge_predict(f, x[a:b])) ** 2))
    best = int(np.argmin(sq))
    stop = train[-1][1]
    fit = ridge_path(x[:stop], y[:stop], ALPHAS[best : best + 1])[0]
    a, b = cycles[k]
    return {
        **scores(y[a:b], ridge_predict(fit, x[a:b])),
        "alpha": float(ALPHAS[best]),
        "loco_rms_um": math.sqrt(sq[best] / stop),
    }


def paper(d: LogData, cycles: list, k: int) -> dict:
    stop = cycles[k - 1][1]
    a, b = cycles[k]
    f = fit_paper_ols(d.time_s[:stop], d.speed_rpm[:stop], d.elongation_um[:stop])
    with np.errstate(all="ignore"):
        pred = f.predict(d.time_s[:b], d.speed_rpm[:b], float(d.elongation_um[0]))
    return {**scores(d.elongation_um[a:b], pred[a:b]), "a": f.a}


# -- the run ------------------------------------------------------------------------------------


def full_record(d: LogData) -> dict:
    """thermocomp with 16 inputs on the whole record: in-sample free run against the report."""
    cpu0 = time.process_time()
    ident = fit_data([d], TEMPS, nested=True, probe_target_um=None)
    cpu = time.process_time() - cpu0
    row = cand(ident.report(), ident.chosen.name)
    ins = scores(d.elongation_um, free_run_um(ident.model, d, d.time_s.size))["rms_um"]
    honest = row["honest_rms_um"]
    return {
        "chosen": row["name"],
        "inputs_kept": bool(ident.model.input_names),
        "in_sample_rms_um": ins,
        "cv_rms_um": row["cv_rms_um"],
        "nested_rms_um": row["nested_rms_um"],
        "honest_rms_um": honest,
        "report_in_sample_rms_um": row["in_sample_rms_um"],
        "report_forward_rms_um": row.get("forward_rms_um"),
        "honest_over_in_sample": honest / ins if honest is not None and ins > 0 else None,
        "fit_cpu_s": cpu,
    }


def channel(path: Path) -> dict:
    d = log_data([read_run_log(path)], TEMPS, [path.stem])[0][0]
    cycles = split_cycles(d.time_s, d.speed_rpm)
    splits = []
    for k in range(2, len(cycles)):
        a, b = cycles[k]
        splits.append(
            {
                "k": k,
                "train_rows": cycles[k - 1][1],
                "predict_rows": [a, b],
                "predict_top_rpm": float(np.abs(d.speed_rpm[a:b]).max()),
                "thermocomp_inputs": thermocomp(d, cycles, k, TEMPS),
                "thermocomp_speed": thermocomp(d, cycles, k, ()),
                "plain_ridge": plain_ridge(d, cycles, k),
                "paper_ols": paper(d, cycles, k),
            }
        )
    medians = {
        m: float(np.median([s[m]["rms_um"] for s in splits])) if splits else None
        for m, _ in METHODS
    }
    return {
        "cycles": cycles,
        "splits": splits,
        "median_rms_um": medians,
        "full_record": full_record(d),
    }


def git(where: Path, *args: str) -> str | None:
    try:
        r = subprocess.run(["git", *args], cwd=where, capture_output=True, text=True)
    except OSError:
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def code_state() -> dict:
    """Which code ran: where the package came from (a copy on PYTHONPATH is not this checkout),
    its commit and the tracked files changed since (None outside a git checkout)."""
    src = Path(calibration.__file__).resolve().parents[1]
    dirty = git(src, "diff", "--name-only", "HEAD")
    return {
        "package": str(src),
        "commit": git(src, "rev-parse", "--short", "HEAD"),
        "modified": dirty.splitlines() if dirty else [],
    }


def cell(r: dict) -> str:
    return f"{r['rms_um']:.2f} / {r['mean_abs_um']:.2f}"


def fmt(v: float | None, spec: str = ".2f") -> str:
    return "–" if v is None else format(v, spec)


def finite(v):
    """Non-finite figures (a diverged free run) as null, so the JSON stays standard."""
    if isinstance(v, dict):
        return {k: finite(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [finite(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def print_tables(out: dict) -> None:
    chans = out["channels"]
    print(
        "\n## Forward splits: fit on cycles 1..k, predict cycle k+1 (free run from the log's start)\n"
    )
    print(
        "RMS / mean |e| um on cycle k+1. thermocomp's pick: the chosen candidate (+T: inputs kept).\n"
    )
    print(
        "| channel | fit → predict | "
        + " | ".join(label for _, label in METHODS)
        + " | thermocomp pick (16 temps / speed) |"
    )
    print("|---|---|" + "---|" * (len(METHODS) + 1))
    for ch, res in chans.items():
        for s in res["splits"]:
            ti, ts = s["thermocomp_inputs"], s["thermocomp_speed"]
            pick = f"{ti['chosen']}{' +T' if ti['inputs_kept'] else ''} / {ts['chosen']}"
            print(
                f"| {ch} | 1–{s['k']} → {s['k'] + 1} ({s['predict_top_rpm']:.0f} rpm) | "
                + " | ".join(cell(s[m]) for m, _ in METHODS)
                + f" | {pick} |"
            )
    print("\n## Median over splits of the RMS on the predicted cycle [um]\n")
    print("| channel | " + " | ".join(label for _, label in METHODS) + " |")
    print("|---|" + "---|" * len(METHODS))
    for ch, res in chans.items():
        print(f"| {ch} | " + " | ".join(fmt(res["median_rms_um"][m]) for m, _ in METHODS) + " |")
    print(
        "\n## The stated 95 % band on the predicted cycle (thermocomp, 16 temperatures offered)\n"
    )
    print(
        "Share of the predicted cycle's errors within the 95th percentile the fit stated for their "
        'speed band (fit["expected_error"]).\n'
    )
    print(
        "| channel | "
        + " | ".join(f"1–{s['k']} → {s['k'] + 1}" for s in next(iter(chans.values()))["splits"])
        + " | pooled |"
    )
    print("|---|" + "---|" * (len(next(iter(chans.values()))["splits"]) + 1))
    for ch, res in chans.items():
        shares = [s["thermocomp_inputs"].get("within_p95") for s in res["splits"]]
        rows = [s["thermocomp_inputs"].get("covered_rows", 0) for s in res["splits"]]
        pooled = (
            (
                sum(v * n for v, n in zip(shares, rows) if v is not None)
                / max(sum(n for v, n in zip(shares, rows) if v is not None), 1)
            )
            if any(v is not None for v in shares)
            else None
        )
        print(
            f"| {ch} | "
            + " | ".join(fmt(v, ".0%") if v is not None else "-" for v in shares)
            + f" | {fmt(pooled, '.0%') if pooled is not None else '-'} |"
        )
    print(
        "\nThe same, split by what the statement says of itself: where it is validated (two folds or more "
        "predicted forward, a speed within the calibrated range, inputs no farther out than validation "
        "reached) and where it says it is not (a floor). Cells: share within (rows).\n"
    )
    print("| channel | validated | not validated |")
    print("|---|---|---|")
    for ch, res in chans.items():
        cells = []
        for key, rows_of in (
            ("within_p95_validated", lambda s: s.get("validated_rows", 0)),
            (
                "within_p95_unvalidated",
                lambda s: s.get("covered_rows", 0) - s.get("validated_rows", 0),
            ),
        ):
            pairs = [
                (s["thermocomp_inputs"].get(key), rows_of(s["thermocomp_inputs"]))
                for s in res["splits"]
            ]
            pairs = [(v, n) for v, n in pairs if v is not None and n]
            total = sum(n for _, n in pairs)
            cells.append(
                f"{fmt(sum(v * n for v, n in pairs) / total, '.0%')} ({total})" if total else "-"
            )
        print(f"| {ch} | {cells[0]} | {cells[1]} |")
    print("\n## thermocomp with 16 temperatures on the whole 40 h\n")
    print(
        "| channel | chosen | in-sample free-run RMS um | LOCO RMS um | nested RMS um | nested / in-sample "
        "| forward RMS um (report) | fit CPU s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for ch, res in chans.items():
        f = res["full_record"]
        print(
            f"| {ch} | {f['chosen']}{' +T' if f['inputs_kept'] else ''} | {fmt(f['in_sample_rms_um'])} | "
            f"{fmt(f['cv_rms_um'])} | {fmt(f['nested_rms_um'])} | {fmt(f['honest_over_in_sample'])} | "
            f"{fmt(f['report_forward_rms_um'])} | {f['fit_cpu_s']:.1f} |"
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--data",
        type=Path,
        help="folder of ch1_train.csv .. (default: written from the real "
        "record in tests/data/real-spindle)",
    )
    p.add_argument("--channels", default=",".join(CHANNELS), help="comma-separated, e.g. ch1,ch3")
    p.add_argument("--json", type=Path, help="write every figure here")
    args = p.parse_args()
    channels = [c.strip() for c in args.channels.split(",") if c.strip()]
    if args.data is None:
        write = runpy.run_path(str(ROOT / "tests/data/real-spindle/channels.py"))["write_channels"]
        args.data = Path(tempfile.mkdtemp(prefix="bench-forward-"))
        write(args.data, tuple(channels))
    missing = [c for c in channels if not (args.data / f"{c}_train.csv").is_file()]
    if missing:
        print(
            f"bench_forward: skipped: no {', '.join(f'{c}_train.csv' for c in missing)} in {args.data} "
            "(pass --data DIR; tests/data/real-spindle/channels.py DIR writes the same files)"
        )
        return
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    out = {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "loadavg_start": load,
            "blas_threads": 1,
        },
        "code": code_state(),
        "data": str(args.data),
        "plain_ridge_alphas": ALPHAS.tolist(),
        "channels": {},
    }
    code = out["code"]
    print(
        f"machine: {out['machine']['platform']}, {out['machine']['processor']}, {os.cpu_count()} CPUs, "
        f"load {' '.join(f'{v:.2f}' for v in load) if load else 'n/a'}, Python {platform.python_version()}, "
        f"one BLAS thread"
    )
    print(
        f"code: {code['package']}, commit {code['commit'] or 'n/a (not a git checkout)'}"
        + (f", uncommitted changes in {', '.join(code['modified'])}" if code["modified"] else "")
    )
    t0, cpu0 = time.perf_counter(), time.process_time()
    for ch in channels:
        out["channels"][ch] = channel(args.data / f"{ch}_train.csv")
        print(f"{ch}: done ({time.perf_counter() - t0:.0f} s so far)", file=sys.stderr, flush=True)
    out["wall_s"], out["cpu_s"] = time.perf_counter() - t0, time.process_time() - cpu0
    out["machine"]["loadavg_end"] = os.getloadavg() if load else None
    print_tables(out)
    print(
        f"\nbench: {out['wall_s']:.0f} s wall, {out['cpu_s']:.0f} s CPU for {len(channels)} channel(s); "
        f"load at the end {' '.join(f'{v:.2f}' for v in out['machine']['loadavg_end'] or ())}"
    )
    if args.json:
        args.json.write_text(json.dumps(finite(out), indent=1))
        print(f"figures: {args.json}")


if __name__ == "__main__":
    main()
