"""Each error hole and footgun of issue #14 that was reproduced on the landed code, one test
each, through the command line in-process (``afmctl.cli.main``): exit status 2 and one line
naming the file and what is wrong, never a traceback."""
from __future__ import annotations

import json

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.control.runlog import SETPOINT_DTYPE, RunLogWriter

UTF16_JSON = '{"kind": "pi", "thresholds": [0.0], "weights": [1.0]}'.encode("utf-16")
BINARY = bytes(range(256)) * 2


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("afmctl: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.fixture
def target(tmp_path):
    path = tmp_path / "target.csv"
    path.write_text("t,y\n0,0\n0.001,100\n0.002,200\n")
    return path


def _pi_model(tmp_path, **extra):
    path = tmp_path / "pi.json"
    path.write_text(json.dumps({"kind": "pi", "thresholds": [0.0, 10.0], "weights": [80.0, 5.0], **extra}))
    return path


@pytest.mark.parametrize("content, needle", [(UTF16_JSON, "is UTF-16 text; save it as UTF-8"),
                                             (BINARY, "is not UTF-8 text (byte 0x80 at offset 128)")])
def test_binary_or_utf16_model_file(tmp_path, target, capsys, content, needle):
    model = tmp_path / "m.json"
    model.write_bytes(content)
    assert main(["compensate", "--model", str(model), "--target", str(target), "--out", str(tmp_path / "o.csv")]) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"afmctl: error: {model}: model file ") and needle in line
    assert main(["model", "show", "--model", str(model)]) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"afmctl: error: {model}: model file ") and needle in line


@pytest.mark.parametrize("content, needle", [(UTF16_JSON, "is UTF-16 text"), (BINARY, "is not UTF-8 text")])
def test_binary_or_utf16_drift_parameter_file(tmp_path, capsys, content, needle):
    params = tmp_path / "p.json"
    params.write_bytes(content)
    temps = tmp_path / "T.csv"
    temps.write_text("t,T\n0,20\n1,21\n2,22\n")
    assert main(["drift", "predict", "--temperature", str(temps), "--params", str(params),
                 "--out", str(tmp_path / "d.csv")]) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"afmctl: error: {params}: drift parameter file ") and needle in line


@pytest.mark.parametrize("content, needle", [("[loop]\nrate_Hz = 1000\n".encode("utf-16"), "is UTF-16 text"),
                                             (BINARY, "is not UTF-8 text"),
                                             (b"[loop]\nrate_Hz = 1\x00\n", "contains NUL bytes"),
                                             (b"[loop]\nrate_Hz = " + b"9" * 5000 + b"\n", "too long")])
def test_binary_or_utf16_toml_config(tmp_path, capsys, content, needle):
    cfg = tmp_path / "c.toml"
    cfg.write_bytes(content)
    assert main(["run", "--config", str(cfg), "--seconds", "0.1"]) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"afmctl: error: {cfg}: ") and needle in line


def test_utf8_bom_config_is_read(tmp_path, capsys):
    """A spreadsheet/Notepad UTF-8 byte-order mark is not an error."""
    cfg = tmp_path / "c.toml"
    cfg.write_bytes(b"\xef\xbb\xbf[loop]\nrate_Hz = 1e9\n")
    assert main(["run", "--config", str(cfg), "--seconds", "0.1"]) == 2
    line = one_error_line(capsys)     # parsed: the error is about the value, not the encoding
    assert line.startswith(f"afmctl: error: {cfg}: field loop.rate_Hz = 1000000000.0: ")


def test_garbage_model_named_in_a_config(tmp_path, capsys):
    model = tmp_path / "x.json"
    model.write_bytes(BINARY)
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[simulation]\nenabled = true\n[amplifier]\ndriver = "can"\n'
                   f'[compensation.x]\nmodel = "{model.name}"\n')
    assert main(["run", "--config", str(cfg), "--seconds", "0.1"]) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"afmctl: error: compensation.x.model: {model}: model file is not UTF-8 text")


def test_wrong_kind_model_error_names_the_file(tmp_path, target, capsys):
    drift = tmp_path / "drift.json"
    main(["drift", "params", "--out", str(drift)])
    capsys.readouterr()
    assert main(["compensate", "--model", str(drift), "--target", str(target), "--out", str(tmp_path / "o.csv")]) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"afmctl: error: {drift}: ") and "unknown model kind 'drift'" in line
    pi = _pi_model(tmp_path)
    assert main(["drift", "predict", "--temperature", str(target), "--params", str(pi),
                 "--out", str(tmp_path / "d.csv")]) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"afmctl: error: {pi}: ") and "kind" in line


