"""All file I/O of thermocomp in one place: run logs and model files.

Run-log format (shared by calibration, replay, the runtime journal and the
simulator)::

    # spindle_id: sp1            <- optional '# key: value' metadata lines
    time_s,speed_rpm,elongation_um,ambient_c
    0,0,0.00,22.0
    60,3000,1.52,22.0

``time_s`` and ``speed_rpm`` are required; ``elongation_um`` is optional; any
other column is kept. Time must strictly increase. Gaps are allowed and
reported. Every error names the file and line.

Model files are the JSON of :class:`~compensator.model.ThermalModel` with a
``sha256`` over the canonical content, so a hand-edited file is refused.
All writes are atomic: temporary file, fsync, rename.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import tempfile
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from .errors import ConfigError, ModelError, ModelFileError, RunLogError, UnstableModelError
from .model import MODEL_FORMAT, ThermalModel

REQUIRED_COLUMNS = ("time_s", "speed_rpm")
ELONGATION_COLUMN = "elongation_um"
GAP_FACTOR = 5.0
"""A step longer than this many median steps is reported as a gap."""


@dataclass(frozen=True)
class Gap:
    line: int
    start_s: float
    duration_s: float


@dataclass(frozen=True)
class RunLog:
    """A parsed run log. Arrays are float64 and share one length."""

    time_s: np.ndarray
    speed_rpm: np.ndarray
    elongation_um: np.ndarray | None = None
    extras: Mapping[str, np.ndarray] = field(default_factory=dict)
    metadata: Mapping[str, str] = field(default_factory=dict)
    gaps: tuple[Gap, ...] = ()
    source: str | None = None

    def __len__(self) -> int:
        return int(self.time_s.size)

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1] - self.time_s[0]) if len(self) else 0.0

    @property
    def median_dt_s(self) -> float:
        return float(np.median(np.diff(self.time_s))) if len(self) > 1 else 0.0

    def line_of(self, row: int) -> int | None:
        """File line of data row ``row``, when the log came from a file."""
        if self.source is None:
            return None
        return _line_of_row(self.source, row)


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "w") -> Iterator[IO[Any]]:
    """Write to a temporary file beside ``path``, fsync, then rename over it.

    A crash at any moment leaves either the old file or the new one, never a
    partial file.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):
        dfd = os.open(target.parent, os.O_DIRECTORY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


# -- run logs -----------------------------------------------------------------


def _is_skipped(line: str) -> bool:
    s = line.strip()
    return not s or s.startswith("#")


def _lines_of_rows(path: str, rows: list[int]) -> dict[int, int]:
    """1-based file lines of data rows (0-based), skipping comments and blanks."""
    wanted = set(rows)
    found: dict[int, int] = {}
    last = max(wanted, default=-1)
    seen = -1  # the header is row -1
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, start=1):
            if _is_skipped(line):
                continue
            if seen in wanted:
                found[seen] = lineno
            if seen >= last:
                break
            seen += 1
    return found


def _line_of_row(path: str, row: int) -> int | None:
    return _lines_of_rows(path, [row]).get(row)


def _first_ragged_line(path: str) -> tuple[int | None, int, int]:
    """(line, fields, header fields) of the first row whose width differs from the header."""
    width = None
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, start=1):
            if _is_skipped(line):
                continue
            fields = len(line.split("#", 1)[0].rstrip("\r\n").split(","))
            if width is None:
                width = fields
            elif fields != width:
                return lineno, fields, width
    return None, 0, width or 0


def _read_metadata(path: str) -> tuple[dict[str, str], int | None]:
    """Leading '# key: value' lines, and the line number of the header."""
    meta: dict[str, str] = {}
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, start=1):
            s = line.strip()
            if not s:
                continue
            if s.startswith("#"):
                key, sep, value = s.lstrip("#").partition(":")
                if sep and key.strip():
                    meta[key.strip()] = value.strip()
                continue
            return meta, lineno
    return meta, None


