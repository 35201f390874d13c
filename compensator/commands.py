"""``thermocomp model``: show a model file or print its JSON schema."""

from __future__ import annotations

import argparse
import json

from .errors import ConfigError
from .io import load_model
from .model import ThermalModel


def model(args: argparse.Namespace) -> int:
    if args.schema:
        print(json.dumps(ThermalModel.model_json_schema(), indent=2))
        return 0
    if not args.model:
        raise ConfigError("give a model file, or --schema")
    m = load_model(args.model)
    if args.json:
        print(json.dumps(m.model_dump(mode="json"), indent=2))
        return 0
    lo, hi = m.speed_range_rpm
    print(f"{args.model}: {m.format}, form {m.form}, spindle {m.spindle_id!r}, machine {m.machine_id!r}")
    print(f"  fitted at {m.fitted_dt_s:g} s over {lo:.0f}..{hi:.0f} rpm; stable over that range")
    for n in (0.0, hi / 2, hi):
        taus = ", ".join(f"{t / 60:.1f}" for t in m.time_constants_s(n))
        print(f"  at {n:7.0f} rpm: tau = {taus} min, equilibrium {m.steady_state_um(n):7.2f} um")
    if m.fit:
        print("  fit: " + ", ".join(f"{k}={v}" for k, v in m.fit.items()))
    return 0
