"""``thermocomp wizard``: one guided calibration session per spindle, blank to validated model.

Steps: 1 identify the spindle and its links, 2 write the NC programs, 3 record (or import)
the runs, 4 fit and validate in free run, 5 save a versioned model, a report and a runtime
configuration. Every question has a flag; with ``--yes`` (or without a terminal) nothing is
asked and a missing answer is an error. The session lives in
``<workdir>/<machine>/<spindle>/session.json``: after an interruption the wizard resumes
where it stopped, appending to the same run log.

This module is the terminal: it asks, prints and drives the steps of ``calibration.session``,
which take the typed session (``calibration.session.model.WizardSession``) and return new values.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.prompt import Confirm, FloatPrompt, Prompt
from rich.table import Table

from compensator.errors import AcquisitionError, CalibrationError, ConfigError, clip
from compensator.io import load_model, write_text
from compensator.speed_programs import Program

from .acquire import AcquireConfig, Event, Problem, Recorder, Sample, progress_fraction, sparkline
from .nc_programs import (
    DIALECTS,
    EXTENSIONS,
    calibration_profile,
    probe_call,
    rest_hours,
    to_nc,
    validation_profile,
)
from .session.fit import RunData, Validated, advise, clean, fit, read_runs, report, validate
from .session.model import (
    ID_PATTERN,
    LIVE,
    RUNS,
    SESSION_FORMAT,
    SOURCES,
    WizardSession,
    check_id,
    inside,
    load_session,
    set_aside,
    write_session,
)
from .session.plan import (
    PROBE_MOVES_S,
    ProbesPlanned,
    ProgramFile,
    cycle_s,
    former_time_constants,
    plan_probes,
    programs,
    write_programs,
)
from .session.record import (
    ImportOptions,
    LinkFailed,
    SensorChecked,
    check_controller,
    check_sensor,
    import_run,
    open_links,
    record,
    recorded,
    rows_in,
    set_run_aside,
    with_runs,
)
from .session.save import SavedFiles, save

__all__ = [
    "ID_PATTERN",
    "LIVE",
    "PROBE_MOVES_S",
    "RUNS",
    "SESSION_FORMAT",
    "SOURCES",
    "Wizard",
    "WizardSession",
    "advise",
    "clean",
    "main",
    "profile_cmd",
]


class Wizard:
    """The terminal around the session's steps: every answer from its flag, the resumed session
    or a prompt; every step's value printed; the session file kept after each answer."""

    def __init__(
        self,
        args: argparse.Namespace,
        console: Console | None = None,
        clock: Callable[[], float] | None = None,
        sleep: Callable[[float], None] = time.sleep,
    ):
        self.args = args
        self.out = console or _console()
        self.interactive = not args.yes and sys.stdin.isatty()
        self._clock = clock
        self.clock: Callable[[], float] = clock or time.time
        self.sleep = (
            sleep if args.time_scale == 1.0 else (lambda s: time.sleep(s / args.time_scale))
        )
        self.session = WizardSession()
        self.workdir: Path = Path(args.workdir).resolve()
        self.dir: Path = self.workdir
        self.model: Any = None
        """The model step 4 fitted, for step 5 to save."""

    # -- questions ---------------------------------------------------------------

    def ask(
        self,
        key: str,
        question: str,
        *,
        flag: str,
        default: Any = None,
        kind: type = str,
        choices: list[str] | None = None,
        check: Callable[[Any], Any] | None = None,
    ) -> Any:
        """The answer from the flag, else the resumed session, else a prompt (or an error);
        ``check`` converts it, or refuses it in one line, before the session keeps it."""

        def shown(answer: Any) -> str:
            # an answer is checked after it is echoed: a huge or markup-laden one must echo safely
            return escape(clip(str(answer), 120))

        def checked(answer: Any) -> Any:
            return answer if check is None else check(answer)

        question = escape(question)
        value = getattr(self.args, key.replace("-", "_"), None)
        if value is not None:
            self.out.print(f"  {question}: [cyan]{shown(value)}[/]  (from {flag})")
            return checked(value)
        held = self.session.get(key)
        if held is not None:
            self.out.print(f"  {question}: [cyan]{shown(held)}[/]  (from the session)")
            return checked(held)
        if not self.interactive:
            if default is not None:
                self.out.print(f"  {question}: [cyan]{shown(default)}[/]  (default)")
                return checked(default)
            raise ConfigError(f"{flag} is needed when the wizard runs unattended")
        while True:
            if kind is float:
                answer = FloatPrompt.ask(f"  {question}", console=self.out, default=default)
            else:
                answer = Prompt.ask(
                    f"  {question}", console=self.out, default=default, choices=choices
                )
            if answer not in (None, ""):
                answer = checked(answer)
                self.session = self.session.updated(**{key: answer})
                if (self.dir / "session.json").parent.is_dir() and self.dir != self.workdir:
                    self.save_session()  # kept at once: an interruption loses no answer
                return answer

    def confirm(self, question: str, *, default: bool = True) -> bool:
        if not self.interactive:
            return default
        return Confirm.ask(f"  {question}", console=self.out, default=default)

    def save_session(self) -> None:
        self.session = write_session(self.dir / "session.json", self.session, _now())

    # -- step 1 ------------------------------------------------------------------

    def step_identify(self) -> None:
        a = self.args
        self.out.rule("[bold]1/5 Identify the spindle")
        machine = self.ask(
            "machine_id",
            "Machine id",
            flag="--machine-id",
            check=lambda v: check_id(v, "--machine-id"),
        )
        spindle = self.ask(
            "spindle_id",
            "Spindle id",
            flag="--model-spindle-id",
            check=lambda v: check_id(v, "--model-spindle-id"),
        )
        self.dir = inside(self.workdir, self.workdir / machine / spindle, "the session directory")
        path = self.dir / "session.json"
        if path.exists() and not a.new:
            self.session = load_session(path)
            self.out.print(
                f"  resuming the session of {self.session.updated_utc or '?'} in {self.dir} "
                f"(recorded: {recorded(self.session)})"
            )
            if self.interactive and not a.resume and not self.confirm("Resume this session?"):
                self.session = WizardSession()
                self._set_aside()
        elif path.exists() and a.new:
            self._set_aside()
        self.dir.mkdir(parents=True, exist_ok=True)
        # a faster clock (virtual machine tool) must read the same in a resumed process
        anchor = self.session.time_anchor_s
        anchor = time.time() if anchor is None else anchor
        self.session = self.session.updated(
            machine_id=machine,
            spindle_id=spindle,
            time_anchor_s=anchor,
            time_scale=float(a.time_scale),  # the service must run at the same
        )
        self.clock = self._clock or _clock(a.time_scale, anchor)
        self.session = self.session.updated(
            max_rpm=self.ask(
                "max_rpm",
                "Maximum spindle speed [rpm]",
                flag="--max-rpm",
                kind=float,
                check=_max_rpm,
            )
        )
        source = self.ask(
            "source",
            "Displacement from (sensor: live eddy-current reading; tool-setter: "
            "the machine's tool setter, the program stopping for it every few minutes; "
            "import: a CSV a DAQ recorded)",
            flag="--source",
            default="sensor",
            choices=list(SOURCES),
            check=_choice("--source", SOURCES),
        )
        self.session = self.session.updated(source=source)
        if source in LIVE:
            while True:
                controller = self.ask(
                    "controller",
                    "Controller link (URL, as in the runtime configuration)",
                    flag="--controller",
                    check=str,
                )
                self.session = self.session.updated(controller=controller)
                if source == "sensor":
                    sensor = self.ask(
                        "sensor",
                        "Sensor (serial:///dev/ttyUSB1?scale=1, ...?protocol=modbus&register=0, "
                        "opc.tcp://...)",
                        flag="--sensor",
                        check=str,
                    )
                    self.session = self.session.updated(sensor=sensor)
                rate_s = self.ask(
                    "rate_s",
                    "Sample period [s]",
                    flag="--rate-s",
                    default=1.0,
                    kind=float,
                    check=_rate_s,
                )
                self.session = self.session.updated(rate_s=rate_s)
                self.save_session()
                if a.no_connection_test or not (
                    self.interactive is False or self.confirm("Test the connections now?")
                ):
                    break
                try:
                    self.test_connections()
                    break
                except LinkFailed as err:
                    if not self.interactive:
                        raise
                    # back to the question that failed; every other answer is kept
                    self.session = self.session.updated(**{err.link: None})
                    setattr(a, err.link, None)
                    self.save_session()
                    self.out.print(
                        f"  [red]connection test failed:[/] {escape(str(err))}; answer again"
                    )
        else:
            self.session = self.session.updated(controller=a.controller or self.session.controller)
        self.save_session()

    def _set_aside(self) -> None:
        aside = set_aside(self.dir, self.session, _now())
        self.session = WizardSession()
        self.out.print(
            f"  a new session: the earlier one (answers, run logs, programs) was kept in "
            f"{_shown(aside)}"
        )

    def test_connections(self) -> None:
        """Each link read once (``calibration.session.record``), and said as it answers."""
        ctl = check_controller(self.session)
        self.out.print(
            f"  controller: [green]ok[/], spindle at {ctl.speed_rpm:.0f} rpm"
            + (", the tool setter's variables read" if ctl.tool_setter else "")
        )
        seen = check_sensor(self.session)
        if seen is not None:
            _say_sensor(self.out, seen)

    # -- step 2 ------------------------------------------------------------------

    def step_programs(self) -> None:
        a = self.args
        self.out.rule("[bold]2/5 Calibration program")
        s = self.session
        dialect = self.ask(
            "dialect",
            "NC dialect",
            flag="--dialect",
            default="fanuc",
            choices=list(DIALECTS),
            check=_choice("--dialect", DIALECTS),
        )
        s = s.updated(
            dialect=dialect,
            step_min=float(a.step_min if a.step_min is not None else s.step_min or 20.0),
            cooldown_min=float(
                a.cooldown_min
                if a.cooldown_min is not None
                else (s.cooldown_min if s.cooldown_min is not None else 60.0)
            ),
        )
        if s.validation is None or a.validation is not None:
            s = s.updated(
                validation=bool(a.validation)
                if a.validation is not None
                else (self.confirm("Also record a different validation profile (recommended)?"))
            )
        self.session = s = s.updated(
            validation_seed=int(
                s.validation_seed if s.validation_seed is not None else a.validation_seed
            )
        )
        taus = former_time_constants(self.dir)
        if s.source == "tool-setter":
            self._plan_probes(taus)
        written = write_programs(self.session, self.dir, taus)
        self.session = s = written.session
        _say_programs(self.out, s, written.files, self.args.time_scale)
        self.save_session()

    def _plan_probes(self, taus: tuple[float, ...] | None) -> None:
        """The tool-setter route's probe plan (:func:`calibration.session.plan.plan_probes`),
        from the flags, and what it costs."""
        a = self.args
        planned = plan_probes(
            self.session,
            probe_spindle=a.probe_spindle,
            touches=getattr(a, "probe_touches", None),
            dwell_s=a.probe_dwell_s,
            every_min=a.probe_every_min,
            former_taus=taus,
        )
        self.session = planned.session
        _say_plan(self.out, planned)

    # -- step 3 ------------------------------------------------------------------

    def step_acquire(self) -> None:
        self.out.rule("[bold]3/5 Record")
        for name, prog in programs(self.session).items():
            self.session = with_runs(self.session, [name], self.dir)
            info = self.session.run(name)
            assert info is not None
            inside(self.workdir, info.log, f"the {name} run log")  # session.json is editable
            self.save_session()
            if info.complete:
                self.out.print(f"  {name}: already recorded ({info.log})")
                continue
            if self.session.source == "import":
                self._import(name)
                continue
            self._record(name, prog)

    def _record(self, name: str, prog: Program) -> None:
        s = self.session
        info = s.run(name)
        assert info is not None and s.programs is not None
        log = Path(info.log)
        resuming = log.exists() and log.stat().st_size > 0
        cycles_s = len(prog.probe_at_s) * cycle_s(s)
        self.out.print(
            f"  [bold]{name}[/]: load [cyan]{s.programs[name]}[/] on the controller "
            f"({_both(self.args.time_scale, prog.duration_s + cycles_s)}); the spindle must be cold (rested "
            f"{_both(self.args.time_scale, float(s.rest_h or 0.0) * 3600)})."
        )
        if resuming:
            self.out.print(f"  resuming into {log} (the interruption shows as a gap)")
        elif self.interactive and not self.confirm(
            "Spindle cold, "
            + ("cold reference taken" if s.source == "tool-setter" else "probe set")
            + ", program loaded: start recording?"
        ):
            raise AcquisitionError(f"{name}: recording not started")
        links = open_links(s)
        cfg = AcquireConfig(rate_s=float(s.rate_s or 1.0), **_acquire_overrides(self.args))
        live = _LiveView(self.out, prog, name, self.args.time_scale)
        pressed = _StartKey(self.interactive, bool(getattr(self.args, "start_now", False)))

        def waiting() -> None:
            self.out.print(
                "  recording: waiting for the spindle to start (press Cycle Start"
                + (
                    "; press Enter here to start the program clock now, for a program that opens at rest)"
                    if self.interactive
                    else ")"
                ),
                highlight=False,
            )

        try:
            done = record(
                s,
                name,
                prog,
                links=links,
                config=cfg,
                clock=self.clock,
                sleep=self.sleep,
                on_sample=live.sample,
                on_event=live.event,
                start_now=pressed,
                on_start=waiting,
                view=live,
            )
        except KeyboardInterrupt:
            self.out.print(
                f"\n  interrupted: {rows_in(log)} rows kept in {log}; run the wizard again to resume"
            )
            raise
        self.session = done.session
        self.save_session()
        setter = done.measurements is not None
        flagged = done.recording.flagged
        self.out.print(
            f"  {name}: [green]recorded[/] {done.rows} rows to {log}"
            + (f", {done.measurements} tool-setter measurements" if setter else "")
            + (f"; flagged: {flagged}" if flagged else "")
        )

    def _import(self, name: str) -> None:
        a = self.args
        src = getattr(a, f"import_{name}", None)
        if src is None:
            if name == "validation":
                self.out.print("  validation: no --import-validation file; skipped")
                self.session = self.session.updated(validation=False)
                return
            raise ConfigError("--import-calibration is needed with --source import")
        options = ImportOptions(
            time_column=a.import_time_column,
            displacement_column=a.import_displacement_column,
            speed_column=a.import_speed_column,
            speed_log=a.import_speed_log,
            scale=a.import_scale,
            offset_um=a.import_offset_um,
        )
        done = import_run(self.session, name, src, options)
        self.session = done.session
        self.save_session()
        log = self.session.run(name)
        if done.converted:
            self.out.print(f"  {name}: {escape(done.converted)}")
        self.out.print(
            f"  {name}: imported {done.rows} rows from {src} into {log.log if log else '?'}"
        )

    # -- step 4 ------------------------------------------------------------------

    def step_fit(self) -> dict[str, Any]:
        from .commands import print_identification

        self.out.rule("[bold]4/5 Fit and validate (free run)")
        s = self.session
        runs = read_runs(s, self.workdir)
        if "calibration" not in runs:
            raise CalibrationError("no complete calibration run to fit")
        _say_runs(self.out, runs)
        try:
            fitted = fit(s, runs, _now())
        except CalibrationError as err:
            # nothing is saved: a model physics forbids, or a run that did not follow its program
            self.out.print(f"  [red]refused:[/] {escape(str(err))}")
            if (
                self.interactive
                and s.source in LIVE
                and "did not follow" in str(err)
                and self.confirm(
                    "Record the calibration run again (the machine must run the "
                    "calibration program)?",
                    default=False,
                )
            ):
                self.session = set_run_aside(self.session, "calibration")
                self.save_session()
                self.step_acquire()
                return self.step_fit()
            raise
        print_identification(fitted.result, fitted.report, self.out)
        checked = validate(fitted)
        _say_validation(self.out, s, checked)
        summary = report(s, fitted, checked, self.dir / "fit.png")
        _say_report(self.out, s, len(runs), summary)
        self.model = checked.model
        return summary

    # -- step 5 ------------------------------------------------------------------

    def step_save(self, summary: dict[str, Any]) -> dict[str, str]:
        self.out.rule("[bold]5/5 Save")
        done = save(
            self.session,
            self.dir,
            summary,
            self.model,
            report_format=self.args.report_format,
            date=datetime.now(UTC).strftime("%Y-%m-%d"),
            now_utc=_now(),
        )
        self.session = done.session
        self.save_session()
        saved = done.saved
        _say_saved(self.out, done)
        return saved.model_dump()

    def run(self) -> int:
        self.step_identify()
        self.step_programs()
        if self.args.programs_only:
            self.out.print("  programs written; stopping as asked (--programs-only)")
            return 0
        self.step_acquire()
        summary = self.step_fit()
        self.step_save(summary)
        return 0


