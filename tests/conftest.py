"""Shared pytest fixtures. Test helpers that users may also want live in the packages
(e.g. ``sim_backend.testing``); this file only wires them into pytest."""
from __future__ import annotations

import os

# Headless plotting everywhere in the test suite.
os.environ.setdefault("MPLBACKEND", "Agg")


# Whole files of end-to-end tests (subprocesses, the demo, real zenoh sessions across processes,
# hardware-in-the-loop with the simulator) that take several seconds each: marked `slow`, so
# that `make test-fast` (pytest -m "not slow") stays an inner loop. Single slow tests elsewhere
# carry @pytest.mark.slow themselves.
SLOW_FILES = frozenset({
    "test_demo.py", "test_drift_scenario.py", "test_examples.py", "test_hil.py",
    "test_hil_live_tip.py", "test_readme_tour.py", "test_zenoh_e2e.py",
    "test_zenoh_run_process.py",
})


def pytest_collection_modifyitems(config, items):
    import pytest
    for item in items:
        if item.path.name in SLOW_FILES:
            item.add_marker(pytest.mark.slow)
