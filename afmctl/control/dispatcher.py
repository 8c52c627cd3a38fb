"""The controller's dispatcher: hands what the loop thread produced to the run log and to
sinks, off the loop thread.

:class:`Dispatcher` runs one thread (``afmctl-dispatch``) per run. Every
``dispatch_interval_s`` it copies the new rows of the loop's ring buffer into setpoint and
drift records (:data:`afmctl.control.runlog.SETPOINT_DTYPE`, ``DRIFT_DTYPE``) for the run log
and the sinks' ``on_setpoints``/``on_drift``, passes the loop's events to the run log and to
``on_status``, sends a periodic status every ``status_interval_s``, and checks the run log: a
run log that cannot be written asks the loop to stop (``runlog-error``: ramp to the safe
value). It then waits for the loop's quiet window (:func:`quiet_window_wait_s`), so that its
work takes the interpreter lock while the loop sleeps. When the loop thread has ended it
dispatches the rest, sends a ``final`` status, writes the ``stats`` event, closes the run log
and sets the controller's done event.

Its interface to the controller (:class:`afmctl.control.controller.Controller`): the ring
(``_ring``, write count ``_w``; it publishes ``_r_done``, the rows handed on), the event deque
``_events``, ``stats()``, ``_status()`` fields (state, seq, tick), ``runlog``, and the request
flag it raises on a run-log error.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any

import numpy as np

from .machine import C_COR, C_D, C_S, C_SEQ, C_T, C_TGT, C_TICK, C_U, RING_ROWS
from .runlog import DRIFT_DTYPE, SETPOINT_DTYPE

log = logging.getLogger(__name__)


def quiet_window_wait_s(now_s: float, deadline_s: float, period_s: float, spin_s: float) -> float:
    """How long [s] a helper thread waits from ``now_s`` to be inside the loop's quiet window.

    The loop ticks at ``deadline_s + k · period_s`` (perf_counter [s]), works for a while, then
    sleeps until ``spin_s`` before the next deadline and spins. The quiet window of each period
    starts a quarter period after the deadline (the tick's work done) and ends ``spin_s`` plus
    a quarter period before the next one; a helper that starts there hands the interpreter
    lock back before the loop needs it. 0 when ``now_s`` is inside a window, when the loop is
    not running (``deadline_s`` 0) or when the period leaves no window (fast loops)."""
    start = 0.25 * period_s
    end = 0.75 * period_s - spin_s
    if deadline_s <= 0.0 or end - start < 1e-4:
        return 0.0
    phase = (now_s - deadline_s) % period_s
    if start <= phase <= end:
        return 0.0
    return (start - phase) % period_s


class Dispatcher:
    """The dispatcher of one controller (see the module docstring); :meth:`start` runs its
    thread for one run. Sinks are registered here (:meth:`add_sink`)."""

    def __init__(self, ctl: Any) -> None:   # an afmctl.control.controller.Controller (no import: no cycle)
        self.ctl = ctl
        self.sinks: list[Any] = []
        self.thread: threading.Thread | None = None

    # ------------------------------------------------------------------ sinks
    def add_sink(self, sink: Any) -> None:
        self.sinks.append(sink)

    def remove_sink(self, sink: Any) -> None:
        if sink in self.sinks:
            self.sinks.remove(sink)

    def call_sinks(self, method: str, arg: Any) -> None:
        """Call ``method(arg)`` on every sink that has it; a sink's exception is logged, never
        raised (a sink must not stop the controller)."""
        for sink in list(self.sinks):
            fn = getattr(sink, method, None)
            if fn is None:
                continue
            try:
                fn(arg)
            except Exception:
                log.exception("sink %r.%s failed", sink, method)

    # ------------------------------------------------------------------ thread
    def start(self) -> threading.Thread:
        self.thread = threading.Thread(target=self._main, name="afmctl-dispatch", daemon=True)
        self.thread.start()
        return self.thread

    def _main(self) -> None:
        ctl = self.ctl
        ctl._helper_priority()
        r = 0
        next_status = time.monotonic()
        try:
            while True:
                alive = ctl._thread is not None and ctl._thread.is_alive()
                r = ctl._r_done = self._records(r)
                self._check_runlog()
                self._events()
                if time.monotonic() >= next_status:
                    next_status = time.monotonic() + ctl.status_interval_s
                    self.call_sinks("on_status", ctl._status("periodic"))
                if not alive:
                    r = self._records(r)
                    self._events()
                    self.call_sinks("on_status", ctl._status("final"))
                    break
                time.sleep(ctl.dispatch_interval_s)
                self._sleep_to_quiet_window()
        finally:
            if ctl.runlog is not None:
                ctl.runlog.write_event({"seq": ctl._seq, "t_s": ctl._tick * ctl.dt_s, "wall_time": time.time(),
                                        "state": ctl._state.value, "event": "stats", "detail": ctl.stats()})
                ctl.runlog.close()
            ctl._done.set()

    def _sleep_to_quiet_window(self) -> None:
        """Wait until just after one of the loop's ticks (see :func:`quiet_window_wait_s`)."""
        ctl = self.ctl
        wait = quiet_window_wait_s(time.perf_counter(), ctl._deadline_s, ctl.dt_s, ctl.config.loop.spin_s)
        if wait > 0.0:
            time.sleep(wait)

    def _check_runlog(self) -> None:
        """A run log that cannot be written stops the run (ramp to the safe value at
        ``safety.ramp_V_per_s``, whatever ``on_finish`` says): no setpoint is sent that no
        record will show, beyond that ramp."""
        ctl = self.ctl
        err = ctl.runlog.error if ctl.runlog is not None else None
        if err is None or ctl.runlog_error is not None:
            return
        ctl.runlog_error = str(err)
        ctl._errors += 1
        ctl._last_error = ctl.runlog_error
        ctl._event("runlog-error", ctl.runlog_error)
        if ctl._request != "estop":
            ctl._request = "runlog-error"
        ctl._feed_stop = True

    def _records(self, r: int) -> int:
        """Hand the ring's rows ``r`` .. ``_w`` on (rows overwritten before they were copied
        are counted in ``dropped_records``); returns the new read count."""
        ctl = self.ctl
        w = ctl._w
        if w == r:
            return r
        if w - r > RING_ROWS:
            ctl._dropped += w - r - RING_ROWS
            r = w - RING_ROWS
        rows = ctl._ring[np.arange(r, w) & (RING_ROWS - 1)]
        if ctl._w - r > RING_ROWS:  # overwritten while copying
            keep = (ctl._w - RING_ROWS) - r
            rows = rows[keep:] if keep < len(rows) else rows[:0]
            ctl._dropped += keep
        sp, dr = self._as_records(rows)
        if ctl.runlog is not None:
            ctl.runlog.write_setpoints(sp)
            ctl.runlog.write_drift(dr)
        if len(sp):
            self.call_sinks("on_setpoints", sp)
            last = dr[-1]
            std = rows[-1, C_S:C_S + 3]
            self.call_sinks("on_drift", {"seq": int(last["seq"]), "t_s": float(last["t_s"]),
                                         "T_C": float(last["T_C"]),
                                         "drift_nm": [float(v) for v in last["drift_nm"]],
                                         "std_nm": None if math.isnan(std[0]) else [float(v) for v in std]})
        return w

    def _as_records(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ring rows → (setpoint records, drift records)."""
        dt = self.ctl.dt_s
        sp = np.zeros(len(rows), SETPOINT_DTYPE)
        sp["seq"] = rows[:, C_SEQ].astype(np.uint64)
        sp["t_s"] = rows[:, C_TICK] * dt
        sp["target_nm"] = rows[:, C_TGT:C_TGT + 3]
        sp["corrected_nm"] = rows[:, C_COR:C_COR + 3]
        sp["u_V"] = rows[:, C_U:C_U + 3]
        dr = np.zeros(len(rows), DRIFT_DTYPE)
        dr["seq"] = sp["seq"]
        dr["t_s"] = sp["t_s"]
        dr["T_C"] = rows[:, C_T]
        dr["drift_nm"] = rows[:, C_D:C_D + 3]
        dr["std_nm"] = rows[:, C_S:C_S + 3]      # NaN when the Kalman filter is off
        return sp, dr

    def _events(self) -> None:
        ctl = self.ctl
        while ctl._events:
            ev = ctl._events.popleft()
            if ctl.runlog is not None:
                ctl.runlog.write_event(ev)
            st = ctl._status(ev["event"], ev.get("detail"))
            st["state"] = ev["state"]
            self.call_sinks("on_status", st)
