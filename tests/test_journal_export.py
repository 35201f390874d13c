"""``thermocomp journal export``: one run log from the runtime's journal (cycles, probe
measurements, chiller commands), read by the run-log reader, replayed, and fitted with sparse
targets. The journal comes from the real runtime on the virtual machine tool (a fake clock:
nothing sleeps) or is written with the journal classes themselves."""

from __future__ import annotations

import argparse
import csv
import json
import math
import runpy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration.replay import replay
from compensator.errors import ConfigError, RunLogError, ThermocompError
from compensator.io import (
    CoolingJournal,
    Journal,
    MeasurementJournal,
    load_any_model,
    read_run_log,
    write_run_log,
)
from compensator.io.retention import day_start_s
from compensator.speed_programs import job_shop_day
from machine_sim import SpindlePlant, preset
from machine_sim.adapter import SimAdapter
from machine_sim.vcnc import SENSOR_KEYS, VirtualMachine
from thermocomp.commands.journal import export
from thermocomp.runtime import SpindleRuntime
from thermocomp.runtime.config import load_config

ROOT = Path(__file__).resolve().parents[1]
WALL0 = day_start_s("2024-04-30") + 22.5 * 3600  # 22:30 UTC: the run crosses midnight
PERIOD_S = 10.0
CYCLES = 1260  # 3.5 h
PROBE_EVERY = 30  # cycles: one measurement each 5 min
COOL_FROM, COOL_EVERY = 20, 6  # cycles: the chiller's first command, then one a minute
ADDED = ["elongation_um", "measurement_sigma_um", "chiller_setpoint_c", "supply_c"]


def namespace(**kw) -> argparse.Namespace:
    base = {
        "journal_dir": None,
        "config": None,
        "spindle": None,
        "from_": None,
        "to": None,
        "output": None,
    }
    return argparse.Namespace(**{**base, **kw})


def rows_of(paths) -> tuple[list[str], list[list[str]]]:
    """Header and rows of CSV files with '# key: value' lines on top (the header of the first)."""
    header, rows = None, []
    for p in paths:
        with open(p, encoding="utf-8") as fh:
            r = csv.reader(line for line in fh if not line.startswith("#"))
            h = next(r)
            header = header or h
            rows += list(r)
    return header, rows


def metadata(path: Path) -> dict[str, str]:
    return read_run_log(path).metadata


def cli_wired() -> bool:
    from thermocomp.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return "journal" in sub.choices


@pytest.fixture(scope="module")
def sim(tmp_path_factory, calibrated_model):
    """3.5 h of the runtime on the virtual machine tool: a measurement every 5 min (`thermocomp
    measure`'s path), a chiller command every minute from the 20th cycle on."""
    tmp = tmp_path_factory.mktemp("journal")
    cfg_path = tmp / "machine.toml"
    cfg_path.write_text(
        "\n".join(
            [
                f'state_dir = "{tmp / "state"}"',
                "watchdog = false",
                "journal_fsync_s = 3600.0",
                "[[spindle]]",
                'name = "s1"',
                f'model = "{calibrated_model}"',
                f"period_s = {PERIOD_S}",
                "state_save_every_s = 600.0",
                'adapter = {url = "sim://motorized-27k?program=job-shop-day&seed=1"}',
                "[spindle.observer]",
                "enabled = true",
            ]
        )
        + "\n"
    )
    cfg = load_config(cfg_path)
    t = {"now": 0.0}
    clock = lambda: t["now"]
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=1), None, clock=clock)
    vm.load_program(job_shop_day(preset("motorized-27k").max_rpm, seed=1, hours=4))
    rt = SpindleRuntime(
        cfg.spindle[0],
        cfg.state_dir,
        cfg.journal_path,
        journal_fsync_s=cfg.journal_fsync_s,
        clock=clock,
        wall=lambda: WALL0 + t["now"],
        adapter=SimAdapter(machine=vm),
    )
    chiller = CoolingJournal(
        cfg.journal_path, "s1", {"spindle": "s1", "source": "test"}, fsync_every_s=3600.0
    )
    rng = np.random.default_rng(0)
    for i in range(CYCLES):
        t["now"] += PERIOD_S
        if i % PROBE_EVERY == PROBE_EVERY - 1:  # fused in this cycle, on its row
            rt.submit(vm.plant.true_elongation_um() + 0.3 * float(rng.standard_normal()), 0.5)
        rt.cycle()
        if i >= COOL_FROM and (i - COOL_FROM) % COOL_EVERY == 0:
            chiller.record(
                rt.anchor_s + t["now"],
                estimate_um=rt.estimate_um(),
                rite_um=10.0,
                phase="pid",
                setpoint_c=round(20.0 + 0.01 * i, 3),
                sent=True,
                supply_c=round(20.5 + 0.01 * i, 3),
                alarm="",
            )
    rt.close()
    chiller.close()
    return {"config": cfg_path, "dir": cfg.journal_path, "model": calibrated_model}


