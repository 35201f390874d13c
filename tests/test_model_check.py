"""``thermocomp model check FILE``: would the runtime take this model file? And ``model schema``
of every registered format. In process through the CLI's ``main``."""

from __future__ import annotations

import json

import pytest

from compensator.io import MODEL_TYPES, model_digest, save_model
from compensator.io.checksum import digest
from compensator.model import MODEL_FORMAT, ThermalModel
from compensator.statespace import STATE_SPACE_FORMAT, InputChannel, StateSpaceModel
from thermocomp.cli import main


def speed_only() -> StateSpaceModel:
    return StateSpaceModel(
        fitted_dt_s=15,
        speed_range_rpm=(0, 10000),
        taus_s=(600.0, 5400.0),
        drive_um=((0.5, 0.05), (2.0, 0.2)),
        feedthrough_um=(0.1, 0.0),
        offset_um=0.0,
        max_measured_um=40.0,
        spindle_id="sp-A",
    )


def with_inputs() -> StateSpaceModel:
    temp = InputChannel(
        name="temp1_c",
        unit="degC",
        reference=25.0,
        trained_range=(20.0, 30.0),
        valid_range=(10.0, 40.0),
    )
    return StateSpaceModel(
        fitted_dt_s=15,
        speed_range_rpm=(0, 10000),
        taus_s=(600.0, 5400.0),
        drive_um=((0.5, 0.05, 0.2), (2.0, 0.2, 0.3)),
        feedthrough_um=(0.1, 0.0, 0.0),
        offset_um=0.0,
        max_measured_um=40.0,
        inputs=(temp,),
        fallback=speed_only(),
        spindle_id="sp-A",
        machine_id="m1",
    )


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def resealed(path, edit) -> None:
    """Edit a model file's content and give it a valid checksum again: only the model's own
    sanity checks can refuse it then."""
    payload = json.loads(path.read_text())
    payload.pop("sha256")
    edit(payload)
    payload["sha256"] = digest(payload)
    path.write_text(json.dumps(payload))


@pytest.fixture
def good(tmp_path):
    p = tmp_path / "model.json"
    save_model(p, with_inputs())
    return p


def test_a_good_file_is_ok_in_one_line(capsys, good):
    code, out, err = run(capsys, "model", "check", good)
    assert code == 0 and err == ""
    assert out == (
        f"{good}: ok: ridge ({STATE_SPACE_FORMAT}), spindle 'sp-A', 2 states, "
        "inputs temp1_c, 0..10000 rpm\n"
    )


def test_a_speed_only_thermal_model_is_ok(capsys, tmp_path):
    p = tmp_path / "thermal.json"
    save_model(
        p,
        ThermalModel.from_discrete(
            0.99, (0.0, 0.02, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 27000.0)
        ),
    )
    code, out, _ = run(capsys, "model", "check", p)
    assert code == 0 and f"({MODEL_FORMAT})" in out and "speed only" in out and "1 states" in out


@pytest.mark.parametrize(
    "edit, reason",
    [
        (lambda d: d.update(taus_s=[600.0, 1e9]), "time constant 1e+09 s is outside 15 s"),
        (
            lambda d: d.update(drive_um=[[500.0, 0.05, 0.2], [2.0, 0.2, 0.3]]),
            "the gains imply a steady elongation",
        ),
        (lambda d: d["fallback"].update(taus_s=[1.0, 5400.0]), "time constant 1 s is outside 15 s"),
    ],
)
def test_insane_content_with_a_valid_checksum_is_refused_in_one_line(capsys, good, edit, reason):
    resealed(good, edit)
    code, out, err = run(capsys, "model", "check", good)
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith(f"thermocomp: error: {good}: invalid model: ")
    assert reason in err


def test_a_wrong_checksum_is_refused(capsys, good):
    good.write_text(good.read_text().replace('"spindle_id": "sp-A"', '"spindle_id": "sp-B"', 1))
    code, out, err = run(capsys, "model", "check", good)
    assert code == 2 and out == ""
    assert (
        err
        == f"thermocomp: error: {good}: checksum mismatch: the file was modified after it was written\n"
    )


