"""Linear scanner dynamics from grating images at several line rates — no position sensor.

After Clayton & Devasia (2009), image-based identification of SPM-nanopositioner
dynamics: a grating of known period is scanned with a periodic (triangular) voltage at
several line rates; in periodic steady state the tip's lag and ringing distort trace and
retrace differently, and that distortion, read off at the grating's edges, is the
scanner's frequency response at the harmonics of each line rate.

Model (Hammerstein, as :mod:`afmctl.compensators.chain`): the tip position is
``x = D[s]``, ``s = S(u)`` the static part (hysteresis, creep; identified from slow images
by :mod:`afmctl.compensators.image_identify`, or a linear gain) and ``D`` linear with unit
DC gain. Per line rate ``f_L`` [lines/s]:

1. *Edges*: in every trace and retrace line (time order) the heights cross the mid level
   (half-way between the line's 5th and 95th percentiles) at the grating's edges; each
   crossing, interpolated between pixel centres, gives a time ``t_k`` [s]. Pixel i of a
   line is centred at ``t = (i + ½)/(2·P·f_L)`` after the line start (trace pixels
   0…P−1, then the retrace's in time order), lines back to back. Edges within 5 % of a
   half-line of the turnarounds are left out (the tip may reverse there).
2. *Static prediction*: ``s(t)`` [nm] is the static model run over the commanded voltages
   of all the lines, one value per pixel centre, linearly interpolated to ``t_k``; its
   Fourier coefficients over the last line, ``S_n`` (n = 1…N), describe the periodic part.
3. *Positions*: an edge is at ``x_k = φ_e + m_k·P_g`` (``P_g`` the grating period, ``φ_e``
   one offset for the left and one for the right edges of the grating's lines). The
   integer ``m_k`` and the edge's side come from the predicted position
   ``p(t) = s(t) + ê(t)`` and its direction of motion (ê: the response found so far,
   from the slower line rates at first, then iterated; the static prediction alone is
   tried too and the placement with the smaller residual wins), so ringing that
   reverses the tip is followed.
4. *Harmonics*: with ``e_k = x_k − s(t_k)`` and, in periodic steady state,
   ``e(t) = (D − 1)[s](t) ≈ c + c_R·[right edge] + b·t + Σ_n 2·Re(H_n·S_n·e^{j2πn f_L t})``,
   ``H_n = G(j2πn f_L) − 1``, linear least squares over all edges of trace and retrace
   gives ``H_n``; ``c`` takes the unknown offset, ``b`` slow creep/drift. Solved for the
   harmonics with ``|S_n| ≥ 0.3·static_error_nm`` (the lowest ``(edges per line/1.5 − 3)/2``
   of them: two unknowns each), for ``E_n = H_n·S_n`` with a ridge ``RIDGE·edges·Σ|E_n|²``: no edge is
   seen at a turnaround, so a comb of odd harmonics (a spike at each turnaround) is
   otherwise nearly invisible. Edges whose residual exceeds 4× the robust RMS are dropped
   and the fit repeated.
5. *Response*: ``G_n = 1 + H_n`` with its standard error from the least-squares
   covariance and the static model's assumed error ``static_error_nm/|S_n|``, read only at
   the triangle's own (odd) harmonics (``|S_n| ≥ ½·|S_1|/n²`` and ``≥ static_error_nm``);
   those with a relative error below ``max_rel_error`` are kept, weighted
   ``min(1, 0.01/rel_err)`` (as √coherence), and all line rates together are fitted by
   :func:`afmctl.compensators.dynamics_identify.fit_frf` (modes, first-order lags, delay;
   :func:`~afmctl.compensators.dynamics_identify.fit_mode_count` for the number of modes).
   A line rate whose edges fit their harmonics more than 4× worse than the median of the
   rates kept before it (and worse than 10 nm RMS) is left out: its edges were placed on
   the wrong grating lines; ``fit_info`` names it.

Pure numerics: arrays in, a :class:`~afmctl.compensators.dynamics.LinearDynamicsModel`
out. Scan arrays are those of the ``--from-images`` file (:mod:`image_identify`), with
``line_rate_Hz`` one value per scan range (docs/SIM.md).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .base import ModelError
from .dynamics_identify import FRF, fit_frf, fit_mode_count, poles_of

log = logging.getLogger(__name__)

#: line rates up to this [lines/s] count as "slow" (static identification), faster ones
#: identify the dynamics
STATIC_MAX_LINE_RATE_HZ = 2.0
#: highest line rate accepted [lines/s]
MAX_LINE_RATE_HZ = 10_000.0

#: harmonics solved for: static coefficient at least this fraction of ``static_error_nm``
EXCITED = 0.3

#: ridge on the harmonics' coefficients, per edge (:func:`solve_harmonics`)
RIDGE = 1e-2

#: static model: voltages (one per pixel centre) [V], pixel period [s] → positions [nm]
StaticFn = Callable[[np.ndarray, float], np.ndarray]


@dataclass
class RateScan:
    """One scan range at one line rate: ``u_line_V`` (2P,) the commanded voltage of the
    trace then retrace pixels in time order [V]; ``trace_nm``/``retrace_nm`` (L, P)
    heights, the retrace in time order [nm]; ``skip`` leading lines not used."""

    u_line_V: np.ndarray
    trace_nm: np.ndarray
    retrace_nm: np.ndarray
    line_rate_Hz: float
    period_nm: float
    skip: int = 1

    @property
    def pixels(self) -> int:
        return int(self.trace_nm.shape[1])

    @property
    def pixel_s(self) -> float:
        """Pixel period [s]: a line (trace + retrace) of 2P pixels lasts 1/f_L."""
        return 1.0 / (2.0 * self.pixels * self.line_rate_Hz)


@dataclass
class RateResponse:
    """Frequency response found at one line rate: harmonics ``f_Hz``, ``G`` (complex),
    relative standard error ``rel_err``, edges used and their residual RMS [nm]."""

    line_rate_Hz: float
    f_Hz: np.ndarray
    G: np.ndarray
    rel_err: np.ndarray
    edges: int
    rms_nm: float


# --------------------------------------------------------------------------- input
def line_rates(scans: Mapping[str, Any], ranges: int) -> np.ndarray:
    """``line_rate_Hz`` of a scan file as one value per range (a scalar applies to all);
    :class:`ModelError` naming the field and the allowed range otherwise."""
    if "line_rate_Hz" not in scans:
        raise ModelError("line_rate_Hz: missing; the dynamics need the line rate of every scan range "
                         f"(lines/s, > 0 … {MAX_LINE_RATE_HZ:g})")
    raw = np.asarray(scans["line_rate_Hz"])
    if raw.dtype.kind not in "iuf" or raw.size not in (1, ranges) or raw.ndim > 1:
        raise ModelError(f"line_rate_Hz: expected one number or {ranges} (one per scan range), got shape {raw.shape}")
    r = np.broadcast_to(raw.astype(np.float64).reshape(-1), (ranges,)).copy()
    if not np.all(np.isfinite(r) & (r > 0) & (r <= MAX_LINE_RATE_HZ)):
        raise ModelError(f"line_rate_Hz: {r.tolist()}; each must be > 0 and ≤ {MAX_LINE_RATE_HZ:g} lines/s")
    return r


def split_scans(scans: Mapping[str, Any], static_max_Hz: float = STATIC_MAX_LINE_RATE_HZ
                ) -> tuple[dict[str, Any] | None, list[RateScan]]:
    """Scan arrays (checked by :func:`~afmctl.compensators.image_identify.check_scans`) →
    the slow ranges (line rate ≤ ``static_max_Hz``) as scan arrays for the static
    identification (None if there are none) and the fast ones as :class:`RateScan`."""
    from .image_identify import check_scans

    s = check_scans(scans)
    R = s["u_trace_V"].shape[0]
    rates = line_rates(scans, R)
    skip = int(np.asarray(s["skip_lines"]).reshape(-1)[0])
    period = float(s["period_nm"].reshape(-1)[0])
    slow = np.flatnonzero(rates <= static_max_Hz)
    static = None
    if slow.size:
        static = {k: (s[k][slow] if k in ("u_trace_V", "u_retrace_V", "trace_nm", "retrace_nm") else s[k])
                  for k in s}
        static["line_rate_Hz"] = rates[slow]
    fast = [RateScan(np.concatenate([s["u_trace_V"][r], s["u_retrace_V"][r]]), s["trace_nm"][r],
                     s["retrace_nm"][r], float(rates[r]), period, skip)
            for r in np.flatnonzero(rates > static_max_Hz)]
    return static, fast


# --------------------------------------------------------------------------- edges
def edge_crossings(height_nm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mid-level crossings of one line (time order): fractional pixel indices and +1
    (height rising in time) / −1 (falling). The level is half-way between the line's 5th
    and 95th percentiles; crossings are interpolated linearly between pixel centres."""
    h = np.asarray(height_nm, dtype=np.float64)
    lo, hi = np.percentile(h, [5, 95])
    if not hi - lo > 0:
        return np.zeros(0), np.zeros(0)
    d = h - 0.5 * (lo + hi)
    i = np.flatnonzero((d[:-1] < 0) != (d[1:] < 0))
    frac = d[i] / (d[i] - d[i + 1])
    return i + frac, np.where(d[i + 1] > d[i], 1.0, -1.0)


