"""Identification of the discrete classical Preisach model from (u [V], y [nm]) data.

Two methods (``method=``):

``"for"`` — first-order reversal curves (image-based paper, Sec. 3.1 / eq. 7): the data
    ascend from ``u_min`` to a reversal value α and descend again (one curve per α, any
    number of curves). The Everett values ``E(α, β) = f_α − f_αβ`` at the grid nodes are
    read off the curves (linear interpolation along each curve; between curves in α when
    the reversal points are not on nodes), then projected onto the nearest model with
    nonnegative cell masses (NNLS), so that the inverse exists.

``"nnls"`` — regularised nonnegative least squares from any rich excitation: the output is
    linear in the cell masses ``w ≥ 0`` (eq. 3 discretised; with eq. 7 interpolation), so
    ``y ≈ y0 + Φ(u)·w``. The normal equations are accumulated over chunks of samples (the
    memory of every sample is traced by the compiled kernel), a smoothness penalty on the
    cell densities (weight ``smoothing``) regularises cells the data barely excite, and the
    nonnegative solution is found by block principal pivoting on the normal equations
    (:mod:`.nnls_gram`; ``scipy.optimize.nnls`` is its tested reference).

``"auto"`` (default) uses ``"for"`` when every ascending run of the data starts at the
bottom of the range and the curves cover the grid, otherwise ``"nnls"``.

Grid size: up to 512 levels with ``"for"``; up to 64 with ``"nnls"`` (the dense normal
equations grow as (L²/2)²).

The fit residual (RMS and max, nm) of the final model on the data is stored in the model
(``fit_residual_nm``, ``fit_max_residual_nm``) and shown by ``summary()``.
"""
from __future__ import annotations

import logging
import math
from typing import Any, cast

import numpy as np

from .base import ModelError, check_finite
from .input_checks import exclude_mask, number_option
from .nnls_gram import nnls_gram
from .preisach_grid import cell_masses_from_nodes

log = logging.getLogger(__name__)

#: weight of the smoothness penalty on the off-diagonal cell masses (relative to the mean
#: diagonal of the normal equations; :func:`_smoothness`). Measured on the user-style
#: records of three unseen plants (static part, raster at 1 line/s, max % of the line) and
#: on minor loops after full-range sines (relay plant, nm RMS): 3e-3 0.51 / 0.39 / 0.25 %,
#: 109 nm; 1e-2 0.33 / 0.40 / 0.15 %, 128 nm; 3e-2 0.28 / 0.47 / 0.23 %, 166 nm (PI 252 nm)
SMOOTHING = 1e-2
#: relative weight of the ridge that pulls the cell masses towards the prior (a fraction of
#: the mean diagonal of the normal equations: negligible in the directions the data determine,
#: decisive in those they do not). Measured: minor loops predicted from full-range sines
#: 128 nm RMS (PI 252, no prior 184; relay plant, 14.5 µm span; 146 / 252 / 303 before the
#: smoothing left the diagonal cells alone); a rich noise-free record kept its 0.11 % max
#: error (0.30 % at 1e-3)
PRIOR_WEIGHT = 1e-4
#: priors of the nnls fit: "pi" (the PI model identified on the same data, as a Preisach
#: density) or "none" (the smoothness penalty alone)
PRIORS: tuple[str, ...] = ("pi", "none")
#: relative ridge weight in the cells no reversal of the record reached
#: (:func:`visited_cells`): there the data say nothing and the prior decides
UNVISITED_PRIOR_WEIGHT = 1e-2
#: the same where the record has no minor loops (reversals inside the range,
#: :class:`~afmctl.compensators.coverage.Coverage`): full-range cycles fix only the plane's row
#: and column sums, its inside is the prior's (#36). Measured on three reference scanners
#: identified on 1 Hz full-range sines and validated on nested loops (nm RMS, PI alone 47.7 /
#: 154.7): 1e-2 69.8 / 38.6, 0.05 51.5 / 38.3, 0.1 47.6 / 39.8, 0.3 44.5 / 44.2, 1 43.0 / 54.2
#: (a generalised-PI plant and a lumpy Preisach plane; their fit RMS unchanged)
NO_MINOR_LOOPS_PRIOR_WEIGHT = 0.1
#: distance [cells] from the nearest visited cell at which the prior takes its full weight
#: in the unvisited ones (it grows as the distance squared): between the reversal curves of
#: a rich record the smoothing interpolates, far inside a plane that only full-range cycles
#: bounded the prior decides
PRIOR_REACH_CELLS = 8.0
#: threshold bins of the prior's density (equal widths in r = (α − β)/2)
PRIOR_BINS = 12

