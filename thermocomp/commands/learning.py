"""``thermocomp refit``, ``thermocomp model history`` and ``thermocomp model rollback``: a spindle
that keeps learning from its own tool-setter measurements, with every model kept and a way back.

- ``refit --config RUNTIME.toml [--spindle NAME] [--from WHEN] [--dry-run] [--json]`` exports the
  journal since the live model went into use, fits a candidate and judges it against the live model
  on the newest measurements (:mod:`calibration.learning`). A candidate the rule accepts goes through
  the checks a reload makes (it loads, names this spindle, is plausible), replaces the configured
  model file and the service is told to reload (SIGHUP), which carries its state over. Every
  candidate, promoted or not, is kept in the history with its figures and the reason.
- ``model history`` lists the history; ``model rollback [DIGEST]`` puts a kept model back (default:
  the one in use before the live one) the same way.

Run it by hand, or weekly from the systemd timer in ``examples/`` (the fit runs in its own process,
never on the compensation thread). It needs the calibration extra; the service does not.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from compensator.errors import ConfigError, ThermocompError, clip
from compensator.io import load_any_model, model_digest, read_run_log, save_model
from compensator.io.history import DIGEST_CHARS, Event, HistoryRecord, ModelHistory, fit_summary
from compensator.io.journal_export import export_journal, iso

from ..runtime.config import RuntimeConfig, SpindleConfig, load_config
from ..runtime.lock import holder
from ..runtime.service import plausible
from .journal import parse_when

SHADOW_KEPT = "shadow.json"
"""The shadow candidate's file, kept aside while it leaves shadow (its record copies it)."""


def _spindle(cfg: RuntimeConfig, name: str | None) -> SpindleConfig:
    names = [s.name for s in cfg.spindle]
    if name is None:
        if len(names) > 1:
            raise ConfigError(
                f"the configuration has {len(names)} spindles ({', '.join(names)}): give --spindle"
            )
        return cfg.spindle[0]
    for sc in cfg.spindle:
        if sc.name == name:
            return sc
    raise ConfigError(f"--spindle {name!r}: the configuration names {', '.join(names)}")


def _entries(path: str | os.PathLike[str]) -> list[Path]:
    """The directory entries reading ``path`` passes through: its own, then each symlink's target
    in turn. Writing a file replaces its own entry (the first) and nothing behind it."""
    out: list[Path] = []
    p = Path(os.path.abspath(path))
    for _ in range(40):  # the kernel's own limit on a chain of links
        entry = Path(os.path.realpath(p.parent)) / p.name
        if entry in out:
            break
        out.append(entry)
        if not entry.is_symlink():
            break
        p = entry.parent / os.readlink(entry)
    return out


def _refuse_shared(cfg: RuntimeConfig, sc: SpindleConfig, what: str) -> None:
    """A write of ``sc``'s model file must change no other spindle's model: refused (ConfigError)
    when another spindle reads the same file, by the same name or through a link."""
    written = _entries(sc.model)[0]
    others = [o.name for o in cfg.spindle if o is not sc and written in _entries(o.model)]
    if others:
        raise ConfigError(
            clip(
                f"spindle {sc.name}: its model file {sc.model} is also spindle "
                f"{', '.join(others)}'s: {what} would change {'their' if len(others) > 1 else 'its'} "
                "model too; give each spindle its own copy of the file (model = in its "
                "[[spindle]]) and reload the service, then try again",
                500,
            )
        )


def _history(cfg: RuntimeConfig, sc: SpindleConfig) -> ModelHistory:
    return ModelHistory.of(cfg.state_dir, sc.name, sc.learning.keep_models)


def _live(history: ModelHistory, sc: SpindleConfig, now: float) -> HistoryRecord:
    """The live model's record; the configured file recorded in use first when the history does
    not know it (a service that has not run since the history began, or a file edited by hand)."""
    live = history.live()
    model = load_any_model(sc.model)
    if live is None or live.digest != model_digest(model):
        live = history.add(
            "in_use",
            sc.model,
            reason="found in the configuration by refit",
            at_wall_s=now,
            fit=fit_summary(model),
        )
    return live


def _checked(sc: SpindleConfig, path: Path) -> Any:
    """What a reload checks: the file loads and verifies, names this spindle, is plausible."""
    model = load_any_model(path)
    sc.refuse_other_spindle(model.spindle_id)
    plausible(model.fallback or model, sc.name, sc.faults.max_speed_rpm)
    return model


