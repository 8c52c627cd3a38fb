"""One failing controller test stays one failure: a generated test file, run by pytest in a
subprocess with this project's conftest, has a controller test that fails on purpose and
leaves its controller running (queue mode: it runs until stopped); the leak check
(tests/conftest.py ``no_leaked_threads``) stops it, so every test after it finds no thread
of it and passes. A test that passes but leaks gets exactly one error (its teardown; pytest counts its call as passed)."""
from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

GENERATED = '''
import threading

import numpy as np
import pytest

from afmctl.control.controller import Controller
from afmctl.simulation.link import RecordingAmplifier
from afmctl.testing import make_config

pytestmark = pytest.mark.usefixtures("no_leaked_threads")


def _controller():
    cfg = make_config(None, "", loop={"rate_Hz": 1000.0},
                      safety={"slew_V_per_s": 5000.0, "ramp_V_per_s": 500.0, "watchdog_s": 0.05})
    return Controller(cfg, RecordingAmplifier())


def test_a_fails_and_leaves_its_controller_running():
    _controller().start(None)      # queue mode: runs until stopped; never closed
    assert False, "deliberate failure"


def test_b_passes_but_leaks():
    _controller().start(None)


@pytest.mark.parametrize("k", range(4))
def test_c_after_it(k):
    assert [t.name for t in threading.enumerate() if t.name.startswith("afmctl-")] == []
    ctl = _controller()
    ctl.start(np.zeros((100, 3)))
    assert ctl.wait(10)
    ctl.close()
'''


def _run(tmp_path: Path, *args: str) -> str:
    shutil.copy(Path(__file__).with_name("conftest.py"), tmp_path / "conftest.py")
    (tmp_path / "test_generated.py").write_text(GENERATED)
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir",
                           str(tmp_path), "-o", "addopts=", *args, str(tmp_path / "test_generated.py")],
                          cwd=tmp_path, capture_output=True, text=True, timeout=240)
    return proc.stdout + proc.stderr


def _summary(out: str) -> str:
    return re.findall(r"^=*\s*(\d+ (?:failed|passed|error).*?) in [\d.]+s", out, re.M)[-1]


def test_a_deliberately_failed_controller_test_is_the_only_failure(tmp_path):
    out = _run(tmp_path, "-k", "not test_b")
    assert _summary(out) == "1 failed, 4 passed, 1 deselected", out
    assert "deliberate failure" in out and "threads left running" in out   # the leak is reported with it


def test_a_passing_test_that_leaks_is_one_error_and_the_rest_pass(tmp_path):
    out = _run(tmp_path, "-k", "not test_a")
    assert _summary(out) == "5 passed, 1 deselected, 1 error", out   # test_b passes, then errs in teardown
    assert re.search(r"ERROR .*test_b_passes_but_leaks", out), out
