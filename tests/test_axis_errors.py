"""Errors a user can check (afmctl/data/axis_errors.py): per axis, in nm and in % of that
axis's line or step, over the central part of a raster's lines; the paths of a
configuration resolve from its folder; a device-timed run's summary does not call its host
ramps' late ticks missed deadlines."""
from __future__ import annotations

import typing
from pathlib import Path

import numpy as np
import pytest

from afmctl.data.axis_errors import axis_errors, raster_lines
from afmctl.inputs.trajectories import collect, moves, raster

DT_S = 1e-4


def _raster(mode: str = "trace-retrace") -> np.ndarray:
    return collect(raster(DT_S, x0_nm=1000.0, y0_nm=1000.0, width_nm=4000.0, height_nm=800.0, lines=10,
                          line_rate_Hz=50.0, mode=mode))


@pytest.mark.parametrize("mode", ["trace-retrace", "bidirectional"])
def test_a_raster_is_judged_on_its_lines_central_part_per_axis_line_or_step(mode):
    tgt = _raster(mode)
    fast, lines = raster_lines(tgt)
    assert fast == "x" and len(lines) == (20 if mode == "trace-retrace" else 10)
    pos = tgt.copy()
    pos[:, 0] += 8.0                                  # x off by 8 nm everywhere
    pos[:, 1] += 0.5 * 800.0 / 9                      # y off by half a line pitch
    corner = lines[0].stop - 1                        # a turnaround: outside the central 80 %
    pos[corner, 0] += 500.0
    r = axis_errors(tgt, pos)
    x, y, z = r.axes
    assert "central 80 % of lines 2.." in r.part and "x is the fast axis" in r.part
    assert (x.ref, x.ref_nm) == ("line", pytest.approx(4000.0, rel=0.01))
    assert x.max_nm == pytest.approx(8.0) and x.max_pct == pytest.approx(0.2, rel=0.01)    # the corner left out
    assert (y.ref, y.ref_nm) == ("step", pytest.approx(800.0 / 9, rel=0.01))
    assert y.max_pct == pytest.approx(50.0, rel=0.01)
    assert z.ref is None and z.max_pct is None and "holds" in z.text()
    assert r.worst_pct() == pytest.approx(50.0, rel=0.01)
    assert "x max 8 nm (0.2 %)" in x.text() and "of its 4000 nm line" in x.text()


def test_a_raster_padded_with_long_rests_is_still_judged_on_its_lines():
    tgt = _raster()                      # a wave table's padding: rests longer than the raster
    pad = 3 * len(tgt)
    padded = np.vstack([np.repeat(tgt[:1], pad, axis=0), tgt, np.repeat(tgt[-1:], pad, axis=0)])
    r = axis_errors(padded, padded + np.array([8.0, 0.0, 0.0]))
    assert "x is the fast axis" in r.part and r.axes[0].ref == "line" and r.axes[0].max_nm == pytest.approx(8.0)


def test_a_trajectory_without_lines_is_judged_whole_in_percent_of_each_axis_range():
    tgt = collect(moves([(3000.0, 500.0, 0.0), (0.0, 2500.0, 0.0)], DT_S, dwell_s=0.01))
    assert raster_lines(tgt) is None
    pos = tgt + np.array([30.0, 25.0, 0.0])
    r = axis_errors(tgt, pos, "xy")
    assert r.part.startswith("the whole record") and r.samples == len(tgt)
    assert [a.ref for a in r.axes] == ["range", "range"]
    assert r.axes[0].max_pct == pytest.approx(1.0) and r.axes[1].max_pct == pytest.approx(1.0)


def _path_fields(model, prefix=""):
    """Every field of the configuration schema typed as a path (walked through the tables)."""
    from pydantic import BaseModel
    for name, f in model.model_fields.items():
        for arg in typing.get_args(f.annotation) or (f.annotation,):
            for leaf in typing.get_args(arg) or (arg,):
                if isinstance(leaf, type) and issubclass(leaf, BaseModel):
                    yield from _path_fields(leaf, prefix + name + ".")
                elif leaf is Path:
                    yield prefix + name


def test_every_path_of_a_configuration_resolves_from_its_folder(tmp_path, monkeypatch):
    from afmctl.config import Config, load_config
    sub = tmp_path / "cfg"
    sub.mkdir()
    monkeypatch.chdir(tmp_path)
    common = """
[amplifier]
driver = "gcs"
output = "wave"
[compensation]
scanner_model = "m/scanner.json"
[compensation.x]
model = "m/x.json"
[compensation.drift]
params = "m/drift.json"
[compensation.temperature]
source = "file"
file = "t.csv"
[runlog]
dir = "logs"
[simulation]
enabled = true
scanner = "sim.json"
[zenoh.tls]
root_ca = "ca.pem"
certificate = "c.pem"
private_key = "k.pem"
[zenoh.auth]
dictionary_file = "users.txt"
"""
    seen = set()
    for traj in ('kind = "learned"\nfile = "../L.afmwave"', 'kind = "file"\npath = "traj.csv"'):
        (sub / "c.toml").write_text(common + "[trajectory]\n" + traj + "\n")
        cfg = load_config(Path("cfg/c.toml"))
        for field in _path_fields(Config):
            obj = cfg
            for part in field.split("."):
                obj = getattr(obj, part, None)
            if obj is None:
                continue
            assert Path(obj).is_absolute() and Path(obj).resolve().is_relative_to(tmp_path), (field, obj)
            seen.add(field)
        assert cfg.compensation.drift.params == str(sub.resolve() / "m/drift.json")
    assert cfg.runlog.dir == sub.resolve() / "logs"
    assert {"trajectory.file", "trajectory.path", "runlog.dir"} <= seen
    assert seen >= set(_path_fields(Config)) - {"compensation.y.model", "compensation.z.model"}
    (sub / "c.toml").write_text(f'[amplifier]\ndriver = "gcs"\noutput = "wave"\n[simulation]\nenabled = true\n'
                                f'[trajectory]\nkind = "learned"\nfile = "{tmp_path / "abs.afmwave"}"\n')
    assert load_config(sub / "c.toml").trajectory.file == tmp_path / "abs.afmwave"    # absolute: as it is
    (sub / "c.toml").write_text("[simulation]\nenabled = true\n")
    assert load_config(sub / "c.toml").runlog.dir == sub.resolve() / "runs"            # the default too


def test_a_device_timed_run_does_not_report_its_host_ramps_as_missed_deadlines(capsys):
    from afmctl.commands.run import _print_summary
    summary = {"state": "stopped", "samples": 5013, "rate_Hz": 20000.0, "lateness_p50_s": 5e-4,
               "lateness_p99_s": 4e-3, "lateness_max_s": 0.3, "missed_deadlines": 945, "overruns": 135,
               "errors": 0, "faults": 0, "reconnects": 0, "watchdog_trips": 0, "slew_limited": 0, "clamped": 0,
               "wave": {"played": 4001, "samples": 4001, "player": "wave table (gcs wave generator)",
                        "inverse": []}, "runlog": "r.afmlog"}
    _print_summary(summary)
    out = capsys.readouterr().out
    assert "missed deadlines" not in out and "overruns" not in out
    assert "device-timed: the table's 4001 samples played on the device's clock" in out
    assert "1012 ticks before and after the table" in out and "not a missed deadline" in out
    _print_summary({**summary, "wave": None})                       # host-timed: as before
    assert "missed deadlines  945" in capsys.readouterr().out
