"""Fits in worker processes (#38, :mod:`afmctl.compensators.fit_pool`): the caller's results
bit for bit, failures raised where they are asked for, speculative work free with one
process, and no worker left behind by a closed pool or a killed parent."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from afmctl.compensators.fit_pool import FitPool, one_blas_thread
from afmctl.compensators.selection import select_model
from plants import pi_with_a_mode_record

CALLS: list[int] = []


def _square_sum(shared: dict, k: int) -> float:
    CALLS.append(k)
    return float(np.sum((shared["x"] * k) ** 2))


def _fails(shared: dict, k: int) -> float:
    raise ValueError(f"task {k} failed")


def _pid(shared: dict) -> int:
    return os.getpid()


@pytest.mark.parametrize("jobs", [1, 2])
def test_results_are_the_callers_whatever_the_number_of_processes(jobs):
    x = np.linspace(0.0, 1.0, 10_001)
    with FitPool(jobs, {"x": x}) as pool:
        for k in range(6):
            pool.submit(k, _square_sum, k)
        got = [pool.result(k) for k in reversed(range(6))]
        assert pool.jobs == jobs
    assert got == [float(np.sum((x * k) ** 2)) for k in reversed(range(6))]


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_failed_task_raises_where_it_is_asked_for_and_the_others_go_on(jobs):
    with FitPool(jobs, {"x": np.ones(3)}) as pool:
        pool.submit("bad", _fails, 1)
        pool.submit("good", _square_sum, 2)
        with pytest.raises(ValueError, match="task 1 failed"):
            pool.result("bad")
        assert pool.result("good") == 12.0
        assert pool.result("late", _square_sum, 1) == 3.0      # submitted by the asking


def test_with_one_process_a_task_runs_only_when_asked_for():
    CALLS.clear()
    with FitPool(1, {"x": np.ones(2)}) as pool:
        pool.submit("guess", _square_sum, 5)           # speculative: never asked for
        pool.submit("needed", _square_sum, 3)
        assert pool.result("needed") == 18.0
    assert CALLS == [3]


def test_workers_are_other_processes_and_end_with_the_pool():
    with FitPool(2, {}) as pool:
        pool.submit("a", _pid)
        pid = pool.result("a")
    assert pid != os.getpid()
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_workers_end_when_their_parent_is_killed(tmp_path):
    """A calibration's identification process killed mid-fit (Ctrl-C closes it with
    terminate) leaves no worker fitting on."""
    pids = tmp_path / "pids"
    script = textwrap.dedent(f"""
        import time
        from afmctl.compensators.fit_pool import FitPool
        def nap(shared, s):
            import os
            time.sleep(s)
        pool = FitPool(2, {{}})
        open({str(pids)!r}, "w").write(" ".join(str(p) for p in pool._pids))
        pool.submit("a", nap, 60.0)
        pool.submit("b", nap, 60.0)
        time.sleep(60.0)
        """)
    proc = subprocess.Popen([sys.executable, "-c", script])
    try:
        deadline = time.monotonic() + 30.0
        while not (pids.exists() and pids.read_text().strip()) and time.monotonic() < deadline:
            time.sleep(0.05)
        workers = [int(p) for p in pids.read_text().split()]
        assert len(workers) == 2
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10.0)
        deadline = time.monotonic() + 10.0
        alive = workers
        while alive and time.monotonic() < deadline:
            time.sleep(0.1)
            alive = [p for p in alive if _alive(p)]
        assert alive == []
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (ended, its parent gone: init reaps it) counts as ended
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
            return stat.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def test_one_blas_thread_finds_the_bundled_openblas():
    """numpy's and scipy's wheels bundle OpenBLAS; a worker sets each to one thread."""
    import scipy.linalg  # noqa: F401 - loads scipy's own build
    if not os.path.exists("/proc/self/maps"):
        pytest.skip("reads /proc/self/maps (Linux)")
    assert one_blas_thread() >= 1


def test_auto_in_two_processes_selects_the_same_model_bit_for_bit():
    """``jobs=2``: the table and the model of one process (the candidate, its ``+dynamics``
    score with the refit and the folds fitted meanwhile, computed by the same functions on
    the same data, only elsewhere; tests/test_identify_worker.py has several candidates)."""
    t, u, y = pi_with_a_mode_record()
    y = y + 0.5 * np.sin(np.arange(u.size) * 0.37)
    opts = {"dynamics_options": {"n_modes": 1}}            # one mode: the test is about the processes
    one, table1 = select_model(t, u, y, candidates=("pi",), options=opts)
    two, table2 = select_model(t, u, y, candidates=("pi",), options=opts, jobs=2)
    assert one.model_dump_json() == two.model_dump_json()
    assert table1 == table2
    assert "dynamics" in one.structure
