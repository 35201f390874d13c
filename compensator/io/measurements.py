"""Measurements files: tool-setter or probe measurements to fuse in replay.

CSV with a header, ``#`` comment lines allowed::

    time_s,elongation_um[,sigma_um,...]

``time_s`` on the log's clock [s], increasing; ``elongation_um`` the measured elongation [um]
(positive: the tool grew toward the workpiece); ``sigma_um`` > 0 its standard deviation [um]
(default: the caller's). Other columns are ignored, so the runtime's measurement journal
(:class:`~compensator.io.journal.MeasurementJournal`) is a measurements file; its rows whose
``outcome`` is ``refused`` (no usable value) are skipped.
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass

import numpy as np

from compensator.errors import RunLogError


@dataclass(frozen=True)
class Measurements:
    time_s: np.ndarray
    elongation_um: np.ndarray
    sigma_um: np.ndarray
    source: str
    sources: tuple[str, ...] = ()
    """Each row's ``source`` column (the service's journal names the probe or the control
    socket), where the file has one: the observer bounds each source's moves apart."""


def _number(text: str, col: str, src: str, line: int) -> float:
    try:
        v = float(text)
    except ValueError as err:
        raise RunLogError(f"column {col}: {text.strip()!r} is not a number", src, line) from err
    if not math.isfinite(v):
        raise RunLogError(f"column {col}: {text.strip()} is not a finite number", src, line)
    return v


def read_measurements(path: str | os.PathLike[str], default_sigma_um: float) -> Measurements:
    """Read a measurements file; :class:`RunLogError` naming file and line on any fault."""
    src = os.fspath(path)
    times: list[float] = []
    values: list[float] = []
    sigmas: list[float] = []
    sources: list[str] = []
    try:
        with open(src, newline="", encoding="utf-8") as fh:
            rows = (
                (n, r)
                for n, r in enumerate(csv.reader(fh), start=1)
                if r and not r[0].lstrip().startswith("#")
            )
            try:
                line, header = next(rows)
            except StopIteration:
                raise RunLogError(
                    "empty file (expected time_s,elongation_um[,sigma_um])", src
                ) from None
            cols = [c.strip() for c in header]
            missing = [c for c in ("time_s", "elongation_um") if c not in cols]
            if missing:
                raise RunLogError(
                    f"missing column(s) {', '.join(missing)} in header {','.join(cols)}", src, line
                )
            it, iy = cols.index("time_s"), cols.index("elongation_um")
            isg = cols.index("sigma_um") if "sigma_um" in cols else None
            io = cols.index("outcome") if "outcome" in cols else None
            isrc = cols.index("source") if "source" in cols else None
            for line, row in rows:
                if len(row) != len(cols):
                    raise RunLogError(
                        f"{len(row)} fields where the header has {len(cols)}", src, line
                    )
                if io is not None and row[io].strip() == "refused":
                    continue
                t = _number(row[it], "time_s", src, line)
                y = _number(row[iy], "elongation_um", src, line)
                s = (
                    default_sigma_um
                    if isg is None or not row[isg].strip()
                    else _number(row[isg], "sigma_um", src, line)
                )
                if s <= 0:
                    raise RunLogError(f"column sigma_um: {s:g} must be > 0", src, line)
                if times and t <= times[-1]:
                    raise RunLogError(f"column time_s: {t:g} does not increase", src, line)
                times.append(t)
                values.append(y)
                sigmas.append(s)
                if isrc is not None:
                    sources.append(row[isrc].strip() or "measurement")
    except OSError as err:
        raise RunLogError(f"cannot read: {err.strerror or err}", src) from err
    except UnicodeError as err:
        raise RunLogError("not a text file", src) from err
    except csv.Error as err:
        raise RunLogError(f"malformed CSV: {err}", src) from err
    if not times:
        raise RunLogError("no measurements", src)
    return Measurements(np.array(times), np.array(values), np.array(sigmas), src, tuple(sources))
