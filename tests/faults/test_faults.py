"""Fault injection with real processes: the service (``thermocomp run``) and the virtual CNC
(``thermocomp virtual-cnc``) as subprocesses on loopback, an asyncua client as the outside
world; the clock step and the corrupt state files in-process, where time and files can be
made to misbehave on purpose.

Every case checks the journal's invariants (:func:`harness.check_invariants`): finite
offsets, inside the clamp or monotonically approaching it, the slew limit between
consecutive rows, strictly increasing time and no row lost; then the alarm bits and the
JSON events of its fault, and that the offset is the model's again after recovery, the
controller's own value (read over OPC UA at the end) equal to the journal's last offset.

The in-process cases come first: the shared virtual CNC boots meanwhile. The table printed
at the end (``-s`` not needed) is the README's fault table.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import resource
import signal
import string
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import first_order  # tests/conftest.py: the hand-built first-order model
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from compensator.io import STATE_FORMAT, load_any_model, load_state, model_digest, save_model
from compensator.io.checksum import digest
from machine_sim.adapter import SimAdapter
from thermocomp.runtime import Alarm, Service, SpindleRuntime
from thermocomp.runtime.config import load_config

from .harness import (
    PYTHON,
    READ_ONLY_ERRORS,
    Setup,
    after_event,
    check_invariants,
    has,
    journal_parts,
    named,
    read_events,
    read_journal,
    recovered_at,
    same_value,
    slew_tol,
    summarize,
    tracking,
    wait_for,
)


def fmt_s(x: float) -> str:
    return f"{x:.1f} s"


def final_controller_check(case, j) -> float:
    """The controller holds what the journal says it holds (the service is stopped)."""
    held = case.vcnc.read_offset()
    assert same_value(held, float(j["offset_um"][-1])), (held, j["offset_um"][-1])
    return held


def index_of(events, ev) -> int:
    return next(i for i, e in enumerate(events) if e is ev or e == ev)


# -- 10. corrupt state files (in-process, hypothesis) ---------------------------------------------

W0 = 1_709_640_000.0  # 2024-03-05 12:00:00 UTC


@contextlib.contextmanager
def capture_events():
    """The runtime's structured events, in-process."""
    got: list[dict] = []

    class Grab(logging.Handler):
        def emit(self, record):
            name = getattr(record, "event", None)
            if name:
                got.append(
                    {
                        "event": name,
                        "msg": record.getMessage(),
                        **(getattr(record, "fields", None) or {}),
                    }
                )

    lg = logging.getLogger("thermocomp.runtime")
    h, old = Grab(logging.DEBUG), lg.level
    lg.addHandler(h)
    lg.setLevel(logging.DEBUG)
    try:
        yield got
    finally:
        lg.removeHandler(h)
        lg.setLevel(old)


def _state_body(sha: str, **over) -> dict:
    body = {
        "format": STATE_FORMAT,
        "spindle": "s1",
        "model_sha256": sha,
        "saved_wall_s": W0 - 60.0,
        "thermal_um": [12.5],
        "elongation_um": 12.5,
        "offset_um": -12.5,
        **over,
    }
    return body


def _signed(body: dict) -> dict:
    body = {k: v for k, v in body.items() if k != "sha256"}
    try:
        body["sha256"] = digest(body)
    except (ValueError, TypeError, RecursionError):
        body["sha256"] = "0" * 64  # cannot be summed (NaN, inf, too deep): a wrong checksum
    return body


def _text(body: dict, literal: str | None = None) -> bytes:
    text = json.dumps(body)
    if literal is not None:
        text = text.replace('"@@"', literal)
    return text.encode()


NUMERIC_KEYS = ("saved_wall_s", "offset_um")
REQUIRED_KEYS = ("format", "saved_wall_s", "thermal_um", "sha256")  # model_sha256: its own kind


