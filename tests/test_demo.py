"""A reduced ``afmctl demo`` (64×64 px, short excitation, two compensators and one unknown
kind) through the real command line: files, metrics and the improvement it measures."""
from __future__ import annotations

import json
import logging

import pytest

from afmctl.cli import main
from afmctl.testing import assert_few_underruns


#: what the models and fits logged at WARNING or above during the module's demo run
FIT_WARNINGS: list[str] = []


class _Collect(logging.Handler):
    def emit(self, record: logging.LogRecord) -> None:
        FIT_WARNINGS.append(f"{record.name}: {record.getMessage()}")


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    fits = logging.getLogger("afmctl.compensators")
    handler = _Collect(logging.WARNING)
    fits.addHandler(handler)
    try:
        rc = main(["demo", "--out", str(out), "--size", "64", "--quick", "--no-progress",
                   "--only", "pi", "--only", "preisach+creep", "--only", "preisach+creep+dynamics",
                   "--only", "no-such-kind"])
    finally:
        fits.removeHandler(handler)
    return rc, out


def test_demo_fits_and_models_warn_of_nothing(demo_run):
    """Issue 40: no warning from a fit inside the demo (a fit's numerical trouble goes to its
    report, ``fit_info``; a trial the fit does not keep is no warning), and the speed
    ladder's runs do not warn of clamps for samples they never send (the loop's warm-up and
    the preview inverse's priming)."""
    assert FIT_WARNINGS == []
    from afmctl.compensators.models import load_model
    _, out = demo_run
    for axis in ("x", "y"):     # the model the demo uses carries no "did not converge"
        info = load_model(out / "models" / "scanner_preisach+creep+dynamics.json").axis(axis).dynamics.fit_info
        assert "problem" not in info and "mode_trials" in info, info


def test_demo_writes_images_plots_and_metrics(demo_run, capsys):
    rc, out = demo_run
    assert rc == 0
    for name in ("demo_images.png", "demo_hysteresis.png", "demo_errors.png", "demo_lines.png", "demo_drift.png"):
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, name
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["max_error_pct"]) == {"none", "pi", "preisach+creep", "preisach+creep+dynamics"}
    assert set(m["rms_error_pct"]) == set(m["max_error_pct"])
    assert "no-such-kind" in m["skipped"]
    for name, v in m["max_error_pct"].items():
        assert 0 < m["rms_error_pct"][name] <= v


def test_demo_compensation_beats_uncompensated(demo_run):
    _, out = demo_run
    m = json.loads((out / "metrics.json").read_text())
    mx = m["max_error_pct"]
    assert mx["none"] > 5.0                       # the simulated scanner really is nonlinear
    best = m["best"]
    assert best == min((k for k in mx if k != "none"), key=mx.get)
    assert mx[best] * 5 <= mx["none"]
    assert mx[best] <= 2.0                        # reduced run; the full size: test_full_size_demo_…
    # issue #11: the dynamics stage must not cost accuracy (it was 78 % vs 0.86 % when
    # the chain's offline inverse ignored the amplifier's slew and range and its rest)
    assert mx["preisach+creep+dynamics"] <= 1.25 * mx["preisach+creep"], mx
    assert m["drift"]["max_true_drift_nm"] > 1.0  # the drift scenario is on
    d = m["drift_effect"]
    assert d["compensator"] == best and d["max_error_pct_with_drift_correction"] == mx[best]
    assert d["max_error_pct_without_drift_correction"] > 0


def test_demo_rejects_bad_size(capsys, tmp_path):
    assert main(["demo", "--out", str(tmp_path), "--size", "3"]) == 2
    assert "--size" in capsys.readouterr().err


