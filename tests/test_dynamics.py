"""Linear dynamics model (kind "dynamics"): discretisation, streaming, inverses, files, fit."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import butter, lsim, sosfiltfilt

from afmctl.compensators.base import ModelError
from afmctl.compensators.dynamics import LinearDynamicsModel
from afmctl.compensators.lti import FIROperator, LTIOperator
from afmctl.compensators.models import load_model, model_from_dict, save_model

DT = 1e-5


def scanner_like(delay_s: float = 13e-6) -> LinearDynamicsModel:
    """1 kHz mode ζ 0.025 behind a 5 kHz amplifier lag: the default simulator's lateral axis."""
    return LinearDynamicsModel.from_modes([(1000.0, 0.025)], [5000.0], delay_s=delay_s)


def nonminimum_phase() -> LinearDynamicsModel:
    """A mode with a right-half-plane zero at 3 kHz and a 50 µs delay (exact inverse unstable)."""
    w = 2 * math.pi * 800
    z = 0.04
    poles = [(-z * w, w * math.sqrt(1 - z * z)), (-z * w, -w * math.sqrt(1 - z * z)), (-2 * math.pi * 6000, 0.0)]
    return LinearDynamicsModel(poles_rad_per_s=poles, zeros_rad_per_s=[(2 * math.pi * 3000, 0.0)], delay_s=50e-6)


def band_limited(n: int, f_Hz: float, seed: int, amp_nm: float = 2000.0, dt: float = DT) -> np.ndarray:
    """Random signal limited to ``f_Hz``, at rest (zero) for its first and last 20 %."""
    rng = np.random.default_rng(seed)
    x = sosfiltfilt(butter(6, f_Hz, fs=1 / dt, output="sos"), rng.standard_normal(n))
    w = np.zeros(n)
    a, b = n // 5, n - n // 5
    w[a:b] = np.sin(np.linspace(0, np.pi, b - a)) ** 2
    x = x * w
    return amp_nm * x / np.max(np.abs(x))


def test_file_round_trip_and_registry(tmp_path):
    m = scanner_like()
    save_model(m, tmp_path / "d.json")
    back = load_model(tmp_path / "d.json")
    assert back == m and back.kind == "dynamics"
    assert abs(back.frequency_response(np.array([0.0]))[0] - 1.0) < 1e-12


@pytest.mark.parametrize("data, field", [
    ({"poles_rad_per_s": [[1.0, 0.0]]}, "negative real part"),
    ({"poles_rad_per_s": [[-1.0, 5.0]]}, "conjugate"),
    ({"poles_rad_per_s": [[-1.0, 0.0]], "zeros_rad_per_s": [[0.0, 0.0]]}, "s = 0"),
    ({"poles_rad_per_s": [[-1.0, 0.0]], "zeros_rad_per_s": [[-2.0, 0.0], [-3.0, 0.0]]}, "no more zeros"),
    ({"poles_rad_per_s": [[-1.0, 0.0]], "delay_s": -1.0}, "delay_s"),
    ({"poles_rad_per_s": [[-1.0, float("nan")]]}, "poles_rad_per_s"),
    ({"poles_rad_per_s": [[-1.0, 0.0]], "lead_samples": 1.5}, "lead_samples"),
    ({"poles_rad_per_s": [[-1.0, 0.0]], "lead_samples": 0.5, "delay_s": 1e-5}, "lead_samples"),
])
def test_bad_model_files_name_the_field(data, field):
    with pytest.raises(ModelError, match=field):
        model_from_dict({"kind": "dynamics", **data}, where="m.json")


@pytest.mark.parametrize("delay_s", [0.0, 30e-6, 37e-6])
def test_zoh_discretisation_matches_continuous_simulation(delay_s):
    """The discrete operator equals the continuous system driven by the held, delayed
    input (simulated with a zero-order hold on a 50× finer grid), whole and fractional delays alike."""
    m = scanner_like(delay_s)
    u = band_limited(3000, 3000.0, 1)
    y = m.forward(DT).block(u)
    over = 50
    t_f = np.arange(u.size * over) * (DT / over)
    shift = int(round(delay_s / (DT / over)))
    u_f = np.concatenate([np.zeros(shift), np.repeat(u, over)])[: t_f.size]
    p, z = m.poles(), m.zeros()
    from afmctl.compensators.lti import unit_dc_gain
    from scipy.signal import zpk2tf
    num, den = zpk2tf(z, p, unit_dc_gain(z, p))
    _, y_f, _ = lsim((np.real(num), np.real(den)), u_f, t_f, interp=False)
    assert np.max(np.abs(y - y_f[::over])) < 1e-6 * np.ptp(u)


