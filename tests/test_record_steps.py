"""Jumps of a recorded command and the transients after them (compensators/record_steps.py),
and the Preisach fit that leaves those samples out (``exclude``)."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.compensators.base import ModelError
from afmctl.compensators.chain import ChainModel
from afmctl.compensators.preisach import PreisachModel
from afmctl.compensators.record_steps import (STEP_SETTLE_S, UNEXPLAINED_MARGIN, UNEXPLAINED_WINDOW_S, jumps,
                                              step_transients, unexplained)
from plants import RelayPreisachPlant, triangle

FS = 5000.0


def pieced_record() -> np.ndarray:
    """Two waveforms joined as a lab pieces them: 1 Hz triangles over 0..150 V, then 10 Hz
    triangles over 30..120 V starting at once at 30 V (a 30 V jump), then a ramp back."""
    t1 = np.arange(int(2 * FS)) / FS
    t2 = np.arange(int(1 * FS)) / FS
    return np.concatenate([triangle(t1, 1.0, 0.0, 150.0), triangle(t2, 10.0, 30.0, 120.0), np.linspace(30.0, 0.0, 500)])


def test_a_join_between_waveforms_is_one_jump():
    u = pieced_record()
    assert jumps(u).tolist() == [int(2 * FS)]
    mask = step_transients(u, 1.0 / FS)
    assert np.flatnonzero(mask).tolist() == list(range(int(2 * FS), int(2 * FS) + int(round(STEP_SETTLE_S * FS))))


def test_fast_waveforms_within_the_slew_rate_have_no_jumps():
    t = np.arange(int(2 * FS)) / FS
    chirp = 75.0 + 10.0 * np.sin(2 * np.pi * (np.exp(np.log(500.0) * t / 2.0) - 1.0) * 2.0 / np.log(500.0))
    assert jumps(chirp).size == 0
    assert jumps(triangle(t, 40.0, 10.0, 140.0)).size == 0
    assert jumps(np.zeros(100)).size == 0 and jumps(np.array([0.0, 1.0])).size == 0


def test_the_chain_leaves_the_transient_after_a_jump_out_of_its_static_fit():
    """After the jump the recorded output is still on its way (slew, lag): a preisach+creep
    fit that takes those samples at face value explains them as creep (the plant has none);
    the chain leaves them out by itself and fits what the clean record gives. An all-False
    ``exclude`` keeps every sample (the behaviour without the mask)."""
    u = pieced_record()
    t = np.arange(u.size) / FS
    y = RelayPreisachPlant(noise_nm=0.0, seed=3).run(u)
    mask = step_transients(u, 1.0 / FS)
    late = y.copy()
    late[mask] -= 1500.0 * np.exp(-np.arange(int(mask.sum())) / (0.01 * FS))

    def fit(y_nm, **kw):
        m = ChainModel.identify(t, u, y_nm, structure="preisach+creep", n_operators=16, **kw)
        err = float(np.sqrt(np.mean((m.forward(1.0 / FS).block(u) - y)[~mask] ** 2)))
        return float(sum(m.creep.creep_weights)), err

    creep_clean, err_clean = fit(y)
    creep_all, err_all = fit(late, exclude=np.zeros(u.size, bool))
    creep_kept, err_kept = fit(late)
    assert creep_clean < 0.01 and creep_kept < 0.01 < 0.05 < creep_all
    assert err_kept <= 1.02 * err_clean + 0.5 < err_all


@pytest.mark.parametrize("exclude, why", [(np.zeros(5, bool), "one boolean per sample"),
                                          ("every", "every sample is left out")])
def test_a_bad_exclude_mask_is_one_clear_error(exclude, why):
    u = pieced_record()
    t = np.arange(u.size) / FS
    if isinstance(exclude, str):
        exclude = np.ones(u.size, bool)
    with pytest.raises(ModelError, match=why):
        PreisachModel.identify(t, u, u * 50.0, n_operators=8, method="nnls", exclude=exclude)


def _noise_and_burst(amp_nm: float, windows: range, dt: float = 1e-4, n_windows: int = 100,
                     gap: int | None = None) -> np.ndarray:
    """1 nm RMS noise (seeded) over ``n_windows`` windows, and a 2.5 kHz ringing of ``amp_nm``
    in ``windows`` (none in window ``gap``)."""
    w = int(round(UNEXPLAINED_WINDOW_S / dt))
    r = np.random.default_rng(7).normal(0.0, 1.0, n_windows * w)
    t = np.arange(r.size) * dt
    for k in windows:
        if k != gap:
            r[k * w:(k + 1) * w] += amp_nm * np.sin(2 * np.pi * 2500.0 * t[k * w:(k + 1) * w])
    return r


def test_unexplained_marks_the_large_windows_their_gaps_and_margins():
    dt, w = 1e-4, int(round(UNEXPLAINED_WINDOW_S / 1e-4))
    mask = unexplained(_noise_and_burst(50.0, range(40, 52), gap=45), dt, span_nm=10_000.0)
    m = UNEXPLAINED_MARGIN
    assert np.flatnonzero(mask).tolist() == list(range((40 - m) * w, (52 + m) * w))


@pytest.mark.parametrize("amp_nm, windows, why", [
    (5.0, range(40, 52), "below 0.1 % of the span (the floor for a noise-free record)"),
    (50.0, range(10, 40), "more than a fifth of the record: the model is wrong, not the record"),
])
def test_unexplained_marks_nothing(amp_nm, windows, why):
    assert not unexplained(_noise_and_burst(amp_nm, windows), 1e-4, span_nm=10_000.0).any(), why


def test_the_chain_leaves_out_only_what_rings_above_its_dynamics_band():
    """A residual at 2.5 kHz, above the 1 kHz the dynamics were identified to, is out of the
    chain's reach and is left out of the static refit; a slow misfit of the same size (what a
    rate-dependent loop leaves) is the static stages' to fit and stays in."""
    from afmctl.compensators.chain import _unexplained_by
    from afmctl.compensators.dynamics import LinearDynamicsModel
    from afmctl.compensators.pi import PIModel

    dt, w = 1e-4, int(round(UNEXPLAINED_WINDOW_S / 1e-4))
    dyn = LinearDynamicsModel.from_modes([(500.0, 0.05)]).model_copy(update={"fit_info": {"f_max_Hz": 1000.0}})
    model = ChainModel(hysteresis=PIModel(thresholds=[0.0, 10.0], weights=[70.0, 10.0]), dynamics=dyn)
    t = np.arange(100 * w) * dt
    u = 75.0 + 60.0 * np.sin(2 * np.pi * 1.0 * t)
    y = model.forward(dt).block(u) - _noise_and_burst(50.0, range(40, 52))
    y[70 * w:82 * w] += 50.0 * np.sin(2 * np.pi * 40.0 * t[70 * w:82 * w])   # slow: 40 Hz
    span = float(np.ptp(y))
    mask = _unexplained_by(model, model.forward(dt).block(u) - y, dt, 0, None, span)
    m = UNEXPLAINED_MARGIN
    assert mask[(40 - m) * w:(52 + m) * w].all() and mask.sum() == (12 + 2 * m) * w
    # the same model with no band recorded: nothing can be said to lie above it
    bare = model.model_copy(update={"dynamics": LinearDynamicsModel.from_modes([(500.0, 0.05)])})
    assert not _unexplained_by(bare, bare.forward(dt).block(u) - y, dt, 0, None, span).any()
