"""The shared run-log format and model files: one reader, line-numbered errors, atomic writes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import first_order, rich_form

from compensator import ModelFileError, RunLogError, UnstableModelError
from compensator.io import load_model, read_run_log, save_model, write_run_log


def write(tmp_path, text, name="run.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


GOOD = """# spindle_id: sp1
# sensor: eddy-current
time_s,speed_rpm,elongation_um,ambient_c,note

0,0,0.0,22.0,start
60,3000,1.5,22.1,x
# operator paused here
120,3000,2.5,22.1,y
"""


def test_reads_columns_extras_metadata(tmp_path):
    log = read_run_log(write(tmp_path, GOOD))
    assert len(log) == 3
    np.testing.assert_array_equal(log.time_s, [0, 60, 120])
    np.testing.assert_array_equal(log.elongation_um, [0, 1.5, 2.5])
    assert set(log.extras) == {"ambient_c", "note"}
    assert log.extras["ambient_c"].dtype == float
    assert list(log.extras["note"]) == ["start", "x", "y"]
    assert log.metadata == {"spindle_id": "sp1", "sensor": "eddy-current"}
    assert log.line_of(2) == 8


def test_elongation_is_optional(tmp_path):
    log = read_run_log(write(tmp_path, "time_s,speed_rpm\n0,0\n1,100\n"))
    assert log.elongation_um is None


@pytest.mark.parametrize(
    "text,line,match",
    [
        ("time_s,elongation_um\n0,1\n", 1, "missing column.*speed_rpm"),
        ("time_s,speed_rpm\n0,0\n1,abc\n2,0\n", 3, "speed_rpm: 'abc'"),
        ("# c\ntime_s,speed_rpm\n0,0\n\n1,\n2,0\n", 5, "speed_rpm: empty cell"),
        ("time_s,speed_rpm,elongation_um\n0,0,0\n1,0,nan\n", 3, "elongation_um"),
        ("time_s,speed_rpm\n0,0\n5,0\n4,0\n", 4, "time does not increase"),
        ("time_s,speed_rpm\n0,0\n5,0\n5,0\n", 4, "time does not increase"),
        ("time_s,speed_rpm\n0,0\n1,inf\n", 3, "not a finite number"),
    ],
)
def test_errors_name_file_and_line(tmp_path, text, line, match):
    p = write(tmp_path, text)
    with pytest.raises(RunLogError, match=match) as exc:
        read_run_log(p)
    assert exc.value.line == line
    assert str(exc.value).startswith(f"{p}:{line}: ")
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize(
    "text,match",
    [("", "no header"), ("# only a comment\n", "no header"), ("time_s,speed_rpm\n", "no data rows"),
     ("time_s,speed_rpm\n0,0,1,2\n1,0\n", "malformed CSV")],
)
def test_structural_errors_are_one_line(tmp_path, text, match):
    with pytest.raises(RunLogError, match=match) as exc:
        read_run_log(write(tmp_path, text))
    assert "\n" not in str(exc.value)


def test_missing_file_is_a_run_log_error(tmp_path):
    with pytest.raises(RunLogError, match="cannot read"):
        read_run_log(tmp_path / "nope.csv")


def test_gaps_are_allowed_and_reported(tmp_path):
    rows = "\n".join(f"{t},{1000}" for t in [0, 1, 2, 3, 100, 101, 102])
    log = read_run_log(write(tmp_path, "time_s,speed_rpm\n" + rows + "\n"))
    assert len(log.gaps) == 1
    g = log.gaps[0]
    assert (g.start_s, g.duration_s, g.line) == (3.0, 97.0, 6)


def test_write_then_read_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    cols = {
        "time_s": np.arange(100) * 0.1,
        "speed_rpm": rng.uniform(0, 27000, 100).round(1),
        "elongation_um": rng.normal(10, 3, 100),
        "offset_um": rng.normal(-10, 3, 100),
        "flags": rng.integers(0, 32, 100),
    }
    p = tmp_path / "out" / "log.csv"
    write_run_log(p, cols, {"model": "m.json"})
    log = read_run_log(p)
    np.testing.assert_allclose(log.elongation_um, cols["elongation_um"], rtol=1e-8)
    np.testing.assert_array_equal(log.extras["flags"], cols["flags"])
    assert log.metadata == {"model": "m.json"}
    assert [f.name for f in p.parent.iterdir()] == ["log.csv"]  # no temp files left


@pytest.mark.parametrize("factory", [first_order, rich_form])
def test_model_file_round_trip(tmp_path, factory):
    m = factory(spindle_id="sp-7") if factory is first_order else factory()
    p = tmp_path / "m.json"
    save_model(p, m)
    assert load_model(p) == m
    assert json.loads(p.read_text())["format"] == "thermocomp.model/1"


def test_tampered_model_is_refused(tmp_path):
    p = tmp_path / "m.json"
    save_model(p, first_order())
    data = json.loads(p.read_text())
    data["states"][0]["generation_um_per_s"][1] *= 1.01
    p.write_text(json.dumps(data))
    with pytest.raises(ModelFileError, match="checksum mismatch"):
        load_model(p)


def test_unknown_format_and_garbage_are_refused(tmp_path):
    p = write(tmp_path, json.dumps({"format": "someone-else/3"}), "m.json")
    with pytest.raises(ModelFileError, match="unknown model format"):
        load_model(p)
    p = write(tmp_path, "{not json", "g.json")
    with pytest.raises(ModelFileError, match="not a JSON"):
        load_model(p)


def test_unstable_model_file_is_refused_with_checksum_intact(tmp_path):
    import hashlib

    from compensator.io.checksum import canonical as _canonical

    data = first_order().model_dump(mode="json")
    data["states"][0]["dissipation_per_s"] = [-1e-4, 0.0]
    data["sha256"] = hashlib.sha256(_canonical(data).encode()).hexdigest()
    p = write(tmp_path, json.dumps(data), "u.json")
    with pytest.raises(UnstableModelError, match="unstable"):
        load_model(p)
