"""Selection on real data split several ways (#24 item 5 and its acceptance: ``auto`` is never
worse on a second recording than the best single kind by more than 10 % RMS). The pea record
(tests/data/smarthysteresis-pea, MIT) cut into parts of different character: the sine record's
moving part halved, and the validation record (amplitude ramps and rests) halved both ways;
identified on one part through the CLI, validated on the other (the identifying part as warm
start, as ``afmctl model validate`` takes it)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.data.datafiles import read_csv, write_csv

DATA = Path(__file__).parent / "data" / "smarthysteresis-pea"
#: the single kinds auto is measured against (bouc-wen is one too: its fits on these parts
#: are slow and never the best in the measurements of docs/BENCHMARKS.md)
SINGLE = ("pi", "preisach", "pi+creep")


def halves(src: Path, folder: Path) -> tuple[Path, Path]:
    """The record's part from where its input first moves, split in the middle."""
    d = read_csv(src, ("t", "u", "y"))
    n = (int(np.flatnonzero(np.diff(d["u"]) != 0)[0]) + d["t"].size) // 2
    a, b = folder / f"{src.stem}_a.csv", folder / f"{src.stem}_b.csv"
    write_csv(a, {k: d[k][:n] for k in "tuy"})
    write_csv(b, {k: d[k][n:] for k in "tuy"})
    return a, b


def validate_rms(kind: str, fit: Path, val: Path, folder: Path, capsys) -> float:
    out = folder / f"{kind}.json"
    assert main(["identify", "--model", kind, "--data", str(fit), "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["model", "validate", "--model", str(out), "--data", str(val), "--warm-start", str(fit)]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if line.split()[:1] == ["all"])
    return float(row.split()[3])


@pytest.mark.parametrize("record, order", [("ident", "ab"), ("validate", "ab"), ("validate", "ba")])
def test_auto_is_within_10_percent_of_the_best_single_kind_on_the_other_part(tmp_path, capsys, record, order):
    a, b = halves(DATA / f"{record}.csv", tmp_path)
    fit, val = (a, b) if order == "ab" else (b, a)
    rms = {kind: validate_rms(kind, fit, val, tmp_path, capsys) for kind in ("auto", *SINGLE)}
    best = min(rms[k] for k in SINGLE)
    assert rms["auto"] <= 1.10 * best, rms
