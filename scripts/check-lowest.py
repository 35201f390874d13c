"""After `make test-lowest` installed the oldest allowed versions: every direct dependency in
the venv is at its declared lower bound, so the tests ran on the floor pyproject.toml claims.
Run with the lowest venv's Python; exit 1, naming each that is not."""

from __future__ import annotations

import importlib.metadata as md
import re
import sys
import tomllib
from pathlib import Path

project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]
specs = list(project["dependencies"]) + [
    d
    for k, v in project["optional-dependencies"].items()
    for d in v
    if not d.startswith("thermocomp")
]
off = []
for spec in specs:
    m = re.match(r"\s*([A-Za-z0-9_.\-]+)\s*>=\s*([0-9][0-9.]*)", spec)
    if m is None:
        off.append(f"{spec}: no lower bound")
        continue
    name, floor = m.groups()
    norm = lambda v: tuple(int(x) for x in v.split(".")) + (0,) * (3 - len(v.split(".")))  # noqa: E731
    have = md.version(name)
    if norm(re.match(r"[0-9.]*[0-9]", have).group()) != norm(floor):
        off.append(f"{name}: declared >={floor}, installed {have}")
for line in off:
    print(f"check-lowest: {line}", file=sys.stderr)
print(
    f"check-lowest: {len(specs) - len(off)} of {len(specs)} direct dependencies at their lower bound"
)
sys.exit(1 if off else 0)
