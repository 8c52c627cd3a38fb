"""The soak (benchmarks/soak.py) cannot rot: its checks catch what they are for, and a short
soak through ``afmctl run`` with one fault of every kind runs to the end with every check held."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parent.parent / "benchmarks"
sys.path.insert(0, str(BENCH))

import soak  # noqa: E402
import soak_checks as sc  # noqa: E402


def test_the_schedule_is_seeded_and_visits_every_kind_once_per_round():
    a = soak.schedule(600, 30, list(soak.KINDS), seed=5, settle_s=20)
    assert a == soak.schedule(600, 30, list(soak.KINDS), seed=5, settle_s=20)
    assert a != soak.schedule(600, 30, list(soak.KINDS), seed=6, settle_s=20)
    for r in range(len(a) // 5):
        assert sorted(k for _, k in a[5 * r:5 * r + 5]) == sorted(soak.KINDS)
    gaps = np.diff([0.0] + [t for t, _ in a])
    assert gaps.min() >= 0.75 * 30 - 1e-9 and gaps.max() <= 1.25 * 30 + 1e-9 and a[-1][0] <= 580


def test_log_steps_finds_a_step_and_skips_only_the_restart_from_a_read_back():
    u = np.zeros((10, 3))
    u[:, 0] = np.arange(10) * 0.5
    assert sc.log_steps(u, []) == pytest.approx(0.5)
    u[6:, 0] += 40.0                                    # a jump inside a stretch
    assert sc.log_steps(u, []) == pytest.approx(40.5)
    assert sc.log_steps(u, [{"event": "resume", "seq": 6}]) == pytest.approx(0.5)
    assert sc.log_steps(u, [{"event": "watchdog", "seq": 6}]) == pytest.approx(40.5)


def test_match_received_aligns_in_order_and_reports_what_is_not_logged():
    logged = np.stack([np.linspace(0, 10, 200), np.linspace(5, 6, 200), np.zeros(200)], axis=1)
    received = np.round(np.delete(logged, np.s_[50:70], axis=0), 4)        # a stretch lost in flight
    m = sc.match_received(received, logged)
    assert (m >= 0).all() and (np.diff(m) > 0).all() and m[50] == 70
    stranger = np.vstack([received[:100], [[99.0, 1.0, 0.0]], received[100:]])   # applied, never logged
    m2 = sc.match_received(stranger, logged)
    assert np.flatnonzero(m2 < 0).tolist() == [100]


def test_amp_steps_start_from_the_power_on_output():
    rows = np.array([[0.5, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert sc.amp_steps(rows) == pytest.approx(0.5)
    assert sc.amp_steps(rows + 30.0) == pytest.approx(30.5)


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_short_soak_with_one_fault_of_each_kind_holds_every_check(tmp_path):
    args = ["--duration-s", "32", "--fault-every-s", "5", "--settle-s", "5", "--legs", "setpoints",
            "--amp-down-s", "1", "--disk-full-s", "2", "--viewer-stop-s", "2", "--seed", "3", "--out", str(tmp_path)]
    plan = soak.schedule(32, 5, list(soak.KINDS), 3, 5)
    assert sorted(k for _, k in plan) == sorted(soak.KINDS)          # one of each kind, in 32 s
    res = subprocess.run([sys.executable, str(BENCH / "soak.py"), *args], capture_output=True, text=True,
                         timeout=220)
    # a soak that ended before its analysis wrote no soak.json: say why (its output), not only that
    assert (tmp_path / "soak.json").exists(), (res.returncode, res.stdout[-3000:], res.stderr[-3000:])
    out = json.loads((tmp_path / "soak.json").read_text())
    assert res.returncode == 0, (res.stdout[-3000:], res.stderr[-3000:])
    assert out["violations"] == []
    assert {k: v["survived"] for k, v in out["faults_by_kind"].items()} == {k: 1 for k in soak.KINDS}
    leg = out["legs"]["setpoints"]
    assert leg["largest_applied_step_V"] <= leg["step_bound_V"] + sc.RESOLUTION_V
    assert leg["largest_logged_step_V"] <= leg["step_bound_V"] + 1e-9
    assert leg["received"] > 5000 and leg["in_log"] + leg["explained"] == leg["received"]
    assert leg["exit_codes"].get("3") == 1                        # the disk-full run ended safely
    assert leg["rss"]["end_MB"] > 10 and leg["stop_s"]            # the last run stopped on SIGTERM
    assert "fault 5" in res.stdout and (tmp_path / "soak.md").read_text().count("| setpoints") >= 1
