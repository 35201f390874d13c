"""``thermocomp status``: what a running service is doing, from its status endpoint, as a table.

Plain text (the edge box's slim install has no ``rich``); ``--json`` prints the endpoint's
answer as it came. Each spindle's state (compensating, holding, not writing) and its reason are
the service's own (:func:`thermocomp.runtime.status.spindle_state`): this only prints them.

With ``--exit-code`` the exit status says how things stand (:data:`thermocomp.status_codes.EXIT_CODES`).

With ``--config``, a service that cannot be reached and does not hold its state directory is not
running: each spindle's saved state says what the control was left holding, and the exit status
is :data:`~thermocomp.status_codes.EXIT_STOPPED` (with or without ``--exit-code``).
"""

from __future__ import annotations

import json
import math
import os
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

from compensator.errors import ConfigError, ThermocompError
from thermocomp.status_codes import (  # the command line's help reads the same
    DEFAULT_URL,
    EXIT_ATTENTION,
    EXIT_NOT_WRITING,
    EXIT_OK,
    EXIT_STOPPED,
)


class StatusUnreachableError(ThermocompError, ConnectionError):
    """The status endpoint did not answer."""


def _url_of(args) -> str:
    if args.url:
        return args.url if args.url.endswith("/") else args.url + "/"
    if args.config:
        from thermocomp.runtime.config import load_config

        cfg = load_config(args.config)
        written = cfg.state_dir / "status.url"  # the service's own word, also for port 0
        try:
            return written.read_text(encoding="utf-8").strip()
        except OSError:
            st = cfg.status
            host = "127.0.0.1" if st.bind in ("0.0.0.0", "::", "") else st.bind
            return f"http://{host}:{st.port}/"
    return DEFAULT_URL


def _token(args) -> str | None:
    if args.token_file:
        try:
            return Path(args.token_file).read_text(encoding="utf-8").strip() or None
        except OSError as err:
            raise ConfigError(f"--token-file {args.token_file}: {err.strerror or err}") from err
    return os.environ.get("THERMOCOMP_STATUS_TOKEN", "").strip() or None


def fetch(url: str, token: str | None, timeout_s: float = 10.0) -> dict[str, Any]:
    req = urllib.request.Request(
        url + "status", headers={"Authorization": f"Bearer {token}"} if token else {}
    )
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as r:
            return json.loads(r.read())
    except urllib.error.HTTPError as err:
        if err.code == 401:
            raise ConfigError(
                f"{url}: the service asks for a token (THERMOCOMP_STATUS_TOKEN or "
                "--token-file)" + (": this one was refused" if token else "")
            ) from err
        if err.code == 503:
            raise StatusUnreachableError(f"{url}: the service has not run a cycle yet") from err
        raise StatusUnreachableError(f"{url}: HTTP {err.code}") from err
    except (urllib.error.URLError, OSError) as err:
        why = getattr(err, "reason", err)
        raise StatusUnreachableError(f"could not reach the service at {url}: {why}") from err
    except ValueError as err:
        raise StatusUnreachableError(f"{url}: not a thermocomp status (not JSON)") from err


def _num(v: Any, fmt: str = ".2f") -> str:
    return "-" if v is None else format(v, fmt)


def _age(s: float | None) -> str:
    if s is None:
        return "never"
    s = int(s)
    return (
        f"{s}s" if s < 120 else f"{s // 60}m" if s < 7200 else f"{s // 3600}h{s % 3600 // 60:02d}m"
    )


