"""Hysteresis identification from AFM images of a calibration grating — no position sensor.

Source: Zhang, Fang, Zhou & Dong, *Image-based hysteresis modeling and compensation for an
AFM piezo-scanner* (seeds/003), Section 2.2; equation numbers are that paper's.

Procedure (the paper's Steps 1–4):

1. *Scans* (done by the caller, e.g. :mod:`afmctl.sim_backend.image_scans`): one line of a grating
   of known period is scanned repeatedly with a triangular voltage u_min → u_max → u_min,
   for several scan ranges u_max. Each pixel's voltage is known.
2. *Features* (eqs. 4–5): every line is cut where its height exceeds the threshold
   ``T = a·mean(height) + c`` (eq. 4); each segment above T gives one feature point, its
   height-weighted centre of gravity ``C_f = Σ i·h(i) / Σ h(i)`` (eq. 5), in pixels
   (heights measured from the line's minimum). Feature voltages are averaged over the
   repeated lines of a range.
3. *Displacement vs voltage* (eq. 6): consecutive features are one grating period apart,
   so feature k is at displacement ``k·period`` (counting periods); its voltage is the
   pixel voltage interpolated at ``C_f``. Polynomials of order m (default 12, lowered to
   features // 3 for small ranges) are fitted by least squares, ``θ = (ΦᵀΦ)⁻¹Φᵀy``
   (eq. 6), to the ascending branch (trace) and the descending branch (retrace) of every
   scan range together, constrained to meet at u_max (the reversal point) and at u_min
   (negative saturation). The trace and retrace see the same grating lines, so they share
   the period count; the retrace's count is aligned so that both branches meet at u_max
   (a miscount is off by a whole period), and the common offset makes y(u_min) = 0.
4. *Weights*: the branches are first-order reversal curves from u_min (ascending to
   α = u_max of the range, descending back), exactly what the Preisach identification
   needs; they are turned into a (t, u, y) record and passed to
   ``Model.identify`` (``compensators.preisach.PreisachModel.identify`` for kind
   "preisach", or any other registered kind).

Pure numerics: arrays in, arrays/models out; the caller reads files.

Scan arrays (the ``--from-images`` file of ``afmctl identify``, see docs/SIM.md):

============== ============ ==========================================================
name           shape        meaning
============== ============ ==========================================================
period_nm      ()           grating period [nm]
u_trace_V      (R, P)       voltage of each trace pixel, ascending, per scan range [V]
u_retrace_V    (R, P)       voltage of each retrace pixel in time order (descending) [V]
trace_nm       (R, L, P)    heights of L repeated trace lines per range [nm]
retrace_nm     (R, L, P)    heights of the retrace lines, pixels in time order [nm]
skip_lines     () optional  leading lines of every range to ignore (default 1)
============== ============ ==========================================================
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .base import ModelError

log = logging.getLogger(__name__)

REQUIRED_ARRAYS = ("period_nm", "u_trace_V", "u_retrace_V", "trace_nm", "retrace_nm")


# --------------------------------------------------------------------------- eqs. 4–5
def threshold(height_nm: np.ndarray, a: float = 1.0, c: float = 0.0) -> float:
    """Eq. 4: T = a · (Σ height(i))/n + c [nm]; a = 1, c = 0 for little noise."""
    h = np.asarray(height_nm, dtype=np.float64)
    return float(a * h.mean() + c)


def feature_points(height_nm: np.ndarray, a: float = 1.0, c: float = 0.0, drop_edges: bool = True,
                   min_width_px: int = 2) -> np.ndarray:
    """Feature points of one scan line (eq. 5): for every run of pixels with
    height ≥ T (eq. 4), the centre of gravity Σ i·w(i) / Σ w(i) in pixel coordinates.

    The weight is the height above the line's minimum, w = h − min(h) (eq. 5 uses the
    height itself; measuring it from the substrate makes the centre independent of the
    height offset of the line, e.g. from z drift). Runs touching the first or last pixel
    are partial features and are dropped when ``drop_edges``; runs narrower than
    ``min_width_px`` pixels are noise and always dropped."""
    h = np.asarray(height_nm, dtype=np.float64)
    if h.ndim != 1 or h.size < 3:
        raise ModelError(f"height_nm: expected one scan line with ≥ 3 pixels, got shape {h.shape}")
    T = threshold(h, a, c)
    above = h >= T
    if not above.any():
        return np.zeros(0)
    d = np.diff(np.concatenate([[0], above.astype(np.int8), [0]]))
    starts = np.flatnonzero(d == 1)
    ends = np.flatnonzero(d == -1)  # exclusive
    w = h - h.min()
    idx = np.arange(h.size, dtype=np.float64)
    out = []
    for s, e in zip(starts, ends):
        if e - s < min_width_px:
            continue
        if drop_edges and (s == 0 or e == h.size):
            continue
        ww = w[s:e]
        tot = ww.sum()
        if tot <= 0:
            continue
        out.append(float((idx[s:e] * ww).sum() / tot))
    return np.asarray(out)


# --------------------------------------------------------------------------- eq. 6
def fit_polynomial(u_V: np.ndarray, y_nm: np.ndarray, order: int = 5) -> np.ndarray:
    """Eq. 6: least-squares polynomial θ = (ΦᵀΦ)⁻¹Φᵀy with Φ the Vandermonde matrix of the
    voltages (columns 1, u, …, u^m). Returns θ (order + 1,), lowest power first. Solved
    with an orthogonal factorisation on scaled voltages (same minimiser, better
    conditioned than forming ΦᵀΦ)."""
    u = np.asarray(u_V, dtype=np.float64)
    y = np.asarray(y_nm, dtype=np.float64)
    if u.shape != y.shape or u.ndim != 1:
        raise ModelError(f"u_V, y_nm: expected two 1-D arrays of equal length, got {u.shape} and {y.shape}")
    if u.size < order + 1:
        raise ModelError(f"order: {order} needs ≥ {order + 1} feature points, got {u.size}")
    s = max(float(np.max(np.abs(u))), 1e-12)
    Phi = np.vander(u / s, order + 1, increasing=True)
    theta_s, *_ = np.linalg.lstsq(Phi, y, rcond=None)
    return theta_s / s ** np.arange(order + 1)


def poly_eval(theta: np.ndarray, u_V: float | np.ndarray) -> np.ndarray:
    """Evaluate a polynomial θ (lowest power first) at u [V]."""
    return np.polynomial.polynomial.polyval(np.asarray(u_V, dtype=np.float64), theta)


def fit_closed_loop(u_asc_V: np.ndarray, y_asc_nm: np.ndarray, u_desc_V: np.ndarray, y_desc_nm: np.ndarray,
                    u_lo_V: float, u_hi_V: float, order: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 6 for the two branches of one loop at once: least squares for the ascending
    polynomial θ_a and the descending θ_d subject to p_a(u_hi) = p_d(u_hi) (the reversal
    point) and p_a(u_lo) = p_d(u_lo) (back in negative saturation). Solved as an
    equality-constrained least-squares problem (KKT system) on scaled voltages."""
    ua = np.asarray(u_asc_V, dtype=np.float64)
    ud = np.asarray(u_desc_V, dtype=np.float64)
    m = order + 1
    s = max(abs(u_lo_V), abs(u_hi_V), 1e-12)
    A = np.zeros((ua.size + ud.size, 2 * m))
    A[: ua.size, :m] = np.vander(ua / s, m, increasing=True)
    A[ua.size:, m:] = np.vander(ud / s, m, increasing=True)
    b = np.concatenate([np.asarray(y_asc_nm, dtype=np.float64), np.asarray(y_desc_nm, dtype=np.float64)])
    C = np.zeros((2, 2 * m))
    for r, u0 in enumerate((u_hi_V, u_lo_V)):
        v = np.vander(np.array([u0 / s]), m, increasing=True)[0]
        C[r, :m] = v
        C[r, m:] = -v
    kkt = np.zeros((2 * m + 2, 2 * m + 2))
    kkt[: 2 * m, : 2 * m] = 2.0 * A.T @ A
    kkt[: 2 * m, 2 * m:] = C.T
    kkt[2 * m:, : 2 * m] = C
    rhs = np.concatenate([2.0 * A.T @ b, np.zeros(2)])
    sol = np.linalg.lstsq(kkt, rhs, rcond=None)[0][: 2 * m]
    scale = s ** np.arange(m)
    return sol[:m] / scale, sol[m:] / scale