# -- helpers ------------------------------------------------------------------------


def _say_sensor(out: Console, seen: SensorChecked) -> None:
    where = ""
    if seen.range_fraction is not None:
        where = f", {seen.range_fraction:.0%} of its range"
        if not 0.2 <= seen.range_fraction <= 0.8:
            out.print(
                f"  [yellow]warning:[/] the probe reads {seen.sensor_um:.1f} um{where}: set "
                "the gap near mid-range so the growth cannot saturate it"
            )
    out.print(f"  sensor: [green]ok[/], {seen.sensor_um:.2f} um{where}")


def _say_programs(
    out: Console, s: WizardSession, files: tuple[ProgramFile, ...], time_scale: float
) -> None:
    """The NC programs written, the cold start they need, and the tool setter's programs."""
    t = Table(title="NC programs")
    for col in ("run", "file", "duration", "top speed"):
        t.add_column(col)
    for f in files:
        t.add_row(f.run, str(f.path), _both(time_scale, f.duration_s), f"{f.top_rpm:.0f} rpm")
    out.print(t)
    out.print(
        f"  [yellow]Cold start:[/] each run starts with the spindle at rest for at least "
        f"{float(s.rest_h or 0.0):g} h (five of its slowest time constants, or a night when no "
        "model exists yet). A warm spindle biases the model."
    )
    if s.source == "tool-setter":
        d = str(s.dialect)
        ext = EXTENSIONS[d]
        n = s.probe_plan.touches if s.probe_plan is not None else 1
        touches = f" --touches {n}" if n > 1 else ""
        out.print(
            f"  [yellow]Tool setter:[/] the programs call the cycle {escape(probe_call(d))}. Write it, and the "
            f"cold-reference program, for this machine's tool and setter:\n"
            f"    thermocomp probe-program --dialect {d} --reference --output tcref{ext}\n"
            f"    thermocomp probe-program --dialect {d} --probe-spindle {s.probe_spindle}{touches} "
            f"--output tcprobe{ext}\n"
            "  then run the reference program once on the cold spindle, before each run's first start.",
            highlight=False,
        )


