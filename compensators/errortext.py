"""One-line error texts: the first error of a pydantic validation as ``field a.b: message``,
and values shown as a user wrote them (numpy scalars as plain numbers). The one place for
this in afmctl: configuration, model and parameter files, zenoh messages and the command
line all use it."""
from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import ValidationError
from pydantic_core import ErrorDetails


def first_validation_error(err: ValidationError, prefix: str = "",
                           skip: tuple[str, ...] = ()) -> tuple[ErrorDetails, str]:
    """The first error of a pydantic ``err`` and the dotted name of its field: ``prefix`` +
    the location without the parts in ``skip`` (e.g. union tags), ``"(root)"`` when empty.
    The one place that turns a pydantic error into a field name (config files, model files,
    zenoh messages and the command line all use it)."""
    first = err.errors()[0]
    name = prefix + ".".join(str(p) for p in first["loc"] if p not in skip)
    return first, name or "(root)"


def validation_error_line(err: ValidationError, prefix: str = "", skip: tuple[str, ...] = ()) -> str:
    """One line ``field a.b: message`` for the first error of a pydantic ``err``."""
    first, name = first_validation_error(err, prefix, skip)
    return f"field {name}: {first['msg']}"


def format_validation_error(err: ValidationError, where: str) -> str:
    """One line ``WHERE: field a.b: message`` for the first error of ``err``."""
    return f"{where}: {validation_error_line(err)}"


def plain_repr(value: Any) -> str:
    """``repr`` for messages, with numpy scalars shown as the Python numbers they hold
    (``1.5``, not ``np.float64(1.5)``)."""
    if isinstance(value, np.generic):
        value = value.item()
    return repr(value)