def _tell_service(cfg: RuntimeConfig) -> str:
    """Have the service on ``cfg.state_dir`` reload (SIGHUP); what happened, in words."""
    held, pid = holder(cfg.state_dir)
    if not held:
        return f"no service runs on {cfg.state_dir}: its next start uses it"
    if pid is None:
        return (
            f"the service on {cfg.state_dir} names no pid: reload it (systemctl reload thermocomp)"
        )
    try:
        os.kill(pid, signal.SIGHUP)
    except OSError as err:
        return f"the service (pid {pid}) could not be told ({err.strerror}): reload it"
    return f"the service (pid {pid}) reloads, carrying its state over"


def _write_model(sc: SpindleConfig, model: Any, path: Path | None = None) -> None:
    """Write ``model`` over the configured model file (or ``path``), atomically; a write that
    fails is a one-line ConfigError, and the file is as it was."""
    target = Path(sc.model) if path is None else path
    try:
        save_model(target, model)
    except OSError as err:
        raise ConfigError(
            clip(f"spindle {sc.name}: {target}: cannot write: {err.strerror or err}", 500)
        ) from err


def _record(history: ModelHistory, event: Event, model_file: Path, **kw: Any) -> str | None:
    """Append a record of what took effect; a history that cannot be written does not undo it:
    said on stderr, and the words for the summary returned (None: recorded)."""
    try:
        history.add(event, model_file, **kw)
    except (OSError, ConfigError) as err:
        why = f"the model history {history.directory} could not be written ({getattr(err, 'strerror', None) or err})"
        print(f"thermocomp: warning: {why}; the {event} took effect", file=sys.stderr)
        return why
    return None


def _judge_shadow(
    args: argparse.Namespace,
    cfg: RuntimeConfig,
    sc: SpindleConfig,
    history: ModelHistory,
    shadow: HistoryRecord,
    live_model: Any,
    rule: Any,
    since_s: float,
) -> dict[str, Any]:
    """The candidate in shadow: held while it has run less than ``shadow_h``; then judged on
    what it would have done (:func:`calibration.learning.judge_shadow`, over the journal since
    the live model went into use, ``since_s``), promoted or rejected, and taken out of shadow
    either way. What happened, for the output (``outcome``: held back, promoted, rejected,
    candidate)."""
    from calibration.learning import judge_shadow
    from compensator.io.journal import SHADOW_COLUMN

    out: dict[str, Any] = {"spindle": sc.name, "shadow": shadow.short}
    with tempfile.TemporaryDirectory(prefix="thermocomp-refit-") as tmp:
        export = Path(tmp) / "shadow.csv"
        try:
            export_journal(cfg.journal_path, export, spindle=sc.name, start_s=since_s)
            log = read_run_log(export)
        except ThermocompError:
            log = None
    # how long it ran, by the journal's own clock: the rows that carry its estimate since it went
    # into shadow (an earlier candidate's rows before it are another model's)
    ran = (
        None
        if log is None
        else np.flatnonzero(
            np.isfinite(
                np.asarray(log.extras.get(SHADOW_COLUMN, np.full(len(log), np.nan)), dtype=float)
            )
            & (np.asarray(log.time_s, dtype=float) >= shadow.at_wall_s)
        )
    )
    ran_h = (
        0.0
        if log is None or ran is None or not ran.size
        else float(log.time_s[ran[-1]] - log.time_s[ran[0]]) / 3600.0
    )
    out["ran_h"] = round(ran_h, 3)
    if log is None or ran is None or not ran.size or ran_h < sc.learning.shadow_h:
        why = (
            "the service has not run it yet (reload it)"
            if ran is None or not ran.size
            else f"it has run {ran_h:.1f} h of {sc.learning.shadow_h:g} h"
        )
        out.update(outcome="held back", reason=f"candidate {shadow.short} in shadow: {why}")
        return out
    path = history.shadow_path
    try:
        candidate = load_any_model(path)
    except ThermocompError as err:
        candidate, failed = None, f"the candidate in shadow does not load: {err}"
    if candidate is not None:
        judged = judge_shadow(
            log,
            sc.estimate(live_model),
            sc.estimate(candidate),
            float(log.time_s[ran[0]]),
            rule,
            default_sigma_um=sc.observer.sigma_um,
        )
        out.update(judged.figures())
        decision = judged.decision
        figures = judged.figures()
    else:
        from calibration.learning import Decision

        decision, figures = Decision(False, failed), {}
    end_s = float(log.time_s[-1])
    if decision.held_back:
        out.update(outcome="held back", reason=decision.reason)
        return out
    if decision.promote:
        try:
            model = _checked(sc, path)
        except ThermocompError as err:
            decision = type(decision)(False, f"the checks of a reload refused it: {err}")
    if args.dry_run:
        # nothing takes effect, so nothing is recorded: it stays in shadow
        out.update(outcome="candidate" if decision.promote else "rejected", reason=decision.reason)
        return out
    event: Event = "promoted" if decision.promote else "rejected"
    said = _leave_shadow(
        cfg,
        sc,
        history,
        model if decision.promote else None,
        event,
        source=shadow.source,
        reason=decision.reason,
        at_wall_s=end_s,
        fit=shadow.fit,
        data=shadow.data,
        judged={**figures, "reason": decision.reason},
    )
    out.update(outcome=event, reason=decision.reason, written=said)
    return out