def _say_plan(out: Console, planned: ProbesPlanned) -> None:
    """The probe plan and what its stops cost."""
    every_min = planned.session.probe_every_min
    if planned.sparser_than_planned:
        out.print(
            f"  [yellow]warning:[/] a stop every {every_min:g} min is sparser than the "
            f"plan's {planned.plan.interval_s / 60:.0f} min: the fastest growth may be missed"
        )
    for line in planned.plan.lines():
        out.print(f"  {escape(line)}", highlight=False)
    if every_min is not None:
        out.print(f"  the program stops every {every_min:g} min, as given (--probe-every-min)")


def _say_runs(out: Console, runs: dict[str, RunData]) -> None:
    """What the fit leaves out of the runs, and their interruptions."""
    if runs["calibration"].dropped:
        out.print(
            f"  {runs['calibration'].dropped} calibration rows left out (flagged saturated, "
            "frozen or jump)"
        )
    for name, run in runs.items():
        if run.long_gaps:
            out.print(
                f"  [yellow]warning:[/] {name} run has {run.long_gaps} gap(s) (interruptions), "
                f"{run.gap_s:.0f} s in all: the speed over a gap is "
                "the last one logged before it"
            )


def _say_validation(out: Console, s: WizardSession, checked: Validated) -> None:
    """The held-out run's figures, and the probe-interval plan judged on it."""
    if checked.replay is None or checked.stats is None:
        return
    v = checked.stats
    what = "tool-setter measurements" if s.source == "tool-setter" else "samples"
    out.print(
        f"  validation run, free run on data the fit never saw: RMS {v['rms_um']:.2f} um, "
        f"max {v['max_abs_um']:.2f} um over {v['samples']} {what}"
        + (f" ({checked.dropped} flagged rows left out)" if checked.dropped else "")
    )
    if checked.closed_loop is not None:
        for line in checked.closed_loop.lines():
            out.print(f"  {line}", markup=False, highlight=False)
    else:
        # the observer's noise is fitted from a residual on every row; measurements minutes
        # apart cannot give it, so the service starts from the product's observer defaults
        out.print(
            "  closed loop: the service fuses the tool setter's measurements with the "
            "model (the observer's default noise; a dense run is needed to fit it)",
            highlight=False,
        )


