"""The spindle thermal test in the terms of ISO 230-3, from a recorded run, beside the product's
own figures. Pure: arrays in, figures out.

ISO 230-3:2020 (Test code for machine tools, Part 3: Determination of thermal effects) defines a
test of the thermal distortion caused by rotating spindles: the displacement of the tool relative
to the table is recorded while the spindle runs, at a constant speed or through a spectrum of
speeds, and then while it stands still; the result is the drift, the largest change of each
displacement from its value at the start of the test (the drift test procedure of ISO/TR 16015,
A.4.2). A calibration run of thermocomp is such a test: a staircase of speeds (a spectrum), then a
rest. One axial sensor measures the drift along Z (the spindle axis) only: X, Y and the tilts need
sensors of their own and are reported as not measured.

Beside the machine's own drift the report gives what remains of it with thermocomp's offset: the
same figures of measured minus predicted growth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .folds import IDLE_RPM


@dataclass(frozen=True)
class Drift:
    """The drift along Z [um] over the running part of the test and over the rest after it."""

    running_um: float
    """Largest |change| from the start while the spindle ran (signed: the change of largest size)."""
    running_at_s: float
    """When it was reached, from the start of the test [s]."""
    rest_um: float | None
    """Change over the rest after the last running segment (None without a rest)."""
    range_um: float
    """Largest minus smallest value over the whole test."""


@dataclass(frozen=True)
class SpindleThermalTest:
    """The test as run, and the drift without and with compensation."""

    kind: str
    """``constant speed`` or ``speed spectrum``."""
    speeds_rpm: tuple[float, ...]
    """The speed levels held (rounded to 100 rpm)."""
    running_s: float
    rest_s: float
    machine: Drift
    compensated: Drift | None


def _drift(
    time_s: np.ndarray, z_um: np.ndarray, running: np.ndarray, rest_from: int | None
) -> Drift:
    # a tool-setter log has no value on its first row: its measurements are from the cold
    # reference the cycle took before the start, so the start is zero
    z = z_um - (z_um[0] if np.isfinite(z_um[0]) else 0.0)
    ok = np.isfinite(z)
    run = running & ok
    k = int(np.argmax(np.where(run, np.abs(z), -1.0))) if run.any() else 0
    rest = None
    if rest_from is not None and ok[rest_from:].any():
        tail = z[rest_from:][ok[rest_from:]]
        rest = float(tail[-1] - tail[0])
    return Drift(
        float(z[k]), float(time_s[k] - time_s[0]), rest, float(np.ptp(z[ok])) if ok.any() else 0.0
    )


def spindle_thermal_test(
    time_s: np.ndarray,
    speed_rpm: np.ndarray,
    z_um: np.ndarray,
    predicted_um: np.ndarray | None = None,
) -> SpindleThermalTest:
    """The test's figures from a run: ``z_um`` the measured growth along the spindle axis (NaN
    where not measured), ``predicted_um`` the model's free run over the same rows (the
    compensated drift is ``z - predicted``)."""
    t = np.asarray(time_s, float)
    n = np.abs(np.asarray(speed_rpm, float))
    z = np.asarray(z_um, float)
    if t.size < 2 or z.shape != t.shape or n.shape != t.shape:
        raise ValueError("one time, speed and displacement per row, two rows or more")
    running = n > IDLE_RPM
    turned = np.flatnonzero(running)
    rest_from = int(turned[-1]) + 1 if turned.size and turned[-1] + 1 < t.size else None
    # measured only at stops (the tool setter): the running part of the test is from the first
    # start to the last stop of the spindle, the probe stops inside it included
    part = running.copy()
    if turned.size and not np.isfinite(z).all():
        part[turned[0] : turned[-1] + 1] = True
    dt = np.diff(t, prepend=t[0])
    levels = np.unique(np.round(n[running], -2)) if running.any() else np.zeros(0)
    # a level held for less than a minute is a ramp passing through, not a level of the test
    held = tuple(float(v) for v in levels if dt[running & (np.round(n, -2) == v)].sum() >= 60.0)
    comp = None
    if predicted_um is not None:
        comp = _drift(t, z - np.asarray(predicted_um, float), part, rest_from)
    return SpindleThermalTest(
        "constant speed" if len(held) == 1 else "speed spectrum",
        held,
        float(dt[running].sum()),
        float(dt[~running][1:].sum()) if (~running).any() else 0.0,
        _drift(t, z, part, rest_from),
        comp,
    )


def report_rows(runs: dict[str, SpindleThermalTest]) -> list[list[str]]:
    """One table for the calibration report: per run, the drift along Z without and with
    compensation; X, Y and tilts as not measured."""

    def f(v: float | None) -> str:
        return "-" if v is None else f"{v:+.2f}"

    rows = [
        [
            "run",
            "test",
            "speeds [rpm]",
            "running / rest [h]",
            "drift Z running [um]",
            "at [h]",
            "drift Z over the rest [um]",
            "range Z [um]",
        ]
    ]
    for name, r in runs.items():
        levels = (
            f"{r.speeds_rpm[0]:.0f}"
            if len(r.speeds_rpm) == 1
            else f"{len(r.speeds_rpm)} levels, {min(r.speeds_rpm):.0f}-{max(r.speeds_rpm):.0f}"
            if r.speeds_rpm
            else "-"
        )
        common = [r.kind, levels, f"{r.running_s / 3600:.2f} / {r.rest_s / 3600:.2f}"]
        for label, d in (("machine", r.machine), ("with thermocomp", r.compensated)):
            if d is None:
                continue
            rows.append(
                [
                    f"{name}: {label}",
                    *common,
                    f(d.running_um),
                    f"{d.running_at_s / 3600:.2f}",
                    f(d.rest_um),
                    f"{d.range_um:.2f}",
                ]
            )
    rows.append(["X, Y and the tilts", "not measured: one axial sensor", "", "", "", "", "", ""])
    return rows
