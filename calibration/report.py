"""The calibration report (HTML or Markdown, plots embedded) and the runtime configuration the
wizard writes. Text in, text out: the wizard writes the files."""

from __future__ import annotations

import base64
import html
import math
import os
import re
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit, urlunsplit

from cnc_adapters.base import redact_url, url_has_password
from compensator.plausibility import steady_state_um
from compensator.predictor import Predictor
from compensator.shaping import ShaperConfig

from .candidate import MIN_FORWARD_FOLDS
from .closedloop import PROBE_SIGMA_UM

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
"""A runtime spindle name (``SpindleConfig.name``)."""


def _b64(path: str | Path) -> str:
    return base64.b64encode(Path(path).read_bytes()).decode("ascii")


def _f(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def _held_out_max(c: dict[str, Any]) -> float | None:
    """The max that goes with ``honest_rms_um``: nested where the candidate was nested."""
    return c["nested_max_abs_um"] if c.get("nested_rms_um") is not None else c["cv_max_abs_um"]


def _error_table(summary: dict[str, Any]) -> list[list[str]]:
    """Every free-run figure the report states, each named by what it was scored on."""
    rep = summary["report"]
    chosen = next(c for c in rep["candidates"] if c["name"] == rep["chosen"])
    basis = "nested " if chosen.get("nested_rms_um") is not None else ""
    rows = [
        ["figure", "RMS [um]", "max [um]", "samples"],
        [
            f"identification (held out): {chosen['name']}, {basis}{rep['scored_by']}",
            _f(chosen["honest_rms_um"]),
            _f(_held_out_max(chosen)),
            "-",
        ],
    ]
    folds = len(chosen.get("forward_folds_rms_um") or [])
    if chosen.get("forward_rms_um") is not None:
        note = (
            " (blocks of one cycle: extrapolation in speed, not decided by)"
            if not rep.get("forward_decides", True)
            else ""
            if folds >= MIN_FORWARD_FOLDS
            else " (too few to decide by)"
        )
        rows.append(
            [
                f"identification (held out): {chosen['name']}, predicted forward, {folds} fold"
                f"{'' if folds == 1 else 's'} each from the ones before it{note}",
                _f(chosen["forward_rms_um"]),
                _f(chosen["forward_max_abs_um"]),
                "-",
            ]
        )
    v = summary.get("validation")
    if v:
        rows.append(
            [
                "validation (held out): a run the fit never saw, free run",
                _f(v["rms_um"]),
                _f(v["max_abs_um"]),
                str(v["samples"]),
            ]
        )
        vr = summary.get("validation_report") or {}
        sh = vr.get("shaping") or {}
        if vr.get("applied_cutting_max_abs_residual_um") is not None and sh.get("policy"):
            rows.append(
                [
                    f"validation (held out): the offset as shaped ({sh['policy']}, "
                    f"{sh['max_rate_um_per_s']:g} um/s while cutting), while the tool cuts",
                    _f(vr.get("applied_cutting_rms_residual_um")),
                    _f(vr["applied_cutting_max_abs_residual_um"]),
                    "-",
                ]
            )
    cal = summary["calibration"]
    rows.append(
        [
            "calibration (in sample): the data the model was fitted on, free run",
            _f(cal["rms_um"]),
            _f(cal["max_abs_um"]),
            str(cal["samples"]),
        ]
    )
    return rows


def _run_use(name: str, info: dict[str, Any], summary: dict[str, Any]) -> str:
    if not info.get("complete"):
        return "incomplete: not used"
    if name == "calibration":
        return "fitted (in sample)"
    if name == "validation" and summary.get("validation"):
        return "held out: free run only"
    return "not used"


def _sections(
    session: dict[str, Any],
    summary: dict[str, Any],
    model: Predictor,
    model_path: Path,
    version: str,
) -> list[tuple[str, list[list[str]] | list[str]]]:
    rep = summary["report"]
    runs_info = session.get("runs", {})
    if session.get("sensor"):
        displacement = redact_url(str(session["sensor"]))
    elif session.get("source") == "import":
        files = [
            Path(i["imported_from"]).name for i in runs_info.values() if i.get("imported_from")
        ]
        displacement = "imported" + (f" from {', '.join(files)}" if files else "")
    elif session.get("source") == "tool-setter":
        plan = session.get("probe_plan") or {}
        displacement = "the machine's tool setter, read by the controller link" + (
            f", every {plan['interval_s'] / 60:.0f} min ({plan['dwell_s']:.0f} s a stop"
            + (f", {plan['touches']} touches averaged" if plan.get("touches", 1) > 1 else "")
            + ")"
            if plan
            else ""
        )
    else:
        displacement = str(session.get("source") or "-")
    controller = session.get("controller")
    ident = [
        ["machine", session["machine_id"]],
        ["spindle", session["spindle_id"]],
        ["maximum speed", f"{session['max_rpm']:.0f} rpm"],
        ["controller", "-" if not controller else redact_url(str(controller))],
        ["displacement", displacement],
        ["model file", f"{model_path.name} ({version})"],
        ["model form", model.form],
        ["created (UTC)", str(getattr(model, "created_utc", None) or "")],
    ]
    runs = [["run", "log", "rows", "flagged", "program", "in this report"]]
    for name, info in runs_info.items():
        runs.append(
            [
                name,
                Path(info["log"]).name,
                str(info.get("rows", "-")),
                ", ".join(f"{k} {v}" for k, v in (info.get("flagged") or {}).items()) or "none",
                Path(session.get("programs", {}).get(name, "-")).name,
                _run_use(name, info, summary),
            ]
        )
    cands = [
        [
            "candidate",
            "held-out RMS [um]",
            "held-out max [um]",
            "forward RMS [um]",
            "forward max [um]",
            "decisive RMS [um]",
            "in-sample RMS [um]",
            "verdict",
        ]
    ]
    for c in rep["candidates"]:
        mark = " (chosen)" if c["name"] == rep["chosen"] else ""
        verdict = (
            "reference only"
            if c["family"] == "reference"
            else "accepted"
            if c["accepted"]
            else "refused: " + "; ".join(c["refusals"])
        )
        cands.append(
            [
                c["name"] + mark,
                _f(c["honest_rms_um"]),
                _f(_held_out_max(c)),
                _f(c.get("forward_rms_um")),
                _f(c.get("forward_max_abs_um")),
                _f(c.get("decisive_rms_um", c["honest_rms_um"])),
                _f(c["in_sample_rms_um"]),
                verdict,
            ]
        )
    steady = [["speed [rpm]", "steady growth [um]"]]
    for frac in (0.25, 0.5, 0.75, 1.0):
        n = frac * session["max_rpm"]
        steady.append([f"{n:.0f}", _f(steady_state_um(model, n))])
    notes = list(summary.get("warnings", []))
    v = summary.get("validation")
    if v and str(rep.get("scored_by", "")).startswith("blocked"):
        # the fit saw one cycle; the validation run is the check on another, kept out of the fit
        notes.append(
            f"the validation run is a second cycle, which the fit never saw: free-run RMS "
            f"{_f(v['rms_um'])} um, max {_f(v['max_abs_um'])} um (held out)"
        )
    elif (
        not v and session.get("validation") and not runs_info.get("validation", {}).get("complete")
    ):
        notes.append("the validation run is incomplete: no run held out of the fit was scored")
    notes += [f"advice: {a}" for a in summary.get("advice", [])]
    loop: list[list[str]] = []
    cl = summary.get("closed_loop")
    if cl:
        loop = [["probe every", "RMS [um]", "max [um]"]]
        loop += [
            [
                "never" if r["interval_s"] is None else f"{r['interval_s']:.0f} s",
                _f(r["rms_um"]),
                _f(r["max_abs_um"]),
            ]
            for r in cl["intervals"]
        ]
        rec = cl["recommended_interval_s"]
        target = f"{cl['target_rms_um']:g} um RMS"
        loop.append(
            [
                "recommended",
                f"none meets {target}" if rec is None else f"{rec:.0f} s",
                f"target {target}",
            ]
        )
    sigma = (
        f", probe sigma {cl['probe_sigma_um']:g} um"
        if cl and cl.get("probe_sigma_um") is not None
        else ""
    )
    return [
        ("Spindle", ident),
        ("Runs", runs),
        (
            "Free-run error: held out (data the fit did not see) and in sample",
            _error_table(summary),
        ),
        (
            f"Candidates (held out: {rep['scored_by']}; forward: each fold from the ones before it; "
            "the choice reads the decisive RMS)",
            cands,
        ),
        (f"Chosen: {rep['chosen']}", [rep["reason"]]),
        ("The model", model.describe()),
        ("Steady-state growth predicted", steady),
        *(
            [
                (
                    "Spindle thermal test in the terms of ISO 230-3 (thermal distortion caused by a rotating "
                    "spindle; drift from the start of the run; calibration in sample, validation held out)",
                    summary["iso230_3"],
                )
            ]
            if summary.get("iso230_3")
            else []
        ),
        *(
            [
                (
                    f"Closed loop with a tool setter (scored on the validation run, held out{sigma})",
                    loop,
                )
            ]
            if loop
            else []
        ),
        ("Warnings and advice", notes or ["none"]),
    ]


def calibration_report(
    session: dict[str, Any],
    summary: dict[str, Any],
    model: Predictor,
    model_path: Path,
    fmt: str,
    version: str,
) -> str:
    """The report as HTML (one self-contained file) or Markdown; the plot embedded as data URI."""
    title = f"Thermal calibration: {session['machine_id']} / {session['spindle_id']}"
    secs = _sections(session, summary, model, model_path, version)
    img = _b64(summary["plot"])
    if fmt == "md":
        out = [f"# {title}", ""]
        for head, body in secs:
            out += [f"## {head}", ""]
            if body and isinstance(body[0], list):
                out.append("| " + " | ".join(body[0]) + " |")
                out.append("|" + "---|" * len(body[0]))
                out += [
                    "| " + " | ".join(c.replace("|", "/") for c in row) + " |" for row in body[1:]
                ]
            else:
                out += [f"- {line}" for line in body]
            out.append("")
        out += [
            "## Measured and predicted (free run)",
            "",
            f"![fit](data:image/png;base64,{img})",
            "",
        ]
        return "\n".join(out)
    if fmt != "html":
        raise ValueError(f"report format {fmt!r}: html or md")
    e = html.escape
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>{e(title)}</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto}"
        "table{border-collapse:collapse}td,th{border:1px solid #bbb;padding:3px 8px}"
        "img{max-width:100%}</style></head><body>",
        f"<h1>{e(title)}</h1>",
    ]
    for head, body in secs:
        parts.append(f"<h2>{e(head)}</h2>")
        if body and isinstance(body[0], list):
            parts.append("<table><tr>" + "".join(f"<th>{e(c)}</th>" for c in body[0]) + "</tr>")
            parts += [
                "<tr>" + "".join(f"<td>{e(c)}</td>" for c in row) + "</tr>" for row in body[1:]
            ]
            parts.append("</table>")
        else:
            parts.append("<ul>" + "".join(f"<li>{e(str(x))}</li>" for x in body) + "</ul>")
    parts += [
        "<h2>Measured and predicted (free run)</h2>",
        f"<img alt='fit' src='data:image/png;base64,{img}'>",
        "</body></html>",
    ]
    return "\n".join(parts)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    out = []
    for ch in str(v):
        if ch in '\\"':
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:  # TOML takes no raw control character
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _without_password(url: str) -> tuple[str, bool]:
    """``url`` without the password in its user information (the runtime refuses a URL that
    carries one: it would end up in logs), and whether there was one."""
    try:
        parts = urlsplit(url)
        userinfo, _at, host = parts.netloc.rpartition("@")
    except ValueError:
        return redact_url(url), "@" in url
    if not url_has_password(url):
        return url, False
    user = userinfo.partition(":")[0]
    return urlunsplit(parts._replace(netloc=f"{user}@{host}" if user else host)), True


