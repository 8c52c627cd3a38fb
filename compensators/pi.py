"""Prandtl–Ishlinskii (PI) hysteresis: operator, exact closed-form inverse, model file,
identification.

**Operator** (extended-PI paper, eqs. 3–4 without the creep term). With thresholds
``0 = r_0 < r_1 < … < r_{n−1}`` [V], weights ``w_i`` [nm/V], play states ``x_i`` [V] and
an output offset ``offset_nm``::

    x_i(t) = max(u(t) − r_i, min(u(t) + r_i, x_i(t − T)))
    y(t)   = offset_nm + Σ_i w_i·x_i(t)

``r_0 = 0`` makes the first play the identity, i.e. ``w_0`` is the linear part.

**Invertibility.** The operator is strictly increasing (hence invertible) iff ``w_0 > 0``
and every partial sum ``S_k = Σ_{j≤k} w_j > 0``: the slope of any branch of the loop is
one of the ``S_k``.

**Inverse** (eqs. 6–11). The inverse is again a PI operator, input ``y − offset_nm`` [nm],
output ``u`` [V], with::

    r'_i  = Σ_{j≤i} w_j·(r_i − r_j)                      (eq. 8)
    w'_0  = 1 / w_0                                       (eq. 9)
    w'_i  = −w_i / (S_i · S_{i−1})                        (eq. 10, minus sign restored)
    x'_0i = Σ_{j≤i} w_j·x_0i + Σ_{j>i} w_j·x_0j           (eq. 11, x_0j the forward states)

The printed eq. 10 of the paper lost its minus sign; with it, the paper's Table I is
reproduced to 1e-12 (see the tests). Note ``Σ_{j≤i} w'_j = 1/S_i``, so the inverse is
itself invertible and inverting twice gives the forward parameters back.

**Model file** (``kind = "pi"``): top-level ``thresholds``, ``weights``, optional
``initial_state`` and ``offset_nm``, and ``direction``: ``"forward"`` (the default; the
arrays describe u[V] → y[nm]: thresholds in V, weights in nm/V, states in V) or
``"inverse"`` (the arrays describe y[nm] → u[V]: thresholds and states in nm, weights in
V/nm — what ``afmctl model invert`` writes). Either file describes the same scanner, so
``forward()``/``inverse()`` mean the same thing for both.

**Identification** (eq. 5 with invertibility constraints): see :meth:`PIModel.identify`.
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any, ClassVar, Literal, overload

import numpy as np
from pydantic import Field, FiniteFloat, ValidationInfo, field_validator

from . import _pi_kernels as K
from .base import ModelError, StreamingOperator, check_finite
from .models import HysteresisModel
from .input_checks import block_samples, exclude_mask, finite_sample, number_option

log = logging.getLogger(__name__)

#: default number of play operators for identification (the paper's Table I has 13)
DEFAULT_OPERATORS = 13
#: most play operators a model file or an identification may have
MAX_OPERATORS = 1000


# --------------------------------------------------------------------- parameters -----

def check_pi_parameters(thresholds: Any, weights: Any, initial_state: Any = None,
                        where: str = "") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate PI parameters; return float64 copies ``(r, w, x0)``.

    Raises :class:`ModelError` naming the field and the allowed range when the thresholds
    are not ``0 = r_0 < r_1 < …``, a weight or partial sum is not positive (non-invertible
    operator), or the initial state is not one a play-operator bank can be in
    (``|x_i − x_{i−1}| ≤ r_i − r_{i−1}``).
    """
    p = f"{where}: " if where else ""
    r = np.array(thresholds, dtype=np.float64).ravel()
    w = np.array(weights, dtype=np.float64).ravel()
    if r.size == 0:
        raise ModelError(f"{p}thresholds: empty; at least one threshold (r_0 = 0) is required")
    if w.size != r.size:
        raise ModelError(f"{p}weights: {w.size} values but {r.size} thresholds; one weight per threshold is required")
    for name, arr in (("thresholds", r), ("weights", w)):
        if not np.all(np.isfinite(arr)):
            raise ModelError(f"{p}{name}: all values must be finite")
    if r[0] != 0.0:
        raise ModelError(f"{p}thresholds: first threshold is {float(r[0]):g}; it must be exactly 0 (the linear play)")
    if r.size > 1 and np.any(np.diff(r) <= 0):
        i = int(np.flatnonzero(np.diff(r) <= 0)[0]) + 1
        raise ModelError(f"{p}thresholds: must be strictly increasing; thresholds[{i}] = {float(r[i]):g} "
                         f"follows {float(r[i - 1]):g}")
    if w[0] <= 0:
        raise ModelError(f"{p}weights: weights[0] = {float(w[0]):.6g} must be > 0 for an invertible model")
    S = np.cumsum(w)
    if np.any(S <= 0):
        i = int(np.flatnonzero(S <= 0)[0])
        raise ModelError(f"{p}weights: partial sum weights[0..{i}] = {float(S[i]):.6g} must be > 0 for an invertible "
                         "model (every branch slope must be positive)")
    if initial_state is None:
        x0 = np.zeros_like(r)
    else:
        x0 = np.array(initial_state, dtype=np.float64).ravel()
        if x0.size != r.size:
            raise ModelError(f"{p}initial_state: {x0.size} values but {r.size} thresholds")
        if not np.all(np.isfinite(x0)):
            raise ModelError(f"{p}initial_state: all values must be finite")
        if r.size > 1:
            gap = np.abs(np.diff(x0)) - np.diff(r)
            tol = 1e-9 * max(1.0, float(np.max(np.abs(x0))), float(r[-1]))
            if np.any(gap > tol):
                i = int(np.flatnonzero(gap > tol)[0]) + 1
                raise ModelError(f"{p}initial_state: |x[{i}] − x[{i - 1}]| must be ≤ thresholds[{i}] − "
                                 f"thresholds[{i - 1}] (a state a play bank can reach)")
    return r, w, x0