# --------------------------------------------------------------------------- branches
@dataclass
class Branch:
    """One branch of one scan range: feature voltages and displacements, and its fit."""

    u_V: np.ndarray  # feature voltages
    y_nm: np.ndarray  # feature displacements (k·period − offset)
    theta: np.ndarray  # polynomial, y(u)
    u_start_V: float
    u_end_V: float
    rms_nm: float

    def __call__(self, u_V: np.ndarray) -> np.ndarray:
        return poly_eval(self.theta, u_V)


@dataclass
class RangeBranches:
    """Ascending (trace) and descending (retrace) branches of one scan range."""

    u_min_V: float
    u_max_V: float
    ascending: Branch
    descending: Branch


def _feature_voltages(lines: np.ndarray, u_px: np.ndarray, a: float, c: float) -> list[np.ndarray]:
    px = np.arange(u_px.size, dtype=np.float64)
    return [np.interp(feature_points(line, a, c), px, u_px) for line in lines]


def _mean_features(per_line: list[np.ndarray]) -> np.ndarray:
    """Average feature voltages over repeated lines (lines with the modal count only)."""
    counts = [f.size for f in per_line]
    if not counts or max(counts) == 0:
        return np.zeros(0)
    vals, freq = np.unique(counts, return_counts=True)
    k = int(vals[np.argmax(freq)])
    sel = [f for f in per_line if f.size == k]
    return np.mean(np.vstack(sel), axis=0)


