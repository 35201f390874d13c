"""``thermocomp init [DIR]``: write the example configurations shipped with the package (the
annotated runtime configuration, cooling, closed loop, controls, the systemd unit, the model
schema and the LinuxCNC sim configuration), for an install that has no source checkout."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from compensator.errors import ConfigError


def _files(root, prefix: str = ""):
    for entry in sorted(root.iterdir(), key=lambda e: e.name):
        if entry.name.startswith(("_", ".")):
            continue  # __init__.py, caches
        if entry.is_dir():
            yield from _files(entry, f"{prefix}{entry.name}/")
        else:
            yield f"{prefix}{entry.name}", entry


def main(args) -> int:
    out = Path(args.directory)
    files = list(_files(resources.files("thermocomp.examples")))
    clash = [name for name, _ in files if (out / name).exists()]
    if clash and not args.force:
        raise ConfigError(
            f"{out}: {', '.join(clash[:3])}{' ...' if len(clash) > 3 else ''} exist(s); "
            "nothing written (--force overwrites)"
        )
    for name, entry in files:
        target = out / name
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(entry.read_bytes())
        print(target)
    print(
        f"thermocomp: {len(files)} example file(s) written; start with machine.toml, then "
        "`thermocomp run --config machine.toml --check`"
    )
    return 0
