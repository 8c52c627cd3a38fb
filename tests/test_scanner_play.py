"""Scanner.play (a block of clock-timed samples) equals the same samples applied one by one."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

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