def _say_report(out: Console, s: WizardSession, n_runs: int, summary: dict[str, Any]) -> None:
    """The plot, the channels a fit with inputs could use, and the advice."""
    out.print(f"  plot: {summary['plot']}")
    all_runs = (s.runs or {}).values()
    chans = sorted({c for info in all_runs for c in info.inputs or []})
    if chans and n_runs > 1:
        files = " ".join(info.log for info in all_runs if info.complete)
        out.print(
            f"  the controller's own channels were logged too ({', '.join(chans)}): "
            f"`thermocomp fit {files} --inputs {','.join(chans)} --output …` keeps those "
            "that help on held-out runs"
        )
    for line in summary["advice"]:
        out.print(f"  [yellow]advice:[/] {line}")
    if not summary["advice"]:
        out.print("  [green]the model is good[/]: no re-run needed")


def _say_saved(out: Console, done: SavedFiles) -> None:
    """The files written, the models kept, and what to run next."""
    saved = done.saved
    t = Table(title="Written")
    t.add_column("what")
    t.add_column("file")
    t.add_row("model", saved.model)
    t.add_row("report", saved.report)
    t.add_row("runtime config", saved.config)
    out.print(t)
    if done.older:
        out.print(f"  earlier models kept: {', '.join(done.older)}")
    out.print(
        f"  next: check it with [bold]thermocomp run --config {saved.config} --check[/], "
        f"or replay a logged day as the service would run it with "
        f"[bold]thermocomp replay LOG --config {saved.config}[/]"
    )


