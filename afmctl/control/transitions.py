"""The loop thread's phases and the table of its transitions: every (phase, event) pair of
every output mode has one defined next phase, and the loop thread looks its next phase up
here (:class:`PhaseMachine`), so a pair missing from the table is a loud error
(``KeyError`` → the run ends in ``fault``, event ``crash``), never a silent loop.

Phases (:class:`Phase`) refine the published :class:`afmctl.control.machine.State`:

========== ===================================================== ================
phase      what the loop thread does                              published state
========== ===================================================== ================
SYNC       reads the device's output back (start, after a         running / fault
           reconnect)
RAMP       ramps from the read-back output to the pending setpoint running
RUN        plays trajectory samples                               running
HOLD       the trajectory stalled (watchdog): holds or ramps to   holding
           the safe value
SETTLE     the trajectory ended: reaches its last setpoint        running
FINISH     ramps to the safe value (or holds), then ends          running
RETRY      link down, waiting ``reconnect_interval_s``            fault
RECONNECT  a reconnect attempt in flight (helper thread)          fault
UPLOAD     wave: collect, plan, approach, upload the table        running
PLAY       wave: the device plays the table from its memory       running
STOPPED    the run is over (terminal)                             stopped
FAULT      the run ended without a usable link (terminal)         fault
========== ===================================================== ================

Events (:class:`Event`): ``stop``/``estop``/``runlog-error`` (requests, any thread; taken
at the next tick), ``fault`` (a link error), ``refused`` (the driver refused a setpoint),
``reconnect-ok``/``reconnect-failed``/``reconnects-exhausted`` (``safety.max_reconnects``
attempts failed), ``readback-in``/``readback-out`` (the output read back is / is not within
one slew step of the limits), ``trajectory-end``, ``sample`` (a trajectory sample after a
stall), ``stall`` (the watchdog), ``done`` (the phase's own work finished: ramp reached,
reconnect wait over, table uploaded / played, finish ramp reached).

Stop bound: from every phase ``stop``/``estop``/``runlog-error`` lead to FINISH or a terminal
phase, and from FINISH every event leads to FINISH or a terminal phase
(tests/test_transitions.py checks both on the tables). The loop takes a request at its next
tick, so a stop ends the run within one loop period plus the finish ramp
(``max(hi − lo) / safety.ramp_V_per_s``; at the slew limit for an estop; no ramp with
``on_finish = "hold"`` or without a link) plus one driver call; a stop during a fault ends
it at the next tick (nothing can be sent; the device holds its output). ``wait()`` returns
after the dispatcher's last pass, at most ``Controller.dispatch_interval_s`` (20 ms) later.

Three tables, one per ``amplifier.output``: :data:`SETPOINT_TABLE` (reconnects after a link
error), :data:`STREAM_TABLE` (a link error while streaming ends the run in FAULT: the FIFO
plays out, then holds), :data:`WAVE_TABLE` (SYNC leads to UPLOAD and PLAY; a link error
ends the run in FAULT).
"""
from __future__ import annotations

import collections
import enum
from collections.abc import Mapping


class State(str, enum.Enum):
    """The controller's published state (status topic, run log events)."""
    IDLE = "idle"          # not started
    RUNNING = "running"    # playing the trajectory, settling or finishing
    HOLDING = "holding"    # the watchdog saw the trajectory stall: output held or ramping to safe
    FAULT = "fault"        # a driver error: reconnecting (or the run ended without a link)
    STOPPED = "stopped"    # the run is over


class Phase(str, enum.Enum):
    """Where the loop thread is (see the module docstring)."""
    SYNC = "sync"
    RAMP = "ramp"
    RUN = "run"
    HOLD = "hold"
    SETTLE = "settle"
    FINISH = "finish"
    RETRY = "retry"
    RECONNECT = "reconnect"
    UPLOAD = "upload"
    PLAY = "play"
    STOPPED = "stopped"
    FAULT = "fault"


class Event(str, enum.Enum):
    """What happens to the loop thread (see the module docstring)."""
    STOP = "stop"
    ESTOP = "estop"
    RUNLOG_ERROR = "runlog-error"
    FAULT = "fault"
    REFUSED = "refused"
    RECONNECT_OK = "reconnect-ok"
    RECONNECT_FAILED = "reconnect-failed"
    RECONNECTS_EXHAUSTED = "reconnects-exhausted"
    READBACK_IN = "readback-in"
    READBACK_OUT = "readback-out"
    TRAJECTORY_END = "trajectory-end"
    SAMPLE = "sample"
    STALL = "stall"
    DONE = "done"


TERMINAL = frozenset({Phase.STOPPED, Phase.FAULT})
#: the events that ask the run to end
REQUESTS = (Event.STOP, Event.ESTOP, Event.RUNLOG_ERROR)
#: request name (``Controller._request``) → event
REQUEST_EVENTS = {"stop": Event.STOP, "estop": Event.ESTOP, "runlog-error": Event.RUNLOG_ERROR}

Table = Mapping[tuple[Phase, Event], Phase]


def _row(phase: Phase, stay: Phase | None = None, **moves: Phase) -> dict[tuple[Phase, Event], Phase]:
    """One phase's row: ``moves`` (event name in lower case → next phase); every other event
    leaves the phase as it is (an event that cannot happen there, or one it ignores)."""
    stay = phase if stay is None else stay
    named = {Event[k.upper()]: v for k, v in moves.items()}
    return {(phase, e): named.get(e, stay) for e in Event}