@pytest.mark.parametrize("lead", [0.25, 1.0])
def test_lead_reads_the_continuous_output_inside_each_hold_interval(lead):
    """With ``lead_samples`` λ the output k is the continuous system's at t_k + λ·T for the
    input held from t_k (a record read at the end of each hold for λ = 1); λ = 1 is the
    lead-free output one sample later."""
    m = scanner_like(0.0).model_copy(update={"lead_samples": lead})
    u = band_limited(3000, 3000.0, 6)
    y = m.forward(DT).block(u)
    over = 40
    t_f = np.arange((u.size + 1) * over) * (DT / over)
    p, z = m.poles(), m.zeros()
    from afmctl.compensators.lti import unit_dc_gain
    from scipy.signal import zpk2tf
    num, den = zpk2tf(z, p, unit_dc_gain(z, p))
    _, y_f, _ = lsim((np.real(num), np.real(den)), np.repeat(np.r_[u, 0.0], over), t_f, interp=False)
    read = np.arange(u.size) * over + int(round(lead * over))
    assert np.max(np.abs(y - y_f[read])) < 1e-6 * np.ptp(u)
    if lead == 1.0:
        plain = scanner_like(0.0).forward(DT).block(u)
        assert np.max(np.abs(y[:-1] - plain[1:])) < 1e-9 * np.ptp(u)
        target = band_limited(20_000, 400.0, 3)      # and the inverse still inverts it
        assert np.max(np.abs(m.forward(DT).block(m.inverse_offline(target, DT)) - target)) < 1e-3 * np.ptp(target)


def test_identify_keeps_the_lead_of_a_record_read_at_the_end_of_each_hold():
    """A record whose output is read at the end of each hold interval (the simulated
    scanner's positions) leads the hold-start convention by one sample: the fit keeps it as
    ``lead_samples`` = 1 (it used to drop it, leaving the model a sample late), and the
    fitted model then predicts the record sample for sample."""
    true = scanner_like(0.0)
    dt = 2e-5
    n = 100_000
    rng = np.random.default_rng(8)
    u = rng.standard_normal(n)
    ahead = true.model_copy(update={"lead_samples": 1.0})
    y = 80.0 * ahead.forward(dt).block(u)
    m = LinearDynamicsModel.identify(np.arange(n) * dt, u, y)
    assert m.delay_s == 0.0 and m.lead_samples == pytest.approx(1.0, abs=0.05)
    pred = 80.0 * m.forward(dt).block(u)
    late = 80.0 * m.model_copy(update={"lead_samples": 0.0}).forward(dt).block(u)
    assert np.std(pred - y) < 0.2 * np.std(late - y)
    # the same plant read at the start of each hold: no lead, no delay beyond the hold
    m0 = LinearDynamicsModel.identify(np.arange(n) * dt, u, 80.0 * true.forward(dt).block(u))
    assert m0.lead_samples < 0.05 and m0.delay_s < 0.05 * dt


def test_block_equals_step_and_compiled_equals_reference():
    m = nonminimum_phase()
    u = band_limited(4000, 2000.0, 2) + 300.0
    fast = m.forward(DT, initial_nm=300.0)
    y = fast.block(u)
    fast.reset()
    assert np.array_equal(np.array([fast.step(v) for v in u]), y)
    ref = LTIOperator(m.discrete(DT), 300.0, use_numba=False)
    assert np.array_equal(ref.block(u), y)
    inv = m.inverse(DT)
    v = inv.block(u)
    inv.reset()
    assert np.array_equal(np.array([inv.step(s) for s in u]), v)
    assert np.array_equal(FIROperator(inv.h, 0.0, use_numba=False).block(u), FIROperator(inv.h).block(u))


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(1, 700), min_size=1, max_size=8), st.integers(0, 10_000))
def test_any_block_split_gives_the_same_numbers(sizes, seed):
    m = scanner_like(23e-6)
    u = band_limited(3000, 2000.0, seed)
    for make in (lambda: m.forward(DT), lambda: m.inverse(DT)):
        whole = make().block(u)
        op = make()
        parts, i = [], 0
        for s in itertools.cycle(sizes):
            if i >= u.size:
                break
            parts.append(op.block(u[i:i + s]))
            i += s
        assert np.array_equal(np.concatenate(parts), whole)


