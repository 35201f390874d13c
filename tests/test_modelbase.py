"""The one model base: shared fields, the one judge of input values (a bool is not a number),
one error for an invalid model, and the model files of every format still load."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import first_order

from compensator.errors import ModelError
from compensator.fusion import FusedPredictor
from compensator.inputs import AugmentedModel, InputTerm
from compensator.io.modelfile import load_any_model, save_model
from compensator.model import ThermalModel
from compensator.modelbase import Channel, ModelBase, check_inputs
from compensator.observer import ObserverConfig
from compensator.statespace import InputChannel, StateSpaceModel


def speed_only() -> StateSpaceModel:
    return StateSpaceModel(
        fitted_dt_s=15,
        speed_range_rpm=(0, 10000),
        taus_s=(600.0,),
        drive_um=((0.5, 0.05),),
        feedthrough_um=(0.1, 0.0),
        max_measured_um=40.0,
    )


def state_space(*names: str) -> StateSpaceModel:
    chans = tuple(
        InputChannel(
            name=n,
            unit="degC",
            reference=25.0,
            trained_range=(20.0, 30.0),
            valid_range=(10.0, 40.0),
        )
        for n in names
    )
    w = len(names)
    return StateSpaceModel(
        fitted_dt_s=15,
        speed_range_rpm=(0, 10000),
        taus_s=(600.0,),
        drive_um=((0.5, 0.05) + (0.2,) * w,),
        feedthrough_um=(0.1, 0.0) + (0.0,) * w,
        max_measured_um=40.0,
        inputs=chans,
        fallback=speed_only(),
    )


def augmented(*names: str) -> AugmentedModel:
    terms = tuple(
        InputTerm(
            name=n,
            unit="degC",
            reference=25.0,
            gain_um_per_unit=0.5,
            tau_s=600.0,
            valid_range=(10.0, 40.0),
        )
        for n in names
    )
    return AugmentedModel(speed_model=first_order(), inputs=terms, fallback=first_order())


MODELS_WITH_INPUTS = {
    "state space": lambda: state_space("amb_c"),
    "augmented": lambda: augmented("amb_c"),
}


@pytest.mark.parametrize("make", MODELS_WITH_INPUTS.values(), ids=MODELS_WITH_INPUTS.keys())
def test_every_model_refuses_a_bool_as_an_input_value(make):
    model = make()
    fused = FusedPredictor(model, ObserverConfig())
    for value in (True, False):
        assert model.check_inputs({"amb_c": value}) == f"amb_c: {value!r} is not a finite number"
        assert fused.check_inputs({"amb_c": value}) is not None
    assert model.check_inputs({"amb_c": 21}) is None
    assert model.check_inputs({"amb_c": np.float64(21.5)}) is None


@pytest.mark.parametrize("make", MODELS_WITH_INPUTS.values(), ids=MODELS_WITH_INPUTS.keys())
def test_every_model_judges_input_values_alike(make):
    model = make()
    assert model.check_inputs({}) == "amb_c: no value"
    assert model.check_inputs({"amb_c": math.nan}) == "amb_c: nan is not a finite number"
    assert model.check_inputs({"amb_c": "21"}) == "amb_c: '21' is not a finite number"
    assert model.check_inputs({"amb_c": 50.0}) == "amb_c: 50 degC is outside 10..40"
    assert model.input_names == ("amb_c",)


def test_a_speed_only_model_reads_no_inputs():
    m = first_order()
    assert m.input_names == () and m.channels == ()
    assert m.check_inputs({"amb_c": True}) is None  # it reads none of them


def test_check_inputs_over_plain_channels():
    chans = [Channel(name="a", unit="%", valid_range=(0.0, 100.0))]
    assert check_inputs(chans, {"a": 50}) is None
    assert check_inputs(chans, {"a": True}) is not None
    with pytest.raises(ValueError, match="valid_range"):
        Channel(name="a", unit="%", valid_range=(1.0, 0.0))


@pytest.mark.parametrize(
    "make",
    [lambda: state_space("a", "a"), lambda: augmented("a", "a")],
    ids=["state space", "augmented"],
)
def test_an_input_twice_is_one_model_error(make):
    with pytest.raises(ModelError, match="an input appears twice"):
        make()


def test_every_model_shares_the_base_fields_and_fails_with_a_model_error():
    for model in (first_order(), state_space("amb_c"), augmented("amb_c")):
        assert isinstance(model, ModelBase)
        assert (model.spindle_id, model.machine_id, model.fit.as_dict(), model.created_utc) == (
            "unknown",
            "",
            {},
            None,
        )
        changed = model.replace(spindle_id="sp-7")
        assert changed.spindle_id == "sp-7" and type(changed) is type(model)
        with pytest.raises(ModelError):
            type(model).model_validate({**model.model_dump(), "spindle_id": 7})
        with pytest.raises(ModelError):
            type(model)(**{**model.model_dump(), "unknown_field": 1})
    bad_term = {
        "name": "amb_c",
        "unit": "degC",
        "reference": 0.0,
        "gain_um_per_unit": 1.0,
        "tau_s": 0.0,
        "valid_range": [1.0],
    }
    with pytest.raises(ModelError, match="inputs.0.valid_range"):
        AugmentedModel.model_validate({**augmented("amb_c").model_dump(), "inputs": [bad_term]})


@pytest.mark.parametrize(
    "model",
    [first_order(), state_space("amb_c"), augmented("amb_c")],
    ids=["speed only", "state space", "augmented"],
)
def test_each_format_round_trips_through_its_file(model, tmp_path):
    save_model(tmp_path / "m.json", model)
    again = load_any_model(tmp_path / "m.json")
    assert type(again) is type(model) and again == model
    assert again.model_dump(mode="json")["format"] == model.format


def test_the_above_range_rule_is_one_for_every_model():
    for model in (first_order(), state_space("amb_c"), augmented("amb_c")):
        top = model.speed_range_rpm[1]
        assert not model.above_range(top * 1.01) and model.above_range(-top * 1.03)


def test_no_form_accepts_a_top_speed_no_calibration_reaches():
    # a zero top made every real speed count as impossible: compensation off
    with pytest.raises(ModelError, match="tops at 0 rpm"):
        ThermalModel(**{**first_order().model_dump(), "speed_range_rpm": (0.0, 0.0)})
    with pytest.raises(ModelError, match="tops at 0 rpm"):
        StateSpaceModel(**{**speed_only().model_dump(), "speed_range_rpm": (0.0, 0.0)})


def test_the_old_homes_of_moved_names_still_serve_them():
    from compensator import filters, inputs, model, modelbase

    assert (
        model.saved_numbers is modelbase.saved_numbers
        and model.SAVED_LIMIT_UM == modelbase.SAVED_LIMIT_UM
    )
    assert inputs.first_order is filters.first_order
    with pytest.raises(ModelError, match="bool, not a number"):
        model.saved_numbers("x", [True])