def scan_edges(scan: RateScan, margin: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Edges of the used lines: times from the first used line's start [s] and the sign
    of the height change (+1 rising). Edges within ``margin`` of a half-line of the
    turnarounds are left out (the tip may reverse there and cross a grating line
    partly)."""
    P, T = scan.pixels, scan.pixel_s
    ts, sg = [], []
    for line in range(scan.skip, scan.trace_nm.shape[0]):
        t0 = (line - scan.skip) * 2 * P * T
        for half, img in ((0, scan.trace_nm), (1, scan.retrace_nm)):
            idx, sign = edge_crossings(img[line])
            inner = (idx >= margin * P) & (idx <= (1.0 - margin) * P - 1.0)
            idx, sign = idx[inner], sign[inner]
            ts.append(t0 + (half * P + idx + 0.5) * T)
            sg.append(sign)
    return np.concatenate(ts), np.concatenate(sg)


# --------------------------------------------------------------------------- one rate
def static_course(scan: RateScan, static: StaticFn) -> np.ndarray:
    """The static prediction ``s`` [nm] at every pixel centre of every line (the model
    run from its own initial state through two warm-up lines and then all the lines),
    flattened in time order, starting with the first used line."""
    lines = scan.trace_nm.shape[0]
    u = np.tile(scan.u_line_V, lines + 2)
    s = np.asarray(static(u, scan.pixel_s), dtype=np.float64)
    return s[(2 + scan.skip) * scan.u_line_V.size:]


def harmonics_of(s_line: np.ndarray, n_max: int) -> np.ndarray:
    """Fourier coefficients ``S_n``, n = 1…n_max, of one period sampled at pixel centres:
    ``s(t) ≈ S_0 + Σ 2·Re(S_n e^{j2πn t f_L})`` with t from the line start."""
    N = s_line.size
    c = np.fft.rfft(s_line) / N
    c = c[1:n_max + 1]
    # pixel centres are at (i + ½)·T: shift the phase reference to the line start
    n = np.arange(1, c.size + 1)
    return c * np.exp(-1j * math.pi * n / N)


def excited_harmonics(S: np.ndarray, floor_nm: float, most: int) -> np.ndarray:
    """Harmonic numbers (1-based) whose static coefficient ``|S_n|`` is at least
    ``floor_nm`` [nm], the lowest ``most`` of them (the unknowns of step 4)."""
    return (np.flatnonzero(np.abs(S) >= floor_nm) + 1)[:max(0, most)]


def triangle_harmonics(n: np.ndarray, S: np.ndarray, floor_nm: float) -> np.ndarray:
    """Harmonics ``n`` the response is read at: a triangle's own (odd) harmonics,
    ``|S_n| ≥ ½·|S_1|/n²``, and at least ``floor_nm`` [nm]. The even ones come from the
    hysteresis' asymmetry alone; the static model knows them too poorly to divide by."""
    return (np.abs(S) >= 0.5 * np.abs(S[0]) / n.astype(np.float64) ** 2) & (np.abs(S) >= floor_nm)


def periodic_part(n: np.ndarray, S: np.ndarray, H: np.ndarray, f_L: float, t_s: np.ndarray) -> np.ndarray:
    """``Σ_n 2·Re(H_n S_n e^{j2πn f_L t})`` [nm] at ``t_s`` over the harmonics ``n``."""
    ph = np.exp(2j * math.pi * f_L * np.outer(t_s, n))
    return 2.0 * np.real(ph @ (H * S))


def assign_positions(p_nm: np.ndarray, v: np.ndarray, sign: np.ndarray, period_nm: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Grating positions of edges predicted at ``p_nm`` moving with velocity sign ``v``:
    rising height while moving +x (or falling while moving −x) is a line's left edge.
    Returns the positions ``φ_side + m·period`` [nm] (``φ_side`` the predictions' mean
    phase for each side) and 1.0 for right edges."""
    right = (sign * np.sign(v) < 0).astype(np.float64)
    x = np.empty_like(p_nm)
    for side in (0.0, 1.0):
        k = right == side
        if not np.any(k):
            continue
        ang = 2 * math.pi * p_nm[k] / period_nm
        phi = math.atan2(np.mean(np.sin(ang)), np.mean(np.cos(ang))) * period_nm / (2 * math.pi)
        x[k] = phi + np.round((p_nm[k] - phi) / period_nm) * period_nm
    return x, right


def solve_harmonics(t: np.ndarray, e: np.ndarray, right: np.ndarray, n: np.ndarray, S: np.ndarray, f_L: float,
                    keep: np.ndarray, ridge: float = RIDGE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares of step 4 (module docstring) over the edges ``keep``: returns
    ``H`` (complex, per harmonic ``n``), its standard error (per harmonic, absolute) and
    the residual of every edge [nm].

    Solved for ``E_n = H_n·S_n`` with a small ridge ``ridge·(edges)·Σ|E_n|²``: no edge is
    seen at the turnarounds, so a comb of odd harmonics (a spike at each turnaround) is
    nearly invisible to the edges; the ridge keeps it out (smallest distortion that
    explains the edges)."""
    ph = np.exp(2j * math.pi * f_L * np.outer(t, n))
    span = max(float(np.ptp(t)), 1e-12)
    A = np.column_stack([np.ones_like(t), right, (t - t.mean()) / span, 2 * ph.real, -2 * ph.imag])
    Ak = A[keep]
    M = Ak.T @ Ak
    reg = np.zeros(A.shape[1])
    reg[3:] = ridge * Ak.shape[0]
    Minv = np.linalg.pinv(M + np.diag(reg))
    coef = Minv @ (Ak.T @ e[keep])
    resid = e - A @ coef
    dof = max(1, int(np.count_nonzero(keep)) - A.shape[1])
    sigma2 = float(np.sum(resid[keep] ** 2)) / dof
    cov_diag = np.diag(Minv @ M @ Minv) * sigma2
    k = n.size
    E = coef[3:3 + k] + 1j * coef[3 + k:]
    se = np.sqrt(cov_diag[3:3 + k] + cov_diag[3 + k:]) / np.abs(S)
    return E / S, se, resid


def rate_response(scan: RateScan, static: StaticFn, priors: list[Callable[[np.ndarray], np.ndarray]],
                  f_max_Hz: float, static_error_nm: float = 1.0, iterations: int = 6) -> RateResponse:
    """Steps 1–4 of the module docstring for one line rate. ``priors`` are candidates
    ``f_Hz → G`` for the response known so far, used to place the edges on the grating
    first (the static prediction alone is tried too; the placement with the smallest
    residual wins).
    ``static_error_nm`` [nm] is the static model's error per harmonic assumed in the
    relative error of ``G`` (it keeps out harmonics the triangle barely excites)."""
    f_L, T, P2 = scan.line_rate_Hz, scan.pixel_s, 2 * scan.pixels
    t, sign = scan_edges(scan)
    per_line = t.size / max(1, scan.trace_nm.shape[0] - scan.skip)
    if per_line < 8:
        raise ModelError(f"trace_nm/retrace_nm at {f_L:g} lines/s: {per_line:.3g} grating edges per line, need ≥ 8 "
                         "(scan range too small for the grating period)")
    n_all = int(f_max_Hz / f_L)
    if n_all < 1:
        raise ModelError(f"line_rate_Hz: {f_L:g} lines/s is above f_max_Hz {f_max_Hz:g}; no harmonic to measure")
    s = static_course(scan, static)
    n = excited_harmonics(harmonics_of(s[-P2:], n_all), EXCITED * static_error_nm, int((per_line / 1.5 - 3) / 2))
    if n.size == 0:
        raise ModelError(f"u_trace_V at {f_L:g} lines/s: no harmonic of the line rate is excited above "
                         f"{static_error_nm:g} nm; scan a larger voltage range")
    S = harmonics_of(s[-P2:], n_all)[n - 1]
    t_px = (np.arange(s.size) + 0.5) * T
    s_t = np.interp(t, t_px, s)
    f_n = f_L * n
    starts = [np.zeros(n.size, complex)] + [prior(f_n) - 1.0 for prior in priors]
    best = min((_place_and_solve(scan, s, s_t, t, t_px, sign, n, S, H0, iterations) for H0 in starts),
               key=lambda r: r[2] * (1.0 + 4.0 * (1.0 - np.mean(r[3]))))
    H, se, rms, keep = best
    G = 1.0 + H
    se = np.hypot(se, static_error_nm / np.maximum(np.abs(S), 1e-12))
    rel = np.where(triangle_harmonics(n, S, static_error_nm), se / np.maximum(np.abs(G), 1e-12), np.inf)
    log.info("image dynamics: %g lines/s, %d edges (%d kept), %d harmonics, residual RMS %.3g nm",
             f_L, t.size, int(np.count_nonzero(keep)), n.size, rms)
    return RateResponse(f_L, f_n, G, rel, int(np.count_nonzero(keep)), rms)


def _place_and_solve(scan: RateScan, s: np.ndarray, s_t: np.ndarray, t: np.ndarray, t_px: np.ndarray,
                     sign: np.ndarray, n: np.ndarray, S: np.ndarray, H: np.ndarray, iterations: int
                     ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Steps 3–4 from the starting response ``H``: place the edges, solve, re-place with
    the new response until the placement no longer changes. Returns ``H``, its standard
    error, the residual RMS [nm] and the mask of the edges kept."""
    f_L = scan.line_rate_Hz
    keep = np.ones(t.size, bool)
    x_prev = None
    for _ in range(iterations):
        p = s_t + periodic_part(n, S, H, f_L, t)
        x, right = assign_positions(p, _velocity(s, n, S, H, f_L, t, t_px), sign, scan.period_nm)
        e = x - s_t
        H, se, resid = solve_harmonics(t, e, right, n, S, f_L, np.ones(t.size, bool))
        rms = float(np.median(np.abs(resid)) * 1.4826)
        keep = np.abs(resid) <= max(4.0 * rms, 1e-6 * scan.period_nm)
        H, se, resid = solve_harmonics(t, e, right, n, S, f_L, keep)
        if x_prev is not None and np.array_equal(x, x_prev):
            break
        x_prev = x
    return H, se, float(np.sqrt(np.mean(resid[keep] ** 2))), keep


def _velocity(s: np.ndarray, n: np.ndarray, S: np.ndarray, H: np.ndarray, f_L: float, t: np.ndarray,
              t_px: np.ndarray) -> np.ndarray:
    """Predicted velocity (sign is what matters) at the edge times: the static course's
    slope plus that of the periodic response found so far."""
    ds = np.interp(t, t_px[:-1] + 0.5 * (t_px[1] - t_px[0]), np.diff(s))
    ph = np.exp(2j * math.pi * f_L * np.outer(t, n))
    de = 2.0 * np.real(ph @ (2j * math.pi * f_L * n * H * S)) * (t_px[1] - t_px[0])
    return ds + de


# --------------------------------------------------------------------------- all rates
def response_frf(responses: list[RateResponse], max_rel_error: float) -> FRF:
    """The kept harmonics of every line rate as one :class:`FRF`, sorted by frequency;
    the weight (``coherence``, used as its square root) is ``min(1, 0.01/rel_err)²``."""
    f = np.concatenate([r.f_Hz for r in responses])
    G = np.concatenate([r.G for r in responses])
    rel = np.concatenate([r.rel_err for r in responses])
    ok = np.isfinite(rel) & (rel < max_rel_error) & np.isfinite(G) & (np.abs(G) > 0)
    o = np.argsort(f[ok], kind="stable")
    w = np.minimum(1.0, 0.01 / np.maximum(rel[ok][o], 1e-12)) ** 2
    return FRF(f[ok][o], G[ok][o], w)


#: a line rate whose edges fit its harmonics this many times worse than the median of the
#: rates kept so far (and worse than REJECT_FLOOR_NM) is left out: its edges were placed on
#: the wrong grating lines (ringing the response known so far did not predict)
REJECT_FACTOR, REJECT_FLOOR_NM = 4.0, 10.0


def placed_well(r: RateResponse, kept: list[RateResponse]) -> bool:
    """False when ``r``'s residual marks a failed placement (:data:`REJECT_FACTOR`); the
    first two rates are always kept."""
    if len(kept) < 2:
        return True
    return not (r.rms_nm > REJECT_FLOOR_NM and r.rms_nm > REJECT_FACTOR * float(np.median([q.rms_nm for q in kept])))


def _fit(frf: FRF, n_modes: int | None, n_lags: int, dt_s: float) -> tuple[int, np.ndarray, float]:
    if n_modes is None:
        return fit_mode_count(frf, n_lags, dt_s)
    x, rms = fit_frf(frf, n_modes, n_lags, dt_s)
    return n_modes, x, rms


def _unit_response(x: np.ndarray, n_modes: int, n_lags: int) -> Callable[[np.ndarray], np.ndarray]:
    """``f_Hz → G`` of a fitted parameter vector with its static gain divided out."""
    from .dynamics_identify import model_response

    return lambda f: model_response(x, f, n_modes, n_lags) / math.exp(x[0])


def identify_dynamics(scans: list[RateScan], static: StaticFn, *, n_modes: int | None = None, n_lags: int = 1,
                      f_max_Hz: float = 3000.0, max_rel_error: float = 0.2, static_error_nm: float = 1.0
                      ) -> tuple[Any, list[RateResponse]]:
    """Steps 1–5 of the module docstring over the line rates of ``scans`` (slowest
    first, each placed with the model fitted on the slower ones). Returns the
    :class:`~afmctl.compensators.dynamics.LinearDynamicsModel` and the per-rate
    responses."""
    from .dynamics import LinearDynamicsModel

    if not scans:
        raise ModelError("line_rate_Hz: no scan range faster than the static ones; the dynamics need grating "
                         f"images at line rates above {STATIC_MAX_LINE_RATE_HZ:g} lines/s (e.g. 10, 25, 50, 100)")
    order = sorted(scans, key=lambda sc: sc.line_rate_Hz)
    dt = min(sc.pixel_s for sc in order)
    responses: list[RateResponse] = []
    priors: list[Callable[[np.ndarray], np.ndarray]] = []
    fitted = None
    rejected: list[float] = []
    for sc in order:
        r = rate_response(sc, static, priors, f_max_Hz, static_error_nm)
        if not placed_well(r, responses):
            log.warning("image dynamics: %g lines/s left out: the edges fit the harmonics to %.3g nm RMS only "
                        "(the others to %.3g nm); the ringing was not followed", r.line_rate_Hz, r.rms_nm,
                        float(np.median([q.rms_nm for q in responses])))
            rejected.append(r.line_rate_Hz)
            continue
        responses.append(r)
        frf = response_frf(responses, max_rel_error)
        if frf.f_Hz.size >= 8:
            fitted = _fit(frf, n_modes, n_lags, dt)
            priors = [_unit_response(fitted[1], fitted[0], n_lags)]
    if fitted is None:
        raise ModelError(f"trace_nm/retrace_nm: only {frf.f_Hz.size} harmonics measured with a relative error "
                         f"< {max_rel_error:g}; need ≥ 8 (more line rates, or larger scan ranges)")
    nm, x, rms = fitted
    poles, tau, K = poles_of(x, nm, n_lags)
    info: dict[str, float | str] = {
        "source": "grating images", "line_rates_Hz": ", ".join(f"{r.line_rate_Hz:g}" for r in responses),
        "rates_left_out_Hz": ", ".join(f"{f:g}" for f in rejected) or "none",
        "static_gain_y_per_u": K, "fit_rms_log": rms, "f_min_Hz": float(frf.f_Hz[0]),
        "f_max_Hz": float(frf.f_Hz[-1]), "bins": float(frf.f_Hz.size), "fitted_delay_s": tau,
    }
    model = LinearDynamicsModel(poles_rad_per_s=[(float(p.real), float(p.imag)) for p in poles],
                                delay_s=max(0.0, tau), fit_info=info)
    return model, responses
