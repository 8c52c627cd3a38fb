"""Scanner.play (a block of clock-timed samples) equals the same samples applied one by one."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.compensators.base import ModelError
from afmctl.sim_backend.scanner import Scanner


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), rate=st.sampled_from([1000.0, 5000.0, 10_000.0, 20_000.0]),
       n=st.integers(1, 300))
def test_play_equals_apply_one_by_one(seed, rate, n):
    rng = np.random.default_rng(seed)
    t0 = 0.0123
    t = t0 + np.arange(n) / rate
    rows = rng.uniform(0.0, 150.0, (n, 3))
    a, b = Scanner(), Scanner()
    for t_k, r in zip(t, rows):
        a.apply({"x": r[0], "y": r[1], "z": r[2]}, t_k)
    b.play(t, rows)
    end = t[-1] + 0.01
    a.advance(end)
    b.advance(end)
    assert abs(a.time_s - b.time_s) < 1e-9
    assert np.allclose(a.position_nm(), b.position_nm(), rtol=0, atol=1e-6)
    assert np.array_equal(a.held_voltage_V(), b.held_voltage_V())


def test_a_stream_on_the_simulated_can_amplifier_reaches_the_scanner_in_blocks():
    from afmctl.sim_backend.amplifiers.can_amp import SimCANAmplifier  # noqa: F401 - import check
    s = Scanner()
    t = np.arange(50) * 1e-4
    s.play(t, np.tile([10.0, 20.0, 30.0], (50, 1)))
    assert np.array_equal(s.held_voltage_V(), [10.0, 20.0, 30.0])


def test_a_timed_play_lands_on_the_same_samples_however_long_the_clock_ran():
    """A device's clock computes each point's time as t0 + k·period; the scanner must apply
    it on the same simulation sample whether its own clock got there in one call or in
    twenty thousand (a running sum of n·dt drifts by rounding and used to apply some points a
    sample early: the same table played twice moved differently)."""
    period, n = 1e-4, 2000
    rows = np.column_stack([60.0 + 8.0 * np.abs(((np.arange(n) / 50.0) % 2.0) - 1.0),
                            np.zeros(n), np.zeros(n)])
    # the pty server polls the device about every millisecond; this sequence of polls put the
    # old running sum 1.4e-8 samples ahead of the exact time
    polls = np.cumsum(np.random.default_rng(3).uniform(0.2e-3, 1.8e-3, 20_000))
    traces = []
    for times in (polls[-1:], polls):
        s = Scanner()
        for t in times:
            s.advance(float(t))
        t0 = np.ceil(polls[-1] / 5e-5) * 5e-5                  # the next servo tick
        cap = s.capture_sensor(t0, period, n)                  # a recorder armed with the wave start
        for k in range(0, n, 40):                              # played in blocks, as the wave generator does
            s.play(t0 + period * np.arange(k, k + 40), rows[k:k + 40])
        s.advance(t0 + period * n)
        traces.append(cap.y_nm[:, 0])
    assert np.array_equal(traces[0], traces[1])


def test_the_tap_simulates_timed_changes_in_blocks_exactly_as_one_by_one():
    """The in-process simulators' sink (ScannerTap) holds timed output changes back and
    simulates them as one block; whatever reads the scanner sees it as if each change had
    been applied at once."""
    from afmctl.simulation.link import ScannerTap
    rng = np.random.default_rng(7)
    n = 3 * ScannerTap.BATCH + 5
    t = 0.002 + np.arange(n) * 1e-4
    rows = rng.uniform(0.0, 150.0, (n, 3))
    eager, tap = Scanner(), ScannerTap(Scanner())
    for k, (t_k, r) in enumerate(zip(t, rows)):
        volts = {"x": r[0], "y": r[1]} if k % 3 else {"x": r[0], "y": r[1], "z": r[2]}
        eager.apply(volts, t_k)
        tap.apply(volts, t_k)
        if k in (10, 100):           # a read in between simulates what waited first
            assert np.allclose(tap.position_nm(), eager.position_nm(), rtol=0, atol=1e-6)
            assert tap.time_s == eager.time_s
    assert np.array_equal(tap.held_voltage_V(), eager.held_voltage_V())
    eager.advance(t[-1] + 0.01)
    tap.advance(t[-1] + 0.01)
    assert np.allclose(tap.position_nm(), eager.position_nm(), rtol=0, atol=1e-6)
    t_perf, u = tap.applied()
    assert len(t_perf) == n and np.all(np.diff(t_perf) >= 0)
    assert np.array_equal(u[-1], eager.held_voltage_V())
    with pytest.raises(ModelError, match="volts.x"):
        tap.apply({"x": float("nan")}, t[-1] + 0.02)