@pytest.fixture(scope="module")
def whole(sim, tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "run.csv"
    assert export(namespace(config=str(sim["config"]), output=str(out))) == 0
    return out


def test_every_row_and_column_of_the_journal_is_kept(sim, whole, capsys):
    days = sorted(sim["dir"].glob("s1-*.csv"))
    assert [p.name for p in days] == ["s1-2024-04-30.csv", "s1-2024-05-01.csv"]
    jh, jrows = rows_of(days)
    header, rows = rows_of([whole])
    assert header == jh + ADDED
    assert len(rows) == len(jrows) == CYCLES
    assert [r[: len(jh)] for r in rows] == jrows  # as written: no cell reformatted
    assert set(SENSOR_KEYS) <= set(jh)  # the input channels the link read
    t = np.array([float(r[0]) for r in rows])
    assert (np.diff(t) > 0).all()
    meta = metadata(whole)
    assert meta["spindle"] == "s1" and meta["source"] == "thermocomp journal export"
    assert meta["from"] == "-" and meta["to"] == "-"
    assert meta["inputs"].split(",") == [c for c in jh if c in SENSOR_KEYS]
    assert set(meta["files"].split(",")) == {p.name for p in sim["dir"].glob("s1*.csv")}
    assert meta["elongation_um"] == "sparse"
    log = read_run_log(whole)
    assert len(log) == CYCLES and log.sparse and log.extras["cutting_source"].dtype == object
    for name in SENSOR_KEYS:
        assert log.extras[name].dtype == float


def test_measurements_land_on_the_row_of_their_cycle(sim, whole):
    _, probes = rows_of(sorted(sim["dir"].glob("s1.measurements-*.csv")))
    taken = {float(p[0]): p for p in probes if p[5] in ("accepted", "restarted")}
    assert len(probes) == CYCLES // PROBE_EVERY and len(taken) >= len(probes) - 3
    header, rows = rows_of([whole])
    e, s = header.index("elongation_um"), header.index("measurement_sigma_um")
    seen = {}
    for r in rows:
        if r[e]:
            seen[float(r[0])] = (r[e], r[s])
        else:
            assert r[s] == ""
    assert seen == {t: (p[1], p[2]) for t, p in taken.items()}
    log = read_run_log(whole)
    assert int(log.measured.sum()) == len(taken) == int(metadata(whole)["measurements"])


def test_chiller_commands_are_carried_forward(sim, whole):
    _, cool = rows_of(sorted(sim["dir"].glob("s1.cooling-*.csv")))
    ct = np.array([float(c[0]) for c in cool])
    header, rows = rows_of([whole])
    sp, su = header.index("chiller_setpoint_c"), header.index("supply_c")
    blank = 0
    for r in rows:
        k = int(np.searchsorted(ct, float(r[0]), side="right")) - 1
        if k < 0:
            blank += 1
            assert r[sp] == r[su] == ""
        else:
            assert (r[sp], r[su]) == (cool[k][4], cool[k][6])
    assert blank == COOL_FROM


def test_a_range_takes_its_rows_only_and_what_came_before(sim, tmp_path):
    out = tmp_path / "r.csv"
    # 02:00+02:00 is 00:00 UTC: the day file of 2024-05-01 starts exactly there
    export(
        namespace(
            journal_dir=str(sim["dir"]),
            from_="2024-05-01T02:00+02:00",
            to="2024-05-01T01:00",
            output=str(out),
        )
    )
    header, rows = rows_of([out])
    t = np.array([float(r[0]) for r in rows])
    lo, hi = day_start_s("2024-05-01"), day_start_s("2024-05-01") + 3600
    assert t[0] == lo and t[-1] == hi - PERIOD_S and len(rows) == 360 and (np.diff(t) > 0).all()
    meta = metadata(out)
    assert meta["from"] == "2024-05-01T00:00:00Z" and meta["to"] == "2024-05-01T01:00:00Z"
    # the first row's chiller command comes from the day before's file
    _, cool = rows_of(sorted(sim["dir"].glob("s1.cooling-*.csv")))
    before = [c for c in cool if float(c[0]) <= lo][-1]
    assert rows[0][header.index("chiller_setpoint_c")] == before[4]
    assert "s1.cooling-2024-04-30.csv" in meta["files"].split(",")
    # a date alone: that day from 00:00 UTC
    export(namespace(journal_dir=str(sim["dir"]), from_="2024-05-01", output=str(out)))
    t2 = [float(r[0]) for r in rows_of([out])[1]]
    assert t2[0] == lo and len(t2) == CYCLES - int((lo - WALL0) / PERIOD_S) + 1


def test_parts_are_merged_repeated_instants_dropped_and_a_torn_row_skipped(tmp_path):
    d = tmp_path / "j"
    t0 = day_start_s("2024-06-01") + 3600
    first = Journal(d, "m2", {"spindle": "m2"}, input_columns=("ambient_c",), fsync_every_s=-1)
    for k in range(10):
        first.write(t0 + k, 1000.0, 1.0, -1.0, True, 0, 0, dt_s=1.0, inputs={"ambient_c": 20.0 + k})
    first.close()
    # a second run after the clock was set back 5 s: its rows go to part 2
    second = Journal(d, "m2", {"spindle": "m2"}, input_columns=("ambient_c",), fsync_every_s=-1)
    for k in range(5, 15):
        second.write(
            t0 + k,
            2000.0,
            2.0,
            -2.0,
            True,
            0,
            0,
            dt_s=1.0,
            inputs={} if k == 7 else {"ambient_c": 30.0},
        )
    second.close()
    probes = MeasurementJournal(d, "m2", {"spindle": "m2"}, fsync_every_s=-1)
    probes.record(
        t0 + 2.5, elongation_um=3.25, sigma_um=0.5, source="setter", sequence=1, outcome="accepted"
    )
    probes.record(
        t0 + 3.0, elongation_um=9.0, sigma_um=0.5, source="setter", sequence=2, outcome="rejected"
    )
    probes.record(
        t0 + 11.2, elongation_um=4.0, sigma_um=0.5, source="setter", sequence=3, outcome="accepted"
    )
    probes.record(
        t0 + 11.7, elongation_um=4.5, sigma_um=0.4, source="setter", sequence=4, outcome="restarted"
    )
    probes.close()
    assert sorted(p.name for p in d.iterdir()) == [
        "m2-2024-06-01.csv",
        "m2-2024-06-01.p2.csv",
        "m2.measurements-2024-06-01.csv",
    ]
    with open(d / "m2-2024-06-01.p2.csv", "a", encoding="utf-8") as fh:
        fh.write(f"{t0 + 20:.3f},3000,3")  # a row being written: no newline yet
    out = tmp_path / "m2.csv"
    export(namespace(journal_dir=str(d), output=str(out)))
    log = read_run_log(out)
    np.testing.assert_array_equal(log.time_s, t0 + np.arange(15))
    np.testing.assert_array_equal(
        log.speed_rpm, [1000] * 10 + [2000] * 5
    )  # part 1 kept where both have a row
    amb = log.extras["ambient_c"]
    assert amb[3] == 23.0 and amb[12] == 30.0 and np.isnan(log.extras["ambient_c"][7]) is np.False_
    assert "chiller_setpoint_c" not in log.extras  # no cooling journal: no cooling columns
    e = log.elongation_um
    assert e[3] == 3.25 and e[12] == 4.5 and np.isnan(e[[0, 1, 2, 4, 11, 13]]).all()
    assert log.extras["measurement_sigma_um"][12] == 0.4
    assert log.metadata["inputs"] == "ambient_c" and log.metadata["measurements"] == "2"


def test_replay_reports_its_error_on_the_measured_rows(sim, whole, capsys):
    from thermocomp.cli import main

    model = load_any_model(sim["model"])
    log = read_run_log(whole)
    rep = replay(model, log)
    m = log.measured
    r = log.elongation_um[m] - rep.predicted_um[m]
    assert rep.report["measured_samples"] == int(m.sum()) > 30
    assert rep.report["rms_residual_um"] == pytest.approx(float(np.sqrt(np.mean(r * r))))
    assert rep.report["max_abs_residual_um"] == pytest.approx(float(np.abs(r).max()))
    assert rep.report["ste_source"] == "predicted" and math.isfinite(
        rep.report["applied_rms_residual_um"]
    )
    assert any("measured on" in w and "sparse" in w for w in rep.report["warnings"])
    for row in rep.report["policies"]:
        assert math.isfinite(row["rms_um"])
    out = whole.parent / "replayed.csv"
    assert (
        main(
            [
                "replay",
                str(whole),
                "--model",
                str(sim["model"]),
                "--config",
                str(sim["config"]),
                "--output",
                str(out),
                "--json",
            ]
        )
        == 0
    )
    rp = json.loads(capsys.readouterr().out)
    assert rp["measured_samples"] == int(m.sum()) and math.isfinite(rp["rms_residual_um"])
    again = read_run_log(out)  # the replay's own output reads back (its elongation is sparse too)
    assert again.sparse and int(again.measured.sum()) == int(m.sum())


@pytest.mark.parametrize(
    "kw,error,match",
    [
        (
            {"from_": "2024-06-01", "to": "2024-06-02"},
            RunLogError,
            r"no journal rows of spindle s1 in \[2024-06-01",
        ),
        ({"from_": "yesterday"}, ConfigError, "--from 'yesterday': not an ISO date"),
        ({"to": "2024-05-01T25:00"}, ConfigError, "--to '2024-05-01T25:00': not an ISO date"),
        ({"from_": "2024-05-01", "to": "2024-04-30"}, ConfigError, "is not before --to"),
        ({"spindle": "s9"}, ConfigError, "no journal of spindle 's9'"),
    ],
)
def test_errors_are_one_line(sim, tmp_path, kw, error, match):
    out = tmp_path / "x.csv"
    with pytest.raises(error, match=match) as exc:
        export(namespace(journal_dir=str(sim["dir"]), output=str(out), **kw))
    assert isinstance(exc.value, ThermocompError) and "\n" not in str(exc.value)
    assert not out.exists()


def test_directory_with_two_spindles_needs_one_named(tmp_path):
    for name in ("a", "b"):
        j = Journal(tmp_path, name, {}, fsync_every_s=-1)
        j.write(day_start_s("2024-06-01") + 10, 100.0, 0.0, 0.0, False, 0, 0)
        j.close()
    with pytest.raises(ConfigError, match=r"2 spindles \(a, b\): name one with --spindle"):
        export(namespace(journal_dir=str(tmp_path), output=str(tmp_path / "x.csv")))
    with pytest.raises(ConfigError, match=r"\(--journal-dir\) or the runtime configuration"):
        export(namespace(output=str(tmp_path / "x.csv")))
    assert (
        export(namespace(journal_dir=str(tmp_path), spindle="b", output=str(tmp_path / "b.csv")))
        == 0
    )
    assert read_run_log(tmp_path / "b.csv").metadata["spindle"] == "b"


@pytest.mark.skipif(
    not cli_wired(), reason="`thermocomp journal` is not wired into thermocomp/cli.py yet"
)
def test_cli_exit_codes(sim, tmp_path, capsys):
    from thermocomp.cli import main

    out = tmp_path / "c.csv"
    assert (
        main(
            [
                "journal",
                "export",
                "--journal-dir",
                str(sim["dir"]),
                "--from",
                "2024-05-01",
                "--output",
                str(out),
            ]
        )
        == 0
    )
    assert out.exists() and capsys.readouterr().out.count("\n") == 1
    for bad in (["--from", "2030-01-01"], ["--to", "noon"]):
        assert (
            main(["journal", "export", "--config", str(sim["config"]), *bad, "--output", str(out)])
            != 0
        )
        err = capsys.readouterr().err
        assert err.startswith("thermocomp: error: ") and err.count("\n") == 1


def test_the_export_needs_neither_pandas_nor_scipy(sim, tmp_path):
    # (with --config, load_config validates the adapter's settings: sim:// brings its plant's scipy)
    code = (
        "import sys, argparse\n"
        "from thermocomp.commands.journal import export\n"
        f"ns = argparse.Namespace(journal_dir={str(sim['dir'])!r}, config=None, spindle=None, "
        f"from_='2024-05-01', to=None, output={str(tmp_path / 'e.csv')!r})\n"
        "assert export(ns) == 0\n"
        "heavy = [m for m in ('pandas', 'scipy', 'statsmodels', 'matplotlib') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=False
    )
    assert r.returncode == 0, r.stderr


# -- fit on an export ------------------------------------------------------------------------------

T0 = day_start_s("2023-11-14") + 6 * 3600


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    channels = runpy.run_path(str(ROOT / "tests/data/real-spindle/channels.py"))["write_channels"]
    return channels(tmp_path_factory.mktemp("real"), ("ch1", "ch3"))


def journal_of(log, directory: Path, probe_every: int) -> None:
    """Write a run log as the runtime would have journaled it: its extra columns as input
    channels, a tool-setter measurement on every ``probe_every``-th row."""
    names = tuple(log.extras)
    j = Journal(directory, "r1", {"spindle": "r1"}, input_columns=names, fsync_every_s=-1)
    m = MeasurementJournal(directory, "r1", {"spindle": "r1"}, fsync_every_s=-1)
    dt = np.diff(log.time_s, prepend=log.time_s[0])
    for k, (t, n) in enumerate(zip(log.time_s, log.speed_rpm)):
        j.write(
            T0 + t,
            n,
            0.0,
            0.0,
            False,
            0,
            0,
            dt_s=dt[k],
            inputs={c: log.extras[c][k] for c in names},
        )
        if k % probe_every == 0:
            m.record(
                T0 + t,
                elongation_um=float(log.elongation_um[k]),
                sigma_um=0.5,
                source="setter",
                sequence=k,
                outcome="accepted",
            )
    j.close()
    m.close()


def fit_json(capsys, *args) -> dict:
    from thermocomp.cli import main

    capsys.readouterr()
    assert main(["fit", *map(str, args), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_a_densely_measured_export_fits_like_the_run_log(real, tmp_path, capsys):
    log = read_run_log(real["ch3"])
    journal_of(log, tmp_path / "j", probe_every=1)
    out = tmp_path / "export.csv"
    export(namespace(journal_dir=str(tmp_path / "j"), output=str(out)))
    exported = read_run_log(out)
    assert (
        not exported.sparse
        and len(exported) == len(log)
        and "elongation_um" not in exported.metadata
    )
    same = tmp_path / "same.csv"  # the equivalent run log: the same numbers, on the same clock
    write_run_log(
        same,
        {
            "time_s": log.time_s + T0,
            "speed_rpm": log.speed_rpm,
            "elongation_um": log.elongation_um,
            **log.extras,
        },
    )
    # three temperatures: the equivalence is the export's, not the many-input structures'
    names = sorted(log.extras)[:3]
    common = ("--inputs", ",".join(names), "--no-physical", "--no-nested")
    a = fit_json(capsys, out, *common, "--output", tmp_path / "a.json")
    b = fit_json(capsys, same, *common, "--output", tmp_path / "b.json")
    assert (
        a["chosen"] == b["chosen"]
        and a["chosen"].startswith("ridge+")
        and a["scored_by"] == b["scored_by"]
    )
    for ca, cb in zip(a["candidates"], b["candidates"]):
        assert ca["name"] == cb["name"] and ca["cv_rms_um"] == pytest.approx(
            cb["cv_rms_um"], rel=1e-9
        )
    ma, mb = load_any_model(tmp_path / "a.json"), load_any_model(tmp_path / "b.json")
    assert [c.name for c in ma.inputs] == [c.name for c in mb.inputs] == names
    np.testing.assert_allclose(ma.drive_um, mb.drive_um, rtol=1e-9)


def test_a_sparsely_measured_export_fits_on_its_measured_rows(real, tmp_path, capsys):
    from thermocomp.cli import main

    log = read_run_log(real["ch1"])
    journal_of(log, tmp_path / "j", probe_every=20)  # a probe every 5 min
    out = tmp_path / "export.csv"
    export(namespace(journal_dir=str(tmp_path / "j"), output=str(out)))
    exported = read_run_log(out)
    assert exported.sparse and int(exported.measured.sum()) == math.ceil(len(log) / 20)
    rep = fit_json(capsys, out, "--output", tmp_path / "s.json")
    assert rep["scored_by"] == "leave-one-cycle-out (on the measured rows) free run"
    assert len(rep["folds"]) == 5 and rep["chosen"] in ("ridge", "exp-baseline")
    assert any(
        w.startswith("sparse targets: fitted and scored on the 480 measured rows of 9600")
        for w in rep["warnings"]
    )
    dense = fit_json(capsys, real["ch1"], "--no-physical", "--output", tmp_path / "d.json")
    # fitted on one row in twenty, it predicts every row of the dense log about as well
    errs = {}
    for name in ("s", "d"):
        pred = load_any_model(tmp_path / f"{name}.json").simulate_um(
            log.speed_rpm, log.time_s, None, None
        )
        errs[name] = float(np.sqrt(np.mean((log.elongation_um - pred) ** 2)))
    assert errs["s"] < 1.25 * errs["d"], (errs, dense["chosen"])
    # what needs every row says so in one line
    for extra, match in ((["--probe-every", "1800"], "--probe-every plans the closed loop"),):
        capsys.readouterr()
        assert main(["fit", str(out), *extra, "--output", str(tmp_path / "x.json")]) == 2
        err = capsys.readouterr().err
        assert match in err and err.count("\n") == 1
    assert not (tmp_path / "x.json").exists()


def test_one_identification_for_dense_and_sparse_logs(real):
    """Dense and sparse logs go through the one registry: the same log with most rows blanked
    keeps the candidates that fit on the measured rows, leaves out the one that needs every row
    (the paper's OLS, and says so), and scores the rest on the measured rows of the same cycles."""
    from calibration.identify import REGISTRY, LogData, identify

    log = read_run_log(real["ch1"])
    data = [LogData("ch1", log.time_s, log.speed_rpm, log.elongation_um)]
    dense = identify(data, probe_target_um=None)
    assert [c.name for c in dense.candidates] == [e.name for e in REGISTRY if not e.needs_inputs]
    blank = np.where(np.arange(log.time_s.size) % 20 == 0, log.elongation_um, np.nan)
    sparse = identify(
        [LogData("ch1", log.time_s, log.speed_rpm, blank)]
    )  # a plan asked for, not made
    assert [c.name for c in sparse.candidates] == [
        e.name for e in REGISTRY if not (e.every_row or e.needs_inputs)
    ]
    assert sparse.dataset.cycles == dense.dataset.cycles
    assert int(sparse.dataset.measured.sum()) == int(np.ceil(log.time_s.size / 20))
    assert any("left out" in w for w in sparse.warnings) and not any(
        "left out" in w for w in dense.warnings
    )
    for c in sparse.candidates:
        d = next(x for x in dense.candidates if x.name == c.name)
        assert math.isfinite(c.honest_rms_um) and c.honest_rms_um == pytest.approx(
            d.honest_rms_um, rel=0.25
        )
    assert sparse.closed_loop is None


def test_blank_input_cells_hold_the_last_value_so_the_export_fits(tmp_path):
    """A cycle whose inputs were not read (link down, a failed read, a NaN) journals blanks; the
    export holds the last value read (the first one, before any), counts them, and reads back
    with every input finite."""
    from compensator.io import Journal, export_journal

    j = Journal(tmp_path / "j", "s1", {"spindle": "s1"}, input_columns=("temp_c", "load_pct"))
    t0 = 1_700_000_000.0
    temps = [None, 20.0, 20.5, None, None, 21.5, 22.0]
    for k, temp in enumerate(temps):
        j.write(
            t0 + k,
            1000.0,
            1.0,
            -1.0,
            True,
            0,
            0,
            dt_s=1.0,
            inputs={"temp_c": float("nan") if k == 4 else temp, "load_pct": 10.0 + k},
        )
    j.close()
    done = export_journal(tmp_path / "j", tmp_path / "out.csv")
    assert done.filled_cells == 3
    log = read_run_log(tmp_path / "out.csv")
    assert list(log.extras["temp_c"]) == [20.0, 20.0, 20.5, 20.5, 20.5, 21.5, 22.0]
    assert list(log.extras["load_pct"]) == [10.0 + k for k in range(7)]


@pytest.mark.parametrize("names", [("cutting",), ("t.1",), ("a", "a"), ("",)])
def test_an_input_channel_name_the_journal_cannot_carry_is_a_config_error(tmp_path, names):
    from compensator.io import Journal

    with pytest.raises(ConfigError, match="input channel names"):
        Journal(tmp_path, "s1", {}, input_columns=names)
