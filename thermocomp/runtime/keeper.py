"""One spindle's state on disk: restore at start, save when due with back-off, and the downtime
measured again when the clock was wrong at the start.

- start-up: the saved state is advanced through the downtime as an idle spindle; missing, older
  than ``max_state_age_s`` or corrupt (kept aside as ``*.corrupt-<time>``): a cold start;
- on a simulated clock (``time_scale``, the virtual machine tool) the state also records the real
  wall time and the scale: the downtime is the real time since the save times the scale, and
  "ahead of the clock" compares real times (the simulated wall clock runs ahead of the real one;
  a state without these fields is taken as before);
- a state saved ahead of the clock (the clock was set back, or ran ahead at the save) raises
  CLOCK_STEP: up to ``DOWNTIME_RECHECK_S`` ahead (a box that booted with its clock where it
  stopped) the downtime is taken as 0 s until the clock's first step forward measures it; further
  ahead its age is unknown, and the start is cold;
- a held offset saved beyond the clamp is restored as the clamp's edge;
- a state save that cannot be written raises an alarm naming the file and the OS error and is
  retried with back-off; compensation goes on; no save for ``faults.state_stale_s``: STATE_STALE;
- the first forward clock step within ``DOWNTIME_RECHECK_S`` of a restore measures the downtime
  again (a box without a real-time clock boots with its clock behind until time
  synchronisation steps it).
"""

from __future__ import annotations

import itertools
import logging
import math
import re
import stat
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from compensator.errors import ConfigError, ModelError, ModelFileError
from compensator.estimate import Estimate, EstimateState
from compensator.io import load_state, quarantine, save_state
from compensator.io.history import ModelHistory, fit_summary
from compensator.modelbase import saved_numbers

from .alarms import Alarm
from .config import SpindleConfig
from .events import event

log = logging.getLogger("thermocomp.runtime")

_SHA256 = re.compile(r"[0-9a-f]{64}")

CLOCK_STEP_S = 2.0
"""A jump of the wall clock against the monotonic clock larger than this is a clock step."""

DOWNTIME_RECHECK_S = 3600.0
"""For this long after a restore [s], the first forward clock step measures the downtime again
(a box that booted with its clock behind, until time synchronisation steps it)."""


SIM_FIELDS = ("saved_wall_s", "input_wall_s", "cold_start_unsettled_until_wall_s")
"""A state's times on the simulated wall clock: moved onto the restarted service's clock."""


MAX_SAVED_LATELY = 4096
"""Entries of the speeds lately a state file may hold (a service writes at most 256)."""


def _speeds_lately(
    value: Any, saved_wall: float, shift: float = 0.0
) -> tuple[tuple[float, float], ...]:
    """The saved speeds lately, checked: absent (an older state) is none; otherwise a list of
    [wall time, |rpm|] pairs, at most :data:`MAX_SAVED_LATELY`, times in order and not after
    the save, speeds at or above 0; :class:`ModelError` otherwise (the state is corrupt). The
    times move by ``shift`` onto a simulated clock, as the save's own time did."""
    if value is None:
        return ()
    if not isinstance(value, list) or len(value) > MAX_SAVED_LATELY:
        raise ModelError(
            f"saved speeds_lately is not a list of at most {MAX_SAVED_LATELY} [time, rpm] pairs"
        )
    if not all(isinstance(p, list) and len(p) == 2 for p in value):
        raise ModelError("saved speeds_lately holds something other than [time, rpm] pairs")
    times = tuple(t + shift for t in saved_numbers("speeds_lately", [p[0] for p in value], 1e11))
    speeds = saved_numbers("speeds_lately", [p[1] for p in value], 1e7)
    if any(b < a for a, b in itertools.pairwise(times)) or (times and times[-1] > saved_wall + 1.0):
        raise ModelError("saved speeds_lately: times out of order or after the save")
    if any(v < 0 for v in speeds):
        raise ModelError("saved speeds_lately holds a negative speed")
    return tuple(zip(times, speeds))


class ScaledWall:
    """The wall clock of a service on a simulated clock: the real wall time at the start plus
    the simulated seconds since (``sim``); ``real`` is the real wall clock, ``scale`` the
    simulated seconds per real second. The state keeper saves the real time too, so a restart
    can tell the real downtime."""

    def __init__(self, sim: Callable[[], float], real: Callable[[], float], scale: float):
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError("time scale must be > 0")
        self.real, self.scale, self._sim = real, float(scale), sim
        self._w0 = real()

    def __call__(self) -> float:
        return self._w0 + self._sim()


