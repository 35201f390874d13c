"""A spindle's model history: every model the service has run, every candidate a refit made, and
why each was promoted, rejected or rolled back to.

One directory per spindle, ``<state_dir>/history/<spindle>/``:

- ``history.jsonl``: one JSON record per line, appended and fsynced (``HistoryRecord``,
  ``thermocomp.model-history/1``). A torn last line (power lost mid-append) is skipped on read.
- ``<digest>.json``: a copy of each model file, by the first 16 hex digits of its checksum, so a
  rollback never depends on a file somewhere else still being there.

Disk use is bounded like the journal's: at most ``keep_models`` copies (the oldest that are not
in use go first; their records stay and say the copy was pruned), and the record file is cut to
its newest ``MAX_RECORDS`` when it holds twice as many.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Final, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..errors import ConfigError, ModelFileError
from ..fitrecord import fit_of
from .atomic import atomic_write, open_regular, read_regular
from .modelfile import load_any_model, model_digest

HISTORY_FORMAT: Final = "thermocomp.model-history/1"
RECORDS = "history.jsonl"
MAX_RECORDS = 1000
"""Records kept once the file holds twice as many."""
KEEP_MODELS = 20
"""Model copies kept by default."""
DIGEST_CHARS = 16
SHADOW_FILE = "shadow.json"

Event = Literal["in_use", "candidate", "promoted", "rejected", "rollback", "shadow"]
LIVE_EVENTS = ("in_use", "promoted", "rollback")
"""Events after which the record's model is the one the service runs."""