#: largest grid for the NNLS fit and the exact nonnegative projection (memory ~ (L²/2)² doubles)
_NNLS_MAX_LEVELS = 64


def _check_data(t_s: Any, u_V: Any, y_nm: Any) -> tuple[np.ndarray, np.ndarray]:
    u = check_finite("u_V", u_V).reshape(-1)
    y = check_finite("y_nm", y_nm).reshape(-1)
    if u.shape != y.shape:
        raise ModelError(f"y_nm: length {y.shape[0]} differs from u_V length {u.shape[0]}; they must be equal")
    if t_s is not None:
        t = check_finite("t_s", t_s).reshape(-1)
        if t.shape != u.shape:
            raise ModelError(f"t_s: length {t.shape[0]} differs from u_V length {u.shape[0]}; they must be equal")
    if u.shape[0] < 10:
        raise ModelError(f"u_V: {u.shape[0]} samples; at least 10 are needed to identify a Preisach model")
    if not np.ptp(u) > 0:
        raise ModelError("u_V: the input never changes; identification needs an input that sweeps the range")
    return u, y


def identify_preisach(cls: Any, t_s: Any, u_V: Any, y_nm: Any, n_operators: int | None = None,
                      **options: Any) -> Any:
    """Fit ``cls`` (a :class:`~afmctl.compensators.preisach.PreisachModel`) to the data; see the
    module docstring. ``n_operators`` (or ``levels``) is the number of grid levels.
    ``fit_from_index`` (nnls only): samples before it only set the memory (a burn-in)."""
    return _identify(cls, t_s, u_V, y_nm, n_operators, **options)[0]


def identify_preisach_with_regressors(cls: Any, t_s: Any, u_V: Any, y_nm: Any, regressors: np.ndarray,
                                      n_operators: int | None = None, **options: Any) -> tuple[Any, np.ndarray]:
    """Fit ``y ≈ y0 + Φ(u)·w + regressors·c`` with cell masses ``w ≥ 0`` and ``c ≥ 0``
    jointly (method nnls): the model and ``c``. ``regressors`` has one row per sample, one
    column per extra term (e.g. the creep corrections of a Preisach + creep chain, in nm)."""
    Z = np.ascontiguousarray(check_finite("regressors", regressors), dtype=float)
    if Z.ndim != 2 or Z.shape[0] != np.asarray(u_V).size:
        raise ModelError(f"regressors: need one row per sample ({np.asarray(u_V).size}), got shape {Z.shape}")
    return _identify(cls, t_s, u_V, y_nm, n_operators, method="nnls", regressors=Z, **options)


