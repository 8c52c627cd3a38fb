"""The rate-dependent Bouc–Wen model (#36 item 5: loops that widen with the scan rate, kind
``rate-bouc-wen``): compiled kernels equal their reference, the inverse is exact, a rest
moves nothing, ``c = 0`` is Bouc–Wen, the fit's ``dh/dc`` is the derivative of the
simulation, identification finds the growth from sweeps at several rates, and ``auto``
tries it only on such a record."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.compensators._bouc_wen_kernels import bw_sens_nb, bw_sens_py
from afmctl.compensators.base import ModelError
from afmctl.compensators.bouc_wen import BoucWenModel
from afmctl.compensators.chain import ChainModel
from afmctl.compensators.rate_bouc_wen import RateBoucWenModel, RateBoucWenOperator, rate_series
from afmctl.compensators.selection import NOT_COVERED_RATE, covered_candidates

FS = 2000.0
DT = 1.0 / FS


def triangles(*parts: tuple[float, float]) -> np.ndarray:
    """Triangles between 10 and 130 V: ``(frequency [Hz], duration [s])`` per part."""
    out = []
    for f_Hz, dur_s in parts:
        t = np.arange(int(dur_s * FS)) * DT
        out.append(10.0 + 120.0 * np.abs(2.0 * ((t * f_Hz + 0.5) % 1.0) - 1.0))
    return np.concatenate(out)


U = triangles((1.0, 3.0), (20.0, 1.0), (5.0, 2.0), (1.0, 2.0))
TRUE = RateBoucWenModel(d_nm_per_V=72.0, A_nm_per_V=21.6, beta=0.012, gamma=0.003, u0_V=10.0,
                        rate_gain_s_per_V=1e-4, rate_max_V_per_s=4800.0, rate_tau_s=0.03)


def test_compiled_kernels_equal_their_reference_bit_for_bit_and_step_equals_block():
    u = U[4000:9000]                           # the slow sweep's end, the fast one, the 5 Hz one's start
    y = TRUE.forward(DT).block(u)
    for inverse, x in ((False, u), (True, y)):
        fast = RateBoucWenOperator(TRUE, DT, inverse=inverse)
        ref = RateBoucWenOperator(TRUE, DT, inverse=inverse, use_numba=False)
        whole = fast.block(x)
        np.testing.assert_array_equal(whole, ref.block(x))
        fast.reset()
        np.testing.assert_array_equal(whole, [fast.step(v) for v in x])


def test_the_inverse_gives_back_the_voltages_and_the_forward_the_target():
    y = TRUE.forward(DT).block(U)
    assert float(np.max(np.abs(TRUE.inverse(DT).block(y) - U))) < 1e-9
    target = 4500.0 + 3500.0 * np.sin(2 * np.pi * 7.0 * np.arange(4000) * DT)
    assert float(np.max(np.abs(TRUE.forward(DT).block(TRUE.inverse(DT).block(target)) - target))) < 1e-8


def test_the_loop_widens_with_the_rate_a_rest_moves_nothing_and_without_gain_it_is_bouc_wen():
    def width(model, f_Hz):                    # rising minus falling branch at mid-range, last cycle
        u = triangles((f_Hz, 3.0 / f_Hz))
        y = model.forward(DT).block(u)
        n = int(FS / f_Hz)
        up, down = y[-n:-n // 2], y[-n // 2:]
        return float(np.interp(70.0, u[-n:-n // 2], up) - np.interp(70.0, u[-n // 2:][::-1], down[::-1]))

    slow, fast = width(TRUE, 0.5), width(TRUE, 10.0)     # ρ 120 and 2400 V/s: A × 1.01 and × 1.24
    assert fast < 1.1 * slow < 0.0                       # wider (the falling branch lies above the rising)
    still = np.r_[triangles((20.0, 0.5)), np.full(int(FS), 70.0)]
    y = TRUE.forward(DT).block(still)
    assert float(np.ptp(y[-int(FS):])) == 0.0            # the growth fades at rest without moving h
    plain = BoucWenModel(**TRUE.model_dump(exclude={"kind", "rate_gain_s_per_V", "rate_max_V_per_s", "rate_tau_s"}))
    flat = RateBoucWenModel(**{**TRUE.model_dump(), "rate_gain_s_per_V": 0.0})
    np.testing.assert_array_equal(flat.forward(DT).block(U), plain.forward().block(U))


def test_the_fits_rate_sensitivity_is_the_derivative_of_the_simulation():
    q = np.minimum(rate_series(U, DT, 0.03, 10.0), 4800.0)
    rows = np.arange(50, U.size, 97)

    def sens(kernel, c):
        h, s = np.empty(rows.size), np.empty((rows.size, 5))
        kernel(U, q, c, 0.0, 10.0, 21.6, 0.012, 0.003, 1.0, TRUE.du_sub_V(), 1000000, rows, False, h, s)
        return h, s

    h, s = sens(bw_sens_nb, 1e-4)
    h_py, s_py = sens(bw_sens_py, 1e-4)
    np.testing.assert_allclose(h, h_py, rtol=1e-12, atol=0)
    np.testing.assert_allclose(s, s_py, rtol=1e-12, atol=1e-300)
    e = 1e-9
    fd = (sens(bw_sens_nb, 1e-4 + e)[0] - sens(bw_sens_nb, 1e-4 - e)[0]) / (2 * e)
    assert float(np.max(np.abs(fd - s[:, 4]))) <= 1e-5 * float(np.max(np.abs(s[:, 4])))
    y = TRUE.forward(DT).block(U)              # the forward operator's h, bit for bit
    np.testing.assert_array_equal(72.0 * U[rows] - h, y[rows])


def test_identification_finds_the_growth_from_slow_and_fast_sweeps():
    y = TRUE.forward(DT).block(U) + np.random.default_rng(3).normal(0.0, 2.0, U.size)
    t = np.arange(U.size) * DT
    m = RateBoucWenModel.identify(t, U, y, n=1.0)
    assert m.rate_tau_s == pytest.approx(0.03)
    assert m.max_growth() - 1.0 == pytest.approx(TRUE.max_growth() - 1.0, rel=0.1)   # at the fastest sweep
    bw = BoucWenModel.identify(t, U, y, n=1.0)
    assert m.fit_residual_nm < 3.0 < 0.2 * bw.fit_residual_nm


def test_a_chain_starts_with_it_and_compensates_to_the_target():
    y = TRUE.forward(DT).block(U)
    t = np.arange(U.size) * DT
    chain = ChainModel.identify(t, U, y, structure="rate-bouc-wen+creep", n=1.0)
    assert chain.structure == "rate-bouc-wen+creep"
    target = 2000.0 + 5000.0 * np.abs(2.0 * ((np.arange(int(FS)) * DT * 10.0) % 1.0) - 1.0)
    err = TRUE.forward(DT).block(chain.inverse(DT).block(target)) - target
    assert float(np.max(np.abs(err[int(0.2 * FS):]))) < 0.005 * float(np.ptp(target))


def test_auto_tries_it_only_on_a_record_at_several_rates():
    t = np.arange(U.size) * DT
    rows, keep = covered_candidates(t, U, ["bouc-wen", "rate-bouc-wen+creep"])
    assert keep == ["bouc-wen", "rate-bouc-wen+creep"] and rows == []
    one = triangles((1.0, 6.0))
    rows, keep = covered_candidates(np.arange(one.size) * DT, one, ["bouc-wen", "rate-bouc-wen"])
    assert keep == ["bouc-wen"] and rows == [{"structure": "rate-bouc-wen", "error": NOT_COVERED_RATE}]


def test_a_growth_without_its_cap_or_past_invertibility_is_refused():
    with pytest.raises(ValueError, match="rate_max_V_per_s"):
        RateBoucWenModel(**{**TRUE.model_dump(), "rate_max_V_per_s": None})
    steep = RateBoucWenModel(**{**TRUE.model_dump(), "rate_max_V_per_s": 1e5})   # A × 11 at the cap
    with pytest.raises(ModelError, match=r"allowed: > 2·A·\(1 \+ c·ρ_max\)·β/\(β\+γ\)"):
        steep.inverse(DT)


def _record_with_fast_sweeps_last(model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slow full triangles and holds, then (in the last 30 %) triangles at 5 and 20 Hz, as
    ``afmctl excite --kind all`` orders them; the output of ``model`` with 2 nm noise."""
    hold = np.full(int(0.5 * FS), 10.0)
    u = np.concatenate([triangles((0.5, 6.0)), hold, triangles((1.0, 2.0)), hold, triangles((0.5, 2.0)),
                        triangles((5.0, 1.2), (20.0, 1.0))])
    y = model.forward(DT).block(u) + np.random.default_rng(7).normal(0.0, 2.0, u.size)
    return np.arange(u.size) * DT, u, y


