"""afmctl: feedforward hysteresis, creep and drift compensation for AFM piezo scanners.

The Python API (docs/PYTHON.md), arrays in and arrays out, units in every name::

    import afmctl
    fit = afmctl.identify("pi", "ident.csv", n_operators=12)      # or t_s=, u_V=, y_nm= arrays
    afmctl.save_model(fit.model, "pi.json")
    check = afmctl.validate(fit.model, t_s, u_V, y_nm)           # held-out error, check.rms_nm
    volts = afmctl.compensate(fit.model, target_nm).u_V          # feedforward voltages [V]
    y_nm = afmctl.predict(model, t_s, u_V)                       # the model's displacement [nm]
    t_s, u_V = afmctl.excite("all", 0.0, 150.0, 50_000.0)        # what to record for identify
    cal = afmctl.calibrate("run.toml", "scanner.json")           # excite, record, identify on the device

``load_model``, ``read_recording``, the result types (``Identified``, ``Validation``,
``Compensated``) and the real-time ``Controller`` complete it. Nothing is imported until a
name is used (``import afmctl`` stays as fast as the command line needs).

The service package: configuration, trajectory sources, the real-time loop, safety, the
zenoh API, run logs, the command line and reports. Model math lives in
:mod:`afmctl.compensators`, amplifier links in :mod:`afmctl.drivers`, the simulated scanner in
:mod:`afmctl.sim_backend`.
"""
from __future__ import annotations

import importlib

TYPE_CHECKING = False  # not typing.TYPE_CHECKING: importing typing would double the import time

__version__ = "0.1.0"

#: public name -> the module that defines it (imported on first use)
_API = {
    "identify": "afmctl.api.identify",
    "Identified": "afmctl.api.identify",
    "read_recording": "afmctl.api.identify",
    "load_model": "afmctl.api.models",
    "save_model": "afmctl.api.models",
    "predict": "afmctl.api.models",
    "validate": "afmctl.api.models",
    "Validation": "afmctl.api.models",
    "Compensated": "afmctl.api.models",
    "LimitsExceeded": "afmctl.api.models",
    "compensate": "afmctl.api.compensation",
    "excite": "afmctl.api.excite",
    "calibrate": "afmctl.api.calibrate",
    "Calibration": "afmctl.api.calibrate",
    "Calibrated": "afmctl.api.calibrate",
    "Controller": "afmctl.control.controller",
    "AfmctlError": "afmctl.errors",
}

__all__ = sorted(_API)

if TYPE_CHECKING:  # the names for type checkers and editors; at run time __getattr__ loads them
    from typing import Any

    from .api.calibrate import Calibrated, Calibration, calibrate
    from .api.compensation import compensate
    from .api.excite import excite
    from .api.identify import Identified, identify, read_recording
    from .api.models import Compensated, LimitsExceeded, Validation, load_model, predict, save_model, validate
    from .control.controller import Controller
    from .errors import AfmctlError


def __getattr__(name: str) -> Any:
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'afmctl' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_API])
