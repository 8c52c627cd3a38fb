"""Nonnegative least squares on the normal equations: ``min ½ xᵀHx − bᵀx`` subject to
``x ≥ 0`` with ``H`` symmetric positive definite — what ``min ‖A x − c‖², x ≥ 0`` becomes
with ``H = AᵀA``, ``b = Aᵀc`` (the regularised Preisach fit forms exactly these).

Solved by block principal pivoting (Júdice & Pires 1994, as used for NNLS by Kim & Park,
"Fast nonnegative matrix factorization: an active-set-like method and comparisons", SIAM J.
Sci. Comput. 33(6), 2011, Algorithm 2): the KKT conditions ``y = Hx − b``, ``x ≥ 0``,
``y ≥ 0``, ``xᵀy = 0`` are met by guessing the set ``F`` of positive variables, solving
``H_FF x_F = b_F`` and exchanging every infeasible variable at once; a backup rule (after
three exchanges that did not reduce the number of infeasible variables, exchange only the
last one) makes it finite. Finite is not fast: on an ill-conditioned system (a 64-level
``preisach+creep`` fit on half of the real pea record, condition number 1.7e12) the block
exchanges stop gaining and the backup rule then fixes about one variable per full Cholesky
solve — some 700 solves, over a minute, where Lawson–Hanson takes 6.6 s; left to its budget
of ``5 n`` exchanges it ran for 14 minutes. So after :data:`_MAX_BACKUP_STEPS` single
exchanges, or :data:`_MAX_SOLVES` solves in all, the problem goes to Lawson–Hanson. Where Lawson–Hanson (``scipy.optimize.nnls``) adds one variable
per iteration — about 1200 on a 64-level Preisach grid — this needs 10–20 Cholesky solves:
0.68 s against 4.76 s for 2080 variables, and a whole 64-level ``preisach+creep``
identification 2× faster (``benchmarks/bench_nnls.py``, docs/BENCHMARKS.md).

With ``H`` positive definite the solution is unique, so both methods give the same ``x`` up
to rounding; ``scipy.optimize.nnls`` on ``H``'s Cholesky factor is the reference it is tested
against (``tests/test_nnls_gram.py``) and the fallback if the pivoting does not settle.
"""
from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

#: backup rule budget (Kim & Park: 3)
_BACKUP_TRIES = 3
#: single exchanges (the backup rule) before Lawson–Hanson takes over: each costs a whole
#: Cholesky solve and fixes one variable, which Lawson–Hanson does far more cheaply
_MAX_BACKUP_STEPS = 20
#: solves in all before Lawson–Hanson takes over (a well-posed fit needs 10–20)
_MAX_SOLVES = 100


def nnls_gram(H: np.ndarray, b: np.ndarray, *, max_iter: int | None = None) -> np.ndarray:
    """The ``x ≥ 0`` minimising ``½ xᵀHx − bᵀx`` for symmetric positive definite ``H`` (n, n)
    and ``b`` (n,). Block principal pivoting; ``scipy.optimize.nnls`` on the Cholesky factor
    when it has not settled within ``max_iter`` solves (default :data:`_MAX_SOLVES`) or
    :data:`_MAX_BACKUP_STEPS` single exchanges (module docstring)."""
    H = np.asarray(H, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    n = b.shape[0]
    if H.shape != (n, n):
        raise ValueError(f"nnls_gram: H must be ({n}, {n}), got {H.shape}")
    x, solves = _block_pivoting(H, b, _MAX_SOLVES if max_iter is None else max_iter)
    if x is None:
        log.info("nnls_gram: block pivoting did not settle in %d solves (%d variables); Lawson-Hanson on the "
                 "Cholesky factor", solves, n)
        return reference_nnls(H, b)
    log.debug("nnls_gram: %d variables, %d solves", n, solves)
    return x


def _block_pivoting(H: np.ndarray, b: np.ndarray, max_solves: int) -> tuple[np.ndarray | None, int]:
    """``(x, solves)``; ``x`` None when it did not settle within ``max_solves`` solves or
    :data:`_MAX_BACKUP_STEPS` single exchanges (or a block was not positive definite)."""
    from scipy.linalg import LinAlgError, cho_factor, cho_solve
    n = b.shape[0]
    tol = 1e-12 * max(1.0, float(np.max(np.abs(b))) if n else 1.0)
    passive = np.zeros(n, dtype=bool)
    x = np.zeros(n)
    y = -b.copy()
    best, tries, single = n + 1, _BACKUP_TRIES, 0
    for solves in range(max_solves + 1):
        infeasible = (passive & (x < -tol)) | (~passive & (y < -tol))
        count = int(np.count_nonzero(infeasible))
        if count == 0:
            return np.maximum(x, 0.0), solves
        if solves == max_solves or single == _MAX_BACKUP_STEPS:
            break
        if count < best:
            best, tries = count, _BACKUP_TRIES
            passive ^= infeasible
        elif tries > 0:
            tries -= 1
            passive ^= infeasible
        else:                                  # backup rule: only the last infeasible variable
            single += 1
            k = int(np.flatnonzero(infeasible)[-1])
            passive[k] = not passive[k]
        x = np.zeros(n)
        if passive.any():
            try:
                x[passive] = cho_solve(cho_factor(H[np.ix_(passive, passive)]), b[passive])
            except LinAlgError:
                return None, solves + 1
        y = H @ x - b
        y[passive] = 0.0
    return None, solves


def reference_nnls(H: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The same problem by Lawson–Hanson: ``scipy.optimize.nnls(R, z)`` with ``RᵀR = H``,
    ``Rᵀz = b`` (``‖R x − z‖² = xᵀHx − 2bᵀx + const``)."""
    from scipy.linalg import cholesky, solve_triangular
    from scipy.optimize import nnls
    R = cholesky(H, lower=False)
    z = solve_triangular(R, b, trans="T", lower=False)
    x, _ = nnls(R, z, maxiter=50 * b.shape[0])
    return x
