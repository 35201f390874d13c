"""The alarm bits a spindle's cycle raises: journaled as one integer, named in the status."""

from __future__ import annotations

import enum

from compensator.io.journal import ALARM_COLD_START


class Alarm(enum.IntFlag):
    NONE = 0
    SPEED_READ_FAILED = 1
    IDLE_ASSUMED = 2
    OVER_RANGE = 4
    LINK_DOWN = 8
    WRITE_REJECTED = 16
    COLD_START = ALARM_COLD_START
    OUTAGE = 64
    NOT_READY = 128
    INPUT_FALLBACK = 256
    OFFSET_MISMATCH = 512
    WRITE_BACKOFF = 1024
    JOURNAL_FAILED = 2048
    STATE_SAVE_FAILED = 4096
    STATE_STALE = 8192
    STATE_CORRUPT = 16384
    CLOCK_STEP = 32768
    RELOAD_FAILED = 65536
    INPUTS_EXTRAPOLATED = 131072
    PROBE_REJECTED = 262144
    OBSERVER_STALE = 524288
    PROBE_FAILED = 1048576
    CUTTING_SIGNAL_FAILED = 2097152
    ESTIMATE_REFUSED = 4194304
    EXPECTED_ERROR_HIGH = 8388608
    MODEL_DRIFT = 16777216
    # a cold start (no usable saved state) whose first speed read shows the spindle turning (at
    # least TURNING_MIN_RPM, or 1 % of the calibrated top): the machine is probably warm, the
    # estimate starts from rest. Raised until cold_start_settle_taus (3) x the model's slowest
    # time constant have passed (the start's error decayed to exp(-k), 5 %), or until the observer
    # takes a measurement (accepted, or the bias restarted from it); a restart does not clear it.
    COLD_START_TURNING = 33554432
    # the observer's correction (estimate minus the model's free run) is at max_correction_um, or
    # a source's last measurement was cut to its max_source_move_um: measurements are held back
    OBSERVER_BOUND = 67108864
    # the offset was written (or confirmed) but the sign of life was not: a life counter or
    # valid flag refused, missing or of a type that cannot hold it. The counter stays where the
    # control last took it, so the control's watch reacts as if thermocomp had stopped
    SIGN_OF_LIFE = 134217728


UNREAD = Alarm.SPEED_READ_FAILED | Alarm.IDLE_ASSUMED
"""The speed of this cycle was not read: held from the last read, or idle assumed."""