@pytest.mark.parametrize("rated", [True, False])
def test_auto_takes_the_growth_from_the_whole_record_and_keeps_it_only_where_loops_widen(rated):
    """The training part has no fast sweep: the rate candidate's growth comes from the whole
    record, and the held-out fast sweeps decide; a scanner whose loops do not widen keeps
    Bouc–Wen."""
    from afmctl.compensators.selection import GROWTH_FROM_WHOLE, growth_from_whole, select_model

    plant = TRUE if rated else RateBoucWenModel(**{**TRUE.model_dump(), "rate_gain_s_per_V": 0.0})
    t, u, y = _record_with_fast_sweeps_last(plant)
    split = int(round(0.7 * u.size))
    growth = growth_from_whole(t, u, y, 0, split, ["rate-bouc-wen+creep"], {"n": 1.0})
    assert growth is not None and set(growth) == {"rate_tau_s", "rate_gain_s_per_V", "rate_max_V_per_s", "rate_start"}
    assert growth_from_whole(t, u, y, 0, u.size - 10, ["rate-bouc-wen+creep"], {"n": 1.0}) is None  # sees them
    assert growth_from_whole(t, u, y, 0, split, ["bouc-wen+creep"], {"n": 1.0}) is None            # not asked
    best, table = select_model(t, u, y, ["bouc-wen+creep", "rate-bouc-wen+creep"], options={"n": 1.0},
                               with_dynamics=False)
    assert best.structure == ("rate-bouc-wen+creep" if rated else "bouc-wen+creep")
    assert not any(GROWTH_FROM_WHOLE in str(r) for r in table)
    if rated:
        assert best.hysteresis.max_growth() - 1.0 == pytest.approx(TRUE.max_growth() - 1.0, rel=0.15)
        rows = {r["structure"]: r for r in table}       # the fast sweeps held out decide, by far
        assert rows["bouc-wen+creep"]["fast_rms_nm"] > 20.0 * rows["rate-bouc-wen+creep"]["fast_rms_nm"]


