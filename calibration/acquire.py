"""Recording a calibration run: speed from the controller, displacement from the sensor, or the
machine's tool setter alone.

Each sample the recorder reads both, checks the reading, and appends one row to the run
log (flushed per row, fsynced every few seconds), so an interruption loses at most the row
being written and the recording can resume into the same log.

Checks, each reported once when it begins (and again when it clears):

- **sensor fault**: the sensor does not answer (unplugged, silent, garbage); after
  ``sensor_grace_s`` the recording stops;
- **saturation**: the reading is at the end of the sensor's range or the sensor reports
  over-range; after ``abort_saturated_s`` the recording stops (re-set the probe gap);
- **frozen**: the very same value for ``frozen_s``, or for ``frozen_after_step_s`` across a
  speed step, where the elastic growth alone must move it (a hung amplifier or a stale
  buffer); after another ``abort_frozen_s`` the recording stops;
- **jump**: a step larger than the spindle can grow in one sample (``max_rate_um_per_s``
  plus ``jump_um``; more at a speed step, where the elastic term jumps);
- **not following**: the spindle speed differs from the program for ``follow_alarm_s``
  (override not at 100 %, feed hold, another program).

Rows carry these as a ``flags`` column (:class:`Problem`); the fit leaves out rows flagged
saturated, frozen or jump. Time is ``clock()`` minus the recording's start, so a resumed
recording shows the interruption as a gap. Injected ``clock`` and ``sleep`` let tests run
without waiting.

**The tool setter alone** (``sensor=None``): the program carries probe stops
(``Program.probe_at_s``, :func:`calibration.nc_programs.with_probe_stops`) and the controller's
link reads the probe cycle's measurement (``controller.read_measurement()``, the counter
handshake). Every sample is logged as above; the elongation is empty (NaN, the log marked
``elongation_um: sparse``) except on the row of a new measurement, which carries its value (the
cycle measures the growth from the cold reference). The cycle measures at rest: when the spindle
already turns again at the sample that sees the value, the value goes on a row of its own at rest,
half-way since the previous sample, so that no speed's elastic growth is put on it. At a stop
the recorder's program clock waits for the measurement (the machine's program waits for its
cycle), so the commanded speed is 0 there and the spindle at rest is no "not following"; no
measurement within ``probe_timeout_s`` wall seconds stops the recording. The frozen, jump and
saturation checks are the eddy-current sensor's; a failed read of the measurement counts as a
sensor fault.
"""

from __future__ import annotations

import enum
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from cnc_adapters.base import Adapter, AdapterError
from cnc_adapters.sensors import Sensor, SensorOverRangeError
from compensator.errors import AcquisitionError, ConfigError
from compensator.io import RunLogAppender
from compensator.io.runlog import ELONGATION_COLUMN, SPARSE
from compensator.speed_programs import Program

COLUMNS = ("time_s", "speed_rpm", "elongation_um", "sensor_um", "commanded_rpm", "flags")
IDLE_RPM = 1.0


class Problem(enum.IntFlag):
    SENSOR_FAULT = 1
    SATURATED = 2
    FROZEN = 4
    JUMP = 8
    NOT_FOLLOWING = 16
    SPEED_FAULT = 32


EXCLUDED = Problem.SATURATED | Problem.FROZEN | Problem.JUMP
"""Rows with these flags are left out of the fit."""


class AcquireConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    rate_s: float = Field(1.0, gt=0, description="sample period")
    max_rate_um_per_s: float = Field(
        0.5, gt=0, description="fastest thermal growth the spindle can show"
    )
    jump_um: float = Field(
        3.0, gt=0, description="allowed step on top of that (noise, quantisation)"
    )
    elastic_jump_um: float = Field(
        15.0, ge=0, description="extra allowed at a speed step (centrifugal growth)"
    )
    frozen_s: float = Field(900.0, gt=0, description="same reading this long: frozen")
    frozen_after_step_s: float = Field(
        120.0, gt=0, description="... or this long across a speed step"
    )
    abort_frozen_s: float = Field(300.0, ge=0, description="frozen this long: the recording stops")
    saturation_margin: float = Field(
        0.002, ge=0, lt=0.5, description="fraction of the range counted as its end"
    )
    abort_saturated_s: float = Field(30.0, ge=0)
    sensor_grace_s: float = Field(
        30.0, ge=0, description="a silent sensor this long (wall seconds) stops the recording"
    )
    speed_grace_s: float = Field(
        30.0, ge=0, description="a silent controller this long (wall seconds) stops the recording"
    )
    follow_tolerance_rpm: float | None = Field(
        None, gt=0, description="default: 3 % of max speed, >= 50 rpm"
    )
    follow_window_s: float = Field(
        30.0, ge=0, description="lag allowed around a programmed speed change"
    )
    follow_alarm_s: float = Field(60.0, gt=0)
    start_timeout_s: float = Field(
        3600.0,
        gt=0,
        description="stop if the spindle has not started this "
        "many wall seconds after the recording began (or resumed)",
    )
    probe_timeout_s: float = Field(
        900.0,
        gt=0,
        description="a probe stop without a new tool-setter "
        "measurement this long (wall seconds) stops the recording",
    )


@dataclass
class Sample:
    time_s: float
    speed_rpm: float | None
    sensor_um: float | None
    elongation_um: float | None
    commanded_rpm: float | None
    flags: Problem
    program_time_s: float | None


@dataclass
class Event:
    time_s: float
    problem: Problem
    message: str
    begins: bool = True


@dataclass
class Recording:
    path: Path
    rows: int
    rows_before: int
    events: list[Event] = field(default_factory=list)
    flagged: dict[str, int] = field(default_factory=dict)
    program_start_s: float | None = None
    complete: bool = False
    measurements: int = 0
    """Tool-setter measurements logged by this recording."""


HELD_RPM_SHARE = 0.002
"""A laser's measurement at speed goes on a row of its own when the speed moved by more than this
share of the top speed since the row before: the growth at speed goes with the square of the
speed, 0.4 % of it (0.06 um of 16 um at 27 000 rpm) for 0.2 % of the speed."""


