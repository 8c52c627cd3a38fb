"""The loop thread for ``[amplifier] output = "wave"``: a finite trajectory computed whole
before it is played, then played on the amplifier's own clock.

:class:`WaveMachine` (same interface as :class:`afmctl.loop_machine.LoopMachine`) runs in
four named phases:

1. ``collect`` — the whole trajectory from the feeder (a finite one: queue mode and live
   setpoints need ``output = "setpoints"`` or ``"stream"``), and the present output read
   back;
2. ``plan`` — :func:`afmctl.wave_plan.plan_table`: the compensation pipeline over the whole
   target with the chain's offline inverse within the limits (what ``afmctl compensate``
   does), the table checked row by row against the limits and the slew limit per sample;
   a ``wave`` event reports it;
3. ``approach`` — host setpoints ramp the output from the read-back voltage to the table's
   first row at ``safety.ramp_V_per_s`` (the setpoint loop's start ramp);
4. ``play`` — the table plays on the amplifier's clock at ``loop.rate_Hz``: a PI GCS
   controller's or NV200's wave generator (:class:`TablePlayer`: the columns are uploaded
   whole, then started together), or the CAN amplifier's stream FIFO
   (:class:`FifoPlayer`: queued ahead between ``amplifier.low_water_s`` and
   ``high_water_s``); host stalls shorter than what the device holds never reach the tip;

then the setpoint loop's ``finish`` mode (ramp to the safe value, or hold, as
``safety.on_finish`` says), starting from the output read back from the device.

Every played row goes into the run log with ``t_s`` = its play time on the amplifier's
clock; the rows of the table that were never played (a stop or estop) are not recorded.
Stop and estop during ``play`` stop the device at once (wave generator stopped, FIFO
flushed: the output holds where playing stopped), then the finish ramp runs (estop: at the
slew limit). A link error ends the run in ``fault`` (the device plays out or holds).
"""
from __future__ import annotations

import enum
import math
import time
from typing import Any

import numpy as np

from afmctl.drivers import codec_gcs_wave as wcodec
from afmctl.drivers.errors import LimitError

from . import loop_stats
from .errors import AfmctlError, error_line
from .loop_machine import (C_COR, C_D, C_S, C_T, C_TGT, C_U, END_OF_TRAJECTORY, FAULT_ERRORS, RING_ROWS,
                           LoopMachine, Mode, State)
from .stream_producer import StreamProducer
from .wave_plan import MAX_TABLE_SAMPLES, WaveTable, driven_steps_ok, plan_table


class Phase(enum.Enum):
    """Where a wave run is (see the module docstring)."""
    COLLECT = "collect"
    PLAN = "plan"
    APPROACH = "approach"
    PLAY = "play"
    FINISH = "finish"


def check_wave_config(config, amplifier: Any) -> None:
    """Refuse at once what ``output = "wave"`` cannot do (one line naming the field):
    a driver without device-timed output, a loop rate the device clock cannot play, a
    Kalman filter (its measurements arrive during the run)."""
    driver = config.amplifier.driver
    if not (hasattr(amplifier, "upload_wave") or hasattr(amplifier, "start_stream")):
        raise AfmctlError(f"amplifier.output = 'wave': the {driver} driver has no wave table or buffered "
                          "stream; allowed with driver 'gcs', 'nv200' or 'can'")
    if config.compensation.drift.kalman:
        raise AfmctlError("amplifier.output = 'wave': the table is computed before the run, so drift "
                          "measurements cannot reach it; set compensation.drift.kalman = false or use "
                          "output = 'setpoints' or 'stream'")
    rate = config.loop.rate_Hz
    if not hasattr(amplifier, "upload_wave") and rate != round(rate):
        raise AfmctlError(f"loop.rate_Hz: {rate:g} must be a whole number of Hz for the {driver} stream FIFO")
    if hasattr(amplifier, "upload_wave"):
        try:
            wcodec.divider_for(config.loop.rate_Hz, amplifier.servo_cycle_s())
        except ValueError as err:
            raise AfmctlError(f"loop.rate_Hz: {err} (the {driver} wave generator plays a point every "
                              "whole number of its clock ticks)") from None


