"""Typed settings per backend: every constructor option in a pydantic model, checked before
anything is built, and a bad configuration said in one line (the key, the value, what is
allowed). Nothing here connects anywhere."""

from __future__ import annotations

import inspect
import math
import random

import pytest
from pydantic import BaseModel, ValidationError

from cnc_adapters import BACKENDS, backend, check_adapter, open_adapter, settings_model
from cnc_adapters.base import RUNTIME_ONLY, Link
from cnc_adapters.sensors import SENSORS, open_sensor
from cnc_adapters.sensors import settings_model as sensor_settings_model
from compensator.errors import ConfigError
from machine_sim import SpindlePlant, preset
from machine_sim.vcnc import SimClock, VirtualMachine

# the smallest configuration of each, by URL
MINIMAL = {
    "sim": "sim://",
    "opcua": "opc.tcp://127.0.0.1:4840?preset=virtual-cnc",
    "line": "serial:///dev/ttyX?protocol=line",
    "haas": "serial:///dev/ttyX?protocol=haas",
    "modbus": "serial:///dev/ttyX?protocol=modbus",
    "linuxcnc": "linuxcnc://thermocomp",
    "plc": "s7://127.0.0.1?offset_address=DB100.DBD0&speed_address=DB100.DBD4",
    "focas": "focas://127.0.0.1:8193",
    "haas-mdc": "haas://127.0.0.1:5051",
}
MINIMAL_SENSOR = {
    "ascii": "serial:///dev/ttyX",
    "modbus": "serial:///dev/ttyX?protocol=modbus",
    "opcua": "opc.tcp://127.0.0.1:4840?preset=virtual-cnc",
}


def constructor_options(cls: type) -> dict[str, object]:
    """Every keyword the constructor chain of ``cls`` takes (its own, then its bases', through
    ``**kw``), with its default; runtime-only keywords left out."""
    options: dict[str, object] = {}
    for klass in cls.__mro__:
        if "__init__" not in klass.__dict__ or klass in (object, BaseModel):
            continue
        for name, p in inspect.signature(klass.__init__).parameters.items():
            if (
                name == "self"
                or p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL)
                or name in RUNTIME_ONLY
            ):
                continue
            options.setdefault(name, p.default)
        if klass is Link:
            break
    return options


ALL = [("adapter", kind) for kind in BACKENDS] + [("sensor", kind) for kind in SENSORS]


def cls_and_model(family: str, kind: str) -> tuple[type, type[BaseModel]]:
    if family == "adapter":
        return backend(kind), settings_model(kind)  # type: ignore[return-value]
    return SENSORS[kind], sensor_settings_model(kind)


@pytest.mark.parametrize("family,kind", ALL)
def test_every_constructor_option_is_in_the_settings_model(family, kind):
    cls, model = cls_and_model(family, kind)
    assert model is cls.Settings
    assert set(model.model_fields) == set(constructor_options(cls)), kind
    cfg = model.model_config
    assert cfg["extra"] == "forbid" and cfg["frozen"] is True and cfg["allow_inf_nan"] is False
    model.model_json_schema()  # documentable: the runtime can print it


@pytest.mark.parametrize("family,kind", ALL)
def test_the_settings_defaults_are_the_constructors(family, kind):
    cls, model = cls_and_model(family, kind)
    ctor = constructor_options(cls)
    own = {("linuxcnc", "offset_sign"): -1}  # set by the backend itself, through **kw
    for name, field in model.model_fields.items():
        default = field.get_default(call_default_factory=True)
        if (kind, name) in own:
            assert default == own[kind, name]
            continue
        if default is None or ctor[name] is inspect.Parameter.empty:
            continue  # None: the backend's or the preset's own (Haas, offset_scale, ...)
        given = list(ctor[name]) if isinstance(ctor[name], tuple) else ctor[name]
        assert default == given, (kind, name)


