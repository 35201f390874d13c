"""``thermocomp model show|check|schema``: describe or check a model file, or print the JSON schema of a
format (``history`` and ``rollback`` are in :mod:`.learning`)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from compensator.errors import ConfigError, ThermocompError, clip
from compensator.fitrecord import fit_of
from compensator.io import MODEL_TYPES, load_any_model, model_digest
from compensator.model import MODEL_FORMAT
from compensator.plausibility import (
    direction_of,
    not_following_refusal,
    steady_growth_refusal,
    time_constant_refusal,
)

REASON_CHARS = 500


def show(args: argparse.Namespace) -> int:
    """``thermocomp model show FILE``: what the model is, or the whole of it as JSON."""
    m = load_any_model(args.file)
    if args.json:
        print(json.dumps(m.model_dump(mode="json"), indent=2))
        return 0
    first, *rest = m.describe()
    print(f"{args.file}: {first}")
    for line in rest:
        print(line)
    return 0


def check_cmd(args: argparse.Namespace) -> int:
    return check(args.file, as_json=args.json)


def schema(args: argparse.Namespace) -> int:
    return _schema(args.format)


def _schema(fmt: str | None) -> int:
    """One format's schema (default: the speed-only model's, as before), or every registered
    format's keyed by format name (``all``)."""
    if fmt == "all":
        print(
            json.dumps(
                {name: cls.model_json_schema() for name, cls in MODEL_TYPES.items()}, indent=2
            )
        )
        return 0
    cls = MODEL_TYPES.get(fmt or MODEL_FORMAT)
    if cls is None:
        raise ConfigError(
            clip(
                f"--format {fmt!r}: not a model format; known: {', '.join(MODEL_TYPES)}, or all",
                500,
            )
        )
    print(json.dumps(cls.model_json_schema(), indent=2))
    return 0


def summary(m: Any) -> dict[str, Any]:
    """What a checked model is, for people and for ``--json``."""
    lo, hi = m.speed_range_rpm
    return {
        "format": m.format,
        "form": m.form,
        "spindle_id": m.spindle_id,
        "machine_id": m.machine_id,
        "states": getattr(m, "order", None),
        "inputs": list(m.input_names),
        "speed_range_rpm": [lo, hi],
        "fallback": m.fallback.form if m.fallback is not None else None,
        "sha256": model_digest(m),
    }


def check(path: str, as_json: bool = False) -> int:
    """Would the runtime take this file: verified and sane (:func:`load_any_model`), plausible
    (the runtime's own check), and one physics allows (:mod:`compensator.plausibility`: a
    calibration that followed its program, a steady growth that rises with speed in the growth
    direction its fit record states, else its own, and a spindle's time scale). Exit 0, or 2
    with a one-line reason, as any refusal."""
    from thermocomp.runtime.service import implausible  # the runtime's own rule, loaded only here

    try:
        m = load_any_model(path)
        why = implausible(m.fallback or m)
        if why is None:
            why = not_following_refusal(fit_of(m).not_following_share)
        if why is None:
            why = steady_growth_refusal(m, direction_of(fit_of(m).growth_direction))
        if why is None:
            why = time_constant_refusal(m)
        if why is not None:
            raise ConfigError(f"{path}: {why}")
    except ThermocompError as err:
        if not as_json:
            raise  # the CLI prints it as one line and exits 2
        reason = str(err)
        reason = (
            reason[len(path) + 2 :] if reason.startswith(f"{path}: ") else reason
        )  # "file" says it
        print(json.dumps({"file": path, "ok": False, "reason": clip(reason, REASON_CHARS)}))
        return 2
    info = summary(m)
    if as_json:
        print(json.dumps({"file": path, "ok": True, "reason": None, **info}))
        return 0
    states = f", {info['states']} states" if info["states"] is not None else ""
    inputs = ", inputs " + ", ".join(info["inputs"]) if info["inputs"] else ", speed only"
    lo, hi = info["speed_range_rpm"]
    print(
        clip(
            f"{path}: ok: {info['form']} ({info['format']}), spindle {info['spindle_id']!r}"
            f"{states}{inputs}, {lo:.0f}..{hi:.0f} rpm",
            1000,
        )
    )
    return 0