class WaveMachine(LoopMachine):
    """One wave run of the loop thread of ``ctl`` (see the module docstring)."""

    def __init__(self, ctl: Any) -> None:
        super().__init__(ctl)
        amp = ctl.amplifier
        self.phase = Phase.COLLECT
        self.player: TablePlayer | FifoPlayer = (TablePlayer(self) if hasattr(amp, "upload_wave")
                                                 else FifoPlayer(self))
        self.table: WaveTable | None = None
        self.recorded = 0           # rows of the table already in the run log
        self.tick0 = 0              # the loop tick at which row 0 of the table plays

    # ------------------------------------------------------------------ phases
    def run(self) -> None:
        ctl = self.ctl
        self.T_C = ctl._T_C
        self._sync_at_start()
        if ctl._state is State.FAULT:
            self.in_fault = True
            self._end_of_run()
            return
        targets = self._collect()
        try:
            if targets is not None and ctl._request is None:
                self.phase = Phase.PLAN
                self.table = self._plan(targets)
                self.player.check(self.table)
                self.phase = Phase.APPROACH
                if self._approach():
                    self.phase = Phase.PLAY
                    self.player.play(self.table)
        except (AfmctlError, LimitError) as err:
            self._refused(err)          # the table cannot be played: nothing of it was
        except FAULT_ERRORS as err:
            ctl._enter_fault(err)
            self.in_fault = True
            self._end_of_run()
            return
        self.phase = Phase.FINISH
        self._finish()

    def _refused(self, err: BaseException) -> None:
        """The trajectory cannot be played as a wave (too long for the device, refused by the
        driver's checks, a plan that cannot be made): say so, as a trajectory error (``afmctl
        run`` exits 2), and finish from where the output is."""
        ctl = self.ctl
        ctl._errors += 1
        ctl._last_error = ctl._feed_error = error_line(err)
        ctl._event("wave-refused", ctl._last_error)

    def _collect(self) -> np.ndarray | None:
        """Phase ``collect``: every trajectory sample from the feeder, (N, 3) [nm]; None when
        the trajectory failed, was empty, or a stop came first."""
        ctl = self.ctl
        blocks: list[list[float]] = []
        n = 0
        while True:
            if ctl._request is not None:
                ctl._event("stop", "stopped before the wave was played")
                return None
            item = ctl._deque.popleft() if ctl._deque else None
            if item is None:
                time.sleep(0.001)
                continue
            if item is END_OF_TRAJECTORY:
                break
            blocks.append(item)
            n += len(item) // 3
            if n > MAX_TABLE_SAMPLES:
                ctl._feed_stop = True
                self._refused(AfmctlError(f"amplifier.output = 'wave': the trajectory has more than "
                                          f"{MAX_TABLE_SAMPLES} samples at the loop period (shorten it or lower "
                                          "loop.rate_Hz)"))
                return None
        if ctl._feed_error:
            ctl._errors += 1
            ctl._last_error = ctl._feed_error
            ctl._event("trajectory-error", ctl._feed_error)
            return None
        if n == 0:
            ctl._event("end", "the trajectory has no samples")
            return None
        return np.asarray([v for b in blocks for v in b], dtype=np.float64).reshape(-1, 3)

    def _plan(self, targets: np.ndarray) -> WaveTable:
        """Phase ``plan``: the table (:func:`afmctl.wave_plan.plan_table`), reported."""
        ctl, s = self.ctl, self.safety
        T = ctl._T_C
        if self.T_file is not None:
            t, temps = self.T_file
            T = np.interp(np.arange(len(targets)) * self.period_s, t, temps)
        limits = {a: (s.lo[i], s.hi[i]) for i, a in enumerate(s.axes)}
        table = plan_table(ctl.config, self.pipe, targets, T, limits, self.player.max_step_V)
        s.clamped += table.clamped
        s.slew_limited += table.slew_limited
        ctl._wave_stats = {"player": self.player.what, "samples": len(table), "pad": table.pad, "played": 0,
                           "inverse": table.report, "table_clamped": table.clamped,
                           "table_slew_limited": table.slew_limited}
        ctl._event("wave", f"{self.player.what} at {ctl.config.loop.rate_Hz:g} Hz: {table.describe()}")
        return table

    def _approach(self) -> bool:
        """Phase ``approach``: host setpoints ramp to the table's first row (one per loop
        period); False when a stop or estop came first."""
        ctl, s = self.ctl, self.safety
        table = self.table
        assert table is not None
        self._set_aim(0)
        goal = s.driven_target(table.u_V[0])
        self.next_t_s = self.now_s = time.perf_counter()
        ctl._event("ramp", "ramping from the present output to the wave's first sample")
        while not all(s.last[i] == goal[i] for i in range(len(goal))):
            self._wait_for_deadline()
            ctl._tick += 1
            if ctl._request is not None:
                return False
            s.ramp_step(goal, self.ramp_rate_V_per_s)
            self._record()
        ctl._event("ramp-done")
        return True

    def _finish(self) -> None:
        """After the table: the setpoint loop's ``finish`` mode from the read-back output
        (ramp to the safe value or hold; an estop ramps at the slew limit)."""
        ctl = self.ctl
        self.mode = Mode.FINISH
        req = ctl._request
        if req == "estop":
            self.finish_rate_V_per_s = self.safety.slew_V_per_s
            self.finish_hold = False
            ctl._event("estop")
        elif req == "runlog-error":
            self.finish_hold = False
            ctl._event("safe-stop", "the run log cannot be written: ramping to the safe value")
        else:
            self.finish_hold = self.on_finish == "hold"
            if req == "stop":
                ctl._event("stop")
        if self.table is not None:
            self._set_aim(len(self.table) - 1)
        LoopMachine.run(self)

    def _take_request(self) -> None:
        """Requests were taken by the phases before ``finish``; an estop during the finish
        ramp raises its rate to the slew limit."""
        ctl = self.ctl
        if ctl._request == "estop" and self.finish_rate_V_per_s != self.safety.slew_V_per_s:
            self.finish_rate_V_per_s = self.safety.slew_V_per_s
            self.finish_hold = False
            ctl._event("estop")

    # ------------------------------------------------------------------ records
    def _set_aim(self, k: int) -> None:
        """Record columns of the host's own samples: those of table row ``k``."""
        t = self.table
        assert t is not None
        self.last_tgt = tuple(t.target_nm[k].tolist())
        self.last_cor = tuple(t.corrected_nm[k].tolist())
        self.last_d = tuple(t.drift_nm[k].tolist())

    def record_played(self, n_played: int) -> None:
        """Put rows ``recorded .. n_played`` of the table into the run log (``t_s`` = play
        time: the tick after the approach plus the row index), in pieces the dispatcher
        drains (the ring is never overrun)."""
        ctl, t = self.ctl, self.table
        assert t is not None
        n_played = min(n_played, len(t))
        piece = RING_ROWS // 4
        while self.recorded < n_played:
            while ctl._w - ctl._r_done > RING_ROWS // 2 and ctl._dispatcher is not None \
                    and ctl._dispatcher.is_alive():
                time.sleep(0.005)       # let the dispatcher catch up
            k0 = self.recorded
            k1 = min(n_played, k0 + piece)
            self._write_rows(t, k0, k1)
            self.recorded = k1
        self.u_prev[:] = t.u_V[n_played - 1].tolist() if n_played else self.u_prev

    def _write_rows(self, t: WaveTable, k0: int, k1: int) -> None:
        ctl = self.ctl
        n = k1 - k0
        rows = np.empty((n, ctl._ring.shape[1]))
        rows[:, 0] = ctl._seq + np.arange(n)
        rows[:, 1] = self.tick0 + k0 + np.arange(n)
        rows[:, C_TGT:C_TGT + 3] = t.target_nm[k0:k1]
        rows[:, C_COR:C_COR + 3] = t.corrected_nm[k0:k1]
        rows[:, C_U:C_U + 3] = t.u_V[k0:k1]
        rows[:, C_T] = t.T_C[k0:k1]
        rows[:, C_D:C_D + 3] = t.drift_nm[k0:k1]
        rows[:, C_S:C_S + 3] = math.nan
        idx = (ctl._w + np.arange(n)) & (RING_ROWS - 1)
        ctl._ring[idx] = rows
        ctl._w += n
        ctl._seq += n
        ctl._tick = self.tick0 + k1
        if ctl._wave_stats is not None:
            ctl._wave_stats["played"] = k1

    def played_to(self, n_played: int, why: str) -> None:
        """The device stopped after ``n_played`` rows: record them, put the safety layer's
        reference on the device's output (read back) and say where it stopped."""
        ctl = self.ctl
        self.record_played(n_played)
        for w in self.safety.sync_from_device():
            ctl._event("readback", w)
        if self.table is not None and n_played < len(self.table):
            ctl._event("wave-stopped", f"{why}: {n_played} of {len(self.table)} samples played")
        else:
            ctl._event("end")
        if self.table is not None and n_played:
            self._set_aim(n_played - 1)