def corrupt_files(sha: str) -> dict[str, st.SearchStrategy[bytes]]:
    """A strategy of corrupt state-file bytes per kind of corruption."""
    valid = _signed(_state_body(sha))
    valid_text = _text(valid)

    def put(key: str, value, literal: str | None = None) -> bytes:
        """``key`` set to ``value`` (``thermal_um``: its one element; ``thermal_um/``: the
        list itself), the checksum made valid again where it can be."""
        body = dict(valid)
        if key == "thermal_um":
            value = [value]
        body[key.rstrip("/")] = value
        return _text(_signed(body) if literal is None else body, literal)

    nan = st.builds(
        lambda k, lit: put(k, "@@", lit),
        st.sampled_from((*NUMERIC_KEYS, "thermal_um", "elongation_um")),
        st.sampled_from(("NaN", "Infinity", "-Infinity")),
    )

    def nested(depth: int, opener: str, where: str) -> bytes:
        closer = "]" if opener == "[" else "}"
        deep = opener * depth + "0" + closer * depth
        if where == "top":
            return deep.encode()
        if depth <= 400:  # shallow enough to be summed: a valid checksum, caught further in
            return put(where, json.loads(deep))
        return put(where, "@@", deep)

    deep = st.builds(
        nested,
        st.integers(60, 400_000),
        st.sampled_from(("[", '{"a":')),
        st.sampled_from(("top", "saved_wall_s", "thermal_um", "offset_um")),
    )

    def drop(key: str) -> bytes:
        body = {k: v for k, v in valid.items() if k != key}
        return _text(body if key == "sha256" else _signed(body))

    missing = st.builds(drop, st.sampled_from(REQUIRED_KEYS))
    # the model's digest: absent, or not a string (a valid checksum over it all the same)
    bad_sha = st.just(drop("model_sha256")) | st.one_of(
        st.none(), st.booleans(), st.integers(), st.lists(st.integers(), max_size=2)
    ).map(lambda v: put("model_sha256", v))
    truncated = st.builds(lambda n: valid_text[:n], st.integers(0, len(valid_text) - 1))
    random_bytes = st.binary(max_size=3000)

    def wrong_for(key: str):
        anything = st.one_of(
            st.text(string.printable, max_size=12),
            st.booleans(),
            st.none(),
            st.lists(st.integers(-5, 5), max_size=3),
            st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
            st.sampled_from(["12.5", "1e9", "-0", " 3 "]),
        )
        if key == "format":
            return anything.filter(lambda v: not isinstance(v, str))
        if key == "thermal_um/":  # one number in a list is a valid state of the one-state model
            return anything.filter(lambda v: not (isinstance(v, list) and len(v) == 1))
        # a number is the right type (a bool is not one)
        return anything.filter(
            lambda v: not (isinstance(v, (int, float)) and not isinstance(v, bool))
        )

    wrong = st.sampled_from(("format", *NUMERIC_KEYS, "thermal_um", "thermal_um/")).flatmap(
        lambda k: wrong_for(k).map(lambda v: put(k, v))
    )
    keys = st.sampled_from((*NUMERIC_KEYS, "thermal_um"))
    # an integer literal no float can hold (a valid checksum: JSON integers are unbounded)
    huge_int = st.builds(lambda k, e: put(k, 10**e), keys, st.integers(309, 4000))
    # finite but absurd (1e300 s, 1e300 um), or beyond a double (1e400: inf when read)
    huge_float = st.builds(
        lambda k, v: put(k, "@@", v) if isinstance(v, str) else put(k, v),
        keys,
        st.sampled_from((1e300, -1e300, 1.7976931348623157e308, "1e400", "-1e400")),
    )
    return {
        "nan": nan,
        "deep": deep,
        "missing_key": missing,
        "bad_model_sha256": bad_sha,
        "truncated": truncated,
        "random_bytes": random_bytes,
        "wrong_type": wrong,
        "huge_int": huge_int,
        "huge_float": huge_float,
    }


CORRUPTIONS = (
    "nan",
    "deep",
    "missing_key",
    "bad_model_sha256",
    "truncated",
    "random_bytes",
    "wrong_type",
    "huge_int",
    "huge_float",
)


