"""Series checks shared by the estimators: the core's checks, with their errors as
:class:`~compensator.errors.CalibrationError` (a non-finite value keeps its own class). Pure."""

from __future__ import annotations

from typing import Any

import numpy as np

from compensator.errors import CalibrationError, ModelError, NonFiniteInputError
from compensator.filters import series, times


def as_series(name: str, values: Any, size: int | None = None) -> np.ndarray:
    """``values`` as a finite float array (of ``size`` rows when given)."""
    try:
        return series(name, values, size)
    except NonFiniteInputError:
        raise
    except ModelError as err:
        raise CalibrationError(str(err)) from err


def as_times(time_s: Any) -> np.ndarray:
    """Time stamps [s], finite and strictly increasing."""
    try:
        return times(time_s)
    except NonFiniteInputError:
        raise
    except ModelError as err:
        raise CalibrationError(str(err)) from err
