"""Journal retention (compensator.io.retention): old journal files go, by age then by size, never
today's, the ones being written or anything that is not a journal file."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from compensator.io import SweepResult, sweep
from compensator.io.retention import DAY_S, JournalFile, day_start_s, parse_name, plan, utc_day

NOW = day_start_s("2024-05-01") + 13 * 3600.0  # 2024-05-01 13:00 UTC


def day(offset: int) -> str:
    """The UTC day ``offset`` days from NOW's."""
    return utc_day(NOW + offset * DAY_S)


def put(d: Path, name: str, size: int) -> Path:
    p = d / name
    p.write_bytes(b"x" * size)
    return p


@pytest.mark.parametrize(
    "name,expected",
    [
        ("s1-2024-05-01.csv", ("2024-05-01", 1, "cycles", "s1")),
        ("s1-2024-05-01.p3.csv", ("2024-05-01", 3, "cycles", "s1")),
        ("s1.measurements-2024-04-30.csv", ("2024-04-30", 1, "measurements", "s1")),
        ("s1.cooling-2024-04-30.p2.csv", ("2024-04-30", 2, "cooling", "s1")),
        ("spindle-A_2-2023-12-31.csv", ("2023-12-31", 1, "cycles", "spindle-A_2")),
        ("left.z-2024-02-29.csv", ("2024-02-29", 1, "cycles", "left.z")),
    ],
)
def test_journal_names_are_recognised(name, expected):
    f = parse_name(name)
    assert f is not None and (f.day, f.part, f.kind, f.spindle) == expected and f.name == name


@pytest.mark.parametrize(
    "name",
    [
        "s1-2024-02-30.csv",  # no such day
        "s1-2024-05-01.p1.csv",  # the first part has no suffix
        "s1-2024-05-01.csv.tmp",
        ".s1-2024-05-01.csv.3f2a.tmp",
        "s1.state.json",
        "s1-2024-05-01.json",
        "s1-24-05-01.csv",
        "-2024-05-01.csv",
        "notes.csv",
        "s1-2024-05-01.p0.csv",
    ],
)
def test_other_names_are_not_journal_files(name):
    assert parse_name(name) is None


def test_files_older_than_the_age_go_and_nothing_else(tmp_path):
    old = [
        put(tmp_path, f"s1-{day(-120)}.csv", 10),
        put(tmp_path, f"s1.measurements-{day(-92)}.csv", 10),
        put(tmp_path, f"s2.cooling-{day(-91)}.p2.csv", 10),
    ]
    young = [
        put(tmp_path, f"s1-{day(-90)}.csv", 10),  # its day ended 89.5 days ago
        put(tmp_path, f"s1-{day(-1)}.csv", 10),
        put(tmp_path, f"s1-{day(0)}.csv", 10),
    ]
    other = [
        put(tmp_path, f"s1-{day(-200)}.csv.bak", 10),
        put(tmp_path, "s1.state.json", 10),
        put(tmp_path, f"s1-{day(-300)}.p1.csv", 10),
    ]
    (tmp_path / f"dir-{day(-300)}.csv").mkdir()  # a directory named like a journal file
    os.symlink(young[0], tmp_path / f"link-{day(-300)}.csv")
    res = sweep(tmp_path, now_wall_s=NOW, max_age_days=90)
    assert isinstance(res, SweepResult)
    assert sorted(res.removed) == sorted(old) and res.freed_bytes == 30 and res.total_bytes == 30
    assert res.errors == ()
    for p in young + other:
        assert p.exists()
    assert (tmp_path / f"dir-{day(-300)}.csv").is_dir() and (
        tmp_path / f"link-{day(-300)}.csv"
    ).is_symlink()


def test_over_the_size_the_oldest_go_first_by_day_then_part(tmp_path):
    a = put(tmp_path, f"s1-{day(-3)}.csv", 100)
    b = put(tmp_path, f"s1-{day(-3)}.p2.csv", 100)
    c = put(tmp_path, f"s2.measurements-{day(-2)}.csv", 100)
    d = put(tmp_path, f"s1-{day(-1)}.csv", 100)
    e = put(tmp_path, f"s1-{day(0)}.csv", 100)
    put(tmp_path, "big-unrelated.bin", 10_000)  # not a journal file: neither counted nor removed
    res = sweep(tmp_path, now_wall_s=NOW, max_bytes=250)
    assert list(res.removed) == [a, b, c] and res.freed_bytes == 300 and res.total_bytes == 200
    assert d.exists() and e.exists() and (tmp_path / "big-unrelated.bin").exists()


