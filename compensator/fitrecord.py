"""A model's fit record: what the identification stated about the model it chose. Pure: no I/O.

Every model file carries one under ``fit``. The identification writes it once
(``calibration.identify``); a later step adds to it through :meth:`FitRecord.with_changes` (or
:func:`compensator.modelbase.with_fit` on the model), never by rebuilding a dict. The runtime
reads it through typed fields: :attr:`FitRecord.expected_error` (the error to expect by speed
band), :attr:`FitRecord.observer` (the observer settings fitted with the model) and
:attr:`FitRecord.growth_direction`.

Records written before the record was typed carry no ``schema_version`` (version 1) and may
hold keys this version does not know; both still load, and a record read from a file dumps back
to the very JSON it was read from, so the checksum that names the model in the runtime's state
file stays the same across an upgrade.
"""

from __future__ import annotations

from collections.abc import ItemsView, KeysView, Mapping
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    SerializerFunctionWrapHandler,
    ValidationError,
    ValidatorFunctionWrapHandler,
    WithJsonSchema,
    model_serializer,
    model_validator,
)

from .errors import ModelError
from .expected import ExpectedError
from .observer import ObserverConfig

FIT_SCHEMA_VERSION = 2
"""The version of the records this code writes; a record without one is version 1 (the untyped
record written before)."""

Number = Annotated[int | float, WithJsonSchema({"type": "number"})]
"""A real number that stays an integer where the file wrote one: a float field would read ``2``
as ``2.0`` and write it back so, and the record's checksum would change on the round trip."""

_ADVICE = ("expected_error",)
"""Entries that are advice: an unreadable one (a newer format, say) is left out of the typed
record and kept as written, and the model runs without it, as it always did."""


class FitRecord(BaseModel):
    """The fit statistics and settings stored with a model (its ``fit`` entry)."""

    # extra="allow": every record written so far must load, and older records hold entries this
    # version no longer writes (in_sample_rms_um...) or never typed; they are kept and written
    # back unchanged, and new code reads only the typed fields below.
    model_config = ConfigDict(frozen=True, extra="allow")

    schema_version: int = Field(
        default=1,
        ge=1,
        description="version of the record; absent in records written before it was typed",
    )
    method: str | None = Field(
        default=None, description="the candidate chosen (calibration.identify)"
    )
    scored_by: str | None = Field(default=None, description="how the candidates were scored")
    folds: int | None = Field(default=None, ge=0, description="folds scored")
    cv_rms_um: Number | None = Field(
        default=None, description="held-out free-run RMS over the folds"
    )
    cv_max_abs_um: Number | None = Field(
        default=None, description="held-out free-run largest |error|"
    )
    folds_rms_um: tuple[Number, ...] | None = Field(
        default=None, description="held-out RMS per fold"
    )
    reason: str | None = Field(default=None, description="why this candidate was chosen")
    expected_error: ExpectedError | None = Field(
        default=None, description="the error to expect by speed band (compensator.expected)"
    )
    nested_rms_um: Number | None = Field(
        default=None, description="RMS with the choice itself held out"
    )
    forward_rms_um: Number | None = Field(
        default=None, description="RMS predicting later folds forward"
    )
    alpha: Number | None = Field(default=None, description="the ridge strength chosen")
    grid: str | None = Field(default=None, description="the filter bank's time-constant grid")
    observer: ObserverConfig | None = Field(
        default=None, description="observer settings fitted from held-out residuals"
    )
    not_following_share: Number | None = Field(
        default=None, description="share of calibration rows the spindle did not follow its program"
    )
    growth_direction: Literal[-1, 1] | None = Field(
        default=None,
        description="+1: the tool tip grows toward the workpiece as measured; -1: away",
    )
    fallback: str | None = Field(
        default=None,
        description="how the speed-only fallback was chosen when no speed-only candidate "
        "passed the checks",
    )
    in_sample_rms_um: Number | None = Field(
        default=None, description="in-sample RMS (older records)"
    )
    score_rms_um: Number | None = Field(
        default=None, description="the score chosen by (older records)"
    )
    runs: int | None = Field(default=None, ge=0, description="runs fitted (older records)")
    fit_dt_s: Number | None = Field(default=None, description="time step fitted at (older records)")

    _unreadable: dict[str, Any] = PrivateAttr(default_factory=dict)
    """Advice entries (:data:`_ADVICE`) read from a file but not understood: written back as read."""

    @model_validator(mode="wrap")
    @classmethod
    def _advice_as_written(cls, data: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        if not isinstance(data, Mapping):
            return handler(data)
        unreadable: dict[str, Any] = {}
        for key in _ADVICE:
            value = data.get(key)
            if value is None or isinstance(value, ExpectedError):
                continue
            try:
                ExpectedError.model_validate(value)
            except (ValidationError, ValueError, TypeError):
                unreadable[key] = value
        record = handler({k: v for k, v in data.items() if k not in unreadable})
        if unreadable:
            record._unreadable = unreadable
        return record

    @model_serializer(mode="wrap")
    def _as_stored(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        # only what was set (by the file or the writer): an old record dumps to what it was read
        # from, no schema_version or empty entries added
        out = {
            k: v
            for k, v in handler(self).items()
            if k in self.model_fields_set or k not in type(self).model_fields
        }
        out.update(self._unreadable)
        return out

    @classmethod
    def of(cls, value: Any) -> FitRecord:
        """A record from what a model carries: a record, a mapping (the JSON form), or None
        (no record). :class:`ModelError` in one line for anything else or an invalid entry."""
        if isinstance(value, FitRecord):
            return value
        if value is None:
            return cls()
        if not isinstance(value, Mapping):
            raise ModelError(f"fit: a {type(value).__name__}, not a record")
        try:
            return cls.model_validate(dict(value))
        except ValidationError as err:
            item = err.errors()[0]
            where = ".".join(str(p) for p in item["loc"])
            raise ModelError(f"fit.{where}: {item['msg']}") from err

    def with_changes(self, **changes: Any) -> FitRecord:
        """A new record with some entries changed (a value of None removes the entry), checked
        again and stamped with this version's :data:`FIT_SCHEMA_VERSION`."""
        data = {**self.as_dict(), **changes, "schema_version": FIT_SCHEMA_VERSION}
        return FitRecord.of({k: v for k, v in data.items() if v is not None})

    def as_dict(self) -> dict[str, Any]:
        """The record as stored in the model file (JSON types)."""
        return self.model_dump(mode="json")

    # A read-only mapping view of the stored form, for readers written when the record was a
    # dict (``fit.get("cv_rms_um")``, ``fit["observer"]``, ``{**fit}``); new code reads fields.
    def __getitem__(self, key: str) -> Any:
        return self.as_dict()[key]

    def __contains__(self, key: object) -> bool:
        return key in self.as_dict()

    def get(self, key: str, default: Any = None) -> Any:
        return self.as_dict().get(key, default)

    def keys(self) -> KeysView[str]:
        return self.as_dict().keys()

    def items(self) -> ItemsView[str, Any]:
        return self.as_dict().items()


def fit_of(model: object) -> FitRecord:
    """The fit record ``model`` carries: a model's typed record, the JSON form read as one (by
    something that is no :class:`~compensator.modelbase.ModelBase`), else the empty record. An
    unreadable JSON form reads as the empty record: readers take advice from it, never a
    reason to stop."""
    fit = getattr(model, "fit", None)
    if isinstance(fit, FitRecord):
        return fit
    try:
        return FitRecord.of(fit if isinstance(fit, Mapping) else None)
    except ModelError:
        return FitRecord()
