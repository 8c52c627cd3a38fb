"""``afmctl learn`` on a configuration with host-timed setpoints (as most shipped examples are)
on a device that plays tables and records: it learns as ``output = "wave"`` and says so in one
line, and ``afmctl run`` of the learned table reproduces the learned figure per axis. A table
the recorder cannot hold is refused before anything plays."""
from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow

CONFIG = """
[scanner]
name = "host-timed"
axes = ["x", "y", "z"]
[scanner.calibration.x]
nm_per_V = 80.0
[amplifier]
driver = "gcs"
{output}
slew_V_per_s = 10000.0
settle_s = 0.2
[loop]
rate_Hz = 10000
[safety]
slew_V_per_s = 10000.0
ramp_V_per_s = 5000.0
[trajectory]
{trajectory}
[runlog]
dir = "{dir}"
fsync = false
[simulation]
enabled = true
baud = 921600
scanner = "{scanner}"
"""
RASTER = """kind = "raster"
x0_nm = 3000.0
y0_nm = 3000.0
width_nm = 2000.0
height_nm = 0.0
lines = 2
line_rate_Hz = 20.0"""
#: a learned figure: axis, max [nm]
FIGURE = re.compile(r"\b([xyz]) max ([\d.e+-]+) nm \(")


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "afmctl", *args], capture_output=True, text=True, timeout=600)


def _scanner(tmp_path):
    from afmctl.sim_backend.scanner import default_scanner_config
    cfg = default_scanner_config()
    cfg.dt_s = 5e-5          # two simulation steps per table point: the in-process simulator keeps up when loaded
    path = tmp_path / "scanner.json"
    path.write_text(cfg.model_dump_json())
    return path


def test_learn_on_host_timed_setpoints_learns_a_wave_that_run_reproduces(tmp_path):
    fill = dict(dir=tmp_path, scanner=_scanner(tmp_path))
    (tmp_path / "learn.toml").write_text(CONFIG.format(output='output = "setpoints"', trajectory=RASTER, **fill))
    res = _cli("learn", "--config", str(tmp_path / "learn.toml"), "--iterations", "1", "--out", str(tmp_path / "L.afmwave"))
    assert res.returncode == 0, res.stderr[-3000:]
    assert "amplifier.output = 'setpoints': learning plays each table on the gcs amplifier's clock" in res.stderr
    final = next(ln for ln in res.stderr.splitlines() if ln.startswith("afmctl: learned table"))
    learned = {a: float(v) for a, v in FIGURE.findall(final)}
    assert set(learned) == {"x"}, final

    trajectory = f'kind = "learned"\nfile = "{tmp_path / "L.afmwave"}"'
    (tmp_path / "run.toml").write_text(CONFIG.format(output='output = "wave"', trajectory=trajectory, **fill))
    run = _cli("run", "--config", str(tmp_path / "run.toml"), "--json")
    assert run.returncode == 0, run.stderr[-3000:]
    tracking = json.loads(run.stdout)["tracking"]
    played = tracking["recorded"]["axes"]["x"]["max_nm"]
    # within 20 % of the learned figure, or 1.5 nm near the noise floor (two plays from rest differ by ~1 nm)
    assert abs(played - learned["x"]) <= 0.2 * learned["x"] + 1.5, (played, learned)
    assert tracking["lag"]["recorded"][0]["axis"] == "x"          # the lag, from the recorder as well
    assert tracking["lag"]["path_delay"]["advance_samples"] == 0


def test_a_table_the_recorder_cannot_hold_is_refused_before_it_plays(tmp_path):
    long_raster = RASTER.replace("lines = 2", "lines = 200")       # 10 s at 10 kHz: 100000 rows
    (tmp_path / "learn.toml").write_text(CONFIG.format(output="", trajectory=long_raster, dir=tmp_path,
                                                       scanner=_scanner(tmp_path)))
    res = _cli("learn", "--config", str(tmp_path / "learn.toml"), "--out", str(tmp_path / "L.afmwave"))
    assert res.returncode == 2, res.stderr[-3000:]
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("afmctl: error:")]
    assert len(errors) == 1 and "do not fit the gcs recorder's" in errors[0] and "nothing was played" in errors[0]
    assert "Traceback" not in res.stderr
