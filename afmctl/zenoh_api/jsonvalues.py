"""Plain JSON values and one-line texts for what the zenoh API publishes: numpy scalars and
arrays, enums and pydantic models turned into JSON values (NaN/inf -> null), controller
states as names, exceptions as one line naming the field (docs/ZENOH.md)."""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np


def jsonable(value: Any) -> Any:
    """Plain JSON values from numpy scalars/arrays, enums, nested dicts (NaN/inf -> None)."""
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if hasattr(value, "value") and isinstance(getattr(value, "value"), (str, int)):  # Enum
        return value.value
    if hasattr(value, "model_dump"):
        return jsonable(value.model_dump(mode="json"))
    return str(value)


def state_name(state: Any) -> str:
    """The controller state's name (``"unknown"`` for None)."""
    if state is None:
        return "unknown"
    value = getattr(state, "value", state)
    return str(value)


def one_line(err: BaseException) -> str:
    """An exception as one line (a pydantic error names its field and the allowed range)."""
    from pydantic import ValidationError
    if isinstance(err, ValidationError):
        from afmctl.compensators.errortext import validation_error_line
        return validation_error_line(err)
    return " ".join(str(err).split()) or type(err).__name__
