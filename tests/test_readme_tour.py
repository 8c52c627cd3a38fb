"""The README's offline tour, run as written: make data from the simulated scanner,
identify a Preisach model, compensate a target, check the tracking error."""
from __future__ import annotations

import importlib.util
from pathlib import Path

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
    import numpy as np
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
                                  "amp", "log", "report", "schema"])
def test_every_verb_has_help(verb, capsys):
    with pytest.raises(SystemExit) as exc:
        main([verb, "--help"])
    assert exc.value.code == 0
    assert len(capsys.readouterr().out) > 200
