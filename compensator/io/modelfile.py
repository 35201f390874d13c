"""Model files: the JSON of a model value with a ``sha256`` over its canonical content.

A hand-edited file is refused. The file's ``format`` names the model class
(:data:`MODEL_TYPES`); the loader is the one place that knows the classes, so every other
module sees only the :class:`~compensator.predictor.Predictor` interface.
"""

from __future__ import annotations

import json
import os
from typing import Any

from pydantic import ValidationError

from ..errors import ModelError, ModelFileError, UnstableModelError, clip
from ..inputs import AUGMENTED_FORMAT, AugmentedModel
from ..model import MODEL_FORMAT, ThermalModel
from ..predictor import Predictor
from ..statespace import STATE_SPACE_FORMAT, StateSpaceModel
from .atomic import atomic_write, read_regular
from .checksum import digest

ModelClass = type[ThermalModel] | type[AugmentedModel] | type[StateSpaceModel]
"""The model classes a file can hold (a new form joins here and in :data:`MODEL_TYPES`)."""

MODEL_TYPES: dict[str, ModelClass] = {
    MODEL_FORMAT: ThermalModel,
    AUGMENTED_FORMAT: AugmentedModel,
    STATE_SPACE_FORMAT: StateSpaceModel,
}
"""Model classes by the ``format`` their files carry: a new model form registers here."""


MAX_MODEL_BYTES = 8 * 1024 * 1024
"""A model file is a few kB; anything larger than this is refused unread (no MemoryError)."""

MAX_MODEL_DEPTH = 32
"""Nesting of arrays and objects in a model file (about 6 in practice): deeper is refused."""


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
        raise ModelFileError(
            clip(
                f"{os.fspath(path)}: a model with extra inputs "
                f"({', '.join(model.input_names)}); this command takes speed-only "
                "models",
                500,
            )
        )
    return model  # type: ignore[return-value]


def _refuse_constant(name: str) -> Any:
    # json reads NaN and Infinity, which are not JSON and not a usable coefficient
    raise ValueError(f"{name} is not a JSON number")


def _too_deep(payload: Any) -> bool:
    """Nested beyond :data:`MAX_MODEL_DEPTH`, walked without recursion."""
    stack = [(payload, 1)]
    while stack:
        value, depth = stack.pop()
        children = (
            value.values() if isinstance(value, dict) else value if isinstance(value, list) else ()
        )
        for child in children:
            if isinstance(child, (dict, list)):
                if depth >= MAX_MODEL_DEPTH:
                    return True
                stack.append((child, depth + 1))
    return False


def _unstable(err: BaseException) -> UnstableModelError | None:
    """The UnstableModelError behind ``err``, if any: a nested model's validator raised it,
    and pydantic or the outer model wrapped it."""
    seen: set[int] = set()
    todo: list[BaseException] = [err]
    while todo:
        e = todo.pop()
        if id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, UnstableModelError):
            return e
        if isinstance(e, ValidationError):
            for item in e.errors():
                inner = (item.get("ctx") or {}).get("error")
                if isinstance(inner, BaseException):
                    todo.append(inner)
        if e.__cause__ is not None:
            todo.append(e.__cause__)
    return None


def _invalid(src: str, err: Exception) -> ModelError:
    """The error for a file whose content the model class refuses, in one line: an unstable
    pole stays an UnstableModelError, our own message is kept, else pydantic's first."""
    unstable = _unstable(err)
    if unstable is not None:
        return UnstableModelError(clip(f"{src}: {unstable}", 500))
    if isinstance(err, ValidationError):
        for item in err.errors():
            original = (item.get("ctx") or {}).get("error")
            if isinstance(original, ModelError):
                return ModelFileError(clip(f"{src}: invalid model: {original}", 500))
        item = err.errors()[0]
        where = ".".join(str(x) for x in item["loc"]) or "model"
        return ModelFileError(clip(f"{src}: invalid model: {where}: {item['msg']}", 500))
    return ModelFileError(clip(f"{src}: invalid model: {err}", 500))


def load_any_model(path: str | os.PathLike[str]) -> Predictor:
    """Any registered model (speed only, with inputs, ...), verified.

    Every fault of the file, however corrupt (NaN, deep nesting, truncated, huge, a key
    missing), is a one-line :class:`ModelFileError` (:class:`UnstableModelError` for an
    unstable model).
    """
    src = os.fspath(path)
    try:
        raw = read_regular(src, MAX_MODEL_BYTES)
    except OSError as err:
        raise ModelFileError(f"{src}: cannot read: {err.strerror or err}") from err
    if len(raw) > MAX_MODEL_BYTES:
        raise ModelFileError(f"{src}: larger than {MAX_MODEL_BYTES // 2**20} MiB: not a model file")
    try:
        payload = json.loads(raw.decode("utf-8"), parse_constant=_refuse_constant)
    except RecursionError as err:
        raise ModelFileError(f"{src}: not a model file (nested too deeply)") from err
    except ValueError as err:  # JSONDecodeError, UnicodeDecodeError, NaN
        raise ModelFileError(clip(f"{src}: not a JSON model file ({err})", 500)) from err
    if not isinstance(payload, dict):
        raise ModelFileError(f"{src}: not a JSON model file (top level is not an object)")
    if _too_deep(payload):
        raise ModelFileError(f"{src}: not a model file (nested deeper than {MAX_MODEL_DEPTH})")
    fmt = payload.get("format")
    cls = MODEL_TYPES.get(fmt) if isinstance(fmt, str) else None
    if cls is None:
        raise ModelFileError(
            clip(
                f"{src}: unknown model format {clip(repr(fmt), 80)} "
                f"(this thermocomp reads {' and '.join(MODEL_TYPES)})",
                500,
            )
        )
    expected = payload.pop("sha256", None)
    if expected is None:
        raise ModelFileError(f"{src}: no sha256 checksum; refusing an unverified model")
    try:
        actual = digest(payload)
    except ValueError as err:
        raise ModelFileError(f"{src}: non-finite number in model file") from err
    if actual != expected:
        raise ModelFileError(
            f"{src}: checksum mismatch: the file was modified after it was written"
        )
    try:
        model: Predictor = cls.model_validate(payload)
        return model
    except (
        ValueError,
        TypeError,
        KeyError,
    ) as err:  # ModelError, or pydantic's from a nested model
        raise _invalid(src, err) from err
