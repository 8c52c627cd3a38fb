"""The loop thread as a producer for a link that buffers (``[amplifier] output = "stream"``).

:class:`StreamMachine` runs the same trajectory → pipeline (with its preview horizon) →
safety chain as :class:`afmctl.control.machine.LoopMachine`, but instead of sending one
setpoint per tick it queues samples ahead into the amplifier's stream FIFO, which plays
them on its own clock (sample k at t0 + k / ``loop.rate_Hz``). It wakes every poll period;
when the FIFO holds less than ``amplifier.low_water_s`` of samples it computes and queues
enough to reach ``amplifier.high_water_s`` (:class:`afmctl.control.stream_producer.StreamProducer`'s
water marks). A host stall shorter than the low water mark never reaches the tip.

Every queued sample passes the safety layer's limiter (limits; at most the slew limit per
sample period, less one frame quantum: samples play exactly one period apart) and goes into
the run log with ``t_s`` = its play time on the amplifier's clock (since the stream began).
Modes as in the setpoint loop: the start ramps (``safety.ramp_V_per_s``) from the read-back
voltage to the first sample, ``settle`` reaches the last setpoint, ``finish`` ramps to the
safe value (or holds) and then the FIFO drains. Estop: the FIFO is flushed at once (the
output holds where playing stopped, read back; queued samples after that point are never
played: an ``estop-flush`` event says from which ``seq``), then a ramp to the safe value at
the slew limit is queued and played. A link error ends the run in ``fault`` (the amplifier
plays out or holds; no reconnect while streaming).

Statistics (``stats()["stream"]``): device ``underruns``, the ``lowest_level`` of the FIFO
[samples] the amplifier reported while playing, ``queued`` samples; the lateness
histogram counts how late the producer woke (host lateness).
"""
from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from . import stats as loop_stats
from .machine import FAULT_ERRORS, LoopMachine, Mode, State
from .stream_producer import StreamProducer


#: samples queued per driver call while topping up (a multiple of the CAN FD frame's 10)
QUEUE_CHUNK = 50


def sleep_to_next_wake(ctl: Any, next_wake_s: float, poll_s: float) -> float:
    """A producer's wait: sleep until ``next_wake_s + poll_s`` (perf_counter [s]), count how
    late it woke in the controller's lateness histogram (host lateness) and, more than a poll
    period late, as a missed deadline (the schedule then restarts from now). Returns the
    wake-up time the next wait starts from."""
    perf = time.perf_counter
    next_wake_s += poll_s
    rem = next_wake_s - perf()
    if rem > 0:
        time.sleep(rem)
    late = max(perf() - next_wake_s, 0.0)
    loop_stats.add(ctl._hist, late)
    ctl._late_max = max(ctl._late_max, late)
    if late > poll_s:
        ctl._missed += 1
        next_wake_s = perf()
    return next_wake_s


