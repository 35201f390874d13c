"""Real processes for the fault-injection suite: the virtual CNC and the service as
subprocesses, an asyncua client for outside reads and writes, and the journal and JSON-log
readers and invariant checks every case shares.

Waiting is always a ``time.monotonic`` deadline with polling; a fixed sleep only paces a
fault (how long a controller stays stopped), never decides an assertion.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from compensator import ThermalModel, ThermalStateCoefficients
from compensator.io import read_run_log
from machine_sim.vcnc import NAMESPACE_URI, NODE_PATHS, free_port
from thermocomp.runtime import Alarm

PYTHON = sys.executable
OFFSET_NODE = NODE_PATHS["thermal_offset"]
COLUMNS = (
    "time_s",
    "speed_rpm",
    "predicted_um",
    "offset_um",
    "written",
    "flags",
    "alarms",
    "dt_s",
    "wall_s",
)
SPEED_RPM = 20000.0
"""The virtual CNC holds this speed (``hold.ngc``); every model here grows 30 um at it."""


class Timeout(AssertionError):
    pass


def wait_for(pred: Callable[[], Any], timeout: float, what: str, poll: float = 0.05) -> Any:
    """Poll ``pred`` until it returns something truthy, or fail naming ``what``."""
    end = time.monotonic() + timeout
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() > end:
            raise Timeout(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(poll)


# -- models and programs ---------------------------------------------------------------


def spindle_model(tau_s: float, steady_um: float = 30.0) -> ThermalModel:
    """One thermal state with time constant ``tau_s`` that settles at ``steady_um`` at
    20 000 rpm (40.5 um at the 27 000 rpm top of its range: plausible)."""
    lam = 1.0 / tau_s
    return ThermalModel(
        fitted_dt_s=1.0,
        speed_range_rpm=(0.0, 27000.0),
        states=(
            ThermalStateCoefficients(
                dissipation_per_s=(lam, 0.0),
                generation_um_per_s=(0.0, steady_um * lam / 20.0, 0.0, 0.0),
            ),
        ),
    )


HOLD_NC = "%\n(thermocomp fault suite: one speed, held)\nS20000 M3\nG4 P1000000\nM2\n%\n"


# -- configuration ---------------------------------------------------------------------


def _toml(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, (str, os.PathLike)):
        return json.dumps(os.fspath(v))
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + "}"
    raise TypeError(v)


DEFAULT_SHAPING = {"max_offset_um": 60.0, "max_rate_um_per_s": 100.0, "deadband_um": 0.1}
DEFAULT_FAULTS = {
    "max_outage_s": 1.0,
    "readback_every": 2,
    "speed_hold_s": 0.5,
    "state_retry_s": 0.25,
    "max_write_backoff_s": 1.0,
    "state_stale_s": 1.5,
}


@dataclass
class Setup:
    """One case's files and settings; :meth:`write` (re)writes the TOML."""

    root: Path
    model: Path
    adapter: dict[str, Any]
    period_s: float = 0.25
    save_every_s: float = 0.5
    shaping: dict[str, Any] = field(default_factory=dict)
    faults: dict[str, Any] = field(default_factory=dict)

    @property
    def config(self) -> Path:
        return self.root / "machine.toml"

    @property
    def state_dir(self) -> Path:
        return self.root / "state"

    @property
    def journal_dir(self) -> Path:
        return self.state_dir / "journal"

    @property
    def state_file(self) -> Path:
        return self.state_dir / "s1.state.json"

    @property
    def log_file(self) -> Path:
        return self.root / "log.jsonl"

    @property
    def sh(self) -> dict[str, Any]:
        return {**DEFAULT_SHAPING, **self.shaping}

    @property
    def clamp(self) -> float:
        return float(self.sh["max_offset_um"])

    @property
    def rate(self) -> float:
        return float(self.sh["max_rate_um_per_s"])

    @property
    def deadband(self) -> float:
        return float(self.sh["deadband_um"])

    def write(self) -> Path:
        fa = {**DEFAULT_FAULTS, **self.faults}
        lines = [
            f"state_dir = {_toml(self.state_dir)}",
            "watchdog = false",
            f"log_file = {_toml(self.log_file)}",
            "journal_fsync_s = 1.0",
            "[[spindle]]",
            'name = "s1"',
            f"model = {_toml(self.model)}",
            f"period_s = {self.period_s!r}",
            f"state_save_every_s = {self.save_every_s!r}",
            f"adapter = {_toml(self.adapter)}",
            "[spindle.shaping]",
            *(f"{k} = {_toml(v)}" for k, v in self.sh.items()),
            "[spindle.shaping.transient]",
            "enabled = false",
            "[spindle.faults]",
            *(f"{k} = {_toml(v)}" for k, v in fa.items()),
        ]
        tmp = self.config.with_suffix(".tmp")
        tmp.write_text("\n".join(lines) + "\n")
        os.replace(tmp, self.config)  # a SIGHUP never reads half a file
        return self.config