def _max_rpm(value: Any) -> float:
    max_rpm = float(value)
    if not (math.isfinite(max_rpm) and 100 <= max_rpm <= 200_000):
        raise ConfigError(f"--max-rpm {max_rpm:g}: not a plausible spindle speed (100 to 200000)")
    return max_rpm


def _rate_s(value: Any) -> float:
    rate = float(value)
    if not rate > 0 or not math.isfinite(rate):
        raise ConfigError("--rate-s must be > 0")
    return rate


def _choice(flag: str, allowed: tuple[str, ...]) -> Callable[[Any], str]:
    def check(value: Any) -> str:
        if value not in allowed:
            raise ConfigError(f"{flag} {value!r}: choose from {', '.join(allowed)}")
        return str(value)

    return check


def _both(time_scale: float, seconds: float) -> str:
    """A duration of the machine's (simulated) time, with the wall time it takes when the
    virtual machine tool runs faster than the wall."""
    scale = float(time_scale)
    own = f"{seconds / 3600:.2f} h" if seconds >= 3600 else f"{seconds / 60:.1f} min"
    if scale == 1.0:
        return own
    wall = seconds / scale
    shown = (
        f"{wall / 3600:.2f} h"
        if wall >= 3600
        else f"{wall / 60:.1f} min"
        if wall >= 60
        else f"{wall:.0f} s"
    )
    return f"{own} ({shown} wall at {scale:g}x)"


