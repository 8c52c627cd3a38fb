"""Discrete classical Preisach model (CPM) with an exact streaming inverse.

Source: Zhang, Fang, Zhou & Dong, *Image-based hysteresis modeling and compensation for an
AFM piezo-scanner* (seeds/003). Equation numbers below are that paper's.

Model (eqs. 1–3)
    The output is a weighted superposition of relay hysterons ``γ_αβ`` (β ≤ α) over the
    Preisach half-plane. The half-plane over the input range ``[u_min_V, u_max_V]`` is cut
    into ``levels`` equal sub-ranges (the paper: −160…160 V in 32 sub-ranges of 10 V), so
    the grid has ``levels + 1`` nodes ``v_0 = u_min … v_L = u_max``.

First-order reversal / Everett representation (eq. 7)
    ``f_α`` is the output after ascending from negative saturation (``u_min``) to ``α``;
    ``f_αβ`` the output after then descending to ``β``. The model stores the Everett
    function ``E(α, β) = f_α − f_αβ`` [nm] at the grid nodes (``everett_nm[i][j]`` for
    ``α = v_i ≥ β = v_j``) and ``offset_nm = f_{u_min}``. Inside a cell ``E`` is bilinear,
    ``E = c0 + c1·α + c2·β + c3·α·β`` (eq. 7). Above the diagonal ``E`` is extended
    antisymmetrically, which makes ``E(α, α) = 0`` inside diagonal cells as well.
    ``f_α = offset + E(α, u_min)`` and ``f_αβ = f_α − E(α, β)`` (:meth:`PreisachModel.forc_nm`).

Output from memory (eq. 8)
    The memory is the sequence of alternating dominant extrema ``u_min = s_0 < M_1 > m_1
    < M_2 > …`` ending with the present input; a new extremum wipes out all dominated
    pairs (wiping-out property). ``y = offset + Σ_k ±E(max, min)`` over consecutive pairs
    (+ for ascending, − for descending pairs), which for a single reversal is eq. 8.

Exact inverse (eqs. 9–11)
    For a target ``y`` the inverse decides the direction, skips the memory pairs that the
    target wipes out, and then walks grid cells from the present input: inside a cell
    ``E`` is linear in the moving coordinate, so the input is one division (eq. 11). No
    bisection and no iteration; the result reproduces ``y`` to rounding.

Memory bound
    The stack holds at most ``memory_depth`` pairs (default ``2·levels + 2``; the grid has
    that many distinct node lines). A reversal that would exceed it forgets the innermost
    (smallest) remembered loop: the output then differs by at most the Everett mass of that
    loop. Random and scanning signals stay far below the bound.

Out-of-range inputs
    Inputs outside ``[u_min_V, u_max_V]`` are **clamped** to the range and a warning is
    logged (once per operator until :meth:`reset`); the number of clamped samples is kept
    in ``operator.n_clamped``. Targets the model cannot reach are clamped the same way by
    the inverse. Non-finite samples raise :class:`~afmctl.compensators.base.ModelError`.

Initial state (``reset``): negative saturation at ``u_min_V`` (output ``offset_nm``); the
first sample then ascends from ``u_min_V``.
"""
from __future__ import annotations

import logging
import math
from typing import Any, Callable, ClassVar, Literal

import numpy as np
from pydantic import Field, FiniteFloat, model_validator

from . import _preisach_kernels as _k
from .base import ModelError, StreamingOperator
from .input_checks import block_samples, finite_sample
from .models import HysteresisModel
from .preisach_grid import cell_masses_from_nodes, nodes_from_cell_masses

log = logging.getLogger(__name__)

#: tolerance on negative cell masses, relative to the largest Everett value
_NEG_TOL = 1e-9


