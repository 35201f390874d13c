"""The runtime's journal: one run-log file per spindle and UTC day, a row per cycle."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

from .runlog import header_text


class Journal:
    """The runtime's journal: the common run-log format, one file per UTC day, flushed per row."""

    COLUMNS = ("time_s", "speed_rpm", "predicted_um", "offset_um", "written", "flags", "alarms")

    def __init__(self, directory: str | os.PathLike[str], name: str, metadata: Mapping[str, Any]):
        self.directory = Path(directory)
        self.name = name
        self.metadata = dict(metadata)
        self._fh: IO[str] | None = None
        self._day: str | None = None
        self._last_t = -math.inf

    def path_for(self, day: str) -> Path:
        return self.directory / f"{self.name}-{day}.csv"

    def write(self, wall_s: float, speed_rpm: float, predicted_um: float, offset_um: float,
              written: bool, flags: int, alarms: int) -> None:
        day = time.strftime("%Y-%m-%d", time.gmtime(wall_s))
        if day != self._day:
            self.close()
            self.directory.mkdir(parents=True, exist_ok=True)
            path = self.path_for(day)
            new = not path.exists() or path.stat().st_size == 0
            self._fh = open(path, "a", encoding="utf-8")
            if new:
                self._fh.write(header_text(self.COLUMNS, self.metadata))
            self._day = day
        t = max(wall_s, self._last_t + 1e-3)  # the run-log format needs increasing time
        self._last_t = t
        assert self._fh is not None
        self._fh.write(f"{t:.3f},{speed_rpm:.9g},{predicted_um:.9g},{offset_um:.9g},"
                       f"{int(written)},{int(flags)},{int(alarms)}\n")
        self._fh.flush()

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None
