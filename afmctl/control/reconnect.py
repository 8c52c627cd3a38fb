"""The loop's fault and reconnect policy: what a link error, a reconnect attempt and a
read-back do to a run (``safety.reconnect_interval_s``, ``safety.max_reconnects``; the
transitions are those of :mod:`afmctl.control.transitions`).

* read-back at the start and after a reconnect: within one slew step of the limits → go on;
  not a voltage or further outside → the run ends in ``fault`` at once
  (``readback-refused``; nothing is sent);
* a link error in a tick → ``fault``; the device holds its output; ``reconnect()`` every
  ``reconnect_interval_s`` on a helper thread (``afmctl-reconnect``: a serial driver blocks for
  up to its reconnect timeout, the loop keeps ticking and honours a stop at once), up to
  ``max_reconnects`` attempts (then ``give-up``: the run ends in ``fault``); on success the
  output is read back and the run resumes where it was (the machine's ``_resume``);
* a refused setpoint (``LimitError``: the driver's limits disagree with the configuration,
  nothing was sent) ends the run in ``fault`` without reconnecting;
* a link error while finishing ends the run (``stop-in-fault``; the device holds).

:class:`FaultPolicy` holds the attempt count, the next attempt's time and the attempt in
flight; it talks to the machine through ``fsm``, ``in_fault``, ``now_s``, ``u_prev`` and
``_resume()``, and to the controller through its counters and events.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any

from afmctl.drivers.errors import AmplifierError, LimitError

from ..errors import error_line
from .safety import ReadbackError
from .transitions import Event, Phase, State

log = logging.getLogger(__name__)

#: errors of the amplifier link that put the loop into the fault state
FAULT_ERRORS = (AmplifierError, OSError)


def enter_fault(ctl: Any, err: BaseException) -> None:
    """Count a link error on the controller and publish ``fault``."""
    ctl._errors += 1
    ctl._faults += 1
    ctl._last_error = error_line(err)
    log.warning("amplifier fault: %s", ctl._last_error)
    ctl._set_state(State.FAULT, "fault", ctl._last_error)


class FaultPolicy:
    """The fault/reconnect policy of one run of ``machine`` (see the module docstring)."""

    def __init__(self, machine: Any) -> None:
        self.m = machine
        self.ctl = machine.ctl
        cfg = self.ctl.config
        self.interval_s = cfg.safety.reconnect_interval_s
        self.max_reconnects = cfg.safety.max_reconnects
        self.attempts = 0
        self.next_attempt_s = 0.0
        self.rc_thread: threading.Thread | None = None      # reconnect attempt in flight
        self.rc_error: BaseException | None = None

    # ------------------------------------------------------------------ read-back
    def sync_at_start(self) -> bool:
        """Read the device's present output. A link error starts the run in fault
        (reconnecting, as the table says); a read-back that is not a voltage or lies more than
        one slew step outside the limits ends the run (:meth:`refuse_readback`: False)."""
        m, ctl, safety = self.m, self.ctl, self.m.safety
        try:
            warnings = safety.stop_leftover_playback() + safety.sync_from_device()
        except ReadbackError as err:
            return self.refuse_readback(err)
        except FAULT_ERRORS as err:
            enter_fault(ctl, err)
            self.next_attempt_s = time.perf_counter() + self.interval_s
            if m.fsm.fire(Event.FAULT) is Phase.FAULT:
                m.in_fault = True
            return True
        for w in warnings:
            ctl._event("readback", w)
        m.u_prev = safety.xyz(safety.last)
        m.fsm.fire(Event.READBACK_IN)
        return True

    def refuse_readback(self, err: BaseException) -> bool:
        """The output read back cannot be placed within the limits: end the run in fault
        without sending anything (a ramp from there would leave the limits). Returns False."""
        ctl = self.ctl
        self.m.fsm.fire(Event.READBACK_OUT)
        ctl._errors += 1
        ctl._faults += 1
        ctl._last_error = error_line(err)
        ctl._set_state(State.FAULT, "readback-refused", ctl._last_error)
        self.m.in_fault = True
        return False

    # ------------------------------------------------------------------ link errors
    def on_link_error(self, err: BaseException) -> bool:
        """A driver error in a tick: False when it ends the run (refused setpoint, or a link
        error while finishing, or an output mode without reconnects), True when reconnecting."""
        m, ctl = self.m, self.ctl
        if isinstance(err, LimitError):
            m.fsm.fire(Event.REFUSED)
            ctl._errors += 1
            ctl._last_error = error_line(err)
            ctl._set_state(State.FAULT, "refused", f"the driver refused a setpoint: {ctl._last_error}")
            m.in_fault = True
            return False
        enter_fault(ctl, err)
        nxt = m.fsm.fire(Event.FAULT)
        if nxt is Phase.STOPPED:            # finishing: nothing more can be sent, the device holds
            ctl._event("stop-in-fault", "link lost: the output could not be ramped")
            ctl._set_state(State.STOPPED, "stopped")
        if nxt is not Phase.RETRY:
            m.in_fault = True
            return False
        m.ramping = False
        self.next_attempt_s = time.perf_counter() + self.interval_s
        self.attempts = 0
        return True

    # ------------------------------------------------------------------ reconnects
    def tick(self) -> bool:
        """One tick with the link down: start an attempt when the interval is over, take
        the outcome of the attempt in flight; False when the run ends (give-up)."""
        m, ctl = self.m, self.ctl
        if self.rc_thread is not None:
            if not self.rc_thread.is_alive():
                self.rc_thread = None
                return self._after_attempt()
            return True
        if m.now_s < self.next_attempt_s:
            return True
        if self.attempts >= self.max_reconnects:
            m.fsm.fire(Event.RECONNECTS_EXHAUSTED)
            ctl._event("give-up", f"{self.attempts} reconnect attempts failed")
            m.in_fault = True
            return False
        m.fsm.fire(Event.DONE)           # the wait is over: RETRY -> RECONNECT
        self.attempts += 1
        self.rc_error = None
        self.rc_thread = threading.Thread(target=self._attempt, name="afmctl-reconnect", daemon=True)
        ctl._rc_thread = self.rc_thread  # the controller joins it on close() and before a new start
        self.rc_thread.start()
        return True

    def _attempt(self) -> None:
        """One ``amplifier.reconnect()`` (helper thread; may block for the driver's
        reconnect timeout). The loop thread reads the outcome from ``rc_error``."""
        try:
            self.ctl.amplifier.reconnect()
        except Exception as err:  # noqa: BLE001 - reported by the loop thread
            self.rc_error = err

    def _after_attempt(self) -> bool:
        """An attempt finished: on success read the output back and resume; on failure try
        again after the interval; a read-back outside the limits ends the run (False)."""
        m, ctl, safety = self.m, self.ctl, self.m.safety
        err = self.rc_error
        if err is None:
            m.fsm.fire(Event.RECONNECT_OK)
            try:
                warnings = safety.stop_leftover_playback() + safety.sync_from_device()
            except ReadbackError as e:
                return self.refuse_readback(e)
            except Exception as e:   # noqa: BLE001 - any other failure: the link is still down
                err = e
                m.fsm.fire(Event.FAULT)
        else:
            m.fsm.fire(Event.RECONNECT_FAILED)
        if err is not None:
            ctl._errors += 1
            ctl._last_error = error_line(err)
            self.next_attempt_s = time.perf_counter() + self.interval_s
            return True
        for w in warnings:
            ctl._event("readback", w)
        ctl._reconnects += 1
        m.u_prev[:] = safety.xyz(safety.last)
        self.attempts = 0
        m.fsm.fire(Event.READBACK_IN)
        m._resume()
        return True