class PreisachModel(HysteresisModel):
    """Discrete classical Preisach model, input ``u`` [V] → displacement ``y`` [nm].

    See the module docstring for the representation. Build one with
    :meth:`from_density`, :meth:`from_cell_masses` or :meth:`identify`.
    """

    kind: Literal["preisach"] = "preisach"
    u_min_V: FiniteFloat = Field(-160.0, description="lower end of the input grid [V]")
    u_max_V: FiniteFloat = Field(160.0, description="upper end of the input grid [V]")
    levels: int = Field(32, ge=1, le=512, description="number of sub-ranges of the input grid")
    everett_nm: list[list[float]] = Field(
        description="Everett function E(v_i, v_j) = f_α − f_αβ [nm] at grid nodes, row i has "
                    "i+1 values j = 0..i (lower triangle, diagonal 0)")
    offset_nm: FiniteFloat = Field(0.0, description="output at negative saturation f(u_min) [nm]")
    memory_depth: int | None = Field(None, ge=2, le=100000,
                                     description="max remembered pairs; default 2·levels+2")
    fit_method: str | None = Field(None, description="identification method, if identified")
    fit_residual_nm: float | None = Field(None, description="RMS fit residual on the data [nm]")
    fit_max_residual_nm: float | None = Field(None, description="max |fit residual| [nm]")

    time_dependent: ClassVar[bool] = False
    fits_with_burn_in: ClassVar[bool] = True
    fits_exclude: ClassVar[bool] = True

    @model_validator(mode="after")
    def _check(self) -> "PreisachModel":
        if not (math.isfinite(self.u_min_V) and math.isfinite(self.u_max_V)) or self.u_max_V <= self.u_min_V:
            raise ValueError(f"u_max_V must be > u_min_V (got u_min_V={self.u_min_V}, u_max_V={self.u_max_V})")
        L = self.levels
        if len(self.everett_nm) != L + 1:
            raise ValueError(f"everett_nm must have levels+1 = {L + 1} rows, got {len(self.everett_nm)}")
        for i, row in enumerate(self.everett_nm):
            if len(row) != i + 1:
                raise ValueError(f"everett_nm row {i} must have {i + 1} values (j = 0..{i}), got {len(row)}")
        G = self._lower()
        if not np.all(np.isfinite(G)):
            raise ValueError("everett_nm values must be finite")
        if float(np.max(np.abs(G))) > 1e12 or abs(self.offset_nm) > 1e12:
            raise ValueError("everett_nm, offset_nm: values must be within ±1e12 nm (sums of them must not overflow)")
        if np.any(np.diag(G) != 0.0):
            raise ValueError("everett_nm diagonal E(v_i, v_i) must be 0")
        w = cell_masses_from_nodes(G)
        tol = _NEG_TOL * max(1.0, float(np.max(np.abs(G))))
        if w.size and float(np.nanmin(w)) < -tol:
            i, j = map(int, np.unravel_index(int(np.argmin(np.where(np.isnan(w), np.inf, w))), w.shape))
            raise ValueError(f"everett_nm: cell (alpha {i}, beta {j}) has negative Preisach mass {w[i, j]:.3g} nm; "
                             "allowed: >= 0 (the inverse needs a monotone model)")
        return self

    # ----------------------------------------------------------------- geometry
    @property
    def cap(self) -> int:
        return self.memory_depth if self.memory_depth is not None else 2 * self.levels + 2

    def nodes_V(self) -> np.ndarray:
        """Grid nodes v_0..v_L [V] (``v_L == u_max_V`` exactly)."""
        v = self.u_min_V + (self.u_max_V - self.u_min_V) * np.arange(self.levels + 1) / self.levels
        v[-1] = self.u_max_V
        return v

    def _lower(self) -> np.ndarray:
        L = self.levels
        G = np.zeros((L + 1, L + 1))
        for i, row in enumerate(self.everett_nm):
            G[i, : i + 1] = row
        return G

    def everett_matrix(self) -> np.ndarray:
        """Antisymmetric node matrix ``G[i, j] = E(v_i, v_j)`` [nm], shape (L+1, L+1)."""
        G = self._lower()
        return G - G.T

    def cell_masses(self) -> np.ndarray:
        """Preisach mass of each grid cell [nm] (α cell i ≥ β cell j; NaN above)."""
        return cell_masses_from_nodes(self._lower())

    def forc_nm(self) -> np.ndarray:
        """First-order reversal values ``f_αβ`` [nm] at the nodes (α = v_i ≥ β = v_j;
        NaN above the diagonal); ``f_α`` is the diagonal."""
        G = self._lower()
        f_alpha = self.offset_nm + G[:, 0]
        F = f_alpha[:, None] - G
        F[np.triu_indices_from(F, 1)] = np.nan
        return F

    def output_range_nm(self) -> tuple[float, float]:
        """(y at u_min from negative saturation, y at u_max from negative saturation)."""
        return self.offset_nm, self.offset_nm + self.everett_nm[-1][0]

    # ----------------------------------------------------------------- constructors
    @classmethod
    def from_cell_masses(cls, masses: np.ndarray, u_min_V: float = -160.0, u_max_V: float = 160.0,
                         offset_nm: float = 0.0, **fields: Any) -> "PreisachModel":
        """Model from nonnegative cell masses ``masses[i, j]`` [nm] (α cell i ≥ β cell j;
        entries above the diagonal are ignored)."""
        w = np.array(masses, dtype=np.float64)
        if w.ndim != 2 or w.shape[0] != w.shape[1] or w.shape[0] < 1:
            raise ModelError(f"masses: expected a square (levels, levels) array, got shape {w.shape}")
        w = np.tril(np.nan_to_num(w))
        if np.any(w < 0):
            raise ModelError("masses: every cell mass must be >= 0")
        G = nodes_from_cell_masses(w)
        return cls(u_min_V=u_min_V, u_max_V=u_max_V, levels=w.shape[0], everett_nm=_tri_list(G),
                   offset_nm=offset_nm, **fields)

    @classmethod
    def from_density(cls, density: Callable[[np.ndarray, np.ndarray], np.ndarray], u_min_V: float = -160.0,
                     u_max_V: float = 160.0, levels: int = 32, offset_nm: float = 0.0, subsamples: int = 8,
                     **fields: Any) -> "PreisachModel":
        """Model from a Preisach density ``μ(α, β)`` [nm/V²] (vectorised callable, ≥ 0),
        integrated over each cell with ``subsamples²`` midpoints."""
        L = int(levels)
        if L < 1:
            raise ModelError(f"levels: must be >= 1, got {levels}")
        if not (math.isfinite(u_min_V) and math.isfinite(u_max_V)) or u_max_V <= u_min_V:
            raise ModelError(f"u_max_V: must be > u_min_V (got u_min_V={u_min_V}, u_max_V={u_max_V})")
        du = (u_max_V - u_min_V) / L
        S = int(subsamples)
        q = (np.arange(S) + 0.5) / S
        w = np.zeros((L, L))
        for i in range(L):  # one α row of cells at a time, vectorised over β
            a = (u_min_V + (i + q) * du)[:, None]
            b = (u_min_V + (np.arange(i + 1)[:, None] + q[None, :]).ravel() * du)[None, :]
            mu = np.broadcast_to(np.asarray(density(a, b), dtype=np.float64), (S, (i + 1) * S))
            mu = np.where(a >= b, mu, 0.0)  # only the lower half of the diagonal cell
            w[i, : i + 1] = mu.reshape(S, i + 1, S).sum(axis=(0, 2)) * du * du / S ** 2
        if not np.all(np.isfinite(w)):
            raise ModelError("density: returned non-finite values")
        return cls.from_cell_masses(np.maximum(w, 0.0), u_min_V, u_max_V, offset_nm, **fields)

    def voltage_range_V(self) -> tuple[float, float] | None:
        """The identified input range [V], else the grid ``u_min_V…u_max_V`` (inputs outside
        it are clamped by the operators anyway)."""
        return self.u_range_V or (float(self.u_min_V), float(self.u_max_V))

    # ----------------------------------------------------------------- operators
    def forward(self, dt_s: float | None = None) -> "PreisachOperator":
        """Streaming operator u [V] → y [nm] (eq. 8). ``dt_s`` is ignored."""
        return PreisachOperator(self)

    def inverse(self, dt_s: float | None = None) -> "PreisachInverse":
        """Streaming exact inverse y [nm] → u [V] (eqs. 9–11). ``dt_s`` is ignored."""
        return PreisachInverse(self)

    @classmethod
    def identify(cls, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, n_operators: int | None = None,
                 **options: Any) -> "PreisachModel":
        """Fit a Preisach model to measured input u [V] / output y [nm].

        ``n_operators`` is the number of levels (default 32). Options: ``u_min_V``,
        ``u_max_V`` (grid range; default the data range), ``method`` (``"for"`` first-order
        reversal curves, ``"nnls"`` regularised nonnegative least squares, ``"auto"``
        default: FOR when the data are reversal curves from ``u_min``), ``smoothing``
        (NNLS smoothness weight, default 1e-2), ``max_rows`` (NNLS rows, default 200000).
        See :mod:`afmctl.compensators.preisach_identify`.
        """
        from .preisach_identify import identify_preisach
        return identify_preisach(cls, t_s, u_V, y_nm, n_operators=n_operators, **options)

    def summary(self) -> str:
        lo, hi = self.output_range_nm()
        lines = [
            f"Preisach model (classical, discrete): {self.levels} levels over {self.u_min_V:g}…{self.u_max_V:g} V "
            f"({(self.u_max_V - self.u_min_V) / self.levels:g} V per cell)",
            f"  output from negative saturation: {lo:.6g} nm at {self.u_min_V:g} V … {hi:.6g} nm at {self.u_max_V:g} V",
            f"  memory depth: {self.cap} pairs",
        ]
        if self.fit_method is not None:
            res = "n/a" if self.fit_residual_nm is None else f"{self.fit_residual_nm:.4g} nm RMS"
            mx = "" if self.fit_max_residual_nm is None else f", {self.fit_max_residual_nm:.4g} nm max"
            span = hi - lo
            rel = "" if self.fit_residual_nm is None or span == 0 else f" ({100 * self.fit_residual_nm / abs(span):.3g} % of range)"
            lines.append(f"  identified by {self.fit_method}: residual {res}{rel}{mx}")
        return "\n".join(lines)


