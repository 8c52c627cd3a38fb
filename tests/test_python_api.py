"""The Python API (`import afmctl`, docs/PYTHON.md): lazy at import, arrays in and out, the
same code and figures as the command line. The examples of docs/PYTHON.md are executed
here, and on the shared real data they print what `afmctl identify`/`model validate`/
`compensate` print, to the last digit."""
from __future__ import annotations

import contextlib
import io
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import afmctl
from afmctl.cli import main as cli_main
from afmctl.data.datafiles import read_csv, write_csv

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "PYTHON.md"
SHARED = ROOT.parent / "shared" / "realdata" / "smarthysteresis-pea"
PEA = SHARED if SHARED.is_dir() else ROOT / "tests" / "data" / "smarthysteresis-pea"


def test_import_afmctl_loads_nothing_until_a_name_is_used():
    probe = ("import sys, afmctl\n"
             "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('numpy', 'scipy', 'numba', 'pydantic')"
             " or m.startswith('afmctl.'))\n"
             "print(heavy)\n"
             "print(afmctl.compensate.__module__, afmctl.Controller.__name__, 'identify' in dir(afmctl))\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == ["[]", "afmctl.api.compensation Controller True"]
    with pytest.raises(AttributeError, match="no attribute 'nonexistent'"):
        afmctl.nonexistent  # noqa: B018


def _record(n: int = 3000):
    """A decaying triangle through a known PI model (t [s], u [V], y [nm])."""
    from afmctl.compensators.pi import PIModel
    t = np.arange(n) * 1e-3
    u = 75.0 + 75.0 * np.exp(-t / 2.0) * (2 * np.abs((t * 2.0) % 2 - 1) - 1)
    truth = PIModel(thresholds=[0.0, 20.0, 40.0, 60.0], weights=[80.0, 20.0, 10.0, 5.0])
    return t, u, truth.forward().block(u), truth


def test_identify_arrays_and_csv_agree_and_compensate_inverts(tmp_path):
    t, u, y, _ = _record()
    write_csv(tmp_path / "rec.csv", {"t": t, "u": u, "y": y})
    from_arrays = afmctl.identify("pi", t_s=t, u_V=u, y_nm=y, burn_in="none", delay="0", thresholds=[0, 20, 40, 60])
    from_csv = afmctl.identify("pi", tmp_path / "rec.csv", burn_in="none", delay="0", thresholds=[0, 20, 40, 60])
    assert from_arrays.model.model_dump() == from_csv.model.model_dump()
    assert from_arrays.residual() == from_csv.residual() and from_arrays.rms_nm < 0.01 * np.ptp(y)
    afmctl.save_model(from_arrays.model, tmp_path / "m.json")
    model = afmctl.load_model(tmp_path / "m.json")
    target = y[500:1500]
    with pytest.raises(afmctl.LimitsExceeded, match="the model's voltage range"):
        afmctl.compensate(model, target)          # it was identified on 16.6..150 V only
    comp = afmctl.compensate(model, target, limits_V=(0.0, 150.0))
    assert comp.clipped == 0 and comp.limits_from == "limits_V"
    # the model run forward on the compensating voltages gives the target back
    assert afmctl.predict(model, t[:1000], comp.u_V) == pytest.approx(target, abs=1e-6 * np.ptp(y))
    assert afmctl.validate(model, t, u, y).rms_nm < 0.01 * np.ptp(y)


def test_api_errors_are_one_clear_line():
    t, u, y, truth = _record(500)
    with pytest.raises(afmctl.AfmctlError, match="t_s, u_V, y_nm need one equal length"):
        afmctl.identify("pi", t_s=t, u_V=u[:-1], y_nm=y)
    with pytest.raises(afmctl.AfmctlError, match="give either data"):
        afmctl.identify("pi", "x.csv", t_s=t, u_V=u, y_nm=y)
    with pytest.raises(ValueError, match="unknown model kind 'nope'"):
        afmctl.identify("nope", t_s=t, u_V=u, y_nm=y)
    with pytest.raises(afmctl.LimitsExceeded, match=r"outside the limits 10..20 V") as info:
        afmctl.compensate(truth, y, limits_V=(10.0, 20.0))
    assert info.value.count > 0 and info.value.index >= 0
    clipped = afmctl.compensate(truth, y, limits_V=(10.0, 20.0), clip=True)
    assert clipped.u_V.min() >= 10.0 and clipped.u_V.max() <= 20.0 and clipped.clipped == info.value.count
    with pytest.raises(afmctl.AfmctlError, match="u_V: non-finite"):
        afmctl.predict(truth, t, np.where(t > 0.1, np.nan, u))


def test_excite_is_what_the_command_writes(tmp_path):
    t, u = afmctl.excite("all", 0.0, 100.0, 2000.0, slew_V_per_s=2000.0)
    assert cli_main(["excite", "--kind", "all", "--u-min-V", "0", "--u-max-V", "100", "--rate-Hz", "2000",
                     "--slew-V-per-s", "2000", "--out", str(tmp_path / "e.csv")]) == 0
    d = read_csv(tmp_path / "e.csv", ("t", "u"))
    assert np.array_equal(d["t"], t) and np.array_equal(d["u"], u)
    assert np.max(np.abs(np.diff(u))) * 2000.0 <= 1000.0 + 1e-9


def _python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def _cli(argv: list[str]) -> list[str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli_main(argv) == 0
    return out.getvalue().splitlines()


@pytest.mark.slow
def test_python_md_runs_and_prints_the_command_lines_figures(tmp_path, monkeypatch):
    (tmp_path / "tests" / "data").mkdir(parents=True)
    os.symlink(PEA, tmp_path / "tests" / "data" / "smarthysteresis-pea")
    monkeypatch.chdir(tmp_path)
    blocks = _python_blocks(DOC.read_text(encoding="utf-8"))
    assert len(blocks) >= 5
    ns: dict = {"__name__": "python_md"}
    printed: list[list[str]] = []
    for block in blocks:
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            exec(compile(block, str(DOC), "exec"), ns)  # noqa: S102 - the documentation's own examples
        printed.append(out.getvalue().splitlines())
        if "comp = afmctl.compensate" in block:
            real = {k: ns[k] for k in ("t", "target_nm", "comp")}
    D = "tests/data/smarthysteresis-pea"
    cli_identify = _cli(["identify", "--model", "pi", "--operators", "12", "--data", f"{D}/ident.csv",
                         "--out", "cli.json"])
    # identify: the summary, the residual and the data notes, line for line
    api_identify = printed[0]
    assert [ln for ln in cli_identify if ln.startswith(("fit residual", "data "))] == \
        [ln for ln in api_identify if ln.startswith(("fit residual", "data "))]
    summary = afmctl.load_model("pea.json").summary().splitlines()
    assert summary == api_identify[:len(summary)] == cli_identify[:len(summary)]
    assert Path("cli.json").read_text() == Path("pea.json").read_text()
    # validate: the error table
    cli_validate = _cli(["model", "validate", "--model", "pea.json", "--data", f"{D}/validate.csv",
                         "--warm-start", f"{D}/ident.csv"])
    table = [ln for ln in printed[1] if not ln.startswith("held-out error")]
    assert table == cli_validate[-len(table):] and "55.8" in table[1]
    # compensate: the same voltages, bit for bit (the CSV holds full precision)
    write_csv("target.csv", {"t": real["t"], "y": real["target_nm"]})
    _cli(["compensate", "--model", "pea.json", "--target", "target.csv", "--out", "volts.csv"])
    assert np.array_equal(read_csv("volts.csv", ("t", "u"))["u"], real["comp"].u_V)
    # the simulator: compensation beats the straight line
    compensated, naive = map(float, re.findall(r"(\d+) nm", printed[-1][-1]))
    assert compensated < 0.5 * naive
