"""AFM image files for ``identify --from-images``: each format written by its own library
(gwyfile, gsffile, tifffile) from the simulator's scans, read back, and identified to the same
model as the equivalent ``.npz``."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.compensators.base import ModelError
from afmctl.compensators.models import load_model
from afmctl.compensators.scan_files import read_scan_image, scans_from_images
from afmctl.sim_backend.nanoscope_writer import LSB_NM

GAIN = 80.0          # nm/V: the nominal gain turning a range's voltages into its scan size
RANGES = (150.0, 120.0, 90.0, 60.0)


@pytest.fixture(scope="module")
def scans():
    from afmctl.sim_backend.image_scans import scan_grating_lines
    from afmctl.sim_backend.scanner import Scanner

    return scan_grating_lines(Scanner(), axis="x", pixels=512, lines_per_range=3, ranges_V=RANGES, line_rate_Hz=2.0)


def _spatial(scans, r):
    """Trace and retrace of range r as an instrument stores them: both left to right, in m."""
    return scans.trace_nm[r] * 1e-9, scans.retrace_nm[r][:, ::-1] * 1e-9


def write_gwy(path, scans, r):
    from gwyfile.objects import GwyContainer, GwyDataField

    tr, rt = _spatial(scans, r)
    size_m = RANGES[r] / 1.0 * GAIN * 1e-9
    c = GwyContainer()
    for k, (title, img) in enumerate((("Height trace", tr), ("Height retrace", rt))):
        c[f"/{k}/data/title"] = title
        c[f"/{k}/data"] = GwyDataField(np.ascontiguousarray(img), xreal=size_m, yreal=size_m * img.shape[0] / img.shape[1])
    c["/0/meta"] = GwyContainer({"Line rate": "2 Hz"})
    c.tofile(str(path))


def write_gsf(path, scans, r):
    import gsffile

    tr, rt = _spatial(scans, r)
    meta = {"XReal": RANGES[r] * GAIN * 1e-9, "YReal": 1e-6, "XYUnits": "m", "ZUnits": "m", "LineRate": "2"}
    gsffile.write_gsf(path, tr.astype(np.float32), meta)
    gsffile.write_gsf(path.with_name(path.name.replace("trace", "retrace")), rt.astype(np.float32), meta)


def write_tiff(path, scans, r):
    import tifffile

    tr, rt = _spatial(scans, r)
    tifffile.imwrite(path, np.stack([tr, rt]) * 1e9,
                     metadata={"scan_size_nm": RANGES[r] * GAIN, "line_rate_Hz": 2.0, "z_unit": "nm"})


def write_ibw(path, scans, r):
    """Asylum layout, written by igorwriter: (points, lines, layers) in m, layer names as the
    labels of dimension 2, the scan parameters as ``key: value`` lines of the wave note."""
    from igorwriter import IgorWave

    tr, rt = _spatial(scans, r)
    wave = IgorWave(np.ascontiguousarray(np.stack([tr.T, rt.T], axis=2)), name="r%d" % r)
    for k, name in enumerate(("HeightTrace", "HeightRetrace")):
        wave.set_dimlabel(2, k, name)
    wave.set_note(f"ScanSize: {RANGES[r] * GAIN * 1e-9!r}\rScanRate: 2\rScanLines: {tr.shape[0]}\r"
                  f"ScanPoints: {tr.shape[1]}\r")
    wave.save(str(path))


def write_spm(path, scans, r):
    """Bruker Nanoscope v9 layout from the test-fixture generator (no library writes Nanoscope
    files): trace and retrace height channels as int32 codes of 1e-6 nm."""
    from afmctl.sim_backend.nanoscope_writer import write_nanoscope

    tr, rt = _spatial(scans, r)
    write_nanoscope(path, {"Trace": tr * 1e9, "Retrace": rt * 1e9}, scan_size_nm=RANGES[r] * GAIN, line_rate_Hz=2.0)


WRITERS = {"gwy": (write_gwy, "r{}.gwy"), "gsf": (write_gsf, "r{}_trace.gsf"), "tiff": (write_tiff, "r{}.tif"),
           "ibw": (write_ibw, "r{}.ibw"), "spm": (write_spm, "r{}.spm"), "nanoscope-numbered": (write_spm, "r.00{}")}


def _write_all(tmp_path, scans, fmt):
    writer, pattern = WRITERS[fmt]
    paths = []
    for r in range(len(RANGES)):
        p = tmp_path / pattern.format(r)
        writer(p, scans, r)
        paths.append(p)
    return paths


@pytest.mark.parametrize("fmt", sorted(WRITERS))
def test_each_format_reads_back_channels_size_and_rate(tmp_path, scans, fmt):
    paths = _write_all(tmp_path, scans, fmt)
    img = read_scan_image(paths[0])
    # gsf stores float32, Nanoscope int32 codes of LSB_NM (1e-6 nm)
    tol = {"gsf": 1e-6 * np.ptp(scans.trace_nm), "spm": LSB_NM, "nanoscope-numbered": LSB_NM}.get(fmt, 1e-9)
    np.testing.assert_allclose(img.trace_nm, scans.trace_nm[0], atol=tol)
    np.testing.assert_allclose(img.retrace_nm[:, ::-1], scans.retrace_nm[0], atol=tol)
    assert img.scan_size_nm == pytest.approx(150.0 * GAIN)
    assert img.line_rate_Hz == pytest.approx(2.0)
    arrays = scans_from_images(paths, gain_nm_per_V=GAIN, period_nm=278.0)
    np.testing.assert_allclose(arrays["u_trace_V"], scans.u_trace_V, rtol=1e-12)


@pytest.mark.parametrize("fmt", ["gsf", "gwy", "tiff", "ibw", "spm"])
def test_identify_from_image_files_equals_npz(tmp_path, scans, fmt, capsys):
    npz = scans.save_npz(tmp_path / "scans.npz")
    common = ["identify", "--model", "preisach", "--operators", "15"]
    assert main(common + ["--from-images", str(npz), "--out", str(tmp_path / "a.json")]) == 0
    paths = [str(p) for p in _write_all(tmp_path, scans, fmt)]
    assert main(common + ["--from-images", *paths, "--out", str(tmp_path / "b.json"),
                          "--param", f"gain_nm_per_V={GAIN}", "--param", "period_nm=278"]) == 0
    a, b = load_model(tmp_path / "a.json"), load_model(tmp_path / "b.json")
    ea, eb = np.array(a.everett_matrix()), np.array(b.everett_matrix())
    # the same model to 1 ppm of its output range (heights pass through m and back: ulp-level changes)
    np.testing.assert_allclose(eb, ea, rtol=0, atol=1e-6 * np.max(np.abs(ea)))
    assert b.u_max_V == pytest.approx(a.u_max_V)


def test_image_file_errors_name_the_file(tmp_path, capsys):
    (tmp_path / "bad.gwy").write_bytes(b"GWYP garbage")
    with pytest.raises(ModelError, match="bad.gwy: not a readable"):
        read_scan_image(tmp_path / "bad.gwy")
    with pytest.raises(ModelError, match="unknown image format"):
        read_scan_image(tmp_path / "x.jpg")
    (tmp_path / "bad.ibw").write_bytes(b"\x05\x00" + b"\x00" * 40)
    with pytest.raises(ModelError, match="bad.ibw: not a readable"):
        read_scan_image(tmp_path / "bad.ibw")
    rc = main(["identify", "--model", "preisach", "--from-images", str(tmp_path / "bad.gwy"),
               "--out", str(tmp_path / "m.json")])
    err = capsys.readouterr().err
    assert rc == 2 and "gain_nm_per_V" in err and len(err.strip().splitlines()) == 1