def _identify(cls: Any, t_s: Any, u_V: Any, y_nm: Any, n_operators: int | None = None, *,
              u_min_V: float | None = None, u_max_V: float | None = None, method: str = "auto",
              smoothing: float = SMOOTHING, max_rows: int = 200000, memory_depth: int | None = None,
              levels: int | None = None, fit_from_index: int = 0,
              regressors: np.ndarray | None = None, prior: str = "pi",
              prior_weight: float = PRIOR_WEIGHT, exclude: np.ndarray | None = None) -> tuple[Any, np.ndarray]:
    u, y = _check_data(t_s, u_V, y_nm)
    skip = exclude_mask(exclude, u.size)
    L = n_operators if n_operators is not None else (levels if levels is not None else 32)
    if isinstance(L, bool) or not isinstance(L, (int, np.integer)) or not 1 <= int(L) <= 512:
        raise ModelError(f"n_operators: number of Preisach levels must be an integer in 1..512, got {L!r}")
    L = int(L)
    lo = float(np.min(u)) if u_min_V is None else number_option("u_min_V", u_min_V)
    hi = float(np.max(u)) if u_max_V is None else number_option("u_max_V", u_max_V)
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        raise ModelError(f"u_max_V: must be > u_min_V (got u_min_V={lo}, u_max_V={hi})")
    if method not in ("auto", "for", "nnls"):
        raise ModelError(f"method: {method!r} is not known; allowed: auto, for, nnls")
    if not (isinstance(smoothing, (int, float)) and smoothing >= 0 and math.isfinite(smoothing)):
        raise ModelError(f"smoothing: must be a finite number >= 0, got {smoothing!r}")
    if not isinstance(max_rows, (int, np.integer)) or max_rows < 10:
        raise ModelError(f"max_rows: must be an integer >= 10, got {max_rows!r}")
    if prior not in PRIORS:
        raise ModelError(f"prior: {prior!r} is not known; allowed: {', '.join(PRIORS)}")
    if not (isinstance(prior_weight, (int, float)) and 0 <= prior_weight <= 1e3 and math.isfinite(prior_weight)):
        raise ModelError(f"prior_weight: must be a number in 0 … 1000, got {prior_weight!r}")
    if memory_depth is not None and (not isinstance(memory_depth, (int, np.integer)) or memory_depth < 2):
        raise ModelError(f"memory_depth: must be an integer >= 2, got {memory_depth!r}")
    n_out = int(np.count_nonzero((u < lo) | (u > hi)))
    if n_out:
        log.warning("identify: %d sample(s) of u_V outside %g…%g V are clamped to the grid", n_out, lo, hi)
        u = np.clip(u, lo, hi)
    fit_from_index = number_option("fit_from_index", fit_from_index, lo=0, hi=u.size - 10, integer=True)
    if (fit_from_index or skip is not None) and method == "auto":
        method = "nnls"  # reversal curves from u_min are read from the start of the data
    cap = int(memory_depth) if memory_depth is not None else 2 * L + 2
    fields = {"memory_depth": memory_depth} if memory_depth is not None else {}

    chosen = method
    G: Any = None
    y0 = None
    if method in ("auto", "for"):
        try:
            G, y0 = _for_nodes(u, y, lo, hi, L)
            chosen = "for"
        except ModelError:
            if method == "for":
                raise
            chosen = "nnls"
    if chosen == "nnls" and L > _NNLS_MAX_LEVELS:
        raise ModelError(f"n_operators: {L} levels is too many for method=nnls (dense normal equations); "
                         f"allowed: 1..{_NNLS_MAX_LEVELS}, or first-order reversal data with method=for")
    coef = np.zeros(0)
    if chosen == "for":
        w = _project_nonneg(G)
        model = cls.from_cell_masses(w, lo, hi, y0, fit_method="first-order reversal curves", **fields)
    else:
        w, y0, coef = _nnls_fit(u, y, lo, hi, L, cap, smoothing, max_rows, fit_from_index, regressors,
                                prior_weight if prior == "pi" else 0.0, skip, _unvisited_weight(u[fit_from_index:]))
        how = f"nnls (smoothing {smoothing:g}" + (f", PI prior {prior_weight:g})" if prior == "pi" else ")")
        model = cls.from_cell_masses(w, lo, hi, y0, fit_method=how, **fields)
    r = model.forward().block(u) - y
    if coef.size:
        r = r + cast(np.ndarray, regressors) @ coef
    r = r[fit_from_index:] if skip is None else r[fit_from_index:][~skip[fit_from_index:]]
    model.fit_residual_nm = float(np.sqrt(np.mean(r * r)))
    model.fit_max_residual_nm = float(np.max(np.abs(r)))
    log.info("identify preisach: %s, %d levels, residual %.4g nm RMS", model.fit_method, L, model.fit_residual_nm)
    return model, coef


# ------------------------------------------------------------------ first-order reversal curves
def _runs(u: np.ndarray) -> list[tuple[int, int]]:
    """Monotone runs [start, end] (inclusive) of u, ignoring flat steps."""
    d = np.diff(u)
    sgn = np.sign(d)
    runs: list[tuple[int, int]] = []
    start = 0
    cur = 0
    for k, sk in enumerate(sgn):
        if sk == 0:
            continue
        if cur == 0:
            cur = sk
        elif sk != cur:
            runs.append((start, k))
            start = k
            cur = sk
    runs.append((start, len(u) - 1))
    return runs


