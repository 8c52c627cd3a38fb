"""The suite gives the same answer twice: under the `ci` profile (the default of `make test`
and .ci/run, tests/conftest.py) hypothesis draws the same examples on every run and keeps no
database; `fuzz` (`make fuzz`) explores at random with a database and many more examples."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

PROPERTY = '''
from hypothesis import given, settings, strategies as st

@settings(max_examples=30)
@given(x=st.floats(-1e6, 1e6), n=st.integers(0, 10**9))
def test_draws(x, n):
    with open("drawn.txt", "a") as f:
        f.write(f"{x!r} {n}\\n")
'''


def _draws(tmp_path: Path, profile: str) -> list[str]:
    shutil.copy(Path(__file__).with_name("conftest.py"), tmp_path / "conftest.py")
    (tmp_path / "test_prop.py").write_text(PROPERTY)
    drawn = tmp_path / "drawn.txt"
    drawn.unlink(missing_ok=True)
    env = {"PATH": "/usr/bin:/bin", "HYPOTHESIS_PROFILE": profile, "HYPOTHESIS_FUZZ_FACTOR": "2", "HYPOTHESIS_FUZZ_MIN": "10"}
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir",
                           str(tmp_path), "-o", "addopts=", "test_prop.py"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return drawn.read_text().splitlines()


@pytest.mark.slow
def test_ci_profile_draws_the_same_examples_every_run_and_fuzz_does_not(tmp_path):
    first, second = _draws(tmp_path, "ci"), _draws(tmp_path, "ci")
    assert first == second and len(first) == 30
    fuzz1, fuzz2 = _draws(tmp_path, "fuzz"), _draws(tmp_path, "fuzz")
    assert fuzz1 != fuzz2 and len(fuzz1) >= 60          # random, and scaled: 2 x the test's 30 examples


@settings(max_examples=3)
@given(st.integers())
def test_this_suite_runs_derandomised_without_a_database(_n):
    current = settings.default
    if current.database is None:        # ci (the default): deterministic
        assert current.derandomize and current.deadline is None
    else:                               # fuzz
        assert not current.derandomize
