"""The service's checks outside its loop: ``thermocomp run --check`` (:func:`check`: validate,
load, connect, read once, write nothing), ``thermocomp measure`` (:func:`measure`: one
measurement to the running service) and the plausibility rule a model must pass to be run."""

from __future__ import annotations

import argparse
import json
import math

from cnc_adapters import BACKENDS, open_adapter
from cnc_adapters.base import Adapter, query_params
from cnc_adapters.chiller import open_chiller
from cnc_adapters.control_profiles import adapter_settings, profile
from compensator.errors import ConfigError, ControlError
from compensator.io import load_any_model
from compensator.modelbase import range_share_refusal
from compensator.observer import SIGMA_LIMIT_UM
from compensator.plausibility import steady_state_um
from compensator.predictor import Predictor

from .config import RuntimeConfig, SpindleConfig, load_config, spindle_scope
from .control import send_measurement
from .spindle import cutting_from_controller

PLAUSIBLE_ELONGATION_UM = 5000.0
"""A model whose steady elongation anywhere in its speed range exceeds this (5 mm) is not a
spindle's: a reload refuses it."""


def implausible(model: Predictor) -> str | None:
    """Why a model that loads cannot be a spindle's, or None. ``model``: a speed-only one (the
    fallback of a model with inputs)."""
    lo, hi = model.speed_range_rpm
    for n in (lo, (lo + hi) / 2, hi):
        s = steady_state_um(model, n)
        if not math.isfinite(s) or abs(s) > PLAUSIBLE_ELONGATION_UM:
            return f"model predicts {s:g} um at {n:g} rpm: not plausible"
    return None


def plausible(model: Predictor, name: str, max_speed_rpm: float | None = None) -> None:
    """Refuse a model that loads but cannot be a spindle's, or this one's, rated
    ``max_speed_rpm`` (ConfigError)."""
    why = implausible(model) or range_share_refusal(model.speed_range_rpm[1], max_speed_rpm)
    if why is not None:
        raise ConfigError(f"{spindle_scope(name)}: {why}")


def shaping_check(sc: SpindleConfig, link: Adapter) -> str:
    """What the shaping will do with this link: the policy, its limits, and where the cutting
    state comes from (read once now); a ConfigError where the controller's signal is required
    and the link has none."""
    sh = sc.shaping
    words = {
        "dual-slew": f"dual slew {sh.max_rate_um_per_s:g} um/s cutting, {sh.fast_rate_um_per_s:g} um/s not",
        "longer-cycle": f"longer cycle in transients, {sh.max_rate_um_per_s:g} um/s",
        "hold": f"hold in transients, {sh.max_rate_um_per_s:g} um/s",
        "slow-slew": f"one slew limit, {sh.max_rate_um_per_s:g} um/s",
    }
    if cutting_from_controller(sc, link.capabilities):
        source = f"cutting signal from the controller, now {'cutting' if link.read_cutting() else 'not cutting'}"
    else:
        source = (
            f"cutting inferred from the speed (held {sh.cutting.settle_s:g} s within "
            f"{sh.cutting.speed_tolerance_rpm:g} rpm or {sh.cutting.speed_tolerance_pct:g} %)"
        )
    return f"shaping: {words[sh.policy]}; {source}"


FAMILY_DOCS = {
    "linuxcnc": "linuxcnc",
    "focas": "fanuc",
    "haas": "haas",
    "haas-mdc": "haas",
    "plc": "plc",
    "modbus": "plc",
}
"""A link's backend -> its control family's page in ``docs/controls/`` (the others: the index)."""


LIFE_OPTIONS = {
    "opcua": "life_node and valid_node",
    "modbus": "life_register and valid_register",
    "plc": "life_address and valid_address",
    "focas": "life_macro and valid_macro",
    "haas": "life_var and valid_var",
    "haas-mdc": "life_var and valid_var",
    "line": "life_request",
}
"""A link's backend -> the options that name its sign of life."""


def _backend(link: Adapter) -> str:
    spec = f"{type(link).__module__}:{type(link).__name__}"
    return next((name for name, where in BACKENDS.items() if where == spec), "")


def family_doc(sc: SpindleConfig, link: Adapter) -> str:
    """The page of the control family a spindle's link drives: its profile's, else its
    backend's family, else the index of the families."""
    if sc.profile is not None:
        return sc.profile.doc
    if sc.adapter.get("preset") == "virtual-cnc":  # the virtual CNC's, without its profile
        return profile("virtual").doc
    return f"docs/controls/{FAMILY_DOCS.get(_backend(link), 'index')}.md"


def life_check(sc: SpindleConfig, link: Adapter) -> str | None:
    """A warning where the link writes no sign of life: the control cannot watch the service;
    it names the backend's options that would write one, and the page of its recipe."""
    if link.capabilities.life_sign:
        return None
    options = LIFE_OPTIONS.get(_backend(link))
    fix = f"set {options}" if options else "this link writes none"
    return (
        f"{sc.name}: warning: the control cannot tell when thermocomp stops: {fix} "
        f"({family_doc(sc, link)})"
    )


def life_settings(sc: SpindleConfig) -> dict[str, object]:
    """The spindle's adapter settings as the link gets them (a profile's route merged, a URL's
    query under the keys given): what ``run --check`` says its sign of life is."""
    settings = adapter_settings(sc.adapter)
    url = settings.get("url")
    return {**query_params(url), **settings} if isinstance(url, str) else settings


