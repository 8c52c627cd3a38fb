"""The lag of a motion behind its target (afmctl/data/lag.py), the output path's delay known
in advance (afmctl/control/path_delay.py) and the loop advancing the setpoints by it."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from afmctl.control.controller import Controller, State
from afmctl.control.path_delay import LINK_CEILING_PER_S, path_delay
from afmctl.control.runlog import RunLogReader
from afmctl.data.lag import measure_lags
from afmctl.simulation.link import RecordingAmplifier
from afmctl.testing import make_config

pytestmark = pytest.mark.usefixtures("no_leaked_threads")   # tests/conftest.py


def raster(n_lines: int = 6, per_line: int = 200) -> np.ndarray:
    """Trace-retrace lines of 4000 nm on x, y stepping 100 nm per line, z held [nm]."""
    up = np.linspace(0.0, 4000.0, per_line)
    x = np.concatenate([up if k % 2 == 0 else up[::-1] for k in range(n_lines)])
    y = np.repeat(100.0 * np.arange(n_lines), per_line)
    return np.column_stack([x, y, np.full(x.size, 40.0)])


@pytest.mark.parametrize("lag", [0.0, 3.4, -1.25])
def test_a_delayed_raster_gives_its_delay_to_a_fraction_of_a_sample(lag):
    tgt = raster()
    k = np.arange(len(tgt), dtype=float)
    pos = tgt.copy()
    pos[:, 0] = np.interp(k - lag, k, tgt[:, 0]) + 2.0      # delayed by `lag` samples, 2 nm off
    x, y, z = measure_lags(tgt, pos, 1e-3, "xyz")
    assert x.samples == pytest.approx(lag, abs=0.02) and x.ms == pytest.approx(lag, abs=0.02)
    assert x.rest_max_nm == pytest.approx(2.0, abs=0.1)     # the offset is what the delay leaves
    assert y.samples is None and "slow axis" in y.why
    assert z.samples is None and "holds" in z.why


def test_path_delay_per_output_path(tmp_path):
    serial = make_config(tmp_path, amplifier={"driver": "mdt693b", "port": "/dev/ttyUSB0"}, loop={"rate_Hz": 500},
                         simulation={"enabled": False})
    p = path_delay(serial)
    assert p.delay_s == pytest.approx(1.0 / LINK_CEILING_PER_S["mdt693b"]) and p.advance == 1
    assert "115200 baud" in p.path
    assert path_delay(make_config(tmp_path, amplifier={"driver": "can", "port": "virtual:x"})).advance == 0
    tcp = make_config(tmp_path, amplifier={"driver": "gcs", "port": "socket://127.0.0.1:1"}, simulation={"enabled": False})
    assert path_delay(tcp).delay_s == 0.0
    wave = make_config(tmp_path, amplifier={"driver": "gcs", "output": "wave"})
    assert path_delay(wave).advance == 0 and "aligned" in path_delay(wave).path


class SerialRecordingAmplifier(RecordingAmplifier):
    """A recording amplifier that describes its link as an MDT693B's 115200-baud serial line
    (the transport's ``url`` and ``baudrate``, what path_delay reads)."""

    name = "mdt693b"
    transport = SimpleNamespace(url="/dev/ttyUSB0", baudrate=115200)


def _run(cfg, traj, log, amp_class=RecordingAmplifier):
    amp = amp_class()
    with Controller(cfg, amp) as ctl:
        ctl.start(traj, runlog_path=log)
        assert ctl.wait(20)
        assert ctl.state is State.STOPPED
        limited = ctl.stats()["slew_limited"]
    r = RunLogReader(log)
    ev = {e["event"]: e["seq"] for e in r.events()}
    return amp.as_array(), r.setpoints(), ev, r.meta(), limited


def test_the_loop_advances_the_setpoints_by_the_paths_ticks(tmp_path):
    """At 500 Hz a 115200-baud MDT693B setpoint takes 2.6 ms, over one 2 ms tick, to arrive: the
    loop reads one tick further ahead, each output aims at the next tick's target and is logged beside the
    target it reaches; the log's meta records the advance."""
    s = 0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, 60))
    traj = np.column_stack([1000.0 + 2000.0 * s, np.full(60, 500.0), np.full(60, 40.0)])
    common = dict(loop={"rate_Hz": 500}, safety={"slew_V_per_s": 1e5, "ramp_V_per_s": 5000})
    u0, sp0, ev0, _, lim0 = _run(make_config(tmp_path, amplifier={"driver": "mdt693b", "port": "/dev/null"}, **common),
                                 traj, tmp_path / "a.afmlog")     # in memory: no link, nothing to advance
    u1, sp1, ev1, meta, lim1 = _run(make_config(tmp_path, amplifier={"driver": "mdt693b", "port": "/dev/null"}, **common),
                                    traj, tmp_path / "b.afmlog", SerialRecordingAmplifier)
    assert meta["path_delay"]["advance_samples"] == 1
    assert RunLogReader(tmp_path / "a.afmlog").meta()["path_delay"]["advance_samples"] == 0
    a0, a1 = u0[ev0["ramp-done"]:ev0["end"]], u1[ev1["ramp-done"]:ev1["end"]]
    assert len(a1) == len(a0) + 1                      # one more output aims at the held start
    # the same outputs, one tick earlier against the targets logged (bit for bit, except
    # catch-ups after a late tick that the slew limit slowed)
    assert int(np.any(np.abs(a1[:len(a0)] - a0) > 1e-9, axis=1).sum()) <= lim0 + lim1
    np.testing.assert_array_equal(sp1["target_nm"][ev1["ramp-done"]:ev1["end"]], np.vstack([traj[:1], traj]))
    np.testing.assert_array_equal(sp0["target_nm"][ev0["ramp-done"]:ev0["end"]], traj)
