"""The runtime's two state machines alone, and the import contracts that keep the layers apart."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from compensator.shaping import Flag, ShaperConfig, TransientPolicy
from thermocomp.runtime.link import LinkHealth, LinkState
from thermocomp.runtime.offset import OffsetMode, OffsetTracker

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("thermocomp", "calibration", "machine_sim", "cnc_adapters", "compensator")


def test_link_health_connected_retrying_outage_and_back():
    link = LinkHealth(max_outage_s=600)
    assert link.state is LinkState.CONNECTED and link.up
    assert link.succeeded(0.0) is None  # up stays up
    assert link.failed(10.0) is LinkState.RETRYING and not link.up
    assert link.failed(300.0) is LinkState.RETRYING
    assert link.failed(610.0) is LinkState.RETRYING  # exactly 600 s: not yet
    assert link.failed(611.0) is LinkState.OUTAGE
    assert link.succeeded(700.0) == pytest.approx(690.0)  # how long it was down
    assert link.state is LinkState.CONNECTED and link.down_since is None
    assert link.failed(800.0) is LinkState.RETRYING  # a new outage counts from its own start


def _cfg(rate=1.0):
    return ShaperConfig(
        max_offset_um=40,
        max_rate_um_per_s=rate,
        deadband_um=0,
        transient=TransientPolicy(enabled=False),
    )


def test_offset_tracks_ramps_and_holds():
    off = OffsetTracker(_cfg(), held_um=0.0)
    shaped = off.plan(0.5, 1000, 1.0)
    assert off.wants_write(shaped)
    off.written(shaped)
    assert off.mode is OffsetMode.TRACKING and off.held_um == pytest.approx(-0.5)
    shaped = off.plan(5.0, 1000, 1.0)  # a step larger than the slew limit
    assert Flag.SLEW_LIMITED in shaped.flags
    off.written(shaped)
    assert off.mode is OffsetMode.RAMPING and off.held_um == pytest.approx(-1.5)
    # the write fails: the controller keeps -1.5 and the shaper moves on from there
    shaped = off.plan(5.0, 1000, 1.0)
    off.kept(wanted=off.wants_write(shaped))
    assert off.mode is OffsetMode.HOLDING and off.pending
    assert off.shaper.output_um == pytest.approx(-1.5) and off.held_um == pytest.approx(-1.5)
    # ten cycles later the write goes through: one slew step from what the controller holds
    for _ in range(10):
        off.kept(wanted=off.wants_write(off.plan(5.0, 1000, 1.0)))
    shaped = off.plan(5.0, 1000, 1.0)
    assert shaped.offset_um == pytest.approx(-2.5)
    off.written(shaped)
    assert not off.pending and off.mode is OffsetMode.RAMPING


def test_offset_after_the_controller_lost_it_rewrites_from_what_it_holds():
    off = OffsetTracker(_cfg(rate=2.0), held_um=-10.0)
    assert off.held_um == -10.0
    off.controller_holds(0.0)  # an NC reset cleared the variable
    assert off.mode is OffsetMode.HOLDING and off.pending and off.shaper.output_um == 0.0
    shaped = off.plan(10.0, 0, 1.0)
    assert off.wants_write(shaped) and shaped.offset_um == pytest.approx(-2.0)  # no jump back
    off.written(shaped)
    # nothing to change and nothing pending: no write wanted
    off2 = OffsetTracker(_cfg(), held_um=-3.0)
    assert not off2.wants_write(off2.plan(3.0, 0, 1.0))
    off2.rewrite()  # a link came back: write again even though nothing changed
    assert off2.wants_write(off2.plan(3.0, 0, 1.0))


def test_a_controller_value_that_is_not_a_number_is_rewritten_not_followed():
    off = OffsetTracker(_cfg(rate=2.0), held_um=-4.0)
    off.controller_holds(float("nan"))
    assert off.pending and off.mode is OffsetMode.HOLDING
    assert off.held_um == -4.0 and off.shaper.output_um == -4.0  # still moves on from -4
    shaped = off.plan(4.0, 0, 1.0)
    assert off.wants_write(shaped) and shaped.offset_um == pytest.approx(-4.0)


@pytest.mark.parametrize("held", [999.0, -1e308])
def test_a_held_value_beyond_the_clamp_counts_as_the_clamps_edge(held):
    """A foreign value beyond the clamp is never what the offset counts as held (nor journals):
    the clamp's edge on its side is, and the next write goes from there."""
    off = OffsetTracker(_cfg(rate=2.0), held_um=-4.0)
    assert off.observe(held, 0.5) == pytest.approx(held + 4.0)
    assert off.held_um == math.copysign(40.0, held) and off.pending
    off.kept(True)  # the write did not go through: still the edge, never the foreign value
    assert off.held_um == math.copysign(40.0, held)
    shaped = off.plan(4.0, 0, 1.0)
    assert abs(shaped.offset_um) <= 40.0


def test_a_backend_option_typo_is_a_one_line_config_error():
    from cnc_adapters import open_adapter
    from cnc_adapters.sensors import open_sensor
    from compensator.errors import ConfigError

    with pytest.raises(
        ConfigError, match="speed_nod = .*: unknown key \\(did you mean 'speed_node'\\?\\)"
    ):
        open_adapter("opc.tcp://127.0.0.1:4840?speed_nod=ns=2;s=x")
    with pytest.raises(ConfigError, match="bogus = 1: unknown key"):
        open_sensor({"type": "ascii", "port": "/dev/null", "bogus": 1})
    with pytest.raises(ConfigError, match="offset_sign = 1.7: expected"):
        open_adapter({"type": "sim", "offset_sign": 1.7})
    assert open_adapter({"type": "sim", "offset_sign": -1.0}).offset_sign == -1


