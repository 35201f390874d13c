"""The fit record: typed and versioned, and every record written so far loads and writes back
unchanged (the checksum that names a model in the runtime's state file survives an upgrade)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest
from conftest import first_order

from compensator.errors import ModelError, ModelFileError
from compensator.expected import ExpectedError, parse_expected
from compensator.fitrecord import FIT_SCHEMA_VERSION, FitRecord, fit_of
from compensator.fusion import observer_config_of
from compensator.io import load_any_model, model_digest, save_model
from compensator.io.checksum import digest
from compensator.modelbase import with_fit
from compensator.observer import ObserverConfig

EXAMPLE = Path(__file__).parents[1] / "examples" / "linuxcnc" / "spindle-model.json"

# what `thermocomp fit` wrote before the record was typed (cal.csv and val.csv of the CLI tests)
WRITTEN_BEFORE = {
    "method": "physical",
    "scored_by": "leave-one-cycle-out free run",
    "folds": 2,
    "cv_rms_um": 0.2329,
    "cv_max_abs_um": 0.7514,
    "folds_rms_um": [0.2457, 0.2155],
    "reason": "physical has the lowest leave-one-cycle-out free-run RMS",
    "expected_error": {
        "format": "thermocomp.expected-error/1",
        "bands": [
            {
                "speed_rpm": [0.0, 1.0],
                "source": "held out",
                "samples": 134,
                "rms_um": 0.2346,
                "p95_abs_um": 0.4196,
                "outside": None,
            },
            {
                "speed_rpm": [1.0, 27000.0],
                "source": "held out",
                "samples": 146,
                "rms_um": 0.2185,
                "p95_abs_um": 0.3894,
                "outside": None,
            },
        ],
        "outside_validated": 0.0,
        "forward_folds": 0,
    },
    "observer": {
        "bias_q_um2_per_s": 9.575260121546873e-06,
        "drift_q_um2_per_s3": 0.0,
        "model_sd_um": 0.11679914744758808,
        "gate_sigma": 5.0,
        "initial_bias_sd_um": 10.0,
        "reaccept_after": 2,
    },
    "growth_direction": 1,
}


def signed_file(path: Path, fit: object) -> dict:
    """A model file as an earlier thermocomp wrote it: ``fit`` as given, signed."""
    payload = first_order().model_dump(mode="json")
    payload["fit"] = fit
    payload["sha256"] = digest(payload)
    path.write_text(json.dumps(payload))
    return payload


def test_a_record_written_before_reads_typed_and_writes_back_the_same(tmp_path):
    payload = signed_file(tmp_path / "m.json", WRITTEN_BEFORE)
    m = load_any_model(tmp_path / "m.json")
    fit = m.fit
    assert isinstance(fit, FitRecord) and fit.schema_version == 1
    assert fit.method == "physical" and fit.folds == 2 and fit.folds_rms_um == (0.2457, 0.2155)
    assert fit.growth_direction == 1
    assert isinstance(fit.observer, ObserverConfig) and fit.observer.reaccept_after == 2
    assert isinstance(fit.expected_error, ExpectedError)
    assert fit.expected_error.at(5000.0).rms_um == 0.2185
    # the same JSON back: same checksum, so the runtime's saved state still names this model
    assert fit.as_dict() == WRITTEN_BEFORE
    assert model_digest(m) == payload["sha256"]
    # readers written for the dict still read it
    assert fit["observer"] == WRITTEN_BEFORE["observer"] and fit.get("nope", 3) == 3
    assert "growth_direction" in fit and "not_following_share" not in fit
    assert {**fit} == WRITTEN_BEFORE


def test_the_example_model_loads_to_its_own_checksum():
    m = load_any_model(EXAMPLE)
    assert model_digest(m) == json.loads(EXAMPLE.read_text())["sha256"]
    # entries of older records are typed too, an integer stays one
    assert m.fit.runs == 2 and isinstance(m.fit.runs, int) and m.fit.in_sample_rms_um > 0


def test_unknown_entries_are_kept_and_integers_stay_integers(tmp_path):
    old = {"scored_by": "loro", "cv_rms_um": 1, "tuning": {"kept": None}, "runs": 3}
    payload = signed_file(tmp_path / "m.json", old)
    m = load_any_model(tmp_path / "m.json")
    assert m.fit["tuning"] == {"kept": None} and m.fit.cv_rms_um == 1
    assert model_digest(m) == payload["sha256"]
    save_model(tmp_path / "again.json", with_fit(m, growth_direction=-1))
    again = load_any_model(tmp_path / "again.json")
    assert again.fit["tuning"] == {"kept": None} and again.fit.growth_direction == -1
    assert again.fit.schema_version == FIT_SCHEMA_VERSION
    assert json.loads((tmp_path / "again.json").read_text())["fit"]["cv_rms_um"] == 1


def test_an_unreadable_statement_is_advice_the_model_runs_without(tmp_path):
    newer = {"cv_rms_um": 0.5, "expected_error": {"format": "thermocomp.expected-error/9"}}
    payload = signed_file(tmp_path / "m.json", newer)
    m = load_any_model(tmp_path / "m.json")
    assert m.fit.expected_error is None and parse_expected(m.fit) is None
    assert model_digest(m) == payload["sha256"]  # kept as written


def test_a_typed_entry_that_is_wrong_refuses_the_file_in_one_line(tmp_path):
    signed_file(tmp_path / "m.json", {"growth_direction": 2})
    with pytest.raises(ModelFileError, match=r"fit\.growth_direction") as err:
        load_any_model(tmp_path / "m.json")
    assert "\n" not in str(err.value)
    with pytest.raises(ModelError, match="not a record"):
        first_order().model_copy(update={"fit": [1, 2]})


def test_a_new_record_round_trips_and_carries_its_version(tmp_path):
    statement = ExpectedError.model_validate(WRITTEN_BEFORE["expected_error"])
    m = with_fit(first_order(), observer=ObserverConfig(model_sd_um=0.2), expected_error=statement)
    assert m.fit.schema_version == FIT_SCHEMA_VERSION
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # pydantic warns when it serialises a field off its type
        save_model(tmp_path / "m.json", m)
    back = load_any_model(tmp_path / "m.json")
    assert back.fit == m.fit and back.fit.observer.model_sd_um == 0.2
    assert json.loads((tmp_path / "m.json").read_text())["fit"]["schema_version"] == 2
    # a change of None takes the entry out
    assert with_fit(back, observer=None).fit.observer is None
    assert "observer" not in with_fit(back, observer=None).fit


def test_a_dict_given_to_model_copy_becomes_a_checked_record():
    # the way the record was rebuilt before with_fit: still typed, still checked
    m = first_order()
    m2 = m.model_copy(update={"fit": {**m.fit, "observer": {"model_sd_um": 0.4}}})
    assert isinstance(m2.fit, FitRecord) and m2.fit.observer.model_sd_um == 0.4
    assert observer_config_of(m2).model_sd_um == 0.4
    assert first_order().model_copy(update={"fit": None}).fit == FitRecord()


def test_readers_take_the_record_its_json_form_or_nothing():
    statement = WRITTEN_BEFORE["expected_error"]
    typed = FitRecord.of(WRITTEN_BEFORE)
    assert parse_expected(typed) == parse_expected(WRITTEN_BEFORE) == typed.expected_error
    assert parse_expected({"expected_error": {**statement, "bands": []}}) is None
    assert parse_expected(None) is None and parse_expected("garbage") is None

    class Stub:  # something that is no ModelBase, carrying the JSON form
        fit = WRITTEN_BEFORE

    assert fit_of(Stub()).growth_direction == 1
    Stub.fit = {"growth_direction": "up"}
    assert fit_of(Stub()) == FitRecord()
