"""Input checks shared by the streaming operators of the PI, Preisach and Bouc–Wen models,
and by their fits (:func:`exclude_mask`).

``block(x)`` of every operator takes a 1-D array of samples; ``step(x)`` one number.
Anything else — NaN/inf, a 0-d or 2-D array, text — is a :class:`ModelError` naming the
input, never a numba typing error or a silently wrong shape.
"""
from __future__ import annotations

import math
from typing import Any, Literal, overload

import numpy as np

from .base import ModelError, check_finite
from .errortext import plain_repr


def block_samples(name: str, x: Any) -> np.ndarray:
    """``x`` as a C-contiguous 1-D float64 array (ints, float32, strided views and read-only
    arrays are accepted); :class:`ModelError` naming ``name`` for another number of
    dimensions or a non-finite value."""
    arr = check_finite(name, x)
    if arr.ndim != 1:
        raise ModelError(f"{name}: expected a 1-D array of samples, got shape {arr.shape}")
    return np.ascontiguousarray(arr)


def finite_sample(name: str, x: Any) -> float:
    """``x`` as a float; :class:`ModelError` naming ``name`` if it is not a finite number.
    (Called on every ``step``: kept to one conversion and one test.)"""
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ModelError(f"{name}: {x!r} is not a number; one finite sample is expected") from None
    if v - v != 0.0:  # NaN or ±inf
        raise ModelError(f"{name}: non-finite value {v}; all values must be finite")
    return v


@overload
def number_option(name: str, value: Any, *, lo: float | None = None, hi: float | None = None,
                  integer: Literal[True], allowed: str = "") -> int: ...


@overload
def number_option(name: str, value: Any, *, lo: float | None = None, hi: float | None = None,
                  integer: Literal[False] = False, allowed: str = "") -> float: ...


@overload
def number_option(name: str, value: Any, *, lo: float | None = None, hi: float | None = None,
                  integer: bool = False, allowed: str = "") -> float | int: ...


def number_option(name: str, value: Any, *, lo: float | None = None, hi: float | None = None,
                  integer: bool = False, allowed: str = "") -> float | int:
    """An identification option as a finite float (or an int with ``integer=True``) within
    ``[lo, hi]``; :class:`ModelError` naming the option and the allowed range otherwise.
    ``allowed`` overrides the range text of the message."""
    rng = allowed or (f"{'an integer' if integer else 'a number'}"
                      + (f" ≥ {lo:g}" if lo is not None else "") + (f" and ≤ {hi:g}" if hi is not None else ""))
    bad = ModelError(f"{name}: {value!r} is not allowed; expected {rng}")
    if isinstance(value, bool) or isinstance(value, str) or value is None:
        raise bad
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise bad from None
    if not math.isfinite(v) or (lo is not None and v < lo) or (hi is not None and v > hi):
        raise bad
    if integer:
        if v != int(v):
            raise bad
        return int(v)
    return v


def sample_period(dt_s: Any, model: str) -> float:
    """The sample period ``dt_s`` [s] a time-dependent ``model`` (its name in the message)
    runs at; :class:`ModelError` when there is none (None, not a number, not finite, ≤ 0)."""
    try:
        dt = float(dt_s)
    except (TypeError, ValueError):
        dt = math.nan
    if not (math.isfinite(dt) and dt > 0):
        raise ModelError(f"dt_s: {plain_repr(dt_s)}; the {model} needs a sample period > 0 s")
    return dt


def sample_mask(name: str, value: Any, n: int) -> np.ndarray:
    """``value`` checked to be one boolean per sample (``n``); a one-line :class:`ModelError`
    naming ``name`` otherwise."""
    mask = np.asarray(value)
    if mask.dtype != bool or mask.shape != (n,):
        raise ModelError(f"{name}: need one boolean per sample ({n}), got {mask.dtype} of shape {mask.shape}")
    return mask


def exclude_mask(exclude: Any, n: int) -> np.ndarray | None:
    """The ``exclude`` option of a fit: one boolean per sample (``n``), True for samples left
    out of the fit (they still set the model's memory and lags: the transients after a jump
    of the command, :func:`~afmctl.compensators.record_steps.step_transients`, or samples
    whose ``y`` was not measured). None when nothing is left out; a one-line
    :class:`ModelError` for another shape or when everything is."""
    if exclude is None:
        return None
    mask = sample_mask("exclude", exclude, n)
    if mask.all():
        raise ModelError("exclude: every sample is left out; nothing to fit")
    return mask if mask.any() else None
