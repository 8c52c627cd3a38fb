"""The loop thread of :class:`afmctl.control.controller.Controller` as a state machine of named states.

One :class:`LoopMachine` lives for one run. Each tick it waits for its absolute deadline
(sleep, then spin), counts the lateness, takes a stop/estop request, then runs the tick
method of where it is:

* controller state :attr:`State.FAULT` (the link is down) → :meth:`LoopMachine._tick_fault`:
  reconnect attempts on a helper thread, then resume (ramping from the read-back voltage);
  this takes precedence over the mode below;
* otherwise by :class:`Mode`:

  - :attr:`Mode.RUN` → :meth:`LoopMachine._tick_run`: the next trajectory sample through the
    compensation pipeline to the safety layer (first ramping to it at start and resume;
    ``holding`` when the watchdog sees the trajectory stall). With a preview horizon
    (the pipeline's ``latency_samples`` = L > 0, a dynamics stage; :mod:`afmctl.control.preview`)
    the pipeline is fed the trajectory L samples ahead of the output: the first sample L
    extra times before the first output, the last one L extra times after the end (and in
    queue mode when the segments pause), and each output is recorded beside the target it
    aims at;
  - :attr:`Mode.SETTLE` → :meth:`LoopMachine._tick_settle`: reach the trajectory's last
    setpoint at the slew limit;
  - :attr:`Mode.FINISH` → :meth:`LoopMachine._tick_finish`: ramp to the safe value (or hold),
    then end the run.

A tick method returns True to go on ticking and False to end the run. Every counter of
:meth:`afmctl.control.controller.Controller.stats` and every event stays on the controller; this module
only moves the loop's control flow out of it. Nothing here writes files, logs or calls
user code (the controller's dispatcher thread does that).
"""
from __future__ import annotations

import collections
import enum
import math
import time
from typing import Any, cast

import numpy as np

from . import stats as loop_stats
from ..errors import error_line
from .reconnect import FAULT_ERRORS, FaultPolicy
from .safety import Watchdog
from .transitions import REQUEST_EVENTS, TABLES, Event, Phase, PhaseMachine, State  # noqa: F401 - State re-exported
from afmctl.compensators.base import quiet_clamps
from afmctl.drivers.base import ConnectionState


#: the feeder puts this into the sample deque after the trajectory's last block
END_OF_TRAJECTORY = object()
#: ring buffer of sent setpoints: rows (power of two) and column layout
RING_ROWS = 1 << 16
C_SEQ, C_TICK = 0, 1
C_TGT, C_COR, C_U, C_T, C_D, C_S = 2, 5, 8, 11, 12, 15
N_COLS = 18
NAN3 = (math.nan, math.nan, math.nan)
#: most re-bases of the loop's clock kept (Controller.clock_bases); a run with more has no
#: tick deadlines after them (the summary's arrival figure is then left out)
CLOCK_BASES_MAX = 100_000


def aligned_s(now_s: float, period_s: float, phase: float | None) -> float:
    """A tick's deadline [s, perf_counter: the machine's monotonic clock, shared by its
    processes] at or before ``now_s`` that falls ``phase`` of a period after a whole number
    of periods (``loop.phase``), so that the next falls within one period after ``now_s``;
    ``now_s`` itself when ``phase`` is None."""
    if phase is None:
        return now_s
    return now_s - ((now_s - phase * period_s) % period_s)


class Mode(enum.Enum):
    """What the loop thread does on a tick when the link is up (see the module docstring)."""
    RUN = "run"            # play trajectory samples
    SETTLE = "settle"      # reach the last setpoint (slowed by the slew limit) before finishing
    FINISH = "finish"      # ramp to the safe value or hold, then stop


