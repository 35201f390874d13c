"""The wizard's step 5 as a value: the model, its report and its runtime configuration written,
each under a new version; nothing earlier is overwritten."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from compensator.io import save_model, versioned_path, write_text

from .model import Saved, WizardSession


@dataclass(frozen=True)
class SavedFiles:
    """The save step's value: the session with what it wrote, and the earlier models kept."""

    session: WizardSession
    saved: Saved
    older: tuple[str, ...]


def save(
    session: WizardSession,
    directory: Path,
    summary: dict[str, Any],
    model: Any,
    *,
    report_format: str,
    date: str,
    now_utc: str,
) -> SavedFiles:
    """Write ``model`` as ``models/<machine>_<spindle>_<date>[.vN].json`` under ``directory``,
    the calibration report (``report_format``: html or md) and the runtime configuration."""
    from ..report import calibration_report, runtime_config

    s = session
    base = f"{s.machine_id}_{s.spindle_id}_{date}"
    model_path = versioned_path(directory / "models" / f"{base}.json")
    model_path.parent.mkdir(parents=True, exist_ok=True)
    save_model(model_path, model)
    version = model_path.stem[len(base) :].lstrip(".") or "v1"
    as_read = s.as_dict()  # the report and configuration writers read the session's file form
    report_path = versioned_path(directory / "reports" / f"{base}.{report_format}")
    write_text(
        report_path,
        calibration_report(as_read, summary, model, model_path, report_format, version),
    )
    config_path = versioned_path(directory / "config" / f"{base}.toml")
    write_text(
        config_path, runtime_config(as_read, model, model_path, config_dir=config_path.parent)
    )
    older = tuple(sorted(p.name for p in (directory / "models").glob("*.json") if p != model_path))
    saved = Saved(
        model=str(model_path),
        report=str(report_path),
        config=str(config_path),
        version=version,
        at_utc=now_utc,
    )
    return SavedFiles(s.updated(saved=saved.model_dump()), saved, older)
