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
import tomllib
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, FiniteFloat, ValidationError, field_validator

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
    u_range_V: tuple[FiniteFloat, FiniteFloat] | None = Field(
        default=None, description="input voltage range the model was identified on (lo, hi) [V]; "
                                  "absent in files written before it was recorded")
    #: input–output delay [s]: the model's output answers the input ``delay_s`` earlier
    #: (``y(t) = M[u](t − delay_s)``); estimated by ``afmctl identify`` from measured data
    delay_s: float = Field(default=0.0, ge=0.0, le=1.0, allow_inf_nan=False,
                           description="input–output delay [s], 0…1 s")
    #: which model kinds are time-dependent (need a uniform sample period)
    time_dependent: ClassVar[bool] = False
    #: whether the kind models the input–output delay itself (then ``delay_s`` is its own
    #: fitted parameter, not a shift applied around it)
    has_own_delay: ClassVar[bool] = False
    #: whether ``identify`` takes ``fit_from_index`` (a burn-in: earlier samples only set the memory)
    fits_with_burn_in: ClassVar[bool] = False

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


def first_validation_error(err: ValidationError, prefix: str = "",
                           skip: tuple[str, ...] = ()) -> tuple[dict[str, Any], str]:
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


def read_text_file(path: str | Path, what: str, error: type[Exception] = ModelError) -> str:
    """The text of a UTF-8 file (a leading byte-order mark, as spreadsheets write, is dropped).
    Unreadable, UTF-16 or binary files raise ``error`` with one line naming the file: the one
    place where afmctl turns a user's file into text (model, drift-parameter, configuration and
    simulator settings files)."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as err:
        raise error(f"{p}: cannot read {what} ({err.strerror or err})") from None
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise error(f"{p}: {what} is UTF-16 text; save it as UTF-8")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise error(f"{p}: {what} is not UTF-8 text (byte 0x{raw[err.start]:02x} at offset {err.start}); "
                    "is it a binary file?") from None
    if "\x00" in text:
        raise error(f"{p}: {what} contains NUL bytes; is it a binary file?")
    return text


def decode_text(text: str, fmt: str, where: str, error: type[Exception] = ModelError) -> Any:
    """``text`` decoded as ``fmt`` (``"JSON"`` or ``"TOML"``); bad syntax, integers of more
    than 4300 digits and nesting too deep to decode raise ``error`` with one line naming
    ``where`` (the file)."""
    loads = {"JSON": json.loads, "TOML": tomllib.loads}[fmt]
    try:
        return loads(text)
    except RecursionError:
        raise error(f"{where}: nested too deeply to decode as {fmt}") from None
    except ValueError as err:          # JSONDecodeError and TOMLDecodeError are ValueErrors too
        if isinstance(err, json.JSONDecodeError):
            raise error(f"{where}: not valid JSON (line {err.lineno}: {err.msg})") from None
        if isinstance(err, tomllib.TOMLDecodeError):
            raise error(f"{where}: not valid TOML ({err})") from None
        raise error(f"{where}: a number in it is too long (at most 4300 digits)") from None


def read_json_file(path: str | Path, what: str = "model file") -> Any:
    """Decode a JSON file; :class:`ModelError` naming the file for I/O, encoding and syntax
    errors (:func:`read_text_file`, :func:`decode_text`)."""
    return decode_text(read_text_file(path, what), "JSON", str(path))


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
