"""The loop thread's state machine, timing histograms and the moved ``resample``."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from afmctl.control import stats as loop_stats
from afmctl.errors import error_line
from afmctl.control.machine import LoopMachine, Mode, State
from afmctl.inputs.trajectories import resample

from test_architecture import import_graph

ROOT = Path(__file__).resolve().parents[1]


def test_modes_and_states_are_named():
    assert [m.value for m in Mode] == ["run", "settle", "finish"]
    assert [s.value for s in State] == ["idle", "running", "holding", "fault", "stopped"]
    # every mode has a tick method
    for m in Mode:
        assert hasattr(LoopMachine, f"_tick_{m.value}")


@pytest.mark.parametrize("v", [0.0, 1e-7, 0.49e-6, 0.5e-6, 1.234e-3, 1.99999e-3, 2e-3, 2.05e-3, 0.05, 0.1019, 0.2, 5.0])
def test_fast_histogram_add_lands_in_the_bin_of(v):
    h = loop_stats.new_histogram()
    loop_stats.add(h, v)
    assert h.sum() == 1 and h[loop_stats.bin_of(v)] == 1


def test_percentiles_are_bin_centres():
    h = loop_stats.new_histogram()
    for v in (10e-6, 10e-6, 10e-6, 3e-3):
        loop_stats.add(h, v)
    p50, p99 = loop_stats.percentiles(h, (0.5, 0.99))
    assert p50 == pytest.approx(10.25e-6) and p99 == pytest.approx(3.05e-3)


def test_resample_lives_with_the_trajectories_and_interpolates_linearly():
    p = np.column_stack([np.arange(5.0), 2 * np.arange(5.0), np.zeros(5)])
    out = resample(p, 1.0, 0.5)
    assert out.shape == (9, 3)
    np.testing.assert_allclose(out[:, 0], np.arange(9) * 0.5)
    np.testing.assert_allclose(out[:, 1], np.arange(9) * 1.0)
    assert resample(p, 1.0, 1.0) is not None and np.array_equal(resample(p, 1.0, 1.0), p)


def test_trajectories_and_loop_machine_do_not_import_the_controller():
    graph = import_graph(ROOT)
    for module in ("afmctl.inputs.trajectories", "afmctl.control.machine"):
        assert "afmctl.control.controller" not in graph[module]


def test_error_line_folds_whitespace_and_names_an_empty_error():
    assert error_line(OSError("disk\n  full")) == "disk full"
    assert error_line(TimeoutError()) == "TimeoutError"




def test_aligned_deadlines_fall_at_the_phase_of_a_period():
    """loop.phase: a tick's deadline at or before now, at that share of a period on the
    monotonic clock (every process the same), the next within one period; unset: now."""
    from afmctl.control.machine import aligned_s
    period = 1e-3
    for now in (10.0004, 10.0011, 5.12345, 7.0):
        for phase in (0.0, 1 / 3, 0.5, 0.99):
            t = aligned_s(now, period, phase)
            assert now - period < t <= now
            k = (t - phase * period) / period
            assert abs(k - round(k)) < 1e-6, (now, phase, t)
    assert aligned_s(10.0004, period, None) == 10.0004
