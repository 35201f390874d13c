"""Does the stated 95 % band hold what it states? The real 40 h record, per channel: fit on cycles
1..k with the 16 temperatures offered (``thermocomp fit --inputs all``), take the error the fit
states (``fit["expected_error"]``), free-run the model from the log's start through cycle k+1 and
count the share of cycle k+1's errors within the band stated for their speed and inputs, for
k = 2, 3, 4. The same share through ``replay`` (which sets a log's errors beside the stated band)
on cycle k+1.

Three shares per split:

- *validated*: over the rows where the statement claims a validated figure, the share within it
  (the promise: about 95 %);
- *claimed*: the share of the rows that got a validated figure at all (the rest are "not
  validated": a floor in older statements, no figure in newer ones);
- *floors included*: over every row with any figure, floors of older statements included (what
  the status page showed as a number).

The code measured is whatever ``calibration`` imports: run it once on this checkout and once with
``PYTHONPATH`` set to a worktree of an older commit to compare (``--json`` each, then
``--compare before.json after.json`` prints both side by side). One BLAS thread.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_bands.py [--channels ch1,ch3]
     [--splits 2,3,4] [--json out.json] [--dump residuals.npz]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

for _k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_k, "1")  # before numpy loads

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parents[1]
DATA = HERE / "tests" / "data" / "real-spindle"
TEMPS = tuple(f"temp{i}_c" for i in range(1, 17))
CHANNELS = ("ch1", "ch2", "ch3", "ch4", "ch5")


def code_state() -> dict:
    import calibration

    src = Path(calibration.__file__).resolve().parents[1]

    def git(*args: str) -> str | None:
        r = subprocess.run(["git", *args], cwd=src, capture_output=True, text=True)
        return r.stdout.strip() if r.returncode == 0 else None

    dirty = git("diff", "--name-only", "HEAD")
    return {
        "package": str(src),
        "commit": git("rev-parse", "--short", "HEAD"),
        "modified": dirty.splitlines() if dirty else [],
    }


def write_channels(out: Path, channels: tuple[str, ...]) -> dict[str, Path]:
    sys.path.insert(0, str(DATA))
    try:
        from channels import write_channels as write  # type: ignore[import-not-found]
    finally:
        sys.path.pop(0)
    return write(out, channels)


def head_csv(src: Path, stop: int, out: Path) -> Path:
    """Rows 0..stop-1 of a run log, as a run log."""
    with open(src, newline="") as fh, open(out, "w", newline="") as w:
        r, wr = csv.reader(fh), csv.writer(w, lineterminator="\n")
        wr.writerow(next(r))
        for i, row in enumerate(r):
            if i >= stop:
                break
            wr.writerow(row)
    return out


def distance_of(model, inputs: dict, a: int, b: int) -> np.ndarray | None:
    from compensator.expected import distance_outside

    if not model.input_names:
        return None
    ch = model.inputs
    return distance_outside(
        np.column_stack([inputs[c.name][a:b] for c in ch]),
        np.array([c.trained_range[0] for c in ch]),
        np.array([c.trained_range[1] for c in ch]),
    )


def shares(err: np.ndarray, bound: np.ndarray, ok: np.ndarray) -> dict:
    """The three shares of the module docstring; ``bound`` NaN where no figure is given."""
    err = np.abs(err)
    has = np.isfinite(bound)
    claim = ok & has
    return {
        "rows": int(err.size),
        "claimed_rows": int(claim.sum()),
        "within_validated": float(np.mean(err[claim] <= bound[claim])) if claim.any() else None,
        "within_validated_n": int((err[claim] <= bound[claim]).sum()),
        "within_any": float(np.mean(err[has] <= bound[has])) if has.any() else None,
        "within_unvalidated": (
            float(np.mean(err[has & ~ok] <= bound[has & ~ok])) if (has & ~ok).any() else None
        ),
    }


def split(path: Path, d, cycles, k: int, tmp: Path, dump: dict | None) -> dict:
    from calibration.fit import fit_data
    from compensator.expected import parse_expected

    stop = cycles[k - 1][1]
    a, b = cycles[k]
    part = type(d)(
        d.name,
        d.time_s[:stop],
        d.speed_rpm[:stop],
        d.elongation_um[:stop],
        {n: v[:stop] for n, v in d.inputs.items()},
    )
    from compensator.errors import CalibrationError

    cpu0 = time.process_time()
    try:
        ident = fit_data([part], TEMPS, nested=True, probe_target_um=None)
    except CalibrationError as err_:  # the fit refused the channel: nothing stated
        return {"k": k, "refused": str(err_)[:300], "stated": None}
    cpu = time.process_time() - cpu0
    model = ident.model
    expected = parse_expected(model.fit)
    inputs = {n: d.inputs[n][:b] for n in model.input_names} if model.input_names else None
    with np.errstate(all="ignore"):
        pred = model.simulate_um(d.speed_rpm[:b], d.time_s[:b], inputs, float(d.elongation_um[0]))
    err = d.elongation_um[a:b] - pred[a:b]
    row: dict = {
        "k": k,
        "chosen": ident.chosen.name,
        "inputs_kept": bool(model.input_names),
        "rms_um": float(np.sqrt(np.mean(err**2))),
        "fit_cpu_s": cpu,
        "forward_folds": None if expected is None else expected.forward_folds,
    }
    if expected is None:
        row["stated"] = None
        return row
    dist = distance_of(model, d.inputs, a, b)
    sp = d.speed_rpm[a:b]
    bound = np.asarray(expected.p95_at(sp, dist), float)
    # the speeds lately, from the log's start (statements that keep a history)
    lately = (
        expected.recent_rpm(d.time_s[:b], d.speed_rpm[:b])
        if hasattr(expected, "recent_rpm")
        else None
    )
    ok = np.asarray(
        expected.validated(sp, dist)
        if lately is None
        else expected.validated(sp, dist, lately[a:b]),
        bool,
    )
    row["stated"] = shares(err, bound, ok)
    row["bands"] = [
        {"label": x.label, "p95_abs_um": x.p95_abs_um, "source": x.source} for x in expected.bands
    ]
    row["measured_rpm"] = getattr(expected, "measured_rpm", None)
    row["history_rpm"] = getattr(expected, "history_rpm", None)
    # replay: the service's own estimate over the log (it clamps the speed to the calibrated
    # range, holds inputs to their valid range, ...), its errors on cycle k+1 beside the band
    from compensator.errors import ThermocompError

    try:
        from calibration.replay import replay
        from compensator.io import read_run_log

        log = read_run_log(head_csv(path, b, tmp / f"{path.stem}_{k}.csv"))
        rp = replay(model, log, initial_um=float(d.elongation_um[0]), compare=False)
        res = (rp.measured_um - rp.predicted_um)[a:b]
        row["replay"] = {"rms_um": float(np.sqrt(np.mean(res**2))), **shares(res, bound, ok)}
    except (ThermocompError, ValueError, KeyError) as err_:  # the comparison stands without it
        row["replay"] = {"error": f"{type(err_).__name__}: {err_}"}
    if dump is not None:
        c = ident.chosen
        key = f"{d.name}_k{k}"
        dump[f"{key}_forward"] = (
            c.forward_residual_um if c.forward_residual_um is not None else np.full(stop, np.nan)
        )
        dump[f"{key}_held"] = (
            c.held_out_residual_um if c.held_out_residual_um is not None else np.full(stop, np.nan)
        )
        dump[f"{key}_distance"] = (
            c.forward_distance if c.forward_distance is not None else np.full(stop, np.nan)
        )
        dump[f"{key}_next_err"] = err
        dump[f"{key}_next_dist"] = dist if dist is not None else np.zeros(b - a)
    return row


def channel(path: Path, ks: tuple[int, ...], tmp: Path, dump: dict | None) -> dict:
    from calibration.dataset import log_data
    from calibration.folds import split_cycles
    from compensator.io import read_run_log

    d = log_data([read_run_log(path)], TEMPS, [path.stem])[0][0]
    cycles = split_cycles(d.time_s, d.speed_rpm)
    if dump is not None:
        dump[f"{path.stem}_speed"] = d.speed_rpm
    return {
        "cycles": cycles,
        "splits": [split(path, d, cycles, k, tmp, dump) for k in ks if k < len(cycles)],
    }


def pct(v: float | None) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{100 * v:.0f} %"


def pooled(splits: list[dict], key: str = "within_validated") -> tuple[float | None, int]:
    num = den = 0
    for s in splits:
        st = s.get("stated")
        if not st or st.get(key) is None:
            continue
        n = st["claimed_rows"] if key == "within_validated" else st["rows"]
        num += st[key] * n
        den += n
    return (num / den if den else None), den


def cell(s: dict) -> str:
    st = s.get("stated")
    if s.get("refused"):
        return "fit refused"
    if not st:
        return "no statement"
    claimed = st["claimed_rows"] / st["rows"]
    return (
        f"{pct(st['within_validated'])} of {pct(claimed)} claimed"
        f" ({pct(st['within_any'])} floors incl.)"
    )


def table(runs: dict[str, dict]) -> str:
    """Markdown: per channel and split, each run's shares."""
    out = []
    names = list(runs)
    out.append(
        "| channel | fit → predict | "
        + " | ".join(f"{n}: within validated band, of rows claimed (floors incl.)" for n in names)
        + " | "
        + " | ".join(f"{n}: replay within" for n in names)
        + " |"
    )
    out.append("|---|---|" + "---|" * (2 * len(names)))
    chans = list(next(iter(runs.values()))["channels"])
    for ch in chans:
        splits = [runs[n]["channels"][ch]["splits"] for n in names]
        for i, s0 in enumerate(splits[0]):
            k = s0["k"]
            cells = [cell(sp[i]) for sp in splits]
            rep = [pct((sp[i].get("replay") or {}).get("within_validated")) for sp in splits]
            out.append(f"| {ch} | 1–{k} → {k + 1} | " + " | ".join(cells + rep) + " |")
    out.append("")
    out.append(
        "| channel | "
        + " | ".join(f"{n}: pooled within validated (rows)" for n in names)
        + " | "
        + " | ".join(f"{n}: pooled within, floors incl." for n in names)
        + " |"
    )
    out.append("|---|" + "---|" * (2 * len(names)))
    for ch in chans:
        a = [pooled(runs[n]["channels"][ch]["splits"]) for n in names]
        f = [pooled(runs[n]["channels"][ch]["splits"], "within_any") for n in names]
        out.append(
            f"| {ch} | "
            + " | ".join(f"{pct(v)} ({m})" for v, m in a)
            + " | "
            + " | ".join(pct(v) for v, _ in f)
            + " |"
        )
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--channels", default=",".join(CHANNELS))
    ap.add_argument("--splits", default="2,3,4", help="k: fit on cycles 1..k, predict k+1")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--dump", type=Path, help="write the residuals behind each statement (npz)")
    ap.add_argument("--compare", nargs="+", type=Path, help="print these --json runs side by side")
    args = ap.parse_args()
    if args.compare:
        runs = {p.stem: json.loads(p.read_text()) for p in args.compare}
        for n, r in runs.items():
            print(f"{n}: {r['code']}")
        print(table(runs))
        return 0
    chans = tuple(c for c in args.channels.split(",") if c)
    ks = tuple(int(k) for k in args.splits.split(","))
    dump: dict | None = {} if args.dump else None
    wall0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_channels(Path(tmp), chans)
        res = {}
        for ch in chans:
            res[ch] = channel(paths[ch], ks, Path(tmp), dump)
            print(
                ch,
                json.dumps(
                    [{k: v for k, v in s.items() if k != "replay"} for s in res[ch]["splits"]],
                    default=str,
                ),
                flush=True,
            )
    out = {
        "code": code_state(),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}",
        "wall_s": time.perf_counter() - wall0,
        "channels": res,
    }
    if args.json:
        args.json.write_text(json.dumps(out, indent=1, default=str))
    if dump is not None:
        np.savez_compressed(args.dump, **dump)
    print(table({"run": out}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
