"""``thermocomp controls [NAME]``: the controller profiles, and what one does on its control."""

from __future__ import annotations

import argparse
import json

from cnc_adapters.control_profiles import PROFILES, profile


def main(args: argparse.Namespace) -> int:
    if args.name is None:
        rows = [(p.name, p.title, p.unit, ", ".join(p.routes), p.doc) for p in PROFILES.values()]
        if args.json:
            print(
                json.dumps([dict(zip(("name", "title", "unit", "routes", "doc"), r)) for r in rows])
            )
            return 0
        for r in rows:
            print(f"{r[0]:<11} {r[1]:<34} {r[2]:<48} routes: {r[3]:<12} {r[4]}")
        return 0
    p = profile(args.name)  # a ConfigError naming the known ones
    if args.json:
        print(
            json.dumps(
                {
                    **p.model_dump(mode="json"),
                    "limit_um": p.limit_um,
                    "resolution_um": p.resolution_um,
                }
            )
        )
        return 0
    for route in p.routes:
        print(p.describe(route))
        print()
    print("On the control (the short form; the whole recipe is in " + p.doc + "):")
    print(p.snippet)
    return 0
