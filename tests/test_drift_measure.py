"""``afmctl drift measure``: simulated frames of nanoparticles with known tip drifts, written
as TIFF (tifffile) and Gwyddion (gwyfile) files, recovered by phase correlation ≤ 0.2 px."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.data.datafiles import read_csv
from afmctl.sim_backend.samples import Nanoparticles

SCAN_NM, PX = 400.0, 128
DRIFTS_NM = [(0.0, 0.0), (7.3, -4.1), (15.9, -9.4), (22.2, -11.0)]   # tip drift (x, y) per frame


def frame(sample, drift_nm, rng):
    c = (np.arange(PX) + 0.5) * SCAN_NM / PX
    x, y = np.meshgrid(c + drift_nm[0], c + drift_nm[1])   # rows = y (slow axis), columns = x
    return sample.height_nm(x, y) + rng.normal(0.0, 0.05, x.shape)


@pytest.fixture(scope="module")
def frames():
    sample = Nanoparticles.random(60, (SCAN_NM * 1.3, SCAN_NM * 1.3), diameter_nm=15.0, spread=0.3, seed=2)
    rng = np.random.default_rng(1)
    return [frame(sample, d, rng) for d in DRIFTS_NM]


def write_tiff(path, img):
    import tifffile
    tifffile.imwrite(path, img, metadata={"scan_size_nm": SCAN_NM, "line_rate_Hz": 1.0, "z_unit": "nm"})


def write_gwy(path, img):
    from gwyfile.objects import GwyContainer, GwyDataField
    c = GwyContainer()
    c["/0/data/title"] = "Height trace"
    c["/0/data"] = GwyDataField(np.ascontiguousarray(img * 1e-9), xreal=SCAN_NM * 1e-9, yreal=SCAN_NM * 1e-9)
    c["/0/meta"] = GwyContainer({"Scan rate": "1.0 Hz"})
    c.tofile(str(path))


def write_ibw(path, img):
    """Asylum layout (igorwriter): (points, lines, layers) in m, layer names in dimension 2's labels."""
    from igorwriter import IgorWave
    wave = IgorWave(np.ascontiguousarray((img * 1e-9).T[:, :, None]), name="frame")
    wave.set_dimlabel(2, 0, "HeightTrace")
    wave.set_note(f"ScanSize: {SCAN_NM * 1e-9!r}\rScanRate: 1.0\r")
    wave.save(str(path))


@pytest.mark.parametrize("suffix,writer", [(".tif", write_tiff), (".gwy", write_gwy), (".ibw", write_ibw)])
def test_drift_measure_recovers_known_shifts(tmp_path, frames, capsys, suffix, writer):
    paths = []
    for k, img in enumerate(frames):
        p = tmp_path / f"f{k}{suffix}"
        writer(p, img)
        paths.append(str(p))
    rc = main(["drift", "measure", *paths, "--out", str(tmp_path / "d.csv")])
    out = capsys.readouterr().out
    assert rc == 0 and out.startswith("drift measure: 4 frames")
    d = read_csv(tmp_path / "d.csv", ("t", "x", "y", "dx_px", "dy_px"))
    px_nm = SCAN_NM / PX
    err_px = np.hypot(d["x"] - [a for a, _ in DRIFTS_NM], d["y"] - [b for _, b in DRIFTS_NM]) / px_nm
    assert np.max(err_px) <= 0.2, err_px
    np.testing.assert_allclose(d["t"], [0.0, 128.0, 256.0, 384.0])   # lines / line rate


def test_drift_measure_needs_a_frame_period_without_line_rate(tmp_path, frames, capsys):
    import tifffile
    for k in range(2):
        tifffile.imwrite(tmp_path / f"g{k}.tif", frames[k], metadata={"scan_size_nm": SCAN_NM})
    rc = main(["drift", "measure", str(tmp_path / "g0.tif"), str(tmp_path / "g1.tif"), "--out", str(tmp_path / "d.csv")])
    err = capsys.readouterr().err
    assert rc == 2 and "--frame-period-s" in err
    assert main(["drift", "measure", str(tmp_path / "g0.tif"), str(tmp_path / "g1.tif"), "--out",
                 str(tmp_path / "d.csv"), "--frame-period-s", "60"]) == 0
