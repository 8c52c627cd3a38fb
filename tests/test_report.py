"""``afmctl report RUN``: a run log written by afmctl.control.runlog → plots and a summary."""
from __future__ import annotations

import json

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.control.runlog import DRIFT_DTYPE, SETPOINT_DTYPE, RunLogWriter


def _write_log(path, n=3000, dt=1e-3):
    sp = np.zeros(n, SETPOINT_DTYPE)
    sp["seq"] = np.arange(n)
    sp["t_s"] = np.arange(n) * dt
    sp["target_nm"][:, 0] = 5000 + 4000 * np.sin(2 * np.pi * 2 * sp["t_s"])
    sp["target_nm"][:, 1] = 3000
    drift = np.zeros((n, 3))
    drift[:, 0] = 20 * sp["t_s"]
    sp["corrected_nm"] = sp["target_nm"] - drift
    sp["u_V"] = np.clip(sp["corrected_nm"] / 80.0, 0, 150)
    sp["u_V"][:, 2] = 0
    dr = np.zeros(n, DRIFT_DTYPE)
    dr["seq"], dr["t_s"], dr["T_C"], dr["drift_nm"] = sp["seq"], sp["t_s"], 22 + sp["t_s"], drift
    with RunLogWriter(path, {"scanner": "s1"}, fsync=False) as w:
        w.write_event({"seq": 0, "t_s": 0.0, "state": "running", "event": "start"})
        w.write_event({"seq": 100, "t_s": 0.1, "state": "running", "event": "ramp-done"})
        w.write_event({"seq": n - 100, "t_s": (n - 100) * dt, "state": "running", "event": "end"})
        for k in range(0, n, 500):
            w.write_setpoints(sp[k:k + 500])
            w.write_drift(dr[k:k + 500])
        w.write_event({"seq": n, "t_s": n * dt, "state": "stopped", "event": "stopped"})
    return sp


def test_report_writes_plots_and_summary(tmp_path, capsys):
    run = tmp_path / "scan.afmlog"
    _write_log(run)
    out = tmp_path / "rep"
    assert main(["report", str(run), "--out", str(out), "--simulate"]) == 0
    for name in ("report_loops.png", "report_tracking.png", "report_errors.png", "report_drift.png"):
        assert (out / name).read_bytes()[:4] == b"\x89PNG", name
    summary = json.loads((out / "report_summary.json").read_text())
    assert summary["samples"] == 3000 and summary["seq_gaps"] == 0
    assert summary["states"] == ["running", "stopped"]
    assert summary["error_samples"] == 2800          # start ramp and final ramp left out
    corr = summary["errors_pct_of_range"]["drift correction"]
    # the largest correction is the drift at the last tracked sample: 20 nm/s · 2.899 s of an 8 µm range
    assert corr["max"] == pytest.approx(20 * 2.899 / 8000.0 * 100, rel=1e-3)
    sim = summary["errors_pct_of_range"]["tracking error"]
    assert sim["max"] > 1.0      # a linear map on the hysteretic default scanner: visibly wrong
    assert "setpoints" in capsys.readouterr().out


def test_report_default_out_dir(tmp_path):
    run = tmp_path / "a.afmlog"
    _write_log(run, n=200)
    assert main(["report", str(run)]) == 0
    assert (tmp_path / "a-report" / "report_loops.png").exists()


def test_report_bad_inputs_one_line(tmp_path, capsys):
    assert main(["report", str(tmp_path / "missing.afmlog")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("afmctl: error:") and err.count("\n") == 1
    empty = tmp_path / "empty.afmlog"
    RunLogWriter(empty, {}, fsync=False).close()
    assert main(["report", str(empty)]) == 2
    assert "no setpoints" in capsys.readouterr().err
    good = tmp_path / "good.afmlog"
    _write_log(good, n=50)
    assert main(["report", str(good), "--out", str(good / "sub")]) == 2   # a file is in the way
    assert "--out" in capsys.readouterr().err


def test_error_histograms_tell_the_series_apart():
    """Every series of a histogram plot gets its own colour (the report's 'correction' and
    'simulated error' were both grey)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from afmctl.reports.report import plot_error_histograms
    fig, ax = plt.subplots()
    rng = np.random.default_rng(0)
    names = ["correction", "simulated error", "mystery", "another"]
    plot_error_histograms(ax, {n: rng.normal(size=100) for n in names}, "t")
    colours = [tuple(p.get_edgecolor()) for p in ax.patches]
    plt.close(fig)
    assert len(colours) == len(names) and len(set(colours)) == len(names)