def _tri_list(G: np.ndarray) -> list[list[float]]:
    return [[float(x) for x in G[i, : i + 1]] for i in range(G.shape[0])]


# --------------------------------------------------------------------- operators
class _PreisachBase(StreamingOperator):
    def __init__(self, model: PreisachModel) -> None:
        self.model = model
        self.L = model.levels
        self.capacity = model.cap
        self.u_min = float(model.u_min_V)
        self.u_max = float(model.u_max_V)
        self.du = (self.u_max - self.u_min) / self.L
        self.inv_du = 1.0 / self.du
        self.G = np.ascontiguousarray(model.everett_matrix())
        self.v = model.nodes_V()
        self.s = np.zeros(self.capacity + 1)
        self.P = np.zeros(self.capacity + 1)
        self.ist = np.zeros(2, dtype=np.int64)
        self.fst = np.zeros(1)
        self.reset()

    def reset(self) -> None:
        self.s[:] = 0.0
        self.P[:] = 0.0
        self.s[0] = self.u_min
        self.P[0] = float(self.model.offset_nm)
        self.ist[:] = 0
        self.fst[0] = self.P[0]
        self._warned = False

    @property
    def n_clamped(self) -> int:
        """Samples clamped to the model range since the last reset."""
        return int(self.ist[1])

    @property
    def y_nm(self) -> float:
        """Present output [nm]."""
        return float(self.fst[0])

    @property
    def u_V(self) -> float:
        """Present input [V]."""
        return float(self.s[self.ist[0]])

    def memory_V(self) -> np.ndarray:
        """Present memory: u_min, alternating dominant extrema, present input [V]."""
        return self.s[: self.ist[0] + 1].copy()

    #: log a warning on the first clamp since :meth:`reset` (the loop turns it off while it
    #: primes a preview inverse with samples that are never sent, afmctl.control.machine)
    warn_clamps: bool = True

    def _warn(self, before: int, what: str) -> None:
        if self.ist[1] > before and not self._warned and self.warn_clamps:
            self._warned = True
            log.warning("Preisach %s: %d sample(s) outside the model range were clamped (input range %g…%g V); "
                        "further clamping is counted in n_clamped", what, int(self.ist[1] - before),
                        self.u_min, self.u_max)


