"""The rate-dependent Prandtl–Ishlinskii model (#36 item 5: loops that widen with the scan
rate): compiled kernels equal their references, the inverse is exact, ``c = 0`` is PI, and
identification finds the rate gain from a record at several rates — and is tried by
``auto`` only on such a record."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.compensators import _rate_pi_kernels as K
from afmctl.compensators.chain import ChainModel
from afmctl.compensators.pi import PIModel
from afmctl.compensators.rate_pi import RatePIModel, RatePIOperator, play_matrix, rate_series
from afmctl.compensators.selection import NOT_COVERED_RATE, covered_candidates

FS = 2000.0
DT = 1.0 / FS


def triangles(*parts: tuple[float, float]) -> np.ndarray:
    """Full-range (0–100 V) triangles: ``(frequency [Hz], duration [s])`` per part."""
    out = []
    for f_Hz, dur_s in parts:
        t = np.arange(int(dur_s * FS)) * DT
        out.append(100.0 * np.abs(2.0 * ((t * f_Hz + 0.5) % 1.0) - 1.0))
    return np.concatenate(out)


U = triangles((1.0, 3.0), (20.0, 1.0), (5.0, 2.0), (1.0, 2.0))
TRUE = RatePIModel(thresholds=[0.0, 10.0, 20.0, 30.0, 40.0], weights=[60.0, 10.0, 8.0, 6.0, 4.0],
                   initial_state=[0.0] * 5, offset_nm=-20.0, rate_gain_s_per_V=2e-4, rate_tau_s=0.01)


def test_compiled_kernels_equal_their_references_bit_for_bit():
    u = U[4000:10000]                          # the slow sweep's end, the fast one, the 5 Hz one's start
    y = TRUE.forward(DT).block(u)
    for inverse, x in ((False, u), (True, y)):
        fast = RatePIOperator(TRUE, DT, inverse=inverse)
        ref = RatePIOperator(TRUE, DT, inverse=inverse, use_numba=False)
        np.testing.assert_array_equal(fast.block(x), ref.block(x))


def test_the_inverse_gives_back_the_voltages_and_the_forward_the_target():
    y = TRUE.forward(DT).block(U)
    u = TRUE.inverse(DT).block(y)
    assert float(np.max(np.abs(u - U))) < 1e-9
    target = 3000.0 + 2500.0 * np.sin(2 * np.pi * 7.0 * np.arange(4000) * DT)
    assert float(np.max(np.abs(TRUE.forward(DT).block(TRUE.inverse(DT).block(target)) - target))) < 1e-8


def test_the_loop_widens_with_the_rate_and_without_rate_gain_it_is_pi():
    """Each play's share of the loop's width at mid-range is 2·r(t) while r(t) stays below a
    quarter of the sweep (a wider play lags less of the way back): thresholds up to 20 V
    on 100 V sweeps."""
    narrow = RatePIModel(**{**TRUE.model_dump(), "thresholds": [0.0, 5.0, 10.0, 15.0, 20.0]})
    width = []
    for f_Hz in (1.0, 5.0):                 # ρ 200 and 1000 V/s: thresholds × 1.04 and × 1.2
        u = triangles((f_Hz, 3.0 / f_Hz))
        y = narrow.forward(DT).block(u)
        n = int(FS / f_Hz)                  # the last cycle: rising, then falling branch
        rise, fall = slice(u.size - n, u.size - n // 2), slice(u.size - n // 2, u.size)
        up = np.interp(50.0, u[rise], y[rise])
        down = np.interp(50.0, u[fall][::-1], y[fall][::-1])
        width.append(down - up)
    assert width[1] == pytest.approx(1.2 / 1.04 * width[0], rel=0.02)
    pi = PIModel(thresholds=TRUE.thresholds, weights=TRUE.weights, initial_state=TRUE.initial_state,
                 offset_nm=TRUE.offset_nm)
    flat = RatePIModel(**{**TRUE.model_dump(), "rate_gain_s_per_V": 0.0})
    np.testing.assert_allclose(flat.forward(DT).block(U), pi.forward().block(U), rtol=0, atol=1e-9)


def test_the_rate_the_plays_see_is_the_smoothed_slope_and_does_not_grow_with_the_sample_rate():
    rho = rate_series(U, DT, 0.01)
    assert rho[0] == 0.0
    assert abs(float(rho[int(2.5 * FS)]) - 200.0) < 2.0             # 1 Hz full-range triangle: 200 V/s
    fine = np.repeat(U, 5)                                          # the same input sampled at 10 kHz
    rho_fine = rate_series(fine, DT / 5, 0.01)[::5]
    np.testing.assert_allclose(rho_fine[100:], rho[100:], rtol=0.02, atol=2.0)
    step = np.where(np.arange(2000) < 1000, 0.0, 100.0)             # a 100 V jump: at most ΔV/τ
    assert 0.2 * 100.0 / 0.01 < float(np.max(rate_series(step, DT, 0.01))) <= 100.0 / 0.01
    X = play_matrix(U, np.asarray(TRUE.thresholds), np.zeros(5), DT, TRUE.rate_gain_s_per_V, TRUE.rate_tau_s)
    np.testing.assert_allclose(X @ np.asarray(TRUE.weights) + TRUE.offset_nm, TRUE.forward(DT).block(U),
                               rtol=0, atol=1e-9)


def test_identification_finds_the_rate_gain_from_slow_and_fast_sweeps():
    y = TRUE.forward(DT).block(U) + np.random.default_rng(3).normal(0.0, 2.0, U.size)
    t = np.arange(U.size) * DT
    m = RatePIModel.identify(t, U, y, n_operators=5)
    assert m.rate_tau_s == pytest.approx(0.01)
    assert m.rate_gain_s_per_V == pytest.approx(2e-4, rel=0.05)
    assert m.rate_max_V_per_s == pytest.approx(float(np.max(rate_series(U, DT, 0.01))))
    resid = m.forward(DT).block(U) - y
    pi_resid = PIModel.identify(t, U, y, n_operators=5).forward().block(U) - y
    assert float(np.sqrt(np.mean(resid ** 2))) < 3.0 < 0.1 * float(np.sqrt(np.mean(pi_resid ** 2)))


def test_a_chain_starts_with_it_and_compensates_to_the_target():
    y = TRUE.forward(DT).block(U)
    t = np.arange(U.size) * DT
    chain = ChainModel.identify(t, U, y, structure="rate-pi+creep", n_operators=5)
    assert chain.structure == "rate-pi+creep"
    target = 1000.0 + 4000.0 * np.abs(2.0 * ((np.arange(int(FS)) * DT * 10.0) % 1.0) - 1.0)
    err = TRUE.forward(DT).block(chain.inverse(DT).block(target)) - target
    assert float(np.max(np.abs(err[int(0.2 * FS):]))) < 0.005 * float(np.ptp(target))


def test_past_the_highest_rate_it_was_identified_on_the_loop_stops_growing():
    capped = RatePIModel(**{**TRUE.model_dump(), "rate_max_V_per_s": 1000.0})
    at_cap = RatePIModel(**{**TRUE.model_dump(), "rate_gain_s_per_V": 0.0, "thresholds": [
        r * (1.0 + TRUE.rate_gain_s_per_V * 1000.0) for r in TRUE.thresholds]})
    fast = triangles((40.0, 1.0))                                  # ρ → 8000 V/s: far past the cap
    tail = slice(int(0.5 * FS), None)
    np.testing.assert_allclose(capped.forward(DT).block(fast)[tail], at_cap.forward(DT).block(fast)[tail],
                               rtol=0, atol=1e-6)
    y = capped.forward(DT).block(fast)
    assert float(np.max(np.abs(capped.forward(DT).block(capped.inverse(DT).block(y)) - y))) < 1e-8


def test_auto_tries_it_only_on_a_record_at_several_rates():
    t = np.arange(U.size) * DT
    rows, keep = covered_candidates(t, U, ["pi", "rate-pi", "rate-pi+creep"])
    assert keep == ["pi", "rate-pi", "rate-pi+creep"] and rows == []
    one = triangles((1.0, 6.0))
    rows, keep = covered_candidates(np.arange(one.size) * DT, one, ["pi", "rate-pi"])
    assert keep == ["pi"] and rows == [{"structure": "rate-pi", "error": NOT_COVERED_RATE}]


def test_the_smoothing_factor_is_a_sampled_first_order_lag():
    assert K.smoothing_factor(1e-3, 1e-3) == pytest.approx(1.0 - np.exp(-1.0))


def test_the_command_line_identifies_shows_and_compensates_with_it(tmp_path, capsys):
    from afmctl.cli import main
    from afmctl.data.datafiles import write_csv

    y = TRUE.forward(DT).block(U)
    t = np.arange(U.size) * DT
    write_csv(tmp_path / "sweeps.csv", {"t": t, "u": U, "y": y})
    target = 1000.0 + 4000.0 * np.abs(2.0 * ((np.arange(int(FS)) * DT * 10.0) % 1.0) - 1.0)
    write_csv(tmp_path / "target.csv", {"t": np.arange(target.size) * DT, "y": target})
    model = tmp_path / "rpi.json"
    assert main(["identify", "--model", "rate-pi", "--data", str(tmp_path / "sweeps.csv"), "--out", str(model),
                 "--operators", "5"]) == 0
    assert main(["model", "show", "--model", str(model)]) == 0
    assert "rate-dependent Prandtl–Ishlinskii (kind rate-pi)" in capsys.readouterr().out
    volts = tmp_path / "volts.csv"
    assert main(["compensate", "--model", str(model), "--target", str(tmp_path / "target.csv"), "--out", str(volts),
                 "--limits", "0", "150"]) == 0
    u = np.genfromtxt(volts, delimiter=",", names=True)["u"]
    err = TRUE.forward(DT).block(u) - target
    assert float(np.max(np.abs(err[int(0.2 * FS):]))) < 0.005 * float(np.ptp(target))
    capsys.readouterr()
    assert main(["identify", "--model", "rate-pi", "--data", str(tmp_path / "sweeps.csv"), "--out",
                 str(tmp_path / "bad.json"), "--param", "rate_tau_s=0"]) == 2
    assert "rate_tau_s" in capsys.readouterr().err


def test_a_record_that_barely_moves_keeps_the_rate_gain_within_the_files_bound():
    slow = 1.0 + 0.5 * np.abs(2.0 * ((np.arange(int(20 * FS)) * DT * 0.05) % 1.0) - 1.0)     # ≤ 0.05 V/s
    t = np.arange(slow.size) * DT
    m = RatePIModel.identify(t, slow, 100.0 * slow + 3.0 * np.sin(slow), n_operators=3)
    assert 0.0 <= m.rate_gain_s_per_V <= 1.0
