"""The Preisach grid's two representations and the maps between them (eq. 7 of seeds/003,
Zhang et al.): node Everett values ``G[a, b] = E(v_a, v_b)`` [nm] on the lower triangle of an
``(L + 1) × (L + 1)`` grid, and cell masses ``w[i, j]`` [nm] (hysteron weights) on the lower
triangle of ``L × L``. Shared by the model (:mod:`afmctl.compensators.preisach`) and its
identification (:mod:`afmctl.compensators.preisach_identify`), which therefore need not import
each other both ways."""
from __future__ import annotations

import numpy as np


def nodes_from_cell_masses(w: np.ndarray) -> np.ndarray:
    """Lower-triangular node Everett values E(v_a, v_b) = Σ_{b ≤ j ≤ i < a} w[i, j]."""
    L = w.shape[0]
    w = np.tril(w)
    # C[a, j] = Σ_{i < a} w[i, j]; then E(a, b) = Σ_{j ≥ b, j < a} C[a, j]
    C = np.zeros((L + 1, L))
    C[1:] = np.cumsum(w, axis=0)
    G = np.zeros((L + 1, L + 1))
    # reverse cumulative over j
    R = np.cumsum(C[:, ::-1], axis=1)[:, ::-1]  # R[a, b] = Σ_{j ≥ b} C[a, j]
    G[:, :L] = R
    G = np.tril(G, -1)
    return G


def cell_masses_from_nodes(G: np.ndarray) -> np.ndarray:
    """Cell masses from lower-triangular node values (inverse of :func:`nodes_from_cell_masses`)."""
    L = G.shape[0] - 1
    Gl = np.tril(G, -1)
    w = np.full((L, L), np.nan)
    if L == 0:
        return w
    # w[i, j] = E(i+1, j) − E(i, j) − E(i+1, j+1) + E(i, j+1) (lower-tri values, 0 on/above diag)
    d = Gl[1:, :-1] - Gl[:-1, :-1] - Gl[1:, 1:] + Gl[:-1, 1:]
    il = np.tril_indices(L)
    w[il] = d[il]
    return w
