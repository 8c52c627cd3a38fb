"""The loop thread's state machine, timing histograms and the moved ``resample``."""
from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from afmctl import loop_stats
from afmctl.errors import error_line
from afmctl.loop_machine import LoopMachine, Mode, State
from afmctl.trajectories import resample

ROOT = Path(__file__).resolve().parents[1]


def test_modes_and_states_are_named():
    assert [m.value for m in Mode] == ["run", "settle", "finish"]
    assert [s.value for s in State] == ["idle", "running", "holding", "fault", "stopped"]
    # every mode has a tick method
    for m in Mode:
        assert hasattr(LoopMachine, f"_tick_{m.value}")


@pytest.mark.parametrize("v", [0.0, 1e-7, 0.49e-6, 0.5e-6, 1.234e-3, 1.99999e-3, 2e-3, 2.05e-3, 0.05, 0.1019, 0.2, 5.0])
def test_fast_histogram_add_lands_in_the_bin_of(v):
    h = loop_stats.new_histogram()
    loop_stats.add(h, v)
    assert h.sum() == 1 and h[loop_stats.bin_of(v)] == 1


def test_percentiles_are_bin_centres():
    h = loop_stats.new_histogram()
    for v in (10e-6, 10e-6, 10e-6, 3e-3):
        loop_stats.add(h, v)
    p50, p99 = loop_stats.percentiles(h, (0.5, 0.99))
    assert p50 == pytest.approx(10.25e-6) and p99 == pytest.approx(3.05e-3)


def test_resample_lives_with_the_trajectories_and_interpolates_linearly():
    p = np.column_stack([np.arange(5.0), 2 * np.arange(5.0), np.zeros(5)])
    out = resample(p, 1.0, 0.5)
    assert out.shape == (9, 3)
    np.testing.assert_allclose(out[:, 0], np.arange(9) * 0.5)
    np.testing.assert_allclose(out[:, 1], np.arange(9) * 1.0)
    assert resample(p, 1.0, 1.0) is not None and np.array_equal(resample(p, 1.0, 1.0), p)


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    for n in ast.walk(tree):   # imports for type checkers only are not run
        if isinstance(n, ast.If) and getattr(n.test, "id", None) == "TYPE_CHECKING":
            n.body = []
    out = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.ImportFrom):
            out.add(("." * n.level) + (n.module or ""))
            out.update(("." * n.level) + a.name for a in n.names if n.module is None)
    return out


def test_trajectories_and_loop_machine_do_not_import_the_loop():
    assert not any(m in (".loop", "afmctl.loop") for m in _imports(ROOT / "afmctl" / "trajectories.py"))
    assert not any(m in (".loop", "afmctl.loop") for m in _imports(ROOT / "afmctl" / "loop_machine.py"))


def test_error_line_folds_whitespace_and_names_an_empty_error():
    assert error_line(OSError("disk\n  full")) == "disk full"
    assert error_line(TimeoutError()) == "TimeoutError"


def test_no_function_over_100_lines_in_the_loop_modules():
    for name in ("loop.py", "loop_machine.py", "loop_stats.py", "trajectories.py", "runlog.py", "zenoh_api.py",
                 "commands/run.py"):
        tree = ast.parse((ROOT / "afmctl" / name).read_text())
        for n in ast.walk(tree):
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
                assert n.end_lineno - n.lineno + 1 <= 100, f"{name}:{n.name}"
