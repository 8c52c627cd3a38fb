"""What a record's input covers (#36, a choice that holds on the next recording): minor
loops, holds after a step, several rates, large fast parts — on plain arrays, and what
``covered_candidates`` then leaves out of the selection."""
from __future__ import annotations

import numpy as np

from afmctl.compensators.coverage import MIN_HOLD_S, Coverage, interior_reversals, longest_hold_s
from afmctl.compensators.selection import NOT_COVERED_CREEP, NOT_COVERED_EPI, covered_candidates

FS = 2000.0


def full_range_sine(cycles: int = 5, f_Hz: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(int(cycles / f_Hz * FS)) / FS
    return t, 75.0 - 75.0 * np.cos(2 * np.pi * f_Hz * t)


def test_full_range_cycles_have_no_minor_loops_no_holds_and_one_rate():
    t, u = full_range_sine()
    cov = Coverage.of(t, u)
    assert cov.interior_reversals == 0 and not cov.minor_loops
    assert cov.longest_hold_s < 0.5 * MIN_HOLD_S and not cov.holds  # a turnaround is no hold and not cov.long_holds
    assert not cov.several_rates and not cov.large_fast


def test_an_amplitude_that_ramps_down_and_up_makes_minor_loops():
    """The P-885's validation session: nested loops, each reversal inside the range."""
    t = np.arange(int(8 * FS)) / FS
    amp = 75.0 * (0.2 + 0.8 * np.abs(1.0 - t / 4.0))
    u = 75.0 + amp * np.sin(2 * np.pi * 1.0 * t)
    cov = Coverage.of(t, u)
    assert cov.interior_reversals >= 8 and cov.minor_loops


def test_a_step_and_its_hold_are_measured_in_seconds():
    t = np.arange(int(3 * FS)) / FS
    u = np.where(t < 1.0, 10.0, 120.0)
    u = np.where(t > 1.5, 60.0, u)
    assert abs(longest_hold_s(t, u, 0.5) - 1.5) < 3.0 / FS
    cov = Coverage.of(t, u)
    assert cov.holds and cov.long_holds
    short = np.where(t < 1.0, 10.0, np.where(t < 1.0 + 0.5 * MIN_HOLD_S, 120.0, 120.0 - 40.0 * (t - 1.0)))
    assert not Coverage.of(t, short).holds


def test_large_fast_triangles_at_several_rates_count_as_large_fast_parts():
    """What ``afmctl excite --kind fast`` plays: large triangles at rising rates."""
    parts = []
    for f_Hz in (2.0, 10.0, 40.0):
        tt = np.arange(int(4 / f_Hz * FS)) / FS
        parts.append(15.0 + 120.0 * (1.0 - np.abs(2.0 * ((tt * f_Hz) % 1.0) - 1.0)))
    u = np.concatenate(parts)
    t = np.arange(u.size) / FS
    cov = Coverage.of(t, u)
    assert cov.several_rates and cov.large_fast
    assert interior_reversals(u) == 0                       # full-range triangles: no minor loops


def test_without_a_hold_creep_candidates_get_a_failed_row_and_the_rest_are_tried():
    t, u = full_range_sine()
    rows, keep = covered_candidates(t, u, ["pi", "pi+creep", "epi", "preisach+creep+dynamics", "bouc-wen"])
    assert keep == ["pi", "bouc-wen"]
    assert [r["structure"] for r in rows] == ["pi+creep", "epi", "preisach+creep+dynamics"]
    assert [r["error"] for r in rows] == [NOT_COVERED_CREEP, NOT_COVERED_EPI, NOT_COVERED_CREEP]
    # when every candidate needs a hold, all are tried (the user asked for them)
    rows, keep = covered_candidates(t, u, ["pi+creep", "epi"])
    assert rows == [] and keep == ["pi+creep", "epi"]


def test_slow_and_fast_sweeps_without_a_hold_try_creep_but_not_inflexion_creep():
    """A lab's record of triangles at 1 and 10 Hz, no hold: creep is what makes the slow and
    the fast sweeps differ besides the dynamics, so ``+creep`` is tried; ``epi`` is fitted on
    dwells and is not (amp-first from check.py's lab record: 0.43 → 0.24 % at 1 line/s)."""
    t = np.arange(int(4 * FS)) / FS
    u = np.where(t < 2.0, 150.0 * (1 - np.abs((t % 1.0) * 2 - 1)), 20.0 + 110.0 * (1 - np.abs((t * 10 % 1.0) * 2 - 1)))
    cov = Coverage.of(t, u)
    assert not cov.holds and cov.several_rates
    rows, keep = covered_candidates(t, u, ["pi", "pi+creep", "epi", "preisach+creep+dynamics"])
    assert keep == ["pi", "pi+creep", "preisach+creep+dynamics"]
    assert rows == [{"structure": "epi", "error": NOT_COVERED_EPI}]


def test_with_a_hold_every_candidate_is_tried():
    t = np.arange(int(4 * FS)) / FS
    u = np.where((t > 1.0) & (t < 2.0), 140.0, 75.0 - 75.0 * np.cos(2 * np.pi * t))
    rows, keep = covered_candidates(t, u, ["pi", "pi+creep", "epi"])
    assert rows == [] and keep == ["pi", "pi+creep", "epi"]


def test_the_compiled_loops_equal_their_plain_python_references():
    """Turning points and the longest hold: the numba twins give what the references give,
    on a record with wiggles under the tolerance, nested loops, steps and holds."""
    from afmctl.compensators.coverage import _reversals
    rng = np.random.default_rng(7)
    t = np.arange(int(6 * FS)) / FS
    u = 60 + 50 * np.sin(2 * np.pi * 0.7 * t) * np.abs(np.cos(2 * np.pi * 0.11 * t)) + 0.3 * rng.standard_normal(t.size)
    u[3000:4200] = u[3000]                                       # a hold after a step
    for tol in (0.0, 0.5, 2.0, 40.0):
        fast, ref = _reversals(u, tol), _reversals(u, tol, use_numba=False)
        assert fast.dtype == ref.dtype == np.int64 and np.array_equal(fast, ref)
        assert longest_hold_s(t, u, tol) == longest_hold_s(t, u, tol, use_numba=False)
    assert _reversals(u, 2.0).size > 4 and longest_hold_s(t, u, 0.5) >= 1200 / FS - 1 / FS