def _console() -> Console:
    c = Console(highlight=False)
    return c if c.is_terminal else Console(highlight=False, width=130)


def _now() -> str:
    return datetime.now(UTC).replace(microsecond=0).isoformat()


def _clock(scale: float, anchor_s: float) -> Callable[[], float]:
    """Wall time, or for the virtual machine tool a faster one that runs ``scale`` times
    wall time from ``anchor_s`` (the session's start), so every process agrees on it."""
    if scale == 1.0:
        return time.time
    return lambda: anchor_s + (time.time() - anchor_s) * scale


def _acquire_overrides(args: argparse.Namespace) -> dict[str, Any]:
    out = {}
    for key in (
        "frozen_s",
        "frozen_after_step_s",
        "abort_frozen_s",
        "abort_saturated_s",
        "sensor_grace_s",
        "start_timeout_s",
        "probe_timeout_s",
    ):
        v = getattr(args, key, None)
        if v is not None:
            out[key] = v
    return out


class _StartKey:
    """ "Start now": ``--start-now``, or Enter on the terminal while the recording waits for the
    spindle. Polled without blocking, and only while the recording waits, so no later answer is
    taken for it."""

    def __init__(self, interactive: bool, at_once: bool):
        self.interactive, self.pressed = interactive, at_once

    def __call__(self) -> bool:
        if self.pressed or not self.interactive:
            return self.pressed
        import select

        try:
            ready, _, _ = select.select([sys.stdin], [], [], 0)
            if ready and sys.stdin.readline():
                self.pressed = True
        except (OSError, ValueError):
            self.interactive = False  # no terminal to read after all
        return self.pressed


