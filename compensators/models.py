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
from pydantic import BaseModel, ConfigDict, Field, FiniteFloat, PrivateAttr, ValidationError, field_validator

from .base import ModelError, StreamingOperator
from .errortext import format_validation_error
from .textfiles import read_json_file

#: kind → "module:Class". Add a line here when a new model kind lands.
KINDS: dict[str, str] = {
    "pi": "afmctl.compensators.pi:PIModel",
    "epi": "afmctl.compensators.epi:EPIModel",
    "creep": "afmctl.compensators.creep:LinearCreepModel",
    "preisach": "afmctl.compensators.preisach:PreisachModel",
    "bouc-wen": "afmctl.compensators.bouc_wen:BoucWenModel",
    "rate-pi": "afmctl.compensators.rate_pi:RatePIModel",
    "rate-bouc-wen": "afmctl.compensators.rate_bouc_wen:RateBoucWenModel",
    "dynamics": "afmctl.compensators.dynamics:LinearDynamicsModel",
    "amplifier": "afmctl.compensators.amplifier:AmplifierModel",
    "chain": "afmctl.compensators.chain:ChainModel",
    "scanner": "afmctl.compensators.scanner_model:ScannerModel",
}


class HysteresisModel(BaseModel):
    """Base of every model file. Subclasses set ``kind: Literal["..."]``."""

    model_config = ConfigDict(extra="forbid", frozen=False)

    kind: str
    u_range_V: tuple[FiniteFloat, FiniteFloat] | None = Field(
        default=None, description="input voltage range the model was identified on (lo, hi) [V]; "
                                  "absent in files written before it was recorded")
    #: input–output delay [s]: the model's output answers the input ``delay_s`` earlier
    #: (``y(t) = M[u](t − delay_s)``); estimated by ``afmctl identify`` from measured data
    delay_s: float = Field(default=0.0, ge=0.0, le=1.0, allow_inf_nan=False,
                           description="input–output delay [s], 0…1 s")
    provenance: dict[str, Any] | None = Field(
        default=None, description="how the model was made (afmctl calibrate: device, identity, recorder rate, "
                                  "settle hold, date, afmctl version, excitation, validation); not used by the model")
    #: which model kinds are time-dependent (need a uniform sample period)
    time_dependent: ClassVar[bool] = False
    #: whether the kind models the input–output delay itself (then ``delay_s`` is its own
    #: fitted parameter, not a shift applied around it)
    has_own_delay: ClassVar[bool] = False
    #: whether ``identify`` takes ``fit_from_index`` (a burn-in: earlier samples only set the memory)
    fits_with_burn_in: ClassVar[bool] = False
    #: whether ``identify`` takes ``exclude`` (one boolean per sample, True for samples left
    #: out of the fit while the model still runs through them: samples not measured)
    fits_exclude: ClassVar[bool] = False
    #: what went wrong in the fit that produced this model (not saved): an optimiser that did
    #: not converge, a parameter on its bound; one short clause each
    #: (:mod:`afmctl.compensators.fit_health`)
    _fit_problems: list[str] = PrivateAttr(default_factory=list)

    @field_validator("u_range_V")
    @classmethod
    def _check_u_range(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not v[0] < v[1]:
            raise ValueError(f"({v[0]:g}, {v[1]:g}) V; need lo < hi")
        return v

    def voltage_range_V(self) -> tuple[float, float] | None:
        """The input voltages (lo, hi) [V] this model is known to describe: the range it was
        identified on, or None when the file does not say."""
        return self.u_range_V

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


def model_from_dict(data: Any, where: str = "model") -> HysteresisModel:
    """Validate a decoded JSON object into the model class named by its ``kind``."""
    if not isinstance(data, dict):
        raise ModelError(f"{where}: expected a JSON object with a 'kind' field")
    kind = data.get("kind")
    if not isinstance(kind, str):
        raise ModelError(f"{where}: missing field 'kind' (one of {', '.join(sorted(KINDS))})")
    try:
        cls = model_class(kind)
    except ModelError as err:
        raise ModelError(f"{where}: {err}") from None
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