@pytest.mark.parametrize("kind", list(BACKENDS))
def test_a_minimal_configuration_validates_and_builds(kind):
    checked = check_adapter(MINIMAL[kind])
    assert isinstance(checked, settings_model(kind))
    with pytest.raises(ValidationError):
        checked.timeout_s = 1.0  # type: ignore[misc] - frozen (whatever the field)
    link = open_adapter(MINIMAL[kind])
    assert isinstance(link, backend(kind))
    link.close()


@pytest.mark.parametrize("kind", list(SENSORS))
def test_a_minimal_sensor_builds(kind):
    s = open_sensor(MINIMAL_SENSOR[kind])
    assert isinstance(s, SENSORS[kind])
    s.close()


# -- one line: the key, the value, what is allowed --------------------------------------------


@pytest.mark.parametrize(
    "target,expected",
    [
        (
            "opc.tcp://127.0.0.1:4840?speed_nod=ns=2;s=x",
            "opcua adapter: speed_nod = 'ns=2;s=x': unknown key (did you mean 'speed_node'?)",
        ),
        (
            {"type": "opcua", "url": "opc.tcp://h:1", "preset": "virtual-cnc", "timout_s": 2},
            "opcua adapter: timout_s = 2: unknown key (did you mean 'timeout_s'?)",
        ),
        (
            {"url": "sim://", "bogus": 1},
            "sim adapter: bogus = 1: unknown key; allowed: preset, program, ",
        ),
        (
            {"type": "modbus", "port": "/dev/x", "input_registers": {"t": {"reg": 1}}},
            "modbus adapter: input_registers.t.reg = 1: unknown key; allowed: register, type, table, scale",
        ),
    ],
)
def test_a_misspelt_key_is_one_line_that_names_it(target, expected):
    with pytest.raises(ConfigError) as info:
        open_adapter(target)
    first, *more = str(info.value).split("\n")
    assert first.startswith(expected)
    # every other problem on a line of its own: the modbus register then lacks its address
    assert more == (
        []
        if "reg" not in first
        else [
            "modbus adapter: input_registers.t.register: required key missing; "
            "expected a register address 0..65535"
        ]
    )


