"""The streaming-operator contract, checked the same way for every operator of the PI,
extended-PI, linear-creep, Preisach and Bouc–Wen models:

* ``block`` over any split of a signal == one ``block`` == per-sample ``step``, bit for bit
  (hypothesis chooses the signal, its dwells and the cut points);
* ``reset()`` restores the initial state exactly (a reset operator and a fresh one give
  identical outputs on a new signal);
* bad samples (NaN/inf, 0-d or 2-D arrays, text) are a ``ModelError`` naming the input;
  ints, float32, strided and read-only arrays, and empty blocks work;
* the Preisach output equals an independent relay (hysteron) sum for inputs on the grid
  nodes (eqs. 3 and 8 of the image-based paper), and its memory stays bounded.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.compensators.base import ModelError
from afmctl.compensators.bouc_wen import BoucWenModel
from afmctl.compensators.creep import LinearCreepModel
from afmctl.compensators.epi import EPIModel
from afmctl.compensators.models import model_from_dict
from afmctl.compensators.pi import PIModel
from afmctl.compensators.play import PlayOperator
from afmctl.compensators.preisach import PreisachModel, ReferencePreisach
from afmctl.compensators.rate_bouc_wen import RateBoucWenModel
from afmctl.compensators.rate_pi import RatePIModel

DT = 1e-3
PI = PIModel(thresholds=[0.0, 6.0, 15.0, 30.0, 45.0], weights=[60.0, 12.0, -4.0, 9.0, 5.0], offset_nm=-30.0)
EPI = EPIModel(thresholds=[0.0, 6.0, 15.0, 30.0, 45.0], weights=[60.0, 12.0, -4.0, 9.0, 5.0], offset_nm=-30.0,
               creep_a_nm=40.0, creep_b=1.01, creep_lambda_per_s=20.0)
CREEP = LinearCreepModel(gain_nm_per_V=90.0, offset_nm=5.0, initial_V=10.0, time_constants_s=[0.01, 0.2],
                         creep_weights=[0.03, 0.05])
PRE = PreisachModel.from_density(lambda a, b: 1.0 + 0.02 * (a - b) + 0.5 * np.exp(-((a - 90) ** 2 + (b - 30) ** 2) / 900),
                                 0.0, 150.0, 16, offset_nm=12.0)
PRE_SMALL_MEMORY = PreisachModel(**{**PRE.model_dump(), "memory_depth": 3})
RPI = RatePIModel(thresholds=[0.0, 6.0, 15.0, 30.0, 45.0], weights=[60.0, 12.0, -4.0, 9.0, 5.0], offset_nm=-30.0,
                  initial_state=[40.0] * 5, rate_gain_s_per_V=2e-4, rate_tau_s=0.004)
BW = BoucWenModel(d_nm_per_V=100.0, A_nm_per_V=30.0, beta=0.004, gamma=0.0015, n=1.2)
RBW = RateBoucWenModel(**BW.model_dump(exclude={"kind"}), rate_gain_s_per_V=2e-5, rate_max_V_per_s=2e4,
                       rate_tau_s=0.004)

#: name -> (factory, (lo, hi) of sensible inputs)
OPERATORS = {
    "play": (lambda: PlayOperator(7.5, initial_state=40.0), (0.0, 150.0)),
    "pi.forward": (lambda: PI.forward(), (0.0, 150.0)),
    "pi.inverse": (lambda: PI.inverse(), (-30.0, 11000.0)),
    "epi.forward": (lambda: EPI.forward(DT), (0.0, 150.0)),
    "epi.inverse": (lambda: EPI.inverse(DT), (-30.0, 11000.0)),
    "creep.forward": (lambda: CREEP.forward(DT), (0.0, 150.0)),
    "creep.inverse": (lambda: CREEP.inverse(DT), (0.0, 13000.0)),
    "preisach.forward": (lambda: PRE.forward(), (0.0, 150.0)),
    "preisach.inverse": (lambda: PRE.inverse(), (PRE.output_range_nm())),
    "preisach3.forward": (lambda: PRE_SMALL_MEMORY.forward(), (0.0, 150.0)),
    "preisach3.inverse": (lambda: PRE_SMALL_MEMORY.inverse(), (PRE.output_range_nm())),
    "bouc-wen.forward": (lambda: BW.forward(), (0.0, 150.0)),
    "bouc-wen.inverse": (lambda: BW.inverse(), (0.0, 14000.0)),
    "rate-pi.forward": (lambda: RPI.forward(DT), (0.0, 150.0)),
    "rate-pi.inverse": (lambda: RPI.inverse(DT), (-30.0, 11000.0)),
    "rate-bouc-wen.forward": (lambda: RBW.forward(DT), (0.0, 150.0)),
    "rate-bouc-wen.inverse": (lambda: RBW.inverse(DT), (0.0, 14000.0)),
}

# a signal: levels in [0, 1] (scaled to the operator's range), each held for 1–30 samples
# (dwells matter for the creep models), and the cut points of a block split
plans = st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(1, 30)), min_size=1, max_size=25)
cuts = st.lists(st.integers(0, 400), max_size=8)


def _signal(plan, lo: float, hi: float) -> np.ndarray:
    return np.concatenate([np.full(n, lo + (hi - lo) * v) for v, n in plan])


@pytest.mark.parametrize("name", sorted(OPERATORS))
@settings(max_examples=25, deadline=None)
@given(plan=plans, cut=cuts, plan2=plans)
def test_block_split_step_and_reset_are_bit_exact(name, plan, cut, plan2):
    make, (lo, hi) = OPERATORS[name]
    x = _signal(plan, lo, hi)
    op = make()
    whole = op.block(x)
    op.reset()
    steps = np.array([op.step(v) for v in x.tolist()])
    np.testing.assert_array_equal(whole, steps)
    op.reset()
    pieces = [op.block(p) for p in np.split(x, sorted(c for c in cut if c <= x.size))]
    np.testing.assert_array_equal(np.concatenate(pieces), whole)
    # reset restores the initial state exactly: same as a fresh operator on a new signal
    x2 = _signal(plan2, lo, hi)
    op.reset()
    np.testing.assert_array_equal(op.block(x2), make().block(x2))


@pytest.mark.parametrize("name", sorted(OPERATORS))
def test_bad_samples_are_model_errors_and_odd_arrays_work(name):
    make, (lo, hi) = OPERATORS[name]
    x = np.linspace(lo, hi, 24)
    ref = make().block(x)
    for bad in (np.array([lo, np.nan]), np.array([lo, np.inf]), np.array(lo), np.full((3, 2), lo)):
        with pytest.raises(ModelError, match="u_V|y_nm|input"):
            make().block(bad)
    for bad in (float("nan"), float("-inf"), "x", np.array([1.0, 2.0])):
        with pytest.raises(ModelError, match="u_V|y_nm|input"):
            make().step(bad)
    empty = make().block(np.array([]))
    assert empty.shape == (0,) and empty.dtype == np.float64
    wide = np.linspace(lo, hi, 48)
    ro = x.copy()
    ro.flags.writeable = False
    np.testing.assert_array_equal(make().block(wide[::2]), make().block(np.ascontiguousarray(wide[::2])))
    np.testing.assert_array_equal(make().block(ro), ref)
    np.testing.assert_array_equal(make().block(list(x)), ref)
    xi = np.round(x).astype(np.int32)
    np.testing.assert_array_equal(make().block(xi), make().block(xi.astype(np.float64)))
    # a rejected sample leaves the state untouched
    op = make()
    op.block(x[:10])
    with pytest.raises(ModelError):
        op.block(np.array([x[10], np.nan]))
    np.testing.assert_array_equal(op.block(x[10:]), ref[10:])


# ------------------------------------------------------------------ Preisach vs relays ---

def _relay_output(model: PreisachModel, idx: list[int]) -> list[float]:
    """Independent evaluation of eq. 3: cell (i, j) of the grid is a relay that switches up
    when the input reaches node i+1 and down when it falls to node j (inputs on nodes only),
    starting from negative saturation (all relays down)."""
    w = np.nan_to_num(model.cell_masses())
    L = model.levels
    on = np.zeros((L, L), dtype=bool)
    lower = np.tril(np.ones((L, L), dtype=bool))
    out = []
    for k in idx:
        on |= lower & (np.arange(L)[:, None] + 1 <= k)          # α-node i+1 ≤ u
        on &= ~(lower & (np.arange(L)[None, :] >= k))           # β-node j ≥ u
        out.append(model.offset_nm + float(np.sum(w[on])))
    return out


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 16), min_size=1, max_size=60))
def test_preisach_equals_relay_sum_on_grid_nodes(idx):
    v = PRE.nodes_V()
    y = PRE.forward().block(v[idx])
    np.testing.assert_allclose(y, _relay_output(PRE, idx), rtol=0, atol=1e-9 * PRE.everett_nm[-1][0])


def test_preisach_memory_bound_is_enforced():
    # ever smaller nested loops: the ideal model would remember every reversal
    ext = 75.0 + 75.0 * np.array([(-0.8) ** k for k in range(40)])
    big = PreisachModel(**{**PRE.model_dump(), "memory_depth": 1000})
    f = big.forward()
    f.block(ext)
    assert len(f.memory_V()) == 41                     # unbounded without the cap
    small = PRE_SMALL_MEMORY.forward()
    y = np.array([small.step(v) for v in ext])
    depth = []
    small.reset()
    for v in ext:
        small.step(v)
        depth.append(int(small.ist[0]))                # remembered pairs after each sample
    assert max(depth) == PRE_SMALL_MEMORY.cap          # reaches the bound, never beyond
    ref = ReferencePreisach(PRE_SMALL_MEMORY)
    np.testing.assert_array_equal(y, ref.forward(ext))
    inv = PRE_SMALL_MEMORY.inverse()
    inv.block(y)
    assert int(inv.ist[0]) <= PRE_SMALL_MEMORY.cap


# ------------------------------------------------------------------- Bouc–Wen extremes ---

def test_bouc_wen_huge_steps_and_stiff_models_stay_finite():
    x = np.array([0.0, 1e12, -1e300, 1e300, 50.0])
    y = BW.forward().block(x)
    assert np.all(np.isfinite(y))
    assert abs(BW.forward().block(x)[-1] - BW.forward().block(np.array([1e300, 50.0]))[-1]) < 1e-9 * 15000
    stiff = BoucWenModel(d_nm_per_V=100.0, A_nm_per_V=30.0, beta=1e4, gamma=0.0)   # h saturates at 3 pm
    u = np.array([0.0, 25.0, 5.0])                     # 25 V = 2.5e6 sub-steps: capped
    ys = stiff.forward().block(u)
    assert np.all(np.isfinite(ys))
    np.testing.assert_allclose(ys[1:], 100.0 * u[1:] + np.array([-1, 1]) * stiff.h_max_nm(), rtol=1e-12)


# --------------------------------------------------------------------- model files ------

@pytest.mark.parametrize("data, field", [
    ({"kind": "pi", "thresholds": list(range(1001)), "weights": [1.0] * 1001}, "thresholds"),
    ({"kind": "creep", "gain_nm_per_V": 1.0, "time_constants_s": [1.0] * 1001, "creep_weights": [0.0] * 1001},
     "time_constants_s"),
    ({**PRE.model_dump(), "offset_nm": float("nan")}, "offset_nm"),
    ({**PRE.model_dump(), "u_max_V": float("inf")}, "u_max_V"),
    ({**PRE.model_dump(), "levels": 100000}, "levels"),
    ({**PRE.model_dump(), "offset_nm": 1e300}, "offset_nm"),
    ({**PRE.model_dump(), "memory_depth": 0}, "memory_depth"),
    ({**PRE.model_dump(), "kind": "bouc-wen"}, "d_nm_per_V|Extra inputs"),
    ({**PI.model_dump(), "kind": "preisach"}, "everett_nm|Extra inputs"),
    ({**BW.model_dump(), "beta": -1.0}, "beta"),
    ({**RPI.model_dump(), "rate_tau_s": 0.0}, "rate_tau_s"),
    ({**RPI.model_dump(), "rate_gain_s_per_V": -1e-4}, "rate_gain_s_per_V"),
    ({**RPI.model_dump(), "weights": [-1.0, 1.0, 1.0, 1.0, 1.0]}, "weights"),
])
def test_model_file_edge_cases_name_the_field(data, field):
    with pytest.raises(ModelError, match=field):
        model_from_dict(data, where="m.json")
