"""The scanner-level model file (``kind = "scanner"``): per-axis models plus coupling.

``axes`` maps ``x``, ``y``, ``z`` to a per-axis model (usually a :class:`.chain.ChainModel`;
any kind of :data:`.models.KINDS` except ``scanner``) or ``null`` (that axis keeps the
linear calibration of the configuration). ``coupling`` is the 3×3 matrix ``C`` with
``d_actual = C · d_axis`` — column *j* is the motion of every axis [nm] per nm of axis *j*'s
own displacement (``C[0, 1]``: x moves ``C[0, 1]`` nm per nm of y); ``coupling_inverse`` is
``C⁻¹``, the decoupler applied to the target before the per-axis inverses
(``d_axis = C⁻¹ · r``). Both are stored; loading checks that they agree.

A scanner model is not a single-input operator: :meth:`ScannerModel.forward` and
:meth:`ScannerModel.inverse` refuse with a message; use :meth:`ScannerModel.axis`.
"""
from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import Field, SerializeAsAny, ValidationInfo, field_validator, model_validator

from .base import ModelError, StreamingOperator
from .models import HysteresisModel, model_from_dict

AXES: tuple[str, ...] = ("x", "y", "z")


class ScannerModel(HysteresisModel):
    """Per-axis models and the 3×3 coupling matrix with its inverse (module docstring)."""

    kind: Literal["scanner"] = "scanner"
    axes: dict[Literal["x", "y", "z"], SerializeAsAny[HysteresisModel] | None] = Field(
        description="per-axis model (u [V] → displacement [nm]) or null for the linear calibration")
    coupling: list[list[float]] = Field(default_factory=lambda: np.eye(3).tolist(),
                                        description="3×3 C: actual displacement = C · axis displacement [nm/nm]")
    coupling_inverse: list[list[float]] | None = Field(None, description="C⁻¹ (computed when omitted)")

    @field_validator("axes", mode="before")
    @classmethod
    def _axes(cls, v: Any) -> Any:
        if not isinstance(v, dict):
            raise ValueError("expected an object with keys x, y, z")
        out = {}
        for axis, m in v.items():
            if m is not None and not isinstance(m, HysteresisModel):
                m = model_from_dict(m, where=f"axes.{axis}")
            if m is not None and m.kind == "scanner":
                raise ValueError(f"axes.{axis}: a scanner model cannot hold a scanner model")
            out[axis] = m
        return out

    @field_validator("coupling")
    @classmethod
    def _coupling(cls, v: list[list[float]]) -> list[list[float]]:
        C = np.asarray(v, dtype=float)
        if C.shape != (3, 3) or not np.all(np.isfinite(C)):
            raise ValueError("need a 3×3 matrix of finite numbers")
        if np.linalg.cond(C) > 1e6:
            raise ValueError("the matrix is singular (condition number > 1e6)")
        return v

    @field_validator("coupling_inverse")
    @classmethod
    def _inverse(cls, v: list[list[float]] | None, info: ValidationInfo) -> list[list[float]] | None:
        if v is None or "coupling" not in info.data:
            return v
        given = np.asarray(v, dtype=float)
        C = np.asarray(info.data["coupling"], dtype=float)
        if given.shape != (3, 3) or not np.allclose(given @ C, np.eye(3), atol=1e-6):
            raise ValueError("is not the inverse of coupling (tolerance 1e-6)")
        return v

    @model_validator(mode="after")
    def _fill_inverse(self) -> "ScannerModel":
        if self.coupling_inverse is None:
            self.coupling_inverse = np.linalg.inv(np.asarray(self.coupling, dtype=float)).tolist()
        return self

    def axis(self, name: str) -> HysteresisModel | None:
        """The model of axis ``name`` (x, y or z), None where the file has none."""
        if name not in AXES:
            raise ModelError(f"axis: {name!r}; allowed x, y, z")
        return self.axes.get(name)  # type: ignore[call-overload]

    def inverse_coupling(self) -> np.ndarray:
        """``C⁻¹`` as a (3, 3) array."""
        return np.asarray(self.coupling_inverse, dtype=float)

    def forward(self, dt_s: float | None = None) -> StreamingOperator:
        raise ModelError("kind scanner: a scanner model holds one model per axis; choose one (e.g. --axis x)")

    def inverse(self, dt_s: float | None = None) -> StreamingOperator:
        return self.forward(dt_s)

    def describe_axis(self, name: str) -> str:
        """``preisach+creep`` / ``pi`` / ``none`` for axis ``name``."""
        m = self.axis(name)
        return "none" if m is None else getattr(m, "structure", m.kind)

    def summary(self) -> str:
        C = np.asarray(self.coupling)
        lines = ["model            : scanner (per-axis models + coupling)"]
        for a in AXES:
            lines.append(f"  {a}: {self.describe_axis(a)}")
        lines.append("coupling C      : " + "; ".join(" ".join(f"{v:.6g}" for v in row) for row in C))
        return "\n".join(lines)

    @classmethod
    def identify(cls, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, **options: Any) -> "ScannerModel":
        raise ModelError("kind scanner: identify each axis (e.g. --model auto) and combine them with "
                         "afmctl.compensators.scanner_model.ScannerModel(axes=..., coupling=...)")


def estimate_coupling(driven_nm: dict[int, np.ndarray], passive_nm: dict[int, dict[int, np.ndarray]]) -> np.ndarray:
    """``C`` from runs where one axis at a time is driven: for each driven axis *j*,
    ``C[i, j]`` = least-squares slope of axis *i*'s motion on axis *j*'s motion [nm/nm]
    (both measured from their first sample). ``driven_nm[j]``: axis *j*'s displacement;
    ``passive_nm[j][i]``: axis *i*'s displacement in the same run."""
    C = np.eye(3)
    for j, yj in driven_nm.items():
        d = np.asarray(yj, float) - float(yj[0])
        for i, yi in passive_nm.get(j, {}).items():
            o = np.asarray(yi, float) - float(yi[0])
            C[i, j] = float(np.dot(d, o) / max(float(np.dot(d, d)), 1e-12))
    return C
