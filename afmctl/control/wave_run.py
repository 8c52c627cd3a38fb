"""The loop thread for ``[amplifier] output = "wave"``: a finite trajectory computed whole
before it is played, then played on the amplifier's own clock.

:class:`WaveMachine` (same interface as :class:`afmctl.control.machine.LoopMachine`) runs in
named phases:

1. ``collect`` — the whole trajectory from the feeder (a finite one: queue mode and live
   setpoints need ``output = "setpoints"`` or ``"stream"``), and the present output read
   back;
2. ``plan`` — :func:`afmctl.control.wave_plan.plan_table`: the compensation pipeline over the whole
   target with the chain's offline inverse within the limits (what ``afmctl compensate``
   does); the player checks the table (finite, limits, slew per sample, fits the device)
   before anything is sent; a ``wave`` event reports it;
3. ``upload`` — a wave generator's table goes to the device while the output still rests
   where it was (the player's ``prepare``; the CAN FIFO has nothing to send ahead): the
   scanner does not sit at the table's first row, creeping, for as long as the link takes;
4. ``approach`` — host setpoints ramp from the read-back voltage to the table's first row
   at ``safety.ramp_V_per_s`` (the setpoint loop's start ramp), then hold there for
   ``amplifier.settle_s`` (the ramp's ringing and fast creep die out the same way before
   every play). The hold counts from a round trip behind the ramp's last setpoint and the
   device holds the row alone (the host sends nothing); a stream FIFO is armed and primed
   during it, so that its clock starts when the hold ends (``WavePlayer.arm``); events
   ``ramp``, ``settle`` (the first row reached) and ``ramp-done`` (the table starts: the
   run log's rows after it are the table's);
5. ``play`` — the table plays on the amplifier's clock at ``loop.rate_Hz``
   (:mod:`afmctl.control.wave_players`: a GCS or NV200 wave generator, or the CAN stream FIFO);
   host stalls shorter than what the device holds never reach the tip;
6. ``finish`` — the setpoint loop's finish mode (ramp to the safe value, or hold, as
   ``safety.on_finish`` says; an estop ramps at the slew limit) from the output read back.

Every played row goes into the run log with ``t_s`` = its play time on the amplifier's
clock, counted in loop periods from the start of the run (collect, plan and upload take no
ticks); rows never played are not recorded. Stop and estop during ``play`` stop the device at
once (wave generator stopped, FIFO flushed: the output holds where playing stopped). A
trajectory the device cannot play ends the run as bad input (``trajectory_error``: ``afmctl
run`` exits 2) before anything of it is sent; a link error ends it in ``fault`` (the device
plays out or holds); any other error once the device plays stops the device, then ``fault``.
"""
from __future__ import annotations

import enum
import time
from typing import Any

import numpy as np

from afmctl.drivers import codec_gcs_wave as wcodec

from ..errors import AfmctlError, error_line
from .machine import (C_COR, C_D, C_S, C_T, C_TGT, C_U, END_OF_TRAJECTORY, FAULT_ERRORS, RING_ROWS,
                           LoopMachine, Mode, State)
from .approach_history import with_approach_taken_out
from .wave_plan import KALMAN_REFUSAL, MAX_TABLE_SAMPLES, WaveTable, plan_table, planned_models
from .wave_players import FifoPlayer, TablePlayer, WavePlayer, WaveRefused
from . import transitions

#: longest the loop thread waits for the dispatcher to make room in the ring [s]
RING_WAIT_S = 1.0


class Phase(enum.Enum):
    """Where a wave run is (see the module docstring)."""
    COLLECT = "collect"
    PLAN = "plan"
    UPLOAD = "upload"
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
        raise AfmctlError(KALMAN_REFUSAL)
    rate = config.loop.rate_Hz
    if not hasattr(amplifier, "upload_wave"):
        if rate != round(rate):
            raise AfmctlError(f"loop.rate_Hz: {rate:g} must be a whole number of Hz for the {driver} stream FIFO")
        return
    try:
        wcodec.divider_for(rate, amplifier.servo_cycle_s())
    except ValueError as err:
        raise AfmctlError(f"loop.rate_Hz: {err} (the {driver} wave generator plays a point every "
                          "whole number of its clock ticks)") from None