def _say_shadow(out: dict[str, Any]) -> str:
    return (
        f"refit {out['spindle']}: {out['outcome']} the candidate {out['shadow']} in shadow: "
        + out["reason"].removeprefix("in shadow: ")
        + (f"; {out['written']}" if "written" in out else "")
    )


def _leave_shadow(
    cfg: RuntimeConfig,
    sc: SpindleConfig,
    history: ModelHistory,
    promoted: Any,
    event: Event,
    **record: Any,
) -> str:
    """Take the candidate out of shadow: ``promoted`` (the candidate, checked) over the model
    file first, or rejected; then its record (of what took effect); then the service told."""
    path = history.shadow_path
    with tempfile.TemporaryDirectory(prefix="thermocomp-shadow-") as tmp:
        kept = Path(tmp) / SHADOW_KEPT
        shutil.copyfile(path, kept)  # what the record keeps a copy of, once the file is gone
        if promoted is not None:
            _write_model(sc, promoted)
        try:
            path.unlink()
        except OSError as err:
            if promoted is None:
                raise ConfigError(
                    clip(f"spindle {sc.name}: {path}: cannot remove: {err.strerror or err}", 500)
                ) from err
            # promoted all the same: it runs beside itself until the next refit clears it
            print(f"thermocomp: warning: {path}: cannot remove: {err.strerror}", file=sys.stderr)
        unrecorded = _record(history, event, kept, **record)
    said = (f"written to {sc.model}; " if promoted is not None else "") + _tell_service(cfg)
    return said if unrecorded is None else f"{said}; {unrecorded}"


def _opened(
    args: argparse.Namespace, writes: str | None
) -> tuple[RuntimeConfig, SpindleConfig, ModelHistory, float, HistoryRecord]:
    """The configuration, the spindle, its history, now, and the live model's record. ``writes``:
    what the command may do to the model file, refused before anything is recorded when the
    file is another spindle's too (None: it writes none)."""
    cfg = load_config(args.config)
    sc = _spindle(cfg, args.spindle)
    if writes is not None:
        _refuse_shared(cfg, sc, writes)
    history = _history(cfg, sc)
    now = time.time()
    return cfg, sc, history, now, _live(history, sc, now)


