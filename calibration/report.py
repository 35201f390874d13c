"""The calibration report (HTML or Markdown, plots embedded) and the runtime configuration the
wizard writes. Text in, text out: the wizard writes the files."""

from __future__ import annotations

import base64
import html
import math
from pathlib import Path
from typing import Any

from compensator.predictor import Predictor


def _b64(path: str | Path) -> str:
    return base64.b64encode(Path(path).read_bytes()).decode("ascii")


def _f(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def _sections(session: dict[str, Any], summary: dict[str, Any], model: Predictor,
              model_path: Path, version: str) -> list[tuple[str, list[list[str]] | list[str]]]:
    rep = summary["report"]
    ident = [["machine", session["machine_id"]], ["spindle", session["spindle_id"]],
             ["maximum speed", f"{session['max_rpm']:.0f} rpm"], ["controller", str(session.get("controller"))],
             ["displacement", str(session.get("sensor") or session.get("source"))],
             ["model file", f"{model_path.name} ({version})"], ["model form", model.form],
             ["created (UTC)", str(model.created_utc or "")]]
    runs = [["run", "log", "rows", "flagged", "program"]]
    for name, info in session.get("runs", {}).items():
        runs.append([name, Path(info["log"]).name, str(info.get("rows", "-")),
                     ", ".join(f"{k} {v}" for k, v in (info.get("flagged") or {}).items()) or "none",
                     Path(session.get("programs", {}).get(name, "-")).name])
    cands = [["candidate", "held-out RMS [um]", "held-out max [um]", "in-sample RMS [um]", "verdict"]]
    for c in rep["candidates"]:
        mark = " (chosen)" if c["name"] == rep["chosen"] else ""
        verdict = ("reference only" if c["family"] == "reference" else "accepted" if c["accepted"]
                   else "refused: " + "; ".join(c["refusals"]))
        cands.append([c["name"] + mark, _f(c["honest_rms_um"]), _f(c["cv_max_abs_um"]),
                      _f(c["in_sample_rms_um"]), verdict])
    res = [["run", "RMS [um]", "max [um]", "samples"]]
    cal = summary["calibration"]
    res.append(["calibration (in sample)", _f(cal["rms_um"]), _f(cal["max_abs_um"]), str(cal["samples"])])
    if summary.get("validation"):
        v = summary["validation"]
        res.append(["validation (held out)", _f(v["rms_um"]), _f(v["max_abs_um"]), str(v["samples"])])
    steady = [["speed [rpm]", "steady growth [um]"]]
    for frac in (0.25, 0.5, 0.75, 1.0):
        n = frac * session["max_rpm"]
        steady.append([f"{n:.0f}", _f(model.steady_state_um(n))])
    notes = list(summary.get("warnings", [])) + [f"advice: {a}" for a in summary.get("advice", [])]
    loop: list[list[str]] = []
    if summary.get("closed_loop"):
        cl = summary["closed_loop"]
        loop = [["probe every", "RMS [um]", "max [um]"]]
        loop += [["never" if r["interval_s"] is None else f"{r['interval_s']:.0f} s", _f(r["rms_um"]),
                  _f(r["max_abs_um"])] for r in cl["intervals"]]
        rec = cl["recommended_interval_s"]
        loop.append(["recommended", "-" if rec is None else f"{rec:.0f} s",
                     f"target {cl['target_rms_um']:g} um RMS"])
    return [("Spindle", ident), ("Runs", runs), (f"Candidates (free run, {rep['scored_by']})", cands),
            (f"Chosen: {rep['chosen']}", [rep["reason"]]), ("The model", model.describe()),
            ("Free-run residuals", res), ("Steady-state growth predicted", steady),
            *([("Closed loop with a tool setter (validation run, probe sigma 0.5 um)", loop)] if loop else []),
            ("Warnings and advice", notes or ["none"])]


def calibration_report(session: dict[str, Any], summary: dict[str, Any], model: Predictor,
                       model_path: Path, fmt: str, version: str) -> str:
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
                out += ["| " + " | ".join(c.replace("|", "/") for c in row) + " |" for row in body[1:]]
            else:
                out += [f"- {line}" for line in body]
            out.append("")
        out += ["## Measured and predicted (free run)", "",
                f"![fit](data:image/png;base64,{img})", ""]
        return "\n".join(out)
    if fmt != "html":
        raise ValueError(f"report format {fmt!r}: html or md")
    e = html.escape
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{e(title)}</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto}"
             "table{border-collapse:collapse}td,th{border:1px solid #bbb;padding:3px 8px}"
             "img{max-width:100%}</style></head><body>", f"<h1>{e(title)}</h1>"]
    for head, body in secs:
        parts.append(f"<h2>{e(head)}</h2>")
        if body and isinstance(body[0], list):
            parts.append("<table><tr>" + "".join(f"<th>{e(c)}</th>" for c in body[0]) + "</tr>")
            parts += ["<tr>" + "".join(f"<td>{e(c)}</td>" for c in row) + "</tr>" for row in body[1:]]
            parts.append("</table>")
        else:
            parts.append("<ul>" + "".join(f"<li>{e(str(x))}</li>" for x in body) + "</ul>")
    parts += ["<h2>Measured and predicted (free run)</h2>",
              f"<img alt='fit' src='data:image/png;base64,{img}'>", "</body></html>"]
    return "\n".join(parts)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    s = str(v).replace("\\", "\\\\").replace('"', '\\"')
    return f'"{s}"'


def runtime_config(session: dict[str, Any], model: Predictor, model_path: Path) -> str:
    """A complete ``thermocomp run`` configuration for this spindle."""
    top = abs(model.steady_state_um(session["max_rpm"]))
    clamp = max(20.0, math.ceil(1.5 * top / 5.0) * 5.0)
    controller = session.get("controller") or "opc.tcp://CHANGE-ME:4840"
    return f"""# thermocomp runtime configuration for {session['machine_id']} / {session['spindle_id']}
# written by `thermocomp wizard`; check it with `thermocomp run --config THIS --check`
# See examples/machine.toml for every option.
state_dir = "/var/lib/thermocomp"
log_level = "info"

[[spindle]]
name = {_toml_value(f"{session['machine_id']}-{session['spindle_id']}")}
model = {_toml_value(str(model_path))}
period_s = 1.0

[spindle.adapter]
url = {_toml_value(controller)}

[spindle.shaping]
max_offset_um = {clamp:g}                 # 1.5 x the predicted growth at {session['max_rpm']:.0f} rpm
max_rate_um_per_s = 1.0
deadband_um = 0.2

[spindle.shaping.transient]
enabled = true
mode = "slow"
"""