def test_demo_unwritable_out_is_one_line(capsys, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["demo", "--out", str(blocker / "out"), "--size", "16", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("afmctl: error: --out") and err.count("\n") == 1


def test_demo_error_is_actual_minus_commanded_over_every_sample(tmp_path):
    """The uncompensated metric recomputed from the raw simulation signals (true tip
    position and commanded target per sample, settle line dropped, averaged per pixel):
    every pixel of trace and retrace, x and y — nothing left out."""
    import numpy as np
    from afmctl.reports.demo import DemoOptions, run_demo
    ctx = run_demo(DemoOptions(out=tmp_path, size=16, quick=True, compensators=()), progress=False)
    o = ctx.options
    sig = ctx.scans["none"].image.signals
    rec = sig["t_s"] >= 0
    err = (sig["position_nm"][rec] - sig["target_nm"][rec])[:, :2]
    per_pixel = err.reshape(o.size, 2, o.size, o.samples_per_pixel, 2).mean(axis=3)
    assert per_pixel.size == o.size * o.size * 2 * 2
    expected_max = np.max(np.abs(per_pixel)) / o.scan_nm * 100
    expected_rms = np.sqrt(np.mean(per_pixel ** 2)) / o.scan_nm * 100
    assert ctx.metrics["max_error_pct"]["none"] == pytest.approx(expected_max, abs=1e-4)
    assert ctx.metrics["rms_error_pct"]["none"] == pytest.approx(expected_rms, abs=1e-4)
    assert ctx.metrics["best"] is None and set(ctx.metrics["max_error_pct"]) == {"none"}


def test_full_size_demo_meets_the_acceptance_figures(tmp_path):
    """The README's demo at its full size (256×256 px, full excitation), for its best
    compensator: ≥ 5× lower max error than uncompensated and ≤ 1.5 % of the range."""
    assert main(["demo", "--out", str(tmp_path), "--only", "preisach+creep", "--no-progress"]) == 0
    m = json.loads((tmp_path / "metrics.json").read_text())
    mx = m["max_error_pct"]
    assert m["best"] == "preisach+creep"
    assert mx["preisach+creep"] <= 1.5
    assert mx["preisach+creep"] * 5 <= mx["none"]


def test_demo_speed_ladder_through_the_controller(demo_run):
    """metrics.json speed_ladder = {line_rate_Hz: {compensator: {max_error_pct, rms_error_pct}}}:
    1, 4, 16 lines/s from the real Controller (simulated CAN amplifier; the dynamics chain
    at 10 kHz with its preview horizon), 50 from the Controller with ``output = "wave"``
    (computed whole, played from the amplifier's FIFO at 20 kHz); the model files the demo
    wrote are what the controller loaded."""
    _, out = demo_run
    m = json.loads((out / "metrics.json").read_text())
    ladder = m["speed_ladder"]
    assert list(ladder) == ["1", "4", "16", "50"]
    for rate, row in ladder.items():
        assert set(row) == {"none", "static", "chain", "chain+dynamics"}, row
        for label, cell in row.items():
            assert 0 < cell["rms_error_pct"] <= cell["max_error_pct"], (rate, label, cell)
            assert cell["path"] == "controller"
            if label == "chain+dynamics" and rate != "50":   # the loop reads the trajectory ahead
                assert cell["loop_rate_Hz"] == 10000.0 and cell["latency_s"] > 0, cell
            if rate == "50":    # device-timed (a bounded number of underruns on a loaded machine: the output holds)
                assert cell["output"] == "wave" and cell["loop_rate_Hz"] == 20000.0, cell
                assert_few_underruns(cell["underruns"], cell["samples"])
        assert row["chain"]["model"] == "preisach+creep" and row["static"]["model"] == "pi"
        # any model beats the linear calibration at every speed
        assert row["chain"]["max_error_pct"] < row["none"]["max_error_pct"]
    # 50 lines/s: the dynamics stage is no worse (13.5 % vs 3.6 % before #11's fix)
    fifty = ladder["50"]
    assert fifty["chain+dynamics"]["max_error_pct"] <= 1.1 * fifty["chain"]["max_error_pct"], fifty
    # issue #11's targets, met even by the reduced demo's models (quick excitation):
    # measured 0.06 / 0.05 / 0.10 % max, 0.02 / 0.01 / 0.04 % RMS, 0.30 % at 50 lines/s (0.71 / 0.69 / 0.77
    # and 1.36 % before the Preisach fit's smoothness penalty left the diagonal cells alone)
    dyn = {rate: row["chain+dynamics"] for rate, row in ladder.items()}
    for rate in ("1", "4", "16"):
        assert dyn[rate]["max_error_pct"] <= 1.0 and dyn[rate]["rms_error_pct"] <= 0.5, (rate, dyn[rate])
    assert dyn["50"]["max_error_pct"] <= 2.0, dyn["50"]
    assert (out / "models" / "scanner_preisach+creep.json").exists()
    assert (out / "ladder" / "ladder-1-scanner_preisach+creep.afmlog").exists()
    png = (out / "demo_speed_ladder.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


@pytest.mark.parametrize("path", ["gcs-wave", "can-stream"])
def test_afmctl_run_scans_50_lines_per_s_within_2_percent(demo_run, tmp_path, path):
    """Issue #12: a raster at 50 lines/s (≥ 10 kHz output) through ``afmctl run`` (its own
    process) with the demo's chain + dynamics model, via a PI GCS wave table (simulated
    E-727 on a pty, 20 kHz, played on its servo clock) and via the live buffered CAN FD
    stream (10 kHz, the loop reading ahead by the preview horizon): ≤ 2 % max error over
    the central 80 % of each line, and the stream never ran dry while the host loop kept
    within the FIFO's low-water depth."""
    import os
    import subprocess
    import sys

    from afmctl.reports import speed_ladder as sl
    from afmctl.config import load_config
    from afmctl.sim_backend.scanner import DriftConfig, Scanner, default_scanner_config
    _, out = demo_run
    scfg = default_scanner_config().model_copy(update={"drift": DriftConfig(kind="none")})
    scanner_json = sl.write_scanner_json(scfg, tmp_path / "scanner.json")
    gain = Scanner(scfg).nominal_gain_nm_per_V().tolist()
    model = out / "models" / "scanner_preisach+creep+dynamics.json"
    loop_Hz, amp = (20000.0, 'output = "wave"\n') if path == "gcs-wave" else (10000.0, sl.STREAM_FD_TOML)
    text = sl._config_text(tmp_path, scanner_json, model, 50.0, loop_Hz, 10, f"t50-{os.getpid()}", gain, amp)
    if path == "gcs-wave":
        text = text.replace('driver = "can"', 'driver = "gcs"').replace(f'port = "virtual:t50-{os.getpid()}"', "")
        text = text.replace("[simulation]\nenabled = true", "[simulation]\nenabled = true\nbaud = 921600")
    cfg = tmp_path / "run.toml"
    cfg.write_text(text)
    log = tmp_path / "run.afmlog"
    res = subprocess.run([sys.executable, "-m", "afmctl", "run", "--config", str(cfg), "--log", str(log),
                          "--json", "--quiet"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    err = sl.error_pct(sl.runlog_errors_nm(load_config(cfg), log, 50.0))
    print(path, err, summary["stream"], summary["wave"] and summary["wave"]["inverse"],
          {k: summary[k] for k in ("lateness_p99_s", "lateness_max_s", "missed_deadlines")})
    assert summary["state"] == "stopped" and summary["clamped"] == 0
    if path == "gcs-wave":
        assert summary["output"] == "wave" and summary["wave"]["played"] == summary["wave"]["samples"]
        assert summary["wave"]["table_slew_limited"] == 0 and summary["wave"]["table_clamped"] == 0
    else:
        assert summary["output"] == "stream"
        # the FIFO holds at least low_water_s of samples: a host loop never later than that
        # cannot let it run dry; a longer host stall (a loaded CI machine: 1622 underruns in
        # 2923 samples once) is the host's, not the stream's, and the accuracy above still holds
        if summary["lateness_max_s"] < 0.1:
            assert_few_underruns(summary["stream"]["underruns"], summary["stream"]["queued"])
    assert err["max_error_pct"] <= 2.0, err