def _for_nodes(u: np.ndarray, y: np.ndarray, lo: float, hi: float, L: int) -> tuple[np.ndarray, float]:
    """Everett node values from first-order reversal curves; ModelError if the data are not FORCs."""
    span = hi - lo
    tol = 1e-6 * span + 1e-12
    v = lo + span * np.arange(L + 1) / L
    v[-1] = hi
    runs = _runs(u)
    curves = []  # (alpha, f_alpha, desc_u ascending order, desc_y)
    y0s = []
    asc_u: list[np.ndarray] = []
    asc_y: list[np.ndarray] = []
    for n, (a, b) in enumerate(runs):
        if u[b] <= u[a]:
            continue
        if u[a] > lo + tol:
            raise ModelError("data: an ascending run does not start at the bottom of the range; not first-order reversal curves")
        y0s.append(y[a])
        asc_u.append(u[a:b + 1])
        asc_y.append(y[a:b + 1])
        if n + 1 < len(runs):
            c, d = runs[n + 1]
            du_ = u[c:d + 1][::-1]
            dy_ = y[c:d + 1][::-1]
            curves.append((u[b], y[b], du_, dy_))
    if not curves or not y0s:
        raise ModelError("data: no first-order reversal curves found (ascend from u_min to α, descend to β)")
    y0 = float(np.mean(y0s))
    alphas = np.array([c[0] for c in curves])
    if alphas.max() < hi - tol:
        raise ModelError("data: the highest reversal point is below u_max_V; the curves do not cover the grid")
    inner = np.unique(np.round(alphas[(alphas > lo + 0.1 * span) & (alphas < hi - 0.1 * span)] / (span / L)))
    if inner.size < 2:
        raise ModelError("data: fewer than two reversal points inside the range; the curves leave the inside of "
                         "the grid unvisited (use method=nnls, which falls back to its prior there)")
    # E(v_i, v_0) from the ascending branches (longest first)
    G = np.full((L + 1, L + 1), np.nan)
    order = np.argsort([-len(a) for a in asc_u])
    for i in range(L + 1):
        G[i, i] = 0.0
    for i in range(1, L + 1):
        for k in order:
            au = asc_u[k]
            if au[-1] >= v[i] - tol:
                G[i, 0] = float(np.interp(v[i], au, asc_y[k])) - y0
                break
    # E(alpha_r, v_j) along each descending curve, then interpolate across alpha
    Ec = np.full((len(curves), L + 1), np.nan)
    for r, (alpha, fa, du_, dy_) in enumerate(curves):
        ok = (v >= du_[0] - tol) & (v <= alpha + tol)
        if np.any(ok):
            Ec[r, ok] = fa - np.interp(np.minimum(v[ok], alpha), du_, dy_)
    srt = np.argsort(alphas)
    alphas, Ec = alphas[srt], Ec[srt]
    for i in range(1, L + 1):
        for j in range(1, i):
            col = Ec[:, j]
            good = np.isfinite(col) & (alphas >= v[j] - tol)
            if not np.any(good):
                raise ModelError(f"data: no reversal curve covers alpha={v[i]:g} V, beta={v[j]:g} V; use method=nnls")
            # anchor E(β, β) = 0 on the diagonal, so α below the lowest reversal interpolates too
            aa, ee = np.r_[v[j], alphas[good]], np.r_[0.0, col[good]]
            if v[i] > aa[-1] + tol:
                raise ModelError(f"data: no reversal point at or above alpha={v[i]:g} V; use method=nnls")
            # near-duplicate alphas: average
            ua, inv = np.unique(np.round(aa / tol), return_inverse=True)
            am = np.bincount(inv, aa) / np.bincount(inv)
            em = np.bincount(inv, ee) / np.bincount(inv)
            G[i, j] = float(np.interp(v[i], am, em))
    if not np.all(np.isfinite(np.tril(G))):
        raise ModelError("data: first-order reversal curves do not cover the grid; use method=nnls")
    return np.tril(G, -1), y0


def _node_cell_matrix(L: int) -> np.ndarray:
    """M[node(a,b), cell(i,j)] = 1 if b ≤ j ≤ i < a (nodes a > b, cells i ≥ j, row-major)."""
    na = np.tril_indices(L + 1, -1)
    ci = np.tril_indices(L)
    a = na[0][:, None]
    b = na[1][:, None]
    i = ci[0][None, :]
    j = ci[1][None, :]
    return ((b <= j) & (j <= i) & (i < a)).astype(np.float64)


def _project_nonneg(G: np.ndarray) -> np.ndarray:
    """Nearest nonnegative cell masses (least squares on the node values)."""
    from scipy.optimize import nnls
    L = G.shape[0] - 1
    w = cell_masses_from_nodes(G)
    ci = np.tril_indices(L)
    if np.all(w[ci] >= 0):
        return np.where(np.isnan(w), 0.0, w)
    if L > _NNLS_MAX_LEVELS:
        log.warning("identify: %d levels; negative cell masses clipped to 0 instead of an exact NNLS projection", L)
        return np.where(np.isnan(w), 0.0, np.maximum(w, 0.0))
    M = _node_cell_matrix(L)
    e = G[np.tril_indices(L + 1, -1)]
    x, _ = nnls(M, e, maxiter=50 * M.shape[1])
    out = np.zeros((L, L))
    out[ci] = x
    return out