def check(config_path: str) -> int:
    """Validate the configuration, load the models, connect, read one speed; write nothing."""
    cfg = load_config(config_path)
    for sc in cfg.spindle:
        model = load_any_model(sc.model)
        sc.refuse_other_spindle(model.spindle_id)
        plausible(model.fallback or model, sc.name, sc.faults.max_speed_rpm)
        with open_adapter(sc.adapter) as link:
            speed = link.read_speed()
            extra = ""
            names = model.input_names
            if names:
                missing = sorted(set(names) - set(link.input_channels()))
                if missing:
                    raise ConfigError(
                        f"{spindle_scope(sc.name)}: the model needs input(s) {', '.join(missing)}; "
                        "map them in the adapter"
                    )
                values = link.read_inputs()
                extra = ", inputs " + ", ".join(f"{n} {values[n]:g}" for n in names)
            if getattr(link, "can_read_offset", False):
                extra += f", holds offset {link.read_offset_um():.3f} um"
            extra += "; " + shaping_check(sc, link)
            life = life_check(sc, link)
            writes_life = link.capabilities.life_sign
            # looked up, not written: the offset goes without them, the control's watch does not
            life_problems = link.life_problems()
        print(f"{sc.name}: model {model.form} ({sc.model}), link ok, speed {speed:.0f} rpm{extra}")
        if life is not None:
            print(life)
        for line in life_problems:
            print(f"{sc.name}: warning: the sign of life cannot be written: {line}")
        if sc.profile is not None:
            res = (
                f"; the offset moves in whole counts of {sc.shaping.resolution_um:g} um"
                if sc.shaping.resolution_um
                else ""
            )
            described = sc.profile.describe(sc.route, life_settings(sc), writes_life)
            print(f"{sc.name}: {described}{res}")
            ctl = sc.profile.control_rate_um_per_s
            if ctl is not None and ctl < sc.shaping.rate_limit_um_per_s:
                print(
                    f"{sc.name}: warning: the control moves the offset at most {ctl:g} um/s, slower "
                    f"than the shaping's {sc.shaping.rate_limit_um_per_s:g} um/s: the elastic step of a "
                    "speed change lands late, in the first seconds of the next cut"
                )
    c = cfg.cooling
    if c is not None and c.mode != "off":
        with open_chiller(c.chiller["type"], c.chiller_options) as chiller:
            supply = chiller.read_supply_c()
        mode = (
            "the chiller only, no offset" if c.mode == "cooling" else "the chiller and the offset"
        )
        print(
            f"cooling ({mode}) on {cfg.cooling_spindle}'s estimate: chiller {c.chiller['type']} ok, "
            f"supply {supply:.1f} degC"
        )
        for line in c.law().describe():
            print(f"cooling: {line}")
    st = cfg.status
    if st.enabled:
        st.token()  # a missing or short token: a one-line ConfigError now, not at the service's start
        print(
            f"status: http://{st.bind}:{st.port}/ ({'token' if st.access == 'token' else 'open'} access)"
        )
    if cfg.mqtt is not None and cfg.mqtt.enabled:
        m = cfg.mqtt
        m.password()
        if m.tls and m.ca_file is not None and not m.ca_file.is_file():
            raise ConfigError(f"mqtt.ca_file {m.ca_file}: not a file")
        print(f"mqtt: {m.host}:{m.port}, topic {m.topic} (not connected by --check)")
    print(f"configuration {config_path}: ok ({len(cfg.spindle)} spindle(s)); nothing was written")
    return 0


def measure(args: argparse.Namespace) -> int:
    """``thermocomp measure``: one measurement to the running service; exit 0 when it was
    taken (accepted, or the bias restarted from it), 1 when the observer rejected it or took it
    only in part (its bounds: ``limited``)."""
    um, sigma = args.um, args.sigma_um
    if not math.isfinite(um) or abs(um) > 1e4:
        raise ConfigError(f"--um must be a finite elongation in um (|um| <= 10000), not {um:g}")
    if sigma is not None and not (math.isfinite(sigma) and 0 < sigma <= SIGMA_LIMIT_UM):
        raise ConfigError(
            f"--sigma-um must be a number > 0 and at most {SIGMA_LIMIT_UM:g} um, not {sigma:g}"
        )
    if args.timeout_s is not None and not (math.isfinite(args.timeout_s) and args.timeout_s > 0):
        raise ConfigError("--timeout-s must be a number > 0")
    if args.state_dir and args.config:
        raise ConfigError("give --state-dir or --config, not both")
    state_dir = args.state_dir or (
        load_config(args.config).state_dir
        if args.config
        else RuntimeConfig.model_fields["state_dir"].default
    )
    answer = send_measurement(state_dir, um, sigma, args.spindle, args.timeout_s or 60.0)
    if not answer.get("ok"):
        raise ControlError(f"the service refused it: {answer.get('error', 'no reason given')}")
    if args.json:
        print(json.dumps(answer, allow_nan=False))
    else:
        print(
            f"{answer.get('spindle')}: {answer.get('outcome')}: measured {answer.get('measured_um', um):.3f} um, "
            f"estimate {answer.get('estimate_um', math.nan):.3f} um, innovation "
            f"{answer.get('innovation_um', math.nan):+.3f} um (sd {answer.get('innovation_sd_um', math.nan):.3f} "
            f"um); bias now {answer.get('bias_um', math.nan):+.3f} um"
        )
    return 1 if answer.get("outcome") in ("rejected", "limited") else 0
