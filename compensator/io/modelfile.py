"""Model files: the JSON of a model value with a ``sha256`` over its canonical content.

A hand-edited file is refused. The file's ``format`` names the model class
(:data:`MODEL_TYPES`); the loader is the one place that knows the classes, so every other
module sees only the :class:`~compensator.predictor.Predictor` interface.
"""

from __future__ import annotations

import json
import os
from typing import Any

from ..errors import ModelError, ModelFileError, UnstableModelError
from ..inputs import AUGMENTED_FORMAT, AugmentedModel
from ..model import MODEL_FORMAT, ThermalModel
from ..predictor import Predictor
from .atomic import atomic_write
from .checksum import digest

MODEL_TYPES: dict[str, Any] = {MODEL_FORMAT: ThermalModel, AUGMENTED_FORMAT: AugmentedModel}
"""Model classes by the ``format`` their files carry: a new model form registers here."""


def model_to_json(model: Predictor) -> str:
    payload = model.model_dump(mode="json")
    payload["sha256"] = digest(payload)
    return json.dumps(payload, indent=2, sort_keys=False, allow_nan=False) + "\n"


def model_digest(model: Predictor) -> str:
    """The checksum a model file of ``model`` carries: identifies the model in state files."""
    return digest(model.model_dump(mode="json"))


def save_model(path: str | os.PathLike[str], model: Predictor) -> None:
    """Atomically write a model file with its checksum."""
    text = model_to_json(model)
    with atomic_write(path) as fh:
        fh.write(text)


def load_model(path: str | os.PathLike[str]) -> ThermalModel:
    """Read and verify a speed-only model file.

    Raises :class:`ModelFileError` for an unreadable, unknown or tampered file, or a model
    with inputs, and :class:`UnstableModelError` for an unstable one.
    """
    model = load_any_model(path)
    if model.input_names:
        raise ModelFileError(f"{os.fspath(path)}: a model with extra inputs "
                             f"({', '.join(model.input_names)}); this command takes speed-only models")
    return model  # type: ignore[return-value]


def load_any_model(path: str | os.PathLike[str]) -> Predictor:
    """Any registered model (speed only, with inputs, ...), verified."""
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
    cls = MODEL_TYPES.get(fmt) if isinstance(fmt, str) else None
    if cls is None:
        raise ModelFileError(
            f"{src}: unknown model format {fmt!r} (this thermocomp reads {' and '.join(MODEL_TYPES)})"
        )
    expected = payload.pop("sha256", None)
    if expected is None:
        raise ModelFileError(f"{src}: no sha256 checksum; refusing an unverified model")
    try:
        actual = digest(payload)
    except ValueError as err:
        raise ModelFileError(f"{src}: non-finite number in model file") from err
    if actual != expected:
        raise ModelFileError(f"{src}: checksum mismatch: the file was modified after it was written")
    try:
        return cls.model_validate(payload)
    except UnstableModelError as err:
        raise UnstableModelError(f"{src}: {err}") from err
    except ModelError as err:
        raise ModelFileError(f"{src}: invalid model: {err}") from err