def read_run_log(path: str | os.PathLike[str]) -> RunLog:
    """Read a run log; raise :class:`RunLogError` naming file and line on any fault."""
    import pandas as pd  # heavy; only the reader needs it

    src = os.fspath(path)
    try:
        meta, header_line = _read_metadata(src)
    except OSError as err:
        raise RunLogError(f"cannot read: {err.strerror or err}", src) from err
    except UnicodeError as err:
        raise RunLogError("not a text file", src) from err
    if header_line is None:
        raise RunLogError("no header line (expected time_s,speed_rpm[,elongation_um,...])", src)
    try:
        with warnings.catch_warnings():
            # a row longer than the header must not silently become an index
            warnings.simplefilter("error", pd.errors.ParserWarning)
            df = pd.read_csv(
                src,
                comment="#",
                skip_blank_lines=True,
                skipinitialspace=True,
                index_col=False,
                engine="c",
                low_memory=False,
            )
    except pd.errors.EmptyDataError as err:
        raise RunLogError("empty file", src) from err
    except (pd.errors.ParserError, pd.errors.ParserWarning, ValueError, UnicodeError) as err:
        line, fields, width = _first_ragged_line(src)
        if line is not None:
            raise RunLogError(
                f"malformed CSV: {fields} fields where the header has {width}", src, line
            ) from err
        msg = str(err).strip().splitlines()[-1]
        raise RunLogError(f"malformed CSV: {msg}", src) from err
    df.columns = [str(c).strip() for c in df.columns]
    dupes = sorted({c for c in df.columns if list(df.columns).count(c) > 1})
    if dupes:
        raise RunLogError(f"duplicate column(s) {', '.join(dupes)}", src, header_line)
    missing = [c for c in REQUIRED_COLUMNS if c not in df.columns]
    if missing:
        raise RunLogError(
            f"missing column(s) {', '.join(missing)} in header {','.join(df.columns)}",
            src,
            header_line,
        )
    if len(df) == 0:
        raise RunLogError("no data rows", src)

    def numeric(col: str, allow_nan: bool = False) -> np.ndarray:
        raw = df[col]
        values = pd.to_numeric(raw, errors="coerce").to_numpy(dtype=float)
        bad = ~np.isfinite(values)
        if bad.any() and not allow_nan:
            row = int(np.flatnonzero(bad)[0])
            cell = raw.iloc[row]
            what = "empty cell" if cell is None or (isinstance(cell, float) and math.isnan(cell)) else f"'{cell}'"
            raise RunLogError(
                f"column {col}: {what} is not a finite number", src, _line_of_row(src, row)
            )
        return values

    time_s = numeric("time_s")
    speed = numeric("speed_rpm")
    elong = numeric(ELONGATION_COLUMN) if ELONGATION_COLUMN in df.columns else None
    dt = np.diff(time_s)
    back = np.flatnonzero(dt <= 0)
    if back.size:
        row = int(back[0]) + 1
        raise RunLogError(
            f"time does not increase ({time_s[row]:g} s after {time_s[row - 1]:g} s)",
            src,
            _line_of_row(src, row),
        )
    extras: dict[str, np.ndarray] = {}
    for col in df.columns:
        if col in REQUIRED_COLUMNS or col == ELONGATION_COLUMN:
            continue
        conv = pd.to_numeric(df[col], errors="coerce")
        extras[col] = (
            conv.to_numpy(dtype=float)
            if conv.notna().sum() == df[col].notna().sum()
            else df[col].to_numpy(dtype=object)
        )
    gaps: tuple[Gap, ...] = ()
    if dt.size:
        idx = np.flatnonzero(dt > GAP_FACTOR * float(np.median(dt)))
        lines = _lines_of_rows(src, [int(k) + 1 for k in idx[:100]])
        gaps = tuple(
            Gap(lines.get(int(k) + 1, -1), float(time_s[k]), float(dt[k])) for k in idx
        )
    return RunLog(
        time_s=time_s,
        speed_rpm=speed,
        elongation_um=elong,
        extras=extras,
        metadata=meta,
        gaps=gaps,
        source=src,
    )


