"""``thermocomp wizard``: one guided calibration session per spindle, blank to validated model.

Steps: 1 identify the spindle and its links, 2 write the NC programs, 3 record (or import)
the runs, 4 fit and validate in free run, 5 save a versioned model, a report and a runtime
configuration. Every question has a flag; with ``--yes`` (or without a terminal) nothing is
asked and a missing answer is an error. The session lives in
``<workdir>/<machine>/<spindle>/session.json``: after an interruption the wizard resumes
where it stopped, appending to the same run log.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.prompt import Confirm, FloatPrompt, Prompt
from rich.table import Table

from compensator.errors import (
    AcquisitionError,
    CalibrationError,
    ConfigError,
    ThermocompError,
    clip,
)
from compensator.io import (
    RunLog,
    atomic_write,
    load_model,
    read_daq_csv,
    read_run_log,
    read_text,
    save_model,
    versioned_path,
    write_run_log,
    write_text,
)

from .acquire import (
    EXCLUDED,
    AcquireConfig,
    Event,
    Problem,
    Recorder,
    Sample,
    progress_fraction,
    sparkline,
)
from .fit import FEW_LEVELS, NO_COOLDOWN
from .nc_programs import (
    DIALECTS,
    EXTENSIONS,
    calibration_profile,
    probe_call,
    rest_hours,
    to_nc,
    validation_profile,
    with_probe_stops,
)

SESSION_FORMAT = "thermocomp.wizard/1"
RUNS = ("calibration", "validation")
SOURCES = ("sensor", "tool-setter", "import")
"""Where the displacement comes from: an eddy-current sensor read live, the machine's tool setter
(the program stops for it every few minutes; the controller link reads its measurement), or a
DAQ file recorded beside the controller."""
LIVE = ("sensor", "tool-setter")
"""The sources the wizard records itself."""
PROBE_MOVES_S = 10.0
"""The rapid moves to the tool setter and back, on top of the cycle's measuring time [s]: the
default of ``--probe-dwell-s`` with the cycle's measuring time."""

ID_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
"""A machine or spindle id (and no ``..`` in it): it names a directory and files, so nothing
that could leave the work directory or trouble a shell (``/``, ``\\``, NUL, spaces, ...)."""


