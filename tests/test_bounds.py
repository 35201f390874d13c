"""Bounds on what comes out: an error echoing a huge bad value prints as one short line."""

from __future__ import annotations

import pickle
import subprocess
import sys

import pytest
from conftest import first_order
from hypothesis import given
from hypothesis import strategies as st

from compensator.errors import (
    MAX_MESSAGE_CHARS,
    ConfigError,
    RunLogError,
    UnreachableError,
    clip,
)
from compensator.io import save_model

MB = "Z" * 1_000_000
LINE_MAX = 400  # the printed line, "thermocomp: error: " included


def tc(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "thermocomp", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=120,
        check=False,
    )


def assert_one_short_line(r: subprocess.CompletedProcess) -> str:
    assert r.returncode != 0, r.stdout[-500:]
    err = r.stderr
    assert err.endswith("\n") and err.count("\n") == 1, err[:500]
    assert err.startswith("thermocomp: error: ") and "Traceback" not in err, err[:500]
    assert len(err) < LINE_MAX, len(err)
    return err


# -- clip ------------------------------------------------------------------------------


@given(st.text(), st.integers(40, 2000))
def test_clip_is_one_line_within_the_limit(text, limit):
    out = clip(text, limit)
    assert len(out) <= limit
    assert len(out.splitlines()) <= 1 and "\t" not in out
    assert all(c.isprintable() or c == " " for c in out), repr(out)


@given(st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E)), st.integers(40, 500))
def test_clip_keeps_a_printable_start_and_counts_the_rest(text, limit):
    out = clip(text, limit)
    if len(text) <= limit:
        assert out == text
    else:
        head, _, tail = out.rpartition("... (")
        assert text.startswith(head) and tail == f"{len(text) - len(head)} characters cut)"


def test_clip_escapes_controls_and_joins_lines():
    assert clip("a\r\nb\nc\x1b[2Jd\te") == "a | b | c\\x1b[2Jd e"


def test_clip_of_a_clipped_text_counts_both_cuts():
    once = clip(MB, 2000)
    assert once.endswith(f"... ({1_000_000 - len(once.rpartition('... (')[0])} characters cut)")
    twice = clip(once, 300)
    head = twice.rpartition("... (")[0]
    assert twice.endswith(f"... ({1_000_000 - len(head)} characters cut)"), twice[-60:]


def test_error_messages_are_clipped_when_made():
    err = ConfigError(f"bad value {MB!r}")
    assert len(str(err)) <= MAX_MESSAGE_CHARS and "characters cut" in str(err)
    assert str(RunLogError(MB, "run.csv", 7)).startswith("run.csv:7: ZZZ")
    assert len(str(RunLogError(MB, "run.csv", 7))) <= MAX_MESSAGE_CHARS
    short = ConfigError("two\nlines")
    assert str(short) == "two\nlines"  # a short message is left as it is
    # an OSError-based error keeps its errno form, and survives a pickle round trip
    refused = UnreachableError(111, "refused")
    assert refused.errno == 111 and str(refused) == "[Errno 111] refused"
    back = pickle.loads(pickle.dumps(UnreachableError(MB)))
    assert isinstance(back, UnreachableError) and len(str(back)) <= MAX_MESSAGE_CHARS


# -- the command -------------------------------------------------------------------------


CONFIG = """state_dir = "state"
[[spindle]]
name = "{name}"
model = "{model}"
period_s = {period}
{extra}
[spindle.adapter]
type = "sim"
preset = "{preset}"
"""
BOGUS = {
    "a value": {"period": f'"{MB}"'},
    "a key": {"extra": f"{MB} = 1"},
    "a name": {"name": MB},
    "a model path": {"model": f"{MB}.json"},
    "an adapter option": {"preset": MB},
}


@pytest.mark.parametrize("where", sorted(BOGUS))
def test_run_check_with_a_megabyte_bogus_config_value(tmp_path, where):
    save_model(tmp_path / "m.json", first_order())
    fields = {
        "name": "s1",
        "model": "m.json",
        "period": "1.0",
        "extra": "",
        "preset": "motorized-27k",
    }
    fields.update(BOGUS[where])
    (tmp_path / "c.toml").write_text(CONFIG.format(**fields))
    assert_one_short_line(tc("run", "--config", tmp_path / "c.toml", "--check"))


def test_run_check_of_the_valid_config_passes(tmp_path):
    """The base of the bogus configs above is good: each fails for its bogus value only."""
    save_model(tmp_path / "m.json", first_order())
    fields = {
        "name": "s1",
        "model": "m.json",
        "period": "1.0",
        "extra": "",
        "preset": "motorized-27k",
    }
    (tmp_path / "c.toml").write_text(CONFIG.format(**fields))
    r = tc("run", "--config", tmp_path / "c.toml", "--check")
    assert r.returncode == 0, r.stderr


def run_log(n=40):
    return "time_s,speed_rpm,elongation_um\n" + "".join(
        f"{60 * k},{1000 * (k % 20)},{0.1 * k}\n" for k in range(n)
    )


@pytest.mark.parametrize(
    "bogus",
    [f"60,{MB},0.1", f"{MB},1000,0.1", f'60,"{MB}\n{MB}",0.1'],
    ids=["speed", "time", "quoted-multiline"],
)
def test_replay_with_a_megabyte_bogus_cell(tmp_path, bogus):
    save_model(tmp_path / "m.json", first_order())
    (tmp_path / "log.csv").write_text(run_log().replace("60,1000,0.1", bogus))
    err = assert_one_short_line(tc("replay", tmp_path / "log.csv", "--model", tmp_path / "m.json"))
    assert "log.csv:3: column" in err and "characters cut" in err


def test_replay_with_a_terminal_escape_in_a_cell(tmp_path):
    save_model(tmp_path / "m.json", first_order())
    (tmp_path / "log.csv").write_text(
        run_log().replace("60,1000,0.1", "60,\x1b[2J\x1b[31mfast,0.1")
    )
    err = assert_one_short_line(tc("replay", tmp_path / "log.csv", "--model", tmp_path / "m.json"))
    assert "\x1b" not in err and "\\x1b[2J" in err


def test_a_huge_bad_argument_is_clipped_too(tmp_path):
    r = tc("fit", "run.csv", "--output", tmp_path / "m.json", "--probe-every", "Y" * 100_000)
    assert r.returncode == 2
    last = r.stderr.splitlines()[-1]
    assert (
        last.startswith("thermocomp fit: error: argument --probe-every")
        and "characters cut" in last
    )
    assert len(r.stderr) < 2000  # the usage, then one clipped line


def test_a_logged_message_is_one_bounded_line():
    import logging

    from thermocomp.cli import LOG_CHARS, _OneLineFormatter

    fmt = _OneLineFormatter("thermocomp: %(levelname)s: %(name)s: %(message)s")
    record = logging.LogRecord(
        "cnc_adapters.opcua", logging.WARNING, __file__, 1, "bad value %r\nagain", (MB,), None
    )
    line = fmt.format(record)
    assert "\n" not in line and "characters cut" in line
    assert len(line) <= len("thermocomp: WARNING: cnc_adapters.opcua: ") + LOG_CHARS
