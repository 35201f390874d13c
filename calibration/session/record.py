"""The wizard's step 3 as values: the links checked, a run recorded live or imported from a DAQ
file. Nothing here asks or prints; the recorder's progress goes to the callbacks given."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from compensator.errors import AcquisitionError, CalibrationError, ConfigError, ThermocompError
from compensator.io import read_daq_csv, read_run_log, versioned_path, write_run_log
from compensator.io.runlog import MIN_CALIBRATION_SPAN_S, time_unit_of, time_unit_refusal
from compensator.speed_programs import Program

from ..acquire import AcquireConfig, Event, Recorder, Recording, Sample
from .model import WizardSession


def rows_in(path: Path) -> int:
    """The rows of the run log at ``path`` (0 when there is none, or none readable)."""
    try:
        return len(read_run_log(path))
    except ThermocompError:
        return 0


def recorded(session: WizardSession) -> str:
    """What the session holds: complete runs, and the rows of one cut short."""
    parts = []
    for name, info in (session.runs or {}).items():
        log = Path(info.log)
        if info.complete:
            parts.append(f"{name} complete")
        elif log.is_file() and rows_in(log):
            parts.append(f"{name} {rows_in(log)} rows, not complete")
    return ", ".join(parts) or "nothing yet"


def with_runs(session: WizardSession, names: Iterable[str], directory: Path) -> WizardSession:
    """The session with a record for each run of ``names`` it has none for yet, its log in
    ``directory/runs``."""
    runs: dict[str, Any] = dict(session.runs or {})
    for name in names:
        runs.setdefault(name, {"log": str(directory / "runs" / f"{name}.csv"), "complete": False})
    return session.updated(runs=runs)


def set_run_aside(session: WizardSession, name: str) -> WizardSession:
    """Run ``name`` to record again: its log kept beside as ``<name>.refused-N.csv``."""
    info = session.run(name)
    if info is None:
        return session
    log = Path(info.log)
    if log.exists():
        log.rename(versioned_path(log.with_name(f"{log.stem}.refused.csv")))
    return session.with_run(name, complete=False, rows=0)


class LinkFailed(ConfigError):
    """A connection test failed; ``link`` names the answer to ask again (controller or sensor)."""

    def __init__(self, link: str, message: str):
        super().__init__(message)
        self.link = link


@dataclass(frozen=True)
class ControllerChecked:
    """What the connection test read from the controller."""

    speed_rpm: float
    tool_setter: bool
    """The tool setter's variables read (the tool-setter route)."""


@dataclass(frozen=True)
class SensorChecked:
    """What the connection test read from the displacement sensor."""

    sensor_um: float
    range_fraction: float | None
    """Where the reading sits in the sensor's range (0 to 1), when it has one."""


def open_links(session: WizardSession) -> tuple[Any, Any]:
    """The controller link, and the displacement sensor's (None on the tool-setter route: the
    controller reads the tool setter's measurements)."""
    from cnc_adapters import open_adapter
    from cnc_adapters.sensors import open_sensor

    ctl = open_adapter(str(session.controller))
    if session.source == "tool-setter":
        return ctl, None
    return ctl, open_sensor(str(session.sensor))


def check_controller(session: WizardSession) -> ControllerChecked:
    """Open the controller link and read it once; a :class:`LinkFailed` if it fails."""
    from cnc_adapters import open_adapter
    from cnc_adapters.base import AdapterError, redact_url

    controller = str(session.controller)
    try:
        ctl = open_adapter(controller)
    except (AdapterError, ConfigError) as err:
        raise LinkFailed("controller", f"controller link: {err}") from err
    setter = session.source == "tool-setter"
    if setter and not ctl.can_read_measurement:
        ctl.close()
        raise LinkFailed(
            "controller",
            f"controller {redact_url(controller)}: the link reads "
            "no tool-setter measurement: give it the probe cycle's value and counter variables "
            "(measurement_node and measurement_sequence_node, or the control's own keys)",
        )
    try:
        with ctl:
            rpm = ctl.read_speed()
            if setter:
                ctl.read_measurement()  # the variables exist and read; a value there is stale
    except AdapterError as err:
        raise LinkFailed("controller", f"controller {redact_url(controller)}: {err}") from err
    return ControllerChecked(rpm, setter)


def check_sensor(session: WizardSession) -> SensorChecked | None:
    """Open the displacement sensor's link and read it once (None on the tool-setter route,
    which has none); a :class:`LinkFailed` if it fails."""
    from cnc_adapters.base import AdapterError, redact_url
    from cnc_adapters.sensors import open_sensor

    if session.source == "tool-setter":
        return None
    url = str(session.sensor)
    try:
        sensor = open_sensor(url)
    except (AdapterError, ConfigError) as err:
        raise LinkFailed("sensor", f"sensor link: {err}") from err
    try:
        with sensor:
            um = sensor.read_um()
    except AdapterError as err:
        raise LinkFailed("sensor", f"sensor {redact_url(url)}: {err}") from err
    rng = sensor.range_um
    return SensorChecked(um, None if rng is None else (um - rng[0]) / (rng[1] - rng[0]))


@dataclass(frozen=True)
class Recorded:
    """The record step's value: the session with the run's record, and the recording."""

    session: WizardSession
    recording: Recording
    rows: int
    measurements: int | None
    """Tool-setter measurements in the log (None with a sensor)."""


