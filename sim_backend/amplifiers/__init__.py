"""Simulated piezo amplifiers that speak the real wire protocols (docs/PROTOCOLS.md).

* sans-I/O state machines (bytes in → reply bytes out): :class:`SimMDT693B`
  (``channels=1`` or :func:`SimMDT694B` for the MDT694B), :class:`SimGCS`,
  :class:`SimNV200`;
* :class:`PtyServer` serves one of them on a pty, throttled to its baud rate;
* :class:`SimCANAmplifier` answers the frames of ``drivers/afm_amplifier.dbc`` on a
  python-can bus.

Each drives a *sink* (``sink.apply(volts, t_s)``, e.g. a
:class:`afmctl.sim_backend.scanner.Scanner` or a :class:`RecordingSink`). Nothing is imported
eagerly.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "RecordingSink": "afmctl.sim_backend.amplifiers.base",
    "CsvRecorder": "afmctl.sim_backend.amplifiers.base",
    "SimDevice": "afmctl.sim_backend.amplifiers.base",
    "SimMDT693B": "afmctl.sim_backend.amplifiers.mdt693b",
    "SimMDT694B": "afmctl.sim_backend.amplifiers.mdt693b",
    "SimGCS": "afmctl.sim_backend.amplifiers.gcs",
    "SimNV200": "afmctl.sim_backend.amplifiers.nv200",
    "PtyServer": "afmctl.sim_backend.amplifiers.pty_server",
    "SimCANAmplifier": "afmctl.sim_backend.amplifiers.can_amp",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(name)


def make_device(protocol: str, sink=None, **options):
    """A simulated serial device by protocol name: mdt693b, mdt694b, gcs, nv200."""
    from .gcs import SimGCS
    from .mdt693b import SimMDT693B
    from .nv200 import SimNV200
    p = protocol.lower()
    if p == "mdt693b":
        return SimMDT693B(sink, **options)
    if p == "mdt694b":
        return SimMDT693B(sink, channels=1, **options)
    if p == "gcs":
        return SimGCS(sink, **options)
    if p == "nv200":
        return SimNV200(sink, **options)
    raise ValueError(f"unknown simulated protocol {protocol!r}; choose mdt693b, mdt694b, gcs or nv200")
