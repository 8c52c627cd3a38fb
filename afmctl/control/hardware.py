"""Open the amplifier a configuration names — the hardware path of ``afmctl run`` (and the
path the in-process simulation of :mod:`afmctl.simulation.link` uses too, on its own port)."""
from __future__ import annotations

import logging
from typing import Any

from afmctl.drivers.base import Amplifier

from ..errors import AfmctlError

log = logging.getLogger(__name__)


def open_driver(config: Any, port: str) -> Amplifier:
    """Open ``config.amplifier.driver`` on ``port`` through
    :func:`afmctl.drivers.registry.open_amplifier`, with ``config.amplifier.options`` and
    the configured ``limits_V`` of the scanner's axes as host limits [V]."""
    from afmctl.drivers.registry import open_amplifier
    options = dict(config.amplifier.options)
    if "host_limits" not in options and config.amplifier.limits_V:
        options["host_limits"] = {a: (lim.min_V, lim.max_V) for a, lim in config.amplifier.limits_V.items()
                                  if a in config.scanner.axes}
    try:
        amp = open_amplifier(config.amplifier.driver, port, **options)
    except TypeError as err:  # an option the driver does not take
        raise AfmctlError(f"amplifier.options: {err} (driver {config.amplifier.driver})") from None
    changed = getattr(amp, "changed_settings", None)   # an NV200's stored settings, changed at connect
    if changed and not options.get("restore_settings"):
        log.warning("amplifier.options: restore_settings = true writes %s back when afmctl lets go",
                    ", ".join(f"{k}={v}" for k, v in changed.items()))
    return amp