@dataclass(frozen=True)
class Restored:
    """A saved state that fits, advanced through the downtime."""

    est: EstimateState
    held_um: float
    downtime_s: float
    unsettled_until_wall_s: float | None
    """An unsettled cold start's end (wall time) the state carried: a restart does not settle it."""
    speeds_lately: tuple[tuple[float, float], ...] = ()
    """The speeds lately (wall time, |rpm|), oldest first: a restart still knows the spindle ran
    faster than validation saw."""


@dataclass(frozen=True)
class Cold:
    """No saved state fits: a cold start, and why."""

    reason: str


class StateKeeper:
    """The state file: restore, save with back-off, and the alarms of saving."""

    def __init__(
        self,
        cfg: SpindleConfig,
        path: Path,
        counters: dict[str, int],
        wall: Callable[[], float] | None = None,
    ):
        self.cfg = cfg
        # the real wall clock and the time scale: a simulated wall clock saves the real time too
        self.real_wall: Callable[[], float] | None = (
            wall.real if isinstance(wall, ScaledWall) else wall
        )
        self.time_scale = wall.scale if isinstance(wall, ScaledWall) else 1.0
        # set by the service's clean stop for its last save: `thermocomp status` tells a
        # clean stop from a kill by it
        self.stopping = False
        self.path = path
        self.counters = counters
        self.last_save_s = -math.inf
        self.last_good_save_s: float | None = None
        self.failures = 0
        self.next_try_s = -math.inf
        self.error: str | None = None
        self.stale = False
        self.alarms = Alarm.NONE  # of the last save

    def follow(self, old: StateKeeper, *, same_model: bool) -> None:
        """Go on from ``old`` (a reload): its save bookkeeping; another model's state is saved
        at once."""
        self.last_save_s = old.last_save_s if same_model else -math.inf
        self.last_good_save_s, self.failures = old.last_good_save_s, old.failures
        self.next_try_s, self.error = old.next_try_s, old.error
        self.stale, self.alarms = old.stale, old.alarms

    def restore(
        self, estimate: Estimate, digest: str, now_wall: float
    ) -> tuple[Restored | Cold, Alarm, Any]:
        """The saved state advanced through the downtime, or why there is none that fits; the
        start-up alarms; and the parsed saved state (for the downtime re-check). A corrupt file
        is moved aside and never crashes the start."""
        cfg = self.cfg
        try:
            saved = load_state(self.path)
            if saved is None:
                return Cold("no saved state"), Alarm.NONE, None
            sha = saved.get("model_sha256")
            if not (isinstance(sha, str) and _SHA256.fullmatch(sha)):
                raise ModelFileError(f"model_sha256 is {str(sha)[:70]!r}, not a digest")
            if sha != digest:
                return Cold("saved state belongs to another model"), Alarm.NONE, None
            saved_wall = saved_numbers("saved_wall_s", [saved["saved_wall_s"]], 1e11)[0]
            held = saved_numbers("offset_um", [saved.get("offset_um", 0.0)])[0]
            if saved_wall <= 0:
                raise ModelFileError(f"saved_wall_s {saved_wall:g} is not a time")
            real = self._real_age(saved, now_wall)
            shift = 0.0
            if real is not None:
                # a simulated clock: the state's times moved onto this run's simulated clock,
                # which started at the real time of the start
                age = real * self.time_scale
                shift = (now_wall - age) - saved_wall
                saved = {
                    k: (v + shift if k in SIM_FIELDS and _number(v) else v)
                    for k, v in saved.items()
                }
                saved_wall = now_wall - age
            parsed = estimate.parse_saved(saved)
            lately = _speeds_lately(saved.get("speeds_lately"), saved_wall, shift)
        except (
            ModelError,
            ValueError,
            TypeError,
            KeyError,
            AttributeError,
            RecursionError,
            OverflowError,
        ) as err:
            stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(now_wall))
            moved = quarantine(self.path, stamp)
            event(
                "state_corrupt",
                cfg.name,
                "%s: state file %s is corrupt (%s); kept as %s",
                cfg.name,
                self.path,
                str(err)[:200],
                moved or "(could not be moved)",
                level=logging.ERROR,
                path=str(self.path),
                kept_as=moved,
            )
            return Cold("corrupt state file"), Alarm.STATE_CORRUPT, None
        age = now_wall - saved_wall
        # how far ahead of the clock the state was saved, in real seconds (on a simulated
        # clock the simulated wall time of the save runs ahead of the real one)
        ahead = -age if real is None else -real
        if age > cfg.max_state_age_s:
            return Cold(f"saved state is {age / 3600:.1f} h old"), Alarm.NONE, None
        alarms = Alarm.NONE
        if ahead > CLOCK_STEP_S:
            # saved "in the future": the clock was set back since, or ran ahead at the save;
            # either way the downtime is unknown
            alarms = Alarm.CLOCK_STEP
            if ahead > DOWNTIME_RECHECK_S:
                # far beyond a clock that boots where it stopped: the state's age, and so
                # whether it is younger than max_state_age_s, cannot be known
                far = _duration(ahead)
                event(
                    "clock_step",
                    cfg.name,
                    "%s: the state was saved %s ahead of the clock: its age is unknown, "
                    "the state is not used",
                    cfg.name,
                    far,
                    level=logging.ERROR,
                    step_s=round(-ahead, 3),
                    path=str(self.path),
                )
                return Cold(f"saved state is dated {far} ahead of the clock"), alarms, None
            event(
                "clock_step",
                cfg.name,
                "%s: the state was saved %.0f s ahead of the clock: the downtime is taken as "
                "0 s and measured again at the clock's first step forward",
                cfg.name,
                ahead,
                level=logging.WARNING,
                step_s=round(-ahead, 3),
                path=str(self.path),
            )
            age = min(age, 0.0)  # on a simulated clock too: the downtime is unknown
        downtime = max(0.0, age)
        # the spindle stood still while we were down: the model's own cooling; the input
        # model's state is advanced once the inputs are read
        est = estimate.resume(parsed, downtime, now_wall, cfg.max_state_age_s)
        unsettled = saved.get("cold_start_unsettled_until_wall_s")
        until = (
            float(unsettled)
            if isinstance(unsettled, (int, float))
            and not isinstance(unsettled, bool)
            and math.isfinite(unsettled)
            and unsettled > now_wall
            else None
        )
        # an old version saved a foreign value beyond the clamp, or the clamp was lowered since:
        # the clamp's edge counts as held (and is journaled), as for a value read back
        limit = cfg.shaping.max_offset_um
        held = min(max(held, -limit), limit)
        return Restored(est, held, downtime, until, lately), alarms, (parsed, saved_wall)

    def _real_age(self, saved: Mapping[str, Any], now_wall: float) -> float | None:
        """Real seconds since the save, where this run or the save was on a simulated clock
        and the state recorded the real time (a state from before: None, taken as before)."""
        real_saved, scale = saved.get("saved_real_wall_s"), saved.get("time_scale")
        if real_saved is None or scale is None:
            return None  # an older state file: its saved_wall_s only
        real_saved = saved_numbers("saved_real_wall_s", [real_saved], 1e11)[0]
        scale = saved_numbers("time_scale", [scale], 1e4)[0]
        if real_saved <= 0 or scale <= 0:
            raise ModelFileError(f"saved_real_wall_s {real_saved:g} or time_scale {scale:g} wrong")
        if scale == 1.0 and self.time_scale == 1.0:
            return None  # real time both: saved_wall_s is the real time, as before
        real_now = self.real_wall() if self.real_wall is not None else now_wall
        return real_now - real_saved

    def due(self, now: float) -> bool:
        """A save is due and not backing off."""
        return now - self.last_save_s >= self.cfg.state_save_every_s and now >= self.next_try_s

    def save(self, now: float, record: Mapping[str, Any]) -> bool:
        """Save ``record``; a failure is an alarm and a retry with back-off, never an exception."""
        body = dict(record)
        if self.real_wall is not None:
            # the real time too: on a simulated clock, saved_wall_s runs ahead of it
            body["saved_real_wall_s"] = self.real_wall()
            body["time_scale"] = self.time_scale
        body["clean_stop"] = self.stopping
        try:
            save_state(self.path, body)
        except (OSError, ValueError) as err:
            self.counters["state_save_failed"] += 1
            self.failures += 1
            faults = self.cfg.faults
            self.next_try_s = now + min(
                faults.max_write_backoff_s, faults.state_retry_s * 2 ** (self.failures - 1)
            )
            why = f"{self.path}: {getattr(err, 'strerror', None) or err}"  # not the temp file
            if why != self.error:
                event(
                    "state_save_failed",
                    self.cfg.name,
                    "%s: cannot save the state: %s; compensation goes on, retrying",
                    self.cfg.name,
                    why,
                    level=logging.ERROR,
                    path=str(self.path),
                    error=why,
                )
            self.error = why
            return False
        self.last_save_s = now
        self.last_good_save_s = now
        if self.error is not None:
            event(
                "state_saved_again",
                self.cfg.name,
                "%s: state saved again after %d failure(s)",
                self.cfg.name,
                self.failures,
                path=str(self.path),
            )
        self.error, self.failures, self.stale = None, 0, False
        self.next_try_s = -math.inf
        return True

    def judge(self, now: float, first_s: float | None) -> Alarm:
        """The alarms of saving at ``now``: STATE_SAVE_FAILED while the last save failed, and
        STATE_STALE once no save has landed for ``faults.state_stale_s``."""
        if self.error is None:
            self.alarms = Alarm.NONE
            return self.alarms
        alarms = Alarm.STATE_SAVE_FAILED
        since = self.last_good_save_s if self.last_good_save_s is not None else first_s
        if since is not None and now - since > self.cfg.faults.state_stale_s:
            alarms |= Alarm.STATE_STALE
            if not self.stale:
                self.stale = True
                event(
                    "state_stale",
                    self.cfg.name,
                    "%s: no state saved for %.0f s: %s",
                    self.cfg.name,
                    now - since,
                    self.error,
                    level=logging.CRITICAL,
                    path=str(self.path),
                    error=self.error,
                )
        self.alarms = alarms
        return alarms