def write_run_log(
    path: str | os.PathLike[str],
    columns: Mapping[str, np.ndarray],
    metadata: Mapping[str, Any] | None = None,
) -> None:
    """Atomically write a run log. ``columns`` must start with time_s, speed_rpm."""
    names = list(columns)
    if names[:2] != list(REQUIRED_COLUMNS):
        raise RunLogError(f"a run log starts with columns {REQUIRED_COLUMNS}, got {names[:2]}")
    arrays = [np.asarray(columns[name]) for name in names]
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1:
        raise RunLogError(f"columns differ in length: {sorted(shapes)}")
    # 9 significant digits: sub-nanometre for um; time gets 15, so that epoch seconds
    # (a controller's own clock) keep their milliseconds
    fmt = ",".join(
        ("%.15g" if i == 0 else "%.9g") if a.dtype.kind == "f" else "%d" if a.dtype.kind in "iub" else "%s"
        for i, a in enumerate(arrays)
    )
    rows = arrays[0].shape[0]
    with atomic_write(path) as fh:
        fh.write("".join(f"# {k}: {v}\n" for k, v in (metadata or {}).items()))
        fh.write(",".join(names) + "\n")
        for s in range(0, rows, 100_000):  # bounded memory on month-long logs
            block = zip(*(a[s : s + 100_000].tolist() for a in arrays))
            fh.write("\n".join(map(fmt.__mod__, block)) + "\n")


# -- model files -----------------------------------------------------------------


def _canonical(payload: Mapping[str, Any]) -> str:
    return json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False)


def model_to_json(model: Any) -> str:
    payload = model.model_dump(mode="json")
    payload["sha256"] = hashlib.sha256(_canonical(payload).encode()).hexdigest()
    return json.dumps(payload, indent=2, sort_keys=False, allow_nan=False) + "\n"


def save_model(path: str | os.PathLike[str], model: Any) -> None:
    """Atomically write a model file with its checksum."""
    text = model_to_json(model)
    with atomic_write(path) as fh:
        fh.write(text)


def load_model(path: str | os.PathLike[str]) -> ThermalModel:
    """Read and verify a speed-only model file.

    Raises :class:`ModelFileError` for an unreadable, unknown or tampered file
    and :class:`UnstableModelError` for an unstable one.
    """
    model = load_any_model(path)
    if not isinstance(model, ThermalModel):
        raise ModelFileError(f"{os.fspath(path)}: a model with extra inputs "
                             f"({', '.join(model.input_names)}); this command takes speed-only models")
    return model


def load_any_model(path: str | os.PathLike[str]):
    """A speed-only :class:`ThermalModel` or an :class:`~compensator.inputs.AugmentedModel`."""
    from .inputs import AUGMENTED_FORMAT, AugmentedModel

    src = os.fspath(path)
    try:
        with open(src, encoding="utf-8") as fh:
            payload = json.load(fh)
    except OSError as err:
        raise ModelFileError(f"{src}: cannot read: {err.strerror or err}") from err
    except (json.JSONDecodeError, UnicodeError) as err:
        raise ModelFileError(f"{src}: not a JSON model file ({err})") from err
    if not isinstance(payload, dict):
        raise ModelFileError(f"{src}: not a JSON model file (top level is not an object)")
    fmt = payload.get("format")
    if fmt not in (MODEL_FORMAT, AUGMENTED_FORMAT):
        raise ModelFileError(
            f"{src}: unknown model format {fmt!r} (this thermocomp reads {MODEL_FORMAT} "
            f"and {AUGMENTED_FORMAT})"
        )
    digest = payload.pop("sha256", None)
    if digest is None:
        raise ModelFileError(f"{src}: no sha256 checksum; refusing an unverified model")
    try:
        actual = hashlib.sha256(_canonical(payload).encode()).hexdigest()
    except ValueError as err:
        raise ModelFileError(f"{src}: non-finite number in model file") from err
    if actual != digest:
        raise ModelFileError(f"{src}: checksum mismatch: the file was modified after it was written")
    try:
        if fmt == AUGMENTED_FORMAT:
            return AugmentedModel(**payload)
        return ThermalModel.model_validate(payload)
    except UnstableModelError as err:
        raise UnstableModelError(f"{src}: {err}") from err
    except ModelError as err:
        raise ModelFileError(f"{src}: invalid model: {err}") from err


# -- runtime state -------------------------------------------------------------------

STATE_FORMAT = "thermocomp.state/1"


def model_digest(model: Any) -> str:
    return hashlib.sha256(_canonical(model.model_dump(mode="json")).encode()).hexdigest()


def save_state(path: str | os.PathLike[str], payload: Mapping[str, Any]) -> None:
    """Atomically write a runtime state file with its checksum."""
    body = {"format": STATE_FORMAT, **payload}
    body["sha256"] = hashlib.sha256(_canonical(body).encode()).hexdigest()
    text = json.dumps(body, allow_nan=False)
    with atomic_write(path) as fh:
        fh.write(text)