def refit_cmd(args: argparse.Namespace) -> int:
    from calibration.learning import Rule, refit

    cfg, sc, history, _now, live_rec = _opened(
        args, None if args.dry_run else "a promotion of its candidate"
    )
    live_model = _checked(sc, Path(sc.model))
    start = parse_when(args.from_, "--from") if args.from_ else live_rec.at_wall_s
    rule = Rule(
        min_train=sc.learning.min_train,
        min_holdout=sc.learning.min_holdout,
        holdout_share=sc.learning.holdout_share,
        margin=sc.learning.margin,
        observer_tolerance=sc.learning.observer_tolerance,
        fit_days=sc.learning.fit_days,
        shadow_min=sc.learning.shadow_min,
    )
    shadow = history.shadow()
    judged_shadow: dict[str, Any] | None = None
    if shadow is not None:
        judged_shadow = _judge_shadow(
            args, cfg, sc, history, shadow, live_model, rule, live_rec.at_wall_s
        )
        promoted = judged_shadow["outcome"] == "promoted"
        if not (promoted or judged_shadow["outcome"] == "rejected") or args.dry_run:
            # held back, or a dry run: nothing took effect
            if args.json:
                print(json.dumps(judged_shadow, indent=2))
            else:
                print(_say_shadow(judged_shadow))
            return 0
        # decided: a new candidate goes into shadow in its place, fitted on the newest journal
        print(_say_shadow(judged_shadow), file=sys.stderr if args.json else sys.stdout)
        if promoted:
            # judged against the model now in use; its record begins where the shadow's data
            # end, so the newest fit_days before that are the spindle's newest measurements
            live_rec = history.live() or live_rec
            live_model = _checked(sc, Path(sc.model))
            if not args.from_:
                start = live_rec.at_wall_s - 86400.0 * (rule.fit_days or 7.0)
    # the live model by name; its figures, once judged, go under "live" (as the candidate's do)
    out: dict[str, Any] = {"spindle": sc.name, "live_model": live_rec.short, "from": iso(start)}
    if judged_shadow is not None:
        out["shadow_judged"] = judged_shadow
    with tempfile.TemporaryDirectory(prefix="thermocomp-refit-") as tmp:
        export = Path(tmp) / "production.csv"
        try:
            done = export_journal(cfg.journal_path, export, spindle=sc.name, start_s=start)
        except ThermocompError as err:
            raise ConfigError(
                f"refit {sc.name}: nothing to refit on since {iso(start)}: {err}"
            ) from err
        log = read_run_log(export)
        result = refit(
            log,
            sc.estimate(live_model),
            sc.estimate,
            rule=rule,
            spindle_id=sc.spindle_id or live_model.spindle_id,
            machine_id=getattr(live_model, "machine_id", None),
            created_utc=datetime.now(UTC).isoformat(timespec="seconds"),
            default_sigma_um=sc.observer.sigma_um,
        )
        data = {
            "from": iso(done.first_s),
            "to": iso(done.last_s),
            "rows": done.rows,
            "journal_files": list(done.files)[:20],
        }
        out.update(data=data, notes=result.notes, **result.figures())
        say = [
            f"refit {sc.name}: the journal from {iso(done.first_s)} to {iso(done.last_s)}, {done.rows} rows, "
            f"{result.measurements} usable measurement(s)"
        ]
        say += [f"  {n}" for n in result.notes]
        decision = result.decision
        if result.candidate is not None:
            assert result.cut_s is not None  # the cut is made before a candidate is fitted
            # the journal's time is the wall clock's (anchored once): an instant as it is
            say.append(
                f"  fitted on {result.train} measurement(s) before {iso(result.cut_s)}, judged on "
                f"the {result.holdout} from there"
            )
            say.append(
                f"  candidate {result.candidate.form}: "
                + _figs(result.scored)
                + f"; live model {live_rec.short}: "
                + _figs(result.live)
            )
            cand_path = Path(tmp) / "candidate.json"
            save_model(cand_path, result.candidate)
            if decision.promote:
                try:
                    _checked(sc, cand_path)
                except ThermocompError as err:
                    decision = type(decision)(False, f"the checks of a reload refused it: {err}")
            judged = {**result.figures(), "rule": vars(rule), "reason": decision.reason}
            to_shadow = decision.promote and not args.dry_run and sc.learning.shadow_h > 0
            event: Event = (
                "shadow"
                if to_shadow
                else "promoted"
                if decision.promote and not args.dry_run
                else "candidate"
                if decision.promote
                else "rejected"
            )
            # dated at the end of the data it was judged on: the journal's clock, which the next
            # refit's export starts from
            record: dict[str, Any] = {
                "source": f"refit of {data['from']} .. {data['to']}",
                "reason": decision.reason,
                "at_wall_s": done.last_s,
                "fit": fit_summary(result.candidate),
                "data": data,
                "judged": judged,
            }
            short = model_digest(result.candidate)[:DIGEST_CHARS]
            out["candidate"] = {
                **out.get("candidate", {}),
                "digest": short,
                "form": result.candidate.form,
            }
            # what takes effect (the shadow file, the model file) first, then its record: the
            # history holds only what took effect; the service is told last
            if to_shadow:
                _write_model(sc, result.candidate, history.shadow_path)
                try:
                    history.add(event, cand_path, **record)
                except (OSError, ConfigError):
                    # unrecorded, the next refit would not know it: not left in shadow
                    history.shadow_path.unlink(missing_ok=True)
                    raise
                said = _tell_service(cfg)
                say.append(
                    f"into shadow for {sc.learning.shadow_h:g} h: {short} ({decision.reason}); {said}"
                )
                out.update(outcome="shadow", reason=decision.reason, written=said)
            elif event == "promoted":
                _write_model(sc, result.candidate)
                unrecorded = _record(history, event, cand_path, **record)
                said = f"written to {sc.model}; " + _tell_service(cfg)
                if unrecorded is not None:
                    said += f"; {unrecorded}"
                say.append(f"promoted {short}: {decision.reason}; {said}")
                out.update(outcome="promoted", reason=decision.reason, written=said)
            else:
                # a candidate, promoted or not, is kept in the history: the record is the effect
                history.add(event, cand_path, **record)
                if decision.promote:
                    say.append(
                        f"would promote {short} (--dry-run: kept as a candidate): {decision.reason}"
                    )
                    out.update(outcome="candidate", reason=decision.reason)
                else:
                    say.append(f"rejected {short}, kept in the history: {decision.reason}")
                    out.update(outcome="rejected", reason=decision.reason)
        else:
            say.append(
                f"held back: {decision.reason}"
                if decision.held_back
                else f"no candidate: {decision.reason}"
            )
            out.update(
                outcome="held back" if decision.held_back else "rejected", reason=decision.reason
            )
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print("\n".join(say))
    return 0


