"""The loop's state machine (afmctl.control.transitions), exhaustively: every (phase, event)
pair of every output mode's table has a defined next phase, from every phase a stop leads to
FINISH or a terminal phase and FINISH only to itself or a terminal phase (the stop bound), and
both checks fail on a copy of the table with one entry removed or one stop transition
redirected. The loop thread looks its next phase up in these tables (PhaseMachine.fire), so
an undefined pair cannot silently loop: it raises. tests/test_stop_bound.py drives the real
controller into each phase and stops it there."""
from __future__ import annotations

import pytest

from afmctl.control.transitions import (REQUESTS, TABLES, TERMINAL, Event, Phase, PhaseMachine, missing_pairs,
                                        stop_escapes)

PAIRS = [(p, e) for p in Phase for e in Event]


def test_the_tables_are_exhaustive_and_keep_the_stop_bound():
    assert len(PAIRS) == len(Phase) * len(Event) == 168
    for name, table in TABLES.items():
        assert missing_pairs(table) == [], name
        assert len(table) == len(PAIRS), name
        assert stop_escapes(table) == [], name
        for p in TERMINAL:      # terminal phases absorb every event
            assert all(table[(p, e)] is p for e in Event), (name, p)


@pytest.mark.parametrize("output", sorted(TABLES))
def test_every_phase_reaches_an_end_after_a_request_and_max_reconnects_ends_in_fault(output):
    """From every phase, a request and then the finish's own ``done`` (or a link error) end
    the run; retries end in FAULT once ``max_reconnects`` attempts failed."""
    table = TABLES[output]
    for p in Phase:
        for r in REQUESTS:
            for then in (Event.DONE, Event.FAULT, Event.REFUSED):
                m = PhaseMachine(table, p)
                m.fire(r)
                m.fire(then)
                assert m.ended, (output, p, r, then, list(m.trail))
    for p in (Phase.RETRY, Phase.RECONNECT):
        m = PhaseMachine(table, p)
        assert m.fire(Event.RECONNECTS_EXHAUSTED) is Phase.FAULT


def test_read_back_outside_the_limits_ends_in_fault_at_start_and_after_a_reconnect():
    for table in TABLES.values():
        assert table[(Phase.SYNC, Event.READBACK_OUT)] is Phase.FAULT
    m = PhaseMachine(TABLES["setpoints"], Phase.RUN)
    for e in (Event.FAULT, Event.DONE, Event.RECONNECT_OK, Event.READBACK_OUT):
        m.fire(e)
    assert [t[2] for t in m.trail] == [Phase.RETRY, Phase.RECONNECT, Phase.SYNC, Phase.FAULT]


@pytest.mark.parametrize("pair", PAIRS, ids=lambda pe: f"{pe[0].value}-{pe[1].value}")
def test_self_check_a_removed_transition_is_caught(pair):
    """The checks above are not vacuous: the setpoint table with this one entry removed fails
    the exhaustiveness check, and the loop's phase machine raises on that pair instead of
    guessing."""
    broken = dict(TABLES["setpoints"])
    del broken[pair]
    assert missing_pairs(broken) == [pair]
    m = PhaseMachine(broken, pair[0])
    with pytest.raises(KeyError):
        m.fire(pair[1])


@pytest.mark.parametrize("phase", [p for p in Phase if p not in TERMINAL])
def test_self_check_a_stop_that_does_not_stop_is_caught(phase):
    """Redirecting one request transition back into the phase (a stop that is not honoured)
    or FINISH's ``done`` back into RUN breaks the stop bound, and the check says where."""
    for r in REQUESTS:
        broken = dict(TABLES["setpoints"])
        if phase is Phase.FINISH:
            broken[(phase, Event.DONE)] = Phase.RUN
        else:
            broken[(phase, r)] = phase
        assert stop_escapes(broken), (phase, r)
