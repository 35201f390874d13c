"""Has the spindle changed since its model was fitted? A two-sided CUSUM on the model's own
misses. Pure: numbers in, a :class:`DriftState` out.

Each accepted probe measurement ``y`` gives the model's miss ``r = y - m``, where ``m`` is the
model's estimate without the observer's bias (the bias absorbs a drift: the innovations of the
fused estimate stay small while the model goes wrong). ``r`` is standardised by what the fit said
to expect, ``z = r / sd`` with ``sd = sqrt(rms_fit^2 + sigma^2)``: the fit's held-out RMS for the
speed band of the measurement (``fit.expected_error``) and the measurement's own sigma. Then
(Page 1954; Montgomery, *Introduction to Statistical Quality Control*, 7th ed., sec. 9.1)::

    S+ = max(0, S+ + z - k)        S- = max(0, S- - z - k)

with ``z`` limited to 3 sd, so one wild measurement cannot raise the alarm by itself. A drift is
declared when either exceeds ``h``. With ``k = 0.5`` and ``h = 5`` a sustained shift
of one ``sd`` is found after about 10 measurements (ARL1 ~ 10.4) while an unchanged model raises a
false alarm about once in 465 measurements (ARL0, independent normal misses; the misses of a
model are autocorrelated, so the real false-alarm rate is higher: the alarm is advice, never a
change of the offset). The change is dated at the first measurement after the sum last stood at
zero, and its size is the mean miss since then. The alarm clears when the sum falls below
``h/2`` (so a change near the threshold does not raise it again and again); each sum is held at
``2h`` at most, so that takes about ``1.5 h / k`` measurements once the misses are back to normal.

The detector restarts at known events, which must not count as a change: a new model (reload,
promotion, rollback) and a cold start or a restart after a long idle; the first ``grace``
measurements after a restart are left out (a start from equilibrium on a warm machine misses by
design until the estimate settles).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from .errors import ConfigError

K_DEFAULT = 0.5
"""Reference value [sd]: half the smallest shift worth finding quickly (one sd)."""
H_DEFAULT = 5.0
"""Decision interval [sd]."""
GRACE_DEFAULT = 2
"""Measurements left out after a restart."""
Z_LIMIT = 3.0
"""A miss counts this many sd at most (a robust CUSUM: one outlier cannot raise the alarm)."""


@dataclass(frozen=True)
class DriftConfig:
    k: float = K_DEFAULT
    h: float = H_DEFAULT
    grace: int = GRACE_DEFAULT

    def __post_init__(self) -> None:
        if not (
            math.isfinite(self.k)
            and self.k >= 0
            and math.isfinite(self.h)
            and self.h > 0
            and self.grace >= 0
        ):
            raise ConfigError(
                f"drift detector: k >= 0, h > 0 and grace >= 0 are needed, got k={self.k!r}, "
                f"h={self.h!r}, grace={self.grace!r}"
            )


@dataclass(frozen=True)
class DriftState:
    """The sums and what they have seen since the last restart."""

    high: float = 0.0
    """S+: evidence that the spindle grows more than the model says [sd]."""
    low: float = 0.0
    """S-: evidence that it grows less [sd]."""
    seen: int = 0
    """Measurements since the restart, the grace included."""
    high_from: float | None = None
    """Time of the first measurement of the current run of S+ above zero [s]."""
    low_from: float | None = None
    high_sum_um: float = 0.0
    """Sum of the misses since ``high_from`` [um]."""
    low_sum_um: float = 0.0
    high_n: int = 0
    low_n: int = 0
    detected: bool = False

    @property
    def statistic(self) -> float:
        """The larger of the two sums [sd]."""
        return max(self.high, self.low)

    def change(self) -> tuple[float, float, int] | None:
        """(its mean size [um], signed; when it began [s]; measurements since) of the side that
        crossed, or None while no drift is declared."""
        if not self.detected:
            return None
        if self.high >= self.low and self.high_n:
            return self.high_sum_um / self.high_n, float(self.high_from or 0.0), self.high_n
        if self.low_n:
            return self.low_sum_um / self.low_n, float(self.low_from or 0.0), self.low_n
        return None


def update(
    state: DriftState,
    miss_um: float,
    sd_um: float,
    time_s: float,
    config: DriftConfig = DriftConfig(),
) -> DriftState:
    """The state after one measurement whose model miss is ``miss_um`` (measured minus the
    model's estimate without bias) with standard deviation ``sd_um``, taken at ``time_s``. A
    non-finite miss or an sd that is not > 0 leaves the state as it was."""
    if not (
        math.isfinite(miss_um) and math.isfinite(sd_um) and sd_um > 0 and math.isfinite(time_s)
    ):
        return state
    if state.seen < config.grace:
        return replace(state, seen=state.seen + 1)
    # one wild measurement (a chip on the setter) is no drift: a miss counts 3 sd at most, so
    # three in a row are needed to cross h = 5
    z = min(max(miss_um / sd_um, -Z_LIMIT), Z_LIMIT)
    # held at 2h at most, so that a change that has ended clears after about h/k normal
    # measurements instead of as many as it lasted
    high = min(max(0.0, state.high + z - config.k), 2.0 * config.h)
    low = min(max(0.0, state.low - z - config.k), 2.0 * config.h)
    # each side's run: from the first measurement after it last stood at zero
    if high > 0.0:
        h_from, h_sum, h_n = (
            (state.high_from, state.high_sum_um + miss_um, state.high_n + 1)
            if state.high > 0
            else (time_s, miss_um, 1)
        )
    else:
        h_from, h_sum, h_n = None, 0.0, 0
    if low > 0.0:
        l_from, l_sum, l_n = (
            (state.low_from, state.low_sum_um + miss_um, state.low_n + 1)
            if state.low > 0
            else (time_s, miss_um, 1)
        )
    else:
        l_from, l_sum, l_n = None, 0.0, 0
    # raised above h, cleared below h/2: a change near the threshold does not flap the alarm
    stat = max(high, low)
    detected = stat > config.h or (state.detected and stat > 0.5 * config.h)
    return DriftState(
        high=high,
        low=low,
        seen=state.seen + 1,
        high_from=h_from,
        low_from=l_from,
        high_sum_um=h_sum,
        low_sum_um=l_sum,
        high_n=h_n,
        low_n=l_n,
        detected=detected,
    )


def miss_sd_um(fit_rms_um: float | None, sigma_um: float, floor_um: float = 0.1) -> float:
    """The standard deviation of a model's miss at a measurement: the fit's held-out RMS there
    and the measurement's sigma, in quadrature; at least ``floor_um`` (a fit that states a
    vanishing error would make every miss a drift)."""
    rms = fit_rms_um if fit_rms_um is not None and math.isfinite(fit_rms_um) else 0.0
    return max(math.hypot(rms, sigma_um), floor_um)