class TablePlayer:
    """Plays a :class:`~afmctl.wave_plan.WaveTable` with a wave generator (PI GCS ``WAV``/
    ``WGO``, NV200 waveform buffer): every driven column uploaded whole, then started
    together, polled (``#9``, ``grun``) until it ends or a request stops it."""

    #: how often the host asks whether the generator still runs [s]
    poll_s = 0.02

    def __init__(self, machine: WaveMachine) -> None:
        self.m = machine
        self.amp = machine.ctl.amplifier
        self.what = f"wave table ({machine.ctl.config.amplifier.driver} wave generator)"
        self.max_step_V = machine.safety.max_step_V

    def play(self, table: WaveTable) -> None:
        m, amp, ctl = self.m, self.amp, self.m.ctl
        axes = list(m.safety.axes)
        self._check(table)
        for a in axes:
            if ctl._request is not None:      # a stop during the upload: nothing is started
                ctl._event("wave-stopped", f"{ctl._request} while the table was uploaded: not started")
                return
            amp.upload_wave(a, table.u_V[:, "xyz".index(a)])
        if ctl._request is not None:
            ctl._event("wave-stopped", f"{ctl._request} while the table was uploaded: not started")
            return
        divider = wcodec.divider_for(ctl.config.loop.rate_Hz, amp.servo_cycle_s())
        m.tick0 = ctl._tick + 1
        t0 = time.perf_counter()
        st = amp.start_wave(divider=divider, cycles=1, axes=axes)
        rate = st.rate_Hz
        n = len(table)
        while any(st.running.values()):
            if ctl._request is not None:
                amp.stop_wave()
                done = min(n, int((time.perf_counter() - t0) * rate))
                m.played_to(done, f"{ctl._request} during the wave (position from the host clock)")
                return
            m.record_played(min(n - 1, int((time.perf_counter() - t0) * rate)))
            if time.perf_counter() - t0 > n / rate + 5.0:
                amp.stop_wave()
                raise AfmctlError(f"the wave generator still runs {n / rate + 5.0:.1f} s after its start; stopped")
            time.sleep(self.poll_s)
            st = amp.wave_status()
        m.played_to(n, "end")

    def check(self, table: WaveTable) -> None:
        """Before the approach: the table fits the device's wave tables (:class:`AfmctlError`
        naming the capacity: nothing is sent)."""
        for a in self.m.safety.axes:
            capacity = self.amp.wave_capacity(a)
            if len(table) > capacity:
                raise AfmctlError(f"amplifier.output = 'wave': the trajectory makes {len(table)} samples at "
                                  f"{self.m.ctl.config.loop.rate_Hz:g} Hz, the {self.m.ctl.config.amplifier.driver} "
                                  f"wave table of axis {a} holds {capacity} (shorten the trajectory or lower "
                                  "loop.rate_Hz)")

    def _check(self, table: WaveTable) -> None:
        s = self.m.safety
        limits = {a: (s.lo[i], s.hi[i]) for i, a in enumerate(s.axes)}
        if not driven_steps_ok(table.u_V, s.axes, limits, self.max_step_V, s.last):
            raise AfmctlError("amplifier.output = 'wave': the table breaks the limits or the slew limit "
                              "(a bug: nothing was sent)")