class LoopMachine:
    """One run of the loop thread of ``ctl`` (see the module docstring); :meth:`run` blocks
    until the run ends.

    Link errors, reconnects and read-backs are the :class:`afmctl.control.reconnect.FaultPolicy`'s
    job; the phases move through :mod:`afmctl.control.transitions`. Why the rest is one class
    of about 400 lines: the per-tick state (the block being played, the pending sample, mode,
    ramp, preview queue, watchdog) is read and written on every tick at 1–20 kHz, as plain
    attributes of one object, and the stream and wave machines are subclasses that reuse its
    tick methods; splitting it would put attribute hops on the hot path and into both
    subclasses."""

    def __init__(self, ctl: Any) -> None:  # an afmctl.control.controller.Controller (not imported: no cycle)
        cfg = ctl.config
        self.ctl = ctl
        self.safety = safety = ctl.safety
        self.pipe = pipe = ctl.pipeline
        self.period_s = ctl.dt_s
        self.ramp_rate_V_per_s = min(cfg.safety.ramp_V_per_s, safety.slew_V_per_s)
        self.safe_V = list(safety.safe)
        self.on_finish = cfg.safety.on_finish
        self.on_stall = cfg.safety.on_stall
        self.watchdog = Watchdog(cfg.safety.watchdog_s)
        self.T_file = ctl._T_file
        self.has_kalman = getattr(pipe, "kalman", None) is not None
        self.mode = Mode.RUN
        #: the loop's phase, moved only through the output mode's transition table
        self.fsm = PhaseMachine(TABLES.get(cfg.amplifier.output, TABLES["setpoints"]))
        ctl._fsm = self.fsm
        #: link errors, reconnects, read-backs (afmctl.control.reconnect)
        self.faults = FaultPolicy(self)
        self.req_taken: str | None = None   # the latest request taken (ctl._request)
        self.finish_rate_V_per_s = self.ramp_rate_V_per_s
        self.finish_hold = False
        self.blk: list | None = None        # flat block x0, y0, z0, x1, ... being played
        self.bi = 0                         # index of the next sample's x in blk
        self.cur: tuple | None = None       # computed sample not yet fully sent
        self.need_ramp = True               # ramp to the next sample (start / resume)
        self.ramping = False
        self.last_u_cmd: tuple | None = None  # the trajectory's latest setpoint voltages (x, y, z)
        self.last_tgt = (0.0, 0.0, 0.0)
        self.last_cor = (0.0, 0.0, 0.0)
        self.last_d = (0.0, 0.0, 0.0)
        self.last_s = pipe.drift_std_nm() if self.has_kalman else NAN3
        self.u_prev = [0.0, 0.0, 0.0]
        self.in_fault = False                           # the loop ended without a link
        self.now_s = 0.0                                # start of this tick (perf_counter)
        self.next_t_s = 0.0                             # this tick's deadline (perf_counter)
        self.T_C = 0.0
        self.spin_s = cfg.loop.spin_s
        self.resync_s = cfg.loop.resync_periods * self.period_s
        # preview horizon (afmctl.control.preview): the pipeline's output lags its input by L samples;
        # plus the ticks the output path delays it by (afmctl.control.path_delay): read that much further
        self.latency = int(getattr(pipe, "latency_samples", 0)) + ctl.path_delay.advance
        self.primed = False                 # the first sample was fed L extra times
        self.aims: collections.deque = collections.deque()  # (tgt, cor, d) of the last L inputs
        self.last_in = (0.0, 0.0, 0.0)      # the latest trajectory sample fed
        self.hold_left = 0                  # held samples still to feed (drain the preview)

    # ------------------------------------------------------------------ main loop
    def run(self) -> None:
        """Tick until a tick method ends the run, then flush the link and publish ``stopped``."""
        if not self._sync_at_start():
            self._end_of_run()
            return
        ctl = self.ctl
        FAULT = State.FAULT
        self.now_s = time.perf_counter()
        self.next_t_s = aligned_s(self.now_s, self.period_s, ctl.config.loop.phase)
        ctl.clock_bases = [(ctl._tick, self.next_t_s)]     # this tick's deadline on perf_counter
        self.watchdog.feed(self.now_s)
        while True:
            self._wait_for_deadline()
            ctl._tick += 1
            self.T_C = ctl._T_C if self.T_file is None else self._T_from_file()
            if ctl._request is not None and not self._take_request():
                break
            if ctl._state is FAULT:
                if not self._tick_fault():
                    break
                continue
            mode = self.mode
            try:
                if mode is Mode.RUN:
                    go_on = self._tick_run()
                elif mode is Mode.SETTLE:
                    go_on = self._tick_settle()
                else:
                    go_on = self._tick_finish()
                if not go_on:
                    break
            except FAULT_ERRORS as err:
                if not self._on_link_error(err):
                    break
        self._end_of_run()

    def _wait_for_deadline(self) -> None:
        """Count the previous tick's work, wait for the next deadline (sleep, then spin) and
        count this tick's lateness (not while in fault: reconnect time is not lateness)."""
        ctl = self.ctl
        perf = time.perf_counter
        work = perf() - self.now_s
        if work > 0.0:
            loop_stats.add(ctl._whist, work)
        period = self.period_s
        next_t = self.next_t_s + period
        now = perf()
        rem = next_t - now
        spin = self.spin_s
        if rem > spin:
            time.sleep(rem - spin)
        while perf() < next_t:
            pass
        now = perf()
        late = now - next_t
        if ctl._state is not State.FAULT:
            loop_stats.add(ctl._hist, late)
            if late > ctl._late_max:
                ctl._late_max = late
            if late > 0.5 * period:
                ctl._missed += 1
                ctl._missed_log.append((ctl._tick, late))
        if late > self.resync_s:
            ctl._overruns += 1
            next_t = aligned_s(now, period, ctl.config.loop.phase)
            if len(ctl.clock_bases) < CLOCK_BASES_MAX:
                ctl.clock_bases.append((ctl._tick + 1, next_t))   # the tick about to run: its deadline
        self.now_s = now
        self.next_t_s = next_t
        ctl._deadline_s = next_t

    def _T_from_file(self) -> float:
        """Ambient temperature [°C] of ``compensation.temperature.file`` at this tick."""
        t, T = self.T_file
        return float(np.interp(self.ctl._tick * self.period_s, t, T))

    def _sync_at_start(self) -> bool:
        """Read the device's output back (:meth:`afmctl.control.reconnect.FaultPolicy.sync_at_start`);
        False when the read-back refuses the run."""
        return self.faults.sync_at_start()

    def _synced_or_ended(self) -> bool:
        """Read the device's output back (:meth:`_sync_at_start`); with the link down, end
        the run in fault at once and return False (machines that do not reconnect)."""
        if not self._sync_at_start() or self.ctl._state is State.FAULT:
            self.in_fault = True
            self._end_of_run()
            return False
        return True

    def _take_request(self) -> bool:
        """A new request (any thread) goes through the transition table: in a fault
        (RETRY, RECONNECT) the run ends at once (``stop-in-fault``: nothing can be sent, the
        device holds) and this returns False; otherwise it switches to :attr:`Mode.FINISH`:
        ``stop`` (ramp or hold as ``safety.on_finish`` says), ``estop`` (ramp at the slew
        limit), ``runlog-error`` (ramp to the safe value: the run log cannot be written). An
        estop during another request's ramp raises the ramp rate to the slew limit."""
        ctl = self.ctl
        req = ctl._request
        if req is None or req == self.req_taken:
            return True
        self.req_taken = req
        nxt = self.fsm.fire(REQUEST_EVENTS.get(req, Event.STOP))
        self._finish_for(req)
        if nxt is Phase.STOPPED or nxt is Phase.FAULT:
            ctl._event("stop-in-fault", "link lost: the output could not be ramped")
            ctl._set_state(State.STOPPED, "stopped")
            self.in_fault = True
            return False
        return True

    def _finish_for(self, req: str) -> None:
        """Mode, rate and hold of the finish a request asks for (see :meth:`_take_request`)."""
        ctl = self.ctl
        slew = self.safety.slew_V_per_s
        if req is not None and self.mode is not Mode.FINISH:
            self.mode = Mode.FINISH
            if req == "estop":
                self.finish_rate_V_per_s = slew
                self.finish_hold = False
                ctl._event("estop")
            elif req == "runlog-error":
                self.finish_rate_V_per_s = self.ramp_rate_V_per_s
                self.finish_hold = False
                ctl._event("safe-stop", "the run log cannot be written: ramping to the safe value")
            else:
                self.finish_rate_V_per_s = self.ramp_rate_V_per_s
                self.finish_hold = self.on_finish == "hold"
                ctl._event("stop")
        elif req == "estop" and self.finish_rate_V_per_s != slew:
            self.finish_rate_V_per_s = slew
            self.finish_hold = False
            ctl._event("estop")

    def _end_of_run(self) -> None:
        """Flush pipelined setpoints (when the link is up) and publish ``stopped``."""
        ctl = self.ctl
        if not self.in_fault and ctl._state is not State.FAULT and ctl.amplifier.state is ConnectionState.CONNECTED:
            try:
                ctl.amplifier.flush()       # pipelined setpoints applied and checked
            except FAULT_ERRORS as err:
                ctl._errors += 1
                ctl._last_error = error_line(err)
                ctl._event("flush-error", ctl._last_error)
        if ctl._state not in (State.FAULT, State.STOPPED):
            ctl._set_state(State.STOPPED, "stopped")

    # ------------------------------------------------------------------ FAULT
    def _tick_fault(self) -> bool:
        """The link is down: the fault/reconnect policy's tick (:mod:`afmctl.control.reconnect`)."""
        return self.faults.tick()

    def _on_link_error(self, err: BaseException) -> bool:
        """A driver error in a tick (:meth:`afmctl.control.reconnect.FaultPolicy.on_link_error`)."""
        return self.faults.on_link_error(err)

    def _resume(self) -> None:
        """Reconnected and read back: resume where the run was — ramp from the read-back
        voltage to the pending setpoint, or settle on the last one when the trajectory had
        ended."""
        if self.mode is Mode.SETTLE:
            self.fsm.fire(Event.TRAJECTORY_END)
        else:
            self.mode = Mode.RUN
            self.need_ramp = True
        self.ctl._set_state(State.RUNNING, "resume", "reconnected; ramping from the read-back voltage")
        self.watchdog.feed()
        self.next_t_s = aligned_s(time.perf_counter(), self.period_s, self.ctl.config.loop.phase)
        if len(self.ctl.clock_bases) < CLOCK_BASES_MAX:
            self.ctl.clock_bases.append((self.ctl._tick + 1, self.next_t_s + self.period_s))

    # ------------------------------------------------------------------ SETTLE / FINISH
    def _tick_settle(self) -> bool:
        """The trajectory's last setpoint, not yet reached because the slew limit slowed the
        samples sent back to back after a late tick: reach it (at the slew limit) before the
        finish ramp or the hold."""
        safety = self.safety
        done = safety.ramp_step(safety.driven_target(self.last_u_cmd), safety.slew_V_per_s)
        self._record()
        if done:
            self.fsm.fire(Event.DONE)
            self.mode = Mode.FINISH
        return True

    def _tick_finish(self) -> bool:
        """Ramp to the safe value at the finish rate (or hold: end at once)."""
        if self.finish_hold:
            self.fsm.fire(Event.DONE)
            return False
        done = self.safety.ramp_step(self.safe_V, self.finish_rate_V_per_s)
        self._record()
        if done:
            self.fsm.fire(Event.DONE)
        return not done

    def _end_trajectory(self) -> None:
        """No more samples: settle on the last setpoint if needed, then finish."""
        self.fsm.fire(Event.TRAJECTORY_END)
        self.mode = Mode.FINISH if self._reached(self.last_u_cmd) else Mode.SETTLE
        if self.mode is Mode.FINISH:
            self.fsm.fire(Event.DONE)
        self.finish_rate_V_per_s = self.ramp_rate_V_per_s
        self.finish_hold = self.on_finish == "hold"

    def _reached(self, u_xyz: Any) -> bool:
        """Whether the output already is the setpoint ``u_xyz`` [V] (clamped into the limits)."""
        if u_xyz is None:
            return True
        safety = self.safety
        tgt = safety.driven_target(u_xyz)
        return all(not math.isfinite(tgt[i]) or min(max(tgt[i], safety.lo[i]), safety.hi[i]) == safety.last[i]
                   for i in range(len(tgt)))

    # ------------------------------------------------------------------ RUN
    def _tick_run(self) -> bool:
        """Compute the next sample (if none is pending), ramp to it when starting or
        resuming, else send it."""
        if self.cur is None and not self._next_sample():
            return True
        cur = cast("tuple[Any, ...]", self.cur)  # _next_sample() set it
        safety = self.safety
        if self.need_ramp:
            self.need_ramp = False
            tgt = safety.driven_target(cur[6:9])
            m = safety.max_step_V
            self.ramping = any(abs(min(max(tgt[i], safety.lo[i]), safety.hi[i]) - safety.last[i]) > m
                               for i in range(len(tgt)))
            if self.ramping:
                self.ctl._event("ramp", "ramping from the present output to the setpoint")
            elif self.fsm.phase is Phase.RAMP:
                self.fsm.fire(Event.DONE)
        if self.ramping:
            if safety.ramp_step(safety.driven_target(cur[6:9]), self.ramp_rate_V_per_s):
                self.ramping = False
                self.cur = None
                self.fsm.fire(Event.DONE)
                self.ctl._event("ramp-done")
            self._record()
            return True
        safety.send(cur[6:9])
        self.cur = None
        self._record()
        return True

    def _next_sample(self) -> bool:
        """Take the next trajectory sample and run it through the pipeline into
        ``self.cur``; False when there is none this tick (end, idle queue or a stall)."""
        ctl = self.ctl
        blk = self.blk
        if blk is None or self.bi >= len(blk):
            self.blk = None
            dq = ctl._deque
            item = dq.popleft() if dq else None
            if item is END_OF_TRAJECTORY and not ctl._feed_error and self.hold_left > 0:
                dq.appendleft(item)          # emit the last L outputs first
                return self._feed_held()
            if item is END_OF_TRAJECTORY:
                if ctl._feed_error:
                    ctl._errors += 1
                    ctl._last_error = ctl._feed_error
                    ctl._event("trajectory-error", ctl._feed_error)
                else:
                    ctl._event("end")
                self._end_trajectory()
                return False
            if item is None:
                if ctl._queue_mode and self.hold_left > 0:
                    return self._feed_held()    # live setpoints paused: the target holds
                self._no_sample()
                return False
            self.blk = blk = item
            self.bi = 0
        j = self.bi
        self.bi = j + 3
        rx, ry, rz = blk[j], blk[j + 1], blk[j + 2]
        self.watchdog.feed(self.now_s)
        if ctl._state is State.HOLDING:
            self.fsm.fire(Event.SAMPLE)
            ctl._set_state(State.RUNNING, "resume", "trajectory samples again")
            self.need_ramp = True
        if ctl._drift_meas:
            ctl._apply_drift_measurement(ctl._drift_meas.popleft())
        if self.latency:
            if not self.primed:
                self._prime(rx, ry, rz)
            self.hold_left = self.latency
        self._compute(rx, ry, rz)
        return True

    def _compute(self, rx: float, ry: float, rz: float) -> None:
        """Run one input sample through the pipeline into ``self.cur``; the record columns
        (target, corrected, drift) are those of the input the output aims at (L samples
        back with a preview horizon)."""
        pipe = self.pipe
        cur = self.cur = pipe.step(rx, ry, rz, self.T_C, self.u_prev)
        self.last_u_cmd = (cur[6], cur[7], cur[8])
        if self.has_kalman:
            self.last_s = pipe.drift_std_nm()
        tgt, cor, d = (rx, ry, rz), (cur[3], cur[4], cur[5]), (cur[0], cur[1], cur[2])
        if self.latency:
            self.last_in = tgt
            aims = self.aims
            aims.append((tgt, cor, d))
            tgt, cor, d = aims.popleft()
        self.last_tgt = tgt
        self.last_cor = cor
        self.last_d = d

    def _prime(self, rx: float, ry: float, rz: float) -> None:
        """Before the first output: feed the first sample L times (the scanner held there
        before the trajectory starts), so that the first output aims at it."""
        pipe, T_C, u, L = self.pipe, self.T_C, self.u_prev, self.latency
        aims = self.aims
        # the inverse starts at rest at 0 nm and sees a step to the first sample: its
        # pre-ringing may ask a Preisach stage for targets out of reach; those outputs are
        # never sent, so they do not warn (a clamp in the run still does, once)
        with quiet_clamps(*getattr(pipe, "inverses", ())):
            if getattr(pipe, "drift", None) is None and getattr(pipe, "kalman", None) is None:
                # block() gives the numbers of L step() calls, bit for bit, in a fraction of the time
                d, c, _ = pipe.block(np.tile((rx, ry, rz), (L, 1)), T_C, np.tile(u, (L, 1)))
                for k in range(L):
                    aims.append(((rx, ry, rz), tuple(c[k].tolist()), tuple(d[k].tolist())))
            else:
                for _ in range(L):
                    cur = pipe.step(rx, ry, rz, T_C, u)
                    aims.append(((rx, ry, rz), (cur[3], cur[4], cur[5]), (cur[0], cur[1], cur[2])))
        self.primed = True

    def _feed_held(self) -> bool:
        """No new sample: feed the latest one again (the target holds), one of the L that
        bring the output to it."""
        self.hold_left -= 1
        self._compute(*self.last_in)
        return True

    def _no_sample(self) -> None:
        """The sample deque is empty: end an idle queue run (``idle = "end"``), or after
        ``safety.watchdog_s`` enter ``holding`` (and ramp to safe with ``on_stall = "safe"``)."""
        ctl = self.ctl
        if ctl._queue_mode and ctl._queue_end_when_idle:
            ctl._event("end")
            self._end_trajectory()
            return
        now = self.now_s
        if self.watchdog.expired(now):
            if ctl._state is not State.HOLDING:
                self.fsm.fire(Event.STALL)
                ctl._watchdog_trips += 1
                ctl._watchdog_log.append(ctl._tick * ctl.dt_s)
                ctl._set_state(State.HOLDING, "watchdog",
                               f"no trajectory sample for {self.watchdog.since(now):.3f} s")
            self._stall_action()

    def _stall_action(self) -> None:
        """Holding (the trajectory stalled): with ``on_stall = "safe"`` one ramp step to the
        safe value."""
        if self.on_stall == "safe":
            self.safety.ramp_step(self.safe_V, self.ramp_rate_V_per_s)
            self._record()

    def _record(self) -> None:
        """Put the output just sent (and the sample it came from) into the ring buffer."""
        ctl = self.ctl
        safety = self.safety
        seq = ctl._seq
        u = safety.last
        ux = uy = uz = 0.0
        for i, k in enumerate(safety.index):
            if k == 0:
                ux = u[i]
            elif k == 1:
                uy = u[i]
            else:
                uz = u[i]
        tgt, cor, d, s = self.last_tgt, self.last_cor, self.last_d, self.last_s
        ctl._ring[ctl._w & (RING_ROWS - 1)] = (seq, ctl._tick, tgt[0], tgt[1], tgt[2], cor[0], cor[1], cor[2],
                                               ux, uy, uz, self.T_C, d[0], d[1], d[2], s[0], s[1], s[2])
        ctl._w += 1
        ctl._seq = seq + 1
        u_prev = self.u_prev
        u_prev[0] = ux
        u_prev[1] = uy
        u_prev[2] = uz