class PreisachOperator(_PreisachBase):
    """Forward streaming operator u [V] → y [nm] (eq. 8)."""

    def step(self, x: float) -> float:
        x = finite_sample("u_V", x)
        before = self.ist[1]
        y = _k.fwd_update(x, self.s, self.P, self.ist, self.fst, self.G, self.u_min, self.u_max,
                          self.inv_du, self.L, self.capacity)
        if self.ist[1] != before:
            self._warn(int(before), "forward")
        return y

    def block(self, x: np.ndarray) -> np.ndarray:
        x = block_samples("u_V", x)
        before = int(self.ist[1])
        y = _k.forward_block(x, self.s, self.P, self.ist, self.fst, self.G, self.u_min, self.u_max,
                             self.inv_du, self.L, self.capacity)
        self._warn(before, "forward")
        return y


class PreisachInverse(_PreisachBase):
    """Exact inverse y [nm] → u [V] (eqs. 9–11); its memory is the forward model's
    memory driven by the computed u, so ``forward(inverse(y)) == y`` for reachable y."""

    def step(self, x: float) -> float:
        x = finite_sample("y_nm", x)
        before = self.ist[1]
        u = _k.inv_step(x, self.s, self.P, self.ist, self.fst, self.G, self.v, self.u_min, self.u_max,
                        self.inv_du, self.du, self.L, self.capacity)
        if self.ist[1] != before:
            self._warn(int(before), "inverse (target out of reach)")
        return u

    def block(self, x: np.ndarray) -> np.ndarray:
        x = block_samples("y_nm", x)
        before = int(self.ist[1])
        u = _k.inverse_block(x, self.s, self.P, self.ist, self.fst, self.G, self.v, self.u_min, self.u_max,
                             self.inv_du, self.du, self.L, self.capacity)
        self._warn(before, "inverse (target out of reach)")
        return u


