"""Sensorless identification of the linear dynamics from grating images at several line
rates (issue #11 item 3; :mod:`afmctl.compensators.image_dynamics`), on the default
simulated scanner, compared with the same chain identified with a position sensor
(benchmarks/image_dynamics.py)."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.compensators.base import ModelError
from afmctl.compensators.image_dynamics import edge_crossings, line_rates, split_scans
from afmctl.sim_backend.image_scans import scan_grating_lines
from afmctl.sim_backend.rate_scans import scan_grating_rates
from afmctl.sim_backend.scanner import Scanner, default_scanner_config

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("image_dynamics_bench", ROOT / "benchmarks" / "image_dynamics.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["image_dynamics_bench"] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def chains(bench):
    cfg = default_scanner_config()
    return cfg, bench.image_chain(cfg), bench.sensor_chain(cfg, creep=True), bench.image_chain(cfg, creep=True)


def test_mode_found_from_images_is_the_scanners(bench, chains):
    """Measured: 1000.2 Hz, ζ 0.0280 (true 1000 Hz, ζ 0.025); the sensor fits 1002.6 Hz,
    ζ 0.0248 (preisach+dynamics) and 1002.7 Hz, ζ 0.0201 (preisach+creep+dynamics)."""
    _, img, _, _ = chains
    f, zeta = bench.mode_of(img)
    assert abs(f - 1000.0) < 10.0
    assert 0.02 < zeta < 0.032
    assert img.dynamics.fit_info["source"] == "grating images"


@pytest.mark.parametrize("rate", [16.0, 50.0])
def test_image_chain_compensates_raster_lines_close_to_the_sensor_chain(bench, chains, rate):
    """Measured x max / RMS (% of the 4 µm line): preisach+dynamics from images 1.01 / 0.48
    at 16 lines/s and 1.21 / 0.49 at 50; the sensor-identified preisach+creep+dynamics
    0.27 and 0.49 max (0.70 and 1.19 before the Preisach fit's smoothing left the diagonal
    cells alone: the images' chain, read from reversal curves, did not change, the gap to
    the sensor grew from 0.3 to 0.7 points; benchmarks/image_dynamics.py)."""
    cfg, img, sensor, _ = chains
    e_img = bench.x_errors_pct(cfg, img, rate)
    e_sensor = bench.x_errors_pct(cfg, sensor, rate)
    limit = {16.0: (1.15, 0.55), 50.0: (1.35, 0.6)}[rate]
    assert e_img["max_error_pct"] < limit[0] and e_img["rms_error_pct"] < limit[1]
    assert e_img["max_error_pct"] < e_sensor["max_error_pct"] + 0.85


@pytest.mark.parametrize("rate, limit", [(1.0, 0.35), (4.0, 0.5), (16.0, 1.05), (50.0, 2.0)])
def test_image_creep_chain_compensates_raster_lines(bench, chains, rate, limit):
    """preisach+creep+dynamics from images only, measured x max / RMS %: 0.27 / 0.11 at
    1 line/s, 0.42 / 0.15 at 4, 0.95 / 0.32 at 16, 1.82 / 0.72 at 50 (the sensor's
    preisach+creep+dynamics: 0.68, 0.62, 0.70, 1.19 % max; without creep from images
    1.83, 1.40, 1.01, 1.21)."""
    cfg, _, _, img_creep = chains
    assert img_creep.structure == "preisach+creep+dynamics"
    assert bench.x_errors_pct(cfg, img_creep, rate)["max_error_pct"] < limit


def test_virtual_sensor_record_follows_the_true_position():
    """The slow scans turned into (t, u, y) (:mod:`image_creep`): 2.0 nm RMS from the true
    tip position and a 5.1 nm offset (measured), over a 12 µm range."""
    from afmctl.compensators.image_creep import virtual_record
    from afmctl.compensators.image_identify import identify_from_images

    sc = Scanner(default_scanner_config())
    slow = scan_grating_lines(sc, lines_per_range=4, keep_truth=True)
    pre = identify_from_images(slow.arrays(), kind="preisach", n_operators=15)
    t, u, y = virtual_record(slow.arrays(), pre)
    err = y - slow.truth["y_nm"]
    assert t.size == slow.truth["y_nm"].size and np.allclose(u, slow.truth["u_V"])
    offset = float(np.median(err))     # measured 5.1 nm: the lattice's one open constant
    assert float(np.sqrt(np.mean((err - offset) ** 2))) < 3.0 and abs(offset) < 8.0


def test_a_wrong_or_missing_mode_would_fail_the_figure(bench, chains):
    """The accuracy test can fail: at 50 lines/s the chain with its mode moved 10 % gives
    1.41 % max, the Preisach stage alone 2.32 % (measured)."""
    cfg, img, _, _ = chains
    dyn = img.dynamics.model_copy(update={"poles_rad_per_s": [(re * 1.1, im * 1.1) for re, im in
                                                             img.dynamics.poles_rad_per_s]})
    assert bench.x_errors_pct(cfg, img.model_copy(update={"dynamics": dyn}), 50.0)["max_error_pct"] > 1.35
    assert bench.x_errors_pct(cfg, img.model_copy(update={"dynamics": None}), 50.0)["max_error_pct"] > 2.0


def test_edges_of_a_synthetic_line():
    h = np.array([0, 0, 10, 20, 20, 10, 0, 0], dtype=float)
    idx, sign = edge_crossings(h)
    assert np.allclose(idx, [2.0, 5.0]) and sign.tolist() == [1.0, -1.0]


def test_line_rate_field_is_checked():
    sc = Scanner(default_scanner_config())
    arrays = scan_grating_rates(sc, rates_Hz=(10.0, 50.0), pixels=256, lines=3, keep_truth=False).arrays()
    slow, fast = split_scans(arrays)
    assert slow is None and [f.line_rate_Hz for f in fast] == [10.0, 50.0]
    with pytest.raises(ModelError, match=r"line_rate_Hz: .*each must be > 0 and ≤ 10000"):
        line_rates({"line_rate_Hz": np.array([10.0, -1.0])}, 2)
    with pytest.raises(ModelError, match="line_rate_Hz: expected one number or 2"):
        line_rates({"line_rate_Hz": np.array([1.0, 2.0, 3.0])}, 2)


def test_cli_identifies_from_images_and_bad_input_is_one_line(tmp_path, capsys):
    sc = Scanner(default_scanner_config())
    slow = scan_grating_lines(sc, lines_per_range=4, keep_truth=False).save_npz(tmp_path / "slow.npz")
    sc.reset()
    fast_scans = scan_grating_rates(sc, keep_truth=False)
    fast = fast_scans.save_npz(tmp_path / "fast.npz")
    out = tmp_path / "pd.json"
    assert main(["identify", "--model", "preisach+dynamics", "--from-images", str(slow), str(fast),
                 "--operators", "15", "--out", str(out)]) == 0
    assert "fit source: grating images" in capsys.readouterr().out and out.is_file()
    bad = fast_scans.arrays()
    bad["line_rate_Hz"] = np.array(bad["line_rate_Hz"])
    bad["line_rate_Hz"][2] = 0.0
    np.savez(tmp_path / "bad.npz", **bad)
    for args, needle in (
            (["--model", "preisach+dynamics", "--from-images", str(slow), str(tmp_path / "bad.npz")],
             "bad.npz: line_rate_Hz: [10.0, 12.0, 0.0, 20.0,"),
            (["--model", "preisach+dynamics", "--from-images", str(slow), str(tmp_path / "bad.npz")],
             "each must be > 0 and ≤ 10000 lines/s"),
            (["--model", "preisach+dynamics", "--from-images", str(fast)], "no scan range at ≤ 2 lines/s"),
            (["--model", "dynamics", "--from-images", str(fast)], "gain_nm_per_V: needed"),
            (["--model", "pi+creep+dynamics", "--from-images", str(slow), str(fast)],
             "from grating images the chains are dynamics, preisach+dynamics, preisach+creep"),
            (["--model", "dynamics", "--from-images", str(fast), "--param", "n_lags=9"], "n_lags"),
            (["--model", "preisach+dynamics", "--from-images", str(slow), str(tmp_path / "r1.gwy")],
             "r1.gwy: the dynamics are identified from .npz scan files")):
        rc = main(["identify", *args, "--out", str(tmp_path / "x.json")])
        err = capsys.readouterr().err
        assert rc == 2 and needle in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err


def test_a_miscounted_grating_line_is_unwrapped():
    """image_creep: residuals that jump by a period from one edge to the next are edges
    placed on the neighbouring grating line (measured on the `stiff` plant of
    benchmarks/unseen_plants.py: without this the virtual record was 275.6 nm, one
    278 nm period, off)."""
    from afmctl.compensators.image_creep import unwrap_periods

    r = np.array([1.0, 2.0, 3.0 - 278.0, 4.0 - 278.0, 5.0, 6.0 + 278.0])
    assert np.allclose(unwrap_periods(r, 278.0), [1.0, 2.0, 3.0, 4.0, 5.0, 6.0])


def test_a_rate_whose_edges_were_not_placed_is_left_out():
    from afmctl.compensators.image_dynamics import RateResponse, placed_well

    def resp(rms):
        return RateResponse(10.0, np.array([10.0]), np.array([1.0 + 0j]), np.array([0.01]), 100, rms)
    kept = [resp(2.0), resp(3.0), resp(2.5)]
    assert placed_well(resp(9.0), kept) and placed_well(resp(40.0), kept[:1])
    assert not placed_well(resp(42.7), kept)