def test_no_numpy_scalar_reprs_in_messages(tmp_path, capsys):
    temps = tmp_path / "T.csv"
    temps.write_text("t,T\n0,20\n1,500\n")
    assert main(["drift", "predict", "--temperature", str(temps), "--out", str(tmp_path / "d.csv")]) == 2
    line = one_error_line(capsys)
    assert "row 2 is 500.0 °C" in line and "np." not in line
    from afmctl.compensators.base import ModelError
    from afmctl.compensators.drift_kalman import DriftKalman
    from afmctl.compensators.errortext import plain_repr
    from afmctl.sim_backend.scanner import Scanner, default_scanner_config
    assert plain_repr(np.float64(1.5)) == "1.5" and plain_repr(np.int64(3)) == "3"
    with pytest.raises(ModelError, match=r"^T_C: 500\.0 out of range"):
        Scanner(default_scanner_config()).set_ambient_temperature(np.float64(500.0))
    with pytest.raises(ModelError, match=r"^dt_s: -0\.5 s;"):
        DriftKalman(np.float64(-0.5))


def test_compensate_defaults_its_limits_to_the_models_range(tmp_path, capsys):
    """A target the model cannot reach is refused, not written as megavolts."""
    model = _pi_model(tmp_path, u_range_V=[0.0, 150.0])
    far = tmp_path / "far.csv"
    far.write_text("t,y\n0,0\n0.001,1e9\n")       # 1 m: about 12 MV through this model
    out = tmp_path / "o.csv"
    assert main(["compensate", "--model", str(model), "--target", str(far), "--out", str(out)]) == 2
    line = one_error_line(capsys)
    assert "outside the limits 0..150 V (the model's voltage range" in line and not out.exists()
    assert main(["compensate", "--model", str(model), "--target", str(far), "--out", str(out), "--clip"]) == 0
    assert "limits           : 0 .. 150 V (the model's voltage range)" in capsys.readouterr().out
    u = np.loadtxt(out, delimiter=",", skiprows=1)[:, 1]
    assert u.max() == 150.0
    # a model file without a recorded range: 0..150 V, and the output says so
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"kind": "pi", "thresholds": [0.0], "weights": [80.0]}))
    assert main(["compensate", "--model", str(old), "--target", str(far), "--out", str(out)]) == 2
    assert "the model file records no voltage range; give --limits" in one_error_line(capsys)


def test_identify_records_the_voltage_range(tmp_path, capsys):
    t = np.arange(400) * 1e-3
    u = 20 + 60 * np.abs(np.sin(2 * np.pi * t))
    data = tmp_path / "d.csv"
    np.savetxt(data, np.column_stack([t, u, 80 * u]), delimiter=",", header="t,u,y", comments="")
    out = tmp_path / "m.json"
    assert main(["identify", "--model", "pi", "--data", str(data), "--out", str(out)]) == 0
    lo, hi = json.loads(out.read_text())["u_range_V"]
    assert lo == pytest.approx(u.min()) and hi == pytest.approx(u.max())


def _log(path, meta):
    n = 400
    sp = np.zeros(n, SETPOINT_DTYPE)
    sp["seq"] = np.arange(n)
    sp["t_s"] = np.arange(n) * 1e-3
    sp["target_nm"][:, 0] = 2000 + 1500 * np.sin(2 * np.pi * 5 * sp["t_s"])
    sp["corrected_nm"] = sp["target_nm"]               # no drift correction at all
    sp["u_V"][:, 0] = sp["target_nm"][:, 0] / 80.0     # a plain linear map: hysteresis untouched
    with RunLogWriter(path, meta, fsync=False) as w:
        w.write_setpoints(sp)


def test_report_names_its_quantities_and_shows_the_tracking_error_when_known(tmp_path, capsys):
    sim_run = tmp_path / "sim.afmlog"
    _log(sim_run, {"config": {"simulation": {"enabled": True}}})
    assert main(["report", str(sim_run)]) == 0
    out = capsys.readouterr().out
    corr = next(ln for ln in out.splitlines() if ln.startswith("drift correction"))
    track = next(ln for ln in out.splitlines() if ln.startswith("tracking error"))
    assert "(corrected target - target" in corr and "max 0.000 %" in corr
    assert "(tip position - target" in track
    assert float(track.split("max ")[1].split(" %")[0]) > 1.0     # the hysteresis shows
    hw_run = tmp_path / "hw.afmlog"
    _log(hw_run, {"config": {"simulation": {"enabled": False}}})
    assert main(["report", str(hw_run)]) == 0
    assert "tracking error: not known" in capsys.readouterr().out


def _identify_record(tmp_path, u):
    t = np.arange(u.size) * 1e-3
    path = tmp_path / "rec.csv"
    np.savetxt(path, np.column_stack([t, u, 50.0 * u]), delimiter=",", header="t,u,y", comments="")
    return path


def test_identify_unknown_param_is_not_reported_as_a_short_burn_in(tmp_path, capsys):
    """An unknown ``--param`` whose error text lists ``fit_from_index`` among the allowed
    options is that error, not the burn-in hint."""
    t = np.arange(4000) * 1e-3
    data = _identify_record(tmp_path, 75.0 + 60.0 * np.sin(2 * np.pi * t))
    assert main(["identify", "--model", "pi", "--data", str(data), "--param", "bogus=1",
                 "--out", str(tmp_path / "m.json")]) == 2
    err = one_error_line(capsys)
    assert "bogus" in err and "burn-in" not in err, err