# --------------------------------------------------------------------- reference (plain Python)
class ReferencePreisach:
    """Plain-Python reference of the forward model and its inverse (lists, no numba).

    Same memory rules and arithmetic order as the compiled kernels; the output is summed
    over the whole memory every sample (no incremental update). Tests compare the two.
    """

    def __init__(self, model: PreisachModel) -> None:
        self.m = model
        self.G = model.everett_matrix().tolist()
        self.v = model.nodes_V().tolist()
        self.L = model.levels
        self.cap = model.cap
        self.u_min = float(model.u_min_V)
        self.u_max = float(model.u_max_V)
        self.du = (self.u_max - self.u_min) / self.L
        self.inv_du = 1.0 / self.du
        self.reset()

    def reset(self) -> None:
        self.stack = [self.u_min]

    def E(self, a: float, b: float) -> float:
        G, L = self.G, self.L
        x = (a - self.u_min) * self.inv_du
        i = min(int(x), L - 1)
        fa = x - i
        z = (b - self.u_min) * self.inv_du
        j = min(int(z), L - 1)
        fb = z - j
        return (G[i][j] * (1.0 - fa) * (1.0 - fb) + G[i + 1][j] * fa * (1.0 - fb)
                + G[i][j + 1] * (1.0 - fa) * fb + G[i + 1][j + 1] * fa * fb)

    def output(self, stack: list[float] | None = None) -> float:
        s = self.stack if stack is None else stack
        y = float(self.m.offset_nm)
        for k in range(1, len(s)):
            if k % 2 == 1:
                y = y + self.E(s[k], s[k - 1])
            else:
                y = y - self.E(s[k - 1], s[k])
        return y

    def apply(self, u: float) -> None:
        s = self.stack
        u = min(max(u, self.u_min), self.u_max)
        K = len(s) - 1
        if K == 0:
            if u > s[0]:
                s.append(u)
            return
        rev = u < s[K] if K % 2 == 1 else u > s[K]
        if rev:
            if K >= self.cap:
                s[K - 1] = s[K]
                s.pop()
                s[-1] = u
            else:
                s.append(u)
        else:
            s[K] = u
        while len(s) >= 3:
            K = len(s) - 1
            if K % 2 == 1:
                if K >= 3 and u >= s[K - 2]:
                    del s[K - 1:]
                    s[-1] = u
                else:
                    break
            else:
                if u <= s[K - 2]:
                    del s[K - 1:]
                    s[-1] = u
                else:
                    break

    def forward(self, u: np.ndarray) -> np.ndarray:
        out = np.empty(len(u))
        for n, x in enumerate(np.asarray(u, dtype=float)):
            self.apply(float(x))
            out[n] = self.output()
        return out

    def _prefix(self, k: int) -> float:
        return self.output(self.stack[: k + 1])

    def _solve_cells(self, fixed: float, lo: float, hi: float, t: float, up: bool) -> float:
        """Walk cells from the present input; in each cell E is linear in the moving
        coordinate (eq. 10) and the candidate is one division (eq. 11)."""
        G, L, du, v = self.G, self.L, self.du, self.v
        z = (fixed - self.u_min) * self.inv_du
        f_i = min(int(z), L - 1)
        f_frac = z - f_i
        if up:
            i = min(int((lo - self.u_min) * self.inv_du), L - 1)
            j, fb = f_i, f_frac
            while True:
                last = v[i + 1] >= hi or i >= L - 1
                a_top = hi if last else v[i + 1]
                a_lo = max(v[i], lo)
                A = G[i][j] * (1.0 - fb) + G[i][j + 1] * fb
                B = (G[i + 1][j] - G[i][j]) * (1.0 - fb) + (G[i + 1][j + 1] - G[i][j + 1]) * fb
                if B > 0.0:
                    a = v[i] + (t - A) / B * du
                    if a <= a_top or last:
                        return min(max(a, a_lo), a_top)
                elif t <= A or last:
                    return a_lo
                i += 1
        i, fa = f_i, f_frac
        j = min(int((hi - self.u_min) * self.inv_du), L - 1)
        while True:
            last = v[j] <= lo or j <= 0
            b_bot = lo if last else v[j]
            b_hi = min(v[j + 1], hi)
            A = G[i][j] * (1.0 - fa) + G[i + 1][j] * fa
            B = (G[i][j + 1] - G[i][j]) * (1.0 - fa) + (G[i + 1][j + 1] - G[i + 1][j]) * fa
            if B < 0.0:
                b = v[j] + (t - A) / B * du
                if b >= b_bot or last:
                    return max(min(b, b_hi), b_bot)
            elif t <= A or last:
                return b_hi
            j -= 1

    def inverse(self, y: np.ndarray) -> np.ndarray:
        out = np.empty(len(y))
        for n, target in enumerate(np.asarray(y, dtype=float)):
            u = self._inv_one(float(target))
            self.apply(u)
            out[n] = u
        return out

    def _inv_one(self, y: float) -> float:
        s = self.stack
        K = len(s) - 1
        ycur = self.output()
        ucur = s[K]
        if y == ycur:
            return ucur
        up = y > ycur
        if K == 0 and not up:
            return self.u_min
        if K >= self.cap and (up == (K % 2 == 0)):
            s[K - 1] = s[K]
            s.pop()
            K -= 1
            ycur = self.output()
            if (y > ycur) != up or y == ycur:
                return min(math.nextafter(ucur, math.inf), self.u_max) if up else max(math.nextafter(ucur, -math.inf), self.u_min)
        if up:
            kb, base = (K - 1, self._prefix(K - 1)) if K % 2 == 1 else (K, ycur)
            lo = ucur
            while kb >= 2 and y > self._prefix(kb - 1):
                lo = s[kb - 1]
                kb -= 2
                base = self._prefix(kb)
            if kb == 0:
                hi = self.u_max
                if y >= self.m.offset_nm + self.E(self.u_max, self.u_min):
                    return self.u_max
            else:
                hi = s[kb - 1]
            return self._solve_cells(s[kb], lo, hi, y - base, True)
        kt, base = (K, ycur) if K % 2 == 1 else (K - 1, self._prefix(K - 1))
        hi = ucur
        while kt >= 3 and y < self._prefix(kt - 1):
            hi = s[kt - 1]
            kt -= 2
            base = self._prefix(kt)
        if kt == 1 and y <= self.m.offset_nm:
            return self.u_min
        return self._solve_cells(s[kt], s[kt - 1], hi, base - y, False)