@dataclass(frozen=True)
class SavedView:
    """What a spindle's state file says for people while the service is not running."""

    held_um: float
    """The offset the control held at the last save [µm]."""
    saved_wall_s: float
    """When it was saved: the real wall time (on a simulated clock too)."""
    clean_stop: bool | None
    """Saved by a clean stop; False: by a cycle (then killed, crashed, or a stop could not save);
    None: a state of an older version, which does not say."""


def state_file(state_dir: Path, spindle: str) -> Path:
    """A spindle's state file in ``state_dir``."""
    return Path(state_dir) / f"{spindle}.state.json"


def read_saved(path: Path) -> SavedView | None:
    """A spindle's saved state read as the service restores it, for people (nothing is moved
    or written); None where there is none. ``ModelFileError`` for one that cannot be read, or a
    link, which is never followed."""
    try:
        before = path.lstat()
    except FileNotFoundError:
        return None
    except OSError as err:
        raise ModelFileError(f"{path}: unreadable state file ({err.strerror or err})") from err
    if stat.S_ISLNK(before.st_mode):
        raise ModelFileError(f"{path}: a link, not a state file: not followed")
    saved = load_state(path)
    if saved is None:
        return None  # removed since
    try:
        after = path.lstat()
    except OSError:
        after = None
    if after is None or (after.st_dev, after.st_ino) != (before.st_dev, before.st_ino):
        raise ModelFileError(f"{path}: replaced while it was read")
    try:
        wall = saved.get("saved_real_wall_s", saved["saved_wall_s"])
        saved_wall = saved_numbers("saved_wall_s", [wall], 1e11)[0]
        held = saved_numbers("offset_um", [saved.get("offset_um", 0.0)])[0]
    except (ModelError, KeyError, TypeError, ValueError) as err:
        raise ModelFileError(f"{path}: {str(err)[:200]}") from err
    clean = saved.get("clean_stop")
    return SavedView(held, saved_wall, clean if isinstance(clean, bool) else None)


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _duration(seconds: float) -> str:
    """A long time for people: days (or years) rather than seconds."""
    days = seconds / 86400.0
    return f"{days / 365.25:.1f} years" if days >= 365.25 else f"{days:.1f} days"


