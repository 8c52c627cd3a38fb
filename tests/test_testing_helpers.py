"""The test helpers shipped in :mod:`afmctl.testing`."""
from __future__ import annotations

import pytest

from afmctl.errors import AfmctlError
from afmctl.testing import make_config, wait_until


def test_wait_until_names_what_it_waited_for():
    def motor_is_home():
        return False
    with pytest.raises(AssertionError, match=r"^timed out after 0\.05 s waiting for "
                                             r"test_wait_until_names_what_it_waited_for\.<locals>\.motor_is_home$"):
        wait_until(motor_is_home, 0.05)
    with pytest.raises(AssertionError, match=r"waiting for lambda: len\(\[\]\) > 3"):
        wait_until(lambda: len([]) > 3, 0.02)
    with pytest.raises(AssertionError, match=r"waiting for 3 ticks$"):
        wait_until(lambda: False, 0.02, what="3 ticks")
    wait_until(lambda: True, 0.02)


def test_make_config_merges_defaults_toml_and_sections(tmp_path):
    cfg = make_config(tmp_path, '[compensation.drift]\nenabled = true\n[loop]\nrate_Hz = 500\n',
                      loop={"rate_Hz": 1000}, safety={"slew_V_per_s": 2500})
    assert cfg.simulation.enabled and cfg.runlog.dir == tmp_path and cfg.runlog.fsync is False
    assert cfg.compensation.drift.enabled and cfg.loop.rate_Hz == 1000 and cfg.safety.slew_V_per_s == 2500
    assert make_config().runlog.enabled is False


def test_make_config_rejects_like_a_file():
    with pytest.raises(AfmctlError, match=r"^make_config: field loop\.rate_Hz = 1000000000\.0: .*allowed: 1 <= value <= 20000"):
        make_config(loop={"rate_Hz": 1e9})


def test_slow_lists_name_real_tests():
    """Every file and test the conftest marks slow exists (a rename must not silently move a
    slow test into `make test-fast`)."""
    import ast
    from pathlib import Path

    from conftest import SLOW_FILES, SLOW_TESTS
    here = Path(__file__).parent
    assert [f for f in SLOW_FILES if not (here / f).is_file()] == []
    missing = []
    for entry in SLOW_TESTS:
        file, _, name = entry.partition("::")
        tree = ast.parse((here / file).read_text(encoding="utf-8"))
        if name not in {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}:
            missing.append(entry)
    assert missing == []