class Recorder:
    """Record ``program`` on ``controller`` and ``sensor`` into ``path`` (resumes if it exists);
    ``sensor=None``: the controller's tool setter at the program's probe stops (a sparse log)."""

    def __init__(
        self,
        controller: Adapter,
        sensor: Sensor | None,
        path: str | Path,
        program: Program,
        *,
        max_rpm: float,
        config: AcquireConfig = AcquireConfig(),  # noqa: B008 - frozen: one default serves all
        metadata: dict[str, Any] | None = None,
        clock: Callable[[], float] = time.time,
        sleep: Callable[[float], None] = time.sleep,
        on_sample: Callable[[Sample, Recorder], None] | None = None,
        on_event: Callable[[Event], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        wall: Callable[[], float] = time.monotonic,
        start_now: Callable[[], bool] | None = None,
        at_speed: bool = False,
    ):
        self.controller, self.sensor = controller, sensor
        self.at_speed = bool(at_speed)
        """The tool setter measures the turning tool (a laser at the program's speed): the
        spindle keeps its speed through a stop, and a measurement goes on the row it came in,
        or, when the speed has changed since the row before (the program moved on after the
        cycle), on a row between the two at the speed held through the cycle."""
        self.path = Path(path)
        self.program = program
        self.max_rpm = float(max_rpm)
        self.cfg = config
        self.metadata = dict(metadata or {})
        self.stops = tuple(float(p) for p in program.probe_at_s)
        if sensor is None and not self.stops:
            raise ConfigError(
                "a recording with the tool setter alone needs a program with probe stops"
            )
        if sensor is not None and self.stops:
            raise ConfigError(
                "probe stops are for a recording with the tool setter alone (no sensor)"
            )
        if self.stops and not controller.can_read_measurement:
            raise ConfigError(
                f"the program stops for the tool setter, but the {controller.name} link reads "
                "no measurement: configure the controller's measurement variables"
            )
        if sensor is None:
            self.metadata[ELONGATION_COLUMN] = SPARSE  # empty on the rows without a measurement
            self.metadata["tool_setter"] = "at speed" if self.at_speed else "at rest"
        self.stops_done = 0
        """Probe stops whose measurement has come in."""
        self.holding = False
        """The program clock waits at a probe stop for the tool setter."""
        self.clock, self.sleep = clock, sleep
        self.on_sample, self.on_event = on_sample, on_event
        self.should_stop = should_stop or (lambda: False)
        # time-outs count wall seconds: a faster simulated clock must not shorten them
        self.wall = wall
        self.start_now = start_now or (lambda: False)
        self.tol_rpm = config.follow_tolerance_rpm or max(0.03 * self.max_rpm, 50.0)
        self._edges = np.cumsum([d for d, _ in program.segments])
        self._speeds = np.array([s for _, s in program.segments], dtype=float)
        self.events: list[Event] = []
        self._active: dict[Problem, float] = {}  # problem -> since (time_s)
        self.recent: list[float] = []  # last elongations, for a live sparkline
        self.last: Sample | None = None
        self._follow_told = False  # "not following" reported and not yet cleared
        # whatever else the controller publishes (temperatures, load) is logged too, for
        # `thermocomp fit --inputs`; a failed read of them is a NaN cell, never a lost row
        try:
            self.channels = tuple(controller.input_channels())
        except AdapterError:
            self.channels = ()
        self.columns = COLUMNS + tuple(c for c in self.channels if c not in COLUMNS)

    # -- the checks -----------------------------------------------------------

    def _event(self, t: float, problem: Problem, message: str, begins: bool = True) -> None:
        ev = Event(t, problem, message, begins)
        self.events.append(ev)
        if self.on_event is not None:
            self.on_event(ev)

    def _raise(self, t: float, problem: Problem, message: str) -> None:
        if problem not in self._active:
            self._active[problem] = t
            self._event(t, problem, message)

    def _clear(self, t: float, problem: Problem, message: str) -> None:
        if problem in self._active:
            del self._active[problem]
            self._event(t, problem, message, begins=False)

    def _lasted(self, problem: Problem, t: float) -> float:
        return t - self._active[problem] if problem in self._active else 0.0

    def commanded_between(self, t0: float, t1: float) -> np.ndarray:
        """Programmed speeds over program time [t0, t1] (0 after the end, and 0 last when a probe
        stop lies within: the cycle stops the spindle)."""
        d = self.program.duration_s
        i0 = int(np.searchsorted(self._edges, max(t0, 0.0), side="right"))
        i1 = int(np.searchsorted(self._edges, max(t1, 0.0), side="right"))
        speeds = list(
            self._speeds[min(i0, len(self._speeds) - 1) : min(i1, len(self._speeds) - 1) + 1]
        )
        if t1 >= d or (not self.at_speed and any(t0 <= p <= t1 for p in self.stops)):
            speeds.append(0.0)
        return np.array(speeds)

    # -- the loop -------------------------------------------------------------

    def run(self) -> Recording:
        cfg = self.cfg
        appender = RunLogAppender(
            self.path,
            self.columns,
            {
                **self.metadata,
                "start_epoch_s": f"{self.clock():.3f}",
                "columns": "flags: calibration.acquire.Problem",
            },
            clock=self.clock,
        )
        start = float(appender.metadata.get("start_epoch_s", self.clock()))
        program_start: float | None = None
        reference: float | None = None
        prev_value: float | None = None
        prev_speed: float | None = None
        same_since: float | None = None
        same_speed: float | None = None
        wall0 = last_sensor_ok = last_speed_ok = self.wall()
        paused_s = 0.0  # program time the machine spent in probe cycles: its program waited
        hold_wall: float | None = None  # wall time the program clock began to wait at a stop
        last_seq: int | None = None  # the tool-setter counter of the last value seen
        if appender.first_row is not None:
            if self.sensor is not None:
                reference = appender.first_row[3]
                prev_value = appender.last_row[3] if appender.last_row else None
            program_start = self._program_start_from(appender)
            if self.sensor is None and program_start is not None:
                paused_s = self._stops_from_log(program_start)
        rec = Recording(self.path, 0, appender.rows_before)
        next_t = self.clock()
        try:
            while True:
                if self.should_stop():
                    raise KeyboardInterrupt
                t = self.clock() - start
                flags = Problem(0)
                speed: float | None = None
                value: float | None = None
                try:
                    speed = abs(self.controller.read_speed())
                    last_speed_ok = self.wall()
                    self._clear(t, Problem.SPEED_FAULT, "controller answers again")
                except AdapterError as err:
                    flags |= Problem.SPEED_FAULT
                    self._raise(t, Problem.SPEED_FAULT, f"controller: {err}")
                    if self.wall() - last_speed_ok > cfg.speed_grace_s:
                        raise AcquisitionError(
                            f"no spindle speed from the controller for "
                            f"{self.wall() - last_speed_ok:.0f} s ({err})"
                        ) from err
                meas: float | None = None  # a new tool-setter measurement [um]
                ran = 1  # probe cycles since the last value seen: the counter's step
                if self.sensor is None:
                    try:
                        got = self.controller.read_measurement()
                        last_sensor_ok = self.wall()
                        self._clear(t, Problem.SENSOR_FAULT, "tool setter's variables answer again")
                        meas = None if got is None else float(got.elongation_um)
                        if got is not None:
                            if (
                                last_seq is not None and got.sequence > last_seq
                            ):  # a wrap counts one
                                ran = got.sequence - last_seq
                            last_seq = got.sequence
                    except AdapterError as err:
                        flags |= Problem.SENSOR_FAULT
                        self._raise(t, Problem.SENSOR_FAULT, f"tool setter: {err}")
                        if self.wall() - last_sensor_ok > cfg.sensor_grace_s:
                            raise AcquisitionError(
                                f"no tool-setter measurement read from the controller for "
                                f"{self.wall() - last_sensor_ok:.0f} s ({err})"
                            ) from err
                else:
                    try:
                        value = self.sensor.read_um()
                        last_sensor_ok = self.wall()
                        self._clear(t, Problem.SENSOR_FAULT, "sensor answers again")
                        lo_hi = self.sensor.range_um
                        if lo_hi is not None:
                            margin = cfg.saturation_margin * (lo_hi[1] - lo_hi[0])
                            if value <= lo_hi[0] + margin or value >= lo_hi[1] - margin:
                                raise SensorOverRangeError(
                                    f"reading {value:.2f} um at the end of the "
                                    f"range {lo_hi[0]:g}..{lo_hi[1]:g} um"
                                )
                        self._clear(t, Problem.SATURATED, "sensor back in range")
                    except SensorOverRangeError as err:
                        flags |= Problem.SATURATED
                        self._raise(t, Problem.SATURATED, f"sensor saturated: {err}")
                        if self._lasted(Problem.SATURATED, t) >= cfg.abort_saturated_s:
                            raise AcquisitionError(
                                f"sensor saturated for {self._lasted(Problem.SATURATED, t):.0f} s "
                                f"({err}): re-set the probe gap to mid-range"
                            ) from err
                    except AdapterError as err:
                        value = None
                        flags |= Problem.SENSOR_FAULT
                        self._raise(t, Problem.SENSOR_FAULT, f"sensor: {err}")
                        if self.wall() - last_sensor_ok > cfg.sensor_grace_s:
                            raise AcquisitionError(
                                f"no reading from the sensor for {self.wall() - last_sensor_ok:.0f} s "
                                f"({err}): is it unplugged?"
                            ) from err

                # the program starts when the spindle first turns
                if program_start is None and speed is not None and speed > IDLE_RPM:
                    program_start = t - min(cfg.rate_s, t)
                    if rec.rows == 0 and appender.rows_before == 0:
                        self._event(
                            t,
                            Problem(0),
                            "the spindle was already turning when the recording "
                            "started: the cold start and the program's first seconds are missed",
                        )
                    else:
                        self._event(t, Problem(0), "spindle started: program clock running")
                if program_start is None and self.start_now():
                    program_start = t
                    self._event(t, Problem(0), "program started by hand: program clock running")
                if program_start is None and self.wall() - wall0 > cfg.start_timeout_s:
                    raise AcquisitionError(
                        f"the spindle did not start within {cfg.start_timeout_s:.0f} s: "
                        "is the program loaded and cycle start pressed?"
                    )
                ptime = None if program_start is None else t - program_start - paused_s
                t_meas = t  # the row a measurement goes on: at the speed the cycle measured at
                held = (
                    0.0,
                    0.0,
                )  # that speed and the commanded one: at rest, or a laser's held speed
                if (
                    meas is not None
                    and not self.at_speed
                    and not (speed is not None and speed <= IDLE_RPM)
                ):
                    last_t = (
                        appender.last_row[0] if appender.last_row is not None else t - cfg.rate_s
                    )
                    t_meas = (last_t + t) / 2  # the spindle turns again: between the two samples
                elif (
                    meas is not None
                    and self.at_speed
                    and speed is not None
                    and appender.last_row is not None
                    and abs(speed - appender.last_row[1]) > HELD_RPM_SHARE * self.max_rpm
                ):
                    # the program moved on to another speed after the cycle: the value was taken at
                    # the speed held through it, whose growth at speed it includes
                    t_meas = (appender.last_row[0] + t) / 2
                    held = (appender.last_row[1], appender.last_row[4])
                if self.stops and ptime is not None and program_start is not None:
                    k = self.stops_done
                    if meas is not None and k < len(self.stops):
                        # the program calls the cycle at its stops only: a new value is the next
                        # stop's however late the recording saw it (a stalled computer), and a
                        # counter that moved by more than one says stops went by unread
                        missed = min(ran - 1, len(self.stops) - k - 1)
                        k += missed
                        behind = self.stops[k] - ptime
                        # the machine's program resumes at the stop once the value is in
                        paused_s = t_meas - program_start - self.stops[k]
                        ptime = t - program_start - paused_s
                        self.stops_done = k + 1
                        hold_wall = None
                        note = ""
                        if missed:
                            note += f"; {missed} stop(s) went by while the recording did not read: their values are lost"
                        if behind > cfg.follow_window_s + cfg.rate_s:
                            note += (
                                f"; the recording's clock was {behind:.0f} s behind the machine's"
                            )
                        self._event(
                            t,
                            Problem(0),
                            f"tool setter: {meas:+.1f} um (stop {k + 1}/{len(self.stops)}{note})",
                        )
                    elif meas is not None:
                        self._event(
                            t, Problem(0), f"tool setter: {meas:+.1f} um (not at a programmed stop)"
                        )
                    if self.stops_done < len(self.stops) and ptime >= self.stops[self.stops_done]:
                        ptime = self.stops[self.stops_done]  # the program waits for the cycle
                        if hold_wall is None:
                            hold_wall = self.wall()
                        elif self.wall() - hold_wall > cfg.probe_timeout_s:
                            raise AcquisitionError(
                                f"no tool-setter measurement {self.wall() - hold_wall:.0f} s after probe stop "
                                f"{self.stops_done + 1}/{len(self.stops)}: did the cycle alarm (setter not "
                                "tripped, no cold reference, growth out of range)?"
                            )
                self.holding = hold_wall is not None
                commanded = None
                if ptime is not None:
                    commanded = float(self.commanded_between(ptime, ptime)[-1])
                    if speed is not None:
                        window = self.commanded_between(ptime - cfg.follow_window_s, ptime)
                        if np.min(np.abs(window - speed)) > self.tol_rpm:
                            if Problem.NOT_FOLLOWING not in self._active:
                                self._active[Problem.NOT_FOLLOWING] = t
                            if self._lasted(Problem.NOT_FOLLOWING, t) >= cfg.follow_alarm_s:
                                flags |= Problem.NOT_FOLLOWING
                                if not self._follow_told:
                                    self._follow_told = True
                                    self._event(
                                        t,
                                        Problem.NOT_FOLLOWING,
                                        f"spindle not following the program: {speed:.0f} rpm where "
                                        f"{commanded:.0f} rpm is programmed (override not 100 %, feed "
                                        "hold, or another program?)",
                                    )
                        elif Problem.NOT_FOLLOWING in self._active:
                            del self._active[Problem.NOT_FOLLOWING]
                            if self._follow_told:
                                self._follow_told = False
                                self._event(
                                    t,
                                    Problem.NOT_FOLLOWING,
                                    "spindle follows the program again",
                                    begins=False,
                                )

                if value is not None:
                    if prev_value is not None and same_since is not None and value == prev_value:
                        # a live probe has noise, but a fine quantisation step can hold at a
                        # steady temperature; no change across a speed step is never physical
                        stepped = (
                            speed is not None
                            and same_speed is not None
                            and abs(speed - same_speed) > 0.1 * self.max_rpm
                        )
                        if t - same_since >= (cfg.frozen_after_step_s if stepped else cfg.frozen_s):
                            flags |= Problem.FROZEN
                            self._raise(
                                t,
                                Problem.FROZEN,
                                f"sensor frozen: {value:.3f} um unchanged for "
                                f"{t - same_since:.0f} s",
                            )
                            if self._lasted(Problem.FROZEN, t) >= cfg.abort_frozen_s:
                                raise AcquisitionError(
                                    f"sensor frozen at {value:.3f} um for "
                                    f"{t - same_since:.0f} s: check the amplifier and cable"
                                )
                    else:
                        same_since, same_speed = t, speed
                        self._clear(t, Problem.FROZEN, "sensor reading changes again")
                    if prev_value is not None and appender.last_row is not None:
                        dt = max(t - appender.last_row[0], 0.0)
                        allowed = cfg.jump_um + cfg.max_rate_um_per_s * dt
                        # speed and probe are read one after the other: a step may show in one
                        # sample's reading and the next sample's speed, so the program says too
                        near = (
                            self.commanded_between(ptime - 3 * cfg.rate_s, ptime + 3 * cfg.rate_s)
                            if ptime is not None
                            else np.zeros(1)
                        )
                        if (
                            speed is not None
                            and prev_speed is not None
                            and abs(speed - prev_speed) > 0.02 * self.max_rpm
                        ) or np.ptp(near) > 0.02 * self.max_rpm:
                            allowed += cfg.elastic_jump_um
                        if abs(value - prev_value) > allowed:
                            flags |= Problem.JUMP
                            self._event(
                                t,
                                Problem.JUMP,
                                f"sensor jumped {value - prev_value:+.2f} um in "
                                f"{dt:.1f} s (at most {allowed:.1f} um is physical): probe or bracket knocked?",
                            )
                    prev_value = value
                    if reference is None:
                        reference = value  # growth is counted from the cold start
                if speed is not None:
                    prev_speed = speed
                elong = None if value is None or reference is None else value - reference
                if self.sensor is None:
                    value = elong = meas  # the cycle's value is the growth from the cold reference
                sample = Sample(t, speed, value, elong, commanded, flags, ptime)
                self.last = sample
                rows: list[tuple[float, float, float | None, float | None, float]] = []
                if self.sensor is None:
                    if meas is not None and t_meas < t:
                        rows.append((t_meas, held[0], meas, meas, held[1]))
                    if speed is not None:
                        on_row = meas if t_meas == t else None
                        rows.append(
                            (t, speed, on_row, on_row, commanded if commanded is not None else 0.0)
                        )
                elif speed is not None and value is not None:
                    rows.append(
                        (t, speed, elong, value, commanded if commanded is not None else 0.0)
                    )
                if rows:
                    extra: tuple[float, ...] = ()
                    if len(self.columns) > len(COLUMNS):
                        try:
                            inputs = self.controller.read_inputs()
                        except AdapterError:
                            inputs = {}
                        extra = tuple(
                            float(inputs.get(c, math.nan)) for c in self.columns[len(COLUMNS) :]
                        )
                    for row_t, row_speed, row_elong, row_value, row_cmd in rows:
                        appender.append(
                            (
                                row_t,
                                row_speed,
                                math.nan if row_elong is None else row_elong,
                                math.nan if row_value is None else row_value,
                                row_cmd,
                                int(flags),
                                *extra,
                            )
                        )
                        rec.rows += 1
                        for p in Problem:
                            if flags & p and p.name is not None:  # a member has its name
                                rec.flagged[p.name] = rec.flagged.get(p.name, 0) + 1
                    if elong is not None:
                        self.recent.append(float(elong))
                        del self.recent[:-120]
                    if meas is not None:
                        rec.measurements += 1
                if self.on_sample is not None:
                    self.on_sample(sample, self)
                if (
                    ptime is not None
                    and ptime >= self.program.duration_s
                    and self.stops_done >= len(self.stops)
                ):
                    rec.complete = True
                    break
                next_t += cfg.rate_s
                wait = next_t - self.clock()
                if wait < -cfg.rate_s:
                    next_t = self.clock()  # fell behind (a slow link): no burst of catch-up reads
                elif wait > 0:
                    self.sleep(wait)
        finally:
            appender.close()
            rec.events = self.events
            rec.program_start_s = program_start
        return rec

    def _stops_from_log(self, program_start: float) -> float:
        """On resume: the stops whose measurement is logged, by the rule the recording follows
        (each value after the start is the next stop's; the program resumes at the stop on the
        measured row); the program time spent in cycles."""
        from compensator.io import read_run_log

        log = read_run_log(self.path)
        paused = 0.0
        for tm in log.time_s[log.measured]:
            k = self.stops_done
            if k < len(self.stops) and tm > program_start:
                paused = float(tm) - program_start - self.stops[k]
                self.stops_done += 1
        return paused

    def _program_start_from(self, appender: RunLogAppender) -> float | None:
        """On resume: the instant of the first logged row at speed."""
        from compensator.io import read_run_log

        log = read_run_log(self.path)
        moving = np.flatnonzero(np.abs(log.speed_rpm) > IDLE_RPM)
        if moving.size == 0:
            return None
        k = int(moving[0])
        return float(log.time_s[k - 1] if k > 0 else log.time_s[0] - self.cfg.rate_s)


def progress_fraction(sample: Sample, program: Program) -> float:
    if sample.program_time_s is None:
        return 0.0
    return float(min(max(sample.program_time_s / program.duration_s, 0.0), 1.0))


def sparkline(values: list[float], width: int = 60) -> str:
    """Unicode block sparkline of the last ``width`` values."""
    blocks = "▁▂▃▄▅▆▇█"
    v = values[-width:]
    if not v:
        return ""
    lo, hi = min(v), max(v)
    span = hi - lo if hi > lo else 1.0
    return "".join(blocks[min(int((x - lo) / span * 7.999), 7)] for x in v if math.isfinite(x))