def _relative(path: Path, start: Path) -> str:
    """``path`` relative to ``start`` (what the runtime resolves it against), else absolute."""
    try:
        return os.path.relpath(Path(path).absolute(), Path(start).absolute())
    except ValueError:  # another drive
        return str(Path(path).absolute())


def _line(key: str, value: Any, why: str = "") -> str:
    text = f"{key} = {_toml_value(value)}"
    return f"{text:<38} # {why}" if why else text


def runtime_config(
    session: dict[str, Any], model: Predictor, model_path: Path, config_dir: Path | None = None
) -> str:
    """A ``thermocomp run`` configuration for this spindle, to be written into ``config_dir``
    (default ``<session>/config``, beside the wizard's ``<session>/models``): the product's
    defaults but for what this spindle needs; paths relative to the file (the runtime resolves
    them so); the spindle id the model file must carry; the controller link without a password."""
    model_path = Path(model_path)
    config_dir = model_path.parent.parent / "config" if config_dir is None else Path(config_dir)
    machine, spindle = session["machine_id"], session["spindle_id"]
    name = f"{machine}-{spindle}"
    if not _NAME.fullmatch(name) or ".." in name:
        name = spindle  # both ids are too long for a spindle name: the spindle's alone
    lines = [
        f"# thermocomp runtime configuration for {machine} / {spindle}",
        "# written by `thermocomp wizard`; check it with `thermocomp run --config THIS --check`",
        "# What is left out is the product's default (examples/machine.toml shows every option).",
        "# Paths are relative to this file, so the session directory can move as a whole.",
        _line(
            "state_dir",
            _relative(config_dir.parent / "state", config_dir),
            "this session's; a system service keeps /var/lib/thermocomp",
        ),
        *(
            [
                _line(
                    "time_scale",
                    float(session["time_scale"]),
                    "the virtual machine tool's, as calibrated: remove on a real machine",
                )
            ]
            if float(session.get("time_scale") or 1.0) != 1.0
            else []
        ),
        "",
        "[[spindle]]",
        _line("name", name),
        _line("spindle_id", spindle, "a model file fitted on another spindle is refused"),
        _line("model", _relative(model_path, config_dir)),
        "",
        "[spindle.adapter]",
    ]
    controller = session.get("controller")
    if controller:
        url, had_password = _without_password(str(controller))
        if had_password:
            lines += [
                "# the wizard's link carried a password, left out here (a URL with one is refused):",
                "# give it in password_file, a systemd credential or the environment",
            ]
        lines.append(_line("url", url))
    else:
        lines.append(
            _line("url", "opc.tcp://CHANGE-ME:4840", "the wizard was given no controller link")
        )
    if session.get("source") == "tool-setter":
        # the link read the tool setter at calibration: the service fuses its measurements too
        lines += [
            "",
            "# call the tool-setter cycle from the production programs too (every 30 to 60 min):",
            "# without measurements the observer goes stale (OBSERVER_STALE) and the model runs open loop",
            "[spindle.observer]",
            _line(
                "enabled",
                True,
                "fuse the tool setter's measurements with the model (the closed loop)",
            ),
        ]
        touches = int((session.get("probe_plan") or {}).get("touches", 1))
        if touches > 1:  # the cycle hands on the mean of its touches
            sigma = PROBE_SIGMA_UM / math.sqrt(touches)
            lines.append(
                _line(
                    "sigma_um",
                    round(sigma, 3),
                    f"one touch's default, over sqrt({touches}): the cycle "
                    f"averages {touches} touches (probe-program --touches {touches})",
                )
            )
    top = abs(steady_state_um(model, session["max_rpm"]))
    default = ShaperConfig().max_offset_um
    at = f"{top:.0f} um predicted at {session['max_rpm']:.0f} rpm"
    if math.isfinite(top):
        clamp = math.ceil(1.5 * top / 5.0) * 5.0
        if clamp > default:
            lines += [
                "",
                "[spindle.shaping]",
                _line(
                    "max_offset_um",
                    clamp,
                    f"1.5 x the {at}; the default {default:g} um would cut it",
                ),
            ]
        else:
            lines += [
                "",
                f"# shaping: the defaults (dual slew; the clamp, {default:g} um, is over 1.5 x the {at})",
            ]
    return "\n".join(lines) + "\n"