class Wizard:
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
        self.sleep = (
            sleep if args.time_scale == 1.0 else (lambda s: time.sleep(s / args.time_scale))
        )
        self.session: dict[str, Any] = {}
        self.workdir: Path = Path(args.workdir).resolve()
        self.dir: Path = self.workdir

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
    ) -> Any:
        """The answer from the flag, else the resumed session, else a prompt (or an error)."""
        from rich.markup import escape

        def shown(answer: Any) -> str:
            # an answer is checked after it is echoed: a huge or markup-laden one must echo safely
            return escape(clip(str(answer), 120))

        question = escape(question)
        value = getattr(self.args, key.replace("-", "_"), None)
        if value is not None:
            self.out.print(f"  {question}: [cyan]{shown(value)}[/]  (from {flag})")
            return value
        if key in self.session:
            self.out.print(f"  {question}: [cyan]{shown(self.session[key])}[/]  (from the session)")
            return self.session[key]
        if not self.interactive:
            if default is not None:
                self.out.print(f"  {question}: [cyan]{shown(default)}[/]  (default)")
                return default
            raise ConfigError(f"{flag} is needed when the wizard runs unattended")
        while True:
            if kind is float:
                answer = FloatPrompt.ask(f"  {question}", console=self.out, default=default)
            else:
                answer = Prompt.ask(
                    f"  {question}", console=self.out, default=default, choices=choices
                )
            if answer not in (None, ""):
                self.session[key] = answer
                if (self.dir / "session.json").parent.is_dir() and self.dir != self.workdir:
                    self.save_session()  # kept at once: an interruption loses no answer
                return answer

    def confirm(self, question: str, *, default: bool = True) -> bool:
        if not self.interactive:
            return default
        return Confirm.ask(f"  {question}", console=self.out, default=default)

    def save_session(self) -> None:
        self.session["format"] = SESSION_FORMAT
        self.session["updated_utc"] = _now()
        # private: it keeps the controller and sensor links as typed, which may carry credentials
        with atomic_write(self.dir / "session.json", mode=0o600) as fh:
            json.dump(self.session, fh, indent=2)

    # -- step 1 ------------------------------------------------------------------

    def step_identify(self) -> None:
        a = self.args
        self.out.rule("[bold]1/5 Identify the spindle")
        machine = _ident(self.ask("machine_id", "Machine id", flag="--machine-id"), "--machine-id")
        spindle = _ident(
            self.ask("spindle_id", "Spindle id", flag="--model-spindle-id"), "--model-spindle-id"
        )
        self.dir = _inside(self.workdir, self.workdir / machine / spindle, "the session directory")
        path = self.dir / "session.json"
        if path.exists() and not a.new:
            try:
                self.session = json.loads(read_text(path))
            except ValueError as err:
                raise ConfigError(f"{path}: not a wizard session: {err}") from err
            if self.session.get("format") != SESSION_FORMAT:
                raise ConfigError(f"{path}: not a wizard session ({self.session.get('format')!r})")
            self.out.print(
                f"  resuming the session of {self.session.get('updated_utc', '?')} in {self.dir} "
                f"(recorded: {self._recorded()})"
            )
            if self.interactive and not a.resume and not self.confirm("Resume this session?"):
                self.session = {}
                self._set_aside()
        elif path.exists() and a.new:
            self._set_aside()
        self.dir.mkdir(parents=True, exist_ok=True)
        self.session.update(machine_id=machine, spindle_id=spindle)
        # a faster clock (virtual machine tool) must read the same in a resumed process
        anchor = self.session.setdefault("time_anchor_s", time.time())
        self.session["time_scale"] = float(a.time_scale)  # the service must run at the same
        self.clock = self._clock or _clock(a.time_scale, anchor)
        max_rpm = float(
            self.ask("max_rpm", "Maximum spindle speed [rpm]", flag="--max-rpm", kind=float)
        )
        if not (math.isfinite(max_rpm) and 100 <= max_rpm <= 200_000):
            raise ConfigError(
                f"--max-rpm {max_rpm:g}: not a plausible spindle speed (100 to 200000)"
            )
        self.session["max_rpm"] = max_rpm
        source = self.ask(
            "source",
            "Displacement from (sensor: live eddy-current reading; tool-setter: "
            "the machine's tool setter, the program stopping for it every few minutes; "
            "import: a CSV a DAQ recorded)",
            flag="--source",
            default="sensor",
            choices=list(SOURCES),
        )
        if source not in SOURCES:
            raise ConfigError(f"--source {source!r}: choose from {', '.join(SOURCES)}")
        self.session["source"] = source
        if source in LIVE:
            while True:
                self.session["controller"] = self.ask(
                    "controller",
                    "Controller link (URL, as in the runtime configuration)",
                    flag="--controller",
                )
                if source == "sensor":
                    self.session["sensor"] = self.ask(
                        "sensor",
                        "Sensor (serial:///dev/ttyUSB1?scale=1, ...?protocol=modbus&register=0, "
                        "opc.tcp://...)",
                        flag="--sensor",
                    )
                self.session["rate_s"] = float(
                    self.ask(
                        "rate_s", "Sample period [s]", flag="--rate-s", default=1.0, kind=float
                    )
                )
                if not self.session["rate_s"] > 0:
                    raise ConfigError("--rate-s must be > 0")
                self.save_session()
                if a.no_connection_test or not (
                    self.interactive is False or self.confirm("Test the connections now?")
                ):
                    break
                try:
                    self.test_connections()
                    break
                except ConfigError as err:
                    if not self.interactive:
                        raise
                    # back to the question that failed; every other answer is kept
                    which = getattr(err, "link", None) or "controller"
                    self.session.pop(which, None)
                    setattr(a, which, None)
                    self.save_session()
                    self.out.print(
                        f"  [red]connection test failed:[/] {escape(str(err))}; answer again"
                    )
        else:
            self.session["controller"] = a.controller or self.session.get("controller")
        self.save_session()

    def _recorded(self) -> str:
        """What the session holds: complete runs, and the rows of one cut short."""
        parts = []
        for name, info in self.session.get("runs", {}).items():
            log = Path(str(info.get("log", "")))
            if info.get("complete"):
                parts.append(f"{name} complete")
            elif log.is_file() and _rows(log):
                parts.append(f"{name} {_rows(log)} rows, not complete")
        return ", ".join(parts) or "nothing yet"

    def _set_aside(self) -> None:
        """A new session: the earlier one's answers, run logs, programs and plot move to
        ``earlier/<when it was last updated>/``; models, reports and configurations stay."""
        import shutil

        stamp = (
            re.sub(r"[^0-9A-Za-z]", "", str(self.session.get("updated_utc") or _now()))[:15]
            or "session"
        )
        aside = self.dir / "earlier" / stamp
        k = 2
        while aside.exists():
            aside, k = self.dir / "earlier" / f"{stamp}-{k}", k + 1
        moved = [
            p
            for p in (
                self.dir / "session.json",
                self.dir / "runs",
                self.dir / "fit.png",
                *(self.dir / f"{r}{ext}" for r in RUNS for ext in set(EXTENSIONS.values())),
            )
            if p.exists()
        ]
        aside.mkdir(parents=True)
        for p in moved:
            shutil.move(str(p), str(aside / p.name))
        self.session = {}
        self.out.print(
            f"  a new session: the earlier one (answers, run logs, programs) was kept in "
            f"{_shown(aside)}"
        )

    def _set_run_aside(self, name: str) -> None:
        """A run to record again: its log kept beside as ``<name>.refused-N.csv``."""
        info = self.session["runs"][name]
        log = Path(info["log"])
        if log.exists():
            log.rename(versioned_path(log.with_name(f"{log.stem}.refused.csv")))
        info.update(complete=False, rows=0)
        self.save_session()

    def _links(self):
        """The controller link, and the displacement sensor's (None on the tool-setter route: the
        controller reads the tool setter's measurements)."""
        from cnc_adapters import open_adapter
        from cnc_adapters.sensors import open_sensor

        ctl = open_adapter(self.session["controller"])
        if self.session["source"] == "tool-setter":
            return ctl, None
        return ctl, open_sensor(self.session["sensor"])

    def test_connections(self) -> None:
        from cnc_adapters.base import AdapterError, redact_url

        def failed(link: str, message: str) -> ConfigError:
            err = ConfigError(message)
            err.link = link  # type: ignore[attr-defined]
            return err

        from cnc_adapters import open_adapter
        from cnc_adapters.sensors import open_sensor

        try:
            ctl = open_adapter(self.session["controller"])
        except (AdapterError, ConfigError) as err:
            raise failed("controller", f"controller link: {err}") from err
        setter = self.session["source"] == "tool-setter"
        if setter and not ctl.can_read_measurement:
            ctl.close()
            raise failed(
                "controller",
                f"controller {redact_url(self.session['controller'])}: the link reads "
                "no tool-setter measurement: give it the probe cycle's value and counter variables "
                "(measurement_node and measurement_sequence_node, or the control's own keys)",
            )
        try:
            sensor = None if setter else open_sensor(self.session["sensor"])
        except (AdapterError, ConfigError) as err:
            raise failed("sensor", f"sensor link: {err}") from err
        try:
            with ctl:
                rpm = ctl.read_speed()
                if setter:
                    ctl.read_measurement()  # the variables exist and read; a value there is stale
            self.out.print(
                f"  controller: [green]ok[/], spindle at {rpm:.0f} rpm"
                + (", the tool setter's variables read" if setter else "")
            )
        except AdapterError as err:
            raise failed(
                "controller", f"controller {redact_url(self.session['controller'])}: {err}"
            ) from err
        if sensor is None:
            return
        try:
            with sensor:
                um = sensor.read_um()
            rng = sensor.range_um
            where = ""
            if rng is not None:
                frac = (um - rng[0]) / (rng[1] - rng[0])
                where = f", {frac:.0%} of its range"
                if not 0.2 <= frac <= 0.8:
                    self.out.print(
                        f"  [yellow]warning:[/] the probe reads {um:.1f} um{where}: set the gap "
                        "near mid-range so the growth cannot saturate it"
                    )
            self.out.print(f"  sensor: [green]ok[/], {um:.2f} um{where}")
        except AdapterError as err:
            raise failed("sensor", f"sensor {redact_url(self.session['sensor'])}: {err}") from err

    def both(self, seconds: float) -> str:
        """A duration of the machine's (simulated) time, with the wall time it takes when the
        virtual machine tool runs faster than the wall."""
        scale = float(self.args.time_scale)
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

    # -- step 2 ------------------------------------------------------------------

    def programs(self) -> dict[str, Any]:
        s = self.session
        every = s.get("probe_every_s") if s.get("source") == "tool-setter" else None
        cal = calibration_profile(
            s["max_rpm"],
            step_min=s["step_min"],
            cooldown_min=s["cooldown_min"],
            probe_every_s=every,
        )
        progs = {"calibration": cal}
        if s["validation"]:
            val = validation_profile(s["max_rpm"], seed=s["validation_seed"])
            # with the tool setter alone, the validation run is measured by the same stops
            progs["validation"] = val if every is None else with_probe_stops(val, every)
        return progs

    def plan_probes(self) -> None:
        """The tool-setter route: how often the program stops for a measurement, and what the
        stops cost (``calibration.toolsetter_plan``)."""
        from .probeprog import MAX_TOUCHES, measuring_time_s, probe_cycle, touch_time_s
        from .toolsetter_plan import plan_probe_interval

        a, s = self.args, self.session
        s["probe_spindle"] = a.probe_spindle or s.get("probe_spindle") or "stop"
        touches = (
            a.probe_touches
            if getattr(a, "probe_touches", None) is not None
            else s.get("probe_touches")
        )
        if touches is not None:
            if not (
                math.isfinite(touches) and touches == int(touches) and 1 <= touches <= MAX_TOUCHES
            ):
                raise ConfigError(
                    f"--probe-touches {touches:g}: a whole number from 1 to {MAX_TOUCHES}"
                )
            if int(touches) > 1 and s["dialect"] == "heidenhain":
                raise ConfigError(
                    "--probe-touches is not for heidenhain: TCH PROBE 481 measures once per call"
                )
            touches = s["probe_touches"] = int(touches)
        if a.probe_dwell_s is not None:
            s["probe_dwell_s"] = float(a.probe_dwell_s)
            s["probe_touch_s"] = 0.0  # the cycle as timed on the machine, every touch included
        if "probe_dwell_s" not in s:
            # the cycle's own measuring time with its default feeds, one touch, and the moves to and
            # from the setter; each further touch adds one slow touch's time
            cycle = probe_cycle(
                s["dialect"],
                spindle=s["probe_spindle"],
                approach_z_mm=-5.0 if s["dialect"] == "heidenhain" else None,
            )
            s["probe_dwell_s"] = round(measuring_time_s(cycle) + PROBE_MOVES_S)
            s["probe_touch_s"] = 0.0 if s["dialect"] == "heidenhain" else touch_time_s(cycle)
        dwell = s["probe_dwell_s"]
        if not (math.isfinite(dwell) and 0 <= dwell <= 3600):
            raise ConfigError(
                f"--probe-dwell-s {dwell:g}: one tool-setter cycle's seconds, 0 to 3600"
            )
        taus = self._former_time_constants()
        plan = plan_probe_interval(
            60 * s["step_min"],
            60 * s["cooldown_min"],
            dwell,
            min(taus) if taus else None,
            at_speed=s["probe_spindle"] == "keep",
            touches=touches,
            touch_s=float(s.get("probe_touch_s") or 0.0),
        )
        every_min = a.probe_every_min if a.probe_every_min is not None else s.get("probe_every_min")
        if every_min is not None:
            every_min = float(every_min)
            if not (math.isfinite(every_min) and 1 <= every_min <= 240):
                raise ConfigError(f"--probe-every-min {every_min:g}: 1 to 240 minutes")
            s["probe_every_min"] = every_min
            if 60 * every_min > plan.interval_s:
                self.out.print(
                    f"  [yellow]warning:[/] a stop every {every_min:g} min is sparser than the plan's "
                    f"{plan.interval_s / 60:.0f} min: the fastest growth may be missed"
                )
        s["probe_every_s"] = 60 * every_min if every_min is not None else plan.interval_s
        for line in plan.lines():
            self.out.print(f"  {escape(line)}", highlight=False)
        if every_min is not None:
            self.out.print(
                f"  the program stops every {every_min:g} min, as given (--probe-every-min)"
            )
        s["probe_plan"] = {
            "interval_s": s["probe_every_s"],
            "planned_interval_s": plan.interval_s,
            "dwell_s": plan.cycle_s,
            "touches": plan.touches,
            "bound": plan.bound,
            "fastest_tau_s": plan.fastest_tau_s,
            "tau_assumed": plan.tau_assumed,
        }

    def step_programs(self) -> None:
        a = self.args
        self.out.rule("[bold]2/5 Calibration program")
        s = self.session
        s["dialect"] = self.ask(
            "dialect", "NC dialect", flag="--dialect", default="fanuc", choices=list(DIALECTS)
        )
        if s["dialect"] not in DIALECTS:
            raise ConfigError(f"--dialect {s['dialect']!r}: choose from {', '.join(DIALECTS)}")
        s["step_min"] = float(a.step_min if a.step_min is not None else s.get("step_min", 20.0))
        s["cooldown_min"] = float(
            a.cooldown_min if a.cooldown_min is not None else s.get("cooldown_min", 60.0)
        )
        if "validation" not in s or a.validation is not None:
            s["validation"] = (
                bool(a.validation)
                if a.validation is not None
                else (self.confirm("Also record a different validation profile (recommended)?"))
            )
        s["validation_seed"] = int(s.get("validation_seed", a.validation_seed))
        if s["source"] == "tool-setter":
            self.plan_probes()
        rest = rest_hours(self._former_time_constants())
        s["rest_h"] = rest
        ext = EXTENSIONS[s["dialect"]]
        t = Table(title="NC programs")
        for col in ("run", "file", "duration", "top speed"):
            t.add_column(col)
        files = {}
        for name, prog in self.programs().items():
            text = to_nc(
                prog,
                s["dialect"],
                name=f"TC_{name[:5]}",
                notes=(
                    f"MACHINE {s['machine_id']} SPINDLE {s['spindle_id']}",
                    f"COLD START: SPINDLE AT REST FOR {rest:g} H BEFOREHAND",
                ),
            )
            path = self.dir / f"{name}{ext}"
            write_text(path, text)
            files[name] = str(path)
            # with the tool setter, the program waits at each stop for the cycle
            cycles_s = len(prog.probe_at_s) * self._cycle_s()
            t.add_row(
                name,
                str(path),
                self.both(prog.duration_s + cycles_s),
                f"{max(sp for _, sp in prog.segments):.0f} rpm",
            )
        s["programs"] = files
        self.out.print(t)
        self.out.print(
            f"  [yellow]Cold start:[/] each run starts with the spindle at rest for at least "
            f"{rest:g} h (five of its slowest time constants, or a night when no model exists "
            "yet). A warm spindle biases the model."
        )
        if s["source"] == "tool-setter":
            d = s["dialect"]
            n = (s.get("probe_plan") or {}).get("touches", 1)
            touches = f" --touches {n}" if n > 1 else ""
            self.out.print(
                f"  [yellow]Tool setter:[/] the programs call the cycle {escape(probe_call(d))}. Write it, and the "
                f"cold-reference program, for this machine's tool and setter:\n"
                f"    thermocomp probe-program --dialect {d} --reference --output tcref{ext}\n"
                f"    thermocomp probe-program --dialect {d} --probe-spindle {s['probe_spindle']}{touches} "
                f"--output tcprobe{ext}\n"
                "  then run the reference program once on the cold spindle, before each run's first start.",
                highlight=False,
            )
        self.save_session()

    def _cycle_s(self) -> float:
        """One tool-setter stop as planned, every touch included [s] (0 without the tool setter)."""
        plan = self.session.get("probe_plan") or {}
        return float(plan.get("dwell_s", self.session.get("probe_dwell_s") or 0.0))

    def _former_time_constants(self) -> tuple[float, ...] | None:
        models = (
            sorted((self.dir / "models").glob("*.json")) if (self.dir / "models").is_dir() else []
        )
        for p in reversed(models):
            try:
                return load_model(p).time_constants_s()
            except ThermocompError:
                continue
        return None

    # -- step 3 ------------------------------------------------------------------

    def step_acquire(self) -> None:
        self.out.rule("[bold]3/5 Record")
        runs = self.session.setdefault("runs", {})
        for name, prog in self.programs().items():
            info = runs.setdefault(
                name, {"log": str(self.dir / "runs" / f"{name}.csv"), "complete": False}
            )
            _inside(self.workdir, info["log"], f"the {name} run log")  # session.json is editable
            self.save_session()
            if info.get("complete"):
                self.out.print(f"  {name}: already recorded ({info['log']})")
                continue
            if self.session["source"] == "import":
                self.import_run(name, info)
                continue
            self.record_run(name, prog, info)

    def record_run(self, name: str, prog, info: dict[str, Any]) -> None:
        s = self.session
        log = Path(info["log"])
        resuming = log.exists() and log.stat().st_size > 0
        cycles_s = len(prog.probe_at_s) * self._cycle_s()
        self.out.print(
            f"  [bold]{name}[/]: load [cyan]{s['programs'][name]}[/] on the controller "
            f"({self.both(prog.duration_s + cycles_s)}); the spindle must be cold (rested "
            f"{self.both(s['rest_h'] * 3600)})."
        )
        if resuming:
            self.out.print(f"  resuming into {log} (the interruption shows as a gap)")
        elif self.interactive and not self.confirm(
            "Spindle cold, "
            + ("cold reference taken" if s["source"] == "tool-setter" else "probe set")
            + ", program loaded: start recording?"
        ):
            raise AcquisitionError(f"{name}: recording not started")
        ctl, sensor = self._links()
        cfg = AcquireConfig(rate_s=s["rate_s"], **_acquire_overrides(self.args))
        meta = {
            "source": "thermocomp wizard",
            "machine_id": s["machine_id"],
            "spindle_id": s["spindle_id"],
            "run": name,
            "program": s["programs"][name],
            "controller": s["controller"],
            "sensor": s.get("sensor") or "the controller's tool setter",
            "max_rpm": s["max_rpm"],
        }
        live = _LiveView(self.out, prog, name, self.args.time_scale)
        pressed = _StartKey(self.interactive, bool(getattr(self.args, "start_now", False)))
        rec = Recorder(
            ctl,
            sensor,
            log,
            prog,
            max_rpm=s["max_rpm"],
            config=cfg,
            metadata=meta,
            clock=self.clock,
            sleep=self.sleep,
            on_sample=live.sample,
            on_event=live.event,
            start_now=pressed,
            at_speed=s.get("probe_spindle") == "keep",
        )
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
            with live:
                result = rec.run()
        except AcquisitionError as err:
            kept = _rows(log)
            raise AcquisitionError(
                f"{name}: recording stopped: {err}; {kept} rows kept in {log}; fix it and "
                "run the wizard again to resume"
            ) from err
        except KeyboardInterrupt:
            self.out.print(
                f"\n  interrupted: {_rows(log)} rows kept in {log}; run the wizard again to resume"
            )
            raise
        finally:
            ctl.close()
            if sensor is not None:
                sensor.close()
        info.update(
            complete=result.complete,
            rows=_rows(log),
            flagged=result.flagged,
            events=[f"{e.time_s:.0f} s: {e.message}" for e in result.events if e.problem][:50],
        )
        self.save_session()
        if rec.channels:
            info["inputs"] = list(rec.channels)
        if sensor is None:
            info["measurements"] = int(read_run_log(log).measured.sum())
        self.out.print(
            f"  {name}: [green]recorded[/] {info['rows']} rows to {log}"
            + (f", {info['measurements']} tool-setter measurements" if sensor is None else "")
            + (f"; flagged: {result.flagged}" if result.flagged else "")
        )

    def import_run(self, name: str, info: dict[str, Any]) -> None:
        a = self.args
        src = getattr(a, f"import_{name}", None)
        if src is None:
            if name == "validation":
                self.out.print("  validation: no --import-validation file; skipped")
                self.session["validation"] = False
                return
            raise ConfigError("--import-calibration is needed with --source import")
        cols = {"displacement": a.import_displacement_column}
        if a.import_speed_column:
            cols["speed"] = a.import_speed_column
        t, data = read_daq_csv(src, a.import_time_column, cols)
        disp = data["displacement"] * a.import_scale + a.import_offset_um
        if "speed" in data:
            speed = np.abs(data["speed"])
        elif a.import_speed_log:
            ctl = read_run_log(a.import_speed_log)
            # the controller logs the speed held up to each of its samples
            idx = np.clip(np.searchsorted(ctl.time_s, t, side="left"), 0, len(ctl) - 1)
            speed = np.abs(ctl.speed_rpm[idx])
            outside = (t < ctl.time_s[0]) | (t > ctl.time_s[-1])
            if outside.mean() > 0.05:
                raise CalibrationError(
                    f"{src}: {outside.mean():.0%} of its rows fall outside the speed log "
                    f"{a.import_speed_log}: do both use the same clock?"
                )
        else:
            raise ConfigError(
                "give --import-speed-column or --import-speed-log: a DAQ file needs the speed too"
            )
        elong = disp - disp[0]
        write_run_log(
            info["log"],
            {
                "time_s": t - t[0],
                "speed_rpm": speed,
                "elongation_um": elong,
                "sensor_um": disp,
                "flags": np.zeros(t.size, dtype=int),
            },
            {
                "source": f"imported from {src}",
                "machine_id": self.session["machine_id"],
                "spindle_id": self.session["spindle_id"],
                "run": name,
            },
        )
        info.update(complete=True, rows=int(t.size), imported_from=str(src))
        self.save_session()
        self.out.print(f"  {name}: imported {t.size} rows from {src} into {info['log']}")

    # -- step 4 ------------------------------------------------------------------

    def step_fit(self) -> dict[str, Any]:
        from .commands import print_identification
        from .fit import fit_logs
        from .metrics import residual_stats
        from .plots import Panel, plot_panels
        from .replay import replay

        self.out.rule("[bold]4/5 Fit and validate (free run)")
        s = self.session
        logs = {
            name: _clean(read_run_log(_inside(self.workdir, info["log"], f"the {name} run log")))
            for name, info in s["runs"].items()
            if info.get("complete")
        }
        if "calibration" not in logs:
            raise CalibrationError("no complete calibration run to fit")
        cal_log, dropped = logs["calibration"]
        if dropped:
            self.out.print(
                f"  {dropped} calibration rows left out (flagged saturated, frozen or jump)"
            )
        for name, (lg, _) in logs.items():
            long = [g for g in lg.gaps if g.duration_s > 60]
            if long:
                self.out.print(
                    f"  [yellow]warning:[/] {name} run has {len(long)} gap(s) (interruptions), "
                    f"{sum(g.duration_s for g in long):.0f} s in all: the speed over a gap is "
                    "the last one logged before it"
                )
        # the one identification `thermocomp fit` runs: the same log gives the same model
        # a live recording measures growth toward the part as positive; an imported DAQ file's
        # sign is the device's, so the data says it
        direction = 1 if s.get("source") in LIVE else None
        try:
            result = fit_logs(
                [cal_log],
                labels=["calibration"],
                spindle_id=s["spindle_id"],
                machine_id=s["machine_id"],
                created_utc=_now(),
                growth_direction=direction,
            )
        except CalibrationError as err:
            # nothing is saved: a model physics forbids, or a run that did not follow its program
            self.out.print(f"  [red]refused:[/] {escape(str(err))}")
            if (
                self.interactive
                and s.get("source") in LIVE
                and "did not follow" in str(err)
                and self.confirm(
                    "Record the calibration run again (the machine must run the "
                    "calibration program)?",
                    default=False,
                )
            ):
                self._set_run_aside("calibration")
                self.step_acquire()
                return self.step_fit()
            raise

        report = result.report()
        print_identification(result, report, self.out)
        model = result.model
        j = result.dataset
        fitted = result.free_run_um()["calibration"]
        cal_res = j.elongation_um - fitted  # NaN where not measured (the tool-setter route)
        summary: dict[str, Any] = {
            "form": model.form,
            "reason": result.reason,
            "calibration": residual_stats(cal_res[j.measured]),
            "warnings": list(result.warnings),
            "report": report,
        }
        panels = [Panel("calibration run", j.time_s, j.speed_rpm, fitted, j.elongation_um)]
        peak = float(np.max(np.abs(j.elongation_um[j.measured])))
        if "validation" in logs:
            vlog, vdrop = logs["validation"]
            rep = replay(model, vlog)
            res = rep.residual_um
            summary["validation"] = residual_stats(res[np.isfinite(res)])
            summary["validation_report"] = rep.report
            panels.append(
                Panel(
                    "validation run (held out)",
                    rep.time_s,
                    rep.speed_rpm,
                    rep.predicted_um,
                    rep.measured_um,
                )
            )
            v = summary["validation"]
            what = "tool-setter measurements" if s.get("source") == "tool-setter" else "samples"
            self.out.print(
                f"  validation run, free run on data the fit never saw: RMS {v['rms_um']:.2f} um, "
                f"max {v['max_abs_um']:.2f} um over {v['samples']} {what}"
                + (f" ({vdrop} flagged rows left out)" if vdrop else "")
            )
            if j.dense and bool(np.isfinite(res).all()):
                # how often a tool setter would have to measure, judged on the held-out run
                from .closedloop import plan_on_run

                loop = plan_on_run(
                    j.time_s, cal_res, rep.time_s, res, max(model.time_constants_s(0.0))
                )
                for line in loop.lines():
                    self.out.print(f"  {line}", markup=False, highlight=False)
                summary["closed_loop"] = loop.report()
                model = model.model_copy(
                    update={"fit": {**model.fit, "observer": loop.observer.model_dump()}}
                )
            else:
                # the observer's noise is fitted from a residual on every row; measurements minutes
                # apart cannot give it, so the service starts from the product's observer defaults
                self.out.print(
                    "  closed loop: the service fuses the tool setter's measurements with the "
                    "model (the observer's default noise; a dense run is needed to fit it)",
                    highlight=False,
                )
        # the standard's drift test, from the same runs: what a shop hands its customer
        from .iso230_3 import report_rows, spindle_thermal_test

        tests = {
            "calibration": spindle_thermal_test(j.time_s, j.speed_rpm, j.elongation_um, fitted)
        }
        if "validation" in summary:
            tests["validation"] = spindle_thermal_test(
                rep.time_s, rep.speed_rpm, rep.measured_um, rep.predicted_um
            )
        summary["iso230_3"] = report_rows(tests)
        plot = self.dir / "fit.png"
        plot_panels(
            plot,
            panels,
            f"{s['machine_id']} / {s['spindle_id']}: {model.form}",
            max_rpm=s["max_rpm"],
        )
        summary["plot"] = str(plot)
        summary["peak_um"] = peak
        summary["advice"] = advise(summary, s)
        self.out.print(f"  plot: {plot}")
        chans = sorted({c for info in s["runs"].values() for c in info.get("inputs", [])})
        if chans and len(logs) > 1:
            files = " ".join(
                str(info["log"]) for info in s["runs"].values() if info.get("complete")
            )
            self.out.print(
                f"  the controller's own channels were logged too ({', '.join(chans)}): "
                f"`thermocomp fit {files} --inputs {','.join(chans)} --output …` keeps those "
                "that help on held-out runs"
            )
        for line in summary["advice"]:
            self.out.print(f"  [yellow]advice:[/] {line}")
        if not summary["advice"]:
            self.out.print("  [green]the model is good[/]: no re-run needed")
        self._model = model
        return summary

    # -- step 5 ------------------------------------------------------------------

    def step_save(self, summary: dict[str, Any]) -> dict[str, str]:
        from .report import calibration_report, runtime_config

        self.out.rule("[bold]5/5 Save")
        s = self.session
        stamp = datetime.now(UTC).strftime("%Y-%m-%d")
        base = f"{s['machine_id']}_{s['spindle_id']}_{stamp}"
        model_path = versioned_path(self.dir / "models" / f"{base}.json")
        model_path.parent.mkdir(parents=True, exist_ok=True)
        save_model(model_path, self._model)
        version = model_path.stem[len(base) :].lstrip(".") or "v1"
        fmt = self.args.report_format
        report_path = versioned_path(self.dir / "reports" / f"{base}.{fmt}")
        write_text(
            report_path, calibration_report(s, summary, self._model, model_path, fmt, version)
        )
        config_path = versioned_path(self.dir / "config" / f"{base}.toml")
        write_text(
            config_path, runtime_config(s, self._model, model_path, config_dir=config_path.parent)
        )
        older = sorted(p.name for p in (self.dir / "models").glob("*.json") if p != model_path)
        s["saved"] = {
            "model": str(model_path),
            "report": str(report_path),
            "config": str(config_path),
            "version": version,
            "at_utc": _now(),
        }
        self.save_session()
        t = Table(title="Written")
        t.add_column("what")
        t.add_column("file")
        t.add_row("model", str(model_path))
        t.add_row("report", str(report_path))
        t.add_row("runtime config", str(config_path))
        self.out.print(t)
        if older:
            self.out.print(f"  earlier models kept: {', '.join(older)}")
        self.out.print(
            f"  next: check it with [bold]thermocomp run --config {config_path} --check[/], "
            f"or replay a logged day as the service would run it with "
            f"[bold]thermocomp replay LOG --config {config_path}[/]"
        )
        return s["saved"]

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


