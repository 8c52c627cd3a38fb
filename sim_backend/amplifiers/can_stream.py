"""The buffered-stream FIFO of the simulated CAN amplifier, sans-I/O (no thread, no bus).

A :class:`StreamPlayer` receives samples stamped with their arrival time [s] and plays
them on its own clock: sample tick k happens at exactly ``t0 + k / rate_Hz``, where t0 is
the arrival time of the first sample after a start. At a tick the oldest sample that had
arrived by then is applied; an empty FIFO at a tick counts an underrun and the output
holds. Timing jitter is zero by construction: the times handed to the sink are computed,
never measured. :meth:`run_until` is called by the amplifier's player thread (or a test)
with the amplifier's clock; a late call plays the overdue ticks with their own times.
"""
from __future__ import annotations

import collections
import enum
from collections.abc import Callable
from dataclasses import dataclass


class StreamState(enum.IntEnum):
    """STREAM_STATE of the DBC's STREAM_STATUS frame."""

    IDLE = 0
    ARMED = 1  # started, waiting for sample 0
    PLAYING = 2
    DRAINING = 3  # plays what is queued, then IDLE (no underruns counted)
    FAULT = 4


@dataclass(frozen=True)
class StreamStatus:
    level: int
    underruns: int
    played_seq: int
    state: StreamState
    capacity_log2: int
    overflows: int


class StreamPlayer:
    """``StreamPlayer(apply, capacity_log2=12)``; ``apply(values, t_s)`` is called for every
    played sample with ``values`` a tuple (x_V, y_V, z_V) and ``t_s`` its tick time."""

    def __init__(self, apply: Callable[[tuple[float, float, float], float], None], capacity_log2: int = 12) -> None:
        self.apply = apply
        self.capacity_log2 = int(capacity_log2)
        self.capacity = 1 << self.capacity_log2
        self._fifo: collections.deque[tuple[float, int, tuple[float, float, float]]] = collections.deque()
        self.state = StreamState.IDLE
        self.rate_Hz = 0.0
        self.t0_s = 0.0
        self.tick = 0
        self.underruns = 0
        self.overflows = 0
        self.gaps = 0
        self.played = 0
        self.played_seq = 0xFFFF
        self.expected_seq = 0

    # -- host commands --
    def start(self, rate_Hz: float, prefill: int = 1) -> None:
        """Empty the FIFO and arm: the clock starts at ``rate_Hz`` when ``prefill`` samples
        are queued (t0 = the arrival of that sample; all of them are there by then)."""
        self._fifo.clear()
        self.prefill = max(1, int(prefill))
        self.rate_Hz = float(rate_Hz)
        self.tick = 0
        self.underruns = 0
        self.overflows = 0
        self.expected_seq = 0
        self.played_seq = 0xFFFF
        self.state = StreamState.ARMED

    def flush(self) -> None:
        """Empty the FIFO and stop at once; the output holds its last value."""
        self._fifo.clear()
        self.state = StreamState.IDLE

    def drain(self, now_s: float) -> None:
        """Play what is queued (starting the clock at ``now_s`` if still armed), then stop."""
        if self.state is StreamState.ARMED and self._fifo:
            self.t0_s = now_s
            self.state = StreamState.DRAINING
        elif self.state is StreamState.PLAYING:
            self.state = StreamState.DRAINING
        elif self.state is StreamState.ARMED:  # nothing queued
            self.state = StreamState.IDLE

    def fault(self) -> None:
        self._fifo.clear()
        self.state = StreamState.FAULT

    def push(self, seq: int, values: tuple[float, float, float], t_arrival_s: float) -> str | None:
        """Queue one sample that arrived at ``t_arrival_s``; returns ``"gap"``, ``"overflow"``,
        ``"idle"`` (not started: refused) or None."""
        if self.state not in (StreamState.ARMED, StreamState.PLAYING, StreamState.DRAINING):
            return "idle"
        if len(self._fifo) >= self.capacity:
            self.overflows += 1
            return "overflow"
        outcome = None
        if seq != self.expected_seq:
            self.gaps += 1
            outcome = "gap"
        self.expected_seq = (seq + 1) & 0xFFFF
        self._fifo.append((t_arrival_s, seq, values))
        if self.state is StreamState.ARMED and len(self._fifo) >= self.prefill:
            self.state = StreamState.PLAYING
            self.t0_s = t_arrival_s
        return outcome

    # -- the amplifier's clock --
    def tick_time_s(self, k: int) -> float:
        """Time of tick ``k`` [s]: ``t0 + k / rate_Hz`` exactly."""
        return self.t0_s + k / self.rate_Hz

    def run_until(self, now_s: float) -> int:
        """Play every tick due at or before ``now_s``; returns how many ticks passed."""
        n = 0
        while self.state in (StreamState.PLAYING, StreamState.DRAINING):
            t_k = self.tick_time_s(self.tick)
            if t_k > now_s:
                break
            if self._fifo and self._fifo[0][0] <= t_k:
                _, seq, values = self._fifo.popleft()
                self.played_seq = seq
                self.played += 1
                self.apply(values, t_k)
                skip = 1
            elif self.state is StreamState.DRAINING and not self._fifo:
                self.state = StreamState.IDLE
                break
            else:  # empty (or the head arrives later): every tick up to then is an underrun
                skip = self._ticks_through(min(now_s, self._fifo[0][0]) if self._fifo else now_s)
                if self._fifo and skip > 1 and self.tick_time_s(self.tick + skip - 1) >= self._fifo[0][0]:
                    skip -= 1  # the head is there at its arrival tick: that one plays
                self.underruns += skip
            self.tick += skip
            n += skip
        return n

    def _ticks_through(self, t_s: float) -> int:
        """How many ticks from the current one lie at or before ``t_s`` (at least 1: the
        current tick is due). Computed, then corrected against :meth:`tick_time_s`."""
        k = max(self.tick, int((t_s - self.t0_s) * self.rate_Hz))
        while self.tick_time_s(k + 1) <= t_s:
            k += 1
        while k > self.tick and self.tick_time_s(k) > t_s:
            k -= 1
        return k - self.tick + 1

    def next_tick_s(self) -> float | None:
        """When the next tick is due [s], or None when not playing."""
        if self.state in (StreamState.PLAYING, StreamState.DRAINING):
            return self.tick_time_s(self.tick)
        return None

    def status(self) -> StreamStatus:
        return StreamStatus(len(self._fifo), self.underruns, self.played_seq, self.state, self.capacity_log2,
                            self.overflows)
