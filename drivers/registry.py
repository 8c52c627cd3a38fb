"""Open an amplifier by driver name and port.

>>> amp = open_amplifier("mdt693b", "/dev/ttyUSB0", host_limits=(0.0, 100.0))  # doctest: +SKIP
>>> amp = open_amplifier("can", "virtual:afm0")                                 # doctest: +SKIP

Serial ports are anything pyserial's ``serial_for_url`` opens (a device path, a pty
path, ``socket://host:port``, ``rfc2217://...``); CAN ports are ``INTERFACE:CHANNEL`` for
python-can (``virtual:afm0``, ``socketcan:can0``). Every driver class builds its own
transport from the URL (:meth:`afmctl.drivers.base.Amplifier.open`), so opening has no
per-driver branches; another backend joins with :func:`register`.
"""
from __future__ import annotations

import importlib
from typing import Any

from .base import Amplifier
from .errors import AmplifierConnectionError

#: driver name -> "module:Class" (imported on first use)
_DRIVERS: dict[str, str] = {}


def register(name: str, target: "str | type[Amplifier]") -> None:
    """Make ``target`` (an :class:`Amplifier` subclass or ``"module:Class"``) openable as ``name``."""
    if not isinstance(target, str):
        target = f"{target.__module__}:{target.__qualname__}"
    _DRIVERS[name.lower()] = target


for _name, _target in (("mdt693b", "afmctl.drivers.mdt:MDT693B"), ("mdt694b", "afmctl.drivers.mdt:MDT694B"),
                       ("gcs", "afmctl.drivers.gcs:GCSAmplifier"), ("nv200", "afmctl.drivers.nv200:NV200"),
                       ("can", "afmctl.drivers.can_amp:CANAmplifier")):
    register(_name, _target)


def driver_names() -> tuple[str, ...]:
    """Names :func:`open_amplifier` accepts."""
    return tuple(_DRIVERS)


def driver_class(driver: str) -> type[Amplifier]:
    """The class registered as ``driver`` (AmplifierConnectionError naming the choices if none)."""
    target = _DRIVERS.get(driver.lower())
    if target is None:
        raise AmplifierConnectionError(f"unknown driver {driver!r}; choose one of {', '.join(_DRIVERS)}")
    module, _, cls_name = target.partition(":")
    return getattr(importlib.import_module(module), cls_name)


def open_amplifier(driver: str, port: str, *, baudrate: int | None = None, timeout_s: float = 0.5,
                   write_timeout_s: float | None = None, **options: Any) -> Amplifier:
    """Connect to an amplifier and return it connected (limits read, output read back).

    ``driver``: one of :func:`driver_names`. ``timeout_s`` bounds every read/write [s].
    ``options`` go to the driver: ``host_limits=(min_V, max_V)`` or
    ``{"x": (min_V, max_V), ...}``, ``max_step_V``, ``reconnect_timeout_s``, and
    driver-specific ones (``max_in_flight`` for MDT, ``check_every``/``n_axes`` for GCS).
    """
    return driver_class(driver).open(port, baudrate=baudrate, timeout_s=timeout_s,
                                     write_timeout_s=write_timeout_s, **options)
