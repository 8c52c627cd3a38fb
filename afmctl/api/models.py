"""Model files and what a model does to arrays: load/save, predict, validate, compensate.

Units: t [s], u [V], y [nm]. The same code ``afmctl model predict``/``model validate`` and
``afmctl compensate`` run (they read the CSV files, call these functions and print).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from afmctl.compensators.base import ModelError  # noqa: F401 - re-raised by callers
from afmctl.compensators.models import HysteresisModel
from afmctl.compensators.models import load_model as _load_model
from afmctl.compensators.models import save_model as _save_model

from ..data.identdata import U_LIMIT_V, Y_UNITS, burn_in_index, check_units, measured_mask
from ..data.prediction import HEADER, ErrorStats, predict_nm, score
from ..errors import AfmctlError

#: limits when neither ``limits_V`` nor the model gives a voltage range [V]
FALLBACK_LIMITS_V = (0.0, 150.0)
#: compensate inverts long targets in chunks of this many samples (same result, less memory)
CHUNK = 200_000

Warm = tuple[np.ndarray, np.ndarray]


def load_model(path: str | Path, kinds: tuple[str, ...] | None = None) -> HysteresisModel:
    """A model file written by ``afmctl identify`` (or :func:`save_model`); ``kinds``
    restricts the accepted kinds."""
    return _load_model(path, expect=kinds)


def save_model(model: HysteresisModel, path: str | Path) -> None:
    """Write ``model`` as a JSON model file (floats at full precision)."""
    _save_model(model, path)


def _floats(name: str, a: object) -> np.ndarray:
    arr = np.ascontiguousarray(a, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(arr)):
        raise AfmctlError(f"{name}: non-finite value at index {int(np.flatnonzero(~np.isfinite(arr))[0])}")
    return arr


def predict(model: HysteresisModel, t_s: np.ndarray, u_V: np.ndarray, *, warm: Warm | None = None,
            where: str = "u_V") -> np.ndarray:
    """The model's displacement y [nm] for the voltages ``u_V`` [V] at times ``t_s`` [s],
    from the model's stored state, or after running through ``warm = (t_s, u_V)`` first
    (the recording before this one). The model's ``delay_s`` is honoured."""
    t, u = _floats("t_s", t_s), _floats("u_V", u_V)
    if float(np.abs(u).max(initial=0.0)) > U_LIMIT_V:
        raise AfmctlError(f"{where}: column u: {float(np.abs(u).max()):g} V is outside the allowed range "
                          f"−{U_LIMIT_V:g}…{U_LIMIT_V:g} V")
    return predict_nm(model, t, u, where, warm=warm)


@dataclass
class Validation:
    """A model scored on a held-out recording: ``stats[0]`` the whole record from ``start``
    (``rms_nm``, ``max_nm``, ... :class:`~afmctl.data.prediction.ErrorStats`), then one per
    input cycle; ``y_pred_nm`` the prediction over the whole record."""

    stats: list[ErrorStats]
    start: int
    y_pred_nm: np.ndarray

    @property
    def rms_nm(self) -> float:
        return self.stats[0].rms_nm

    @property
    def max_nm(self) -> float:
        return self.stats[0].max_nm

    def table(self) -> str:
        """The error table as ``afmctl model validate`` prints it."""
        return "\n".join([HEADER, *(s.row() for s in self.stats)])


def validate(model: HysteresisModel, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, *,
             warm: Warm | None = None, y_unit: str = "nm", where: str = "data",
             measured: np.ndarray | None = None) -> Validation:
    """Predict a held-out recording (t [s], u [V], y in ``y_unit``) and score the error. Without
    ``warm``, samples until the input has passed both its extremes only set the model's
    memory and are not scored. ``measured``: 0/1 per sample (the column ``measured``), 0
    where ``y`` was not measured: not scored either."""
    if y_unit not in Y_UNITS:
        raise AfmctlError(f"y_unit: {y_unit!r} is not known; allowed: nm, um")
    t, u = _floats("t_s", t_s), _floats("u_V", u_V)
    y = _floats("y_nm", y_nm) * Y_UNITS[y_unit]
    check_units(u, y, where)
    y_pred = predict_nm(model, t, u, where, warm=warm)
    start = 0 if warm is not None else burn_in_index(u)
    if start >= t.size - 1:
        start = 0
    return Validation(score(t, u, y, y_pred, start, measured_mask(measured, t.size, where)), start, y_pred)


@dataclass
class Compensated:
    """The voltages [V] for a target, the limits they were held to and where those came from,
    how many samples were clipped, and the dynamics inverse's report (when it ran)."""

    u_V: np.ndarray
    limits_V: tuple[float, float]
    limits_from: str
    clipped: int = 0
    dynamics_report: str | None = None
    notes: list[str] = field(default_factory=list)


class LimitsExceeded(AfmctlError):
    """The target needs voltages outside the limits (and ``clip`` was not asked for):
    ``index`` of the first such sample, its ``value_V``, ``count`` of them."""

    def __init__(self, message: str, index: int, value_V: float, count: int) -> None:
        super().__init__(message)
        self.index, self.value_V, self.count = index, value_V, count


def model_limits_V(model: HysteresisModel, limits_V: tuple[float, float] | None) -> tuple[float, float, str]:
    """``(lo, hi, where from)`` [V]: ``limits_V``, else the model's voltage range, else 0..150 V."""
    if limits_V is not None:
        lo, hi = float(limits_V[0]), float(limits_V[1])
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise AfmctlError(f"limits_V: {lo} {hi}; need finite LO < HI (V)")
        return lo, hi, "limits_V"
    known = model.voltage_range_V()
    if known is not None:
        return float(known[0]), float(known[1]), "the model's voltage range"
    return (*FALLBACK_LIMITS_V, "the model file records no voltage range; give limits")
