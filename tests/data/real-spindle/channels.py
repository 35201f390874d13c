"""Write the real 40 h record as one run log per displacement channel (tests and benchmarks)."""

from __future__ import annotations

import csv
import gzip
import sys
from pathlib import Path

RECORD = Path(__file__).with_name("real40h.csv.gz")
CHANNELS = ("ch1", "ch2", "ch3", "ch4", "ch5")


def write_channels(out_dir: str | Path, channels: tuple[str, ...] = CHANNELS) -> dict[str, Path]:
    """``{channel: path}`` of run logs ``time_s,speed_rpm,elongation_um,temp1_c,...``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with gzip.open(RECORD, "rt", newline="") as fh:
        rows = list(csv.reader(fh))
    head, body = rows[0], rows[1:]
    temps = [i for i, h in enumerate(head) if h.startswith("temp")]
    paths = {}
    for ch in channels:
        j = head.index(f"{ch}_um")
        path = out / f"{ch}_train.csv"
        with open(path, "w", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(["time_s", "speed_rpm", "elongation_um", *(head[i] for i in temps)])
            for r in body:
                w.writerow([r[0], r[1], r[j], *(r[i] for i in temps)])
        paths[ch] = path
    return paths


if __name__ == "__main__":
    for ch, p in write_channels(sys.argv[1] if len(sys.argv) > 1 else ".").items():
        print(ch, p)