class _LiveView:
    """Progress, the latest reading and a sparkline: a rich live panel on a terminal, a plain
    line every 5 % otherwise. Times in the machine's hours, and wall minutes when it runs faster."""

    def __init__(self, console: Console, program: Program, name: str, time_scale: float = 1.0):
        self.out, self.program, self.name = console, program, name
        self.scale = float(time_scale)
        self.live: Any = None
        self.next_mark = 0.0
        self.lines: list[str] = []

    def __enter__(self) -> _LiveView:
        if self.out.is_terminal:
            from rich.live import Live

            self.live = Live(console=self.out, refresh_per_second=4, transient=False)
            self.live.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.live is not None:
            self.live.__exit__(*exc)

    def when(self, t_s: float) -> str:
        own = f"{t_s / 3600:5.2f} h"
        return own if self.scale == 1.0 else f"{own} ({t_s / self.scale / 60:.1f} min wall)"

    def event(self, ev: Event) -> None:
        tag = (
            "[red]problem[/]"
            if ev.problem and ev.begins
            else "[green]ok[/]"
            if ev.problem
            else "[cyan]info[/]"
        )
        msg = f"  {tag} t {self.when(ev.time_s).strip()}: {ev.message}"
        if self.live is not None:
            self.live.console.print(msg)
        else:
            self.out.print(msg)

    def sample(self, s: Sample, rec: Recorder) -> None:
        frac = progress_fraction(s, self.program)
        speed = "-" if s.speed_rpm is None else f"{s.speed_rpm:.0f}"
        cmd = "-" if s.commanded_rpm is None else f"{s.commanded_rpm:.0f}"
        el = "-" if s.elongation_um is None else f"{s.elongation_um:+.2f}"
        flags = f" [red]{Problem(s.flags).name}[/]" if s.flags else ""
        if self.live is not None:
            from rich.progress_bar import ProgressBar
            from rich.table import Table as T

            g = T.grid(padding=(0, 1))
            g.add_row(
                f"[bold]{self.name}[/]",
                ProgressBar(total=1.0, completed=frac, width=40),
                f"{frac:.0%}",
                f"t {self.when(s.time_s)}",
            )
            g.add_row("speed", f"{speed} rpm (programmed {cmd})", "", "")
            g.add_row("growth", f"{el} um{flags}", "", "")
            g.add_row("", sparkline(rec.recent, 60), "", "")
            self.live.update(g)
        elif frac >= self.next_mark:
            self.next_mark = math.floor(frac * 20 + 1) / 20
            self.out.print(
                f"  {self.name} {frac:4.0%}  t {self.when(s.time_s)}  {speed:>6} rpm "
                f"(programmed {cmd})  growth {el} um  {sparkline(rec.recent, 30)}"
            )


def main(args: argparse.Namespace) -> int:
    if args.time_scale <= 0:
        raise ConfigError("--time-scale must be > 0")
    wiz = Wizard(args)
    try:
        return wiz.run()
    except AcquisitionError as err:
        print(f"thermocomp: error: {clip(str(err))}", file=sys.stderr)
        return 3


def _shown(path: Path) -> Path:
    """``path`` as the user can open it from where the command ran: relative to the current
    directory when it lies below it, else absolute."""
    path = Path(path).resolve()
    try:
        return path.relative_to(Path.cwd().resolve())
    except ValueError:
        return path


def profile_cmd(args: argparse.Namespace) -> int:
    """``thermocomp profile``: write the NC program for a calibration (or validation) profile."""
    if args.dialect not in DIALECTS:
        raise ConfigError(f"--dialect {args.dialect!r}: choose from {', '.join(DIALECTS)}")
    try:
        if args.validation:
            prog = validation_profile(args.max_rpm, seed=args.seed)
        else:
            prog = calibration_profile(
                args.max_rpm, step_min=args.step_min, cooldown_min=args.cooldown_min
            )
    except ValueError as err:
        raise ConfigError(str(err)) from err
    rest = rest_hours(load_model(args.model).time_constants_s() if args.model else None)
    text = to_nc(
        prog,
        args.dialect,
        name=args.name,
        notes=(f"COLD START: SPINDLE AT REST FOR {rest:g} H BEFOREHAND",),
    )
    write_text(args.output, text)
    out = Console(highlight=False)
    out.print(
        f"wrote {args.output}: {prog.name} profile, {args.dialect}, {prog.duration_s / 3600:.2f} h, "
        f"up to {max(sp for _, sp in prog.segments):.0f} rpm"
    )
    out.print(f"[yellow]cold start:[/] the spindle must have rested for {rest:g} h before this run")
    return 0