def range_branches(trace_nm: np.ndarray, retrace_nm: np.ndarray, u_trace_V: np.ndarray,
                   u_retrace_V: np.ndarray, period_nm: float, order: int = 12, a: float = 1.0,
                   c: float = 0.0) -> RangeBranches:
    """Steps 2–3 for one scan range: feature points of every repeated line (eq. 5),
    averaged over lines, period counting, polynomial fits (eq. 6), trace/retrace alignment
    at u_max and the offset y(u_min) = 0. The order is lowered to features // 3 (at least
    1) when a small range holds few grating periods. ``trace_nm``/``retrace_nm`` are (L, P) with the
    retrace in time order; voltages (P,)."""
    tr = np.atleast_2d(np.asarray(trace_nm, dtype=np.float64))
    rt = np.atleast_2d(np.asarray(retrace_nm, dtype=np.float64))
    ut = np.asarray(u_trace_V, dtype=np.float64)
    ur = np.asarray(u_retrace_V, dtype=np.float64)
    if not (np.all(np.diff(ut) > 0) and np.all(np.diff(ur) < 0)):
        raise ModelError("u_trace_V must increase and u_retrace_V decrease along the pixels")
    fa = _mean_features(_feature_voltages(tr, ut, a, c))  # ascending voltages
    fd = _mean_features(_feature_voltages(rt, ur, a, c))  # descending voltages (time order)
    n_feat = min(fa.size, fd.size)
    if n_feat < 2:
        raise ModelError(f"trace_nm/retrace_nm: found {fa.size}/{fd.size} grating features in a line, need ≥ 2 "
                         "(period too large for the scan range, or threshold a/c unsuitable)")
    # small ranges hold few periods: at least three features per coefficient, so the
    # polynomial cannot oscillate between them
    order = max(1, min(order, n_feat // 3))
    u_lo, u_hi = float(ut[0]), float(ut[-1])
    ya = np.arange(fa.size) * period_nm
    th_a = fit_polynomial(fa, ya, order)
    y_top = float(poly_eval(th_a, u_hi))
    # retrace feature j (time order, from u_max) is physical feature K0 − j: choose K0 so the
    # descending branch meets the ascending one at u_max (the mismatch is otherwise ≥ a period).
    best: tuple[float, np.ndarray] | None = None
    for K0 in range(fa.size - 3, fa.size + 3):
        yd = (K0 - np.arange(fd.size)) * period_nm
        th_d = fit_polynomial(fd, yd, order)
        miss = abs(float(poly_eval(th_d, u_hi)) - y_top)
        if best is None or miss < best[0]:
            best = (miss, yd)
    assert best is not None  # the loop above runs six times
    yd = best[1]
    # both branches together: the loop is closed at u_max (reversal point) and at u_min
    # (back in negative saturation), two equality constraints on the pair of polynomials
    th_a, th_d = fit_closed_loop(fa, ya, fd, yd, u_lo, u_hi, order)
    off = float(poly_eval(th_a, u_lo))
    ya = ya - off
    yd = yd - off
    th_a[0] -= off
    th_d[0] -= off
    asc = Branch(fa, ya, th_a, u_lo, u_hi, float(np.sqrt(np.mean((poly_eval(th_a, fa) - ya) ** 2))))
    desc = Branch(fd, yd, th_d, u_hi, u_lo, float(np.sqrt(np.mean((poly_eval(th_d, fd) - yd) ** 2))))
    return RangeBranches(u_lo, u_hi, asc, desc)


def check_scans(scans: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Validate the scan arrays (see the module docstring); one-line :class:`ModelError`
    naming the array otherwise."""
    missing = [k for k in REQUIRED_ARRAYS if k not in scans]
    if missing:
        raise ModelError(f"scans: missing array(s) {', '.join(missing)}; required: {', '.join(REQUIRED_ARRAYS)}")
    out = {}
    for k in REQUIRED_ARRAYS:
        try:
            raw = np.asarray(scans[k])
            if raw.dtype.kind not in "biuf":  # complex, strings, objects: no silent casting
                raise TypeError
            out[k] = raw.astype(np.float64)
        except (TypeError, ValueError):
            raise ModelError(f"{k}: not a real numeric array") from None
    if out["period_nm"].size != 1 or not (np.isfinite(out["period_nm"]).all() and out["period_nm"].item() > 0):
        raise ModelError("period_nm: must be one positive number of nanometres")
    R, P = out["u_trace_V"].shape if out["u_trace_V"].ndim == 2 else (0, 0)
    if R < 1 or P < 8:
        raise ModelError(f"u_trace_V: expected shape (ranges, pixels ≥ 8), got {out['u_trace_V'].shape}")
    if out["u_retrace_V"].shape != (R, P):
        raise ModelError(f"u_retrace_V: expected shape {(R, P)}, got {out['u_retrace_V'].shape}")
    for k in ("trace_nm", "retrace_nm"):
        if out[k].ndim != 3 or out[k].shape[0] != R or out[k].shape[2] != P:
            raise ModelError(f"{k}: expected shape ({R}, lines, {P}), got {out[k].shape}")
    for k, v in out.items():
        if not np.all(np.isfinite(v)):
            raise ModelError(f"{k}: contains non-finite values; all values must be finite")
    skip = np.asarray(scans.get("skip_lines", 1))
    lines = out["trace_nm"].shape[1]
    if skip.size != 1 or skip.dtype.kind not in "iu" or not 0 <= int(skip.reshape(-1)[0]) < lines:
        raise ModelError(f"skip_lines: must be one integer in 0…{lines - 1} (lines per range − 1), got {skip!r}")
    out["skip_lines"] = skip
    return out


def branches_from_scans(scans: Mapping[str, Any], order: int = 12, a: float = 1.0,
                        c: float = 0.0) -> list[RangeBranches]:
    """Steps 2–3 for every scan range of a scan file (module docstring), each range fitted
    on its own (:func:`range_branches`)."""
    s = check_scans(scans)
    skip = int(np.asarray(s["skip_lines"]).reshape(-1)[0])
    period = float(s["period_nm"].reshape(-1)[0])
    out = []
    for r in range(s["u_trace_V"].shape[0]):
        tr = s["trace_nm"][r, skip:]
        rt = s["retrace_nm"][r, skip:]
        try:
            out.append(range_branches(tr, rt, s["u_trace_V"][r], s["u_retrace_V"][r], period, order, a, c))
        except ModelError as err:
            raise ModelError(f"scan range {r} (u_max {s['u_trace_V'][r, -1]:g} V): {err}") from None
    return out


def reversal_record(branches: list[RangeBranches], points_per_branch: int = 200) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 4 input: the fitted branches as one record of first-order reversal curves,
    ranges in increasing u_max, each ascending u_min → u_max then descending to u_min.
    Returns (t_s, u_V, y_nm) with a unit time step (the static model ignores time)."""
    us, ys = [], []
    for rb in sorted(branches, key=lambda b: b.u_max_V):
        ua = np.linspace(rb.u_min_V, rb.u_max_V, points_per_branch)
        ud = ua[::-1][1:]
        ya = rb.ascending(ua)
        yd = rb.descending(ud)
        # the two fits meet at u_max only approximately: close the loop at the top
        yd = yd + (ya[-1] - rb.descending(np.array([rb.u_max_V]))[0]) * np.linspace(1.0, 0.0, ud.size)
        us += [ua, ud]
        ys += [ya, yd]
    u = np.concatenate(us)
    y = np.concatenate(ys)
    return np.arange(u.size, dtype=np.float64), u, y


def identify_from_images(scans: Mapping[str, Any], kind: str = "preisach", n_operators: int | None = None,
                         order: int = 12, a: float = 1.0, c: float = 0.0, points_per_branch: int = 200,
                         **options: Any):
    """The whole image-based identification: scan arrays → fitted model of ``kind``.

    ``order`` is the polynomial order m of eq. 6, ``a``/``c`` the threshold parameters of
    eq. 4; other ``options`` go to ``Model.identify`` (for "preisach": the grid range
    defaults to the scanned voltage range)."""
    from .models import model_class

    branches = branches_from_scans(scans, order=order, a=a, c=c)
    t, u, y = reversal_record(branches, points_per_branch)
    if kind == "preisach":
        options.setdefault("u_min_V", float(min(b.u_min_V for b in branches)))
        options.setdefault("u_max_V", float(max(b.u_max_V for b in branches)))
    cls = model_class(kind)
    log.info("image-based identification: %d scan ranges, %d record samples, kind %s", len(branches), u.size, kind)
    return cls.identify(t, u, y, n_operators=n_operators, **options)