# -- the virtual CNC as a process ----------------------------------------------------------


class VirtualCncProcess:
    """``thermocomp virtual-cnc`` on a free loopback port, at 1x, holding 20 000 rpm. Its drive
    reaches a speed at once: a restarted controller finds the spindle turning, and these cases
    are about the link, the disk and signals, not the run-up."""

    def __init__(self, workdir: Path, port: int | None = None):
        self.workdir = workdir
        self.port = port or free_port()
        self.url = f"opc.tcp://127.0.0.1:{self.port}/thermocomp/virtual-cnc/"
        self.program = workdir / "hold.ngc"
        self.program.write_text(HOLD_NC)
        self.out = workdir / "vcnc.out"
        self.proc: subprocess.Popen | None = None
        self.stopped = False
        self.starts = 0

    def start(self) -> None:
        """Start a new process (a fresh controller: it holds offset 0); do not wait."""
        self.starts += 1
        with open(self.out, "w") as fh:
            self.proc = subprocess.Popen(
                [
                    PYTHON,
                    "-m",
                    "thermocomp",
                    "virtual-cnc",
                    "--port",
                    str(self.port),
                    "--time-scale",
                    "1",
                    "--program",
                    str(self.program),
                    "--accel-rpm-per-s",
                    "1e9",
                ],
                stdout=fh,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
        self.stopped = False

    def ready(self) -> bool:
        assert self.proc is not None
        if self.proc.poll() is not None:
            raise AssertionError(
                f"virtual CNC exited {self.proc.returncode}: {self.out.read_text()[-2000:]}"
            )
        return "virtual CNC (" in self.out.read_text()

    def wait_ready(self, timeout: float = 120.0) -> float:
        t0 = time.monotonic()
        wait_for(self.ready, timeout, "the virtual CNC to listen", poll=0.05)
        return time.monotonic() - t0

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            if self.stopped:
                self.cont()
            self.proc.kill()
            self.proc.wait(30)

    def sigstop(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGSTOP)
        self.stopped = True

    def cont(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
        self.stopped = False

    def ensure(self) -> None:
        """Running, listening and holding offset 0, whatever the last case did to it."""
        if self.stopped:
            self.cont()
        if self.proc is None or self.proc.poll() is not None:
            self.start()
        self.wait_ready()
        self.write_offset(0.0)

    # an outside client: what an operator's HMI or another program would do
    def _node(self, fn):
        from asyncua import Client, ua

        async def go():
            client = Client(self.url, timeout=5)
            await client.connect()
            try:
                ns = await client.get_namespace_index(NAMESPACE_URI)
                node = client.get_node(f"ns={ns};s={OFFSET_NODE}")
                return await fn(node, ua)
            finally:
                with contextlib.suppress(Exception):
                    await client.disconnect()

        return asyncio.run(asyncio.wait_for(go(), 20))

    def read_offset(self) -> float:
        async def read(node, ua):
            return float(await node.read_value())

        return self._node(read)

    def write_offset(self, value: float) -> None:
        async def write(node, ua):
            await node.write_value(ua.DataValue(ua.Variant(float(value), ua.VariantType.Double)))

        self._node(write)

    def close(self) -> None:
        self.kill()


# -- the service as a process ----------------------------------------------------------------


class ServiceProcess:
    """``thermocomp run --config`` as a subprocess, with its journal and JSON log."""

    def __init__(
        self,
        setup: Setup,
        *,
        preexec_fn: Callable[[], None] | None = None,
        env: Mapping[str, str] | None = None,
        tag: str = "svc",
    ):
        self.setup = setup
        self.stderr_path = setup.root / f"{tag}.stderr"
        with open(self.stderr_path, "w") as err:
            self.proc = subprocess.Popen(
                [PYTHON, "-m", "thermocomp", "run", "--config", str(setup.config)],
                stdout=subprocess.DEVNULL,
                stderr=err,
                stdin=subprocess.DEVNULL,
                # preexec_fn: only a setrlimit, async-signal-safe enough for the fork
                preexec_fn=preexec_fn,
                env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
            )
        self.t_start = time.monotonic()
        self.pid = self.proc.pid

    @property
    def stderr(self) -> str:
        return self.stderr_path.read_text() if self.stderr_path.exists() else ""

    def alive(self) -> bool:
        return self.proc.poll() is None

    def check_alive(self) -> None:
        if not self.alive():
            raise AssertionError(
                f"the service exited {self.proc.returncode}: {self.stderr[-3000:]}"
            )

    def rows(self) -> dict[str, np.ndarray]:
        self.check_alive()
        return live_rows(self.setup.journal_dir)

    def events(self) -> list[dict[str, Any]]:
        return read_events(self.setup.log_file)

    def wait_rows(self, n: int, timeout: float = 60.0) -> dict[str, np.ndarray]:
        return wait_for(
            lambda: (r := self.rows()) and len(r["time_s"]) >= n and r,
            timeout,
            f"{n} journal rows",
            poll=0.05,
        )

    def wait_event(
        self,
        name: str,
        timeout: float = 30.0,
        after: int = 0,
        where: Callable[[dict[str, Any]], bool] = lambda e: True,
    ) -> dict[str, Any]:
        """The first event ``name`` (after the first ``after`` log records) matching ``where``."""

        def find():
            self.check_alive()
            return next(
                (e for e in self.events()[after:] if e.get("event") == name and where(e)), None
            )

        return wait_for(find, timeout, f"event {name!r}")

    def wait_settled(self, timeout: float = 30.0, n: int = 3) -> dict[str, np.ndarray]:
        """The offset tracks the model (within the deadband) and nothing was written for ``n``
        cycles: the controller holds the model's value."""
        s = self.setup

        def settled():
            r = self.rows()
            if len(r["time_s"]) < n + 2:
                return None
            tail = slice(-n, None)
            want = np.clip(-r["predicted_um"][tail], -s.clamp, s.clamp)
            ok = (
                (np.abs(r["offset_um"][tail] - want) <= s.deadband + 1e-9).all()
                and not r["written"][tail].any()
                and abs(r["offset_um"][-1]) > 1.0
            )
            return r if ok else None

        return wait_for(settled, timeout, "the offset to settle on the model's value")

    def signal(self, sig: int) -> None:
        self.check_alive()
        self.proc.send_signal(sig)

    def stop(self, timeout: float = 30.0) -> int:
        if self.alive():
            self.proc.send_signal(signal.SIGTERM)
        rc = self.proc.wait(timeout)
        return rc

    def kill(self) -> None:
        if self.alive():
            self.proc.kill()
            self.proc.wait(30)


def read_only_dir(path: Path) -> Callable[[], None] | None:
    """Make a directory read-only for the service: ``chmod 0o500`` (root ignores that, so as
    root ``chattr +i``, an immutable directory, where the file system supports it). The undo,
    or None where neither works."""
    if os.geteuid() != 0:
        path.chmod(0o500)
        return lambda: path.chmod(0o755)
    try:
        r = subprocess.run(
            ["chattr", "+i", str(path)], capture_output=True, timeout=30, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    if r.returncode != 0:
        return None
    return lambda: subprocess.run(["chattr", "-i", str(path)], check=True, timeout=30)


READ_ONLY_ERRORS = ("Permission denied", "Operation not permitted", "Read-only file system")


# -- journal and log ---------------------------------------------------------------------------

_PART = re.compile(r"^(?P<name>.+)-(?P<day>\d{4}-\d{2}-\d{2})(?:\.p(?P<part>\d+))?\.csv$")


def journal_parts(journal_dir: Path, name: str = "s1") -> list[Path]:
    """The spindle's journal files in order: by day, then part."""
    out = []
    for p in Path(journal_dir).glob(f"{name}-*.csv"):
        m = _PART.match(p.name)
        if m and m["name"] == name:
            out.append((m["day"], int(m["part"] or 1), p))
    return [p for *_, p in sorted(out)]


def _empty() -> dict[str, np.ndarray]:
    return {c: np.zeros(0) for c in (*COLUMNS, "part")}


def live_rows(journal_dir: Path, name: str = "s1") -> dict[str, np.ndarray]:
    """The complete rows written so far (a row being written is left out), while the
    service runs; the final checks use :func:`read_journal` (``read_run_log``)."""
    rows: list[list[float]] = []
    for k, p in enumerate(journal_parts(journal_dir, name)):
        try:
            text = p.read_text()
        except OSError:
            continue
        for line in text.split("\n")[:-1]:  # the last piece has no newline yet
            if line and line[0].isdigit():
                rows.append([float(x) for x in line.split(",")[: len(COLUMNS)]] + [k])
    if not rows:
        return _empty()
    a = np.array(rows, dtype=float)
    return {c: a[:, i] for i, c in enumerate((*COLUMNS, "part"))}


def read_journal(journal_dir: Path, name: str = "s1") -> dict[str, np.ndarray]:
    """Every part of the journal, read with ``compensator.io.read_run_log``, concatenated."""
    cols: dict[str, list[np.ndarray]] = {c: [] for c in (*COLUMNS, "part")}
    for k, p in enumerate(journal_parts(journal_dir, name)):
        log = read_run_log(p)
        n = len(log)
        cols["time_s"].append(log.time_s)
        cols["speed_rpm"].append(log.speed_rpm)
        for c in COLUMNS[2:]:
            cols[c].append(np.asarray(log.extras[c], dtype=float))
        cols["part"].append(np.full(n, k, dtype=float))
    if not cols["time_s"]:
        return _empty()
    return {c: np.concatenate(v) for c, v in cols.items()}


def read_events(log_file: Path) -> list[dict[str, Any]]:
    """The JSON log's records (complete lines only)."""
    try:
        text = Path(log_file).read_text()
    except FileNotFoundError:
        return []
    out = []
    for line in text.split("\n")[:-1]:
        if line.strip():
            out.append(json.loads(line))
    return out


def named(events: Iterable[dict[str, Any]], *names: str) -> list[dict[str, Any]]:
    return [e for e in events if e.get("event") in names]


def has(alarms: np.ndarray | float, bit: Alarm) -> np.ndarray:
    return (np.asarray(alarms).astype(np.int64) & int(bit)) != 0


# -- invariants ----------------------------------------------------------------------------------


@dataclass
class Checked:
    rows: int
    lost: int
    max_gap_s: float
    runtime_starts: int


def check_invariants(
    j: dict[str, np.ndarray],
    *,
    rate: float,
    clamp: float | np.ndarray,
    events: list[dict[str, Any]],
    period_s: float,
    gap_ok: Callable[[float, float], bool] = lambda w0, w1: False,
    max_gap_periods: float = 8.0,
    one_process: bool = True,
) -> Checked:
    """What must hold on every journal, whatever the fault:

    - every offset is finite;
    - within the clamp on every row written; a value beyond it is only one the controller
      holds (an outside write) until the next write, which steps straight to the clamp;
    - |offset_k - ref| <= max_rate * dt_s_k + 1e-6, ref the previous row's offset (clamped), or, on a row
      that found the controller holding something else (OFFSET_MISMATCH), the value it held
      (the k-th such row goes with the k-th ``offset_mismatch`` event);
    - time_s strictly increasing; no row lost: within one runtime the step between two rows is
      the row's own dt_s (the step the model took), so a row that never reached the disk
      would show; no gap over ``max_gap_periods`` periods unless ``gap_ok(wall0, wall1)``.
    """
    t, off, dt, alarms = j["time_s"], j["offset_um"], j["dt_s"], j["alarms"]
    n = len(t)
    assert n >= 2, "too few journal rows"
    assert np.isfinite(off).all(), f"non-finite offsets at rows {np.flatnonzero(~np.isfinite(off))}"
    assert np.isfinite(j["predicted_um"]).all()
    clamp_a = np.broadcast_to(np.asarray(clamp, dtype=float), off.shape)
    mism = [float(e["held_um"]) for e in named(events, "offset_mismatch")]
    mrows = np.flatnonzero(has(alarms, Alarm.OFFSET_MISMATCH))
    assert len(mrows) == len(mism), (
        f"{len(mrows)} rows with OFFSET_MISMATCH, {len(mism)} offset_mismatch events"
    )
    ref = np.r_[np.nan, off[:-1]]
    ref[mrows] = mism
    # across a process boundary nothing is known about what happened in between
    new_proc = (
        np.r_[True, np.diff(j["part"]) != 0]
        if not one_process
        else np.r_[True, np.zeros(n - 1, bool)]
    )
    back = np.flatnonzero((np.diff(t) <= 0) & ~new_proc[1:]) + 1
    assert back.size == 0, f"time_s not increasing at rows {back}"
    # from a value held beyond the clamp (none of ours) the write steps to the clamp at once
    step = np.abs(off - np.clip(ref, -clamp_a, clamp_a))
    bad = np.flatnonzero(~new_proc & (step > rate * dt + slew_tol(rate, off, ref)))
    assert bad.size == 0, "slew limit broken: " + "; ".join(
        f"row {k}: {ref[k]:.6g} -> {off[k]:.6g} in {dt[k]:.4f} s" for k in bad[:5]
    )
    written = j["written"] == 1
    beyond = np.abs(off) > clamp_a + 1e-9
    for k in np.flatnonzero(beyond):  # only the controller's own value, never one written
        assert not written[k] and (new_proc[k] or off[k] == ref[k]), (
            f"row {k}: offset {off[k]:.6g} beyond the clamp {clamp_a[k]:g} (from {ref[k]:.6g})"
        )
    # rows lost: a runtime's consecutive rows are dt_s apart (3 decimals in time_s)
    within = ~new_proc & (dt > 0)
    lost = int(np.count_nonzero(within & (np.abs(np.r_[0.0, np.diff(t)] - dt) > 1.5e-3)))
    gaps = np.diff(t)
    wall = j["wall_s"]
    # (a runtime's first cycle connects to the controller: the step after it may be long)
    big = [
        k
        for k in np.flatnonzero(gaps > max_gap_periods * period_s)
        if not new_proc[k + 1] and dt[k] != 0 and not gap_ok(wall[k], wall[k + 1])
    ]
    assert not big, "gaps: " + ", ".join(f"{gaps[k]:.2f} s after row {k}" for k in big[:5])
    assert lost == 0, f"{lost} row(s) lost (time steps that are not the row's dt_s)"
    return Checked(
        rows=n,
        lost=lost,
        max_gap_s=float(gaps.max()),
        runtime_starts=int(np.count_nonzero(dt == 0)),
    )


def slew_tol(
    rate: float, a: float | np.ndarray = 0.0, b: float | np.ndarray = 0.0
) -> float | np.ndarray:
    """1e-6 um, plus what the journal's print precision hides: ``dt_s`` has 6 decimals (up to
    0.5 us off, so a full-slew step may look ``rate * 5e-7`` too long) and offsets 9
    significant digits."""
    return 1e-6 + rate * 5e-7 + 5e-9 * (np.abs(a) + np.nan_to_num(np.abs(b)))


def after_event(j: dict[str, np.ndarray], e: dict[str, Any]) -> np.ndarray:
    """Rows of the cycles after event ``e`` (its ``ts`` and the rows' ``wall_s`` are both
    rounded to the millisecond; consecutive rows are a period apart)."""
    return j["wall_s"] >= e["ts"] - 0.002


def tracking(j: dict[str, np.ndarray], clamp: float, deadband: float) -> np.ndarray:
    """Rows where the offset is the model's (-predicted, clamped) within the deadband."""
    want = np.clip(-j["predicted_um"], -clamp, clamp)
    return np.abs(j["offset_um"] - want) <= deadband + 1e-9


def recovered_at(
    j: dict[str, np.ndarray],
    since_wall: float,
    clamp: float,
    deadband: float,
    also: np.ndarray | None = None,
) -> int:
    """Index of the first row at or after ``since_wall`` from which every row tracks the model."""
    ok = tracking(j, clamp, deadband) & (also if also is not None else True)
    tail_bad = np.flatnonzero(~ok)
    first = int(np.searchsorted(j["wall_s"], since_wall))
    k = max(first, int(tail_bad[-1]) + 1 if tail_bad.size else 0)
    assert k < len(ok), "the offset never came back to the model's value"
    return k


def same_value(a: float, b: float) -> bool:
    return abs(a - b) <= 1e-6 * max(1.0, abs(a), abs(b))


# -- the summary table --------------------------------------------------------------------------

SUMMARY: list[dict[str, str]] = []


def summarize(case: str, fault: str, does: str, alarm: str, recover: str, lost: str) -> None:
    SUMMARY[:] = [r for r in SUMMARY if r["case"] != case]
    SUMMARY.append(
        {
            "case": case,
            "fault": fault,
            "does": does,
            "alarm": alarm,
            "recover": recover,
            "lost": lost,
        }
    )


def summary_table() -> list[str]:
    head = ("#", "fault", "what the runtime does", "alarm", "time to recover", "data lost")
    rows = [
        (r["case"], r["fault"], r["does"], r["alarm"], r["recover"], r["lost"])
        for r in sorted(SUMMARY, key=lambda r: (int(r["case"].rstrip("ab")), r["case"]))
    ]
    out = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out
