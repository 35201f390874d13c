"""Fitting 600 000 rows, and replaying a 30-day 1 Hz log (2.6 M rows) end to end.

Targets: OLS fit <= 2 s; replay <= 3 s, parsing included. Every replay
also runs the runtime's shaper over the log, and by default compares the transient policies
(two more shaped series with a dual-slew configuration): timed apart.
Run: .venv/bin/python bench/bench_fit_replay.py
"""

from __future__ import annotations

import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from conftest import rich_form  # noqa: E402

from calibration.estimators import paper_ols  # noqa: E402
from calibration.fit import fit_data  # noqa: E402
from calibration.identify import LogData  # noqa: E402
from calibration.replay import replay  # noqa: E402
from compensator.io import read_run_log, save_model, write_run_log  # noqa: E402
from compensator.speed_programs import job_shop_day  # noqa: E402


def month_of_speeds(days: int = 30) -> tuple[np.ndarray, np.ndarray]:
    parts = []
    for d in range(days):
        _, n = job_shop_day(27000, seed=d, hours=8).sample(1.0)
        parts.append(n[: 9 * 3600])
        parts.append(np.zeros(86400 - min(n.size, 9 * 3600)))
    n = np.concatenate(parts)
    return np.arange(n.size, dtype=float), n


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def main() -> dict:
    res: dict = {}
    model = rich_form()
    rng = np.random.default_rng(0)
    # 600 000 rows: a week of 1 Hz calibration data, three runs
    t, n = month_of_speeds(7)
    t, n = t[:600_000], n[:600_000]
    s = model.simulate(n, t).elongation_um + rng.normal(0, 0.05, t.size)
    runs = [
        LogData(
            f"r{i}",
            np.arange(200_000, dtype=float),
            n[i * 200_000 : (i + 1) * 200_000],
            s[i * 200_000 : (i + 1) * 200_000],
        )
        for i in range(3)
    ]
    res["fit_rows"] = sum(r.time_s.size for r in runs)
    res["ols_fit_s"], _ = timed(lambda: paper_ols.fit_paper_ols(t, n, s))
    res["full_calibration_s"], cal = timed(lambda: fit_data(runs))
    res["full_calibration_chosen"] = cal.chosen.name

    t, n = month_of_speeds(30)
    meas = model.simulate(n, t).elongation_um + rng.normal(0, 0.05, t.size)
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "month.csv"
        mfile = Path(tmp) / "m.json"
        save_model(mfile, model)
        res["write_log_s"], _ = timed(
            lambda: write_run_log(
                log, {"time_s": t, "speed_rpm": n, "elongation_um": np.round(meas, 2)}
            )
        )
        res["replay_rows"] = int(t.size)
        res["parse_s"], parsed = timed(lambda: read_run_log(log))
        res["replay_model_s"], _ = timed(lambda: model.simulate_um(parsed.speed_rpm, parsed.time_s))
        res["replay_shaped_s"], _ = timed(lambda: replay(model, parsed, compare=False))
        res["replay_compute_s"], rep = timed(lambda: replay(model, parsed))
        res["shaping_us_per_sample"] = (
            1e6 * (res["replay_shaped_s"] - res["replay_model_s"]) / t.size
        )
        res["replay_end_to_end_s"] = res["parse_s"] + res["replay_compute_s"]
        res["write_predictions_s"], _ = timed(
            lambda: write_run_log(Path(tmp) / "p.csv", rep.columns())
        )
        t0 = time.perf_counter()
        subprocess.run(
            [
                sys.executable,
                "-m",
                "thermocomp",
                "replay",
                "--model",
                str(mfile),
                str(log),
                "--json",
            ],
            check=True,
            capture_output=True,
        )
        res["replay_cli_wall_s"] = time.perf_counter() - t0
        res["replay_rms_um"] = rep.report["rms_residual_um"]
    return res


if __name__ == "__main__":
    r = main()
    print(f"# {platform.machine()}, Python {platform.python_version()}, numpy {np.__version__}")
    for k, v in r.items():
        print(f"{k:28s} {v:.3f}" if isinstance(v, float) else f"{k:28s} {v}")
    print(json.dumps(r))