class WaveMachine(LoopMachine):
    """One wave run of the loop thread of ``ctl`` (see the module docstring)."""

    def __init__(self, ctl: Any) -> None:
        super().__init__(ctl)
        self.phase = Phase.COLLECT
        self.player: WavePlayer = TablePlayer(self) if hasattr(ctl.amplifier, "upload_wave") else FifoPlayer(self)
        self.table: WaveTable | None = None
        self.recorded = 0           # rows of the table already in the run log
        self.tick0 = 0              # the loop tick at which row 0 of the table plays

    # ------------------------------------------------------------------ phases
    def run(self) -> None:
        """The phases in order (module docstring); returns when the run has ended."""
        ctl = self.ctl
        self.T_C = ctl._T_C
        if not self._synced_or_ended():
            return
        try:
            self._collect_plan_play()
        except WaveRefused as err:
            self._refused(err)
        except FAULT_ERRORS as err:
            self.player.abort()
            self.fsm.fire(transitions.Event.FAULT)
            ctl._enter_fault(err)
            ctl._event("wave-fault", "link error during the wave: the device plays out or holds")
            self.in_fault = True
            self._end_of_run()
            return
        except AfmctlError as err:       # the device plays, something else failed: stop it
            self.player.abort()
            self._after_abort(err)
            return
        self.phase = Phase.FINISH
        self._finish()
        ctl.wave_times["finished"] = time.monotonic()

    def _collect_plan_play(self) -> None:
        """Phases collect, plan, upload, approach and play (each returns early on a request)."""
        targets = self._collect()
        if targets is None or self.ctl._request is not None:
            return
        self.phase = Phase.PLAN
        self.table = self.ctl.wave_table = self._plan(targets)
        self.player.check(self.table)
        self.phase = Phase.UPLOAD
        if not self.player.prepare(self.table):
            return
        self.phase = Phase.APPROACH
        if self._approach():
            self.phase = Phase.PLAY
            self.player.play(self.table)

    def _collect(self) -> np.ndarray | None:
        """Phase ``collect``: every trajectory sample from the feeder, (N, 3) [nm]; None when
        the trajectory failed, was empty, or a request came first."""
        ctl = self.ctl
        chunks: list[np.ndarray] = []
        n = 0
        while ctl._request is None:
            item = ctl._deque.popleft() if ctl._deque else None
            if item is None:
                time.sleep(0.001)
                continue
            if item is END_OF_TRAJECTORY:
                break
            chunks.append(np.asarray(item, dtype=np.float64))
            n += len(item) // 3
            if n > MAX_TABLE_SAMPLES:
                ctl._feed_stop = True
                raise WaveRefused(f"amplifier.output = 'wave': the trajectory has more than {MAX_TABLE_SAMPLES} "
                                  "samples at the loop period (shorten it or lower loop.rate_Hz)")
        else:
            return None
        if ctl._feed_error:
            ctl._errors += 1
            ctl._last_error = ctl._feed_error
            ctl._event("trajectory-error", ctl._feed_error)
            return None
        if n == 0:
            ctl._event("end", "the trajectory has no samples")
            return None
        return np.concatenate(chunks).reshape(-1, 3)

    def _plan(self, targets: np.ndarray) -> WaveTable:
        """Phase ``plan``: the table (:func:`afmctl.control.wave_plan.plan_table`), reported."""
        ctl, s = self.ctl, self.safety
        T = ctl._T_C
        if self.T_file is not None:
            t, temps = self.T_file
            T = np.interp(np.arange(len(targets)) * self.period_s, t, temps)
        learned = getattr(ctl, "_learned_source", None)
        try:
            if learned is not None:
                table = learned.table_for(ctl.config)
            else:
                table = plan_table(ctl.config, self.pipe, targets, T, self.player.limits_V(), self.player.max_step_V,
                                   self.player.max_rows())
                table = with_approach_taken_out(table, ctl.config, planned_models(ctl.config, self.pipe), s.xyz(s.last),
                                                self.player.limits_V(), self.player.max_step_V)
        except AfmctlError as err:
            raise WaveRefused(str(err)) from None
        s.clamped += table.clamped
        s.slew_limited += table.slew_limited
        ctl._wave_stats = {"player": self.player.what, "samples": len(table), "pad": table.pad, "played": 0,
                           "inverse": table.report, "table_clamped": table.clamped,
                           "table_slew_limited": table.slew_limited}
        ctl._event("wave", f"{self.player.what} at {ctl.config.loop.rate_Hz:g} Hz: {table.describe()}")
        return table

    def _approach(self) -> bool:
        """Phase ``approach``: host setpoints ramp to the table's first row (one per loop
        period), then hold it for ``amplifier.settle_s``; False when a request came first."""
        ctl, s = self.ctl, self.safety
        table = self.table
        assert table is not None
        self._set_aim(0)
        goal = s.driven_target(table.u_V[0])
        self.next_t_s = self.now_s = time.perf_counter()
        if not self._rest_after_last_play():
            return False
        ctl.wave_times["approach"] = time.monotonic()
        ctl._event("ramp", "ramping from the present output to the wave's first sample")
        reached: bool | None = False
        while not reached:
            reached = self._towards(goal)
            if reached is None:
                return False
        src = ctl._learned_source
        settle_s = src.settle_s(ctl.config) if src is not None else ctl.config.amplifier.hold_s()
        # the hold counts from when the device holds the row: a link slower than the loop
        # delivers the ramp's last setpoints up to ~0.1 s after the host sent them (E-727
        # simulator: a 15.5 ms ramp applied over 60–105 ms)
        ctl.amplifier.flush()
        ctl.wave_times["settle"] = t_settle = time.monotonic()
        ctl._event("settle", f"at the wave's first sample; holding it {settle_s:g} s before the table starts")
        return self._device_hold(t_settle, settle_s)

    def _rest_after_last_play(self) -> bool:
        """A table learned as recorded on a device starts as long after the last play as
        every play of its learning did (:meth:`afmctl.control.learned_after.AsRecorded.wait_s`):
        the host holds the present output until then, ticking and recording; False when a
        request came first."""
        src = self.ctl._learned_source
        spacing = src.learned.as_recorded if src is not None else None
        wait_s = spacing.wait_s() if spacing is not None else 0.0
        if spacing is None or wait_s <= 0.0:
            return True
        self.ctl._event("rest", spacing.waiting(wait_s))
        return self._hold_until(time.monotonic() + wait_s)

    def _device_hold(self, t_settle: float, settle_s: float) -> bool:
        """The settle hold: the device holds the table's first row (the host sends nothing,
        so no setpoint queued on a slow link delays the table's start), the player gets
        the start ready (:meth:`WavePlayer.arm`), the host ticks and records the row; a
        request stops an armed device (nothing of the table played) and returns False.
        The hold before every play is then the same to a few ms: the scanner creeps at
        ~10 nm/s two seconds after a 5 µm approach (docs/CONTROLLER.md)."""
        assert self.table is not None
        self.player.arm(self.table)
        if not self._hold_until(t_settle + settle_s):
            self.player.abort()
            return False
        self.ctl._event("ramp-done")
        return True

    def _hold_until(self, until_monotonic_s: float) -> bool:
        """Tick and record the output as it is until ``until_monotonic_s`` (host clock,
        :func:`time.monotonic`); False as soon as a request comes."""
        while time.monotonic() < until_monotonic_s:
            self._wait_for_deadline()
            self.ctl._tick += 1
            if self.ctl._request is not None:
                return False
            self._record()
        return True

    def _towards(self, goal: list[float]) -> bool | None:
        """One loop period of the approach: a host setpoint towards ``goal`` at the ramp
        rate, recorded; None when a request came first (nothing sent), else whether the
        output is at ``goal``."""
        self._wait_for_deadline()
        self.ctl._tick += 1
        if self.ctl._request is not None:
            return None
        reached = self.safety.ramp_step(goal, self.ramp_rate_V_per_s)
        self._record()
        return reached

    def _finish(self) -> None:
        """Phase ``finish``: the setpoint loop's finish mode from the read-back output (ramp
        to the safe value or hold; an estop ramps at the slew limit). A pending request is
        taken as the setpoint loop takes it (:meth:`LoopMachine._take_request`: mode, rate,
        hold and event); so are requests during the finish."""
        if self.ctl._request is not None:
            self._take_request()
        else:
            played = self.fsm.phase is transitions.Phase.PLAY
            self.fsm.fire(transitions.Event.DONE if played else transitions.Event.TRAJECTORY_END)
            self.mode = Mode.FINISH
            self.finish_hold = self.on_finish == "hold"
        LoopMachine.run(self)

    # ------------------------------------------------------------------ ends
    def _refused(self, err: BaseException) -> None:
        """The trajectory cannot be played as a wave (nothing of it was): a trajectory error
        (``afmctl run`` exits 2); the finish runs from where the output is."""
        ctl = self.ctl
        ctl._errors += 1
        ctl._last_error = ctl._feed_error = error_line(err)
        ctl._event("wave-refused", ctl._last_error)

    def _after_abort(self, err: BaseException) -> None:
        """The device was stopped after an error during the play: read back where it is,
        record what surely played, then ``fault`` (the output holds)."""
        ctl = self.ctl
        ctl._errors += 1
        ctl._last_error = error_line(err)
        try:
            self.played_to(self.recorded, "error during the wave")
        except FAULT_ERRORS:
            pass
        self.fsm.fire(transitions.Event.FAULT)
        ctl._set_state(State.FAULT, "wave-error", ctl._last_error)
        self.in_fault = True
        self._end_of_run()

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
        drains; a dispatcher that does not keep up for :data:`RING_WAIT_S` loses records
        (counted as ``dropped_records``), never the loop its requests."""
        ctl, t = self.ctl, self.table
        assert t is not None
        n_played = min(n_played, len(t))
        piece = RING_ROWS // 4
        while self.recorded < n_played:
            deadline = time.monotonic() + RING_WAIT_S
            while (ctl._w - ctl._r_done > RING_ROWS // 2 and ctl._request is None
                   and time.monotonic() < deadline and ctl._dispatcher is not None and ctl._dispatcher.is_alive()):
                time.sleep(0.005)
            k1 = min(n_played, self.recorded + piece)
            self._write_rows(t, self.recorded, k1)
            self.recorded = k1
        if n_played:
            self.u_prev[:] = t.u_V[n_played - 1].tolist()

    def _write_rows(self, t: WaveTable, k0: int, k1: int) -> None:
        """Rows ``k0 .. k1`` of the table into the controller's ring (what ``_record`` does
        per sample); the controller's tick becomes that of row ``k1 - 1``."""
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
        rows[:, C_S:C_S + 3] = np.nan
        ctl._ring[(ctl._w + np.arange(n)) & (RING_ROWS - 1)] = rows
        ctl._w += n
        ctl._seq += n
        ctl._tick = self.tick0 + k1 - 1
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
