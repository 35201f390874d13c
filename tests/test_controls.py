"""Controller profiles (issue 19): the profile data and its merge into adapter settings, the
shaper's whole counts, the emulated control side, and the SINUMERIK OPC UA route end to end:
the service writes SD43900 on the virtual CNC's SINUMERIK-like address space, refused without
the SeaWrite right, applied at the control's own rate once the right is given."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from controlrig import control_runtime
from hypothesis import given, settings
from hypothesis import strategies as st
from test_transients import assert_slow_while_cutting

from cnc_adapters import check_adapter
from cnc_adapters.control_profiles import PROFILES, adapter_settings, profile
from compensator.clock import SteppedClock
from compensator.errors import ConfigError
from compensator.io import read_run_log
from compensator.shaping import OffsetShaper, ShaperConfig
from compensator.speed_programs import Program
from machine_sim import SpindlePlant, preset
from machine_sim.controls import EmulatedControl
from machine_sim.vcnc import (
    SINUMERIK_GIVE_ACCESS,
    SINUMERIK_SD43900_NODE,
    VirtualCNC,
    VirtualMachine,
    running,
    step,
)
from thermocomp.runtime import Alarm
from thermocomp.runtime.config import load_config

HEAT = Program("heat", ((10.0, 0.0), (900.0, 22500.0), (30.0, 0.0), (600.0, 12000.0)))


# -- the profiles ------------------------------------------------------------------------


def test_every_family_has_a_profile_with_a_doc_and_a_route_or_says_why():
    assert {"sinumerik", "fanuc", "heidenhain", "haas", "linuxcnc", "beckhoff"} <= set(PROFILES)
    root = Path(__file__).resolve().parents[1]
    for p in PROFILES.values():
        assert p.routes, p.name
        assert p.doc.split("#")[0] and (root / p.doc.split("#")[0]).exists(), p.doc
        text = p.describe()
        assert p.unit in text and p.readback in text


def test_a_profile_presets_the_adapter_and_fixes_the_units():
    merged = adapter_settings(
        {"profile": "sinumerik", "url": "opc.tcp://10.0.0.5:4840", "offset_node": "ns=2;s=/x"}
    )
    assert merged["type"] == "opcua" and merged["preset"] == "sinumerik-sea"
    assert merged["offset_scale"] == 0.001 and merged["offset_sign"] == -1
    assert merged["url"] == "opc.tcp://10.0.0.5:4840"
    assert (
        adapter_settings(
            {
                "profile": "beckhoff",
                "route": "ads",
                "host": "h",
                "ams_net_id": "1.2.3.4.1.1",
                "offset_address": "a",
                "speed_address": "b",
            }
        )["offset_resolution"]
        == 1.0
    )
    with pytest.raises(ConfigError, match="offset_scale is fixed by profile 'sinumerik'"):
        adapter_settings(
            {
                "profile": "sinumerik",
                "url": "opc.tcp://h:4840",
                "offset_node": "x",
                "offset_scale": 1.0,
            }
        )
    with pytest.raises(ConfigError, match="needs offset_node or offset_path"):
        check_adapter({"profile": "sinumerik", "url": "opc.tcp://h:4840"})
    with pytest.raises(ConfigError, match="no route 'modbus'; known: opcua, s7"):
        adapter_settings({"profile": "sinumerik", "route": "modbus"})
    with pytest.raises(
        ConfigError,
        match="unknown controller profile 'fanucc' \\(did you mean 'fanuc'\\?\\); known: sinumerik",
    ):
        adapter_settings({"profile": "fanucc"})
    with pytest.raises(ConfigError, match="profile 'linuxcnc' is for axis_units = 'mm'"):
        adapter_settings({"profile": "linuxcnc", "axis_units": "inch"})
    with pytest.raises(ConfigError, match="'route' goes with 'profile'"):
        adapter_settings({"type": "sim", "route": "s7"})


def _spindle_config(tmp_path: Path, adapter: str, shaping: str = "") -> Path:
    p = tmp_path / "m.toml"
    p.write_text(
        f'state_dir = "{tmp_path}"\n[[spindle]]\nname = "s"\nmodel = "m.json"\n'
        f"adapter = {adapter}\n[spindle.shaping]\n{shaping}\n"
    )
    return p


def test_the_runtime_config_takes_the_profiles_resolution_and_refuses_a_clamp_past_its_limit(
    tmp_path,
):
    fanuc = '{profile = "fanuc", host = "127.0.0.1"}'
    cfg = load_config(_spindle_config(tmp_path, fanuc))
    assert cfg.spindle[0].shaping.resolution_um == 1.0 and cfg.spindle[0].route == "focas"
    cfg = load_config(_spindle_config(tmp_path, fanuc, "resolution_um = 2.0"))
    assert cfg.spindle[0].shaping.resolution_um == 2.0  # the user's own, a whole multiple
    for bad in ("0.0", "0.5", "1.5"):
        with pytest.raises(ConfigError, match="whole multiple of the controller's count, 1 um"):
            load_config(_spindle_config(tmp_path, fanuc, f"resolution_um = {bad}"))
    # no profile: the units given by hand set the count all the same
    plain = '{url = "focas://127.0.0.1:8193", offset_sign = -1, offset_resolution = 1.0}'
    assert load_config(_spindle_config(tmp_path, plain)).spindle[0].shaping.resolution_um == 1.0
    haas = '{profile = "haas", host = "127.0.0.1", offset_decimals = 3}'
    with pytest.raises(ConfigError, match="profile 'haas' is for offset_decimals = 4"):
        load_config(_spindle_config(tmp_path, haas))
    with pytest.raises(ConfigError, match=r"max_offset_um 600 is past what profile 'haas' takes"):
        load_config(
            _spindle_config(
                tmp_path, '{profile = "haas", host = "127.0.0.1"}', "max_offset_um = 600.0"
            )
        )


# -- whole counts --------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    q=st.sampled_from([0.1, 1.0, 2.54]),
    rate=st.sampled_from([0.3, 1.0, 5.0]),
    dt=st.sampled_from([0.25, 1.0, 2.0]),
    s=st.lists(st.floats(-90, 90), min_size=5, max_size=60),
)
def test_the_shaper_moves_in_whole_counts_within_the_clamp_and_the_slew_limit(q, rate, dt, s):
    cfg = ShaperConfig(
        max_offset_um=60.0,
        max_rate_um_per_s=rate,
        not_cutting_rate_um_per_s=rate,
        deadband_um=0.0,
        resolution_um=q,
    )
    sh = OffsetShaper(cfg)
    t, last_move_t, y = 0.0, 0.0, 0.0
    for target in np.repeat(s, 20):
        t += dt
        out = sh.update(-float(target), 10000.0, dt, cutting=True).offset_um
        assert abs(out) <= 60.0
        assert abs(out / q - round(out / q)) < 1e-6  # a whole count
        if out != y:
            assert abs(out - y) <= rate * (t - last_move_t) + 1e-9
            y, last_move_t = out, t
    # and it gets there: within one count of the clamped target
    sh2 = OffsetShaper(cfg)
    for _ in range(int(200 / (rate * dt)) + 10):
        out = sh2.update(-25.0, 10000.0, dt, cutting=True).offset_um
    assert abs(out - 25.0) <= q


# -- the emulated control ------------------------------------------------------------------


def test_the_emulated_control_refuses_what_the_control_would_and_applies_at_its_rate():
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=1), None, clock=SteppedClock())
    fanuc = EmulatedControl(vm, profile("fanuc"))
    assert fanuc.write_raw(12) and fanuc.held_raw == 12
    assert not fanuc.write_raw(12.5) and "whole count" in fanuc.last_refusal
    assert not fanuc.write_raw(40000) and "limit" in fanuc.last_refusal
    assert not fanuc.write_raw(10011) and "alarm" in fanuc.last_refusal
    assert not fanuc.write_raw(math.nan) and fanuc.held_raw == 12 and fanuc.refused == 3 + 1
    assert fanuc.held_um == -12.0  # +S in detection units is the offset A = -12 um
    clock = SteppedClock()
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=1), None, clock=clock)
    tnc = EmulatedControl(vm, profile("heidenhain"))  # follows at 1 um/s
    assert tnc.write_raw(100)  # 10 um
    clock.advance(4.0)
    vm.advance()
    tnc.sync()
    assert tnc.applied_um == pytest.approx(-4.0) and vm.offset_um == pytest.approx(-4.0)
    clock.advance(20.0)
    vm.advance()
    tnc.sync()
    assert tnc.applied_um == pytest.approx(-10.0)


# -- SINUMERIK over OPC UA, end to end -----------------------------------------------------


def _give_access(url: str, user: str, password: str, who: str) -> None:
    from asyncua import ua
    from asyncua.sync import Client

    client = Client(url, timeout=10)
    client.set_user(user)
    client.set_password(password)
    client.connect()
    try:
        methods = client.get_node(f"ns=2;s={SINUMERIK_GIVE_ACCESS.rpartition('/')[0]}")
        methods.call_method(
            client.get_node(f"ns=2;s={SINUMERIK_GIVE_ACCESS}"),
            ua.Variant(who, ua.VariantType.String),
            ua.Variant("StateRead; SeaRead; SeaWrite", ua.VariantType.String),
        )
    finally:
        client.disconnect()


def test_sinumerik_opcua_route_writes_sd43900_only_with_the_seawrite_right(
    tmp_path, calibrated_model, monkeypatch
):
    monkeypatch.setenv("THERMOCOMP_OPCUA_USER", "thermocomp")
    monkeypatch.setenv("THERMOCOMP_OPCUA_PASSWORD", "tc-pw")
    clock = SteppedClock()
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=4), None, clock=clock)
    # MD32760 x MD32000 made to bind: the axis follows SD43900 at 0.5 um/s at most
    control = EmulatedControl(vm, profile("sinumerik"), rate_um_per_s=0.5)
    vcnc = VirtualCNC(
        vm,
        tick_s=None,
        users={"thermocomp": "tc-pw", "auduser": "adm-pw"},
        control=control,
        admins=frozenset({"auduser"}),
    )
    with running(vcnc) as cnc:
        adapter = (
            f'{{profile = "sinumerik", route = "opcua", url = "{cnc.url}", '
            f'offset_node = "ns=2;s={SINUMERIK_SD43900_NODE}", verify_writes = true}}'
        )
        rt = control_runtime(tmp_path, calibrated_model, adapter, clock, period_s=2.0)
        try:
            step(cnc)
            rt.cycle()
            vm.load_program(HEAT)
            rows = []
            for _ in range(60):  # two minutes at speed without the right: every write refused
                clock.advance(rt.next_period_s())
                step(cnc)
                rows.append(rt.cycle())
            assert (
                cnc.denied_writes > 0 and control.held_raw == 0.0 and not control.writes
            )  # none reached it
            assert rows[-1]["alarms"] & int(Alarm.WRITE_REJECTED)
            assert abs(vm.history().tool_tip_error_um[-1]) > 3.0  # the growth goes uncompensated
            # an operator cannot give the right; the administrator can
            from asyncua.ua.uaerrors import BadInvalidArgument

            with pytest.raises(BadInvalidArgument):
                _give_access(cnc.url, "thermocomp", "tc-pw", "thermocomp")
            _give_access(cnc.url, "auduser", "adm-pw", "thermocomp")
            while not vm.program_done:
                clock.advance(rt.next_period_s())
                step(cnc)
                rows.append(rt.cycle())
        finally:
            rt.close()
    assert not rows[-1]["alarms"] & int(Alarm.WRITE_REJECTED)
    h = vm.history()
    # after the catch-up at the slew limit, while the tool is in the part
    later = (h.time_s > h.time_s[0] + 300.0) & h.cutting
    err, true = np.abs(h.tool_tip_error_um[later]), np.abs(h.true_um[later])
    assert true.max() > 10.0
    assert err.max() < 0.1 * true.max(), (err.max(), true.max())
    # what the control received, in mm: within the clamp, never faster than the slew limit
    taken = [w for w in control.writes if w.taken]
    raw = np.array([w.raw for w in taken])
    t = np.array([w.time_s for w in taken])
    assert len(taken) > 100 and np.abs(raw).max() <= 60.0 * 1e-3 + 1e-12
    assert (raw >= -1e-12).all()  # SD43900 holds +S: the growth, positive
    moved = np.flatnonzero(np.diff(raw) != 0) + 1
    gaps = np.diff(np.concatenate([[t[0]], t[moved]]))
    steps = np.abs(np.diff(np.concatenate([[raw[0]], raw[moved]])))
    assert (steps <= 50.0e-3 * gaps + 1e-9).all()  # 50 um/s clear of the part, in mm
    # 1 um/s while the tool cuts (the journal's own clock), and the axis at the control's rate
    (path,) = sorted((tmp_path / "state" / "journal").glob("s1-*.csv"))
    log = read_run_log(path)
    assert_slow_while_cutting(log, np.asarray(log.extras["cutting"], float) == 1)
    moves = np.flatnonzero(np.diff(h.offset_um) != 0) + 1
    axis = np.abs(np.diff(h.offset_um[moves])) / np.diff(h.time_s[moves])
    assert axis.max() <= 0.5 + 1e-9 and axis.max() > 0.49  # it bound: slower than the shaper


def test_the_example_configuration_names_a_route_for_every_tested_family():
    cfg = load_config(Path(__file__).resolve().parents[1] / "examples" / "controls.toml")
    routes = {(s.profile.name, s.route) for s in cfg.spindle}
    assert routes == {
        ("sinumerik", "opcua"),
        ("sinumerik", "s7"),
        ("fanuc", "focas"),
        ("haas", "mdc"),
        ("beckhoff", "ads"),
    }
    fanuc = next(s for s in cfg.spindle if s.profile.name == "fanuc")
    assert fanuc.shaping.resolution_um == 1.0  # whole detection units


@pytest.mark.parametrize("name", ["virtual", *PROFILES])
def test_the_demo_can_act_as_every_profile(tmp_path, name):
    from thermocomp.demo import RUNTIME_CONFIG, demo_link

    adapter, options = demo_link(name, "opc.tcp://127.0.0.1:4840/x/", tmp_path)
    text = RUNTIME_CONFIG.format(state_dir=tmp_path, model=tmp_path / "m.json", adapter=adapter)
    (tmp_path / "c.toml").write_text(text)
    s = load_config(tmp_path / "c.toml").spindle[0]
    link = check_adapter(s.adapter)
    if name in ("virtual", "sinumerik"):
        assert (s.profile.name if s.profile else "virtual") == name
    else:  # the family's units on the virtual CNC's OPC UA node
        p = profile(name)
        assert (link.offset_scale, link.offset_sign) == (p.scale, p.sign)
        assert s.shaping.resolution_um == pytest.approx(
            p.resolution_um
        )  # whole counts of the control
    if name == "sinumerik":
        assert options["rights"]["thermocomp"] == {"SeaWrite"}


def test_thermocomp_controls_lists_the_profiles_and_shows_one(capsys):
    from thermocomp.cli import build_parser, main

    assert main(["controls"]) == 0
    listing = capsys.readouterr().out
    assert all(name in listing for name in PROFILES)
    assert main(["controls", "sinumerik"]) == 0
    shown = capsys.readouterr().out
    assert "route opcua" in shown and "route s7" in shown and "$$SA_TEMP_COMP_ABS_VALUE[Z]" in shown
    with pytest.raises(SystemExit) as stop:  # argparse's refusal, naming the profiles
        main(["controls", "nope"])
    assert (
        stop.value.code == 2
        and "invalid choice: 'nope' (choose from 'sinumerik'" in capsys.readouterr().err
    )
    demo = next(
        a
        for a in build_parser()._subparsers._group_actions[0].choices["demo"]._actions
        if a.dest == "profile"
    )
    assert set(demo.choices) == set(PROFILES)  # the demo can act as every profile


def test_run_check_prints_what_the_profile_will_do_and_warns_of_a_slow_control(
    tmp_path, calibrated_model, capsys
):
    from machine_sim.plc_servers import S7Plc
    from thermocomp.runtime.service import check

    vm = VirtualMachine(SpindlePlant(preset("motorized-27k"), seed=4), None, clock=SteppedClock())
    vm.override_speed(9000.0)
    vm.clock.advance(5.0)
    vm.advance()
    with S7Plc(
        EmulatedControl(vm, profile("heidenhain")),
        offset_type="INT",
        offset_address="DB100.DBW0",
        held_address=None,
    ) as plc:
        plc.sync()
        cfg = tmp_path / "m.toml"
        cfg.write_text(
            f'state_dir = "{tmp_path}"\n[[spindle]]\nname = "tnc"\nmodel = "{calibrated_model}"\n'
            f'[spindle.adapter]\nprofile = "heidenhain"\nprotocol = "s7"\nhost = "127.0.0.1"\n'
            f'port = {plc.port}\noffset_address = "DB100.DBW0"\nspeed_address = "DB100.DBD4"\n'
        )
        assert check(str(cfg)) == 0
    out = capsys.readouterr().out
    assert "tnc: profile heidenhain (HEIDENHAIN TNC), route plc" in out
    assert "in whole counts of 0.1 um" in out and "speed 9000 rpm" in out
    assert (
        "warning: the control moves the offset at most 1 um/s, slower than the shaping's 50 um/s"
        in out
    )
    assert plc.passed_on == 0  # --check writes nothing
