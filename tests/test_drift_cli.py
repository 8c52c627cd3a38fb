"""``afmctl drift`` through afmctl.cli.main: prediction files and bad input."""
from __future__ import annotations

import json

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.compensators.drift import DriftParams


def _write(path, header, rows):
    with open(path, "w", encoding="utf-8") as f:
        f.write(header + "\n")
        for r in rows:
            f.write(",".join(str(v) for v in r) + "\n")
    return str(path)


def _read(path):
    data = np.genfromtxt(path, delimiter=",", names=True)
    return np.column_stack([data["t"], data["x"], data["y"], data["z"]])


def _ramp(tmp_path, t, name="T.csv"):
    T = 20.0 + 2.0 * t / 600.0
    return _write(tmp_path / name, "t,T", zip(t, T)), T


def _err(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("afmctl: error: ")
    return err[0]


def test_uniform_file_equals_the_predictor_exactly(tmp_path):
    t = np.arange(0, 600.0, 0.5)
    tf, T = _ramp(tmp_path, t)
    out = tmp_path / "d.csv"
    assert main(["drift", "predict", "--temperature", tf, "--out", str(out)]) == 0
    d = _read(out)
    assert d.shape == (t.size, 4)
    np.testing.assert_array_equal(d[:, 0], t)
    expected = DriftParams.named("physical_tube").predictor(0.5).block(np.asarray(T, float))
    np.testing.assert_array_equal(d[:, 1:], expected)
    assert 2.5 < d[-1, 1] < 4.0  # a few nm: the 3.3 nm scenario


def test_voltages_file_adds_heat_drift(tmp_path):
    t = np.arange(0, 100.0, 0.1)
    tf, _ = _ramp(tmp_path, t)
    tv = np.arange(0, 100.0, 0.05)
    vf = _write(tmp_path / "V.csv", "t,ux,uy,uz", [(a, 150.0 * (a > 20), 0.0, 0.0) for a in tv])
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    assert main(["drift", "predict", "--temperature", tf, "--out", str(a)]) == 0
    assert main(["drift", "predict", "--temperature", tf, "--voltages", vf, "--out", str(b),
                 "--plot", str(tmp_path / "d.png")]) == 0
    assert (tmp_path / "d.png").read_bytes()[:4] == b"\x89PNG"
    da, db = _read(a), _read(b)
    assert np.all(da[t <= 20.0, 1:] == db[t <= 20.0, 1:])
    assert abs(db[-1, 1] - da[-1, 1]) > 1e-4


def test_non_uniform_times_are_resampled_and_close_to_uniform(tmp_path):
    rng = np.random.default_rng(0)
    t = np.sort(np.concatenate([[0.0, 600.0], rng.uniform(0, 600, 400)]))
    tf, _ = _ramp(tmp_path, t)
    out = tmp_path / "d.csv"
    assert main(["drift", "predict", "--temperature", tf, "--out", str(out)]) == 0
    d = _read(out)
    np.testing.assert_array_equal(d[:, 0], t)
    fine = np.arange(0, 600.0 + 1e-9, 0.01)
    ref = DriftParams.named("physical_tube").predictor(0.01).block(20.0 + 2.0 * fine / 600.0)
    ref_at = np.column_stack([np.interp(t, fine, ref[:, j]) for j in range(3)])
    assert np.max(np.abs(d[:, 1:] - ref_at)[:, :2]) < 0.02      # nm, of ~3 nm
    assert np.max(np.abs(d[:, 3] - ref_at[:, 2])) < 0.5           # nm, of ~64 nm


def test_a_gap_is_bridged_without_a_jump(tmp_path):
    t = np.concatenate([np.arange(0, 200.0, 1.0), np.arange(300.0, 600.0, 1.0)])
    tf, _ = _ramp(tmp_path, t)
    out = tmp_path / "d.csv"
    assert main(["drift", "predict", "--temperature", tf, "--out", str(out)]) == 0
    d = _read(out)
    i = int(np.flatnonzero(t == 300.0)[0])
    full = DriftParams.named("physical_tube").predictor(1.0).block(20.0 + 2.0 * np.arange(0, 600.0) / 600.0)
    # a linear temperature across the gap: the same drift as with no gap at all
    assert abs(d[i, 1] - full[300, 0]) < 1e-3
    assert abs(d[-1, 1] - full[-1, 0]) < 1e-3


def test_a_temperature_step_inside_a_gap_gives_no_drift_jump(tmp_path):
    """T jumps by 1 K between two rows 100 s apart: bridged as a 100 s ramp, the x drift
    (a 2 nm/K lag) moves at most 2 nm/K × 1 K / 100 s per second across the gap."""
    t = np.concatenate([np.arange(0, 200.0, 1.0), np.arange(300.0, 400.0, 1.0)])
    T = np.where(t < 250.0, 20.0, 21.0)
    tf = _write(tmp_path / "T.csv", "t,T", zip(t, T))
    out = tmp_path / "d.csv"
    assert main(["drift", "predict", "--temperature", tf, "--out", str(out)]) == 0
    d = _read(out)
    i = int(np.flatnonzero(t == 300.0)[0])
    k_x = DriftParams.named("physical_tube").paths.xT.K
    assert 0.0 < (d[i, 1] - d[i - 1, 1]) / 100.0 <= k_x * 1.0 / 100.0


@pytest.mark.parametrize("rows, needle", [
    ([(0, 20), (1, "nan"), (2, 20)], "not finite"),
    ([(0, 20), (2, 20), (1, 20)], "strictly increasing"),
    ([(0, 20), (1, 20), (1, 20.5)], "strictly increasing"),
    ([(0, 20), (1, "warm")], "not a number"),
])
def test_bad_temperature_files(tmp_path, capsys, rows, needle):
    tf = _write(tmp_path / "T.csv", "t,T", rows)
    assert main(["drift", "predict", "--temperature", tf, "--out", str(tmp_path / "d.csv")]) == 2
    assert needle in _err(capsys)
    assert not (tmp_path / "d.csv").exists()


def test_bad_step_option(tmp_path, capsys):
    tf = _write(tmp_path / "T.csv", "t,T", [(0, 20), (1, 21)])
    assert main(["drift", "predict", "--temperature", tf, "--out", str(tmp_path / "d.csv"), "--dt", "-1"]) == 2
    assert "--dt" in _err(capsys)
    assert main(["drift", "predict", "--temperature", tf, "--out", str(tmp_path / "d.csv"), "--dt", "1e-9"]) == 2
    assert "at most" in _err(capsys)


def test_gap_longer_than_max_gap_is_rejected(tmp_path, capsys):
    tf = _write(tmp_path / "T.csv", "t,T", [(0, 20), (1, 20), (1000, 21)])
    assert main(["drift", "predict", "--temperature", tf, "--out", str(tmp_path / "d.csv"),
                 "--max-gap", "60"]) == 2
    msg = _err(capsys)
    assert "gap" in msg and "60" in msg


def test_missing_column_and_bad_params(tmp_path, capsys):
    tf = _write(tmp_path / "T.csv", "t,temp", [(0, 20)])
    assert main(["drift", "predict", "--temperature", tf, "--out", str(tmp_path / "d.csv")]) == 2
    assert "missing column" in _err(capsys)
    good = _write(tmp_path / "G.csv", "t,T", [(0, 20), (1, 21)])
    assert main(["drift", "predict", "--temperature", good, "--params", "nope", "--out",
                 str(tmp_path / "d.csv")]) == 2
    assert "physical_tube" in _err(capsys)
    bad = tmp_path / "p.json"
    bad.write_text(json.dumps({"kind": "drift", "paths": {"xT": {"form": "tf", "poles_s": [-5]}}}))
    assert main(["drift", "predict", "--temperature", good, "--params", str(bad), "--out",
                 str(tmp_path / "d.csv")]) == 2
    assert "poles_s" in _err(capsys)
    vf = _write(tmp_path / "V.csv", "t,volts", [(0, 1)])
    assert main(["drift", "predict", "--temperature", good, "--voltages", vf, "--out",
                 str(tmp_path / "d.csv")]) == 2
    assert "ux" in _err(capsys)


def test_params_export_and_reuse(tmp_path, capsys):
    pf = tmp_path / "a1.json"
    assert main(["drift", "params", "--params", "table_a1", "--out", str(pf)]) == 0
    data = json.loads(pf.read_text())
    assert data["kind"] == "drift" and data["doubts"]
    data["paths"]["xT"]["K"] = 1e-9
    pf.write_text(json.dumps(data))
    tf = _write(tmp_path / "T.csv", "t,T", [(k, 20 + 0.01 * k) for k in range(50)])
    out = tmp_path / "d.csv"
    assert main(["drift", "predict", "--temperature", tf, "--params", str(pf), "--out", str(out)]) == 0
    assert _read(out).shape == (50, 4)
    assert main(["drift", "params"]) == 0
    assert '"physical_tube"' in capsys.readouterr().out


def test_help_teaches(capsys):
    with pytest.raises(SystemExit) as e:
        main(["drift", "predict", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "t,T" in out and "t,x,y,z" in out and "Example" in out


def test_fit_recovers_the_gains_of_a_measured_drift(tmp_path, capsys):
    """Drift 'measured' with a scanner whose gains differ from the starting set; the fit
    keeps the structures and finds the gains (noise 0.05 nm)."""
    true = DriftParams.named("physical_tube").scaled(1.4)
    t = np.arange(0, 1800.0, 1.0)
    T = 21.0 + 1.0 * np.sin(2 * np.pi * t / 1500.0) + t / 1800.0
    U = np.column_stack([75 + 70 * np.sin(2 * np.pi * t / 7.3), 75 + 70 * np.sin(2 * np.pi * t / 9.1),
                         75 + 40 * np.sin(2 * np.pi * t / 200.0)])
    d = true.predictor(1.0).block(T, U) + np.random.default_rng(0).normal(0, 0.05, (t.size, 3))
    tf = _write(tmp_path / "T.csv", "t,T", zip(t, T))
    vf = _write(tmp_path / "V.csv", "t,ux,uy,uz", zip(t, *U.T))
    mf = _write(tmp_path / "M.csv", "t,x,y,z", zip(t, *d.T))
    out = tmp_path / "fit.json"
    assert main(["drift", "fit", "--temperature", tf, "--voltages", vf, "--drift", mf, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "G_xT" in printed and "residual z" in printed
    fitted = DriftParams.load(out)
    for name in ("xT", "yT", "zT"):
        assert getattr(fitted.paths, name).K == pytest.approx(getattr(true.paths, name).K, rel=0.02)
    # and without a measured z column the z gains are kept
    mf2 = _write(tmp_path / "M2.csv", "t,x", zip(t, d[:, 0]))
    assert main(["drift", "fit", "--temperature", tf, "--drift", mf2, "--out", str(out)]) == 0
    kept = DriftParams.load(out)
    assert kept.paths.zT.K == DriftParams.named("physical_tube").paths.zT.K
    assert kept.paths.xT.K != DriftParams.named("physical_tube").paths.xT.K


def test_fit_bad_inputs(tmp_path, capsys):
    tf = _write(tmp_path / "T.csv", "t,T", [(k, 20 + 0.01 * k) for k in range(10)])
    mf = _write(tmp_path / "M.csv", "t,q", [(0, 1), (1, 2)])
    assert main(["drift", "fit", "--temperature", tf, "--drift", mf, "--out", str(tmp_path / "f.json")]) == 2
    assert "x,y,z" in _err(capsys)
    mf = _write(tmp_path / "M.csv", "t,x", [(100, 1), (101, 2)])
    assert main(["drift", "fit", "--temperature", tf, "--drift", mf, "--out", str(tmp_path / "f.json")]) == 2
    assert "fewer than 2 rows" in _err(capsys)
