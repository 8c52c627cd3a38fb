"""Jumps of a recorded command and the transients after them (compensators/record_steps.py),
and the Preisach fit that leaves those samples out (``exclude``)."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.compensators.base import ModelError
from afmctl.compensators.chain import ChainModel
from afmctl.compensators.preisach import PreisachModel
from afmctl.compensators.record_steps import STEP_SETTLE_S, jumps, step_transients
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
