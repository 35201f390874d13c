"""``thermocomp replay`` with a runtime configuration: the shaping, the estimate (observer, speed
policy, input-fault timing) and the model of one of its spindles, so that replay writes what that
spindle's runtime would write."""

from __future__ import annotations

import argparse

from calibration.commands import replay_cmd
from compensator.errors import ConfigError
from compensator.shaping import ShaperConfig

from ..runtime.config import load_config


def replay(args: argparse.Namespace) -> int:
    shaping: ShaperConfig | None = None
    spindle = None
    if args.config is not None:
        cfg = load_config(args.config)
        names = [s.name for s in cfg.spindle]
        if args.spindle is None and len(names) > 1:
            raise ConfigError(
                f"{args.config} has {len(names)} spindles ({', '.join(names)}): "
                "name one with --spindle"
            )
        spindle = next((s for s in cfg.spindle if args.spindle in (None, s.name)), None)
        if spindle is None:
            raise ConfigError(
                f"{args.config} has no spindle {args.spindle!r} (it has {', '.join(names)})"
            )
        shaping = spindle.shaping
        if args.model is None:
            args.model = str(spindle.model)
    elif args.spindle is not None:
        raise ConfigError("--spindle goes with --config")
    if args.model is None:
        raise ConfigError(
            "give the model file (--model), or a runtime configuration (--config) "
            "whose spindle names one"
        )
    # the spindle's own estimate: its observer, its speed policy and its input-fault timing
    return replay_cmd(args, shaping, None if spindle is None else spindle.estimate)