@pytest.mark.parametrize(
    "target,expected",
    [
        (
            "opc.tcp://127.0.0.1:4840?preset=virtual-cnc&timeout_s=abc",
            "opcua adapter: timeout_s = 'abc': expected a number > 0 (seconds)",
        ),
        (
            {"type": "opcua", "url": "opc.tcp://h:1", "preset": "virtual-cnc", "timeout_s": 0},
            "opcua adapter: timeout_s = 0: expected a number > 0 (seconds)",
        ),
        (
            {
                "type": "opcua",
                "url": "opc.tcp://h:1",
                "preset": "virtual-cnc",
                "timeout_s": math.inf,
            },
            "opcua adapter: timeout_s = inf: expected a number > 0 (seconds)",
        ),
        (
            {"type": "opcua", "url": "opc.tcp://h:1", "preset": "nope"},
            "opcua adapter: preset = 'nope': expected one of 'virtual-cnc', 'sinumerik', 'sinumerik-sea', 'opc40502', 'generic'",
        ),
        (
            {
                "type": "opcua",
                "url": "opc.tcp://h:1",
                "preset": "virtual-cnc",
                "verify_writes": "sometimes",
            },
            "opcua adapter: verify_writes = 'sometimes': expected true, false, 'immediate' or 'deferred'",
        ),
        (
            {"type": "opcua", "url": "opc.tcp://h:1"},
            "opcua adapter: preset 'generic' needs the speed and offset nodes",
        ),
        (
            {"type": "opcua", "preset": "virtual-cnc"},
            "opcua adapter: url: required key missing; expected an opc.tcp://host:port URL",
        ),
        (
            {
                "type": "opcua",
                "url": "opc.tcp://h:1",
                "preset": "virtual-cnc",
                "security": "Basic256Sha256,Sign",
            },
            "opcua adapter: a secure link (security other than None) needs certificate, private_key and trust_dir",
        ),
        ("sim://?offset_sign=0", "sim adapter: offset_sign = '0': expected +1 or -1"),
        (
            {"type": "sim", "offset_sign": True},
            "sim adapter: offset_sign = True: expected +1 or -1",
        ),
        (
            {"type": "sim", "offset_scale": 0},
            "sim adapter: offset_scale = 0: expected a finite number other than 0",
        ),
        (
            {"type": "sim", "jitter": 1.5},
            "sim adapter: jitter = 1.5: expected a number from 0 up to (not including) 1",
        ),
        (
            {"type": "sim", "backoff_s": math.nan},
            "sim adapter: backoff_s = nan: expected a number > 0 (seconds)",
        ),
        (
            "sim://?program=lunch",
            "sim adapter: program = 'lunch': expected one of 'paper-calibration', ",
        ),
        (
            "serial:///dev/x?protocol=modbus&device_id=300",
            "modbus adapter: device_id = '300': expected a Modbus device address 0..247",
        ),
        (
            "serial:///dev/x?protocol=modbus&offset_type=float64",
            "modbus adapter: offset_type = 'float64': expected one of 'int16', 'uint16', 'int32', 'uint32', 'float32'",
        ),
        (
            "serial:///dev/x?protocol=line&speed_reply=SPEED=(.*)",
            "line adapter: speed_reply = 'SPEED=(.*)': expected a regular expression with a (?P<value>...) group",
        ),
        (
            "serial:///dev/x?protocol=line&baudrate=fast",
            "line adapter: baudrate = 'fast': expected a whole number > 0 (bits per second)",
        ),
        (
            "serial:///dev/x?protocol=haas&offset_decimals=12",
            "haas adapter: offset_decimals = '12': expected a whole number 0..8",
        ),
        (
            "linuxcnc://thermocomp?axis_units=furlong",
            "linuxcnc adapter: axis_units = 'furlong': expected one of 'mm', 'inch'",
        ),
        (
            "linuxcnc://thermocomp?count_um=-1",
            "linuxcnc adapter: count_um = '-1': expected a number > 0",
        ),
    ],
)
def test_a_bad_value_is_one_line_with_key_value_and_what_is_allowed(target, expected):
    with pytest.raises(ConfigError) as info:
        open_adapter(target)
    text = str(info.value)
    assert text.startswith(expected) and "\n" not in text
    assert "Input should" not in text and "pydantic" not in text
    with pytest.raises(ConfigError):
        check_adapter(target)  # the same check, with nothing built


def test_offset_sign_is_plus_or_minus_one_in_any_spelling():
    for given, sign in ((1, 1), (-1, -1), (-1.0, -1), ("+1", 1), ("-1", -1)):
        assert open_adapter({"type": "sim", "offset_sign": given}).offset_sign == sign
    assert open_adapter("sim://?offset_sign=-1").offset_sign == -1
    for bad in (0, 2, 1.7, -0.5, "x", False):
        with pytest.raises(ConfigError, match="offset_sign = .*: expected \\+1 or -1"):
            open_adapter({"type": "sim", "offset_sign": bad})


@pytest.mark.parametrize("kind", ["opcua", "line", "haas", "modbus", "plc", "focas", "haas-mdc"])
@pytest.mark.parametrize("bad", ["abc", "0", "-1", "inf", "nan"])
def test_timeout_s_is_a_finite_number_above_zero(kind, bad):
    sep = "&" if "?" in MINIMAL[kind] else "?"
    with pytest.raises(ConfigError, match=f"{kind} adapter: timeout_s = .*: expected a number > 0"):
        open_adapter(f"{MINIMAL[kind]}{sep}timeout_s={bad}")