class FifoPlayer:
    """Plays a :class:`~afmctl.wave_plan.WaveTable` through the CAN amplifier's stream FIFO
    on its clock: rows queued ahead between the water marks (:class:`StreamProducer`'s
    accounting), recorded as they are queued (the amplifier plays each exactly one period
    after the one before); a request flushes the FIFO."""

    def __init__(self, machine: WaveMachine) -> None:
        self.m = machine
        ctl = machine.ctl
        cfg = ctl.config
        self.amp = ctl.amplifier
        self.what = "stream FIFO (CAN amplifier clock)"
        self.prod = StreamProducer(self.amp, machine.safety, cfg.loop.rate_Hz,
                                   cfg.amplifier.low_water_s, cfg.amplifier.high_water_s)
        self.max_step_V = self.prod.max_step_V
        self.poll_s = max(min(self.prod.high - self.prod.low, self.prod.low) / cfg.loop.rate_Hz / 4, 0.0005)
        self.stall = getattr(ctl, "stream_stall_hook", None)

    def check(self, table: WaveTable) -> None:
        """Any length fits: the FIFO is refilled as it plays."""

    def play(self, table: WaveTable) -> None:
        m, amp, prod, ctl = self.m, self.amp, self.prod, self.m.ctl
        s = m.safety
        limits = {a: (s.lo[i], s.hi[i]) for i, a in enumerate(s.axes)}
        if not driven_steps_ok(table.u_V, s.axes, limits, self.max_step_V, s.last):
            raise AfmctlError("amplifier.output = 'wave': the table breaks the limits or the slew limit "
                              "(a bug: nothing was sent)")
        n = len(table)
        rows = table.u_V.copy()
        held = getattr(amp, "last_output", {}) or {}
        for k, a in enumerate("xyz"):       # an axis the scanner does not drive keeps its output
            if a not in s.axes and a in held:
                rows[:, k] = held[a]
        st = amp.start_stream(prod.rate_Hz, prefill=int(min(prod.high, n)))
        if prod.high > st.capacity:
            raise AfmctlError(f"amplifier.high_water_s: {prod.high} samples do not fit the amplifier's FIFO of "
                              f"{st.capacity} samples at {prod.rate_Hz:g} Hz")
        prod._queued = 0
        m.tick0 = ctl._tick + 1
        next_wake = time.perf_counter()
        while prod._queued < n:
            if ctl._request is not None:
                self._flush(f"{ctl._request} during the wave")
                return
            level = prod._queued - prod._played()
            if level < prod.low or prod._queued == 0:
                k = min(prod.high - level, n - prod._queued)
                amp.queue(rows[prod._queued:prod._queued + k].tolist())
                prod._queued += k
            m.record_played(prod._played())
            if self.stall is not None:
                self.stall()
            next_wake = self._sleep(next_wake)
            self._stats()
        amp.drain_stream()
        while (bs := amp.buffer_status()).state not in ("idle", "fault"):
            if ctl._request is not None:
                self._flush(f"{ctl._request} while the FIFO played out")
                return
            m.record_played(prod._played())
            time.sleep(0.005)
        self._stats()
        if bs.state == "fault":
            raise AfmctlError("the amplifier stopped the stream (fault)")
        m.played_to(n, "end")

    def _sleep(self, next_wake: float) -> float:
        ctl = self.m.ctl
        next_wake += self.poll_s
        rem = next_wake - time.perf_counter()
        if rem > 0:
            time.sleep(rem)
        late = max(time.perf_counter() - next_wake, 0.0)
        loop_stats.add(ctl._hist, late)
        ctl._late_max = max(ctl._late_max, late)
        if late > self.poll_s:
            ctl._missed += 1
            next_wake = time.perf_counter()
        return next_wake

    def _flush(self, why: str) -> None:
        """Empty the FIFO at once (the output holds where playing stopped); the rows played
        go into the run log, the others never do."""
        m, prod = self.m, self.prod
        m.ctl.amplifier.flush_stream()
        played = max(prod._played(), m.recorded)     # the last STREAM_STATUS before the flush
        self._stats()
        m.ctl._event("estop-flush" if m.ctl._request == "estop" else "stop-flush",
                     f"FIFO flushed: table rows from about {played} on were not played")
        m.played_to(played, why)

    def _stats(self) -> None:
        prod = self.prod
        prod._played()
        st = prod.stats
        self.m.ctl._stream_stats = {"underruns": st.underruns, "lowest_level": st.lowest_level,
                                    "queued": prod._queued, "low_water": prod.low, "high_water": prod.high,
                                    "estop_ramp_samples": 0}
