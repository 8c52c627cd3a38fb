"""Open an amplifier by driver name and port.

>>> amp = open_amplifier("mdt693b", "/dev/ttyUSB0", host_limits=(0.0, 100.0))  # doctest: +SKIP
>>> amp = open_amplifier("can", "virtual:afm0")                                 # doctest: +SKIP

Serial ports are anything pyserial's ``serial_for_url`` opens (a device path, a pty
path, ``socket://host:port``, ``rfc2217://...``); CAN ports are ``INTERFACE:CHANNEL`` for
python-can (``virtual:afm0``, ``socketcan:can0``).
"""
from __future__ import annotations

from .base import Amplifier

#: driver name -> (module, class)
DRIVERS: dict[str, tuple[str, str]] = {
    "mdt693b": ("afmctl.drivers.mdt", "MDT693B"),
    "mdt694b": ("afmctl.drivers.mdt", "MDT694B"),
    "gcs": ("afmctl.drivers.gcs", "GCSAmplifier"),
    "nv200": ("afmctl.drivers.nv200", "NV200"),
    "can": ("afmctl.drivers.can_amp", "CANAmplifier"),
}


def open_amplifier(driver: str, port: str, *, baudrate: int | None = None, timeout_s: float = 0.5,
                   write_timeout_s: float | None = None, **options) -> Amplifier:
    """Connect to an amplifier and return it connected (limits read, output read back).

    ``driver``: one of :data:`DRIVERS`. ``timeout_s`` bounds every read/write [s].
    ``options`` go to the driver: ``host_limits=(min_V, max_V)`` or
    ``{"x": (min_V, max_V), ...}``, ``max_step_V``, ``reconnect_timeout_s``, and
    driver-specific ones (``max_in_flight`` for MDT, ``check_every``/``n_axes`` for GCS).
    """
    import importlib

    from .errors import AmplifierConnectionError
    name = driver.lower()
    if name not in DRIVERS:
        raise AmplifierConnectionError(f"unknown driver {driver!r}; choose one of {', '.join(DRIVERS)}")
    module, cls_name = DRIVERS[name]
    cls = getattr(importlib.import_module(module), cls_name)
    if name == "can":
        from .transport_can import CanTransport
        return cls(CanTransport(port, **({"bitrate": baudrate} if baudrate else {})), timeout_s=timeout_s, **options)
    from .transport import SerialTransport
    transport = SerialTransport(port, baudrate=baudrate or cls.default_baudrate, timeout_s=timeout_s,
                                write_timeout_s=write_timeout_s)
    try:
        return cls(transport, **options)
    except BaseException:
        transport.close()
        raise