def advise(summary: dict[str, Any], session: dict[str, Any]) -> list[str]:
    """What to re-run when the fit is poor, from the figures and warnings."""
    out: list[str] = []
    peak = max(summary.get("peak_um", 0.0), 1e-9)
    cal = summary["calibration"]
    val = summary.get("validation")
    limit = max(1.0, 0.1 * peak)
    warnings = " ".join(summary.get("warnings", []))
    if NO_COOLDOWN in warnings:
        out.append(
            "record the calibration run again with its cool-down (>= 60 min at 0 rpm at the end)"
        )
    if FEW_LEVELS in warnings:
        out.append("the run has too few speed levels: run the full staircase")
    if cal["rms_um"] is not None and cal["rms_um"] > limit:
        out.append(
            f"the model misses the calibration run itself (RMS {cal['rms_um']:.2f} um > {limit:.2f} um): "
            "check the probe bracket for its own thermal drift (Invar bracket, coolant off the probe) "
            "and that the spindle was cold at the start"
        )
    if val is None:
        if not session.get("validation"):
            out.append(
                "no validation run: record one (a different profile) to see how the model does "
                "on speeds it was not fitted on"
            )
    elif val["rms_um"] is not None and val["rms_um"] > limit:
        out.append(
            f"the model does not carry over to the validation run (RMS {val['rms_um']:.2f} um > "
            f"{limit:.2f} um): record a second calibration run and fit both with "
            "`thermocomp fit cal1.csv cal2.csv`, or check that ambient and coolant were steady"
        )
    if session.get("source") == "tool-setter" and session.get("probe_spindle", "stop") != "keep":
        out.append(
            "the tool setter measured at rest: the growth that exists only while the spindle turns "
            "(centrifugal, bearing preload; 10 um and more on a fast spindle) is not in the model, so "
            "it is good at rest and misses that part while cutting; calibrate with a laser setter at "
            "speed (--probe-spindle keep) or an eddy-current sensor, or keep probing in production so "
            "the observer carries it"
        )
    for name, info in session.get("runs", {}).items():
        bad = sum(v for k, v in (info.get("flagged") or {}).items() if Problem[k] & EXCLUDED)
        if bad > 0.05 * max(info.get("rows", 1), 1):
            out.append(
                f"{name}: {bad} flagged samples (saturated, frozen, jumps): fix the sensor set-up and "
                "record it again"
            )
    return out