class StreamMachine(LoopMachine):
    """One stream-mode run of the loop thread of ``ctl`` (see the module docstring)."""

    def __init__(self, ctl: Any) -> None:
        super().__init__(ctl)
        cfg = ctl.config
        self.producer = StreamProducer(ctl.amplifier, self.safety, cfg.loop.rate_Hz,
                                       cfg.amplifier.low_water_s, cfg.amplifier.high_water_s)
        self.max_step_V = self.producer.max_step_V
        prod = self.producer
        self.poll_s = max(min(prod.high - prod.low, prod.low) / cfg.loop.rate_Hz / 4, 0.0005)
        self.produced = 0                                  # samples computed since the stream began
        self.done = False                                  # nothing more to produce
        self.stall = getattr(ctl, "stream_stall_hook", None)  # test hook: called once per wake
        #: whole chunks through pipeline.block (== step bit for bit) when no drift predictor
        self.batch_ok = getattr(self.pipe, "drift", None) is None and getattr(self.pipe, "kalman", None) is None

    # ------------------------------------------------------------------ main loop
    def run(self) -> None:
        ctl = self.ctl
        if not self._synced_or_ended():
            return
        try:
            self._start_stream()
            self._produce_loop()
            if ctl._request == "estop":
                self._estop_flush_and_ramp()
            else:
                ctl.amplifier.drain_stream()
            if not self._wait_played(estop_check=ctl._request != "estop"):
                self._estop_flush_and_ramp()    # an estop while the FIFO played out
                self._wait_played(estop_check=False)
        except FAULT_ERRORS as err:
            ctl._enter_fault(err)
            ctl._event("stream-fault", "link lost while streaming: the amplifier plays out its FIFO, then holds")
            self.in_fault = True
        self._update_stream_stats()
        self._end_of_run()

    def _start_stream(self) -> None:
        prod = self.producer
        st = self.ctl.amplifier.start_stream(prod.rate_Hz, prefill=prod.high)
        capacity = int(st.capacity)
        if prod.high > capacity:
            raise ValueError(f"amplifier.high_water_s: {prod.high} samples do not fit the amplifier's FIFO of "
                             f"{capacity} samples at {prod.rate_Hz:g} Hz")
        prod._queued = 0
        self.ctl._event("stream", f"device-timed output at {prod.rate_Hz:g} Hz, FIFO {prod.low}..{prod.high} samples")

    def _produce_loop(self) -> None:
        """Wake every poll period; top the FIFO up to the high mark when below the low mark."""
        ctl, prod = self.ctl, self.producer
        perf = time.perf_counter
        next_wake = perf()
        while not self.done:
            if ctl._request is not None:
                self._take_request()
                if ctl._request == "estop":
                    return
            level = prod._queued - prod._played()
            if level < prod.low or prod._queued == 0:
                self._top_up(prod.high - level)
            if self.stall is not None:
                self.stall()
            next_wake = sleep_to_next_wake(ctl, next_wake, self.poll_s)
            self._update_stream_stats()

    def _top_up(self, n: int) -> None:
        """Compute up to ``n`` samples (fewer when the trajectory has none now) and queue them
        in chunks of :data:`QUEUE_CHUNK` as they are computed, so that the FIFO fills while the
        rest is still being computed."""
        rows: list[tuple[float, float, float]] = []
        left = n
        while left > 0 and not self.done:     # done: the finish ramp has reached its goal
            batch = self._produce_batch(min(left, QUEUE_CHUNK))
            if batch is None:
                row = self._produce_one()
                if row is None:
                    break
                batch = [row]
            rows.extend(batch)
            left -= len(batch)
            if len(rows) >= QUEUE_CHUNK:
                self._queue(rows)
                rows = []
        if rows:
            self._queue(rows)

    def _produce_batch(self, n: int) -> list[tuple[float, float, float]] | None:
        """Fast path while playing the trajectory: up to ``n`` samples of the current block
        through ``pipeline.block`` at once (bit for bit what ``step`` gives; only without a
        drift predictor, whose heat input is the output itself), else None."""
        ctl, pipe = self.ctl, self.pipe
        if (not self.batch_ok or self.mode is not Mode.RUN or self.need_ramp or self.ramping
                or self.cur is not None or not self.primed or ctl._state is not State.RUNNING or ctl._drift_meas):
            return None
        blk = self.blk
        k = 0 if blk is None else min(n, (len(blk) - self.bi) // 3)
        if k < 2:
            return None
        inp = np.asarray(blk[self.bi:self.bi + 3 * k], dtype=np.float64).reshape(k, 3)
        self.bi += 3 * k
        self.watchdog.feed(self.now_s)
        if self.latency:
            self.hold_left = self.latency
        d, c, u = pipe.block(inp, self.T_C, np.zeros((k, 3)))
        aims, out = self.aims, []
        for tgt, cor, dd, uu in zip(inp.tolist(), c.tolist(), d.tolist(), u.tolist()):
            tgt, cor, dd = tuple(tgt), tuple(cor), tuple(dd)
            if self.latency:
                self.last_in = tgt
                aims.append((tgt, cor, dd))
                tgt, cor, dd = aims.popleft()
            self.last_tgt, self.last_cor, self.last_d = tgt, cor, dd
            self.last_u_cmd = tuple(uu)
            out.append(self._queue_row(self._limit_row(uu)))
        return out

    def _queue(self, rows: list[tuple[float, float, float]]) -> None:
        self.ctl.amplifier.queue(rows)
        self.producer._queued += len(rows)

    # ------------------------------------------------------------------ one sample
    def _produce_one(self) -> tuple[float, float, float] | None:
        """The next sample to queue (recorded), or None (none now, or the run is over)."""
        mode = self.mode
        if mode is Mode.RUN:
            if self.cur is None and not self._next_sample():
                return self._stalled_row()
            cur = self.cur
            if self.need_ramp:
                self.need_ramp = False
                self.ramping = True
            if self.ramping:
                row, reached = self._ramp_row(cur[6:9], self.ramp_rate_V_per_s)
                if reached:
                    self.ramping = False
                    self.cur = None
                    self.ctl._event("ramp-done")
                return self._queue_row(row)
            self.cur = None
            return self._queue_row(self._limit_row(cur[6:9]))
        if mode is Mode.SETTLE:
            row, reached = self._ramp_row(self.last_u_cmd, self.safety.slew_V_per_s)
            if reached:
                self.mode = Mode.FINISH
            return self._queue_row(row)
        if self.finish_hold:
            self.done = True
            return None
        row, reached = self._ramp_row(self.safe_V_xyz(), self.finish_rate_V_per_s)
        if reached:
            self.done = True
        return self._queue_row(row)

    def _stalled_row(self) -> tuple[float, float, float] | None:
        """No trajectory sample now: with ``on_stall = "safe"`` while holding, a ramp sample
        towards the safe value; otherwise nothing (the FIFO plays out, then holds)."""
        if self.mode is not Mode.RUN:    # the trajectory ended: settle / finish next
            return self._produce_one()
        if self.ctl._state is State.HOLDING and self.on_stall == "safe":
            row, _ = self._ramp_row(self.safe_V_xyz(), self.ramp_rate_V_per_s)
            return self._queue_row(row)
        return None

    def _stall_action(self) -> None:
        """Nothing is sent from here in stream mode (see :meth:`_stalled_row`)."""

    def safe_V_xyz(self) -> list[float]:
        return self.safety.xyz(self.safe_V, fill=math.nan)

    def _limit_row(self, u_xyz: Any) -> tuple[float, float, float]:
        """``u_xyz`` [V] through the safety limiter (limits, slew per sample); counted."""
        s = self.safety
        m = self.max_step_V
        new = [s.limit(i, float(u_xyz[k]), m) for i, k in enumerate(s.index)]
        s.last[:] = new
        x, y, z = s.xyz(new, fill=0.0)
        return (x, y, z)

    def _ramp_row(self, u_xyz: Any, rate_V_per_s: float) -> tuple[tuple[float, float, float], bool]:
        """One ramp sample towards ``u_xyz`` [V] (clamped into the limits; NaN: hold) at
        ``rate_V_per_s`` (capped by the slew limit); True when it is the goal."""
        s = self.safety
        m = min(min(rate_V_per_s, s.slew_V_per_s) * self.period_s, self.max_step_V)
        reached = True
        for i, k in enumerate(s.index):
            t = float(u_xyz[k])
            if not math.isfinite(t):
                t = s.last[i]
            t = min(max(t, s.lo[i]), s.hi[i])
            d = t - s.last[i]
            if d > m:
                t, reached = s.last[i] + m, False
            elif d < -m:
                t, reached = s.last[i] - m, False
            s.last[i] = t
        x, y, z = s.xyz(s.last, fill=0.0)
        return (x, y, z), reached

    def _queue_row(self, row: tuple[float, float, float]) -> tuple[float, float, float]:
        """Record the sample (``t_s`` = its play time on the amplifier's clock)."""
        self.ctl._tick = self.produced
        self.produced += 1
        self._record()
        return row

    # ------------------------------------------------------------------ end of run
    def _estop_flush_and_ramp(self) -> None:
        """Flush the FIFO (output holds where it stopped), then queue a ramp to the safe
        value at the slew limit and let it play."""
        ctl, prod, s = self.ctl, self.producer, self.safety
        played = prod._played()
        first_unplayed = ctl._seq - (prod._queued - played)
        held = ctl.amplifier.flush_stream()
        ctl._event("estop-flush", f"FIFO flushed: samples from seq {first_unplayed} on were not played; "
                                  f"output held at {held}")
        s.last[:] = [held[a] for a in s.axes]
        ramp = []
        while True:
            row, reached = self._ramp_row(self.safe_V_xyz(), s.slew_V_per_s)
            ramp.append(self._queue_row(row))
            if reached:
                break
        prod._underruns_before = prod.stats.underruns
        ctl.amplifier.start_stream(prod.rate_Hz, prefill=int(min(prod.high, len(ramp))))
        prod._queued = 0
        prod._queue_paced(ramp)
        prod.stats.ramp_samples = len(ramp)
        ctl.amplifier.drain_stream()

    def _wait_played(self, estop_check: bool, timeout_s: float = 60.0) -> bool:
        """Wait until the amplifier has played everything (its stream idle); False when an
        estop came first (``estop_check``)."""
        ctl = self.ctl
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if estop_check and ctl._request == "estop":
                ctl._event("estop")
                return False
            st = ctl.amplifier.buffer_status()
            if st.state in ("idle", "fault"):
                return True
            time.sleep(0.005)
        ctl._event("stream-timeout", f"the amplifier's stream did not drain within {timeout_s:g} s")
        return True

    def _update_stream_stats(self) -> None:
        self.ctl._stream_stats = self.producer.status()

    def _end_of_run(self) -> None:
        ctl = self.ctl
        if ctl._state not in (State.FAULT, State.STOPPED):
            ctl._set_state(State.STOPPED, "stopped")

