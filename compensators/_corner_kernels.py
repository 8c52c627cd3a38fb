"""The Preisach fit's corner prefix sums (:func:`afmctl.compensators.preisach_identify._corner_prefix`):
a plain-Python reference and its numba twin.

:func:`corner_prefix_py` turns rows over the (L+1)² corners of the Preisach grid into rows
over its L(L+1)/2 cells, ``Φ[·, (i, j)] = Σ_{a ≥ i+1} Σ_{b ≤ j} M[·, (a, b)]`` (cells in
``np.tril_indices(L)`` order): the sum over ``a`` from the top down, then over ``b`` from 0
up, in the order numpy's two ``cumsum`` calls add them, so all three agree to the last bit
(tests/test_preisach_identify.py). ``corner_prefix_nb`` is the same source compiled with
``numba.njit(cache=True, nogil=True)``. The normal equations of a 64-level fit pass a
4225 × 4225 Gram matrix through it twice; numpy's cumsum over the reversed and transposed
views took ~0.35 s a fit, 6 s of the 47 s of ``identify --model auto`` on afmctl calibrate's
E-727 recording (#38).
"""
from __future__ import annotations

import numba
import numpy as np


def corner_prefix_py(M, L, out):
    """Write ``M·P`` into ``out`` (rows of ``M``: (L+1)² corners, row-major ``a·(L+1) + b``;
    rows of ``out``: the L(L+1)/2 cells); see the module docstring."""
    n1 = L + 1
    col = np.empty(n1)
    for r in range(M.shape[0]):
        for j in range(n1):
            col[j] = 0.0
        for i in range(L, 0, -1):
            for j in range(n1):
                col[j] += M[r, i * n1 + j]          # col[j] = Σ_{a ≥ i} M[a, j]
            acc = 0.0
            base = (i - 1) * i // 2                 # the cell (i − 1, 0)
            for j in range(i):
                acc += col[j]
                out[r, base + j] = acc
    return out


corner_prefix_nb = numba.njit(cache=True, nogil=True)(corner_prefix_py)
