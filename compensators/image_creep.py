"""A hysteresis + creep chain from slow grating images — no position sensor.

The slow scans of :mod:`afmctl.compensators.image_identify` (one grating line scanned
with a triangle u_min → u_max → u_min, several ranges) are turned into a *virtual sensor
record* ``(t, u, y)``, and the sensor path's own joint fit
(:meth:`afmctl.compensators.chain.ChainModel.identify`, structure ``preisach+creep``)
is run on it:

1. time: the ranges were scanned in the file's order, each range's lines back to back,
   without pauses, at ``line_rate_Hz``; pixel i of a trace is centred at
   ``(i + ½)/(2·P·f_L)`` s after its line's start, the retrace's pixels follow (the
   convention of :mod:`afmctl.compensators.image_dynamics`);
2. a first static model (the Preisach model of the images' reversal curves, ``pre``)
   predicts ``s(t)`` for the whole voltage sequence;
3. every grating edge of every line (mid-height crossings,
   :func:`~afmctl.compensators.image_dynamics.scan_edges`) is placed on the grating
   lattice from ``s`` (:func:`~afmctl.compensators.image_dynamics.assign_positions`):
   the tip's true position ``x_k`` at ``t_k``; where ``s`` is off by more than half a
   period (strong creep) the placement jumps by a period, which is undone from edge to
   edge in time order (:func:`unwrap_periods`);
4. ``y(t) = s(t) + r(t)``, ``r`` the residual ``x_k − s(t_k)`` (outliers beyond 5 robust
   σ dropped) interpolated linearly between edges — the part of the motion the static
   model misses (creep, the hysteresis' misfit), which is smooth, while ``s`` carries the
   turnarounds where no edge is seen. The lattice leaves one constant open: the scans
   are taken to start at rest at u_min, where ``y = s`` (``r`` is zero at the first
   edges; the static model is 0 there, out of negative saturation).

The record is uniform at the pixel period. Creep slower than the whole scan (about a
minute for the default 15 ranges × 4 lines at 1 line/s) is not seen.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import numpy as np

from .base import ModelError
from .image_dynamics import RateScan, assign_positions, line_rates, scan_edges

log = logging.getLogger(__name__)


def slow_scan_sequence(scans: Mapping[str, Any]) -> tuple[list[RateScan], float]:
    """The slow scan arrays (checked) as one :class:`RateScan` per range, in scan order,
    every line used (``skip`` 0), and the pixel period [s]."""
    from .image_identify import check_scans

    s = check_scans(scans)
    R = s["u_trace_V"].shape[0]
    rates = line_rates(scans, R)
    if np.ptp(rates) > 0:
        raise ModelError(f"line_rate_Hz: the slow scans differ in line rate ({rates.tolist()}); "
                         "creep from images needs one line rate for all of them")
    period = float(s["period_nm"].reshape(-1)[0])
    seq = [RateScan(np.concatenate([s["u_trace_V"][r], s["u_retrace_V"][r]]), s["trace_nm"][r],
                    s["retrace_nm"][r], float(rates[r]), period, 0) for r in range(R)]
    return seq, seq[0].pixel_s


def virtual_record(scans: Mapping[str, Any], static: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps 1–4 of the module docstring: ``(t_s, u_V, y_nm)`` at the pixel period, from the
    slow scan arrays and a first static model ``static`` (forward operator u → nm)."""
    seq, T = slow_scan_sequence(scans)
    u = np.concatenate([np.tile(sc.u_line_V, sc.trace_nm.shape[0]) for sc in seq])
    t = (np.arange(u.size) + 0.5) * T
    s = static.forward(T).block(np.ascontiguousarray(u))
    tk_parts, sign_parts, t0 = [], [], 0.0
    for sc in seq:
        te, sg = scan_edges(sc)
        tk_parts.append(te + t0)
        sign_parts.append(sg)
        t0 += sc.trace_nm.shape[0] * sc.u_line_V.size * T
    tk, sign = np.concatenate(tk_parts), np.concatenate(sign_parts)
    if tk.size < 16:
        raise ModelError(f"trace_nm/retrace_nm: {tk.size} grating edges in the slow scans; need ≥ 16")
    sk = np.interp(tk, t, s)
    v = np.interp(tk, t[:-1] + 0.5 * T, np.diff(s))
    x, _ = assign_positions(sk, v, sign, seq[0].period_nm)
    r = unwrap_periods(x - sk, seq[0].period_nm)
    dev = np.abs(r - np.median(r))
    ok = dev <= 5.0 * (1.4826 * float(np.median(dev)) + 1e-9)
    r -= float(np.median(r[ok][:3]))      # the scan starts at rest: y = s at the first edges
    y = s + np.interp(t, tk[ok], r[ok])
    log.info("creep from images: %d edges (%d kept), residual to the static model %.3g nm RMS",
             tk.size, int(np.count_nonzero(ok)), float(np.sqrt(np.mean(r[ok] ** 2))))
    return t, u, y


def unwrap_periods(r_nm: np.ndarray, period_nm: float) -> np.ndarray:
    """Residuals of consecutive edges (time order) with whole-period jumps removed: the
    motion the static model misses changes little from one edge to the next, so a jump of
    about a period is an edge placed on the wrong grating line."""
    jumps = np.round(np.diff(r_nm) / period_nm)
    return r_nm - period_nm * np.concatenate([[0.0], np.cumsum(jumps)])


def identify_static_chain(scans: Mapping[str, Any], n_operators: int | None = None, first: Any = None,
                          **options: Any) -> Any:
    """preisach+creep from the slow scans: the images' Preisach model ``first`` (fitted
    here by :func:`~afmctl.compensators.image_identify.identify_from_images` when None),
    the virtual record, and :meth:`ChainModel.identify` on it. ``options`` go to both
    Preisach fits."""
    from .chain import ChainModel
    from .image_identify import identify_from_images

    if first is None:
        first = identify_from_images(scans, kind="preisach", n_operators=n_operators, **options)
    t, u, y = virtual_record(scans, first)
    opts = dict(options)
    opts.setdefault("u_min_V", float(first.voltage_range_V()[0]) if first.voltage_range_V() else float(u.min()))
    opts.setdefault("u_max_V", float(first.voltage_range_V()[1]) if first.voltage_range_V() else float(u.max()))
    return ChainModel.identify(t, u, y, n_operators=n_operators, structure="preisach+creep", **opts)