# ------------------------------------------------------------------ regularised NNLS
def _corner_terms(u: np.ndarray, rows: np.ndarray, lo: float, hi: float, L: int,
                  cap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The memory of each row as grid-corner terms ``(row, corner, value)``: corner
    ``a·(L+1) + b`` of the (L+1)² grid nodes, each memory pair spread bilinearly over the four
    nodes around it (eq. 7's interpolation) with its sign, the antisymmetric extension
    E(v_a, v_b) = −E(v_b, v_a) folding nodes above the diagonal below it. A row's output is
    ``Σ value · Σ_{cells (i, j): i < a, j ≥ b} w[i, j]`` (:func:`_prefix_matrix`)."""
    from . import _preisach_kernels as k
    R = rows.shape[0]
    plo = np.zeros((R, cap))
    phi = np.zeros((R, cap))
    psg = np.zeros((R, cap))
    pn = np.zeros(R, dtype=np.int64)
    k.memory_trace(np.ascontiguousarray(u), rows, lo, hi, cap, plo, phi, psg, pn)
    inv_du = L / (hi - lo)
    mask = np.arange(cap)[None, :] < pn[:, None]
    rr = np.broadcast_to(np.arange(R)[:, None], (R, cap))[mask]
    a, b, sg = phi[mask], plo[mask], psg[mask]
    x = (a - lo) * inv_du
    i = np.minimum(x.astype(np.int64), L - 1)
    fa = x - i
    z = (b - lo) * inv_du
    j = np.minimum(z.astype(np.int64), L - 1)
    fb = z - j
    out_r, out_c, out_v = [], [], []
    for di, dj, wt in ((0, 0, (1 - fa) * (1 - fb)), (1, 0, fa * (1 - fb)), (0, 1, (1 - fa) * fb), (1, 1, fa * fb)):
        ia, jb = i + di, j + dj
        upper = jb > ia
        out_r.append(rr)
        out_c.append(np.where(upper, jb, ia) * (L + 1) + np.where(upper, ia, jb))
        out_v.append(np.where(upper, -1.0, 1.0) * sg * wt)
    return np.concatenate(out_r), np.concatenate(out_c), np.concatenate(out_v)


def _prefix_matrix(L: int) -> np.ndarray:
    """P[corner, cell] = 1 where corner ``a·(L+1) + b`` reaches cell ``(i, j)`` (cells in
    ``np.tril_indices(L)`` order): ``a ≥ i + 1`` and ``b ≤ j``, so that Φ = N·P for the
    corner terms N of :func:`_corner_terms`."""
    ci = np.tril_indices(L)
    a = np.arange(L + 1)[:, None, None]
    b = np.arange(L + 1)[None, :, None]
    reach = (a >= ci[0][None, None, :] + 1) & (b <= ci[1][None, None, :])
    return reach.reshape((L + 1) ** 2, ci[0].size).astype(float)


def _features(u: np.ndarray, rows: np.ndarray, lo: float, hi: float, L: int, cap: int) -> np.ndarray:
    """Φ[r, cell]: d y(rows[r]) / d w[cell] (cells in np.tril_indices(L) order): the plain
    reference of the normal equations :func:`_normal_terms` accumulates (a dense corner
    array and its two prefix sums, :func:`_corner_prefix`, itself tested against the dense
    :func:`_prefix_matrix`)."""
    rr, corner, value = _corner_terms(u, rows, lo, hi, L, cap)
    flat = np.zeros((rows.shape[0], (L + 1) ** 2))
    np.add.at(flat, (rr, corner), value)
    return _corner_prefix(flat, L)


def _normal_terms(u: np.ndarray, rows: np.ndarray, yc: np.ndarray, lo: float, hi: float, L: int, cap: int,
                  extra: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(AᵀA, Aᵀyc, Σ_rows A)`` of the regressors ``A = [Φ | extra[rows]]`` (:func:`_features`)
    without forming Φ: with Φ = N·P for the sparse corner terms N (a few per memory pair),
    ΦᵀΦ = Pᵀ(NᵀN)P is accumulated on the (L+1)² corners. Chunks keep memory bounded."""
    from scipy import sparse
    n_corner = (L + 1) ** 2
    ne = 0 if extra is None else extra.shape[1]
    G = np.zeros((n_corner + ne, n_corner + ne))
    g = np.zeros(n_corner + ne)
    s = np.zeros(n_corner + ne)
    chunk = 20000
    for s0 in range(0, rows.shape[0], chunk):
        r = rows[s0:s0 + chunk]
        rr, corner, value = _corner_terms(u, r, lo, hi, L, cap)
        N = sparse.csr_matrix((value, (rr, corner)), shape=(r.shape[0], n_corner))
        if ne:
            N = sparse.hstack([N, sparse.csr_matrix(cast(np.ndarray, extra)[r])], format="csr")
        NtN = (N.T @ N).tocoo()                 # entries unique: added in place, no dense copy
        G[NtN.row, NtN.col] += NtN.data
        g += N.T @ yc[s0:s0 + chunk]
        s += np.asarray(N.sum(axis=0)).ravel()
    # Pᵀ·G·P, Pᵀ·g, Pᵀ·s as prefix sums over the corners (O(L⁴), where the product with the
    # dense P costs O(L⁶)); the extra regressors' rows and columns pass unchanged
    c = slice(0, n_corner)
    e = slice(n_corner, n_corner + ne)
    Gc = _corner_prefix_fast(np.ascontiguousarray(_corner_prefix_fast(G[c, c], L).T), L)
    cross = _corner_prefix(G[e, c], L)
    AtA = np.block([[Gc, cross.T], [cross, G[e, e]]])
    return (AtA, np.r_[_corner_prefix(g[None, c], L)[0], g[e]], np.r_[_corner_prefix(s[None, c], L)[0], s[e]])


def _corner_prefix(M: np.ndarray, L: int) -> np.ndarray:
    """``M·P`` for rows over the (L+1)² corners (:func:`_prefix_matrix`) by two prefix sums:
    Φ[·, (i, j)] = Σ_{a ≥ i+1} Σ_{b ≤ j} M[·, (a, b)]."""
    S = M.reshape(M.shape[0], L + 1, L + 1)
    S = np.cumsum(S[:, ::-1, :], axis=1)[:, ::-1, :]
    S = np.cumsum(S, axis=2)
    ci = np.tril_indices(L)
    return S[:, ci[0] + 1, ci[1]]


def _corner_prefix_fast(M: np.ndarray, L: int) -> np.ndarray:
    """:func:`_corner_prefix` by the compiled loop (:mod:`._corner_kernels`; equal to the
    last bit). Its rows are read in order: pass a transposed matrix as a C-contiguous copy."""
    from ._corner_kernels import corner_prefix_nb
    return corner_prefix_nb(M, L, np.empty((M.shape[0], L * (L + 1) // 2)))


def _smoothness(L: int) -> np.ndarray:
    """Differences of the masses of neighbouring off-diagonal cells (all of equal area).
    The diagonal cells (α = β) are left out: they hold the reversible part (the slope just
    after every reversal), a density of another order than the relays' beside them, and
    tying them together would smear it into the plane (measured: stronger smoothing then
    only made the fit worse, 3.2 → 8.5 % max on a raster predicted from a user-style
    record; without the diagonal it fills the plane between the record's reversal curves
    smoothly, 0.16 %). Dense; :func:`_smoothness_gram` is ``DᵀD``."""
    return _smoothness_sparse(L).toarray()


def _smoothness_sparse(L: int) -> Any:
    """:func:`_smoothness` as a sparse matrix (two entries a row)."""
    from scipy import sparse
    ci = np.tril_indices(L)
    n_cells = ci[0].size
    index = {(int(i), int(j)): n for n, (i, j) in enumerate(zip(*ci)) if i != j}
    pairs = [(n, m) for (i, j), n in index.items() for m in (index.get((i + 1, j)), index.get((i, j + 1)))
             if m is not None]
    rows = np.repeat(np.arange(len(pairs)), 2)
    cols = np.array(pairs, dtype=np.int64).reshape(-1)
    vals = np.tile([1.0, -1.0], len(pairs))
    return sparse.csr_matrix((vals, (rows, cols)), shape=(len(pairs), n_cells))


def _smoothness_gram(L: int) -> np.ndarray:
    """``DᵀD`` of :func:`_smoothness` (dense, L(L+1)/2 square): its entries are small
    integers, exact whichever way the product is formed."""
    D = _smoothness_sparse(L)
    return (D.T @ D).toarray()


def _unvisited_weight(u: np.ndarray) -> float:
    """The prior's weight far from the cells the record visits: :data:`NO_MINOR_LOOPS_PRIOR_WEIGHT`
    when the input ``u`` [V] has no minor loops, else :data:`UNVISITED_PRIOR_WEIGHT`."""
    from .coverage import MIN_INTERIOR_REVERSALS, interior_reversals

    return UNVISITED_PRIOR_WEIGHT if interior_reversals(u) >= MIN_INTERIOR_REVERSALS else NO_MINOR_LOOPS_PRIOR_WEIGHT


def _nnls_fit(u: np.ndarray, y: np.ndarray, lo: float, hi: float, L: int, cap: int, smoothing: float,
              max_rows: int, fit_from_index: int = 0, extra: np.ndarray | None = None,
              prior_weight: float = 0.0, skip: np.ndarray | None = None,
              unvisited_weight: float = UNVISITED_PRIOR_WEIGHT) -> tuple[np.ndarray, float, np.ndarray]:
    """Cell masses ``w ≥ 0`` [nm], offset ``y0`` [nm] and the coefficients ``c ≥ 0`` of the
    ``extra`` regressors (columns, one value per sample; none: an empty array) of
    ``y ≈ y0 + Φ(u)·w + extra·c`` (regularised nonnegative least squares). With
    ``prior_weight > 0`` a ridge of that relative weight pulls ``w`` towards the prior
    (:func:`_prior_masses`, fitted on the same normal equations): what the data do not
    determine takes the prior's masses. Samples marked in ``skip`` are no rows of the fit."""
    from scipy.linalg import cholesky
    rows = np.arange(fit_from_index, u.shape[0], dtype=np.int64)
    if skip is not None:
        rows = rows[~skip[rows]]
    if rows.size > max_rows:
        rows = rows[np.unique(np.linspace(0, rows.size - 1, max_rows).round().astype(np.int64))]
    n_cells = L * (L + 1) // 2
    ne = 0 if extra is None else extra.shape[1]
    nc = n_cells + ne
    ysel = y[rows]
    ymean = float(np.mean(ysel))
    AtA, Atb, Asum = _normal_terms(u, rows, ysel - ymean, lo, hi, L, cap, extra)
    m = rows.shape[0]
    mean_f = Asum / m
    # centre (y0 is free): A_c = A − 1·mean_f; Σ(y − ȳ) = 0 so A_cᵀ(y − ȳ) = Aᵀ(y − ȳ)
    AtA -= m * np.outer(mean_f, mean_f)
    # unit-RMS regressor columns: one ridge and one scale for cells and extra regressors alike
    col = np.sqrt(np.maximum(np.diag(AtA), 1e-300) / m)
    col[:n_cells] = 1.0
    AtA /= np.outer(col, col)
    Atb /= col
    scale = float(np.trace(AtA[:n_cells, :n_cells])) / n_cells if np.trace(AtA) > 0 else 1.0
    DtD = np.zeros((nc, nc))
    DtD[:n_cells, :n_cells] = _smoothness_gram(L)
    H = AtA + smoothing * scale * DtD + 1e-9 * scale * np.eye(nc)
    if prior_weight > 0:
        p = _prior_masses(AtA, Atb, lo, hi, L, ne)
        far = np.clip(unvisited_distance(visited_cells(u[fit_from_index:], lo, hi, L), L) / PRIOR_REACH_CELLS,
                      0.0, 1.0)
        weight = prior_weight + (max(prior_weight, unvisited_weight) - prior_weight) * far ** 2
        ridge = np.r_[weight * scale, np.zeros(ne)]
        H += np.diag(ridge)
        # min ‖A x − b‖² + s‖D x‖² + λ‖x − p‖²: the right side gains λ p
        Atb = Atb + ridge * np.r_[p, np.zeros(ne)]
    try:
        cholesky(H, lower=False)                # positive definite, or a little more ridge
    except np.linalg.LinAlgError:
        H += 1e-6 * scale * np.eye(nc)
    # min ½ xᵀHx − Atbᵀx, x ≥ 0 (= min ‖R x − z‖², RᵀR = H, Rᵀz = Atb)
    x = nnls_gram(H, Atb)
    x = x / col
    y0 = ymean - float(mean_f @ x)
    w = np.zeros((L, L))
    w[np.tril_indices(L)] = x[:n_cells]
    return w, y0, x[n_cells:]


# ------------------------------------------------------------------ the prior (#24 item 3)
def prior_basis(lo: float, hi: float, L: int, bins: int = PRIOR_BINS, subsamples: int = 6) -> np.ndarray:
    """Cell masses [nm per unit coefficient] of the prior's density family, one column per
    term: ``b_k(r)·(1 ± ŝ)/2`` with ``b_k`` the indicator of the k-th of ``bins`` equal bins of
    ``r = (α − β)/2`` over ``0 … (hi − lo)/2`` and ``ŝ = (α + β − hi − lo)/(hi − lo) ∈ [−1, 1]``.
    With equal coefficients of a bin's two terms it is a PI model (a play of threshold ``r``
    is the integral of the 0/1 relays on ``α − β = 2r``, Brokate & Sprekels, *Hysteresis and
    Phase Transitions*, §2.4, with its threshold spread over a bin); unequal ones tilt the
    density along ``α + β`` (asymmetric loops). Integrated on ``subsamples²`` midpoints per
    cell (``dα dβ = 2 ds dr``). Rows in ``np.tril_indices(L)`` order."""
    d = (hi - lo) / L
    off = (np.arange(subsamples) + 0.5) / subsamples * d
    i, j = np.tril_indices(L)
    a = lo + (i * d)[:, None, None] + off[None, :, None]
    b = lo + (j * d)[:, None, None] + off[None, None, :]
    r = 0.5 * (a - b)
    s_hat = (a + b - hi - lo) / (hi - lo)
    k = np.minimum((r / (0.5 * (hi - lo)) * bins).astype(np.int64), bins - 1)
    inside = r >= 0
    area = d * d / subsamples ** 2 / 2.0             # dα dβ = 2 ds dr
    B = np.zeros((i.size, 2 * bins))
    for sign, col0 in ((1.0, 0), (-1.0, bins)):
        wt = np.where(inside, 0.5 * (1.0 + sign * s_hat), 0.0) * area
        for kk in range(bins):
            B[:, col0 + kk] = np.where(k == kk, wt, 0.0).sum(axis=(1, 2))
    return B


def _prior_masses(AtA: np.ndarray, Atb: np.ndarray, lo: float, hi: float, L: int, ne: int) -> np.ndarray:
    """The prior's cell masses [nm]: the nonnegative member of :func:`prior_basis`'s family
    (and the extra regressors) that best fits the data, from the fit's centred normal
    equations (cells first, then ``ne`` extra columns)."""
    from scipy.optimize import nnls

    B = prior_basis(lo, hi, L)
    n_cells = B.shape[0]
    T = np.zeros((n_cells + ne, B.shape[1] + ne))
    T[:n_cells, :B.shape[1]] = B
    T[n_cells:, B.shape[1]:] = np.eye(ne)
    M = T.T @ AtA @ T
    g = T.T @ Atb
    scale = float(np.trace(M)) / M.shape[0] if np.trace(M) > 0 else 1.0
    M += 1e-9 * scale * np.eye(M.shape[0])
    try:
        R = np.linalg.cholesky(M).T
    except np.linalg.LinAlgError:
        R = np.linalg.cholesky(M + 1e-6 * scale * np.eye(M.shape[0])).T
    z = np.linalg.solve(R.T, g)
    c, _ = nnls(R, z, maxiter=50 * M.shape[0])
    return B @ c[:B.shape[1]]


def visited_cells(u_V: np.ndarray, lo: float, hi: float, L: int, reach: float = 1.5) -> np.ndarray:
    """Which cells (``np.tril_indices(L)`` order) a reversal of the record reached: a
    maximum ``M`` near cell row ``α`` followed by a descent to the next minimum ``m`` visits
    the cells ``(α, β)`` with ``β ≥ m`` (a descending reversal curve from ``α``), a minimum
    near column ``β`` followed by a rise to ``M`` those with ``α ≤ M``. "Near": within
    ``reach`` cells. The rest of the plane (e.g. its inside after full-range cycles) is known
    only through the prior."""
    u = np.asarray(u_V, dtype=float)
    d = np.diff(u)
    nz = np.flatnonzero(d)
    seen = np.zeros((L, L), dtype=bool)
    if nz.size < 2:
        return seen[np.tril_indices(L)]
    sg = np.sign(d[nz])
    turn = nz[1:][sg[1:] != sg[:-1]]             # index of each turning point's sample
    pts = np.r_[u[nz[0]], u[turn], u[-1]]
    step = (hi - lo) / L
    q = np.clip(np.round((pts - lo) / step - 0.5).astype(np.int64), 0, L - 1)
    pairs = np.unique(np.c_[q[:-1], q[1:]], axis=0)
    idx = np.arange(L)
    for a, b in pairs:
        if a > b:        # a maximum in row a, descending to b: rows near a, columns ≥ b
            rows = np.abs(idx - a) <= reach
            seen[np.ix_(rows, idx >= b - 1)] = True
        elif b > a:      # a minimum in column a, rising to b: columns near a, rows ≤ b
            cols = np.abs(idx - a) <= reach
            seen[np.ix_(idx <= b + 1, cols)] = True
    return seen[np.tril_indices(L)]


def unvisited_distance(seen: np.ndarray, L: int) -> np.ndarray:
    """Per cell (``np.tril_indices(L)`` order) its distance [cells] to the nearest cell a
    reversal of the record reached (``seen``, :func:`visited_cells`); 0 for those."""
    from scipy.ndimage import distance_transform_edt

    grid = np.ones((L, L), dtype=bool)            # True: not seen (the upper triangle too)
    grid[np.tril_indices(L)] = ~np.asarray(seen, dtype=bool)
    if grid.all():
        return np.full(L * (L + 1) // 2, float(L))
    return distance_transform_edt(grid)[np.tril_indices(L)]