def _clean(log: RunLog) -> tuple[RunLog, int]:
    """The log without rows flagged saturated, frozen or jump (by the recorder)."""
    flags = log.extras.get("flags")
    if flags is None or flags.dtype == object:
        return log, 0
    keep = (flags.astype(int) & int(EXCLUDED)) == 0
    if keep.all():
        return log, 0
    return RunLog(
        log.time_s[keep],
        log.speed_rpm[keep],
        None if log.elongation_um is None else log.elongation_um[keep],
        {k: v[keep] for k, v in log.extras.items()},
        log.metadata,
        log.gaps,
        log.source,
    ), int((~keep).sum())


def _rows(path: Path) -> int:
    try:
        return len(read_run_log(path))
    except ThermocompError:
        return 0


def _ident(value: Any, flag: str) -> str:
    """``value`` as an id (surrounding blanks dropped), or a one-line ConfigError naming it."""
    text = str(value).strip()
    if not ID_PATTERN.fullmatch(text) or ".." in text:
        raise ConfigError(
            f"{flag} {clip(repr(text), 80)}: an id names files, so 1 to 64 of A-Z a-z 0-9 "
            "'_' '.' '-', starting with a letter or digit, without '..'"
        )
    return text


def _inside(root: Path, path: str | Path, what: str) -> Path:
    """``path`` resolved, if it stays inside ``root`` (a resolved directory); else a ConfigError."""
    try:
        resolved = Path(path).resolve()
    except (OSError, ValueError) as err:  # a NUL byte, a symlink loop
        raise ConfigError(
            f"{what} {clip(repr(str(path)), 200)}: not a usable path ({err})"
        ) from err
    if not resolved.is_relative_to(root):
        raise ConfigError(f"{what} {clip(str(resolved), 200)} is outside the work directory {root}")
    return resolved


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

    def __init__(self, console: Console, program, name: str, time_scale: float = 1.0):
        self.out, self.program, self.name = console, program, name
        self.scale = float(time_scale)
        self.live = None
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
