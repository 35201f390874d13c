"""The shared run-log format and model files: one reader, line-numbered errors, atomic writes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import first_order, rich_form
from hypothesis import given, settings
from hypothesis import strategies as st

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
    [
        ("", "no header"),
        ("# only a comment\n", "no header"),
        ("time_s,speed_rpm\n", "no data rows"),
        ("time_s,speed_rpm\n0,0,1,2\n1,0\n", "malformed CSV"),
    ],
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


# -- file modes ----------------------------------------------------------------------------


@pytest.fixture
def umask():
    """Set the process umask for one test (the file modes depend on it), then restore it."""
    import os

    old = os.umask(0o022)
    yield os.umask
    os.umask(old)


def mode_of(path):
    import stat

    return stat.S_IMODE(path.stat().st_mode)


def test_a_saved_model_is_world_readable(tmp_path, umask):
    save_model(tmp_path / "m.json", first_order())
    assert mode_of(tmp_path / "m.json") == 0o644  # 0o044: group and others may read it


def test_atomic_write_follows_the_umask_and_mode(tmp_path, umask):
    from compensator.io import atomic_write, write_text

    write_text(tmp_path / "r.html", "report")
    assert mode_of(tmp_path / "r.html") == 0o644
    with atomic_write(tmp_path / "secret.json", mode=0o600) as fh:
        fh.write("{}")
    assert mode_of(tmp_path / "secret.json") == 0o600
    # overwriting gives the new file its own mode: a private file made public, and back
    write_text(tmp_path / "secret.json", "{}")
    assert mode_of(tmp_path / "secret.json") == 0o644
    umask(0o077)
    write_text(tmp_path / "r.html", "report")
    assert mode_of(tmp_path / "r.html") == 0o600
    with atomic_write(tmp_path / "p.png", "wb") as fh:
        fh.write(b"\x89PNG")
    assert (tmp_path / "p.png").read_bytes() == b"\x89PNG"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.png", "r.html", "secret.json"]


def test_atomic_write_text_is_utf8_and_a_failed_write_keeps_the_old_file(tmp_path):
    from compensator.io import atomic_write, write_text

    p = write_text(tmp_path / "r.md", "growth 3 µm, τ 20 min")
    assert p.read_bytes() == "growth 3 µm, τ 20 min".encode()
    with pytest.raises(RuntimeError, match="disk full"), atomic_write(p) as fh:
        fh.write("half")
        raise RuntimeError("disk full")
    assert p.read_text(encoding="utf-8") == "growth 3 µm, τ 20 min"
    assert [q.name for q in tmp_path.iterdir()] == ["r.md"]  # no temp file left
    with pytest.raises(TypeError, match="permission bits"), atomic_write(p, mode="wb"):
        pass


# -- corrupt model files -------------------------------------------------------------------


def signed(data: dict) -> str:
    """A model file with a valid checksum over ``data``, however wrong ``data`` is."""
    from compensator.io.checksum import digest

    return json.dumps({**data, "sha256": digest(data)})


def augmented():
    from compensator.inputs import AugmentedModel, InputTerm

    term = InputTerm(
        name="t_spindle",
        unit="degC",
        reference=20.0,
        gain_um_per_unit=0.5,
        tau_s=600.0,
        valid_range=(0.0, 80.0),
    )
    return AugmentedModel(speed_model=first_order(), inputs=(term,), fallback=first_order())


def without(data: dict, *keys: str) -> dict:
    out = json.loads(json.dumps(data))
    for key in keys:
        *parents, last = key.split(".")
        d = out
        for k in parents:
            d = d[int(k)] if isinstance(d, list) else d[k]
        del d[last]
    return out


GOOD_MODEL = first_order().model_dump(mode="json")
CORRUPT = {
    "nan": (
        json.dumps(GOOD_MODEL).replace('"fitted_dt_s": 60.0', '"fitted_dt_s": NaN'),
        "NaN is not a JSON number",
    ),
    "infinity": (
        json.dumps({**GOOD_MODEL, "elastic_um": [0, -1e400]}),
        "-Infinity is not a JSON number",
    ),
    "deep array": ("[" * 10_000 + "]" * 10_000, "nested too deeply"),
    "deep in a key": (
        '{"format": "thermocomp.model/1", "fit": ' + "[" * 10_000 + "]" * 10_000 + "}",
        "nested too deeply",
    ),
    "deep but parsable": (
        signed({**GOOD_MODEL, "fit": json.loads("[" * 200 + "]" * 200)}),
        "nested deeper than",
    ),
    "missing states": (signed(without(GOOD_MODEL, "states")), "states: Field required"),
    "missing a coefficient": (
        signed(without(GOOD_MODEL, "states.0.generation_um_per_s")),
        "generation_um_per_s",
    ),
    "missing format": (signed(without(GOOD_MODEL, "format")), "unknown model format None"),
    "no checksum": (json.dumps(GOOD_MODEL), "no sha256"),
    "huge string": ('{"format": "' + "x" * 50_000_000 + '"}', "larger than 8 MiB"),
    "huge format name": ('{"format": "' + "x" * 5_000_000 + '"}', "characters cut"),
    "not utf-8": (b'{"format": "\xff"}', "not a JSON model file"),
    "a list": ("[1, 2]", "top level is not an object"),
    "wrong types": (signed({**GOOD_MODEL, "states": "many"}), "invalid model: states"),
}


@pytest.mark.parametrize("name", sorted(CORRUPT))
def test_corrupt_model_file_is_one_line_model_file_error(tmp_path, name):
    text, expected = CORRUPT[name]
    p = tmp_path / "m.json"
    p.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ModelFileError) as info:
        load_model(p)
    msg = str(info.value)
    assert expected in msg and msg.startswith(str(p)), msg[:300]
    assert "\n" not in msg and len(msg) <= 500


def test_corrupt_model_with_inputs_is_one_line_model_file_error(tmp_path):
    from compensator.io.modelfile import load_any_model

    good = augmented().model_dump(mode="json")
    assert load_any_model(write(tmp_path, signed(good), "ok.json")) == augmented()
    for key, expected in (
        ("inputs.0.gain_um_per_unit", "gain_um_per_unit"),
        ("fallback", "fallback"),
        ("speed_model.states", "states"),
    ):
        p = write(tmp_path, signed(without(good, key)), "m.json")
        with pytest.raises(ModelFileError, match=f"invalid model: .*{expected}") as info:
            load_any_model(p)
        assert "\n" not in str(info.value)
    bad = json.loads(json.dumps(good))
    bad["fallback"]["states"][0]["dissipation_per_s"] = [-1e-4, 0.0]
    with pytest.raises(UnstableModelError, match="unstable"):
        load_any_model(write(tmp_path, signed(bad), "u.json"))


def test_every_truncation_of_a_model_file_is_refused(tmp_path):
    save_model(tmp_path / "m.json", rich_form())
    text = (tmp_path / "m.json").read_text()
    p = tmp_path / "cut.json"
    for n in range(len(text.rstrip())):
        p.write_text(text[:n])
        with pytest.raises(ModelFileError) as info:
            load_model(p)
        assert "\n" not in str(info.value)


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_a_damaged_model_file_loads_or_is_refused_in_one_line(tmp_path_factory, data):
    """Bytes overwritten anywhere: the model loads (a change the checksum cannot see, such as
    blanks) or a ModelFileError / UnstableModelError says why; never anything else."""
    p = tmp_path_factory.mktemp("damaged") / "m.json"
    save_model(p, rich_form())
    raw = bytearray(p.read_bytes())
    for _ in range(data.draw(st.integers(1, 4))):
        at = data.draw(st.integers(0, len(raw) - 1))
        raw[at : at + 1] = data.draw(
            st.sampled_from(
                [
                    b"",
                    b"[",
                    b"{",
                    b"]",
                    b'"',
                    b"9",
                    b"-",
                    b"N",
                    b"\x00",
                    b"\xff",
                    b"NaN",
                    b"1e999",
                    b" ",
                    b"\n",
                ]
            )
        )
    p.write_bytes(bytes(raw))
    try:
        load_model(p)
    except (ModelFileError, UnstableModelError) as err:
        assert "\n" not in str(err)
