"""``thermocomp model``: show a model file or print its JSON schema."""

from __future__ import annotations

import argparse
import json

from compensator.errors import ConfigError
from compensator.io import load_any_model
from compensator.model import ThermalModel


def model(args: argparse.Namespace) -> int:
    if args.schema:
        print(json.dumps(ThermalModel.model_json_schema(), indent=2))
        return 0
    if not args.model:
        raise ConfigError("give a model file, or --schema")
    m = load_any_model(args.model)
    if args.json:
        print(json.dumps(m.model_dump(mode="json"), indent=2))
        return 0
    first, *rest = m.describe()
    print(f"{args.model}: {first}")
    for line in rest:
        print(line)
    return 0