def test_a_model_the_runtime_finds_implausible_is_refused(capsys, tmp_path):
    p = tmp_path / "huge.json"  # 2 mm per krpm: 54 mm at the top of its range
    save_model(
        p,
        ThermalModel.from_discrete(
            0.99, (0.0, 20.0, 0.0, 0.0), 1.0, speed_range_rpm=(0.0, 27000.0)
        ),
    )
    code, _, err = run(capsys, "model", "check", p)
    assert code == 2 and err.count("\n") == 1 and "not plausible" in err


def test_a_missing_file_and_no_file(capsys, tmp_path):
    code, _, err = run(capsys, "model", "check", tmp_path / "none.json")
    assert code == 2 and "cannot read" in err and err.count("\n") == 1
    with pytest.raises(SystemExit) as stop:  # argparse's own refusal
        main(["model", "check"])
    assert (
        stop.value.code == 2
        and "the following arguments are required: FILE" in capsys.readouterr().err
    )


def test_json_ok_and_refused(capsys, good, tmp_path):
    code, out, err = run(capsys, "model", "check", "--json", good)  # an option between the two
    assert code == 0 and err == ""
    body = json.loads(out)
    assert body == {
        "file": str(good),
        "ok": True,
        "reason": None,
        "format": STATE_SPACE_FORMAT,
        "form": "ridge",
        "spindle_id": "sp-A",
        "machine_id": "m1",
        "states": 2,
        "inputs": ["temp1_c"],
        "speed_range_rpm": [0.0, 10000.0],
        "fallback": "ridge",
        "sha256": model_digest(with_inputs()),
    }
    bad = tmp_path / "bad.json"
    bad.write_text(good.read_text())
    resealed(bad, lambda d: d.update(taus_s=[600.0, 1e9]))
    code, out, err = run(capsys, "model", "check", bad, "--json")
    assert code == 2 and err == ""  # the reason is in the JSON, for a machine
    body = json.loads(out)
    assert body["file"] == str(bad) and body["ok"] is False
    assert body["reason"].startswith("invalid model: time constant 1e+09 s")  # "file" names it
    assert out.count("\n") == 1


def test_show_describes_a_model(capsys, good):
    code, out, _ = run(capsys, "model", "show", good)
    assert code == 0 and out.startswith(f"{good}: {STATE_SPACE_FORMAT}, form ridge, spindle 'sp-A'")
    code, out, _ = run(capsys, "model", "show", good, "--json")
    assert code == 0 and json.loads(out)["taus_s"] == [600.0, 5400.0]
    with pytest.raises(SystemExit) as stop:
        main(["model", "show", str(good), "other.json"])
    assert stop.value.code == 2 and "unrecognized arguments: other.json" in capsys.readouterr().err


def test_schema_of_each_registered_format(capsys):
    code, out, _ = run(capsys, "model", "schema")  # the speed-only model's
    assert code == 0 and json.loads(out) == ThermalModel.model_json_schema()
    code, out, _ = run(capsys, "model", "schema", "--format", STATE_SPACE_FORMAT)
    schema = json.loads(out)  # a recursive model (its fallback) is a $ref into $defs
    top = schema["$defs"][schema["$ref"].rsplit("/", 1)[1]] if "$ref" in schema else schema
    assert code == 0 and {"taus_s", "drive_um", "inputs"} <= set(top["properties"])
    code, out, _ = run(capsys, "model", "schema", "--format", "all")
    schemas = json.loads(out)
    assert code == 0 and set(schemas) == set(MODEL_TYPES)
    assert all(s == MODEL_TYPES[name].model_json_schema() for name, s in schemas.items())
    with pytest.raises(SystemExit) as stop:
        main(["model", "schema", "--format", "nope/1"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "invalid choice: 'nope/1'" in err and STATE_SPACE_FORMAT in err