def test_a_long_value_is_cut_in_the_message():
    with pytest.raises(ConfigError) as info:
        open_adapter({"type": "sim", "preset": "x" * 5000})
    text = str(info.value)
    assert "xxx..." in text and "x" * 61 not in text and len(text) < 200


# -- what reaches the constructor ------------------------------------------------------------


def test_url_values_are_converted_and_only_given_options_reach_the_constructor():
    sim = open_adapter(
        "sim://mechanical-8k?seed=3&time_scale=120&offset_scale=0.001&offset_sign=-1"
    )
    assert sim.machine.plant.seed == 3 and sim.offset_scale == 0.001 and sim.offset_sign == -1
    assert open_adapter("sim://?program=").machine.program is None  # empty: an idle spindle
    # the preset's and the backend's own defaults stay in force
    o = open_adapter({"type": "opcua", "url": "opc.tcp://127.0.0.1:4840", "preset": "sinumerik"})
    assert o.offset_scale == 0.001 and o.timeout_s == 4.0
    lc = open_adapter("linuxcnc://tc?axis_units=inch&inputs=bearing_temp_c,ambient_c")
    assert lc.offset_sign == -1 and lc.offset_scale == pytest.approx(1 / 25400)
    assert lc.component == "tc" and lc.inputs == ("bearing_temp_c", "ambient_c")
    m = open_adapter(
        {
            "type": "modbus",
            "port": "/dev/x",
            "timeout_s": "0.25",
            "input_registers": {"t": {"register": 4, "scale": 0.1}},
        }
    )
    assert m.timeout_s == 0.25 and m.input_registers == {
        "t": {"register": 4, "type": "int16", "table": "input", "scale": 0.1}
    }
    checked = check_adapter(
        {
            "type": "opcua",
            "url": "opc.tcp://h:1",
            "preset": "virtual-cnc",
            "timeout_s": "2",
            "clock": object(),
        }
    )
    assert checked.model_fields_set == {"url", "preset", "timeout_s"} and checked.timeout_s == 2.0


def test_runtime_only_keywords_pass_through_unchecked():
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    clock = SimClock(60)
    events = []
    link = open_adapter(
        {"type": "sim"},
        machine=vm,
        clock=clock,
        rng=random.Random(1),
        on_link_change=lambda up, why: events.append(up),
    )
    assert link.machine is vm and link._clock is clock and link.on_link_change is not None
    with pytest.raises(ConfigError, match="opcua adapter: machine: unknown key"):
        open_adapter(MINIMAL["opcua"], machine=vm)  # not an option of this backend
    for bad in (
        "sim://?clock=1",
        {"type": "sim", "rng": 3},
        {"url": "sim://", "on_link_change": "log"},
    ):
        with pytest.raises(ConfigError, match="no configuration option"):
            check_adapter(bad)  # from a file or a URL: plain data, which means nothing there


def test_sensor_settings():
    with pytest.raises(ConfigError, match="^ascii sensor: bogus = 1: unknown key; allowed: "):
        open_sensor({"type": "ascii", "port": "/dev/null", "bogus": 1})
    with pytest.raises(
        ConfigError, match="^ascii sensor: scale = '0': expected a finite number other than 0"
    ):
        open_sensor("serial:///dev/x?scale=0")
    with pytest.raises(
        ConfigError, match="^ascii sensor: range_um = .*: expected two finite numbers"
    ):
        open_sensor("serial:///dev/x?range_um=5,1")
    with pytest.raises(ConfigError, match="^opcua sensor: give node"):
        open_sensor("opc.tcp://h:1")
    with pytest.raises(ConfigError, match="unknown sensor type 'laser'"):
        open_sensor({"type": "laser"})
    s = open_sensor(
        "serial:///dev/x?protocol=modbus&register=2&saturated_raw=32767,-32768&range_um=-50,50"
    )
    assert (
        s.register == 2 and s.saturated_raw == (32767.0, -32768.0) and s.range_um == (-50.0, 50.0)
    )
