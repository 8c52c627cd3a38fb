"""``afmctl run --drift-images DIR`` in the product: a real Controller (simulated amplifier,
Kalman on) scanning while frames appear in a directory; the watcher measures them by phase
correlation and the Kalman estimate moves to the measured drift."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.config import load_config
from afmctl.inputs.drift_watch import DriftImageWatcher
from afmctl.errors import AfmctlError
from afmctl.control.controller import Controller
from afmctl.simulation.link import RecordingAmplifier
from afmctl.testing import assert_no_threads_left, wait_until

BASE = """
[simulation]
enabled = true
[loop]
rate_Hz = 1000
[safety]
slew_V_per_s = 5000
ramp_V_per_s = 500
watchdog_s = 0.5
[runlog]
dir = "{dir}"
fsync = false
[compensation.drift]
enabled = true
params = "physical_tube"
kalman = {kalman}
kalman_bias_std0_nm = 20.0
kalman_q_bias_nm2_per_s = 10.0
"""
SCAN_NM, PX = 400.0, 96


class DriftSink:
    def __init__(self):
        self.drift = []

    def on_drift(self, est):
        self.drift.append(est)


def frame(drift_nm):
    from afmctl.sim_backend.samples import Nanoparticles
    sample = Nanoparticles.random(40, (SCAN_NM * 1.3, SCAN_NM * 1.3), diameter_nm=20.0, seed=4)
    c = (np.arange(PX) + 0.5) * SCAN_NM / PX
    x, y = np.meshgrid(c + drift_nm[0], c + drift_nm[1])
    return sample.height_nm(x, y)


def write(path, img):
    tmp = path.with_suffix(".part")
    if path.suffix == ".tif":
        import tifffile
        tifffile.imwrite(tmp, img, metadata={"scan_size_nm": SCAN_NM, "line_rate_Hz": 200.0})
    else:                                   # Bruker Nanoscope, numbered as the instrument names them
        from afmctl.sim_backend.nanoscope_writer import write_nanoscope
        write_nanoscope(tmp, {"Trace": img}, scan_size_nm=SCAN_NM, line_rate_Hz=200.0)
    tmp.rename(path)                        # appears complete, as acquisition software should


@pytest.mark.parametrize("names", [("f000.tif", "f001.tif"), ("frame.000", "frame.001")])
def test_frames_feed_the_kalman_filter_while_running(tmp_path, names):
    cfg = load_config(text=BASE.format(dir=tmp_path, kalman="true"))
    frames = tmp_path / "frames"
    frames.mkdir()
    ctl = Controller(cfg, RecordingAmplifier(check_step_V=cfg.slew_V_per_s() * cfg.dt_s))
    sink = DriftSink()
    ctl.add_sink(sink)
    ctl.start(None)
    ctl.submit_segment(np.zeros((4000, 3)), cfg.dt_s)
    watcher = DriftImageWatcher(ctl, frames, std_nm=0.5, poll_s=0.05)
    try:
        wait_until(lambda: ctl.stats()["samples"] > 600)
        write(frames / names[0], frame((0.0, 0.0)))
        wait_until(lambda: watcher._feeder is not None and len(watcher._feeder.meter.frames) == 1, timeout_s=5)
        before = np.array(sink.drift[-1]["drift_nm"])
        write(frames / names[1], frame((30.0, -18.0)))       # the tip drifted by (+30, −18) nm
        wait_until(lambda: len(watcher.measured) == 1, timeout_s=5)
        seq = ctl.stats()["samples"]
        wait_until(lambda: sink.drift[-1]["seq"] > seq + 50)
        after = np.array(sink.drift[-1]["drift_nm"])
    finally:
        watcher.close()
        ctl.stop()
        ctl.wait(10)
        ctl.close()
    z = watcher.measured[0][1]
    assert z[0] == pytest.approx(30.0, abs=0.2 * SCAN_NM / PX) and z[1] == pytest.approx(-18.0, abs=0.2 * SCAN_NM / PX)
    assert after[0] - before[0] > 20.0 and after[1] - before[1] < -12.0    # the estimate moved to the images
    assert_no_threads_left("afmctl-")


def test_watcher_needs_the_kalman_filter(tmp_path):
    cfg = load_config(text=BASE.format(dir=tmp_path, kalman="false"))
    ctl = Controller(cfg, RecordingAmplifier())
    with pytest.raises(AfmctlError, match="Kalman filter is off"):
        DriftImageWatcher(ctl, tmp_path)
    ctl.close()