@pytest.mark.parametrize("make", [scanner_like, nonminimum_phase])
@pytest.mark.parametrize("seed", [3, 4])
def test_forward_of_inverse_is_identity_on_band_limited_signals(make, seed):
    """Band-limited targets (≤ 400 Hz, well inside the inverse's band), at rest at both ends."""
    m = make()
    y = band_limited(20_000, 400.0, seed)
    off = m.forward(DT).block(m.inverse_offline(y, DT))
    assert np.max(np.abs(off - y)) < 1e-3 * np.ptp(y)
    inv = m.inverse(DT)
    L = inv.latency_samples
    assert L > 0
    live = m.forward(DT).block(inv.block(np.concatenate([y, np.zeros(L)])))
    assert np.max(np.abs(live[L:] - y)) < 1e-3 * np.ptp(y)
    # without preview a plant with delay cannot be inverted: the error is large
    if m.delay_s > 0:
        short = m.forward(DT).block(m.inverse(DT, preview_s=0.0).block(y))
        assert np.max(np.abs(short - y)) > 10 * np.max(np.abs(live[L:] - y))


def test_preview_latency_is_reported_and_respected():
    m = nonminimum_phase()
    inv = m.inverse(DT, preview_s=2e-3)
    assert inv.latency_samples == 200
    assert inv.h.size > 200
    with pytest.raises(ModelError, match="preview_s"):
        m.inverse(DT, preview_s=-1.0)
    with pytest.raises(ModelError, match="dt_s"):
        m.inverse(None)


def test_a_run_s_inverse_starts_at_rest_at_its_first_target_not_where_the_record_began():
    """``initial_nm`` is where the identification record began (9550 nm on the E-727's);
    a run starting at 1000 nm must get a steady command from its first sample (the
    approach and the settle hold put the scanner there), and a reset takes the next run's
    first target; ``initial_nm=`` still pins the rest point, step and block agree."""
    m = scanner_like().model_copy(update={"initial_nm": 9550.0})
    inv = m.inverse(DT)
    out = inv.block(np.full(400, 1000.0))
    np.testing.assert_allclose(out, 1000.0, atol=1e-6)
    inv.reset()
    np.testing.assert_allclose(inv.block(np.full(50, -300.0)), -300.0, atol=1e-6)
    pinned = m.inverse(DT, initial_nm=9550.0).block(np.full(400, 1000.0))
    assert np.max(np.abs(pinned - 1000.0)) > 100.0          # the transient the default avoids
    x = 1000.0 + band_limited(2000, 300.0, seed=3)
    a, b = m.inverse(DT), m.inverse(DT)
    np.testing.assert_array_equal(a.block(x), np.array([b.step(v) for v in x]))
    ref = FIROperator(a.h, None, use_numba=False)
    np.testing.assert_allclose(ref.block(x), m.inverse(DT).block(x), rtol=0, atol=1e-9)


def test_identify_recovers_a_known_model():
    true = scanner_like(13e-6)
    dt = 2e-5
    n = 200_000
    rng = np.random.default_rng(5)
    u = rng.standard_normal(n)
    y = 80.0 * true.forward(dt).block(u) + 0.1 * rng.standard_normal(n)
    m = LinearDynamicsModel.identify(np.arange(n) * dt, u, y)
    assert abs(m.fit_info["static_gain_y_per_u"] / 80.0 - 1) < 0.01
    mode = [p for p in m.poles() if p.imag > 0][0]
    assert abs(abs(mode) / (2 * math.pi) / 1000.0 - 1) < 0.01
    assert abs(-mode.real / abs(mode) / 0.025 - 1) < 0.1
    f = np.linspace(10, 8000, 200)
    g_true, g_fit = true.discrete(dt).frequency_response(f), m.discrete(dt).frequency_response(f)
    assert np.max(np.abs(g_fit / g_true - 1)) < 0.05


def test_identify_rejects_data_without_excitation():
    t = np.arange(5000) * 1e-4
    with pytest.raises(ModelError, match="excite"):
        LinearDynamicsModel.identify(t, np.full(t.size, 3.0) + 1e-9 * np.sin(t), np.zeros(t.size))
    with pytest.raises(ModelError, match="uniformly"):
        LinearDynamicsModel.identify(t ** 2, np.sin(t), np.sin(t))
    with pytest.raises(ModelError, match="n_modes"):
        LinearDynamicsModel.identify(t, np.sin(t), np.sin(t), n_modes=-1)
