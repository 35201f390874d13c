"""Forward origins inside cycles on the real 40 h record: one table per channel, for fits on two,
three, four and all five cycles, of every origin's free-run RMS with the median and the worst.

Origins, the same for every method: every half cycle from the end of cycle 1 on (each cycle's
start and its middle in time, :func:`calibration.folds.split_cycles`). An origin's fold is the
rows from it to the next origin. A method is fitted on the rows before the origin only, its whole
selection included (a structure or penalty is chosen on that past alone), and predicts the fold
in free run from the log's start: the model runs over rows 0..fold end from the first measured
elongation and is scored on the fold's rows. A fit on k cycles is scored on the origins inside
them; for k < 5 the fit on all k cycles is also scored on cycle k+1 ("future").

Methods:

- ``today``: the product at commit 763d0d2 (a git worktree, default /tmp/wt763, made if absent),
  ``thermocomp fit --inputs all --json`` on a CSV of the past rows in a subprocess with that tree
  on PYTHONPATH; its model file simulated by the same tree's loader;
- ``new``: the same with this checkout (the choice as it stands when the bench runs);
- ``ridge``: a plain ridge over the 16 static temperatures plus a bank of first-order filters of
  n and n^2 (n = |speed| in krpm) at 10, 30, 90 and 270 min, columns standardised on the past,
  intercept unpenalised, alpha chosen on forward-chained half-cycle blocks of the past (fit on
  blocks 1..j, score block j+1, pooled) -- self-contained here, numpy only;
- ``paper``: the paper's one-step OLS (:func:`calibration.estimators.paper_ols.fit_paper_ols`)
  on the past, free run from the log's start.

Fits are cached by (method, channel, origin) and, for the product, the code's state (commit and
uncommitted diff) in a JSON file (default /tmp/bench_forward_choice.json): a rerun fits only what
changed. Run:

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_forward_choice.py \
        [--channels ch1,ch3] [--prefixes 2,3,4,5] [--methods today,new,ridge,paper] \
        [--jobs 1] [--json out.json]
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import itertools
import json
import math
import os
import runpy
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

for _k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_k] = "1"  # one BLAS thread: the machine is shared; set before numpy loads

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TODAY_COMMIT = "763d0d2"
CHANNELS = ("ch1", "ch2", "ch3", "ch4", "ch5")
TEMPS = tuple(f"temp{i}_c" for i in range(1, 17))
TAUS_MIN = (10.0, 30.0, 90.0, 270.0)
ALPHAS = np.logspace(-6, 3, 28)
"""The plain ridge's penalties: 1e-6 to 1e3, three per decade."""
METHODS = {
    "today": f"today's choice ({TODAY_COMMIT})",
    "new": "new choice (this tree)",
    "ridge": "plain ridge + speed bank",
    "paper": "paper's OLS",
}
RIDGE_VERSION = "ridge-1"
PAPER_VERSION = "paper-1"


# -- the record --------------------------------------------------------------------------------


def read_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    head, body = rows[0], np.array(rows[1:], dtype=float)
    return {h: body[:, i] for i, h in enumerate(head)}


def cycles_of(d: dict[str, np.ndarray]) -> list[tuple[int, int]]:
    from calibration.folds import split_cycles

    return split_cycles(d["time_s"], d["speed_rpm"])


def grid(t: np.ndarray, cycles: list[tuple[int, int]]) -> list[int]:
    """Boundaries of the half cycles: each cycle's start and its middle in time, and the end."""
    out = []
    for a, b in cycles:
        mid = int(np.searchsorted(t, 0.5 * (t[a] + t[b - 1])))
        out += [a, mid] if a < mid < b else [a]
    return [*out, int(t.size)]


def origins_of(bounds: list[int], cycles: list[tuple[int, int]]) -> list[int]:
    """Every boundary from the end of cycle 1 on, but the log's end."""
    return [o for o in bounds[:-1] if o >= cycles[0][1]]


