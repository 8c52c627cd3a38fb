"""Real measurements (tests/data/smarthysteresis-pea, MIT, see its README): identify on the
first 7 s, validate on the held-out 3 s, through the CLI as a user meets it."""
from __future__ import annotations

import re
from pathlib import Path

from afmctl.cli import main

DATA = Path(__file__).parent / "data" / "smarthysteresis-pea"


def test_pi_identified_on_ident_predicts_validate_within_120_nm(tmp_path, capsys):
    rc = main(["identify", "--model", "pi", "--operators", "12", "--data", str(DATA / "ident.csv"),
               "--out", str(tmp_path / "pi.json")])
    out = capsys.readouterr().out
    assert rc == 0
    assert "burn-in" in out and "delay" in out          # the rest at 0 V and the sensor lag are handled
    assert "afmctl excite --kind static" in out          # full-scale cycles only: Preisach interior unknown
    rc = main(["model", "validate", "--model", str(tmp_path / "pi.json"), "--data", str(DATA / "validate.csv"),
               "--warm-start", str(DATA / "ident.csv")])
    out = capsys.readouterr().out
    assert rc == 0
    row = next(line for line in out.splitlines() if line.split()[:1] == ["all"]).split()
    rms_nm, rms_demeaned_nm = float(row[3]), float(row[5])
    assert rms_nm <= 120.0 and rms_demeaned_nm <= rms_nm
    assert re.search(r"cycle 3", out)
