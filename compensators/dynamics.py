"""Linear scanner dynamics (amplifier bandwidth, structural modes, delay) as a model file.

``kind = "dynamics"``: a stable continuous LTI system with a pure delay and unit DC gain,
input and output in nm. It is the last stage of the Hammerstein chain
hysteresis → creep → dynamics (the static stages map V → nm, this one shapes the nm in
time)::

    G(s) = k · Π(s − z_i) / Π(s − p_i) · e^{−s·delay_s},   G(0) = 1

Poles and zeros are stored as ``[re, im]`` pairs in rad/s (complex ones with their
conjugate). :class:`LinearDynamicsModel` gives

* ``forward(dt_s)`` — zero-order-hold discretisation (exact for a held input, fractional
  delay included) as a streaming operator, :mod:`afmctl.compensators.lti`;
* ``inverse(dt_s, preview_s=None)`` — a causal preview inverse with a fixed, reported
  latency (``latency_samples``), :mod:`afmctl.compensators.dynamics_inverse`;
* ``inverse_offline(y_nm, dt_s)`` — the stable non-causal inverse over a whole known
  trajectory (handles delays and non-minimum-phase zeros);
* ``identify(t_s, u, y_nm)`` — frequency response from a small-signal excitation fitted
  by a stable transfer function, :mod:`afmctl.compensators.dynamics_identify`.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, FiniteFloat, model_validator

from .base import ModelError
from .dynamics_inverse import InverseTaps, PreviewInverse, apply_offline, inverse_taps
from .input_checks import block_samples
from .lti import DiscreteLTI, LTIOperator, discretise, frequency_response
from .models import HysteresisModel

Pair = tuple[FiniteFloat, FiniteFloat]


def _complex(pairs: list[Pair]) -> np.ndarray:
    return np.array([complex(re, im) for re, im in pairs], dtype=complex)


def _check_conjugates(name: str, values: np.ndarray) -> None:
    for v in values:
        if abs(v.imag) > 0 and not np.any(np.isclose(values, np.conj(v), rtol=1e-9, atol=1e-9)):
            raise ValueError(f"{name}: {v.real:g}{v.imag:+g}j has no conjugate partner; "
                             "complex values must come in conjugate pairs")


def first_mode_Hz(poles_rad_per_s: np.ndarray) -> float:
    """The first structural mode [Hz]: the natural frequency of the lowest complex pole pair;
    the slowest pole when every pole is real (nothing but lags); 0 without poles."""
    p = np.asarray(poles_rad_per_s, dtype=complex)
    if p.size == 0:
        return 0.0
    modes = p[np.abs(p.imag) > 0]
    return float(np.min(np.abs(modes if modes.size else p))) / (2 * math.pi)


class LinearDynamicsModel(HysteresisModel):
    """Unit-DC-gain LTI dynamics with delay (``kind = "dynamics"``), nm → nm."""

    kind: Literal["dynamics"] = "dynamics"
    time_dependent: ClassVar[bool] = True
    has_own_delay: ClassVar[bool] = True
    poles_rad_per_s: list[Pair] = Field(default_factory=list, max_length=40,
                                        description="poles [re, im] in rad/s, re < 0")
    zeros_rad_per_s: list[Pair] = Field(default_factory=list, max_length=40,
                                        description="zeros [re, im] in rad/s, not at 0")
    delay_s: FiniteFloat = Field(0.0, ge=0.0, le=1.0, description="pure delay [s]")
    lead_samples: FiniteFloat = Field(0.0, ge=0.0, le=1.0, description=(
        "the record's output is read this fraction of a sample period after each command "
        "(1: at the end of each hold interval); a sampling convention, so in samples; only with delay_s = 0"))
    initial_nm: FiniteFloat = Field(0.0, description="input and output at rest before the first sample [nm]")
    bandwidth_Hz: FiniteFloat | None = Field(None, gt=0, description="band limit of the inverse [Hz]; "
                                             "null = 1.5 × the first structural mode (the slowest pole without one)")
    regularisation: FiniteFloat = Field(1e-3, ge=0, le=10, description="Tikhonov λ of the inverse")
    fit_info: dict[str, float | str] | None = Field(None, description="identification summary")

    @model_validator(mode="after")
    def _check(self) -> "LinearDynamicsModel":
        p, z = self.poles(), self.zeros()
        if np.any(p.real >= 0):
            raise ValueError("poles_rad_per_s: every pole needs a negative real part (a stable system)")
        if np.any(np.abs(z) < 1e-12):
            raise ValueError("zeros_rad_per_s: a zero at s = 0 has no unit DC gain")
        if z.size > p.size:
            raise ValueError(f"zeros_rad_per_s: {z.size} zeros but {p.size} poles; need no more zeros than poles")
        _check_conjugates("poles_rad_per_s", p)
        _check_conjugates("zeros_rad_per_s", z)
        if self.lead_samples > 0 and self.delay_s > 0:
            raise ValueError("lead_samples: a lead only goes with delay_s = 0 (the output is read either late or early)")
        return self

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_modes(cls, modes: Sequence[tuple[float, float]] = (), real_poles_Hz: Sequence[float] = (),
                   delay_s: float = 0.0, **fields: Any) -> "LinearDynamicsModel":
        """Second-order modes ``(f_Hz, ζ)`` and first-order lags ``f_Hz`` in series."""
        poles: list[Pair] = []
        for f, zeta in modes:
            w = 2 * math.pi * float(f)
            if not (0 < zeta < 1):
                raise ModelError(f"modes: damping {zeta!r}; allowed 0 < ζ < 1")
            re, im = -zeta * w, w * math.sqrt(1 - zeta * zeta)
            poles += [(re, im), (re, -im)]
        poles += [(-2 * math.pi * float(f), 0.0) for f in real_poles_Hz]
        return cls(poles_rad_per_s=poles, delay_s=delay_s, **fields)

    def poles(self) -> np.ndarray:
        return _complex(self.poles_rad_per_s)

    def zeros(self) -> np.ndarray:
        return _complex(self.zeros_rad_per_s)

    def frequency_response(self, f_Hz: np.ndarray) -> np.ndarray:
        """Continuous ``G(j2πf)`` (complex, dimensionless) at ``f_Hz`` [Hz]."""
        return frequency_response(self.zeros(), self.poles(), self.delay_s, f_Hz)

    def discrete(self, dt_s: float | None) -> DiscreteLTI:
        """Zero-order-hold discretisation at ``dt_s`` [s]."""
        if dt_s is None:
            raise ModelError("dt_s: None; the dynamics model needs a sample period > 0 s")
        return discretise(self.zeros(), self.poles(), self.delay_s, float(dt_s), float(self.lead_samples))

    def inverse_bandwidth_Hz(self, dt_s: float) -> float:
        """Band limit of the inverse [Hz]: ``bandwidth_Hz``, or 1.5 × the first structural
        mode (the lowest complex pole pair's natural frequency: above it the inverse's gain
        grows as f², and the sharp corners of a raster would need more voltage and slew than
        an amplifier has). A first-order lag below that mode (an amplifier's bandwidth under
        a large capacitance) does not set the limit: its inverse only grows as f, and a
        band stopping below the mode would leave the mode uncancelled (#36: a 354 Hz lag put
        the band at 531 Hz, under a 648 Hz mode). Without a mode, 1.5 × the slowest pole.
        At most 45 % of the sample rate."""
        if self.bandwidth_Hz is not None:
            bw = float(self.bandwidth_Hz)
        else:
            bw = 1.5 * first_mode_Hz(self.poles()) if self.poles().size else 0.45 / dt_s
        return min(bw, 0.45 / dt_s)

    # ------------------------------------------------------------------ operators
    def forward(self, dt_s: float | None = None, initial_nm: float | None = None) -> LTIOperator:
        """Operator y_static [nm] → y [nm] at sample period ``dt_s`` [s]."""
        init = self.initial_nm if initial_nm is None else initial_nm
        return LTIOperator(self.discrete(dt_s), init)

    def taps(self, dt_s: float, preview_s: float | None = None) -> InverseTaps:
        """The inverse filter at ``dt_s`` (see :mod:`afmctl.compensators.dynamics_inverse`)."""
        sys = self.discrete(dt_s)
        preview = None
        if preview_s is not None:
            if not (math.isfinite(preview_s) and preview_s >= 0):
                raise ModelError(f"preview_s: {preview_s!r}; need ≥ 0 s")
            preview = int(round(preview_s / float(dt_s)))
        return inverse_taps(sys, self.inverse_bandwidth_Hz(float(dt_s)), float(self.regularisation), preview)

    def inverse(self, dt_s: float | None = None, preview_s: float | None = None,
                initial_nm: float | None = None) -> PreviewInverse:
        """Causal preview inverse target [nm] → static-stage output [nm]. Its output lags
        the target by ``latency_samples`` (the preview; automatic when ``preview_s`` is
        None: long enough for all but 1e-10 of the inverse's energy). At rest at
        ``initial_nm`` [nm] before its first target, or (None) at its first target, as a run
        starts: the scanner was brought there and held (the approach and the settle hold),
        and :attr:`initial_nm` is where the identification record began, not where a run
        does (a run starting 8.5 µm away rang at its first samples and left the hysteresis
        memory where the model did not expect it). The offline inverse holds its first
        target before it too."""
        if dt_s is None:
            raise ModelError("dt_s: None; the dynamics model needs a sample period > 0 s")
        return PreviewInverse(self.taps(float(dt_s), preview_s), initial_nm)

    def inverse_offline(self, y_nm: np.ndarray, dt_s: float) -> np.ndarray:
        """Stable non-causal inverse of a whole trajectory ``y_nm`` sampled at ``dt_s``:
        the static-stage output [nm] that makes the dynamics follow ``y_nm`` (band-limited
        to :meth:`inverse_bandwidth_Hz`). The trajectory is taken at rest before its first
        and after its last sample."""
        y = block_samples("y_nm", y_nm)
        if y.size == 0:
            return y.copy()
        return apply_offline(self.taps(float(dt_s)), y)

    # ------------------------------------------------------------------ identification
    @classmethod
    def identify(cls, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, **options: Any) -> "LinearDynamicsModel":
        """Fit from a small-signal excitation (chirp, multisine, PRBS around a DC offset);
        ``u`` in any unit (V or nm), the static gain is reported and then divided out.
        Options: see :func:`afmctl.compensators.dynamics_identify.fit_dynamics`."""
        from .dynamics_identify import fit_dynamics

        from .fit_health import note_problem

        fit = fit_dynamics(t_s, u_V, y_nm, **options)
        model = cls(poles_rad_per_s=[(float(p.real), float(p.imag)) for p in fit.poles],
                   zeros_rad_per_s=[(float(z.real), float(z.imag)) for z in fit.zeros],
                   delay_s=fit.delay_s, lead_samples=fit.lead_samples,
                   initial_nm=float(np.asarray(y_nm, dtype=float)[0]), fit_info=fit.info)
        if "problem" in fit.info:
            note_problem(model, str(fit.info["problem"]))
        return model

    def predict_linear(self, t_s: np.ndarray, u: np.ndarray, y_nm: np.ndarray, dt_s: float) -> np.ndarray:
        """What the fitted linear model says ``y`` [nm] was for input ``u``, over each part
        of the record it was fitted on (:meth:`fitted_spans`; NaN elsewhere): the static
        gain of ``fit_info`` times the dynamics' response to the input's change within the
        part, plus the part's mean offset (for the residual ``afmctl identify`` prints)."""
        u = block_samples("u", u)
        info = self.fit_info or {}
        gain = float(info.get("static_gain_y_per_u", 1.0))
        t = np.asarray(t_s, dtype=float)
        y = np.asarray(y_nm, dtype=float)
        out = np.full(u.size, np.nan)
        for t0, t1 in self.fitted_spans():
            sel = (t >= t0) & (t <= t1)
            if np.count_nonzero(sel):
                us = u[sel]
                g = gain * (self.forward(dt_s, initial_nm=float(us[0])).block(us) - float(us[0]))
                out[sel] = g + float(np.mean(y[sel] - g))
        return out

    def fitted_spans(self) -> list[tuple[float, float]]:
        """``(t0, t1)`` [s] of each part of the record the response was measured on
        (``fit_info["fit_spans_s"]``; a file from before it was recorded: ``fit_t0_s`` …
        ``fit_t1_s``; none: the whole record)."""
        info = self.fit_info or {}
        try:
            v = [float(x) for x in str(info.get("fit_spans_s", "")).split()]
        except ValueError:                     # an edited file: the outer bounds below
            v = []
        if v and len(v) % 2 == 0:
            return list(zip(v[::2], v[1::2]))
        return [(float(info.get("fit_t0_s", -np.inf)), float(info.get("fit_t1_s", np.inf)))]

    def summary(self) -> str:
        lines = ["model            : linear dynamics, unit DC gain, with delay (kind dynamics)",
                 f"delay            : {self.delay_s * 1e6:.4g} µs"
                 + (f" (output read {self.lead_samples:.3g} sample after each command)" if self.lead_samples else "")]
        for p in self.poles():
            if p.imag < 0:
                continue
            f = abs(p) / (2 * math.pi)
            zeta = -p.real / abs(p)
            kind = "mode" if p.imag > 0 else "lag "
            lines.append(f"  {kind} {f:10.5g} Hz" + (f"  ζ = {zeta:.4g}" if p.imag > 0 else ""))
        for z in self.zeros():
            if z.imag >= 0:
                lines.append(f"  zero {abs(z) / (2 * math.pi):10.5g} Hz  re {z.real:+.4g} rad/s")
        if self.fit_info:
            lines += [f"  fit {k}: {v}" for k, v in self.fit_info.items()]
        return "\n".join(lines)
