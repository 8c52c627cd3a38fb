"""Grating scans at several line rates, for identifying the scanner's linear dynamics from
images (:mod:`afmctl.compensators.image_dynamics`).

:func:`scan_grating_rates` scans one line of a grating repeatedly with the UNCOMPENSATED
scanner, a triangular voltage per line, at each line rate in turn. The result is a
:class:`~afmctl.sim_backend.image_scans.GratingScans` whose ``line_rate_Hz`` holds one
value per range — the ``--from-images`` file of ``afmctl identify --model …+dynamics``
(docs/SIM.md). The voltage is a ramp at the simulation's own step, so each pixel's
recorded voltage is the voltage at its centre; pixel i of a line at rate f_L is centred
at (i + ½)/(2·P·f_L) s after the line's start (trace, then retrace in time order).
"""
from __future__ import annotations

import logging
import math
from typing import Any, Literal

import numpy as np

from afmctl.compensators.base import ModelError
from .image_scans import GratingScans, scan_lines
from .samples import Grating1D

log = logging.getLogger(__name__)

#: line rates [lines/s] of the default dynamics scans (the divisors of 600 from 10 to 100):
#: harmonics near a 0.5–2 kHz mode at low orders, closely spaced from rate to rate so that
#: some fall within a lightly damped mode's peak, and the lag/delay at the lower rates.
#: Each is simulated with 600/rate samples per pixel, so all share one simulation step and
#: the scanner's drift predictor runs on unbroken
DEFAULT_RATES_HZ = (10.0, 12.0, 15.0, 20.0, 24.0, 25.0, 30.0, 40.0, 50.0, 60.0, 75.0, 100.0)
#: samples per pixel × line rate [lines/s] of the simulation (rates that divide it share
#: one step, 1/(2·pixels·600) s; others get the nearest step below that)
STEP_LINES_PER_S = 600.0
#: the ramp's slope stays below this fraction of the amplifier's slew limit
SLEW_MARGIN = 0.9


def ramp_span_V(line_rate_Hz: float, u_min_V: float, u_max_V: float, slew_V_per_s: float | None) -> float:
    """Top of the triangle [V]: ``u_max_V``, or lower so that the ramp (2·span·f_L V/s)
    stays within :data:`SLEW_MARGIN` of the slew limit."""
    span = u_max_V - u_min_V
    if slew_V_per_s:
        span = min(span, SLEW_MARGIN * slew_V_per_s / (2.0 * line_rate_Hz))
    return u_min_V + span


def line_voltages(lo_V: float, hi_V: float, pixels: int, spp: int) -> tuple[np.ndarray, np.ndarray]:
    """One line's voltages: per pixel centre (2P,) and per simulation sample (2P·spp,),
    trace ascending lo → hi then retrace descending, linear in time."""
    xi = (np.arange(pixels * spp) + 0.5) / spp - 0.5          # pixel coordinate of each sample
    u_samples = lo_V + (hi_V - lo_V) * xi / (pixels - 1)
    u_px = np.linspace(lo_V, hi_V, pixels)
    return np.concatenate([u_px, u_px[::-1]]), np.concatenate([u_samples, u_samples[::-1]])


def scan_grating_rates(scanner: Any, sample: Any | None = None, *, axis: Literal["x", "y"] = "x",
                       rates_Hz: tuple[float, ...] = DEFAULT_RATES_HZ, u_min_V: float = 1.0,
                       u_max_V: float = 121.0, pixels: int = 1024, lines: int = 5, skip_lines: int = 2,
                       keep_truth: bool = True) -> GratingScans:
    """Scan one line of ``sample`` (default: the 278 nm grating) ``lines`` times at every
    line rate in ``rates_Hz``, voltage ``u_min_V`` → top → ``u_min_V`` per line, the top
    from :func:`ramp_span_V` (the slew limit lowers it at fast rates). The other lateral
    axis and z are held at their lowest voltage. ``truth`` holds the true (t, u, x) of all
    the rates one after the other (t from each rate's start), for tests; the
    identification never reads it."""
    if axis not in ("x", "y"):
        raise ModelError(f"axis: {axis!r}; allowed 'x', 'y'")
    if sample is None:
        sample = Grating1D(period_nm=278.0, step_nm=20.0, duty=0.5, edge_nm=10.0, axis=axis)
    ia = 0 if axis == "x" else 1
    lim = scanner.voltage_limits_V()
    amp = getattr(scanner.config, axis).amplifier
    slew = amp.effective_slew_V_per_s()
    R = len(rates_Hz)
    u_px = np.empty((R, 2 * pixels))
    trace = np.empty((R, lines, pixels))
    retrace = np.empty((R, lines, pixels))
    truth: dict[str, list[np.ndarray]] = {"t_s": [], "u_V": [], "y_nm": []}
    for r, rate in enumerate(rates_Hz):
        hi = ramp_span_V(float(rate), u_min_V, u_max_V, slew)
        if not lim[ia, 0] <= u_min_V < hi <= lim[ia, 1]:
            raise ModelError(f"u_min_V/u_max_V: {u_min_V:g}…{hi:g} V outside {lim[ia, 0]:g}…{lim[ia, 1]:g} V")
        spp = max(1, math.ceil(STEP_LINES_PER_S / rate - 1e-9))
        dt = 1.0 / (2.0 * rate * pixels * spp)
        u_px[r], line = line_voltages(u_min_V, hi, pixels, spp)
        u, pos, h = scan_lines(scanner, sample, line, lines, ia, float(lim[1 - ia, 0]), dt, pixels, spp)
        trace[r], retrace[r] = h[:, 0], h[:, 1]
        if keep_truth:
            truth["t_s"].append((np.arange(u.shape[0]) + 0.5) * dt)
            truth["u_V"].append(u[:, ia].copy())
            truth["y_nm"].append(pos[:, ia].copy())
        log.info("rate scans on %s: %g lines/s, %g…%g V, %d samples per pixel", axis, rate, u_min_V, hi, spp)
    period = float(getattr(sample, "period_nm"))
    tr = {k: np.concatenate(v) for k, v in truth.items()} if keep_truth else {}
    return GratingScans(period, u_px[:, :pixels].copy(), u_px[:, pixels:].copy(), trace, retrace, skip_lines, axis,
                        np.asarray(rates_Hz, dtype=np.float64), tr)
