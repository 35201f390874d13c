"""``thermocomp model``: show a model file or print its JSON schema."""

from __future__ import annotations

import argparse
import json

from .errors import ConfigError
from .inputs import AugmentedModel
from .io import load_any_model
from .model import ThermalModel


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
    if isinstance(m, AugmentedModel):
        print(f"{args.model}: {m.format}, inputs {', '.join(m.input_names)}, spindle {m.spindle_id!r}")
        for t in m.inputs:
            dyn = "static" if t.tau_s == 0 else f"lag {t.tau_s:g} s"
            ref = "its value at a cold start" if t.reference_mode == "start" else f"{t.reference:g} {t.unit}"
            print(f"  {t.name}: {t.gain_um_per_unit:.4g} um/{t.unit}, {dyn}, relative to {ref}, "
                  f"valid {t.valid_range[0]:.3g}..{t.valid_range[1]:.3g} {t.unit}")
        if m.fit:
            print("  fit: " + ", ".join(f"{k}={v}" for k, v in m.fit.items()))
        print("  speed part (fitted with the inputs):")
        m, fallback = m.speed_model, m.fallback
        print(f"  fallback when a sensor fails: {fallback.form} (speed only)")
    lo, hi = m.speed_range_rpm
    print(f"{args.model}: {m.format}, form {m.form}, spindle {m.spindle_id!r}, machine {m.machine_id!r}")
    print(f"  fitted at {m.fitted_dt_s:g} s over {lo:.0f}..{hi:.0f} rpm; stable over that range")
    for n in (0.0, hi / 2, hi):
        taus = ", ".join(f"{t / 60:.1f}" for t in m.time_constants_s(n))
        print(f"  at {n:7.0f} rpm: tau = {taus} min, equilibrium {m.steady_state_um(n):7.2f} um")
    if m.fit:
        print("  fit: " + ", ".join(f"{k}={v}" for k, v in m.fit.items()))
    return 0