def _setpoint_table() -> dict[tuple[Phase, Event], Phase]:
    P = Phase
    to_finish = {"stop": P.FINISH, "estop": P.FINISH, "runlog_error": P.FINISH}
    ends_in_fault = {"stop": P.STOPPED, "estop": P.STOPPED, "runlog_error": P.STOPPED}
    t: dict[tuple[Phase, Event], Phase] = {}
    t |= _row(P.SYNC, **to_finish, fault=P.RETRY, refused=P.FAULT, readback_in=P.RAMP, readback_out=P.FAULT)
    t |= _row(P.RAMP, **to_finish, fault=P.RETRY, refused=P.FAULT, trajectory_end=P.SETTLE, stall=P.HOLD,
              done=P.RUN)
    t |= _row(P.RUN, **to_finish, fault=P.RETRY, refused=P.FAULT, trajectory_end=P.SETTLE, stall=P.HOLD)
    t |= _row(P.HOLD, **to_finish, fault=P.RETRY, refused=P.FAULT, trajectory_end=P.SETTLE, sample=P.RAMP)
    t |= _row(P.SETTLE, **to_finish, fault=P.RETRY, refused=P.FAULT, done=P.FINISH)
    # a link error while finishing: nothing more can be sent, the device holds (stop-in-fault)
    t |= _row(P.FINISH, fault=P.STOPPED, refused=P.FAULT, readback_out=P.FAULT, done=P.STOPPED)
    t |= _row(P.RETRY, **ends_in_fault, refused=P.FAULT, reconnects_exhausted=P.FAULT, done=P.RECONNECT)
    t |= _row(P.RECONNECT, **ends_in_fault, refused=P.FAULT, reconnect_ok=P.SYNC, reconnect_failed=P.RETRY,
              reconnects_exhausted=P.FAULT)
    # UPLOAD and PLAY are the wave's; in the setpoint loop they are never entered
    t |= _row(P.UPLOAD, **to_finish, fault=P.FAULT, refused=P.FAULT, trajectory_end=P.FINISH, done=P.PLAY)
    t |= _row(P.PLAY, **to_finish, fault=P.FAULT, refused=P.FAULT, done=P.FINISH)
    t |= _row(P.STOPPED)
    t |= _row(P.FAULT)
    return t


def _no_reconnect(table: Mapping[tuple[Phase, Event], Phase]) -> dict[tuple[Phase, Event], Phase]:
    """``table`` with every link error ending the run in FAULT (stream and wave: the device
    plays out what it holds, then holds; there is no reconnect while it plays)."""
    t = dict(table)
    for p in Phase:
        if p not in TERMINAL and t[(p, Event.FAULT)] in (Phase.RETRY, Phase.STOPPED):
            t[(p, Event.FAULT)] = Phase.FAULT
    return t


#: ``amplifier.output = "setpoints"``
SETPOINT_TABLE: Table = _setpoint_table()
#: ``amplifier.output = "stream"``
STREAM_TABLE: Table = _no_reconnect(SETPOINT_TABLE)
#: ``amplifier.output = "wave"``: the read-back leads to the upload
WAVE_TABLE: Table = {**_no_reconnect(SETPOINT_TABLE), (Phase.SYNC, Event.READBACK_IN): Phase.UPLOAD}
TABLES: dict[str, Table] = {"setpoints": SETPOINT_TABLE, "stream": STREAM_TABLE, "wave": WAVE_TABLE}


def missing_pairs(table: Mapping[tuple[Phase, Event], Phase]) -> list[tuple[Phase, Event]]:
    """The (phase, event) pairs ``table`` leaves undefined (or maps to something that is not a
    :class:`Phase`)."""
    return [(p, e) for p in Phase for e in Event if not isinstance(table.get((p, e)), Phase)]


def stop_escapes(table: Mapping[tuple[Phase, Event], Phase]) -> list[tuple[Phase, Phase | None]]:
    """Paths that break the stop bound: from some phase a request leads somewhere other than
    FINISH or a terminal phase, or a phase reachable after it leads out of that set again.
    Empty for a table that honours every stop."""
    ok = TERMINAL | {Phase.FINISH}
    bad: list[tuple[Phase, Phase | None]] = []
    for p in Phase:
        for r in REQUESTS:
            q = table.get((p, r))
            if q not in ok:
                bad.append((p, q))
    for p in ok:
        for e in Event:
            q = table.get((p, e))
            if q not in ok:
                bad.append((p, q))
    return bad


class PhaseMachine:
    """The loop thread's phase, moved only by :meth:`fire` through a table; the latest
    transitions are kept in :attr:`trail` (phase, event, next) for tests and post-mortems."""

    def __init__(self, table: Table, phase: Phase = Phase.SYNC, trail_len: int = 256) -> None:
        self.table = table
        self.phase = phase
        self.trail: collections.deque[tuple[Phase, Event, Phase]] = collections.deque(maxlen=trail_len)

    def fire(self, event: Event) -> Phase:
        """Move to the table's next phase for ``event``; an undefined pair raises KeyError."""
        nxt = self.table[(self.phase, event)]
        self.trail.append((self.phase, event, nxt))
        self.phase = nxt
        return nxt

    @property
    def ended(self) -> bool:
        return self.phase in TERMINAL
