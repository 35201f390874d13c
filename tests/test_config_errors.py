"""One error dialect: every configuration problem is one line naming the file, the spindle by
name, the key as written, the value given, what is expected and the nearest valid key."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel

from cnc_adapters.base import _nested_model, key_names, names_a_secret
from compensator.errors import ConfigError
from thermocomp.cli import main
from thermocomp.runtime.config import RuntimeConfig, load_config

SPINDLE = "sp1"
REQUIRED: dict[str, Any] = {  # a valid value for every key a section cannot do without
    "name": SPINDLE,
    "model": "m.json",
    "adapter": {"url": "sim://"},
    "preheat_c": 20.0,
    "host": "broker",
    "kp": 2.0,
}
PYDANTIC_WORDS = (
    "Extra inputs",
    "Input should",
    "errors.pydantic.dev",
    "Field required",
    "validation error",
)


def sections(
    model: type[BaseModel] = RuntimeConfig, path: tuple[str, ...] = ()
) -> list[tuple[tuple[str, ...], type[BaseModel]]]:
    """Every section of the configuration, as (its path from the root, its model), walked
    recursively through every field that holds a model (a list of them: [[spindle]])."""
    out = [(path, model)]
    for name, field in model.model_fields.items():
        nested = _nested_model(field.annotation)
        if nested is not None:
            out += sections(nested, (*path, name))
    return out


SECTIONS = sections()


def required_of(model: type[BaseModel]) -> dict[str, Any]:
    """What ``model`` needs, the [[spindle]] array (written on its own) left out."""
    return {
        name: REQUIRED[name]
        for name, f in model.model_fields.items()
        if f.is_required() and not (model is RuntimeConfig and name == "spindle")
    }


def toml_value(v: Any) -> str:
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + "}"
    return json.dumps(v)


def toml_table(header: str, body: dict[str, Any]) -> list[str]:
    return [header, *(f"{k} = {toml_value(v)}" for k, v in body.items())]


def config_text(section: tuple[str, ...], extra: dict[str, Any]) -> str:
    """A valid configuration (one spindle, sp1) whose ``section`` also holds ``extra``, written
    as a user would: [[spindle]], [spindle.shaping.cutting], [cooling.gains]."""
    top = required_of(RuntimeConfig)
    lines = [f"{k} = {toml_value(v)}" for k, v in top.items()]
    if not section:
        lines += [f"{k} = {toml_value(v)}" for k, v in extra.items()]
    in_spindle = section[:1] == ("spindle",)
    lines += toml_table(
        "[[spindle]]",
        {**required_of(dict(SECTIONS)[("spindle",)]), **(extra if section == ("spindle",) else {})},
    )
    if len(section) > 1 or (section and not in_spindle):
        model = dict(SECTIONS)[section]
        # the tables above it, with what each needs (a section's parent that has required keys)
        for i in range(1 if in_spindle else 0, len(section) - 1):
            parent = section[: i + 1]
            need = required_of(dict(SECTIONS)[parent])
            if parent != ("spindle",) and need:
                lines += toml_table(f"[{'.'.join(parent)}]", need)
        lines += toml_table(f"[{'.'.join(section)}]", {**required_of(model), **extra})
    return "\n".join(lines) + "\n"


def load_error(tmp_path: Path, text: str) -> tuple[Path, str]:
    p = tmp_path / "machine.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(p)
    return p, str(info.value)


def one_letter_typo(key: str, choices: list[str]) -> str:
    """``key`` with one letter left out, the first way whose nearest key is still ``key``."""
    import difflib

    for i in range(len(key) - 2, 0, -1):
        typo = key[:i] + key[i + 1 :]
        if typo not in choices and difflib.get_close_matches(typo, choices, n=1) == [key]:
            return typo
    raise AssertionError(f"no one-letter typo of {key!r} is nearest to it")


def test_the_walk_finds_every_section():
    found = {".".join(p) for p, _ in SECTIONS}
    assert {
        "",
        "spindle",
        "spindle.shaping",
        "spindle.shaping.transient",
        "spindle.shaping.cutting",
        "spindle.faults",
        "spindle.observer",
        "spindle.drift",
        "spindle.learning",
        "cooling",
        "cooling.gains",
        "status",
        "mqtt",
        "journal",
    } <= found
    assert len(SECTIONS) >= 14


@pytest.mark.parametrize("section", [p for p, _ in SECTIONS], ids=lambda p: ".".join(p) or "top")
def test_a_typo_in_any_key_of_any_section_names_the_spindle_the_key_and_the_nearest(
    tmp_path, section
):
    model = dict(SECTIONS)[section]
    keys = key_names(model)
    assert keys, section
    checked = 0
    for key in keys:
        if len(key) < 4:  # too short for a one-letter typo to be nearest to it alone ("k", "h")
            continue
        typo = one_letter_typo(key, keys)
        p, text = load_error(tmp_path, config_text(section, {typo: 1}))
        inside = section[1:] if section[:1] == ("spindle",) else section
        written = ".".join((*inside, typo))
        scope = f'spindle "{SPINDLE}": ' if section[:1] == ("spindle",) else ""
        given = "" if names_a_secret(key) else " = 1"  # a secret's value is never echoed
        assert text.startswith(
            f"{p}: {scope}{written}{given}: unknown key (did you mean {key!r}?)"
        ), text
        assert "\n" not in text and not any(w in text for w in PYDANTIC_WORDS), text
        checked += 1
    assert checked >= 1, section


def test_the_spindle_is_named_even_when_it_is_not_the_first(tmp_path):
    text = (
        config_text(("spindle",), {})
        + "\n".join(
            toml_table(
                "[[spindle]]", {"name": "sp2", "model": "m.json", "adapter": {"url": "sim://"}}
            )
        )
        + "\n[spindle.faults]\nmax_outage = 3\n"
    )
    p, msg = load_error(tmp_path, text)
    assert (
        msg
        == f"{p}: spindle \"sp2\": faults.max_outage = 3: unknown key (did you mean 'max_outage_s'?)"
    )
    assert "spindle.1" not in msg and "[1]" not in msg


@pytest.mark.parametrize(
    ("section", "extra", "line"),
    [
        (
            ("spindle",),
            {"period_s": "fast"},
            "spindle \"sp1\": period_s = 'fast': expected a number >= 0.01 and <= 3600",
        ),
        (
            ("spindle", "shaping"),
            {"max_offset_um": -5},
            'spindle "sp1": shaping.max_offset_um = -5: expected a number > 0',
        ),
        (
            ("spindle", "faults"),
            {"readback_every": 1.5},
            'spindle "sp1": faults.readback_every = 1.5: expected a whole number >= 0 and <= 1000000',
        ),
        (
            ("spindle", "shaping", "transient"),
            {"mode": "fast"},
            "spindle \"sp1\": shaping.transient.mode = 'fast': expected one of 'dual-slew', 'slow' or 'hold'",
        ),
        (
            ("spindle", "observer"),
            {"enabled": "maybe"},
            "spindle \"sp1\": observer.enabled = 'maybe': expected true or false",
        ),
        (
            ("status",),
            {"port": 70000},
            "status.port = 70000: expected a whole number >= 0 and <= 65535",
        ),
        (
            ("status",),
            {"bind": ""},
            "status.bind = '': expected a string of at least 1 character(s)",
        ),
        (
            ("journal",),
            {"max_age_days": 0},
            "journal.max_age_days = 0: expected a number > 0 and <= 36500",
        ),
        ((), {"time_scale": "x"}, "time_scale = 'x': expected a number > 0 and <= 10000"),
    ],
)
def test_a_wrong_type_or_a_value_out_of_range_names_the_value_and_what_is_expected(
    tmp_path, section, extra, line
):
    p, text = load_error(tmp_path, config_text(section, extra))
    assert text == f"{p}: {line}"


def test_a_required_key_missing_and_a_table_given_a_value(tmp_path):
    p, text = load_error(tmp_path, '[[spindle]]\nname = "sp1"\nadapter = {url = "sim://"}\n')
    assert text == f'{p}: spindle "sp1": model: required key missing'
    p, text = load_error(tmp_path, config_text((), {"status": 3}))
    assert text == f"{p}: status = 3: expected a table"


def test_every_problem_is_reported_each_on_its_own_line(tmp_path):
    text = config_text(("spindle", "shaping"), {"max_rate_um_per_sec": 2.0, "max_offset_um": -5})
    text += "[status]\nport = 70000\n"
    p, msg = load_error(tmp_path, text)
    assert msg.splitlines() == [
        f"{p}: spindle \"sp1\": shaping.max_rate_um_per_sec = 2.0: unknown key (did you mean 'max_rate_um_per_s'?)",
        f'{p}: spindle "sp1": shaping.max_offset_um = -5: expected a number > 0',
        f"{p}: status.port = 70000: expected a whole number >= 0 and <= 65535",
    ]


def test_an_adapter_and_a_chiller_typo_speak_the_same_dialect_under_their_table(tmp_path):
    adapter = {
        "type": "opcua",
        "url": "opc.tcp://127.0.0.1:4840",
        "preset": "generic",
        "speed_nod": "ns=2;s=Speed",
        "offset_node": "ns=2;s=Offset",
    }
    spindle = [
        "[[spindle]]",
        'name = "sp1"',
        'model = "m.json"',
        *toml_table("[spindle.adapter]", adapter),
    ]
    p, text = load_error(tmp_path, "\n".join(spindle) + "\n")
    assert (
        text
        == f"{p}: spindle \"sp1\": adapter.speed_nod = 'ns=2;s=Speed': unknown key (did you mean 'speed_node'?)"
    )
    p, text = load_error(
        tmp_path, config_text(("spindle",), {}).replace('{url = "sim://"}', '{type = "opcuaa"}')
    )
    assert text.startswith(
        f"{p}: spindle \"sp1\": adapter.type = 'opcuaa': unknown adapter 'opcuaa' "
        "(did you mean 'opcua'?); known: "
    ), text
    chiller = {"type": "modbus", "host": "h", "setpoint_regster": 3}
    p, text = load_error(
        tmp_path, config_text(("cooling",), {"mode": "both", "rite_um": 3.0, "chiller": chiller})
    )
    assert (
        text
        == f"{p}: cooling.chiller.setpoint_regster = 3: unknown key (did you mean 'setpoint_register'?)"
    )


def test_a_secret_is_never_echoed(tmp_path):
    _p, text = load_error(tmp_path, config_text(("mqtt",), {"pasword_file": "hunter2-secret"}))
    assert (
        "hunter2" not in text
        and "mqtt.pasword_file: unknown key (did you mean 'password_file'?)" in text
    )
    _p, text = load_error(
        tmp_path,
        config_text(("mqtt",), {"host": "user:hunter2@broker"}).replace('host = "broker"\n', "", 1),
    )
    assert "hunter2" not in text and "mqtt.host = '***@broker'" in text


def test_the_cli_prints_each_problem_on_its_own_line_and_exits_non_zero(tmp_path, capsys):
    text = (
        config_text(("spindle", "shaping"), {"max_rate_um_per_sec": 2.0}) + "[status]\nport = -1\n"
    )
    p = tmp_path / "machine.toml"
    p.write_text(text)
    for argv in (["run", "--check", "--config", str(p)], ["run", "--config", str(p)]):
        assert main(argv) == 2
        err = capsys.readouterr().err.splitlines()
        assert err == [
            f'thermocomp: error: {p}: spindle "sp1": shaping.max_rate_um_per_sec = 2.0: unknown key '
            "(did you mean 'max_rate_um_per_s'?)",
            f"thermocomp: error: {p}: status.port = -1: expected a whole number >= 0 and <= 65535",
        ], err
        assert not any(re.search("|".join(PYDANTIC_WORDS), line) for line in err)


# -- the controller side: the operation, the node and the server ----------------------------


def test_an_opcua_read_of_a_missing_node_names_the_operation_the_node_and_the_server():
    from cnc_adapters import AdapterError, open_adapter
    from machine_sim import SpindlePlant, preset
    from machine_sim.vcnc import SimClock, VirtualCNC, VirtualMachine, running

    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    with running(VirtualCNC(vm)) as cnc:  # a real asyncua server
        link = open_adapter(
            {
                "type": "opcua",
                "url": cnc.url,
                "speed_node": "ns=2;s=/No/Such/Speed",
                "offset_node": "ns=2;s=/No/Such/Offset",
            }
        )
        try:
            with pytest.raises(AdapterError) as info:
                link.read_speed()
        finally:
            link.close()
    assert (
        str(info.value)
        == f"opcua read speed node ns=2;s=/No/Such/Speed at {cnc.url}: BadNodeIdUnknown"
    )