def test_kept_files_and_today_stay_even_over_the_size(tmp_path):
    kept = put(tmp_path, f"s1-{day(-5)}.csv", 500)
    other = put(tmp_path, f"s1.cooling-{day(-4)}.csv", 500)
    today = put(tmp_path, f"s1.measurements-{day(0)}.csv", 500)
    future = put(tmp_path, f"s1-{day(2)}.csv", 500)  # the wall clock was set back
    res = sweep(tmp_path, now_wall_s=NOW, max_bytes=100, keep=[kept])
    assert res.removed == (other,) and res.total_bytes == 1500
    assert kept.exists() and today.exists() and future.exists()


def test_keep_may_be_relative_and_from_another_directory_it_keeps_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "j").mkdir()
    a = put(tmp_path / "j", f"s1-{day(-2)}.csv", 10)
    res = sweep("j", now_wall_s=NOW, max_bytes=0, keep=[Path("j") / a.name, None])
    assert res.removed == ()
    res = sweep(tmp_path / "j", now_wall_s=NOW, max_bytes=0, keep=[tmp_path / a.name])
    assert res.removed == (tmp_path / "j" / a.name,)


def test_an_os_error_is_collected_never_raised(tmp_path, monkeypatch):
    bad = put(tmp_path, f"s1-{day(-200)}.csv", 10)
    good = put(tmp_path, f"s1-{day(-150)}.csv", 10)
    real = os.unlink

    def unlink(path, *a, **k):
        if Path(path) == bad:
            raise PermissionError(13, "Permission denied", str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(os, "unlink", unlink)
    res = sweep(tmp_path, now_wall_s=NOW)
    assert res.removed == (good,) and res.freed_bytes == 10 and res.total_bytes == 10
    assert (
        len(res.errors) == 1 and str(bad) in res.errors[0] and "Permission denied" in res.errors[0]
    )
    assert bad.exists()
    # a missing directory: nothing to do; one that cannot be listed: an error, no exception
    assert sweep(tmp_path / "nope", now_wall_s=NOW) == SweepResult()
    monkeypatch.setattr(
        os, "scandir", lambda d: (_ for _ in ()).throw(PermissionError(13, "Permission denied"))
    )
    res = sweep(tmp_path, now_wall_s=NOW)
    assert res.removed == () and len(res.errors) == 1 and "Permission denied" in res.errors[0]


def test_plan_is_pure_and_orders_by_day_then_part():
    files = {
        JournalFile(day(-k), p, "cycles", "s1", f"s1-{day(-k)}.p{p}.csv"): 10
        for k in (1, 2)
        for p in (2, 3)
    }
    order = plan(files, now_wall_s=NOW, max_age_days=90, max_bytes=0)
    assert [(f.day, f.part) for f in order] == [
        (day(-2), 2),
        (day(-2), 3),
        (day(-1), 2),
        (day(-1), 3),
    ]
    assert plan(files, now_wall_s=NOW, max_age_days=90, max_bytes=40) == []


# -- the property ----------------------------------------------------------------------------

journal_file = st.tuples(
    st.sampled_from(["s1", "s-2", "a.b"]),
    st.sampled_from(["", ".measurements", ".cooling"]),
    st.integers(-200, 3),
    st.integers(1, 3),
    st.integers(0, 3000),
)
other_file = st.tuples(
    st.sampled_from(
        [
            "notes.txt",
            "s1.state.json",
            "x.csv",
            "s1-2024-13-01.csv",
            "s1-2024-04-01.p1.csv",
            "s1-2024-04-01.csv.bak",
        ]
    ),
    st.integers(0, 3000),
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    files=st.lists(journal_file, max_size=25),
    others=st.lists(other_file, max_size=4),
    max_bytes=st.integers(0, 40_000),
    max_age=st.floats(0.5, 300),
    keep_mask=st.lists(st.booleans(), max_size=25),
    now_offset=st.floats(0, DAY_S - 1),
)
def test_after_a_sweep_the_journal_fits_unless_only_protected_files_remain(
    files, others, max_bytes, max_age, keep_mask, now_offset
):
    now = day_start_s("2024-05-01") + now_offset
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        paths: dict[Path, int] = {}
        for spindle, kind, off, part, size in files:
            name = (
                f"{spindle}{kind}-{utc_day(now + off * DAY_S)}"
                + (f".p{part}" if part > 1 else "")
                + ".csv"
            )
            paths[put(d, name, size)] = size
        foreign = {put(d, name, size): size for name, size in others}
        keep = [p for p, k in zip(paths, keep_mask) if k]
        res = sweep(d, now_wall_s=now, max_age_days=max_age, max_bytes=max_bytes, keep=keep)
        left = {p: s for p, s in paths.items() if p.exists()}
        assert set(res.removed) == set(paths) - set(left)
        assert res.freed_bytes == sum(paths[p] for p in res.removed)
        assert res.total_bytes == sum(left.values()) and res.errors == ()
        today = utc_day(now)

        def protected(p: Path) -> bool:
            f = parse_name(p.name)
            return p in keep or f.day >= today

        # never today's (or later), a kept one, or a file that is not a journal file
        assert all(not protected(p) for p in res.removed)
        assert all(p.exists() and p.stat().st_size == s for p, s in foreign.items())
        # within the size, unless only protected files remain
        assert res.total_bytes <= max_bytes or all(protected(p) for p in left)
        # nothing unprotected older than the age is left
        assert all(
            protected(p) or parse_name(p.name).day_end_s >= now - max_age * DAY_S for p in left
        )


def test_the_service_sweeps_its_journal_at_start_and_hourly(tmp_path, calibrated_model, caplog):
    """The running service applies [journal]: days past the age go at the first tick, then the
    oldest past the size an hour later; its own files and other files stay."""
    import logging
    import time as _time

    from thermocomp.runtime import Service

    wall0 = 1_700_000_000.0  # 2023-11-14 22:13 UTC
    jdir = tmp_path / "state" / "journal"
    jdir.mkdir(parents=True)
    old = [
        jdir / f"s1-{_time.strftime('%Y-%m-%d', _time.gmtime(wall0 - d * DAY_S))}.csv"
        for d in (120, 100)
    ]
    recent = [
        jdir / f"s1.measurements-{_time.strftime('%Y-%m-%d', _time.gmtime(wall0 - d * DAY_S))}.csv"
        for d in (30, 20)
    ]
    for p in old + recent:
        p.write_bytes(b"x" * 400_000)
    other = jdir / "notes.txt"
    other.write_text("keep me")
    cfg = tmp_path / "m.toml"
    cfg.write_text(
        f'state_dir = "{tmp_path / "state"}"\nwatchdog = false\n'
        "[status]\nenabled = false\n[journal]\nmax_age_days = 90\nmax_size_mb = 0.5\n"
        f'[[spindle]]\nname = "s1"\nmodel = "{calibrated_model}"\nadapter = {{url = "sim://"}}\n'
    )
    t = [0.0]
    svc = Service(
        cfg,
        clock=lambda: t[0],
        wall=lambda: wall0 + t[0],
        lock=False,
        clock_synchronized=lambda: True,
    )
    with caplog.at_level(logging.INFO, logger="thermocomp.runtime"):
        svc.tick()
        assert not any(p.exists() for p in old)  # past 90 days
        assert not recent[0].exists() and recent[1].exists()  # the oldest, to get under 0.5 MB
        late = (
            jdir / f"s1.cooling-{_time.strftime('%Y-%m-%d', _time.gmtime(wall0 - 95 * DAY_S))}.csv"
        )
        late.write_text("x")
        while t[0] < 3590.0:
            t[0] += 1.0
            svc.tick()
        assert late.exists()  # not before the next sweep, an hour on
        while t[0] < 3610.0:
            t[0] += 1.0
            svc.tick()
        assert not late.exists()
    svc.close()
    assert other.read_text() == "keep me"  # not a journal file
    assert svc.spindles["s1"].journal.path.exists()  # its own file, of today
    assert sum(getattr(r, "event", None) == "journal_swept" for r in caplog.records) == 2
