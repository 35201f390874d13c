"""Fit every channel of the real record, with its 16 temperatures, on every prefix of two or more
whole cycles: each of the 5 channels x 4 prefixes gives a model (never a refusal), and the model
file says which fallback it carries.

Affordable by design: the product's own :func:`calibration.fit.fit_logs`, as ``thermocomp fit``
runs it but with ``physical=False`` and ``probe_target_um=None``. A full fit takes about 14 s of
CPU on four cycles, a third of it the output-error physical form; twenty of them are minutes of
CI. The refusal under test comes after every candidate is scored: a speed-only candidate is
refused when its held-out figure is worse than the exponential baseline's or when its steady
growth fails the physics check, and the channel is refused when none is left. Leaving the physical
form out takes one speed-only candidate away, so these fits are, if anything, more exposed to that
refusal than the full fit. The nested figure stays: without it the scores change which candidates
are refused as worse than the baseline, and fewer channels were refused than by ``thermocomp fit``
(ch1 and ch2 on three cycles). On four and five cycles, where no channel was ever refused and a
fit costs most, it is left out. One test per channel x prefix, so that pytest-xdist spreads them.
"""

from __future__ import annotations

import json
import runpy
from pathlib import Path

import pytest

from calibration.fit import fit_logs
from calibration.folds import split_cycles
from compensator.io import read_run_log, save_model

ROOT = Path(__file__).resolve().parents[1]
WRITE_CHANNELS = runpy.run_path(str(ROOT / "tests/data/real-spindle/channels.py"))["write_channels"]
CHANNELS = ("ch1", "ch2", "ch3", "ch4", "ch5")
TEMPS = tuple(f"temp{i}_c" for i in range(1, 17))
CYCLES = [(0, 1951), (1951, 3871), (3871, 5791), (5791, 7711), (7711, 9600)]
"""The record's cycles by :func:`split_cycles` (checked below): 15 s rows, about 8 h each."""


@pytest.fixture(scope="module")
def real(tmp_path_factory, computed_once):
    """The five channels' run logs, written once per run."""
    return computed_once("real-prefixes", lambda d: WRITE_CHANNELS(d))


def prefix_log(src: Path, rows: int, out: Path) -> Path:
    """The run log's header and first ``rows`` rows."""
    lines = src.read_text().splitlines(keepends=True)
    out.write_text("".join(lines[: rows + 1]))
    return out


def fallback_named(raw: dict) -> str | None:
    """The fallback a model file carries: its speed-only model's form, else the method its fit
    record names."""
    fb = raw.get("fallback")
    if isinstance(fb, dict):
        return fb.get("form") or (fb.get("fit") or {}).get("method")
    return None


CASES = [pytest.param(ch, k, id=f"{ch}-{k}cycles") for ch in CHANNELS for k in (2, 3, 4, 5)]
"""Before a failing speed-only fallback stopped refusing the channel, ch1, ch2, ch4 and ch5 on
three cycles and ch3 on two were refused ("no speed-only candidate passed the checks:
exp-baseline: physics: ...")."""


@pytest.mark.parametrize(("channel", "cycles"), CASES)
def test_every_channel_fits_on_every_prefix(real, tmp_path, channel, cycles):
    full = real / f"{channel}_train.csv"
    whole = read_run_log(full)
    assert split_cycles(whole.time_s, whole.speed_rpm) == CYCLES
    log = read_run_log(prefix_log(full, CYCLES[cycles - 1][1], tmp_path / "prefix.csv"))
    assert len(log.time_s) == CYCLES[cycles - 1][1]

    # the nested figure where channels were refused (two and three cycles); four and five
    # cycles, never refused, without it (it is 40 % of a fit's time)
    result = fit_logs([log], TEMPS, physical=False, probe_target_um=None, nested=cycles <= 3)

    path = tmp_path / "model.json"
    save_model(path, result.model)
    raw = json.loads(path.read_text())
    if raw.get("inputs"):
        # a model with inputs carries the speed-only model that stands in when an input fails,
        # and its record says which
        name = fallback_named(raw)
        assert name, f"{channel} on {cycles} cycles: the model file names no fallback"
        stated = raw["fit"].get("fallback") or raw["fit"]["reason"]
        assert name in stated, stated
    else:
        assert raw.get("fallback") is None