@pytest.mark.parametrize("kind", CORRUPTIONS)
def test_10_corrupt_state_file_is_kept_aside_and_the_start_is_cold(kind, tmp_path, models):
    """Whatever is in the state file, the runtime starts (cold, STATE_CORRUPT), never raises,
    and the bad file is kept aside byte for byte as ``<name>.state.json.corrupt-<stamp>``."""
    s = Setup(root=tmp_path, model=models["quick"], adapter={"url": "sim://motorized-27k?program="})
    cfg = load_config(s.write())
    sha = model_digest(load_any_model(models["quick"]))
    strategy = corrupt_files(sha)[kind]

    @settings(
        max_examples=40,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(data=strategy)
    def run(data: bytes) -> None:
        d = Path(tempfile.mkdtemp(dir=tmp_path))
        state_dir = d / "state"
        state_dir.mkdir()
        bad = state_dir / "s1.state.json"
        bad.write_bytes(data)
        t = {"now": 0.0}
        clock = lambda: t["now"]
        with capture_events() as ev:
            rt = SpindleRuntime(
                cfg.spindle[0],
                state_dir,
                state_dir / "journal",
                clock=clock,
                wall=lambda: W0 + t["now"],
                adapter=SimAdapter(program=None, clock=clock),
            )
            recs = []
            for _ in range(3):
                t["now"] += 0.25
                recs.append(rt.cycle())
            rt.close()
        assert recs[0]["alarms"] & Alarm.STATE_CORRUPT, f"no STATE_CORRUPT for {data[:400]!r}"
        assert recs[0]["alarms"] & Alarm.COLD_START
        assert all(math.isfinite(r["offset_um"]) for r in recs)
        kept = sorted(state_dir.glob("s1.state.json.corrupt-*"))
        assert len(kept) == 1 and kept[0].read_bytes() == data
        corrupt_ev = named(ev, "state_corrupt")
        assert len(corrupt_ev) == 1 and corrupt_ev[0]["kept_as"] == str(kept[0])
        assert any(e["event"] == "cold_start" and "corrupt" in e["reason"] for e in ev)
        assert load_state(bad)["spindle"] == "s1"  # the new state, saved at close

    try:
        run()
    except BaseException:
        KINDS_DONE[kind] = False
        raise
    finally:
        KINDS_DONE.setdefault(kind, True)
        ok = [k for k in CORRUPTIONS if KINDS_DONE.get(k)]
        bad = [k for k in CORRUPTIONS if KINDS_DONE.get(k) is False]
        summarize(
            "10",
            "corrupt state file, hypothesis: "
            + ", ".join(ok)
            + (f" (FAILING: {', '.join(bad)})" if bad else ""),
            "moves it aside byte for byte as `*.corrupt-<UTC stamp>`, starts cold, never raises",
            "STATE_CORRUPT + COLD_START",
            "at start (first cycle)",
            "the saved thermal state (cold start); the file is kept",
        )


KINDS_DONE: dict[str, bool] = {}


# -- 8. a wall-clock step (in-process, injected clocks) ---------------------------------------------


def _replay(model: Path, journal: Path) -> dict:
    r = subprocess.run(
        [PYTHON, "-m", "thermocomp", "replay", "--model", str(model), str(journal), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_08_wall_clock_step_back(tmp_path):
    """The wall clock steps back an hour mid-run: CLOCK_STEP on that row and an event, the
    journal's time_s stays monotonic (it is the monotonic clock anchored once) and replay
    reads it; a restart with the wall clock behind the journal continues in a .p2 part."""
    model = tmp_path / "first_order.json"
    save_model(model, first_order())
    s = Setup(
        root=tmp_path,
        model=model,
        period_s=1.0,
        adapter={"url": "sim://motorized-27k?program=job-shop-day&seed=3"},
        shaping={"max_rate_um_per_s": 2.0},
    )
    s.write()
    t = {"mono": 1000.0, "wall": W0}
    step_at, n1, n2 = 150, 300, 120
    with capture_events() as ev:
        svc = Service(
            s.config, clock=lambda: t["mono"], wall=lambda: t["wall"], sleep=lambda _s: None
        )
        for k in range(n1):
            if k == step_at:
                t["wall"] -= 3600.0
            svc.tick()
            t["mono"] += 1.0
            t["wall"] += 1.0
        svc.close()
    j = read_journal(s.journal_dir)
    assert len(j["time_s"]) == n1 and len(journal_parts(s.journal_dir)) == 1
    step_rows = np.flatnonzero(has(j["alarms"], Alarm.CLOCK_STEP))
    assert step_rows.tolist() == [step_at]
    assert j["wall_s"][step_at] - j["wall_s"][step_at - 1] == pytest.approx(-3599.0, abs=1e-3)
    (clk,) = named(ev, "clock_step")
    assert clk["step_s"] == pytest.approx(-3600.0, abs=1e-3)
    chk = check_invariants(j, rate=2.0, clamp=s.clamp, events=ev, period_s=1.0)
    assert np.allclose(np.diff(j["time_s"]), 1.0, atol=1.5e-3)  # monotonic, one per period
    assert np.allclose(j["dt_s"][1:], 1.0)  # the model never stepped by the wall's -3600 s
    first = journal_parts(s.journal_dir)[0]
    assert _replay(model, first)["samples"] == n1

    # a restart (a reboot: the monotonic clock starts again) with the wall clock still an hour
    # behind the journal's last row: a new part, both read by replay
    t2 = {"mono": 5.0, "wall": t["wall"] + 30.0}
    assert t2["wall"] < j["time_s"][-1]
    with capture_events() as ev2:
        svc2 = Service(
            s.config, clock=lambda: t2["mono"], wall=lambda: t2["wall"], sleep=lambda _s: None
        )
        for _ in range(n2):
            svc2.tick()
            t2["mono"] += 1.0
            t2["wall"] += 1.0
        svc2.close()
    parts = journal_parts(s.journal_dir)
    assert [p.name.split("-", 1)[1] for p in parts] == ["2024-03-05.csv", "2024-03-05.p2.csv"]
    assert parts[0] == first and len(read_journal(s.journal_dir)["time_s"]) == n1 + n2
    assert _replay(model, parts[1])["samples"] == n2
    assert not named(ev2, "state_corrupt", "clock_step")
    assert named(ev2, "state_restored")
    j2 = read_journal(s.journal_dir)
    check_invariants(j2, rate=2.0, clamp=s.clamp, events=ev + ev2, period_s=1.0, one_process=False)
    assert not has(j2["alarms"][n1:], Alarm.CLOCK_STEP).any()
    summarize(
        "8",
        "wall clock stepped back 1 h (and a restart behind the journal)",
        "flags the step, keeps journal time monotonic; a restart continues in `<day>.p2.csv`",
        "CLOCK_STEP (one row)",
        "immediate (next cycle)",
        f"none ({chk.lost} rows lost)",
    )


# -- 1. controller restart: the offset reset to zero ----------------------------------------------


def test_01_controller_restart_resets_the_offset(case):
    s = case.setup(model="quick", shaping={"max_rate_um_per_s": 40.0})
    svc = case.start(s)
    before = svc.wait_settled()
    held_before = float(before["offset_um"][-1])
    n0 = len(svc.events())
    t_kill = time.time()
    case.vcnc.kill()
    case.vcnc.start()  # a new controller on the same port: it holds 0
    case.vcnc.wait_ready()
    t_up = time.time()
    mm = svc.wait_event("offset_mismatch", after=n0, timeout=30)
    svc.wait_event("link_restored", after=n0)
    wait_for(
        lambda: (
            (r := svc.rows())
            and has(r["alarms"], Alarm.OFFSET_MISMATCH).any()
            and tracking(r, s.clamp, s.deadband)[-4:].all()
        ),
        30,
        "the offset back on the model",
    )
    assert svc.stop() == 0
    final_controller_check(case, j := read_journal(s.journal_dir))
    ev = read_events(s.log_file)
    chk = check_invariants(
        j,
        rate=s.rate,
        clamp=s.clamp,
        events=ev,
        period_s=s.period_s,
        gap_ok=lambda w0, w1: w1 > t_kill and w0 < t_up + 5,
    )

    after = ev[n0:]
    first_link = named(after, "link_down", "timeout", "link_restored", "offset_mismatch")[0]
    assert first_link["event"] in ("link_down", "timeout")
    assert index_of(ev, named(after, "link_restored")[0]) < index_of(ev, mm)
    assert "reset to zero" in mm["cause"] and mm["when"] == "after a reconnect"
    assert abs(mm["held_um"]) <= 0.5 and same_value(mm["expected_um"], held_before)
    down = has(j["alarms"], Alarm.LINK_DOWN)
    assert down.any() and not j["written"][down].any(), "a write while the link was down"
    if t_up - t_kill > 2 * 1.0 + 1.0:  # down longer than max_outage_s, with margin
        assert named(after, "outage") and has(j["alarms"], Alarm.OUTAGE).any()
    (r,) = np.flatnonzero(has(j["alarms"], Alarm.OFFSET_MISMATCH))  # the reconnect's row
    assert down[r - 1] and not down[r]
    # it kept cycling while the controller was gone: a row every period of the journal's time
    gone = np.flatnonzero(down[:r])
    assert (
        gone.size >= 1 and gone.size >= 0.5 * (j["time_s"][r] - j["time_s"][gone[0]]) / s.period_s
    )
    assert j["written"][r] or j["written"][r + 1], "writing did not resume within one cycle"
    # a ramp from 0 at the slew limit, not a jump: several slew-limited rows from 0
    assert abs(j["offset_um"][r]) <= s.rate * j["dt_s"][r] + slew_tol(s.rate, 30.0)
    k = recovered_at(j, j["wall_s"][r], s.clamp, s.deadband)
    ramp = j["offset_um"][r : k + 1]
    assert (np.diff(ramp) <= 1e-9).all(), ramp  # monotonic from 0 to -30 ...
    # ... and no faster than the slew limit over the runtime's own steps
    assert s.rate * j["dt_s"][r : k + 1].sum() >= abs(ramp[-1]) - slew_tol(s.rate, 30.0), ramp
    t_rec = j["wall_s"][k] - t_up
    summarize(
        "1",
        "controller restart (offset reset to 0)",
        "no write while down; on reconnect reads back 0, ramps from 0 to the model at the slew limit",
        'LINK_DOWN, OUTAGE, OFFSET_MISMATCH ("reset to zero")',
        f"{fmt_s(t_rec)} after the controller listens ({fmt_s(t_up - t_kill)} down)",
        f"none ({chk.lost} rows lost; rows kept coming while down)",
    )


# -- 2. an outside write ---------------------------------------------------------------------------------


def test_02_outside_write_is_found_and_ramped_back(case):
    s = case.setup(model="quick", shaping={"max_rate_um_per_s": 250.0})
    svc = case.start(s)
    before = svc.wait_settled()
    n0 = len(svc.events())
    t_write = time.time()
    case.vcnc.write_offset(999.0)  # an operator, an NC program or another client
    mm = svc.wait_event("offset_mismatch", after=n0, timeout=20)
    wait_for(
        lambda: (
            (r := svc.rows())
            and has(r["alarms"], Alarm.OFFSET_MISMATCH).any()
            and tracking(r, s.clamp, s.deadband)[-4:].all()
        ),
        30,
        "the offset back on the model",
    )
    assert svc.stop() == 0
    final_controller_check(case, j := read_journal(s.journal_dir))
    ev = read_events(s.log_file)
    chk = check_invariants(j, rate=s.rate, clamp=s.clamp, events=ev, period_s=s.period_s)

    assert "outside write" in mm["cause"] and mm["held_um"] == 999.0
    assert same_value(mm["expected_um"], float(before["offset_um"][-1]))
    assert mm["when"] in ("periodic check", "after a reconnect")
    (r,) = np.flatnonzero(has(j["alarms"], Alarm.OFFSET_MISMATCH))
    # 999 um is none we wrote: the same cycle writes the clamp, never the value back
    assert not (np.abs(j["offset_um"]) > s.clamp).any()
    assert j["written"][r] and j["offset_um"][r] == s.clamp
    k = recovered_at(j, j["wall_s"][r], s.clamp, s.deadband)
    summarize(
        "2",
        "outside write of 999 um to the offset node",
        "periodic read-back finds it, writes the clamp in the same cycle, then ramps to the model",
        'OFFSET_MISMATCH ("outside write")',
        f"{fmt_s(j['wall_s'][k] - t_write)} (found after {fmt_s(mm['ts'] - t_write)})",
        f"none ({chk.lost} rows lost)",
    )


# -- 3. SIGHUP lowering the clamp -----------------------------------------------------------------------------


def test_03_sighup_lowering_the_clamp_ramps_into_it(case):
    s = case.setup(model="quick", shaping={"max_rate_um_per_s": 20.0})
    svc = case.start(s)
    before = svc.wait_settled()
    assert before["offset_um"][-1] == pytest.approx(-30.0, abs=0.2)
    s.shaping["max_offset_um"] = 10.0
    s.write()
    n0 = len(svc.events())
    t_hup = time.time()
    svc.signal(signal.SIGHUP)
    rel = svc.wait_event("reload", after=n0)
    wait_for(
        lambda: (
            (r := svc.rows())
            and (r["wall_s"] > rel["ts"]).sum() > 8
            and np.allclose(r["offset_um"][-4:], -10.0, atol=1e-9)
        ),
        30,
        "the offset at the new clamp",
    )
    assert svc.stop() == 0
    final_controller_check(case, j := read_journal(s.journal_dir))
    ev = read_events(s.log_file)
    new = after_event(j, rel)
    clamp = np.where(new, 10.0, 60.0)
    chk = check_invariants(j, rate=s.rate, clamp=clamp, events=ev, period_s=s.period_s)
    assert not named(ev, "reload_refused", "offset_mismatch")
    assert not has(j["alarms"], Alarm.RELOAD_FAILED | Alarm.OFFSET_MISMATCH).any()
    r = int(np.argmax(new))
    # the new runtime carries the running one on: its first step is the time since the last row
    assert j["dt_s"][r] == pytest.approx(j["time_s"][r] - j["time_s"][r - 1], abs=2e-3)
    # no offset beyond the clamp is ever written: the first cycle under the new clamp writes it
    assert j["offset_um"][r - 1] == pytest.approx(-30.0, abs=0.2)
    assert j["written"][r] and (j["offset_um"][r:] == -10.0).all()
    summarize(
        "3",
        "SIGHUP lowering max_offset_um below the offset",
        "reloads; the first cycle under the new clamp writes the clamp (no value beyond it is written)",
        "none (event reload)",
        f"{fmt_s(j['wall_s'][r] - t_hup)}",
        f"none ({chk.lost} rows lost)",
    )


# -- 4. SIGHUP with a broken model ------------------------------------------------------------------------------


def test_04_sighup_with_a_broken_model_keeps_the_running_one(case):
    s = case.setup(model="quick")
    svc = case.start(s)
    n_settled = len(svc.wait_settled()["time_s"])  # the start-up ramp is over by this row
    good = s.model
    refused = []
    for bad, why in (
        ("garbage", "not a JSON model file"),
        ("unstable", "unstable"),
        ("implausible", "not plausible"),
    ):
        s.model = case.models[bad]
        s.write()
        n0 = len(svc.events())
        svc.signal(signal.SIGHUP)
        e = svc.wait_event("reload_refused", after=n0)
        assert why in e["error"], e
        if bad == "implausible":  # named as every configuration message names a spindle
            assert e["error"].startswith('spindle "'), e
        refused.append(e)
    n_ref = len(svc.rows()["time_s"])
    rows = svc.wait_rows(n_ref + 6)
    assert has(rows["alarms"][-6:], Alarm.RELOAD_FAILED).all()
    s.model = good
    s.write()
    n0 = len(svc.events())
    t_good = time.time()
    svc.signal(signal.SIGHUP)
    rel = svc.wait_event("reload", after=n0)
    wait_for(
        lambda: (svc.rows()["wall_s"] > rel["ts"]).sum() >= 6, 30, "rows after the good reload"
    )
    assert svc.alive()
    assert svc.stop() == 0
    final_controller_check(case, j := read_journal(s.journal_dir))
    ev = read_events(s.log_file)
    chk = check_invariants(j, rate=s.rate, clamp=s.clamp, events=ev, period_s=s.period_s)
    failed = has(j["alarms"], Alarm.RELOAD_FAILED)
    window = after_event(j, refused[0]) & ~after_event(j, rel)
    assert window.sum() >= 6
    assert (failed == window).all(), (
        "RELOAD_FAILED must be on every row from the refusal to the good reload"
    )
    # compensation went on with the running model: rows at the period, the offset on the model
    # (a reload restores the state advanced through the reload's own few ms as idle: with
    # this 0.1-s model that is a visible dip for a cycle or two, with a real one nothing)
    ok = tracking(j, s.clamp, s.deadband) | (
        after_event(j, rel) & (j["wall_s"] < rel["ts"] + 3 * s.period_s)
    )
    assert ok[n_settled - 1 :].all()
    assert (
        chk.runtime_starts == 1
    )  # a good reload carries the runtime on; a refused one builds nothing
    assert not named(ev[index_of(ev, refused[0]) :], "state_corrupt")
    summarize(
        "4",
        "SIGHUP with a broken model (garbage, unstable pole, 4 cm implausible)",
        "refuses the reload, keeps running the old model; compensation unchanged",
        "RELOAD_FAILED (every row until a good reload)",
        f"{fmt_s(rel['ts'] - t_good)} after a good reload (compensation never stopped)",
        f"none ({chk.lost} rows lost)",
    )
    # the running spindle never started cold: no event may say it did
    spurious = named(ev[index_of(ev, refused[0]) :], "cold_start")
    assert not spurious, f"a refused reload logged {spurious}"


# -- 5. a full disk: the journal cannot be written -----------------------------------------------------------------


@pytest.mark.parametrize("how", ["rlimit", "read_only_dir"])
def test_05_journal_write_failure_keeps_rows_in_memory(case, how):
    """A full disk: the file-size limit (RLIMIT_FSIZE, what a full disk or a quota looks like
    to a write: EFBIG; SIGXFSZ is ignored by the service) is set to a little above the
    journal's current size; or the journal directory is read-only from the start (chmod 0o500,
    as root chattr +i)."""
    s = case.setup(model="slow")
    kw = {}
    if how == "rlimit":

        def generous_limit():  # the service runs under a file-size limit from its start
            resource.setrlimit(resource.RLIMIT_FSIZE, (64 << 20, resource.RLIM_INFINITY))

        kw = {"preexec_fn": generous_limit, "env": {"PYTHONDONTWRITEBYTECODE": "1"}}
    else:
        s.journal_dir.mkdir(parents=True)
        if not case.read_only(s.journal_dir):
            pytest.skip("cannot make a directory read-only here (root without chattr +i)")
    svc = case.start(s, **kw)
    limit = None
    if how == "rlimit":
        # a little above the journal's size: a row or two more, then EFBIG. The limit binds
        # every file: the journal is let grow first past what the JSON log and the state
        # file will hold, so only the journal hits it
        size = lambda: sum(p.stat().st_size for p in journal_parts(s.journal_dir))
        others = lambda: max(
            (p.stat().st_size for p in (s.log_file, s.state_file) if p.exists()), default=0
        )
        wait_for(
            lambda: svc.rows() is not None and size() >= max(2000, others() + 2000),
            60,
            "a journal 2 kB larger than the log and the state file",
        )
        limit = size() + 150
        resource.prlimit(svc.pid, resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))
    fail = svc.wait_event("journal_failed", timeout=60)
    assert any(
        w in fail["error"] for w in (("File too large",) if how == "rlimit" else READ_ONLY_ERRORS)
    ), fail
    # compensation goes on: the controller's offset keeps following the (still heating) model
    polls = []
    end = time.monotonic() + 30
    while len({v for *_, v in polls}) < 3 and time.monotonic() < end:
        t0 = time.time()
        v = case.vcnc.read_offset()
        polls.append((t0, time.time(), v))
        time.sleep(0.3)  # pacing the polls, not an assertion
    assert len({v for *_, v in polls}) >= 3, polls
    if limit is not None:
        assert size() <= limit
    t_lift = time.time()
    if how == "rlimit":
        resource.prlimit(
            svc.pid, resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY)
        )
    else:
        case.writable_again()
    back = svc.wait_event("journal_restored", timeout=60)
    svc.wait_rows(len(svc.rows()["time_s"]) + 4)
    assert svc.stop() == 0, "the service died (SIGXFSZ?)"
    final_controller_check(case, j := read_journal(s.journal_dir))
    ev = read_events(s.log_file)
    chk = check_invariants(j, rate=s.rate, clamp=s.clamp, events=ev, period_s=s.period_s)
    assert back["dropped_rows"] == 0
    jf = has(j["alarms"], Alarm.JOURNAL_FAILED)
    late = np.flatnonzero(jf)
    assert late.size >= 3 and (np.diff(late) == 1).all()  # one stretch, every row of it kept
    assert (
        j["wall_s"][late[-1]] <= back["ts"] + 1e-3
        and j["wall_s"][late[0]] >= fail["ts"] - 2 * s.period_s
    )
    # rows written while the journal failed: the controller had each polled value, written by a
    # cycle between the one before the read began (its write may have been under way) and the
    # last one that began before the read ended, however slow the read
    for t0, t1, v in polls:
        k0 = max(0, int(np.searchsorted(j["wall_s"], t0)) - 2)
        k1 = int(np.searchsorted(j["wall_s"], t1, side="right"))
        assert any(same_value(v, x) for x in j["offset_um"][k0:k1]), (t0, t1, v)
    assert j["written"][late].sum() >= 3 and tracking(j, s.clamp, s.deadband).all()
    summarize(
        "5" if how == "rlimit" else "5b",
        "full disk: RLIMIT_FSIZE just above the journal's size"
        if how == "rlimit"
        else "read-only journal directory",
        "keeps compensating; rows wait in memory and land in order once the disk takes them",
        "JOURNAL_FAILED",
        f"{fmt_s(back['ts'] - t_lift)} after the disk takes writes again "
        f"({late.size} rows written late)",
        f"none ({chk.lost} rows lost, dropped_rows 0)",
    )


# -- 6. the state cannot be saved -------------------------------------------------------------------------------------


@pytest.mark.parametrize("how", ["state_path_is_a_directory", "read_only_dir"])
def test_06_state_save_failure_then_stale_then_recovery(case, how):
    """The state cannot be saved: its path is a directory (os.replace fails with EISDIR, as
    root too), or the state directory is read-only (chmod 0o500; as root chattr +i)."""
    s = case.setup(model="quick", save_every_s=0.25, faults={"state_stale_s": 1.5})
    svc = case.start(s)
    n_settled = len(svc.wait_settled()["time_s"])  # the start-up ramp is over by this row
    wait_for(s.state_file.exists, 10, "the state file")
    n0 = len(svc.events())
    t_break = time.time()
    if how == "read_only_dir":
        if not case.read_only(s.state_dir):
            pytest.skip("cannot make a directory read-only here (root without chattr +i)")
    else:  # os.replace(tmp, path) onto a directory: EISDIR

        def swap():
            with contextlib.suppress(FileNotFoundError):
                s.state_file.unlink()
            try:
                s.state_file.mkdir()
            except FileExistsError:  # the service saved again in between
                return False
            return True

        wait_for(swap, 10, "the state file replaced by a directory", poll=0.0)
    f = svc.wait_event("state_save_failed", after=n0)
    stale = svc.wait_event("state_stale", after=n0)
    wait_for(
        lambda: has(svc.rows()["alarms"][-3:], Alarm.STATE_STALE).all(), 10, "STATE_STALE rows"
    )
    t_fix = time.time()
    if how == "read_only_dir":
        case.writable_again()
    else:
        s.state_file.rmdir()
    again = svc.wait_event("state_saved_again", after=n0)
    wait_for(lambda: (svc.rows()["wall_s"] > again["ts"]).sum() >= 4, 10, "rows after the save")
    assert svc.stop() == 0
    final_controller_check(case, j := read_journal(s.journal_dir))
    ev = read_events(s.log_file)
    chk = check_invariants(j, rate=s.rate, clamp=s.clamp, events=ev, period_s=s.period_s)
    assert any(
        w in f["error"]
        for w in (("Is a directory",) if how != "read_only_dir" else READ_ONLY_ERRORS)
    ), f
    assert stale["ts"] - t_break >= s.faults["state_stale_s"] - 2 * s.save_every_s
    sf, ss = has(j["alarms"], Alarm.STATE_SAVE_FAILED), has(j["alarms"], Alarm.STATE_STALE)
    assert sf.any() and ss.any() and not (ss & ~sf).any()
    assert not (sf | ss)[j["wall_s"] > again["ts"] + s.period_s].any()
    assert not sf[j["wall_s"] < t_break].any()
    # compensation never noticed: the offset stayed on the model, rows at the period
    assert tracking(j, s.clamp, s.deadband)[n_settled - 1 :].all()
    saved = load_state(s.state_file)
    assert saved is not None and saved["saved_wall_s"] >= again["ts"] - 1.0
    summarize(
        "6" if how != "read_only_dir" else "6b",
        "state cannot be saved (state file path is a directory)"
        if how != "read_only_dir"
        else "read-only state directory",
        "keeps compensating; retries with back-off; stale after state_stale_s",
        "STATE_SAVE_FAILED, then STATE_STALE",
        f"{fmt_s(again['ts'] - t_fix)} after the fix",
        f"none ({chk.lost} rows lost); a restart meanwhile would start from the last good save",
    )


# -- 7. two instances on one state directory -------------------------------------------------------------------------


def test_07_second_instance_is_refused(case):
    s = case.setup(model="quick")
    first = case.start(s)
    first.wait_rows(4)
    t0 = time.monotonic()
    second = case.start(s, tag="second", ensure=False)
    rc = second.proc.wait(60)
    t_exit = time.monotonic() - t0
    assert rc != 0
    err = second.stderr.strip()
    assert err.count("\n") == 0 and f"pid {first.pid}" in err, err
    assert t_exit < 20.0
    n = len(first.rows()["time_s"])
    first.wait_rows(n + 8)
    assert (s.state_dir / "thermocomp.lock").read_text() == f"{first.pid}\n"
    assert first.stop() == 0
    final_controller_check(case, j := read_journal(s.journal_dir))
    ev = read_events(s.log_file)
    chk = check_invariants(j, rate=s.rate, clamp=s.clamp, events=ev, period_s=s.period_s)
    assert len(named(ev, "started")) == 1 and chk.runtime_starts == 1
    assert not has(j["alarms"], Alarm.OFFSET_MISMATCH).any()  # the second one wrote nothing
    summarize(
        "7",
        "a second instance on the same state directory",
        f"the second exits {rc} in {t_exit:.1f} s with one line naming the holder's pid",
        "none (exit status, stderr)",
        "nothing to recover: the first ran on",
        f"none ({chk.lost} rows lost by the first)",
    )


# -- 9. a hung controller --------------------------------------------------------------------------------------------


def test_09_hung_controller_sigstop(case):
    s = case.setup(
        model="medium",
        timeout_s=0.5,
        shaping={"max_rate_um_per_s": 40.0},
        faults={"max_outage_s": 1.0, "speed_hold_s": 0.5},
    )
    svc = case.start(s)
    svc.wait_rows(12)
    n0 = len(svc.events())
    t_stop = time.time()
    case.vcnc.sigstop()
    try:
        to = svc.wait_event("timeout", after=n0, timeout=20)
        out = svc.wait_event("outage", after=n0, timeout=20)
        wait_for(
            lambda: has(svc.rows()["alarms"], Alarm.OUTAGE).sum() >= 3,
            30,
            "rows kept coming in the outage",
        )
    finally:
        t_cont = time.time()
        case.vcnc.cont()
    back = svc.wait_event("link_restored", after=n0, timeout=30)
    wait_for(
        lambda: (
            (r := svc.rows())
            and (r["wall_s"] > back["ts"]).sum() > 4
            and tracking(r, s.clamp, s.deadband)[-4:].all()
        ),
        30,
        "the offset back on the model",
    )
    assert svc.stop() == 0
    final_controller_check(case, j := read_journal(s.journal_dir))
    ev = read_events(s.log_file)
    chk = check_invariants(
        j,
        rate=s.rate,
        clamp=s.clamp,
        events=ev,
        period_s=s.period_s,
        gap_ok=lambda w0, w1: w1 > t_stop and w0 < back["ts"] + 1.0,
    )
    after = ev[n0:]
    link_events = [
        e["event"] for e in named(after, "link_down", "timeout", "outage", "link_restored")
    ]
    assert link_events[:3] == ["timeout", "outage", "link_restored"], link_events
    assert out["ts"] > to["ts"]
    down = has(j["alarms"], Alarm.LINK_DOWN)
    outage = has(j["alarms"], Alarm.OUTAGE)
    assert not j["written"][down].any(), "a write while the controller was hung"
    assert outage.sum() >= 3 and not (outage & ~down).any()
    d0 = int(np.argmax(down & (j["wall_s"] >= t_stop - 2 * s.period_s)))
    r = d0 + int(np.argmax(~down[d0:]))  # the first row with the link back
    held = j["offset_um"][d0:r]
    assert np.all(held == j["offset_um"][d0 - 1])  # nothing written, nothing changed
    stopped = (j["wall_s"] > t_stop) & (j["wall_s"] < t_cont)
    gaps = np.diff(j["time_s"][stopped])
    assert (
        stopped.sum() >= 4 and gaps.max() <= 3 * 0.5 + 1 + s.period_s + 0.5
    )  # never stopped cycling
    assert has(j["alarms"][d0:r], Alarm.IDLE_ASSUMED).any()  # the model cooled meanwhile
    assert j["written"][r] or j["written"][r + 1]
    for m in named(after, "offset_mismatch"):  # a write that was in flight when it hung
        assert "outside write" in m["cause"] or "reset" in m["cause"]
    first_out = d0 + int(np.argmax(outage[d0:]))
    assert j["time_s"][first_out] - j["time_s"][d0] > s.faults["max_outage_s"]
    assert j["time_s"][first_out - 1] - j["time_s"][d0] <= s.faults["max_outage_s"]
    k = recovered_at(j, back["ts"], s.clamp, s.deadband)
    summarize(
        "9",
        "hung controller (SIGSTOP of the virtual CNC)",
        "timeouts drop the session; no write while hung; rows keep coming at timeout pace; "
        "on SIGCONT reads back and ramps",
        "LINK_DOWN, OUTAGE (after max_outage_s), IDLE_ASSUMED",
        f"{fmt_s(j['wall_s'][k] - t_cont)} after SIGCONT (link back in {fmt_s(back['ts'] - t_cont)})",
        f"none ({chk.lost} rows lost; {int(stopped.sum())} rows while hung)",
    )


# -- combined faults: a reload while the disk fails --------------------------------------------------------------


def test_11_reload_while_the_journal_fails_loses_no_rows(case):
    """SIGHUP while journal rows wait in memory (RLIMIT_FSIZE): the reload must not drop
    them; once the disk takes rows again every cycle is in the journal."""
    s = case.setup(model="slow")

    def generous_limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 << 20, resource.RLIM_INFINITY))

    svc = case.start(s, preexec_fn=generous_limit, env={"PYTHONDONTWRITEBYTECODE": "1"})
    # the limit binds the JSON log too: let the journal grow past what the log will hold
    size = lambda: sum(p.stat().st_size for p in journal_parts(s.journal_dir))
    wait_for(lambda: svc.rows() is not None and size() >= 3200, 60, "a 3 kB journal")
    resource.prlimit(svc.pid, resource.RLIMIT_FSIZE, (size() + 150, resource.RLIM_INFINITY))
    fail = svc.wait_event("journal_failed", timeout=30)
    wait_for(lambda: time.time() > fail["ts"] + 8 * s.period_s, 10, "rows to pile up in memory")
    n0 = len(svc.events())
    svc.signal(signal.SIGHUP)
    rel = svc.wait_event("reload", after=n0)
    wait_for(lambda: time.time() > rel["ts"] + 4 * s.period_s, 10, "rows after the reload")
    t_lift = time.time()
    resource.prlimit(
        svc.pid, resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY)
    )
    back = svc.wait_event("journal_restored", after=n0, timeout=60)
    wait_for(lambda: (svc.rows()["wall_s"] > back["ts"]).sum() >= 4, 20, "rows after the recovery")
    assert svc.stop() == 0
    j = read_journal(s.journal_dir)
    ev = read_events(s.log_file)
    # every cycle between the failure and the reload: a row (at the period, no hole)
    # (on the journal's own time: each row's time_s is the last one's plus its dt_s, so a hole
    # is a lost row whatever the computer's load did to the period)
    before = np.flatnonzero((j["wall_s"] > fail["ts"] - 2 * s.period_s) & ~after_event(j, rel))
    kept = int(before.size)
    holes = int((np.abs(np.diff(j["time_s"][before]) - j["dt_s"][before][1:]) > 2e-3).sum())
    # the reload came 8 periods or more after the failure: the rows held in memory reach well past it
    reached = kept > 0 and j["wall_s"][before[-1]] >= fail["ts"] + 4 * s.period_s
    summarize(
        "11",
        "SIGHUP reload while journal rows wait in memory (RLIMIT_FSIZE)",
        "reloads; the rows waiting in memory must survive the reload",
        "JOURNAL_FAILED",
        f"{fmt_s(back['ts'] - t_lift)} after the limit is lifted",
        f"{kept} rows between the failure and the reload, {holes} holes",
    )
    assert reached and holes == 0, (
        f"{kept} rows between the journal failure and the reload reached "
        f"the journal, with {holes} holes: the reload dropped the rows "
        "kept in memory"
    )
    check_invariants(j, rate=s.rate, clamp=s.clamp, events=ev, period_s=s.period_s)


