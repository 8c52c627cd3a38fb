"""``afmctl identify --model preisach|bouc-wen`` and ``afmctl compensate`` with those models."""
from __future__ import annotations

import json

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.data.datafiles import read_csv, write_csv
from afmctl.compensators.bouc_wen import BoucWenModel
from afmctl.compensators.models import load_model
from afmctl.compensators.preisach import PreisachModel


def _plant() -> PreisachModel:
    return PreisachModel.from_density(lambda a, b: 1.0 + 0.02 * (a - b) + 0.01 * a, 0.0, 150.0, 60, offset_nm=10.0)


def _loops() -> np.ndarray:
    ext = [150.0, 0.0, 130.0, 20.0, 110.0, 40.0, 90.0, 60.0, 140.0, 30.0, 100.0, 0.0]
    pts = np.r_[0.0, ext]
    return np.concatenate([np.linspace(a, b, 150)[1:] for a, b in zip(pts[:-1], pts[1:])])


def test_identify_and_compensate_preisach(tmp_path, capsys):
    plant = _plant()
    u = _loops()
    data = tmp_path / "data.csv"
    write_csv(data, {"t": np.arange(u.size) * 1e-3, "u": u, "y": plant.forward().block(u)})
    out = tmp_path / "pre.json"
    rc = main(["identify", "--model", "preisach", "--data", str(data), "--out", str(out), "--operators", "24",
               "--param", "u_min_V=0", "--param", "u_max_V=150", "--param", "method=nnls"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "Preisach" in text and "residual" in text
    model = load_model(out)
    assert isinstance(model, PreisachModel) and model.levels == 24
    assert json.loads(out.read_text())["kind"] == "preisach"
    # offline feedforward through the identified inverse, checked on the plant
    lo, hi = plant.output_range_nm()
    t = np.arange(2000) * 1e-3
    target = lo + (hi - lo) * (0.1 + 0.8 * (1 - np.abs((t % 1.0) * 2 - 1)))
    tgt = tmp_path / "target.csv"
    write_csv(tgt, {"t": t, "y": target})
    volts = tmp_path / "volts.csv"
    assert main(["compensate", "--model", str(out), "--target", str(tgt), "--out", str(volts),
                 "--limits", "0", "150"]) == 0
    u_ff = read_csv(volts, ("t", "u"))["u"]
    err = plant.forward().block(u_ff) - target
    assert np.max(np.abs(err)) < 0.005 * (hi - lo)


def test_identify_bouc_wen(tmp_path, capsys):
    true = BoucWenModel(d_nm_per_V=80.0, A_nm_per_V=20.0, beta=0.005, gamma=0.002, n=1.0)
    u = _loops()
    data = tmp_path / "data.csv"
    write_csv(data, {"t": np.arange(u.size) * 1e-3, "u": u, "y": true.forward().block(u)})
    out = tmp_path / "bw.json"
    assert main(["identify", "--model", "bouc-wen", "--data", str(data), "--out", str(out)]) == 0
    fit = load_model(out)
    assert isinstance(fit, BoucWenModel)
    assert fit.d_nm_per_V == pytest.approx(80.0, rel=0.02)
    assert "Bouc" in capsys.readouterr().out


@pytest.mark.parametrize("args, needle", [
    (["--operators", "0"], "--operators"),
    (["--param", "method=magic"], "method"),
    (["--param", "u_min_V=100", "--param", "u_max_V=50"], "u_max_V"),
    (["--param", "nonsense=1"], "--param"),
])
def test_bad_options_are_one_line_errors(tmp_path, capsys, args, needle):
    u = _loops()
    data = tmp_path / "data.csv"
    write_csv(data, {"t": np.arange(u.size) * 1e-3, "u": u, "y": 100.0 * u})
    rc = main(["identify", "--model", "preisach", "--data", str(data), "--out", str(tmp_path / "m.json"), *args])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("afmctl: error:") and needle in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_bad_preisach_model_file_is_one_line_error(tmp_path, capsys):
    bad = _plant().model_dump(mode="json")
    bad["everett_nm"][3] = [0.0]
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(bad))
    tgt = tmp_path / "target.csv"
    write_csv(tgt, {"t": np.arange(3.0), "y": np.arange(3.0)})
    rc = main(["compensate", "--model", str(path), "--target", str(tgt), "--out", str(tmp_path / "v.csv")])
    err = capsys.readouterr().err
    assert rc == 2 and "everett_nm" in err and len(err.strip().splitlines()) == 1
