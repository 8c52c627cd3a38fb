"""Offline CLI: identify / compensate / model invert / model show, and bad input (one
clear error line, exit 2, no traceback) through afmctl.cli.main and a real subprocess."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from plants import RelayPreisachPlant, decaying_triangle, staircase, triangle

from afmctl.cli import main
from afmctl.data.datafiles import read_csv, write_csv
from afmctl.compensators.models import load_model


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    plant = RelayPreisachPlant(grid=30)
    t, u = decaying_triangle(1e-3, 6, 0.0, 150.0, 400)
    write_csv(d / "data.csv", {"t": t, "u": u, "y": plant.run(u), "extra": np.zeros_like(t)})
    tt = np.arange(1500) * 1e-3
    write_csv(d / "target.csv", {"t": tt, "y": triangle(tt, 1.0, 2000.0, 12000.0)})
    # staircase data with dwells for epi / creep
    ts, us = staircase(2e-3, [0, 30, 60, 90, 60, 30, 0, 45, 90, 45, 0], 0.6)
    ys = 100.0 * us + 3.0 * np.concatenate([[0.0], np.cumsum(np.sign(np.diff(us)))])  # a little memory
    from afmctl.compensators.creep import LinearCreep
    ys = LinearCreep([0.2], [0.05], 2e-3).block(ys)
    write_csv(d / "stairs.csv", {"t": ts, "u": us, "y": ys})
    return d


def run_cli(args, capsys):
    rc = main([str(a) for a in args])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_identify_compensate_invert_show_pi(files, capsys, tmp_path):
    rc, out, err = run_cli(["identify", "--model", "pi", "--data", files / "data.csv", "--out", tmp_path / "pi.json",
                            "--operators", "9", "--plot", tmp_path / "fit.png"], capsys)
    assert rc == 0, err
    assert "fit residual" in out and (tmp_path / "fit.png").stat().st_size > 1000
    data = json.loads((tmp_path / "pi.json").read_text())
    assert data["kind"] == "pi" and len(data["thresholds"]) == len(data["weights"]) == 9

    rc, out, err = run_cli(["compensate", "--model", tmp_path / "pi.json", "--target", files / "target.csv",
                            "--out", tmp_path / "volts.csv", "--limits", "0", "150", "--clip"], capsys)
    assert rc == 0, err
    v = read_csv(tmp_path / "volts.csv", ("t", "u"))
    tgt = read_csv(files / "target.csv", ("t", "y"))
    assert v["u"].size == tgt["t"].size and np.array_equal(v["t"], tgt["t"])
    model = load_model(tmp_path / "pi.json")
    np.testing.assert_allclose(model.forward().block(v["u"]), tgt["y"], rtol=1e-9)

    rc, out, err = run_cli(["model", "invert", "--model", tmp_path / "pi.json", "--out", tmp_path / "inv.json"], capsys)
    assert rc == 0, err
    inv = json.loads((tmp_path / "inv.json").read_text())
    assert inv["direction"] == "inverse" and inv["weights"][0] == pytest.approx(1 / data["weights"][0])
    assert len(inv["thresholds"]) == 9
    # compensating with the inverse file gives the same voltages
    rc, _, err = run_cli(["compensate", "--model", tmp_path / "inv.json", "--target", files / "target.csv",
                          "--out", tmp_path / "volts2.csv"], capsys)
    assert rc == 0, err
    u2 = read_csv(tmp_path / "volts2.csv", ("t", "u"))["u"]
    np.testing.assert_allclose(np.clip(u2, 0, 150), v["u"], rtol=0, atol=1e-9)

    rc, out, err = run_cli(["model", "show", "--model", tmp_path / "inv.json"], capsys)
    assert rc == 0 and "Prandtl" in out and "inverse" in out


def test_identify_epi_and_creep_then_compensate(files, capsys, tmp_path):
    for kind in ("epi", "creep"):
        rc, out, err = run_cli(["identify", "--model", kind, "--data", files / "stairs.csv",
                                "--out", tmp_path / f"{kind}.json", "--operators", "3"], capsys)
        assert rc == 0, err
        assert load_model(tmp_path / f"{kind}.json").kind == kind
    ts, tg = staircase(2e-3, [500.0, 3000.0, 1000.0], 0.5)
    write_csv(tmp_path / "t.csv", {"t": ts, "y": tg})
    rc, out, err = run_cli(["compensate", "--model", tmp_path / "epi.json", "--target", tmp_path / "t.csv",
                            "--out", tmp_path / "v.csv"], capsys)
    assert rc == 0, err
    m = load_model(tmp_path / "epi.json")
    u = read_csv(tmp_path / "v.csv", ("t", "u"))["u"]
    np.testing.assert_allclose(m.forward(2e-3).block(u), tg, rtol=1e-9)
    rc, _, err = run_cli(["model", "invert", "--model", tmp_path / "epi.json", "--out", tmp_path / "einv.json"], capsys)
    assert rc == 0, err


def test_param_option_passed_to_identify(files, capsys, tmp_path):
    rc, out, err = run_cli(["identify", "--model", "pi", "--data", files / "data.csv", "--out", tmp_path / "p.json",
                            "--param", "thresholds=[0, 10, 20, 40]", "--param", "min_slope_fraction=0.01"], capsys)
    assert rc == 0, err
    assert json.loads((tmp_path / "p.json").read_text())["thresholds"] == [0, 10, 20, 40]


def _write(path, text):
    path.write_text(text)
    return path


BAD_CASES = {
    "nan": ("identify", "t,u,y\n0,0,0\n0.001,1,nan\n", "not finite"),
    "inf": ("identify", "t,u,y\n0,0,0\n0.001,inf,1\n", "not finite"),
    "empty": ("identify", "", "empty file"),
    "header-only": ("identify", "t,u,y\n", "0 data row"),
    "too-short": ("identify", "t,u,y\n0,0,0\n0.001,1,2\n0.002,2,4\n", "at least"),
    "non-monotone": ("identify", "t,u,y\n0,0,0\n0.002,1,1\n0.001,2,2\n", "strictly increasing"),
    "missing-column": ("identify", "t,u\n0,0\n1,1\n", "missing column(s) y"),
    "text": ("identify", "t,u,y\n0,zero,0\n", "not a number"),
    "target-nan": ("compensate", "t,y\n0,1\n0.001,nan\n", "not finite"),
    "target-missing": ("compensate", "t,u\n0,1\n", "missing column(s) y"),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_data_files(case, files, capsys, tmp_path):
    verb, text, message = BAD_CASES[case]
    f = _write(tmp_path / "bad.csv", text)
    if verb == "identify":
        args = ["identify", "--model", "pi", "--data", f, "--out", tmp_path / "m.json"]
    else:
        run_cli(["identify", "--model", "pi", "--data", files / "data.csv", "--out", tmp_path / "m.json",
                 "--operators", "5"], capsys)
        args = ["compensate", "--model", tmp_path / "m.json", "--target", f, "--out", tmp_path / "v.csv"]
    rc, out, err = run_cli(args, capsys)
    assert rc == 2
    assert err.startswith("afmctl: error: ") and err.count("\n") == 1, err
    assert message in err and "Traceback" not in err


MODEL_CASES = {
    "non-invertible": ({"kind": "pi", "thresholds": [0, 1, 2], "weights": [1.0, -0.5, -0.6]}, "partial sum"),
    "negative-w0": ({"kind": "pi", "thresholds": [0, 1], "weights": [-1.0, 2.0]}, "weights[0]"),
    "unknown-kind": ({"kind": "banana", "thresholds": [0], "weights": [1]}, "unknown model kind"),
    "no-kind": ({"thresholds": [0], "weights": [1]}, "missing field 'kind'"),
    "extra-field": ({"kind": "pi", "thresholds": [0], "weights": [1], "colour": "red"}, "colour"),
    "thresholds": ({"kind": "pi", "thresholds": [0, 3, 2], "weights": [1, 1, 1]}, "strictly increasing"),
}


@pytest.mark.parametrize("case", sorted(MODEL_CASES))
def test_bad_model_files(case, files, capsys, tmp_path):
    data, message = MODEL_CASES[case]
    m = _write(tmp_path / "m.json", json.dumps(data))
    for args in (["compensate", "--model", m, "--target", files / "target.csv", "--out", tmp_path / "v.csv"],
                 ["model", "invert", "--model", m, "--out", tmp_path / "i.json"],
                 ["model", "show", "--model", m]):
        rc, out, err = run_cli(args, capsys)
        assert rc == 2 and err.startswith("afmctl: error: ") and err.count("\n") == 1, err
        assert message in err and "Traceback" not in err


def test_wrong_kind_for_invert_and_other_errors(files, capsys, tmp_path):
    creep = _write(tmp_path / "c.json", json.dumps({"kind": "creep", "gain_nm_per_V": 1.0, "time_constants_s": [1.0],
                                                     "creep_weights": [0.1]}))
    rc, _, err = run_cli(["model", "invert", "--model", creep, "--out", tmp_path / "i.json"], capsys)
    assert rc == 2 and "allowed: pi, epi" in err
    rc, _, err = run_cli(["compensate", "--model", _write(tmp_path / "x.json", "{not json"), "--target",
                          files / "target.csv", "--out", tmp_path / "v.csv"], capsys)
    assert rc == 2 and "not valid JSON" in err
    rc, _, err = run_cli(["compensate", "--model", tmp_path / "missing.json", "--target", files / "target.csv",
                          "--out", tmp_path / "v.csv"], capsys)
    assert rc == 2 and "cannot read" in err
    rc, _, err = run_cli(["identify", "--model", "pi", "--data", files / "data.csv", "--out", tmp_path / "m.json",
                          "--param", "colour=red"], capsys)
    assert rc == 2 and "unknown option" in err
    rc, _, err = run_cli(["identify", "--model", "pi", "--data", files / "data.csv", "--out", tmp_path / "m.json",
                          "--param", "nonsense"], capsys)
    assert rc == 2 and "KEY=VALUE" in err
    rc, _, err = run_cli(["identify", "--model", "epi", "--data", files / "data.csv", "--out", tmp_path / "m.json"],
                         capsys)
    assert rc == 2 and "no dwells" in err
    rc, _, err = run_cli(["identify", "--model", "pi", "--data", files / "data.csv", "--out",
                          tmp_path / "no" / "such" / "dir.json"], capsys)
    assert rc == 2 and "cannot write" in err and err.count("\n") == 1
    rc, _, err = run_cli(["identify", "--model", "pi", "--data", files / "data.csv", "--out", tmp_path / "m.json",
                          "--operators", "0"], capsys)
    assert rc == 2 and "--operators" in err
    # limits refuse voltages outside the range unless clipped
    run_cli(["identify", "--model", "pi", "--data", files / "data.csv", "--out", tmp_path / "m.json"], capsys)
    rc, _, err = run_cli(["compensate", "--model", tmp_path / "m.json", "--target", files / "target.csv",
                          "--out", tmp_path / "v.csv", "--limits", "40", "60"], capsys)
    assert rc == 2 and "outside the limits 40..60 V (--limits" in err
    # non-uniform time for a time-dependent model
    _write(tmp_path / "nu.csv", "t,y\n0,1\n0.001,2\n0.005,3\n")
    epi = {"kind": "epi", "thresholds": [0, 1], "weights": [1, 1], "creep_a_nm": 1, "creep_b": 1,
           "creep_lambda_per_s": 1}
    rc, _, err = run_cli(["compensate", "--model", _write(tmp_path / "e.json", json.dumps(epi)), "--target",
                          tmp_path / "nu.csv", "--out", tmp_path / "v.csv"], capsys)
    assert rc == 2 and "uniformly spaced" in err


def test_real_subprocess_bad_and_good(files, tmp_path):
    bad = _write(tmp_path / "bad.csv", "t,u,y\n0,0,0\n0.001,nan,1\n")
    r = subprocess.run([sys.executable, "-m", "afmctl", "identify", "--model", "pi", "--data", str(bad), "--out",
                        str(tmp_path / "m.json")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert r.stderr.startswith("afmctl: error: ") and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "afmctl", "identify", "--model", "pi", "--data",
                        str(files / "data.csv"), "--out", str(tmp_path / "m.json"), "--operators", "5"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert load_model(tmp_path / "m.json").kind == "pi"


def test_help_teaches(capsys):
    for verb in (["identify"], ["compensate"], ["model", "invert"]):
        with pytest.raises(SystemExit):
            main(verb + ["--help"])
        out = capsys.readouterr().out
        assert "Example" in out


BAD_PARAMS = [
    ("pi", "min_slope_fraction=abc", "min_slope_fraction"),
    ("pi", "max_rows=abc", "max_rows"),
    ("epi", "min_dwell_samples=abc", "min_dwell_samples"),
    ("creep", "tau_min_s=abc", "tau_min_s"),
    ("preisach", "u_min_V=abc", "u_min_V"),
    ("preisach", "method=magic", "method"),
    ("bouc-wen", "u0_V=abc", "u0_V"),
    ("bouc-wen", "n=abc", "n:"),
]


@pytest.mark.parametrize("kind, param, needle", BAD_PARAMS)
def test_bad_param_values_are_one_line_errors(kind, param, needle, files, capsys, tmp_path):
    rc, _, err = run_cli(["identify", "--model", kind, "--data", files / "data.csv", "--out", tmp_path / "m.json",
                          "--param", param], capsys)
    assert rc == 2 and err.startswith("afmctl: error: ") and err.count("\n") == 1, err
    assert needle in err and "Traceback" not in err


def test_non_invertible_bouc_wen_file_is_blamed_on_the_model(files, capsys, tmp_path):
    m = _write(tmp_path / "bw.json", json.dumps({"kind": "bouc-wen", "d_nm_per_V": 1.0, "A_nm_per_V": 30.0,
                                                  "beta": 1.0, "gamma": 0.0}))
    rc, _, err = run_cli(["compensate", "--model", m, "--target", files / "target.csv", "--out", tmp_path / "v.csv"],
                         capsys)
    assert rc == 2 and err.startswith(f"afmctl: error: {m}: d_nm_per_V") and err.count("\n") == 1, err