def test_import_contracts_hold_and_a_wrong_way_import_breaks_them(tmp_path):
    """`lint-imports` passes on this tree and fails once the pure core imports the runtime."""
    lint = Path(sys.executable).with_name("lint-imports")
    ok = subprocess.run([str(lint)], cwd=ROOT, capture_output=True, text=True)
    assert ok.returncode == 0, ok.stdout[-2000:]
    for pkg in PACKAGES:
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    units = tmp_path / "compensator" / "units.py"
    units.write_text(units.read_text() + "\nfrom thermocomp.runtime import spindle  # wrong way\n")
    env = {"PATH": str(lint.parent), "PYTHONPATH": str(tmp_path), "HOME": str(tmp_path)}
    bad = subprocess.run(
        [str(lint), "--no-cache"], cwd=tmp_path, capture_output=True, text=True, env=env
    )
    assert bad.returncode != 0
    assert "compensator.units -> thermocomp.runtime" in bad.stdout


def test_the_wheel_lists_every_package_and_ships_its_data():
    """pyproject.toml names the packages one by one (the examples map in from ./examples), so a
    new package must be added there: this finds one that is not."""
    import tomllib

    root = Path(__file__).parents[1]
    listed = set(
        tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    )
    found = {
        ".".join(p.parent.relative_to(root).parts)
        for top in PACKAGES
        for p in (root / top).rglob("__init__.py")
    }
    assert found | {"thermocomp.examples"} == listed
    for top in PACKAGES:
        assert (root / top / "py.typed").exists()


def test_every_third_party_import_is_declared():
    """Every third-party module the packages import comes from a distribution pyproject.toml
    declares, in the base or an extra (the slim install test runs the base alone). (The ast of each module, its
    imports at any depth; importlib's map of modules to distributions.)"""
    import ast
    import importlib.metadata as md
    import re
    import tomllib

    root = Path(__file__).parents[1]
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    norm = lambda name: re.sub(r"[-_.]+", "-", name).lower()
    req = lambda spec: norm(re.split(r"[<>=!~;\[ ]", spec, maxsplit=1)[0])
    base = {req(d) for d in project["dependencies"]}
    extras = {
        req(d)
        for k, v in project["optional-dependencies"].items()
        if k != "test"
        for d in v
        if not d.startswith("thermocomp")
    }
    dists = {mod: {norm(d) for d in ds} for mod, ds in md.packages_distributions().items()}
    first_party = set(PACKAGES)
    # LinuxCNC's own modules come with LinuxCNC (Debian), not from PyPI
    system = {"hal", "linuxcnc"}
    undeclared = {}
    for top in first_party:
        for path in (root / top).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                names = (
                    [a.name for a in node.names]
                    if isinstance(node, ast.Import)
                    else [node.module]
                    if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module
                    else []
                )
                for name in names:
                    mod = name.split(".")[0]
                    if mod in first_party or mod in system or mod in sys.stdlib_module_names:
                        continue
                    owners = dists.get(mod, {norm(mod)})
                    if not owners & (base | extras):
                        undeclared.setdefault(mod, set()).add(str(path.relative_to(root)))
    assert not undeclared, undeclared


def test_the_architecture_tree_names_every_module():
    """docs/ARCHITECTURE.md's tree ("Where things live") names each module of the product and no
    other, so the map stays true when a module is added, moved or renamed."""
    import re

    root = Path(__file__).parents[1]
    text = (root / "docs" / "ARCHITECTURE.md").read_text()
    tree = text.split("## Where things live", 1)[1].split("```", 2)[1]
    listed, package = set(), None
    for line in tree.splitlines():
        head = re.match(r"^(\S+)/\s", line)
        if head:
            package = head.group(1)
            continue
        entry = re.match(r"^\s+(\S+\.py)\b", line)
        if entry:
            listed.add(f"{package}/{entry.group(1)}")
    found = {
        str(p.relative_to(root))
        for top in PACKAGES
        for p in (root / top).rglob("*.py")
        if p.name not in ("__init__.py", "__main__.py")
    }
    assert listed == found, (
        f"not in the tree: {sorted(found - listed)}; "
        f"in the tree, not in the code: {sorted(listed - found)}"
    )


def test_the_runtime_stays_in_small_parts():
    """Every module of thermocomp/runtime is at most 600 lines, and every class in it spans at
    most 400 lines and assigns at most 20 distinct attributes of ``self``: a part that grows past
    them is split, rather than the service growing back into one class that holds everything."""
    import ast

    root = Path(__file__).parents[1] / "thermocomp" / "runtime"
    too_big = []
    for path in sorted(root.rglob("*.py")):
        text = path.read_text()
        lines = len(text.splitlines())
        if lines > 600:
            too_big.append(f"{path.name}: {lines} lines")
        for cls in ast.walk(ast.parse(text)):
            if not isinstance(cls, ast.ClassDef):
                continue
            span = (cls.end_lineno or cls.lineno) - cls.lineno + 1
            attrs = set()
            for node in ast.walk(cls):
                targets = (
                    node.targets
                    if isinstance(node, ast.Assign)
                    else [node.target]
                    if isinstance(node, (ast.AnnAssign, ast.AugAssign))
                    else []
                )
                for target in targets:
                    for t in ast.walk(target):
                        if (
                            isinstance(t, ast.Attribute)
                            and isinstance(t.value, ast.Name)
                            and t.value.id == "self"
                        ):
                            attrs.add(t.attr)
            if span > 400:
                too_big.append(f"{path.name}: class {cls.name}: {span} lines")
            if len(attrs) > 20:
                too_big.append(f"{path.name}: class {cls.name}: {len(attrs)} attributes")
    assert not too_big, too_big