def invert_pi_parameters(thresholds: Any, weights: Any, initial_state: Any = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form inverse PI parameters ``(r', w', x0')`` (eqs. 8–11; eq. 10 with its minus
    sign). Inputs are validated with :func:`check_pi_parameters`."""
    r, w, x0 = check_pi_parameters(thresholds, weights, initial_state)
    n = r.size
    S = np.cumsum(w)
    r_inv = np.empty(n)
    w_inv = np.empty(n)
    x_inv = np.empty(n)
    w_inv[0] = 1.0 / w[0]
    for i in range(n):
        r_inv[i] = float(np.sum(w[:i + 1] * (r[i] - r[:i + 1])))                    # eq. 8
        if i > 0:
            w_inv[i] = -w[i] / (S[i] * S[i - 1])                                      # eq. 10
        x_inv[i] = S[i] * x0[i] + float(np.sum(w[i + 1:] * x0[i + 1:]))               # eq. 11
    r_inv[0] = 0.0
    return r_inv, w_inv, x_inv


def default_thresholds(u_V: np.ndarray, n_operators: int) -> np.ndarray:
    """Equally spaced thresholds ``r_i = i/n · (max u − min u)/2``, ``i = 0 … n−1`` [V].

    The paper's ``r_i = i/(n+1)·‖u‖∞`` (eq. 3) spends operators on thresholds wider than
    half the input span; such plays never move again after the first excursion, so we
    space the thresholds over half the span instead.
    """
    span = float(np.max(u_V) - np.min(u_V))
    return np.arange(n_operators, dtype=np.float64) * (0.5 * span / n_operators)


# ---------------------------------------------------------------------- operator -------

class PIOperator(StreamingOperator):
    """Streaming PI operator ``y = out_offset + Σ w_i·play_{r_i}(x − in_offset)``.

    Used for the forward model (``in_offset = 0``, ``out_offset = offset_nm``) and, with
    the parameters of :func:`invert_pi_parameters`, for the inverse
    (``in_offset = offset_nm``, ``out_offset = 0``). ``use_numba=False`` selects the
    plain-numpy reference path (bit-identical, much slower).

    ``block`` and ``step`` reject non-finite input and ``block`` anything but a 1-D
    array (:class:`ModelError`): a NaN must never reach the play states.
    """

    def __init__(self, thresholds: Any, weights: Any, initial_state: Any = None, *,
                 in_offset: float = 0.0, out_offset: float = 0.0, use_numba: bool = True,
                 validate: bool = True) -> None:
        if validate:
            r, w, x0 = check_pi_parameters(thresholds, weights, initial_state)
        else:
            r = np.array(thresholds, dtype=np.float64)
            w = np.array(weights, dtype=np.float64)
            x0 = np.zeros_like(r) if initial_state is None else np.array(initial_state, dtype=np.float64)
        # one (3, n) array [thresholds; weights; state]: the step kernel takes it as a
        # single argument (cheaper call); the rows are contiguous views
        self._P = np.ascontiguousarray(np.vstack([r, w, x0]))
        self.thresholds = self._P[0]
        self.weights = self._P[1]
        self.state = self._P[2]
        self.initial_state = x0.copy()
        self.in_offset = float(in_offset)
        self.out_offset = float(out_offset)
        self.use_numba = use_numba

    def reset(self) -> None:
        self.state[:] = self.initial_state

    def step(self, x: float) -> float:
        v = finite_sample("input", x)
        if self.use_numba:
            return K.pi_step_packed(v, self._P, self.in_offset, self.out_offset)
        return K.pi_step_ref(v, self.thresholds, self.weights, self.state, self.in_offset, self.out_offset)

    def peek(self, x: float) -> float:
        """The output ``step(x)`` would give, without changing the state (no input check:
        an internal helper of the extended-PI inverse, which may probe with ±inf)."""
        return K.pi_peek_packed(float(x), self._P, self.in_offset, self.out_offset)

    def block(self, x: np.ndarray) -> np.ndarray:
        x = block_samples("input", x)
        if not self.use_numba:
            return K.pi_block_ref(x, self.thresholds, self.weights, self.state, self.in_offset, self.out_offset)
        out = np.empty_like(x)
        K.pi_block(x, self.thresholds, self.weights, self.state, self.in_offset, self.out_offset, out)
        return out


# ------------------------------------------------------------------- model file --------

class PIFamilyModel(HysteresisModel):
    """Fields shared by the PI and extended-PI model files (see the module docstring)."""

    direction: Literal["forward", "inverse"] = "forward"
    thresholds: list[FiniteFloat] = Field(max_length=MAX_OPERATORS,
                                          description="play thresholds r_i; V (forward) or nm (inverse)")
    weights: list[FiniteFloat] = Field(max_length=MAX_OPERATORS,
                                       description="weights w_i; nm/V (forward) or V/nm (inverse)")
    initial_state: list[FiniteFloat] | None = Field(
        default=None, max_length=MAX_OPERATORS,
        description="initial play states; V (forward) or nm (inverse); default all 0")
    offset_nm: FiniteFloat = Field(default=0.0, description="output offset y = offset_nm + Σ w_i x_i [nm]")

    @field_validator("thresholds")
    @classmethod
    def _check_thresholds(cls, v: list[float]) -> list[float]:
        if not v:
            raise ValueError("at least one threshold (r_0 = 0) is required")
        if v[0] != 0.0:
            raise ValueError(f"first threshold is {v[0]!r}; it must be exactly 0 (the linear play)")
        for i in range(1, len(v)):
            if v[i] <= v[i - 1]:
                raise ValueError(f"must be strictly increasing; thresholds[{i}] = {v[i]!r} follows {v[i - 1]!r}")
        return v

    @field_validator("weights")
    @classmethod
    def _check_weights(cls, v: list[float], info: ValidationInfo) -> list[float]:
        r = info.data.get("thresholds")
        if r is None:
            return v
        try:
            check_pi_parameters(r, v)
        except ModelError as err:
            raise ValueError(str(err).removeprefix("weights: ")) from None
        return v

    @field_validator("initial_state")
    @classmethod
    def _check_state(cls, v: list[float] | None, info: ValidationInfo) -> list[float] | None:
        r, w = info.data.get("thresholds"), info.data.get("weights")
        if v is None or r is None or w is None:
            return v
        try:
            check_pi_parameters(r, w, v)
        except ModelError as err:
            raise ValueError(str(err).removeprefix("initial_state: ")) from None
        return v

    # -- parameters in both directions ------------------------------------------------
    def forward_parameters(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(r [V], w [nm/V], x0 [V])`` of the forward operator u → y − offset."""
        if self.direction == "forward":
            return check_pi_parameters(self.thresholds, self.weights, self.initial_state)
        return invert_pi_parameters(self.thresholds, self.weights, self.initial_state)

    def inverse_parameters(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(r' [nm], w' [V/nm], x0' [nm])`` of the inverse operator y − offset → u."""
        if self.direction == "inverse":
            return check_pi_parameters(self.thresholds, self.weights, self.initial_state)
        return invert_pi_parameters(self.thresholds, self.weights, self.initial_state)

    def inverted(self) -> "PIFamilyModel":
        """The same scanner model with the arrays of the other direction (``model invert``)."""
        if self.direction == "forward":
            r, w, x0 = self.inverse_parameters()
            direction = "inverse"
        else:
            r, w, x0 = self.forward_parameters()
            direction = "forward"
        data = self.model_dump()
        data.update(direction=direction, thresholds=r.tolist(), weights=w.tolist(), initial_state=x0.tolist())
        return type(self).model_validate(data)

    def _pi_summary_lines(self) -> list[str]:
        r, w, x0 = self.forward_parameters()
        S = np.cumsum(w)
        lines = [
            f"stored direction : {self.direction}"
            + ("  (arrays map y[nm] -> u[V])" if self.direction == "inverse" else "  (arrays map u[V] -> y[nm])"),
            f"play operators   : {r.size}, thresholds 0 … {r[-1]:.6g} V",
            f"weights (fwd)    : w0 = {w[0]:.6g} nm/V, sum = {S[-1]:.6g} nm/V, min partial sum = {S.min():.6g} nm/V",
            f"offset           : {self.offset_nm:.6g} nm",
            "invertible       : yes (w0 > 0, all partial sums > 0)",
        ]
        ri, wi, _ = self.inverse_parameters()
        lines.append(f"inverse operator : thresholds 0 … {ri[-1]:.6g} nm, w'0 = {wi[0]:.6g} V/nm "
                     "(eqs. 8-11; 'afmctl model invert' writes it)")
        return lines


class PIModel(PIFamilyModel):
    """Prandtl–Ishlinskii model file (``kind = "pi"``), rate-independent."""

    kind: Literal["pi"] = "pi"
    fits_with_burn_in: ClassVar[bool] = True
    fits_exclude: ClassVar[bool] = True

    def forward(self, dt_s: float | None = None) -> PIOperator:
        """Operator u [V] → y [nm]."""
        r, w, x0 = self.forward_parameters()
        return PIOperator(r, w, x0, in_offset=0.0, out_offset=self.offset_nm, validate=False)

    def inverse(self, dt_s: float | None = None) -> PIOperator:
        """Feedforward compensator y [nm] → u [V] (eqs. 6–11)."""
        r, w, x0 = self.inverse_parameters()
        return PIOperator(r, w, x0, in_offset=self.offset_nm, out_offset=0.0, validate=False)

    def summary(self) -> str:
        return "\n".join(["model            : Prandtl–Ishlinskii (kind pi)"] + self._pi_summary_lines())

    @classmethod
    def identify(cls, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, n_operators: int | None = None,
                 **options: Any) -> "PIModel":
        """Fit a PI model to measured ``(u [V], y [nm])`` by constrained least squares.

        Thresholds: :func:`default_thresholds` (or ``thresholds=[...]`` in V, first 0).
        Initial play states: all equal to the first input sample (a relaxed scanner).
        Weights and offset minimise ``‖offset + Σ w_i·x_i(u) − y‖²`` (eq. 5) subject to
        ``S_k = Σ_{j≤k} w_j ≥ ε`` for every k (so ``w_0 ≥ ε`` too), which keeps the model
        invertible; ``ε = min_slope_fraction · (span y / span u)``, default fraction 1e-3.
        Options: ``thresholds``, ``min_slope_fraction``, ``max_rows`` (rows used in the
        least-squares problem, default 200000; longer data are decimated evenly),
        ``fit_from_index`` (samples before it only drive the play states: a burn-in),
        ``exclude`` (one boolean per sample: True rows drive the play states but are not
        fitted, e.g. samples whose ``y`` was not measured).
        """
        u, y, r, x0 = prepare_pi_identification(t_s, u_V, y_nm, n_operators, options)
        w, off = fit_pi_weights(u, y, r, x0, **_fit_options(options))
        return cls(thresholds=r.tolist(), weights=w.tolist(), initial_state=x0.tolist(), offset_nm=off)


# ------------------------------------------------------------------ identification ----

def check_pi_data(t_s: Any, u_V: Any, y_nm: Any, n_operators: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate identification data; return ``(u, y)`` as float64 arrays."""
    if n_operators < 1 or n_operators > MAX_OPERATORS:
        raise ModelError(f"n_operators: {n_operators} is out of range; allowed 1 … {MAX_OPERATORS}")
    t = check_finite("t_s", t_s).ravel()
    u = check_finite("u_V", u_V).ravel()
    y = check_finite("y_nm", y_nm).ravel()
    if not (t.size == u.size == y.size):
        raise ModelError(f"data: columns have different lengths (t {t.size}, u {u.size}, y {y.size})")
    need = 2 * n_operators + 2
    if u.size < need:
        raise ModelError(f"data: {u.size} samples; at least {need} are needed for {n_operators} operators")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        i = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise ModelError(f"t_s: time must be strictly increasing (sample {i + 1} follows sample {i})")
    if float(np.max(u) - np.min(u)) <= 0:
        raise ModelError("u_V: the input voltage never changes; excite the scanner (e.g. a decaying triangle)")
    return u, y


def prepare_pi_identification(t_s: Any, u_V: Any, y_nm: Any, n_operators: int | None, options: dict
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Validate data, choose thresholds (option ``thresholds`` or :func:`default_thresholds`)
    and the relaxed initial state; pops ``thresholds`` from ``options``."""
    thr = options.pop("thresholds", None)
    if thr is not None:
        try:
            r = np.array(thr, dtype=np.float64).ravel()
        except (TypeError, ValueError):
            raise ModelError("thresholds: expected a list of numbers in V, first 0") from None
        if n_operators is not None and int(n_operators) != r.size:
            raise ModelError(f"thresholds: {r.size} values but n_operators = {n_operators}")
        n = r.size
    else:
        n = DEFAULT_OPERATORS if n_operators is None else int(n_operators)
    u, y = check_pi_data(t_s, u_V, y_nm, n)
    if thr is None:
        r = default_thresholds(u, n)
    x0 = np.full(r.size, float(u[0]))
    check_pi_parameters(r, np.ones(r.size), x0)
    return u, y, r, x0


def _fit_options(options: dict) -> dict:
    allowed = {"min_slope_fraction", "max_rows", "fit_from_index", "exclude"}
    unknown = set(options) - allowed
    if unknown:
        raise ModelError(f"options: unknown option(s) {', '.join(sorted(unknown))}; allowed: "
                         f"thresholds, {', '.join(sorted(allowed))}")
    return dict(options)


def play_matrix(u: np.ndarray, r: np.ndarray, x0: np.ndarray, stride: int = 1) -> np.ndarray:
    """Outputs of every play operator, rows ``u[::stride]``, shape ``(rows, n)`` (eq. 5
    regressors). Computed in chunks so memory stays ``O(rows·n)``."""
    n = r.size
    state = x0.astype(np.float64).copy()
    rows = []
    chunk = max(stride, (65536 // stride) * stride)
    for start in range(0, u.size, chunk):
        seg = np.ascontiguousarray(u[start:start + chunk])
        out = np.empty((seg.size, n))
        K.play_outputs(seg, r, state, out)
        rows.append(out[::stride])
    return np.concatenate(rows, axis=0)


@overload
def fit_pi_weights(u: np.ndarray, y: np.ndarray, r: np.ndarray, x0: np.ndarray, *,
                   min_slope_fraction: float = 1e-3, max_rows: int = 200_000,
                   extra: None = None, fit_from_index: int = 0,
                   matrix: Callable[..., np.ndarray] | None = None,
                   exclude: np.ndarray | None = None) -> tuple[np.ndarray, float]: ...


@overload
def fit_pi_weights(u: np.ndarray, y: np.ndarray, r: np.ndarray, x0: np.ndarray, *,
                   min_slope_fraction: float = 1e-3, max_rows: int = 200_000,
                   extra: np.ndarray, fit_from_index: int = 0,
                   matrix: Callable[..., np.ndarray] | None = None,
                   exclude: np.ndarray | None = None) -> tuple[np.ndarray, float, float]: ...


def fit_pi_weights(u: np.ndarray, y: np.ndarray, r: np.ndarray, x0: np.ndarray, *,
                   min_slope_fraction: float = 1e-3, max_rows: int = 200_000,
                   extra: np.ndarray | None = None, fit_from_index: int = 0,
                   matrix: Callable[..., np.ndarray] | None = None, exclude: np.ndarray | None = None
                   ) -> tuple[np.ndarray, float] | tuple[np.ndarray, float, float]:
    """Constrained least squares for PI weights and offset (see :meth:`PIModel.identify`).

    The problem is solved in the partial sums ``S_k`` (``w = D·S``), where the
    invertibility constraints become simple bounds ``S_k ≥ ε``. The unconstrained
    solution is used as is when it already satisfies them (exact recovery on noise-free
    data); otherwise ``scipy.optimize.lsq_linear`` solves the bounded problem.

    ``extra`` (same length as ``u``) adds one more regressor with a coefficient ≥ 0 (the
    extended PI model's creep signal); then ``(w, offset, coefficient)`` is returned.
    ``fit_from_index``: rows before this sample are simulated (they set the play states)
    but left out of the least-squares problem (a burn-in for data with an unknown start).
    ``matrix(u, r, x0, stride)``: the plays' outputs (default :func:`play_matrix`; the
    rate-dependent PI model passes its own). ``exclude``: one boolean per sample, True rows
    simulated but left out of the problem (samples whose ``y`` was not measured).
    """
    from scipy.optimize import lsq_linear

    min_slope_fraction = number_option("min_slope_fraction", min_slope_fraction, allowed="a number in (0, 1)")
    if not 0 < min_slope_fraction < 1:
        raise ModelError(f"min_slope_fraction: {min_slope_fraction!r} must be in (0, 1)")
    max_rows = number_option("max_rows", max_rows, lo=2 * r.size + 2, integer=True)
    stride = max(1, int(np.ceil(u.size / max_rows)))
    fit_from_index = number_option("fit_from_index", fit_from_index, lo=0, hi=u.size - 2 * r.size - 2, integer=True)
    X = (matrix or play_matrix)(u, r, x0, stride)
    keep = np.arange(0, u.size, stride) >= fit_from_index
    skip = exclude_mask(exclude, u.size)
    if skip is not None:
        keep &= ~skip[::stride]
        if np.count_nonzero(keep) < 2 * r.size + 2:
            raise ModelError(f"exclude: {np.count_nonzero(keep)} rows are left to fit; at least {2 * r.size + 2} "
                             "are needed")
    X = X[keep]
    yy = y[::stride][keep]
    n = r.size
    ne = 0 if extra is None else 1
    # columns for the partial sums: a_j − a_{j+1}, last a_{n−1}; then the offset column
    A = np.empty((X.shape[0], n + 1 + ne))
    A[:, :n - 1] = X[:, :n - 1] - X[:, 1:]
    A[:, n - 1] = X[:, n - 1]
    A[:, n] = 1.0
    if extra is not None:
        A[:, n + 1] = np.asarray(extra, dtype=np.float64)[::stride][keep]
    gain = float(np.ptp(yy)) / float(np.ptp(u)) if np.ptp(yy) > 0 else 1.0
    eps = float(min_slope_fraction) * abs(gain)
    # column scaling for conditioning
    scale = np.sqrt(np.sum(A * A, axis=0))
    scale[scale == 0] = 1.0
    As = A / scale
    p, *_ = np.linalg.lstsq(As, yy, rcond=None)
    p = p / scale
    if np.any(p[:n] < eps) or (ne and p[n + 1] < 0):
        lb = np.full(n + 1 + ne, -np.inf)
        ub = np.full(n + 1 + ne, np.inf)
        lb[:n] = eps * scale[:n]
        if ne:
            lb[n + 1] = 0.0
        res = lsq_linear(As, yy, bounds=(lb, ub), method="bvls", tol=1e-12, max_iter=2000)
        p = res.x / scale
        p[:n] = np.maximum(p[:n], eps)
        if ne:
            p[n + 1] = max(p[n + 1], 0.0)
        log.info("PI fit: invertibility constraints active (%d partial sums at the bound)",
                 int(np.sum(p[:n] <= eps * (1 + 1e-9))))
    S = p[:n]
    w = np.diff(np.concatenate(([0.0], S)))
    off = float(p[n])
    resid = A[:, :n + 1] @ p[:n + 1] - yy
    if ne:
        resid += A[:, n + 1] * p[n + 1]
    log.info("PI fit: %d operators, %d rows, rms residual %.4g nm", n, X.shape[0], float(np.sqrt(np.mean(resid ** 2))))
    if ne:
        return w, off, float(p[n + 1])
    return w, off
