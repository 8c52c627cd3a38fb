"""Bruker Nanoscope files: the real sample ``tests/data/jmarini-nanoscope/full_multiple_images.000``
(Nanoscope v5.12, Dimension 3100, tapping mode; a Height and an Amplitude channel, both
``Line direction: Retrace``) through the loader, ``drift measure`` and ``identify --from-images``;
the trace + retrace case is in tests/test_scan_files.py (files from the fixture generator)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.compensators.scan_files import is_image_file, read_scan_image, scans_from_images
from afmctl.compensators.base import ModelError
from afmctl.data.datafiles import read_csv

REAL = Path(__file__).parent / "data" / "jmarini-nanoscope" / "full_multiple_images.000"
# the file's header: \Data offset / \Data length of the Height image, \Samps/line, \Number of lines,
# \Scan size: 2 2 ~m, \Scan rate: 1.99943, \@2:Z scale: ... 438.6572 V (2 bytes/pixel), \@Sens. Zscan: 12.95302 nm/V
OFFSET, LENGTH, PIXELS, LINES = 40960, 524288, 512, 512
SCAN_NM, RATE_HZ, NM_PER_LSB = 2000.0, 1.99943, 438.6572 / 2**16 * 12.95302


def _codes_top_first(data: bytes) -> np.ndarray:
    """The Height image's int16 codes (stored bottom line first), top line first."""
    return np.frombuffer(data[OFFSET:OFFSET + LENGTH], "<i2").reshape(LINES, PIXELS)[::-1]


def test_real_file_channels_size_rate_and_heights():
    img = read_scan_image(REAL)
    assert img.only_retrace and img.retrace_nm is None      # the file holds only Retrace channels
    assert img.trace_nm.shape == (LINES, PIXELS)
    assert img.scan_size_nm == pytest.approx(SCAN_NM, rel=1e-12)
    assert img.scan_height_nm == pytest.approx(SCAN_NM, rel=1e-12)
    assert img.line_rate_Hz == pytest.approx(RATE_HZ, rel=1e-12)
    # heights = code × Z scale / 2^16 × Z sensitivity: the header's own scaling, checked against the raw bytes
    np.testing.assert_allclose(img.trace_nm, _codes_top_first(REAL.read_bytes()) * NM_PER_LSB, rtol=1e-12)
    assert 300.0 < np.ptp(img.trace_nm) < 400.0            # tapping-mode topography of a 2 µm scan


def test_real_file_refused_for_identification_with_one_line(tmp_path, capsys):
    with pytest.raises(ModelError, match="only a retrace channel"):
        scans_from_images([REAL], gain_nm_per_V=80.0, period_nm=278.0)
    rc = main(["identify", "--model", "preisach", "--from-images", str(REAL), "--out", str(tmp_path / "m.json"),
               "--param", "gain_nm_per_V=80", "--param", "period_nm=278"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert REAL.name in err and "only a retrace channel" in err


def test_drift_measure_on_the_real_file_recovers_a_known_shift(tmp_path, capsys):
    """Frame 2: the real file with its height codes rolled by (3 lines, 5 pixels); the header stays."""
    data = REAL.read_bytes()
    shifted = np.roll(_codes_top_first(data), (3, 5), axis=(0, 1))       # features move +5 px in x, +3 lines
    frame2 = tmp_path / "frame2.001"
    frame2.write_bytes(data[:OFFSET] + np.ascontiguousarray(shifted[::-1]).tobytes() + data[OFFSET + LENGTH:])
    rc = main(["drift", "measure", str(REAL), str(frame2), "--out", str(tmp_path / "d.csv")])
    out = capsys.readouterr().out
    assert rc == 0 and out.startswith("drift measure: 2 frames")
    d = read_csv(tmp_path / "d.csv", ("t", "x", "y", "dx_px", "dy_px"))
    px_nm = SCAN_NM / PIXELS
    # the tip drifted by −shift: features appear at +shift
    np.testing.assert_allclose([d["x"][1], d["y"][1]], [-5 * px_nm, -3 * px_nm], atol=0.05 * px_nm)
    np.testing.assert_allclose(d["t"], [0.0, LINES / RATE_HZ], rtol=1e-12)       # lines / \Scan rate


def test_nanoscope_suffixes_are_image_files():
    assert all(is_image_file(f"a{s}") for s in (".spm", ".SPM", ".000", ".001", ".999", ".gwy", ".ibw"))
    assert not any(is_image_file(f"a{s}") for s in (".0001", ".00", ".csv", ".npz", ".a01"))


def test_missing_converter_is_one_line_saying_what_to_install(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("GWYDDIONPY_CONVERT", str(tmp_path / "no-such-gwyconvert"))
    rc = main(["drift", "measure", str(REAL), str(REAL), "--out", str(tmp_path / "d.csv")])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and REAL.name in err
    assert "afmctl[nanoscope]" in err
