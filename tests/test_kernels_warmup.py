"""``python -m afmctl.kernels`` (run by the Makefile right after installing): on a cold numba
cache it says at once what it is doing and shows a progress bar while it compiles."""
from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.slow


def test_cold_cache_warm_up_says_so_before_compiling(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}   # a fresh, empty cache
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "afmctl.kernels"], stderr=subprocess.PIPE, env=env,
                            cwd=tmp_path)
    try:
        first = proc.stderr.readline().decode()
        seen_first_s = time.monotonic() - t0
        bar = proc.stderr.read1(4096).decode() if hasattr(proc.stderr, "read1") else ""
        assert first.startswith("afmctl: compiling numba kernels into the cache (first time only)")
        assert "numba kernels (compiled once, then cached)" in bar and "0/" in bar
        assert proc.poll() is None          # still compiling: the message came first
        print(f"first line after {seen_first_s:.2f} s")
    finally:
        proc.kill()
        proc.wait(timeout=30)


def test_every_warm_up_step_runs():
    """warm_up() logs and skips a failing step; here none may fail (each kind identifies,
    runs forward and, where invertible, inverse)."""
    from afmctl.kernels import warm_up_steps
    names = []
    for name, step in warm_up_steps():
        step()
        names.append(name)
    assert names[0] == "simulated scanner" and "model preisach" in names and names[-1] == "drift predictor"