class HistoryRecord(BaseModel):
    """What happened to one model, when and why."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    format: Literal["thermocomp.model-history/1"] = HISTORY_FORMAT
    event: Event
    at_wall_s: float = Field(description="when [epoch s]")
    digest: str = Field(min_length=64, max_length=64, description="the model file's checksum")
    copy_name: str = Field(description="the copy in the history directory")
    source: str = Field(
        description="where the model came from: its file, or the refit that made it"
    )
    reason: str = ""
    fit: dict[str, Any] = Field(default_factory=dict, description="the fit's headline figures")
    data: dict[str, Any] = Field(default_factory=dict, description="what it was fitted on")
    judged: dict[str, Any] = Field(
        default_factory=dict, description="how it was judged against the live model"
    )

    @property
    def short(self) -> str:
        return self.digest[:DIGEST_CHARS]


class ModelHistory:
    """The history directory of one spindle."""

    def __init__(self, directory: str | os.PathLike[str], keep_models: int = KEEP_MODELS):
        if keep_models < 2:
            raise ConfigError(
                f"model history: keep_models must be 2 or more (the live model and one "
                f"to roll back to), got {keep_models}"
            )
        self.directory = Path(directory)
        self.keep_models = keep_models

    @classmethod
    def of(
        cls, state_dir: str | os.PathLike[str], spindle: str, keep_models: int = KEEP_MODELS
    ) -> ModelHistory:
        return cls(Path(state_dir) / "history" / spindle, keep_models)

    @property
    def records_path(self) -> Path:
        return self.directory / RECORDS

    def records(self) -> list[HistoryRecord]:
        """Every readable record, oldest first (a damaged line is skipped)."""
        try:
            # a FIFO or a device planted there is refused at once, never waited on
            text = read_regular(self.records_path).decode("utf-8", "replace")
        except FileNotFoundError:
            return []
        except OSError as err:
            raise ConfigError(
                f"{self.records_path}: cannot read the model history: {err.strerror}"
            ) from err
        out = []
        for line in text.splitlines():
            try:
                out.append(HistoryRecord.model_validate_json(line))
            except (ValidationError, ValueError):
                continue  # a torn last line, or a line of a later format
        return out

    def live(self) -> HistoryRecord | None:
        """The record of the model the service runs now (the last that put one in use)."""
        return next((r for r in reversed(self.records()) if r.event in LIVE_EVENTS), None)

    @property
    def shadow_path(self) -> Path:
        """The candidate the service runs in shadow, while there is one."""
        return self.directory / SHADOW_FILE

    def shadow(self) -> HistoryRecord | None:
        """The record of the candidate in shadow, while its file is there."""
        if not self.shadow_path.is_file():
            return None
        return next((r for r in reversed(self.records()) if r.event == "shadow"), None)

    def copy_path(self, record: HistoryRecord) -> Path:
        return self.directory / record.copy_name

    def find(self, prefix: str) -> HistoryRecord:
        """The newest record whose digest starts with ``prefix`` (4 hex digits or more) and whose
        copy is still kept; a one-line ConfigError otherwise."""
        p = prefix.strip().lower()
        if len(p) < 4 or any(c not in "0123456789abcdef" for c in p):
            raise ConfigError(
                f"model digest {prefix[:70]!r}: give 4 or more hex digits of it "
                "(thermocomp model history lists them)"
            )
        hits = [r for r in self.records() if r.digest.startswith(p)]
        if not hits:
            raise ConfigError(f"no model {p} in the history {self.directory}")
        if len({r.digest for r in hits}) > 1:
            raise ConfigError(f"model digest {p} is ambiguous: give more digits")
        rec = hits[-1]
        if not self.copy_path(rec).is_file():
            raise ConfigError(f"model {p}: its copy was pruned from the history (keep_models)")
        return rec

    def add(
        self,
        event: Event,
        model_file: str | os.PathLike[str],
        *,
        source: str | None = None,
        reason: str = "",
        at_wall_s: float,
        fit: dict[str, Any] | None = None,
        data: dict[str, Any] | None = None,
        judged: dict[str, Any] | None = None,
    ) -> HistoryRecord:
        """Keep a copy of ``model_file`` (verified) and append the record; prune. OSError and
        ConfigError go to the caller, which decides whether they matter."""
        try:
            model = load_any_model(model_file)
        except ModelFileError as err:
            raise ConfigError(f"model history: {err}") from err
        digest = model_digest(model)
        name = f"{digest[:DIGEST_CHARS]}.json"
        self.directory.mkdir(parents=True, exist_ok=True)
        copy = self.directory / name
        if not copy.is_file():
            data_bytes = Path(model_file).read_bytes()
            with atomic_write(copy, "wb") as fh:
                fh.write(data_bytes)
        rec = HistoryRecord(
            event=event,
            at_wall_s=float(at_wall_s),
            digest=digest,
            copy_name=name,
            source=str(source if source is not None else model_file),
            reason=reason,
            fit=fit or {},
            data=data or {},
            judged=judged or {},
        )
        line = rec.model_dump_json() + "\n"
        # a link, FIFO or device planted in the state directory is never appended through
        fd = open_regular(self.records_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND)
        try:
            os.write(fd, line.encode("utf-8"))
            os.fsync(fd)
        finally:
            os.close(fd)
        self._prune()
        return rec

    def _prune(self) -> None:
        records = self.records()
        if len(records) > 2 * MAX_RECORDS:
            kept = records[-MAX_RECORDS:]
            with atomic_write(self.records_path) as fh:
                fh.write("".join(r.model_dump_json() + "\n" for r in kept))
            records = kept
        live = self.live()
        # copies by last use, newest first; the live model's is never pruned
        order: list[str] = []
        for r in reversed(records):
            if r.copy_name not in order:
                order.append(r.copy_name)
        keep = set(order[: self.keep_models]) | ({live.copy_name} if live else set())
        for p in self.directory.glob("*.json"):
            if p.name not in keep and len(p.stem) == DIGEST_CHARS:
                try:
                    p.unlink()
                except OSError:
                    pass  # the next prune tries again


def fit_summary(model: Any) -> dict[str, Any]:
    """The headline figures of a model's fit record, for a history record."""
    fit = fit_of(model).as_dict()
    keys = ("method", "folds", "nested_rms_um", "forward_rms_um", "cv_rms_um", "alpha")
    out: dict[str, Any] = {
        "form": getattr(model, "form", None),
        "created_utc": getattr(model, "created_utc", None),
    }
    out.update({k: fit[k] for k in keys if k in fit and isinstance(fit[k], (int, float, str))})
    return out
