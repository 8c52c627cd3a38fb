"""A measured motion from an external sensor as a file (afmctl/data/motion_files.py), read into
the same Recording a device's recorder returns."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.drivers.recording import Recording
from afmctl.errors import AfmctlError
from afmctl.data.motion_files import read_motion_csv, write_motion_csv


def _write(path, text):
    path.write_text(text, encoding="utf-8")
    return path


def test_t_y_file_is_one_axis_in_nm(tmp_path):
    rec = read_motion_csv(_write(tmp_path / "m.csv", "t,y,u\n0,1.5,10\n1e-4,2.5,11\n2e-4,3.5,12\n"))
    assert rec.axes == ("x",) and rec.period_s == pytest.approx(1e-4) and rec.source == "file m.csv"
    np.testing.assert_array_equal(rec.y_nm["x"], [1.5, 2.5, 3.5])
    np.testing.assert_array_equal(rec.u_V["x"], [10, 11, 12])
    assert read_motion_csv(tmp_path / "m.csv", axis="y").axes == ("y",)


def test_t_x_y_z_file_is_per_axis(tmp_path):
    rec = read_motion_csv(_write(tmp_path / "m.csv", "t,x,y,z\n0,1,2,3\n0.5,4,5,6\n"))
    assert set(rec.y_nm) == {"x", "y", "z"} and not rec.u_V and rec.y_nm["z"].tolist() == [3, 6]


def test_round_trip_of_a_device_recording(tmp_path):
    t = np.arange(5) * 1e-4
    for y in ({"x": t * 1e6}, {"x": t * 1e6, "y": t * 2e6}):
        rec = Recording(t, y, {a: v / 100 for a, v in y.items()}, 1e-4, "gcs DRR?")
        write_motion_csv(tmp_path / "r.csv", rec)
        back = read_motion_csv(tmp_path / "r.csv")
        assert set(back.y_nm) == set(y)
        for a in y:
            np.testing.assert_array_equal(back.y_nm[a], y[a])
            np.testing.assert_array_equal(back.u_V[a], y[a] / 100)


@pytest.mark.parametrize("text, match", [
    ("t,pos\n0,1\n1,2\n", "no position column.*t,y"),
    ("t,y\n0,1\n", "at least 2 required"),
    ("t,y\n0,1\n1,nan\n", "row 3: column y.*not finite"),
    ("t,y\n0,1\n1,2\n3,3\n", "uniformly spaced"),
    ("t,y\n0,1\n0,2\n", "strictly increasing"),
])
def test_bad_files_get_one_line_naming_file_and_column(tmp_path, text, match):
    with pytest.raises(AfmctlError, match=match) as info:
        read_motion_csv(_write(tmp_path / "bad.csv", text))
    assert "bad.csv" in str(info.value) and "\n" not in str(info.value)