Replay = tuple[float, float, float, float, Any, "str | None"]
"""One cycle since a restore: speed, dt, clock time, wall time, inputs, input error."""


class DowntimeCheck:
    """Clock steps, and the downtime measured again after the first forward step soon after a
    restore: where it was longer, the estimate restarts from the saved state advanced through
    it, then is stepped again through every cycle since the start."""

    def __init__(self, name: str, anchor_s: float, max_state_age_s: float):
        self.name = name
        self.anchor_s = anchor_s
        self.max_state_age_s = max_state_age_s
        self.skew_s: float | None = None
        # after a restore: the saved state, its wall time, the downtime applied, the clock and
        # wall times of the restore, and the cycles since
        self.restored: tuple[Any, float, float, float, float] | None = None
        self.since: list[Replay] | None = None

    def follow(self, old: DowntimeCheck, *, same_model: bool) -> None:
        self.skew_s = old.skew_s
        if same_model:
            self.restored, self.since = old.restored, old.since

    def started(self, saved: tuple[Any, float], downtime_s: float, now: float, wall: float) -> None:
        self.restored, self.since = (saved[0], saved[1], downtime_s, now, wall), []

    def measured(self) -> None:
        """The estimate has been measured: it is not re-run from the start."""
        self.since = None

    def record(self, cycle: Replay) -> None:
        """A cycle stepped, kept for a clock found wrong at the start."""
        if self.since is None or self.restored is None:
            return
        self.since.append(cycle)
        if cycle[2] - self.restored[3] > DOWNTIME_RECHECK_S:
            self.since = None

    def clock_step(
        self,
        now: float,
        wall_now: float,
        again: Callable[[float, float], None],
    ) -> Alarm:
        """CLOCK_STEP when the wall clock jumped against the monotonic one; a forward step
        soon after a restore calls ``again(now, wall_now)``."""
        skew = wall_now - (self.anchor_s + now)
        prev, self.skew_s = self.skew_s, skew
        if prev is None or abs(skew - prev) <= CLOCK_STEP_S:
            return Alarm.NONE
        event(
            "clock_step",
            self.name,
            "%s: the wall clock stepped by %+.1f s; the journal keeps its monotonic time",
            self.name,
            skew - prev,
            level=logging.WARNING,
            step_s=round(skew - prev, 3),
        )
        if skew > prev and self.since is not None:
            again(now, wall_now)
        return Alarm.CLOCK_STEP

    def rerun(
        self, estimate: Estimate, est: EstimateState, now: float, wall_now: float
    ) -> EstimateState:
        """The estimate with the downtime measured again on the corrected clock (once); ``est``
        where the downtime was not longer or cannot be applied."""
        assert self.restored is not None and self.since is not None
        parsed, saved_wall, applied, started, restore_wall = self.restored
        since, self.since = self.since, None  # once
        start_wall = wall_now - (now - started)
        downtime = start_wall - saved_wall
        if downtime <= applied + CLOCK_STEP_S:
            return est
        before = est.estimate_um
        try:
            new = estimate.resume(parsed, downtime, start_wall, self.max_state_age_s)
            for speed, dt, t, wall, inputs, error in since:
                new, _ = estimate.step(
                    new,
                    speed,
                    dt,
                    now_s=t,
                    wall_s=wall + (start_wall - restore_wall),
                    inputs=inputs,
                    input_error=error,
                )
        except ModelError as err:
            log.warning("%s: the downtime could not be applied again: %s", self.name, err)
            return est
        event(
            "downtime_corrected",
            self.name,
            "%s: the clock was wrong at the start: the downtime was %.0f s, not %.0f s; the "
            "saved state advanced through it again: S %.2f -> %.2f um",
            self.name,
            downtime,
            applied,
            before,
            new.estimate_um,
            level=logging.WARNING,
            downtime_s=round(downtime, 3),
            applied_s=round(applied, 3),
            elongation_um=new.estimate_um,
        )
        return new


def record_in_use(
    history: ModelHistory,
    cfg: SpindleConfig,
    model: Any,
    digest: str,
    reason: str,
    wall_s: float,
) -> None:
    """Keep the model in the spindle's history when it is not the one recorded in use (a
    promotion or a rollback recorded it already). The history is a record: failing to write it
    never stops compensation."""
    try:
        live = history.live()
        if live is None or live.digest != digest:
            history.add(
                "in_use", cfg.model, reason=reason, at_wall_s=wall_s, fit=fit_summary(model)
            )
    except (OSError, ConfigError) as err:
        event(
            "history_failed",
            cfg.name,
            "%s: the model history %s could not be written: %s; compensation goes on",
            cfg.name,
            history.directory,
            getattr(err, "strerror", None) or err,
            level=logging.WARNING,
            path=str(history.directory),
        )