def table(st: dict[str, Any]) -> str:
    """The status as lines of aligned text."""
    head = (
        f"thermocomp {st.get('version')} · pid {st.get('pid')} · up {_age(st.get('uptime_s'))} · "
        f"{st.get('status')}"
    )
    cols = (
        "spindle",
        "state",
        "speed_rpm",
        "S_um",
        "target_um",
        "held_um",
        "read_back_um",
        "last_write",
        "link",
        "estimate",
        "offset",
        "alarms",
    )
    rows = []
    for s in st.get("spindles", []):
        rows.append(
            (
                s["name"],
                str(s.get("state", "?")),
                _num(s.get("speed_rpm"), ".0f"),
                _num(s.get("elongation_um")),
                _num(s.get("offset_target_um")),
                _num(s.get("offset_held_um")),
                _num(s.get("offset_read_back_um")),
                _age(s.get("last_write_age_s")),
                str(s.get("link")),
                str(s.get("estimate")),
                str(s.get("offset_mode")),
                ",".join(s.get("alarms") or []) or "-",
            )
        )
    widths = [
        max(len(c), *(len(r[i]) for r in rows)) if rows else len(c) for i, c in enumerate(cols)
    ]
    out = [head, "  ".join(c.ljust(w) for c, w in zip(cols, widths))]
    out += ["  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip() for r in rows]
    for s in st.get(
        "spindles", []
    ):  # one state word and one reason per spindle, as the service says
        reason = s.get("state_reason")
        out.append(
            f"{s['name']}: {s.get('state', 'state unknown (an older service)')}"
            + (f": {reason}" if reason else "")
        )
    for s in st.get("spindles", []):
        m = s.get("model") or {}
        lo, hi = (m.get("speed_range_rpm") or [None, None])[:2]
        line = (
            f"{s['name']}: model {m.get('form')} ({Path(str(m.get('file'))).name}, {str(m.get('digest'))[:12]}), "
            f"{_num(lo, '.0f')}-{_num(hi, '.0f')} rpm"
        )
        if m.get("inputs"):
            line += ", inputs " + ", ".join(m["inputs"])
        obs = s.get("observer")
        if obs:
            line += (
                f"; observer bias {_num(obs.get('bias_um'))} um, last measurement "
                f"{_age(obs.get('since_measurement_s'))} ago"
                + (" (stale)" if obs.get("stale") else "")
            )
        ex = s.get("expected_error")
        if ex:  # the figure only as a promise where validated, as the status page shows it
            claim = ex.get("claim") or (
                f"expect ±{_num(ex.get('p95_abs_um'), '.1f')} µm (95 %)"
                + ("" if ex.get("validated") else ", not validated here: a floor")
            )
            line += f"; error: {claim}"
        out.append(line)
    c = st.get("cooling")
    if c:
        out.append(
            f"cooling: {c.get('mode')} {c.get('phase')}, set point {_num(c.get('setpoint_c'), '.1f')} °C, "
            f"supply {_num(c.get('supply_c'), '.1f')} °C, RITE {_num(c.get('rite_um'), '.1f')} um"
            + (f", {c.get('alarm')}" if c.get("alarm") else "")
        )
    return "\n".join(out)


def stopped(config: str, now_wall: float) -> dict[str, Any] | None:
    """Each spindle's saved state while no service runs on ``config``'s state directory; None
    while one holds it (running, its endpoint not answering). Nothing is moved or written."""
    from compensator.errors import ModelError
    from thermocomp.runtime.config import load_config
    from thermocomp.runtime.keeper import read_saved, state_file
    from thermocomp.runtime.lock import holder

    cfg = load_config(config)
    held, _ = holder(cfg.state_dir)
    if held:
        return None
    spindles: list[dict[str, Any]] = []
    for sp in cfg.spindle:
        path = state_file(cfg.state_dir, sp.name)
        row: dict[str, Any] = {"name": sp.name, "state": "stopped", "state_file": str(path)}
        try:
            saved = read_saved(path)
        except ModelError as err:
            row.update(state="unknown", error=str(err))
        else:
            if saved is None:
                row["state"] = "never ran"
            else:
                row.update(
                    offset_held_um=saved.held_um,
                    saved_wall_s=saved.saved_wall_s,
                    age_s=now_wall - saved.saved_wall_s,
                    clean_stop=saved.clean_stop,
                )
        spindles.append(row)
    return {"status": "not running", "state_dir": str(cfg.state_dir), "spindles": spindles}


def _ago(s: float) -> str:
    if not math.isfinite(s):
        return "?"
    if s < 0:
        return f"{_age(-s)} ahead of this computer's clock"
    return f"{_age(s)} ago"


def stopped_lines(st: dict[str, Any]) -> str:
    """The saved states as lines for people."""
    out = [f"thermocomp is not running (state directory {st['state_dir']})"]
    for s in st["spindles"]:
        if s["state"] == "never ran":
            out.append(f"{s['name']}: never ran (no saved state)")
        elif s["state"] == "unknown":
            out.append(f"{s['name']}: unknown: {s['error']}")
        else:
            at = time.strftime("%Y-%m-%d %H:%M:%SZ", time.gmtime(s["saved_wall_s"]))
            how = {
                True: "; a clean stop",
                False: "; not by a clean stop: killed, crashed, powered off, or its last "
                "save failed",
                None: "",  # an older version's state does not say
            }[s["clean_stop"]]
            out.append(
                f"{s['name']}: stopped: the control holds {s['offset_held_um']:.2f} µm "
                f"(state saved at {at}, {_ago(s['age_s'])}{how})"
            )
    return "\n".join(out)


def main(args) -> int:
    url = _url_of(args)
    try:
        st = fetch(url, _token(args), args.timeout_s)
    except StatusUnreachableError:
        if not args.config:
            raise  # no state directory to read
        down = stopped(args.config, time.time())
        if down is None:
            raise  # a service holds the state directory: running, not answering
        print(json.dumps(down, allow_nan=False) if args.json else stopped_lines(down))
        return EXIT_STOPPED
    if args.json:
        print(json.dumps(st, allow_nan=False))
    else:
        print(table(st))
    return exit_status(st) if args.exit_code else EXIT_OK


def exit_status(st: dict[str, Any]) -> int:
    """The exit status ``--exit-code`` gives for status ``st`` (:data:`thermocomp.status_codes.EXIT_CODES`)."""
    spindles = st.get("spindles", [])
    if any(s.get("state") == "not writing" for s in spindles):
        return EXIT_NOT_WRITING
    alarmed = any(s.get("alarms") for s in spindles) or bool((st.get("cooling") or {}).get("alarm"))
    # a service too old to say a state: not taken as compensating
    not_compensating = any(s.get("state") != "compensating" for s in spindles)
    return EXIT_ATTENTION if alarmed or not_compensating else EXIT_OK
