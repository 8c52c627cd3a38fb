"""A device still playing on its own clock when a run starts — a wave generator that played
on after an earlier run's link error (found by benchmarks/soak.py) — is stopped before the
output is read back: the host's ramp never alternates with the table's samples."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.control.controller import Controller, State
from afmctl.control.hardware import open_driver
from afmctl.sim_backend.amplifiers.base import RecordingSink
from afmctl.sim_backend.testing import serve_pty
from afmctl.testing import assert_no_threads_left, make_config

pytestmark = pytest.mark.slow
SLEW_V_PER_S = 2000.0
RATE_HZ = 1000.0


@pytest.fixture(autouse=True)
def no_leaked_threads():
    yield
    assert_no_threads_left("afmctl-")


def test_a_run_stops_a_wave_generator_left_playing_before_it_moves(tmp_path):
    sink = RecordingSink(max_history=1_000_000)
    with serve_pty("gcs", sink=sink, baud=921600) as srv:
        cfg = make_config(tmp_path, loop={"rate_Hz": RATE_HZ},
                          amplifier={"driver": "gcs", "port": srv.port, "slew_V_per_s": SLEW_V_PER_S,
                                     "limits_V": {a: {"min_V": 0.0, "max_V": 120.0} for a in "xyz"}},
                          safety={"slew_V_per_s": SLEW_V_PER_S, "ramp_V_per_s": 1000.0, "watchdog_s": 0.2})
        amp = open_driver(cfg, srv.port)
        try:
            # an earlier run's table: a slow 0 -> 60 -> 0 V triangle on x, 30 s, left playing
            n = 6_000
            tri = 60.0 * (1.0 - np.abs(np.linspace(-1.0, 1.0, n)))
            amp.upload_wave("x", tri)
            amp.start_wave(divider=100, cycles=1, axes=["x"])     # 20 kHz servo / 100: 200 Hz, 30 s
            assert amp.wave_status().running["x"]
            with Controller(cfg, amp) as ctl:
                ctl.start(np.column_stack([np.full(200, 800.0), np.zeros(200), np.zeros(200)]))
                assert ctl.wait(60)
            assert ctl.state is State.STOPPED
            assert not any(amp.wave_status().running.values())
        finally:
            amp.close()
    xs = np.array([v["x"] for _t, v in sink.history if "x" in v])
    steps = np.abs(np.diff(xs))
    # the generator's own points step by 0.02 V at most; the ramp by slew/rate = 2 V
    assert steps.max() <= SLEW_V_PER_S / RATE_HZ * (1 + 1e-6) + 1e-9, steps.max()
