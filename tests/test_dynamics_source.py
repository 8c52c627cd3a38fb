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
