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
    "test_demo.py", "test_drift_scenario.py", "test_examples.py", "test_fuzz_files.py", "test_hil.py",
    "test_hil_live_tip.py", "test_readme_tour.py", "test_zenoh_e2e.py",
    "test_zenoh_run_process.py",
})


# Single tests measured at 2.5 s or more on the shared 2-core machine (pytest --durations)
# that start subprocesses or run long property searches.
SLOW_TESTS = frozenset({
    "test_cli_offline.py::test_real_subprocess_bad_and_good",
    "test_safety.py::test_controller_fuzz_never_emits_unsafe_voltage",
    "test_safety.py::test_faults_reconnects_stops_and_readbacks_never_make_an_unsafe_step",
    "test_sim_cli.py::test_sim_prints_the_pty_serves_mdt693b_and_stops_on_sigterm",
    "test_sim_cli.py::test_sim_with_a_config_file_chooses_the_protocol",
    "test_amp_cli.py::test_stream_warns_when_the_rate_is_not_reached",
})


def pytest_collection_modifyitems(config, items):
    import pytest
    for item in items:
        name = f"{item.path.name}::{item.originalname}"
        if item.path.name in SLOW_FILES or name in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)
