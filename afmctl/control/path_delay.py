"""The delay an output path itself adds between a setpoint and the amplifier's output, as the
controller knows it before the run, and the whole loop ticks by which it advances the
setpoints to take it out.

Per ``[amplifier] output``:

* ``setpoints`` over a serial line: a setpoint takes effect when its last byte arrives, one
  setpoint's bytes after the write starts — 1 / (setpoints per second the line carries at
  its baud rate, :data:`LINK_CEILING_PER_S` scaled from 115200 baud) [s]; over TCP and on a
  python-can ``virtual`` bus in this process no transmission time is known in advance (0);
  a CAN frame on a wire: :data:`CAN_FRAME_BITS` at the bus bitrate.
* ``stream``: the samples play on the device's clock, sample k at its tick k: the FIFO's
  prefill puts the output behind the host's clock (reported by the stream's FIFO level), not
  behind the trajectory's samples (0).
* ``wave``: the table is aligned with the target and plays on the device's clock (0).

The loop (:mod:`afmctl.control.machine`) then reads the trajectory ``advance`` ticks further
ahead (``floor(delay / period)``: whole ticks, never more than the delay, so up to one period
stays; rounding up advanced a 115200-baud MDT693B at 200 Hz by a whole 5 ms tick for its
2.6 ms and made its live tip's RMS error 282–324 → 365–438 nm, tests/test_hil_live_tip.py) and records
each output beside the target it reaches, exactly as the preview horizon does
(:mod:`afmctl.control.preview`). Units: s, samples.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

#: three-axis (one-axis for mdt694b/nv200) setpoints per second a link carries at 115200
#: baud, streaming without waiting for replies (docs/PROTOCOLS.md)
LINK_CEILING_PER_S = {"mdt693b": 380.0, "mdt694b": 770.0, "gcs": 600.0, "nv200": 960.0, "can": 7000.0}
#: bits of a classic CAN setpoint frame on the wire (8 data bytes, stuffing included)
CAN_FRAME_BITS = 135
#: CAN bus bitrate [bit/s] when [amplifier.options] does not name one
CAN_DEFAULT_BITRATE = 1_000_000


@dataclass(frozen=True)
class PathDelay:
    """``delay_s`` [s] the path adds before the output changes, ``advance`` [ticks] the loop
    reads ahead to take it out, ``path``: the path in words."""

    delay_s: float
    advance: int
    path: str

    def as_dict(self) -> dict[str, Any]:
        return {"delay_s": self.delay_s, "advance_samples": self.advance, "path": self.path}


def path_delay(config: Any, amp: Any = None) -> PathDelay:
    """The known delay of the configured output path (module docstring), on the link of the
    opened amplifier ``amp`` where given (its transport's URL and baud rate; an amplifier
    without a transport, such as a test's in-memory one, has no link), else as the
    configuration describes it."""
    cfg = config.amplifier
    if cfg.output == "wave":
        return PathDelay(0.0, 0, f"{cfg.driver} wave table on the device's clock, aligned with the target")
    if cfg.output == "stream":
        return PathDelay(0.0, 0, f"{cfg.driver} stream on the device's clock (the FIFO's prefill delays the host's "
                                 "clock, not the samples)")
    name = str(getattr(amp, "name", cfg.driver)) if amp is not None else cfg.driver
    transport = getattr(amp, "transport", None) if amp is not None else None
    if amp is not None and transport is None:
        return PathDelay(0.0, 0, f"host-timed setpoints to an in-memory {name} amplifier (no link)")
    url = str(getattr(transport, "url", None) or cfg.port or "")
    if name == "can":
        interface = getattr(transport, "interface", None) or url.split(":", 1)[0]
        if interface == "virtual" or (transport is None and config.simulation.enabled):
            return PathDelay(0.0, 0, "host-timed setpoints on an in-process CAN bus (no wire)")
        bitrate = float(cfg.options.get("baudrate") or CAN_DEFAULT_BITRATE)
        return _paced(CAN_FRAME_BITS / bitrate, config, f"host-timed setpoints, one CAN frame at {bitrate / 1e3:g} kbit/s")
    if url.startswith("socket://") and not (transport is None and config.simulation.enabled):
        return PathDelay(0.0, 0, f"host-timed {name} setpoints over TCP (no transmission time known)")
    baud = float(getattr(transport, "baudrate", None) or cfg.options.get("baudrate")
                 or (config.simulation.baud if config.simulation.enabled else 115200))
    ceiling = LINK_CEILING_PER_S.get(name)
    if ceiling is None:
        return PathDelay(0.0, 0, f"host-timed {name} setpoints (no transmission time known)")
    return _paced(1.0 / (ceiling * baud / 115200.0), config,
                  f"host-timed {name} setpoints at {baud:g} baud, one setpoint's bytes")


def _paced(delay_s: float, config: Any, path: str) -> PathDelay:
    return PathDelay(delay_s, int(math.floor(delay_s / config.dt_s + 1e-9)), path)


def describe(p: PathDelay, dt_s: float) -> str:
    """``0.88 ms known in advance (path: ...), 0 ticks taken out``."""
    taken = (f"{p.advance} tick{'s' if p.advance != 1 else ''} = {p.advance * dt_s * 1e3:.3g} ms taken out"
             if p.advance else "nothing taken out (under one tick)" if p.delay_s > 0 else "nothing to take out")
    return f"{p.delay_s * 1e3:.3g} ms known in advance ({p.path}); {taken}"