def segment_sse(y: np.ndarray, pred: np.ndarray, bounds: list[int]) -> list[list[float]]:
    """[sse, rows] of every half cycle (inf for a diverged or missing prediction)."""
    out = []
    for a, b in itertools.pairwise(bounds):
        e = y[a:b] - pred[a:b]
        sse = float(e @ e) if np.all(np.isfinite(e)) else math.inf
        out.append([sse, b - a])
    return out


# -- (c) the plain ridge over static temperatures plus a speed filter bank --------------------


def low_pass(u: np.ndarray, t: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order filter, exact for a value held over each step, from equilibrium at row 0;
    causal, so a past-only fit sees only the past."""
    out = np.empty_like(u)
    out[0] = u[0]
    g = -np.expm1(-np.diff(t) / tau_s)
    x = u[0]
    for k in range(1, u.size):
        x += g[k - 1] * (u[k] - x)
        out[k] = x
    return out


def ridge_columns(d: dict[str, np.ndarray]) -> np.ndarray:
    n = np.abs(d["speed_rpm"]) / 1000.0
    t = d["time_s"]
    bank = [low_pass(u, t, tau * 60.0) for u in (n, n * n) for tau in TAUS_MIN]
    return np.column_stack([*bank, *(d[c] for c in TEMPS)])


def ridge_path(x: np.ndarray, y: np.ndarray, alphas: np.ndarray) -> list[tuple]:
    """Ridge on columns standardised on ``x``, intercept unpenalised, one SVD for every alpha:
    minimises ||y - c - Zb||^2/m + alpha*||b||^2. (mean, std, c, b) per alpha."""
    mu, sd = x.mean(axis=0), x.std(axis=0)
    sd[sd == 0] = 1.0
    u, s, vt = np.linalg.svd((x - mu) / sd, full_matrices=False)
    uy = u.T @ (y - y.mean())
    return [(mu, sd, float(y.mean()), vt.T @ (s / (s * s + y.size * a) * uy)) for a in alphas]


def ridge_predict(f: tuple, x: np.ndarray) -> np.ndarray:
    mu, sd, c, b = f
    return c + ((x - mu) / sd) @ b


def fit_ridge(d: dict, x: np.ndarray, bounds: list[int], origin: int) -> dict:
    y = d["elongation_um"]
    past = [b for b in bounds if b <= origin]
    sq = np.zeros(ALPHAS.size)
    for j in range(1, len(past) - 1):  # fit on blocks before past[j], score block j
        a, b = past[j], past[j + 1]
        for i, f in enumerate(ridge_path(x[:a], y[:a], ALPHAS)):
            sq[i] += float(np.sum((y[a:b] - ridge_predict(f, x[a:b])) ** 2))
    best = int(np.argmin(sq))
    f = ridge_path(x[:origin], y[:origin], ALPHAS[best : best + 1])[0]
    return {
        "seg": segment_sse(y, ridge_predict(f, x), bounds),
        "chosen": f"alpha={ALPHAS[best]:.2g}",
    }


# -- (d) the paper's OLS -----------------------------------------------------------------------


def fit_paper(d: dict, bounds: list[int], origin: int) -> dict:
    from calibration.estimators.paper_ols import fit_paper_ols

    t, n, y = d["time_s"], d["speed_rpm"], d["elongation_um"]
    f = fit_paper_ols(t[:origin], n[:origin], y[:origin])
    with np.errstate(all="ignore"):
        pred = f.predict(t, n, float(y[0]))
    return {"seg": segment_sse(y, pred, bounds), "chosen": f"a={f.a:.5f}"}


# -- (a), (b) the product's fit in a subprocess on the past rows --------------------------------


def git(where: Path, *args: str) -> str:
    r = subprocess.run(["git", *args], cwd=where, capture_output=True, text=True, check=False)
    return r.stdout.strip() if r.returncode == 0 else ""


def code_key(tree: Path) -> str:
    """A hash of the product's sources as they are in ``tree`` (committed or not): a cached fit
    of other code is not reused, and a commit elsewhere (docs, tests) keeps the cache."""
    h = hashlib.sha1()
    for sub in ("calibration", "compensator", "thermocomp"):
        for f in sorted((tree / sub).rglob("*.py")):
            h.update(str(f.relative_to(tree)).encode())
            h.update(f.read_bytes())
    return f"{git(tree, 'rev-parse', '--short', 'HEAD')[:7]}~{h.hexdigest()[:12]}"


def ensure_today(tree: Path) -> None:
    if not (tree / "calibration").is_dir():
        r = subprocess.run(
            ["git", "worktree", "add", str(tree), TODAY_COMMIT],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=False,
        )
        if r.returncode != 0:
            raise SystemExit(f"cannot make the worktree {tree}: {r.stderr.strip()}")


def child_env(tree: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(tree)}


def fit_product(tree: Path, csv_path: Path, origin: int, bounds: list[int], y: np.ndarray) -> dict:
    with tempfile.TemporaryDirectory(prefix="fwdchoice-") as tmp:
        past = Path(tmp) / "past.csv"
        with open(csv_path) as src, open(past, "w") as dst:
            for i, line in enumerate(src):
                if i > origin:
                    break
                dst.write(line)
        model = Path(tmp) / "model.json"
        cmd = [sys.executable, "-m", "thermocomp", "fit", str(past), "--inputs", "all"]
        cmd += ["--json", "--output", str(model)]
        t0 = time.perf_counter()
        r = subprocess.run(
            cmd, cwd=tmp, env=child_env(tree), capture_output=True, text=True, check=False
        )
        wall = time.perf_counter() - t0
        if r.returncode != 0:
            why = (r.stderr.strip().splitlines() or [f"exit {r.returncode}"])[-1]
            return {"seg": None, "chosen": None, "error": f"exit {r.returncode}: {why}"}
        rep = json.loads(r.stdout)
        sim = subprocess.run(
            [sys.executable, __file__, "--simulate", str(model), str(csv_path)],
            cwd=tmp,
            env=child_env(tree),
            capture_output=True,
            text=True,
            check=False,
        )
        if sim.returncode != 0:
            why = (sim.stderr.strip().splitlines() or ["?"])[-1]
            return {"seg": None, "chosen": rep.get("chosen"), "error": f"simulate: {why}"}
        out = json.loads(sim.stdout)
    pred = np.array([math.nan if v is None else v for v in out["pred"]])
    return {
        "seg": segment_sse(y, pred, bounds),
        "chosen": rep.get("chosen"),
        "fallback": out.get("fallback"),
        "package": out.get("package"),
        "fit_wall_s": round(wall, 1),
        "fit_cpu_s": rep.get("fit_cpu_s"),
    }


def simulate_main(model_path: str, csv_path: str) -> None:
    """Child: the model's free run over the whole log with the tree on PYTHONPATH."""
    import compensator
    from compensator.io import load_any_model

    m = load_any_model(model_path)
    d = read_csv(Path(csv_path))
    names = list(getattr(m, "input_names", ()) or ())
    ins = {n: d[n] for n in names} if names else None
    with np.errstate(all="ignore"):
        pred = np.asarray(
            m.simulate_um(d["speed_rpm"], d["time_s"], ins, float(d["elongation_um"][0])), float
        )
    raw = json.loads(Path(model_path).read_text())
    fb = raw.get("fallback")
    fallback = None
    if isinstance(fb, dict):
        fallback = fb.get("form") or (fb.get("fit") or {}).get("method") or "yes"
    print(
        json.dumps(
            {
                "pred": [float(v) if math.isfinite(v) else None for v in pred],
                "fallback": fallback,
                "package": str(Path(compensator.__file__).resolve().parents[1]),
            }
        )
    )


# -- the cache and the run ---------------------------------------------------------------------


class Cache:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.lock = threading.Lock()
        try:
            self.data: dict = json.loads(path.read_text())
        except (OSError, ValueError):
            self.data = {}

    def get(self, key: str) -> dict | None:
        return self.data.get(key)

    def put(self, key: str, value: dict) -> None:
        with self.lock:
            self.data[key] = value
            tmp = self.path.with_suffix(".tmp")
            tmp.write_text(json.dumps(self.data))
            tmp.replace(self.path)


def finite(v):
    """Non-finite figures (a diverged free run) as null, so that the JSON stays standard."""
    if isinstance(v, dict):
        return {str(k): finite(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [finite(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def rms(segs: list, idx: list[int]) -> float:
    sse = sum(segs[i][0] for i in idx)
    n = sum(segs[i][1] for i in idx)
    return math.sqrt(sse / n) if math.isfinite(sse) else math.inf


def fmt(v: float | None) -> str:
    if v is None:
        return "ref."
    return "inf" if not math.isfinite(v) else f"{v:.2f}"


def table(ch: str, info: dict, fits: dict, prefixes: list[int], methods: list[str]) -> dict:
    """Print one channel's tables; return its figures."""
    bounds, cycles, t = info["bounds"], info["cycles"], info["t"]
    origins = origins_of(bounds, cycles)
    out: dict = {}
    for k in prefixes:
        end = cycles[k - 1][1]
        inside = [o for o in origins if o < end]
        fut = cycles[k][0] if k < len(cycles) else None
        head = [f"{t[o] / 3600:.1f}h" for o in inside]
        print(f"\n### {ch}, fits on {k} cycles: {len(inside)} origins, RMS [um] per fold")
        cols = ["method", *head, "median", "worst", "refused"]
        cols += ["future"] if fut is not None else []
        print("| " + " | ".join(cols) + " |")
        print("|" + "---|" * len(cols))
        per = {}
        for m in methods:
            vals: list[float | None] = []
            for o in inside:
                f = fits.get((m, o))
                seg = None if f is None else f.get("seg")
                vals.append(None if seg is None else rms(seg, [bounds.index(o)]))
            # a refused fit leaves no model: counted apart, the statistics are over the models
            ok = [v for v in vals if v is not None]
            med = float(np.median(ok)) if ok else None
            worst = max(ok) if ok else None
            fv = None
            if fut is not None:
                f = fits.get((m, fut))
                if f is not None and f.get("seg") is not None:
                    i = bounds.index(fut)
                    j = bounds.index(cycles[k][1])
                    fv = rms(f["seg"], list(range(i, j)))
            refused = sum(v is None for v in vals)
            row = [METHODS[m], *(fmt(v) for v in vals), fmt(med), fmt(worst), str(refused)]
            print("| " + " | ".join([*row, *([fmt(fv)] if fut is not None else [])]) + " |")
            # the origins whose past holds two whole cycles or more (fewer: a one-cycle log's
            # blocks decide the product's choice)
            two = [
                v for o, v in zip(inside, vals, strict=True) if o >= cycles[1][1] and v is not None
            ]
            per[m] = {
                "worst_2cycles_um": max(two) if two else None,
                "origins_h": [round(t[o] / 3600, 2) for o in inside],
                "rms_um": vals,
                "median_um": med,
                "worst_um": worst,
                "refused": refused,
                "future_um": fv,
            }
        out[k] = per
    for m in methods:
        if m in ("today", "new"):
            picks = [
                f"{t[o] / 3600:.1f}h:{(fits.get((m, o)) or {}).get('chosen') or 'refused'}"
                for o in origins
            ]
            print(f"{METHODS[m]} chose: " + ", ".join(picks))
            errs = {
                f"{t[o] / 3600:.1f}h": (fits.get((m, o)) or {}).get("error")
                for o in origins
                if (fits.get((m, o)) or {}).get("error")
            }
            for h, e in errs.items():
                print(f"  {h}: {e}")
    return out


def summary(result: dict, prefixes: list[int], methods: list[str]) -> None:
    """Per channel and method: median / worst over the origins of each prefix, the next cycle's
    RMS after it in brackets, refused folds after a +."""
    print("\n## Summary: median / worst RMS [um] over the origins (future: the next cycle)")
    cols = ["channel", "method", *(f"{k} cycles" for k in prefixes)]
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for ch, per in result.items():
        for m in methods:
            cells = []
            for k in prefixes:
                r = per[k][m]
                c = f"{fmt(r['median_um'])} / {fmt(r['worst_um'])}"
                if r["future_um"] is not None or k < 5:
                    c += f" ({fmt(r['future_um'])})"
                if r["refused"]:
                    c += f" +{r['refused']} ref."
                cells.append(c)
            print(f"| {ch} | {METHODS[m]} | " + " | ".join(cells) + " |")


def checks(result: dict, prefixes: list[int]) -> list[str]:
    """The acceptance checks, one line each."""
    lines = []
    for ch, per in result.items():
        for k in prefixes:
            p = per.get(k, {})
            if "new" in p and "ridge" in p:
                n, r = p["new"]["worst_um"], p["ridge"]["worst_um"]
                gone = p["new"]["refused"]
                ok = not gone and n is not None and r is not None and n <= 1.10 * r
                lines.append(
                    f"{'PASS' if ok else 'FAIL'} {ch} k={k}: new worst {fmt(n)} <= 1.10 x "
                    f"ridge worst {fmt(r)} ({fmt(1.10 * r if r is not None else None)})"
                    + (f"; new refused {gone} fold(s)" if gone else "")
                )
        p = per.get(5, {})
        if "new" in p and "ridge" in p:
            n, r = p["new"]["worst_2cycles_um"], p["ridge"]["worst_2cycles_um"]
            ok = n is not None and r is not None and n <= 1.10 * r
            lines.append(
                f"{'pass' if ok else 'fail'} {ch} k=5, origins with >= 2 cycles of past only: "
                f"new worst {fmt(n)} <= 1.10 x ridge worst {fmt(r)}"
            )
        if "new" in p and "today" in p:
            new, old = p["new"]["rms_um"], p["today"]["rms_um"]
            both = [i for i, (a, b) in enumerate(zip(new, old, strict=True)) if None not in (a, b)]
            for stat, f in (("median", np.median), ("worst", max)):
                n, o = p["new"][f"{stat}_um"], p["today"][f"{stat}_um"]
                # also on the folds where both gave a model: today's refusals favour neither
                pn = float(f([new[i] for i in both])) if both else None
                po = float(f([old[i] for i in both])) if both else None
                # "meets": within 1 %, the rounding of two codes running the same structure
                ok = (
                    not p["new"]["refused"]
                    and n is not None
                    and (o is None or n <= 1.01 * o)
                    and (pn is None or po is None or pn <= 1.01 * po)
                )
                lines.append(
                    f"{'PASS' if ok else 'FAIL'} {ch} k=5: new {stat} {fmt(n)} <= today's "
                    f"{fmt(o)}; on the {len(both)} folds both fitted {fmt(pn)} <= {fmt(po)} "
                    f"(refused: today {p['today']['refused']}, new {p['new']['refused']} "
                    f"of {len(old)})"
                )
    return lines


def main() -> int:
    if len(sys.argv) == 4 and sys.argv[1] == "--simulate":
        simulate_main(sys.argv[2], sys.argv[3])
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--channels", default=",".join(CHANNELS))
    ap.add_argument("--prefixes", default="2,3,4,5")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--jobs", type=int, default=1, help="product fits run at once")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--data", help="folder of ch*_train.csv (default: written from tests/data)")
    ap.add_argument("--cache", default="/tmp/bench_forward_choice.json")
    ap.add_argument("--today-tree", default="/tmp/wt763")
    args = ap.parse_args()
    channels = [c for c in args.channels.split(",") if c]
    prefixes = sorted({int(k) for k in args.prefixes.split(",") if k})
    methods = [m for m in METHODS if m in args.methods.split(",")]
    if bad := [c for c in channels if c not in CHANNELS]:
        raise SystemExit(f"unknown channel(s): {', '.join(bad)}")
    if any(k < 2 or k > 5 for k in prefixes):
        raise SystemExit("prefixes are 2..5 cycles")
    sys.path.insert(0, str(ROOT))
    data = Path(args.data) if args.data else Path(tempfile.gettempdir()) / "fwdchoice-data"
    if not all((data / f"{c}_train.csv").is_file() for c in channels):
        runpy.run_path(str(ROOT / "tests/data/real-spindle/channels.py"))["write_channels"](data)
    trees = {"today": Path(args.today_tree), "new": ROOT}
    if "today" in methods:
        ensure_today(trees["today"])
    keys: dict[str, str] = {m: code_key(trees[m]) for m in ("today", "new") if m in methods}
    paper_src = (ROOT / "calibration" / "estimators" / "paper_ols.py").read_bytes()
    keys |= {
        "ridge": RIDGE_VERSION,
        "paper": f"{PAPER_VERSION}+{hashlib.sha1(paper_src).hexdigest()[:10]}",
    }
    cache = Cache(Path(args.cache))
    print(f"machine: {os.cpu_count()} cores (shared), OPENBLAS_NUM_THREADS=1; jobs {args.jobs}")
    print(f"code: today {keys.get('today', '-')} at {trees['today']}; new {keys.get('new', '-')}")

    infos: dict[str, dict[str, Any]] = {}
    todo = []
    for ch in channels:
        path = data / f"{ch}_train.csv"
        d = read_csv(path)
        cyc = cycles_of(d)
        bounds = grid(d["time_s"], cyc)
        infos[ch] = {"d": d, "path": path, "cycles": cyc, "bounds": bounds, "t": d["time_s"]}
        last = cyc[max(prefixes) - 1][1]
        for o in origins_of(bounds, cyc):
            if o < last or (o == last and o < d["time_s"].size):
                for m in methods:
                    todo.append((m, ch, o))
    fits: dict = {ch: {} for ch in channels}
    xcols = {ch: ridge_columns(infos[ch]["d"]) for ch in channels if "ridge" in methods}

    def run(job: tuple[str, str, int]) -> None:
        m, ch, o = job
        key = f"{m}|{keys[m].split('~')[-1]}|{ch}|{o}"
        hit = cache.get(key)
        if hit is None:
            info = infos[ch]
            t0 = time.perf_counter()
            if m == "ridge":
                hit = fit_ridge(info["d"], xcols[ch], info["bounds"], o)
            elif m == "paper":
                hit = fit_paper(info["d"], info["bounds"], o)
            else:
                y = info["d"]["elongation_um"]
                hit = fit_product(trees[m], info["path"], o, info["bounds"], y)
            hit["wall_s"] = round(time.perf_counter() - t0, 1)
            cache.put(key, hit)
            print(
                f"  fitted {m} {ch} origin {o}: {hit.get('chosen')} "
                f"{hit.get('error') or ''} ({hit['wall_s']} s)",
                file=sys.stderr,
                flush=True,
            )
        fits[ch][(m, o)] = hit

    quick = [j for j in todo if j[0] in ("ridge", "paper")]
    slow = [j for j in todo if j[0] not in ("ridge", "paper")]
    for j in quick:
        run(j)
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        list(pool.map(run, slow))

    result = {}
    for ch in channels:
        info = infos[ch]
        print(f"\n## {ch}: cycles {info['cycles']}")
        result[ch] = table(ch, info, fits[ch], prefixes, methods)
    summary(result, prefixes, methods)
    print("\n## Acceptance checks")
    lines = checks(result, prefixes)
    for line in lines or ["(need the new choice with the ridge, and today's, to check)"]:
        print(line)
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                finite(
                    {
                        "code": keys,
                        "channels": {
                            ch: {str(k): v for k, v in r.items()} for ch, r in result.items()
                        },
                        "checks": lines,
                        "choices": {
                            ch: {f"{m}@{o}": f.get("chosen") for (m, o), f in fits[ch].items()}
                            for ch in channels
                        },
                    }
                ),
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