def load_state(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The saved state, or None when missing; :class:`ModelFileError` when unreadable."""
    src = os.fspath(path)
    try:
        with open(src, encoding="utf-8") as fh:
            body = json.load(fh)
    except FileNotFoundError:
        return None
    except (OSError, json.JSONDecodeError, UnicodeError) as err:
        raise ModelFileError(f"{src}: unreadable state file ({err})") from err
    if not isinstance(body, dict) or body.get("format") != STATE_FORMAT:
        raise ModelFileError(f"{src}: not a {STATE_FORMAT} file")
    digest = body.pop("sha256", None)
    if digest != hashlib.sha256(_canonical(body).encode()).hexdigest():
        raise ModelFileError(f"{src}: state file checksum mismatch")
    return body


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
        import time as _time

        day = _time.strftime("%Y-%m-%d", _time.gmtime(wall_s))
        if day != self._day:
            self.close()
            self.directory.mkdir(parents=True, exist_ok=True)
            path = self.path_for(day)
            new = not path.exists() or path.stat().st_size == 0
            self._fh = open(path, "a", encoding="utf-8")
            if new:
                self._fh.write("".join(f"# {k}: {v}\n" for k, v in self.metadata.items()))
                self._fh.write(",".join(self.COLUMNS) + "\n")
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


# -- recording ------------------------------------------------------------------


class RunLogAppender:
    """Append rows to a run log as they are measured, so an interruption loses nothing.

    A new file gets the metadata and header; an existing one must have the same header, and
    a half-written last line (a crash mid-write) is cut off before appending. Each row is
    flushed; the file is fsynced every ``fsync_every_s`` of ``clock`` and on close.
    """

    def __init__(self, path: str | os.PathLike[str], columns: tuple[str, ...],
                 metadata: Mapping[str, Any] | None = None, *, fsync_every_s: float = 5.0,
                 clock: Any = None):
        import time as _time

        if tuple(columns[:2]) != REQUIRED_COLUMNS:
            raise RunLogError(f"a run log starts with columns {REQUIRED_COLUMNS}")
        self.path = Path(path)
        self.columns = tuple(columns)
        self._clock = clock or _time.monotonic
        self.fsync_every_s = fsync_every_s
        self.rows_before = 0
        self.last_row: tuple[float, ...] | None = None
        self.first_row: tuple[float, ...] | None = None
        self.metadata: dict[str, str] = {}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists() and self.path.stat().st_size > 0:
            self._adopt()
            self._fh = open(self.path, "a", encoding="utf-8")
        else:
            self._fh = open(self.path, "w", encoding="utf-8")
            self.metadata = {k: str(v) for k, v in (metadata or {}).items()}
            self._fh.write("".join(f"# {k}: {v}\n" for k, v in self.metadata.items()))
            self._fh.write(",".join(self.columns) + "\n")
            self._sync()
        self._last_sync = self._clock()

    def _adopt(self) -> None:
        src = str(self.path)
        data = self.path.read_bytes()
        if not data.endswith(b"\n"):
            cut = data.rfind(b"\n") + 1
            with open(self.path, "r+b") as fh:
                fh.truncate(cut)
        meta, header_line = _read_metadata(src)
        self.metadata = meta
        if header_line is None:
            raise RunLogError("no header line", src)
        with open(self.path, encoding="utf-8") as fh:
            lines = fh.read().splitlines()
        header = tuple(c.strip() for c in lines[header_line - 1].split(","))
        if header != self.columns:
            raise RunLogError(f"header {','.join(header)} differs from {','.join(self.columns)}: "
                              "not a log of this recording", src, header_line)
        rows = [ln for ln in lines[header_line:] if not _is_skipped(ln)]
        self.rows_before = len(rows)
        if rows:
            try:
                self.first_row = tuple(float(v) for v in rows[0].split(","))
                self.last_row = tuple(float(v) for v in rows[-1].split(","))
            except ValueError as err:
                raise RunLogError(f"unreadable row: {err}", src, header_line + len(rows)) from err

    def append(self, values: tuple[float, ...] | list[float]) -> None:
        if len(values) != len(self.columns):
            raise RunLogError(f"{len(values)} values for {len(self.columns)} columns", str(self.path))
        if self.last_row is not None and not values[0] > self.last_row[0]:
            return  # the format needs increasing time; a repeated instant adds nothing
        self._fh.write(",".join(("%.15g" if i == 0 else "%.9g") % v for i, v in enumerate(values)) + "\n")
        self._fh.flush()
        self.last_row = tuple(float(v) for v in values)
        if self.first_row is None:
            self.first_row = self.last_row
        if self._clock() - self._last_sync >= self.fsync_every_s:
            self._sync()

    def _sync(self) -> None:
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._last_sync = self._clock()

    def close(self) -> None:
        if not self._fh.closed:
            self._sync()
            self._fh.close()

    def __enter__(self) -> RunLogAppender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_daq_csv(path: str | os.PathLike[str], time_column: str,
                 columns: Mapping[str, str]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Time [s] and named columns from a CSV a data-acquisition system wrote.

    ``columns`` maps the names wanted to the file's column names. The time column may hold
    seconds or date-times (ISO 8601); date-times become seconds since the epoch. Rows are
    sorted by time; an unreadable cell is reported with its line.
    """
    import pandas as pd

    src = os.fspath(path)
    try:
        df = pd.read_csv(src, comment="#", skipinitialspace=True, sep=None, engine="python")
    except OSError as err:
        raise RunLogError(f"cannot read: {err.strerror or err}", src) from err
    except (pd.errors.ParserError, pd.errors.EmptyDataError, ValueError, UnicodeError) as err:
        raise RunLogError(f"not a readable CSV: {str(err).strip().splitlines()[-1]}", src) from err
    df.columns = [str(c).strip() for c in df.columns]
    want = {"time": time_column, **columns}
    missing = [c for c in want.values() if c not in df.columns]
    if missing:
        raise RunLogError(f"no column(s) {', '.join(missing)}; the file has {', '.join(df.columns)}", src)
    header_line = (_read_metadata(src)[1] or 1)

    def bad(row: int, col: str, cell: Any) -> RunLogError:
        return RunLogError(f"column {col}: {cell!r} is not a finite number", src, header_line + 1 + row)

    raw_t = df[time_column]
    t = pd.to_numeric(raw_t, errors="coerce").to_numpy(dtype=float)
    if np.isnan(t).all():
        stamps = pd.to_datetime(raw_t, errors="coerce", utc=True, format="ISO8601")
        if stamps.isna().any():
            row = int(np.flatnonzero(stamps.isna().to_numpy())[0])
            raise RunLogError(f"column {time_column}: {raw_t.iloc[row]!r} is neither seconds nor a "
                              "date-time", src, header_line + 1 + row)
        t = (stamps - pd.Timestamp("1970-01-01", tz="UTC")).dt.total_seconds().to_numpy(dtype=float)
    elif not np.isfinite(t).all():
        row = int(np.flatnonzero(~np.isfinite(t))[0])
        raise bad(row, time_column, raw_t.iloc[row])
    out: dict[str, np.ndarray] = {}
    for name, col in columns.items():
        v = pd.to_numeric(df[col], errors="coerce").to_numpy(dtype=float)
        if not np.isfinite(v).all():
            row = int(np.flatnonzero(~np.isfinite(v))[0])
            raise bad(row, col, df[col].iloc[row])
        out[name] = v
    order = np.argsort(t, kind="stable")
    t = t[order]
    keep = np.r_[True, np.diff(t) > 0]  # repeated instants: the first reading is kept
    return t[keep], {k: v[order][keep] for k, v in out.items()}


def versioned_path(path: str | os.PathLike[str]) -> Path:
    """``path`` if free, else the first free ``stem.v2.suffix``, ``stem.v3.suffix``, ...:
    a model or report is never overwritten."""
    p = Path(path)
    if not p.exists():
        return p
    k = 2
    while True:
        q = p.with_name(f"{p.stem}.v{k}{p.suffix}")
        if not q.exists():
            return q
        k += 1


def write_text(path: str | os.PathLike[str], text: str, *, overwrite: bool = True) -> Path:
    """Atomically write a text file; with ``overwrite=False`` a taken name gets a version suffix."""
    target = Path(path) if overwrite else versioned_path(path)
    with atomic_write(target) as fh:
        fh.write(text)
    return target


def read_text(path: str | os.PathLike[str]) -> str:
    try:
        return Path(path).read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"{path}: cannot read: {err.strerror or err}") from err
    except UnicodeError as err:
        raise ConfigError(f"{path}: not a text file") from err
