"""The page's plot: :class:`History`, one point per ``history_every_s`` per spindle."""

from __future__ import annotations

import collections
import math
import threading
from typing import Any

from .states import finite

_Point = tuple[Any, ...]
"""time, speed, elongation, offset, alarm bits"""


class History:
    """Per spindle, one point per ``every_s`` over the last ``hours``: time (journal time),
    speed, elongation, offset held (the last values of the interval) and the alarms of the
    whole interval. Written by the service's thread, read (copied) by the server's."""

    FIELDS = ("time_s", "speed_rpm", "elongation_um", "offset_um", "alarm_bits")

    def __init__(self, hours: float, every_s: float):
        self.every_s = every_s
        self._n = max(2, math.ceil(hours * 3600.0 / every_s))
        self._points: dict[str, collections.deque[_Point]] = {}
        self._open: dict[
            str, list[Any]
        ] = {}  # the interval being gathered: [start, point, alarm bits]
        self._lock = threading.Lock()

    def add(
        self,
        name: str,
        time_s: float,
        speed_rpm: float | None,
        elongation_um: float | None,
        offset_um: float | None,
        alarm_bits: int,
    ) -> None:
        acc = self._open.get(name)
        if acc is None or time_s - acc[0] >= self.every_s:
            if acc is not None:
                self._commit(name, acc)
            self._open[name] = acc = [time_s, None, 0]
        acc[1] = (time_s, finite(speed_rpm), finite(elongation_um), finite(offset_um))
        acc[2] |= int(alarm_bits)

    def _commit(self, name: str, acc: list[Any]) -> None:
        with self._lock:
            q = self._points.setdefault(name, collections.deque(maxlen=self._n))
            q.append((*acc[1], acc[2]))

    def series(self, name: str, since_s: float | None = None) -> dict[str, list[Any]] | None:
        """The points after ``since_s`` (all without), column by column, the open interval's
        latest values last; None for an unknown spindle."""
        with self._lock:
            if name not in self._points and name not in self._open:
                return None
            rows = list(self._points.get(name, ()))
        acc = self._open.get(name)
        if acc is not None and acc[1] is not None:
            rows.append((*acc[1], acc[2]))
        if since_s is not None:
            rows = [r for r in rows if r[0] > since_s]
        return {f: [r[i] for r in rows] for i, f in enumerate(self.FIELDS)}

    def names(self) -> list[str]:
        with self._lock:
            return sorted(set(self._points) | set(self._open))
