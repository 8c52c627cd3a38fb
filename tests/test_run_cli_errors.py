"""`afmctl run` refuses bad input with one line and exit status 2 before sending anything."""
from __future__ import annotations

import subprocess
import sys

import pytest

from afmctl.cli import main

CFG = """
[scanner]
name = "sim0"
[amplifier]
driver = "can"
port = "virtual:afmctl-run-cli-{tag}"
[trajectory]
kind = "file"
path = "{traj}"
[runlog]
dir = "{dir}"
[simulation]
enabled = true
"""


def _config(tmp_path, traj) -> str:
    p = tmp_path / "c.toml"
    p.write_text(CFG.format(tag=id(tmp_path), traj=traj, dir=tmp_path / "runs"))
    return str(p)


def test_missing_trajectory_file_is_one_line_and_exit_2(tmp_path, capsys):
    missing = tmp_path / "no_such_scan.csv"
    rc = main(["run", "--config", _config(tmp_path, missing), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and str(missing) in err and err.startswith("afmctl: error:")
    assert not list((tmp_path / "runs").glob("*.afmlog")) if (tmp_path / "runs").exists() else True


def test_bad_sample_in_trajectory_file_is_exit_2_naming_the_row(tmp_path, capsys):
    traj = tmp_path / "scan.csv"
    rows = [f"{k * 1e-3},{1000 + k},{1000},{500}" for k in range(3000)]
    rows[2500] = "2.5,nan,1000,500"
    traj.write_text("t,x,y,z\n" + "\n".join(rows) + "\n")
    rc = main(["run", "--config", _config(tmp_path, traj), "--quiet", "--json"])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = [ln for ln in err.splitlines() if ln.startswith("afmctl: error:")]
    assert len(lines) == 1 and str(traj) in lines[0]


@pytest.mark.parametrize("seconds", ["-1", "0", "nan", "inf", "1e9"])
def test_seconds_outside_the_range_is_exit_2(tmp_path, capsys, seconds):
    rc = main(["run", "--config", _config(tmp_path, tmp_path / "x.csv"), "--seconds", seconds])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and "--seconds" in err and "0 < S <= 1e+07 s" in err


def test_missing_trajectory_file_through_a_real_process(tmp_path):
    missing = tmp_path / "gone.npy"
    proc = subprocess.run([sys.executable, "-m", "afmctl", "run", "--config", _config(tmp_path, missing)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and str(missing) in proc.stderr and "Traceback" not in proc.stderr


def test_exit_codes_are_documented_in_help(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    out = capsys.readouterr().out
    assert "Exit status:" in out and "  3  the run log could not be written" in out
