"""The README's tours, run as written: the instrument tour (calibrate → learn → run on
``afmctl sim``), the offline tour (make data from the simulated scanner, identify a Preisach
model, compensate a target, check the tracking error) and the real-data one."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from afmctl.cli import main

ROOT = Path(__file__).resolve().parent.parent


def _make_data_module():
    spec = importlib.util.spec_from_file_location("make_data", ROOT / "examples" / "make_data.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_readme_offline_tour(tmp_path, capsys):
    md = _make_data_module()
    data = tmp_path / "data"
    assert md.main([str(data)]) == 0
    model = tmp_path / "x.json"
    volts = tmp_path / "volts.csv"
    assert main(["identify", "--model", "preisach", "--data", str(data / "x_excitation.csv"),
                 "--out", str(model)]) == 0
    assert main(["model", "show", "--model", str(model)]) == 0
    assert main(["compensate", "--model", str(model), "--target", str(data / "target.csv"),
                 "--out", str(volts)]) == 0
    max_pct = md.check(volts, data / "target.csv")
    assert max_pct < 1.0          # README quotes 0.59 %
    # and the uncompensated linear calibration is far worse on the same scanner
    from afmctl.data.datafiles import read_csv, write_csv
    ex = read_csv(data / "x_excitation.csv", ["t", "u", "y"])
    tg = read_csv(data / "target.csv", ["t", "y"])
    lin = tmp_path / "lin.csv"
    write_csv(lin, {"t": tg["t"], "u": np.polyval(np.polyfit(ex["y"], ex["u"], 1), tg["y"])})
    assert md.check(lin, data / "target.csv") > 5 * max_pct


def test_readme_real_data_tour(tmp_path, capsys):
    """identify → validate on the held-out real recording, as the README shows it."""
    import re
    d = ROOT / "tests" / "data" / "smarthysteresis-pea"
    assert main(["identify", "--model", "pi", "--operators", "12", "--data", str(d / "ident.csv"),
                 "--out", str(tmp_path / "pea.json")]) == 0
    capsys.readouterr()
    assert main(["model", "validate", "--model", str(tmp_path / "pea.json"), "--data", str(d / "validate.csv"),
                 "--warm-start", str(d / "ident.csv"), "--plot", str(tmp_path / "pea.png")]) == 0
    row = next(ln for ln in capsys.readouterr().out.splitlines() if ln.split()[:1] == ["all"]).split()
    quoted = re.search(r"held-out RMS ([\d.]+) nm, max (\d+) nm", (ROOT / "README.md").read_text(encoding="utf-8"))
    assert float(row[3]) == pytest.approx(float(quoted.group(1)), abs=0.5)
    assert float(row[4]) == pytest.approx(float(quoted.group(2)), abs=5.0)


def test_readme_mentions_only_existing_files():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    import re
    for rel in re.findall(r"\((docs/[^)\s]+)\)", text) + re.findall(r"(examples/[\w.]+)", text):
        assert (ROOT / rel).exists(), rel
    lines = [ln for ln in text.splitlines() if ln.strip()]
    assert lines[1] == "```sh" and lines[2].startswith("make demo") and lines[3].startswith("make test")


@pytest.mark.parametrize("verb", ["demo", "run", "sim", "identify", "compensate", "model", "drift",
                                  "amp", "log", "report", "schema", "calibrate", "learn"])
def test_every_verb_has_help(verb, capsys):
    with pytest.raises(SystemExit) as exc:
        main([verb, "--help"])
    assert exc.value.code == 0
    assert len(capsys.readouterr().out) > 200


#: the excitation shortened by calibrate's own options (the README runs the full one, about a
#: minute of excitation and an `auto` selection): the suite stays lean
SHORT_CALIBRATION = ["--kind", "pi", "--dwell-s", "0.3", "--gap-s", "0.1", "--periods", "2", "--f-min-Hz", "50",
                     "--sweep-V-per-s", "600"]


def _tour_lines() -> list[str]:
    """The commands of the README's instrument tour, as written."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    block = text.split("## On an instrument", 1)[1].split("```sh\n", 1)[1].split("```", 1)[0]
    return [ln.split("#")[0].strip() for ln in block.splitlines() if ln.split("#")[0].strip()]