def test_the_command_line_identifies_shows_and_compensates_with_it(tmp_path, capsys):
    from afmctl.cli import main
    from afmctl.data.datafiles import write_csv

    y = TRUE.forward(DT).block(U)
    write_csv(tmp_path / "sweeps.csv", {"t": np.arange(U.size) * DT, "u": U, "y": y})
    target = 2000.0 + 5000.0 * np.abs(2.0 * ((np.arange(int(FS)) * DT * 10.0) % 1.0) - 1.0)
    write_csv(tmp_path / "target.csv", {"t": np.arange(target.size) * DT, "y": target})
    model = tmp_path / "rbw.json"
    assert main(["identify", "--model", "rate-bouc-wen", "--data", str(tmp_path / "sweeps.csv"), "--out", str(model),
                 "--param", "n=1.0", "--param", "rate_tau_s=0.03", "--delay", "0"]) == 0
    assert main(["model", "show", "--model", str(model)]) == 0
    assert "rate-dependent Bouc–Wen model (kind rate-bouc-wen)" in capsys.readouterr().out
    volts = tmp_path / "volts.csv"
    assert main(["compensate", "--model", str(model), "--target", str(tmp_path / "target.csv"), "--out", str(volts),
                 "--limits", "0", "150"]) == 0
    u = np.genfromtxt(volts, delimiter=",", names=True)["u"]
    err = TRUE.forward(DT).block(u) - target
    assert float(np.max(np.abs(err[int(0.2 * FS):]))) < 0.005 * float(np.ptp(target))
    capsys.readouterr()
    assert main(["identify", "--model", "rate-bouc-wen", "--data", str(tmp_path / "sweeps.csv"), "--out",
                 str(tmp_path / "bad.json"), "--param", "rate_gain_s_per_V=1e-4"]) == 2
    err_line = capsys.readouterr().err
    assert "rate_gain_s_per_V, rate_max_V_per_s" in err_line and "Traceback" not in err_line
