"""The controller as a producer for a link that buffers (device-timed output).

:class:`StreamProducer` feeds an amplifier with a stream FIFO (today the CAN amplifier's
``start_stream``/``queue``/``latest_buffer_status``/``flush_stream``/``drain_stream``):
it keeps the device's FIFO between a low and a high water mark [s of samples], so the tip
moves on the amplifier's clock and a host stall shorter than the low water mark changes
nothing at the tip. Every sample passes the :class:`afmctl.control.safety.SafetyLayer`'s limiter
before it is queued: inside the limits, and at most ``slew_V_per_s / rate_Hz`` (less the
frame's voltage quantum) from the sample before — samples play exactly one period apart,
so that is the slew limit at the amplifier. :meth:`estop` (any thread) flushes the FIFO
(the output holds where playing stopped, read back) and ramps to the safe value within the
slew limit through the same FIFO.

Statistics: ``host_lateness_s`` (how late the producer woke for a top-up, max), the device
``underruns`` (ticks the amplifier found its FIFO empty) and the lowest FIFO level the
amplifier reported [samples].

:meth:`StreamProducer.run` plays a plain array of voltages (already compensated; see
benchmarks/bench_stream.py). The Controller (``afmctl run`` with ``[amplifier] output =
"stream"``) uses its water marks, limiter, FIFO accounting and estop queueing from
:class:`afmctl.control.stream.StreamMachine`, computing the samples as it goes.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from afmctl.drivers.codec_can import volts_per_bit

from .safety import SafetyLayer

log = logging.getLogger(__name__)


@dataclass
class ProducerStats:
    queued: int = 0
    underruns: int = 0
    host_lateness_max_s: float = 0.0
    lowest_level: int | None = None
    estop: bool = False
    ramp_samples: int = 0
    lateness_s: list[float] = field(default_factory=list)


class StreamProducer:
    """``StreamProducer(amplifier, safety, rate_Hz, low_water_s=0.03, high_water_s=0.06)``.

    ``safety`` is a SafetyLayer on the same amplifier (its limits, slew and safe value);
    ``low_water_s`` < ``high_water_s`` [s]; the high mark must fit the device FIFO."""

    def __init__(self, amplifier, safety: SafetyLayer, rate_Hz: float, low_water_s: float = 0.03,
                 high_water_s: float = 0.06, clock: Callable[[], float] = time.monotonic) -> None:
        if not (math.isfinite(rate_Hz) and rate_Hz >= 1 and rate_Hz == round(rate_Hz)):
            raise ValueError(f"rate_Hz: {rate_Hz!r} must be a whole number of Hz >= 1")
        if not (0 < low_water_s < high_water_s and math.isfinite(high_water_s)):
            raise ValueError(f"low_water_s {low_water_s!r} and high_water_s {high_water_s!r}: "
                             f"need 0 < low < high [s]")
        self.amp = amplifier
        self.safety = safety
        self.rate_Hz = float(rate_Hz)
        self.low = max(1, round(low_water_s * rate_Hz))
        self.high = max(self.low + 1, round(high_water_s * rate_Hz))
        # samples play exactly 1/rate apart: the slew limit per sample, less one frame quantum
        # so that the driver's rounding to 2.5 mV can never make a step larger
        step = min(safety.slew_V_per_s / self.rate_Hz, safety.max_step_V)
        self.max_step_V = max(step - volts_per_bit(), 0.5 * step)
        self.clock = clock
        self.stats = ProducerStats()
        self._estop = threading.Event()
        self._queued = 0
        self._underruns_before = 0

    def estop(self) -> None:
        """Ask the producer (any thread) to flush the device FIFO and ramp to the safe value."""
        self._estop.set()

    def limit_block(self, block_V: np.ndarray) -> list[tuple[float, float, float]]:
        """Rows x, y, z [V] limited sample by sample (limits, slew per period); updates the
        safety layer's reference to the last row."""
        out = []
        s = self.safety
        for row in block_V:
            new = [s.limit(i, float(row[k]), self.max_step_V) for i, k in enumerate(s.index)]
            s.last[:] = new
            out.append(tuple(s.xyz(new, fill=0.0)))
        return out

    def status(self) -> dict:
        """The FIFO figures of ``Controller.stats()["stream"]``: device ``underruns``, the
        ``lowest_level`` [samples] reported while playing, samples ``queued``, the water marks
        [samples] and the estop ramp's length, from the latest STREAM_STATUS (no I/O)."""
        self._played()
        st = self.stats
        return {"underruns": st.underruns, "lowest_level": st.lowest_level, "queued": self._queued,
                "low_water": self.low, "high_water": self.high, "estop_ramp_samples": st.ramp_samples}

    def _played(self) -> int:
        """Samples the amplifier has played, from its last STREAM_STATUS (SEQ unwrapped)."""
        st = self.amp.latest_buffer_status()
        if st is None or st.state == "armed":
            return 0
        self.stats.underruns = self._underruns_before + st.underruns
        if st.state == "playing":
            low = self.stats.lowest_level
            self.stats.lowest_level = st.level if low is None else min(low, st.level)
        return self._queued - ((self._queued - ((st.played_seq + 1) & 0xFFFF)) & 0xFFFF)

    def _queue_paced(self, rows: list[tuple[float, float, float]]) -> None:
        """Queue ``rows`` in chunks that keep the FIFO under the high water mark."""
        k = 0
        while k < len(rows):
            level = self._queued - self._played()
            if level < self.low or self._queued == 0:
                n = min(self.high - level, len(rows) - k)
                self.amp.queue(rows[k:k + n])
                self._queued += n
                k += n
            time.sleep(0.001)

    def run(self, samples_V: np.ndarray, stall: Callable[[], None] | None = None) -> ProducerStats:
        """Stream ``samples_V`` (n × 3: x, y, z [V]) at ``rate_Hz``; ``stall`` is called once
        per top-up cycle (tests inject host stalls there). Returns the statistics."""
        samples = np.asarray(samples_V, dtype=float).reshape(-1, 3)
        self.safety.sync_from_device()
        self.amp.start_stream(self.rate_Hz, prefill=int(min(self.high, len(samples))))
        self._queued = 0
        poll_s = max(min(self.high - self.low, self.low) / self.rate_Hz / 4, 0.0005)
        next_wake = self.clock()
        while self._queued < len(samples) and not self._estop.is_set():
            level = self._queued - self._played()
            if level < self.low or self._queued == 0:
                n = min(self.high - level, len(samples) - self._queued)
                self.amp.queue(self.limit_block(samples[self._queued:self._queued + n]))
                self._queued += n
            if stall is not None:
                stall()
            next_wake += poll_s
            time.sleep(max(next_wake - self.clock(), 0.0))
            late = self.clock() - next_wake
            self.stats.lateness_s.append(late)
            self.stats.host_lateness_max_s = max(self.stats.host_lateness_max_s, late)
            if late > poll_s:
                next_wake = self.clock()
        if self._estop.is_set():
            self._ramp_to_safe()
        else:
            self.amp.drain_stream()
        self._wait_idle()
        self.stats.queued = self._queued
        st = self.amp.buffer_status()
        self.stats.underruns = self._underruns_before + st.underruns
        return self.stats

    def _ramp_to_safe(self) -> None:
        """Estop: empty the FIFO (the output stops where it is), then ramp to the safe value."""
        self.stats.estop = True
        self._underruns_before = self.stats.underruns
        held = self.amp.flush_stream()
        s = self.safety
        s.last[:] = [held[a] for a in s.axes]
        goal = list(s.safe)
        ramp = []
        while [round(v, 9) for v in s.last] != [round(g, 9) for g in goal]:
            ramp.extend(self.limit_block(np.array([s.xyz(goal, fill=0.0)])))
        self.amp.start_stream(self.rate_Hz, prefill=int(min(self.high, len(ramp))))
        self._queued = 0
        self._queue_paced(ramp)
        self.stats.ramp_samples = len(ramp)
        self.amp.drain_stream()
        log.warning("estop: stream flushed at %s V, ramping to the safe value in %d samples", held, len(ramp))

    def _wait_idle(self, timeout_s: float = 60.0) -> None:
        deadline = self.clock() + timeout_s
        while self.clock() < deadline:
            st = self.amp.buffer_status()
            if st.state in ("idle", "fault"):
                return
            time.sleep(0.005)
        raise TimeoutError("the amplifier's stream did not drain")
