"""Model files: pydantic models saved as JSON with a ``kind`` field.

Every hysteresis/creep model class derives from :class:`HysteresisModel` and is listed in
:data:`KINDS` (``kind`` → ``"module:Class"``), imported lazily so that loading one kind
does not import the others.

A model maps input voltage ``u`` [V] to displacement ``y`` [nm]:

* ``model.forward(dt_s)`` → :class:`~afmctl.compensators.base.StreamingOperator` u[V] → y[nm]
* ``model.inverse(dt_s)`` → :class:`~afmctl.compensators.base.StreamingOperator` y[nm] → u[V]
  (the feedforward compensator)
* ``Model.identify(t_s, u_V, y_nm, **options)`` → a fitted model (classmethod)

``dt_s`` is the sample period in seconds; rate-independent models ignore it.
"""
from __future__ import annotations

import importlib
import json
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError

from .base import ModelError, StreamingOperator

#: kind → "module:Class". Add a line here when a new model kind lands.
KINDS: dict[str, str] = {
    "pi": "afmctl.compensators.pi:PIModel",
    "epi": "afmctl.compensators.epi:EPIModel",
    "creep": "afmctl.compensators.creep:LinearCreepModel",
    "preisach": "afmctl.compensators.preisach:PreisachModel",
    "bouc-wen": "afmctl.compensators.bouc_wen:BoucWenModel",
    "dynamics": "afmctl.compensators.dynamics:LinearDynamicsModel",
    "chain": "afmctl.compensators.chain:ChainModel",
    "scanner": "afmctl.compensators.scanner_model:ScannerModel",
}


class HysteresisModel(BaseModel):
    """Base of every model file. Subclasses set ``kind: Literal["..."]``."""

    model_config = ConfigDict(extra="forbid", frozen=False)

    kind: str
    #: which model kinds are time-dependent (need a uniform sample period)
    time_dependent: ClassVar[bool] = False

    def forward(self, dt_s: float | None = None) -> StreamingOperator:  # pragma: no cover
        raise NotImplementedError

    def inverse(self, dt_s: float | None = None) -> StreamingOperator:  # pragma: no cover
        raise NotImplementedError

    @classmethod
    def identify(cls, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, **options: Any) -> "HysteresisModel":  # pragma: no cover
        raise NotImplementedError

    def summary(self) -> str:
        """A few human-readable lines for ``afmctl model show``."""
        return json.dumps(self.model_dump(mode="json"), indent=2)


def model_class(kind: str) -> type[HysteresisModel]:
    """The class registered for ``kind``; :class:`ModelError` for an unknown kind."""
    try:
        target = KINDS[kind]
    except KeyError:
        raise ModelError(f"kind: unknown model kind {kind!r}; allowed: {', '.join(sorted(KINDS))}") from None
    module_name, cls_name = target.split(":")
    return getattr(importlib.import_module(module_name), cls_name)


def format_validation_error(err: ValidationError, where: str) -> str:
    """One line ``WHERE: field a.b: message`` for the first error of ``err``."""
    first = err.errors()[0]
    loc = ".".join(str(p) for p in first["loc"]) or "(root)"
    return f"{where}: field {loc}: {first['msg']}"


def read_json_file(path: str | Path, what: str = "model file") -> Any:
    """Decode a JSON file; :class:`ModelError` naming the file for I/O and syntax errors."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as err:
        raise ModelError(f"{p}: cannot read {what} ({err.strerror})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise ModelError(f"{p}: not valid JSON (line {err.lineno}: {err.msg})") from None


def model_from_dict(data: Any, where: str = "model") -> HysteresisModel:
    """Validate a decoded JSON object into the model class named by its ``kind``."""
    if not isinstance(data, dict):
        raise ModelError(f"{where}: expected a JSON object with a 'kind' field")
    kind = data.get("kind")
    if not isinstance(kind, str):
        raise ModelError(f"{where}: missing field 'kind' (one of {', '.join(sorted(KINDS))})")
    cls = model_class(kind)
    try:
        return cls.model_validate(data)
    except ValidationError as err:
        raise ModelError(format_validation_error(err, where)) from None


def load_model(path: str | Path, expect: tuple[str, ...] | None = None) -> HysteresisModel:
    """Read a model JSON file. ``expect`` restricts the accepted kinds."""
    p = Path(path)
    model = model_from_dict(read_json_file(p), where=str(p))
    if expect is not None and model.kind not in expect:
        raise ModelError(f"{p}: field kind: {model.kind!r} is not accepted here; allowed: {', '.join(expect)}")
    return model


def save_model(model: HysteresisModel, path: str | Path) -> None:
    """Write a model as pretty JSON (floats at full precision)."""
    p = Path(path)
    try:
        p.write_text(json.dumps(model.model_dump(mode="json"), indent=2) + "\n", encoding="utf-8")
    except OSError as err:
        raise ModelError(f"{p}: cannot write model file ({err.strerror})") from None