@pytest.mark.slow
def test_readme_instrument_tour_runs_as_written_on_afmctl_sim(tmp_path):
    """calibrate → learn → run on ``afmctl sim --protocol gcs --tcp`` (its own process), each
    command as the README writes it (the port a free one; calibrate's excitation shortened)."""
    import shlex
    import socket
    import subprocess
    import sys

    from afmctl.testing import stop_process
    lines = _tour_lines()
    assert lines[0].startswith("mkdir -p tour") and lines[-1] == "kill %1", lines
    # the README waits for the simulator's first line (its address) before calibrating, as
    # this test does below: a command pasted at once would otherwise find nothing listening
    sim_line, wait_line = lines[1], lines.pop(2)
    assert sim_line.endswith("> sim.txt &") and wait_line.startswith("until grep -qs socket:// sim.txt;"), lines
    lines[1] = sim_line.removesuffix("> sim.txt &") + "&"
    assert [ln.split()[1] for ln in lines[1:-1]] == ["sim", "calibrate", "learn", "run"]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = str(s.getsockname()[1])
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    assert subprocess.run(lines[0].split(" && cd ")[0], shell=True, cwd=tmp_path).returncode == 0
    tour = tmp_path / "tour"
    for f in tour.glob("*.toml"):
        f.write_text(f.read_text(encoding="utf-8").replace("50000", port), encoding="utf-8")

    def argv(line: str) -> list[str]:
        words = shlex.split(line.replace("50000", port).rstrip("&").strip())
        assert words[0] == "afmctl"
        return [sys.executable, "-m", "afmctl", *words[1:]]

    sim = subprocess.Popen(argv(lines[1]), cwd=tour, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert sim.stdout.readline().strip() == f"socket://127.0.0.1:{port}"     # it listens
        runs = []
        for line, more in ((lines[2], SHORT_CALIBRATION), (lines[3], []), (lines[4], [])):
            res = subprocess.run(argv(line) + more, cwd=tour, capture_output=True, text=True, timeout=600)
            runs.append(res)
            assert res.returncode == 0 and "Traceback" not in res.stderr, (line, res.stderr[-3000:])
    finally:
        stop_process(sim)
    cal, learn, run = runs
    model = json.loads((tour / "scanner.json").read_text())
    prov = model["provenance"]
    assert model["kind"] == "scanner" and model["axes"]["x"]["kind"] == "pi"     # a scanner file: x calibrated
    assert prov["device"]["driver"] == "gcs" and "E-727" in prov["device"]["identity"]
    assert prov["recorder_rate_Hz"] == 10000.0 and prov["settle_s"] == 2.0 and prov["afmctl_version"]
    assert prov["axes"]["x"]["pieces"] >= 2                  # the recorder's 32,768 points: several pieces
    val = prov["validation"]["x"]
    assert set(val) == {"raster", "minor loops", "all"} and val["all"]["max_pct"] < 10.0   # PI on this scanner: ~2 %
    rec = (tour / "scanner.x-recording.csv").read_text().splitlines()
    assert rec[0] == "t,u,y,v"
    data = np.loadtxt(rec[1:], delimiter=",")
    assert np.ptp(data[:, 2]) > 5000.0                       # the sensor saw the scanner sweep the range
    assert 0 < np.max(np.abs(data[:, 3] - data[:, 1])) < 5.0  # the piezo voltage lags the command a little
    assert "validation raster" in cal.stdout and "written" in cal.stdout
    assert "excite x piece 2/" in cal.stderr                 # the progress bar: which piece, how long to go
    assert "learned table line.afmwave" in learn.stderr and (tour / "line.afmwave").exists()
