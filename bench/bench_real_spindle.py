"""``thermocomp fit`` on the real 40 h record, every channel: the README's per-channel table and
the fit time with 16 inputs on one core.

Target (issue 16): the fit on the 40 h with 16 inputs in <= 60 s on one core.
Every figure is leave-one-cycle-out free run (five cycles); "nested" means the held-out cycle
also took no part in choosing alpha.
Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_real_spindle.py [--quick]
(--quick: ch1 and ch3 only).
"""

from __future__ import annotations

import json
import os
import platform
import resource
import runpy
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHANNELS = runpy.run_path(str(ROOT / "tests/data/real-spindle/channels.py"))["write_channels"]
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def fit(log: Path, out: Path, *extra: str) -> tuple[dict, float, float]:
    """The report, wall time and CPU time (user + system of the child) of one ``fit``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "thermocomp",
            "fit",
            str(log),
            "--output",
            str(out),
            "--json",
            *extra,
        ],
        capture_output=True,
        text=True,
        env=ENV,
        cwd=ROOT,
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if r.returncode != 0:
        raise SystemExit(r.stderr)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return json.loads(r.stdout), wall, cpu


def cand(rep: dict, name: str) -> dict:
    return next(c for c in rep["candidates"] if c["name"] == name)


def cell(c: dict, nested: bool = False) -> str:
    rms = c["nested_rms_um"] if nested and c["nested_rms_um"] is not None else c["cv_rms_um"]
    mx = (
        c["nested_max_abs_um"]
        if nested and c["nested_max_abs_um"] is not None
        else c["cv_max_abs_um"]
    )
    return f"{rms:.2f} / {mx:.2f}"


def main() -> None:
    quick = "--quick" in sys.argv
    channels = ("ch1", "ch3") if quick else ("ch1", "ch2", "ch3", "ch4", "ch5")
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"Python {platform.python_version()}, one BLAS thread"
    )
    rows, timing = [], []
    with tempfile.TemporaryDirectory() as tmp:
        logs = CHANNELS(tmp, channels)
        for ch in channels:
            sp, _, _ = fit(logs[ch], Path(tmp) / f"{ch}-speed.json")
            wt, wall, cpu = fit(logs[ch], Path(tmp) / f"{ch}-temps.json", "--inputs", "all")
            timing.append((ch, wall, cpu, wt["fit_cpu_s"]))
            chosen = cand(sp, sp["chosen"])
            rows.append(
                (
                    ch,
                    f"{sp['chosen']}: {cell(chosen, True)}",
                    cell(cand(sp, "exp-baseline"), True),
                    cell(cand(sp, "physical")),
                    cell(cand(sp, "ridge"), True),
                    f"{wt['chosen']}: {cell(cand(wt, wt['chosen']), True)}",
                    cell(cand(wt, "ridge+inputs")),
                    cell(cand(sp, "paper-ols")),
                )
            )
            print(f"{ch}: done ({wall:.1f} s wall with 16 inputs)", flush=True)
    print(
        "\n| channel | speed only, chosen (nested) | exp. baseline (nested) | physical form | ridge, speed (nested) "
        "| with 16 temperatures, chosen (nested) | ridge + temps (LOCO) | paper's OLS |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")
    print("\nRMS / max um, leave-one-cycle-out free run over the five cycles.")
    print("\n| channel | fit with 16 inputs: wall s | CPU s (process) | CPU s (in the fit) |")
    print("|---|---|---|---|")
    for ch, wall, cpu, inner in timing:
        print(f"| {ch} | {wall:.1f} | {cpu:.1f} | {inner:.1f} |")
    worst = max(t[2] for t in timing)
    print(
        f"\nslowest fit with 16 inputs: {worst:.1f} s CPU (target <= 60 s): {'ok' if worst <= 60 else 'MISSED'}"
    )


if __name__ == "__main__":
    main()
