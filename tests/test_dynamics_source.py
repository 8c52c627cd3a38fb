"""#24 item 1: the chain's dynamics stage from the voltage (the hysteresis's small-signal gain
divided out), not from the identified static stages' output."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.signal import lfilter

from afmctl.compensators.base import ModelError
from afmctl.compensators.chain import ChainModel
from plants import RelayPreisachPlant

FS = 20000.0
LAG_HZ = 600.0


def _record() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nested triangles (2 s), then a ±2 % random-phase multisine around mid-range (1.2 s),
    through an amplifier lag of 600 Hz and a relay-Preisach scanner."""
    n1 = int(2.0 * FS)
    tri = np.abs(((np.arange(n1) / FS) * 2.0) % 2.0 - 1.0)             # 1 Hz triangle, 0…1
    env = np.linspace(1.0, 0.3, n1)
    u1 = 150.0 * (1.0 - tri) * env
    k = np.arange(int(1.2 * FS)) / FS
    rng = np.random.default_rng(3)
    f = np.arange(10.0, 4000.0, 10.0)
    ms = np.sum(np.sin(2 * np.pi * f[:, None] * k[None, :] + rng.uniform(0, 2 * np.pi, f.size)[:, None]), axis=0)
    u2 = 75.0 + 3.0 * ms / np.max(np.abs(ms))
    u = np.r_[u1, np.linspace(u1[-1], 75.0, 2000), u2]
    a = math.exp(-2 * math.pi * LAG_HZ / FS)
    u_amp = lfilter([1 - a], [1, -a], u, zi=[a * u[0]])[0]
    y = RelayPreisachPlant(noise_nm=0.5, seed=0).run(u_amp)
    return np.arange(u.size) / FS, u, y


@pytest.fixture(scope="module")
def record():
    return _record()


def _lag_Hz(model: ChainModel) -> float:
    real = [p for p in model.dynamics.poles() if abs(p.imag) < 1e-9 * max(1.0, abs(p))]
    return min(-p.real for p in real) / (2 * math.pi)


@pytest.mark.slow
def test_dynamics_from_the_voltage_find_the_amplifier_lag(record):
    """Measured: 609 Hz from the voltage; 1189 Hz through the static stages' output (the
    joint Preisach+creep fit's small-signal response folded into the dynamics, as in #24)."""
    t, u, y = record
    m = ChainModel.identify(t, u, y, structure="preisach+creep+dynamics",
                            dynamics_options={"n_modes": 0, "from": "voltage"})
    assert m.dynamics.fit_info["fitted_from"] == "voltage"
    assert abs(_lag_Hz(m) / LAG_HZ - 1) < 0.1


def test_dynamics_source_is_checked(record):
    t, u, y = record
    with pytest.raises(ModelError, match="from: 'current'; allowed voltage, static"):
        ChainModel.identify(t, u, y, structure="pi+dynamics", dynamics_options={"from": "current"})
    m = ChainModel.identify(t, u, y, structure="pi+dynamics", dynamics_options={"from": "static", "n_modes": 0})
    assert m.dynamics.fit_info["fitted_from"] == "static stages' output"


def _chirp_through_a_mode(fs: float = 10000.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A ±1 V chirp 1 Hz → 2 kHz around 75 V, and the output of a 90 nm/V scanner with a mode
    at 1200 Hz (ζ 0.02) and 1 nm of sensor noise."""
    from scipy.signal import bilinear

    t = np.arange(int(4.0 * fs)) / fs
    u = 75.0 + np.sin(2 * np.pi * (1.0 * t + (2000.0 - 1.0) / (2 * 4.0) * t ** 2))
    w = 2 * np.pi * 1200.0
    b, a = bilinear([w * w], [1.0, 2 * 0.02 * w, w * w], fs)
    y = 90.0 * 75.0 + lfilter(b, a, 90.0 * (u - 75.0)) + np.random.default_rng(0).normal(0.0, 1.0, u.size)
    return t, u, y


def test_a_static_output_that_does_not_resolve_the_small_signal_gives_way_to_the_voltage():
    """A hysteresis stage whose small-signal output moves in steps (a coarse Preisach grid
    behind a slow amplifier: lumpy-noisy from check.py's lab recording) is not what the
    scanner did; the output follows the voltage coherently over the whole chirp."""
    from afmctl.compensators.chain import _coherent_source, fit_dynamics_stage
    from afmctl.compensators.pi import PIModel

    t, u, y = _chirp_through_a_mode()
    steps = 90.0 * (np.round(u / 2.34) * 2.34)                # 2.34 V cells: a 64-level grid over 150 V
    x, source = _coherent_source(t, u, steps, y, 0, {"n_modes": "auto"})
    assert x is u and source.startswith("voltage (the output follows the static stages' output coherently up to ")
    smooth = 90.0 * u
    x, source = _coherent_source(t, u, smooth, y, 0, {})
    assert x is smooth and source == "static stages' output"
    # through the chain's stage: a linear "hysteresis" resolves the chirp, so the static source stays
    dyn = fit_dynamics_stage(PIModel(thresholds=[0.0], weights=[90.0]), None, t, u, y, 0, None)
    assert dyn.fit_info["fitted_from"] == "static stages' output"
    modes = [abs(p) / (2 * math.pi) for p in dyn.poles() if p.imag > 0]
    assert modes and abs(modes[0] / 1200.0 - 1.0) < 0.05