def record(
    session: WizardSession,
    name: str,
    program: Program,
    *,
    links: tuple[Any, Any],
    config: AcquireConfig,
    clock: Callable[[], float],
    sleep: Callable[[float], None],
    on_sample: Callable[[Sample, Recorder], None] | None = None,
    on_event: Callable[[Event], None] | None = None,
    start_now: Callable[[], bool] | None = None,
    on_start: Callable[[], None] | None = None,
    view: AbstractContextManager[Any] | None = None,
) -> Recorded:
    """Record run ``name`` of ``program`` on ``links`` (controller, sensor or None) into the run's
    log, appending to what it holds; the links are closed after. ``on_start`` is called once the
    recorder is ready, before it waits for the spindle; ``view`` (a live progress display) is
    entered around the recording."""
    s = session
    info = s.run(name)
    if info is None or s.programs is None:
        raise ConfigError(f"the session has no {name} run to record")
    log = Path(info.log)
    ctl, sensor = links
    meta = {
        "source": "thermocomp wizard",
        "machine_id": s.machine_id,
        "spindle_id": s.spindle_id,
        "run": name,
        "program": s.programs[name],
        "controller": s.controller,
        "sensor": s.sensor or "the controller's tool setter",
        "max_rpm": s.max_rpm,
    }
    try:
        rec = Recorder(
            ctl,
            sensor,
            log,
            program,
            max_rpm=float(s.max_rpm or 0.0),
            config=config,
            metadata=meta,
            clock=clock,
            sleep=sleep,
            on_sample=on_sample,
            on_event=on_event,
            start_now=start_now,
            at_speed=s.probe_spindle == "keep",
        )
        if on_start is not None:
            on_start()
        try:
            with view if view is not None else nullcontext():
                result = rec.run()
        except AcquisitionError as err:
            raise AcquisitionError(
                f"{name}: recording stopped: {err}; {rows_in(log)} rows kept in {log}; fix it "
                "and run the wizard again to resume"
            ) from err
    finally:
        ctl.close()
        if sensor is not None:
            sensor.close()
    rows = rows_in(log)
    measured = None if sensor is not None else int(read_run_log(log).measured.sum())
    done = s.with_run(
        name,
        complete=result.complete,
        rows=rows,
        flagged=dict(result.flagged),
        events=[f"{e.time_s:.0f} s: {e.message}" for e in result.events if e.problem][:50],
        **({"inputs": list(rec.channels)} if rec.channels else {}),
        **({"measurements": measured} if measured is not None else {}),
    )
    return Recorded(done, result, rows, measured)


@dataclass(frozen=True)
class ImportOptions:
    """How to read a DAQ file (the wizard's ``--import-*`` flags)."""

    time_column: str
    displacement_column: str
    speed_column: str | None
    speed_log: str | None
    scale: float
    offset_um: float


@dataclass(frozen=True)
class Imported:
    session: WizardSession
    rows: int
    source: str
    converted: str | None = None
    """What the import did to the time column, when its name says another unit than seconds."""


def import_run(
    session: WizardSession, name: str, source: str | Path, options: ImportOptions
) -> Imported:
    """Run ``name`` from the DAQ file ``source``, its speed from the file or a controller log on
    the same clock, written as the run's log."""
    info = session.run(name)
    if info is None:
        raise ConfigError(f"the session has no {name} run to import")
    o = options
    cols = {"displacement": o.displacement_column}
    if o.speed_column:
        cols["speed"] = o.speed_column
    # a column named for its unit (time_ms, "Time [min]") is converted, and said; any other
    # is seconds or date-times, and refused in one line when its steps and span are no spindle's
    unit = time_unit_of(o.time_column)
    t, data = read_daq_csv(source, o.time_column, cols, seconds_per_unit=unit[2] if unit else 1.0)
    converted = (
        f"{o.time_column} read as {unit[1]} (its name says so) and converted to seconds"
        if unit
        else None
    )
    why = time_unit_refusal(t, o.time_column, min_span_s=MIN_CALIBRATION_SPAN_S)
    if why is not None:
        raise CalibrationError(f"{source}: {why}")
    disp = data["displacement"] * o.scale + o.offset_um
    if "speed" in data:
        speed = np.abs(data["speed"])
    elif o.speed_log:
        ctl = read_run_log(o.speed_log)
        # the controller logs the speed held up to each of its samples
        idx = np.clip(np.searchsorted(ctl.time_s, t, side="left"), 0, len(ctl) - 1)
        speed = np.abs(ctl.speed_rpm[idx])
        outside = (t < ctl.time_s[0]) | (t > ctl.time_s[-1])
        if outside.mean() > 0.05:
            raise CalibrationError(
                f"{source}: {outside.mean():.0%} of its rows fall outside the speed log "
                f"{o.speed_log}: do both use the same clock?"
            )
    else:
        raise ConfigError(
            "give --import-speed-column or --import-speed-log: a DAQ file needs the speed too"
        )
    write_run_log(
        info.log,
        {
            "time_s": t - t[0],
            "speed_rpm": speed,
            "elongation_um": disp - disp[0],
            "sensor_um": disp,
            "flags": np.zeros(t.size, dtype=int),
        },
        {
            "source": f"imported from {source}",
            "machine_id": session.machine_id,
            "spindle_id": session.spindle_id,
            "run": name,
        },
    )
    done = session.with_run(name, complete=True, rows=int(t.size), imported_from=str(source))
    return Imported(done, int(t.size), str(source), converted)