def _figs(s: Any) -> str:
    if s is None:
        return "-"
    text = f"open loop {s.open_loop_rms_um:.2f} um RMS (max {s.open_loop_max_um:.2f})"
    return text + (
        f", with the observer {s.observer_rms_um:.2f} um" if s.observer_rms_um is not None else ""
    )


def history_cmd(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    sc = _spindle(cfg, args.spindle)
    history = _history(cfg, sc)
    records = history.records()
    live = history.live()
    if args.json:
        print(
            json.dumps(
                [
                    {
                        **r.model_dump(mode="json"),
                        "live": live is not None and r is live,
                        "copy_kept": history.copy_path(r).is_file(),
                    }
                    for r in records
                ],
                indent=2,
            )
        )
        return 0
    if not records:
        print(
            f"{sc.name}: no model history yet in {history.directory} (the service records the model it "
            "starts with)"
        )
        return 0
    print(f"{sc.name}: {len(records)} record(s) in {history.directory}; * the model in use")
    for r in records:
        when = datetime.fromtimestamp(r.at_wall_s, UTC).strftime("%Y-%m-%d %H:%M")
        mark = "*" if live is not None and r is live else " "
        kept = "" if history.copy_path(r).is_file() else " (copy pruned)"
        figs = r.judged.get("candidate", {}) if r.judged else {}
        fig = (
            f" open loop {figs['open_loop_rms_um']:.2f} um"
            if figs.get("open_loop_rms_um") is not None
            else ""
        )
        print(
            f"{mark} {when}  {r.event:<9} {r.short}  {r.fit.get('form') or '-':<14}{fig}  {r.reason}{kept}"
        )
    return 0


def rollback_cmd(args: argparse.Namespace) -> int:
    cfg, sc, history, now, live = _opened(args, "a rollback")
    if args.digest:
        target = history.find(args.digest)
    else:
        earlier = [
            r
            for r in history.records()
            if r.event in ("in_use", "promoted", "rollback")
            and r.digest != live.digest
            and history.copy_path(r).is_file()
        ]
        if not earlier:
            raise ConfigError(f"{sc.name}: no earlier model in the history to roll back to")
        target = earlier[-1]
    if target.digest == live.digest:
        print(f"{sc.name}: {target.short} is the model in use already")
        return 0
    model = _checked(sc, history.copy_path(target))
    reason = args.reason or f"rolled back by hand from {live.short}"
    # the file first: the history records only what took effect; then the service, which
    # finds the model recorded
    _write_model(sc, model)
    unrecorded = _record(
        history,
        "rollback",
        history.copy_path(target),
        source=target.source,
        reason=reason,
        at_wall_s=now,
        fit=fit_summary(model),
        data=target.data,
        judged=target.judged,
    )
    said = f"written to {sc.model}; " + _tell_service(cfg)
    print(
        f"{sc.name}: rolled back to {target.short} ({target.event} {iso(target.at_wall_s)}, "
        f"{target.fit.get('form') or '-'}); {said}"
        + ("" if unrecorded is None else f"; {unrecorded}")
    )
    return 0
