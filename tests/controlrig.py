"""What the end-to-end tests of the controller profiles share (issue 19): the runtime on one
stepped clock, configured for a route (the model: the ``calibrated_model`` fixture, conftest)."""

from __future__ import annotations

from pathlib import Path

from test_transients import FAST_RATE, MAX_RATE, WALL0

from thermocomp.runtime import SpindleRuntime
from thermocomp.runtime.config import load_config

MAX_OFFSET_UM = 60.0


def control_runtime(
    tmp_path: Path,
    model: Path,
    adapter: str,
    clock,
    *,
    clamp_um: float = MAX_OFFSET_UM,
    period_s: float = 1.0,
    shaping: tuple[str, ...] = (),
) -> SpindleRuntime:
    """The runtime of one spindle through ``adapter`` (a TOML inline table), its time from
    ``clock``; the shaping of the transient tests (1 um/s cutting, 50 um/s clear)."""
    lines = [
        f'state_dir = "{tmp_path / "state"}"',
        "watchdog = false",
        "journal_fsync_s = 3600.0",
        "[[spindle]]",
        'name = "s1"',
        f'model = "{model}"',
        f"period_s = {period_s}",
        "state_save_every_s = 600.0",
        f"adapter = {adapter}",
        "[spindle.shaping]",
        f"max_offset_um = {clamp_um}",
        f"max_rate_um_per_s = {MAX_RATE}",
        f"not_cutting_rate_um_per_s = {FAST_RATE}",
        "deadband_um = 0.1",
        *shaping,
    ]
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "machine.toml"
    path.write_text("\n".join(lines) + "\n")
    cfg = load_config(path)
    return SpindleRuntime(
        cfg.spindle[0],
        cfg.state_dir,
        cfg.journal_path,
        clock=clock,
        wall=lambda: WALL0 + clock(),
        journal_fsync_s=cfg.journal_fsync_s,
    )