def test_12_reload_while_the_state_cannot_be_saved_keeps_the_model_state(case):
    """SIGHUP while the state cannot be saved (read-only state directory): the reloaded
    runtime must go on from the running model's state, not from the last good save advanced
    as idle; and the STATE_SAVE_FAILED / STATE_STALE alarms must not vanish with a reload."""
    s = case.setup(model="slow", save_every_s=0.25, faults={"state_stale_s": 1.5})
    svc = case.start(s)
    svc.wait_rows(6)
    wait_for(s.state_file.exists, 10, "the state file")
    if not case.read_only(s.state_dir):
        pytest.skip("cannot make a directory read-only here (root without chattr +i)")
    t_break = time.time()
    svc.wait_event("state_save_failed")
    svc.wait_event("state_stale")
    wait_for(lambda: time.time() > t_break + 3.0, 10, "the model to heat on")
    n0 = len(svc.events())
    svc.signal(signal.SIGHUP)
    rel = svc.wait_event("reload", after=n0)
    wait_for(lambda: (svc.rows()["wall_s"] > rel["ts"]).sum() >= 8, 20, "rows after the reload")
    case.writable_again()
    svc.wait_event("state_saved_again", after=n0)
    assert svc.stop() == 0
    j = read_journal(s.journal_dir)
    ev = read_events(s.log_file)
    r = int(np.argmax(after_event(j, rel)))  # the reloaded runtime's first row
    assert j["dt_s"][r] == pytest.approx(j["time_s"][r] - j["time_s"][r - 1], abs=2e-3)
    jump = j["predicted_um"][r] - j["predicted_um"][r - 1]
    broken = (
        (j["wall_s"] > t_break + 2 * s.period_s)
        & (j["wall_s"] < rel["ts"] + 8 * s.period_s)
        & ~after_event(j, named(ev, "state_saved_again")[-1])
    )
    problems = []
    # the model's own rate just before, per second of the runtime's step: the reload's row may
    # have a longer step (the reload itself takes time), never a faster rate
    usual = (np.abs(np.diff(j["predicted_um"][r - 10 : r])) / j["dt_s"][r - 9 : r]).max()
    if abs(jump) > 1.5 * usual * j["dt_s"][r] + 0.05:
        problems.append(
            f"the model's elongation jumped {jump:+.2f} um at the reload "
            f"({j['predicted_um'][r - 1]:.2f} -> {j['predicted_um'][r]:.2f}): the reload "
            "restored the last good save instead of the running state"
        )
    for bit in (Alarm.STATE_SAVE_FAILED, Alarm.STATE_STALE):
        off = np.flatnonzero(broken & ~has(j["alarms"], bit))
        if bit is Alarm.STATE_STALE:
            off = off[j["wall_s"][off] > t_break + s.faults["state_stale_s"] + s.period_s]
        if off.size:
            problems.append(
                f"{bit.name} missing on {off.size} row(s) while the state could not be "
                f"saved (rows {off[:6].tolist()}, the reload at row {r})"
            )
    summarize(
        "12",
        "SIGHUP reload while the state cannot be saved",
        "reloads; must go on from the running model state, alarms kept",
        "STATE_SAVE_FAILED, STATE_STALE",
        "-",
        f"elongation jump at the reload {jump:+.2f} um",
    )
    assert not problems, "; ".join(problems)
    check_invariants(j, rate=s.rate, clamp=s.clamp, events=ev, period_s=s.period_s)
