"""Thermal drift from ambient temperature and piezo heat: transfer functions and a
streaming predictor (drift paper: Korayem & Sadeghzadeh, Scientia Iranica F 17(2) 2010,
eqs. 7–9 and Appendix eqs. A1–A11, Table A1).

Drift sources (inputs, in this order inside the predictor):

* ``T``  — change of the ambient temperature from its value at reset / first sample [K]
* ``Qx``, ``Qy``, ``Qz`` — heat generated in the tube by the x, y, z voltages [W]
  (eq. 8, :mod:`afmctl.compensators.heat`)

Drift (outputs) ``x, y, z`` [nm] is the sum over the paths ``G_IJ`` (drift in direction
``I`` from source ``J``), e.g. ``x = G_xT·ΔT + G_xQx·Qx + G_xQy·Qy (+ G_xQz·Qz)``.

Path forms (Appendix):

* gain/zero/pole/delay (eqs. A1–A4, A6, A7, A9), :class:`TransferPath`::

      G(s) = K · Π(1 + Tz_i·s) · exp(−Td·s) / ( s^n · Π(1 + Tp_j·s) · [1 + 2ζTw·s + (Tw·s)²] )

* discrete state space identified at a sample period ``Ts`` (eqs. A5, A8; G_yQx, G_yQy),
  :class:`StateSpacePath`: ``x[k+1] = A x[k] + B u[k]``, ``y[k] = C x[k] + D u[k]``
  (the innovation term ``K·e`` of the identified model is zero for prediction).

Discretisation (done once in :meth:`DriftParams.predictor`):

* continuous paths are built as a cascade of first/second-order sections (well
  conditioned even for time constants from 1 ms to 1e6 s) and discretised exactly for a
  zero-order-held input (matrix exponential of the augmented system, as
  ``scipy.signal.cont2discrete`` method ``zoh``) at the loop
  period ``dt_s``. A lag whose time constant is below ``1e-6·dt_s`` is taken as a static
  gain (its settling is below 1e-6 of a sample);
* pure delays are an integer-sample ring buffer, ``round(Td/dt_s)`` samples;
* a discrete state-space path runs at its own period ``Ts_s``: its input is averaged over
  ``m = max(1, round(Ts_s/dt_s))`` loop samples, its state advances every ``m`` samples
  and its output is held in between. Its effective period is ``m·dt_s``.

Output timing: ``drift[k] = C·x[k] + D·u[k]``, then ``x[k+1] = A·x[k] + B·u[k]``; every
shipped path is strictly proper, so the drift at sample ``k`` responds to inputs up to
``k−1`` (no response before the input changes).

The per-sample and block paths run the same numba kernel (:func:`_drift_kernel`), so a
signal fed in blocks of any size gives bit-identical output to per-sample stepping; the
plain-python :func:`drift_reference` does the same arithmetic and is tested equal.

Named parameter sets (:meth:`DriftParams.named`): ``"table_a1"`` (the paper's Table A1
and eqs. A10–A11, with its doubts in ``DriftParams.doubts``) and ``"physical_tube"`` (a
40 mm PZT tube: thermal expansion with a thermal time constant; the default).
"""
from __future__ import annotations

import functools
import json
import logging
import math
from pathlib import Path
from collections.abc import Callable
from typing import Annotated, Any, Literal, Union

import numba
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .base import ModelError, check_finite
from .heat import AxisHeat, HeatParams, TubeGeometry
from .errortext import format_validation_error, plain_repr
from .textfiles import read_json_file
from .temperature import T_MAX_C, T_MIN_C

log = logging.getLogger(__name__)

#: source names, in the predictor's input-channel order
SOURCES = ("T", "Qx", "Qy", "Qz")
#: output axes
AXES = ("x", "y", "z")
#: path names ``<axis><source>``, the order they are assembled in
PATH_NAMES = tuple(f"{a}{s}" for s in SOURCES for a in AXES)

#: a lag faster than this fraction of the sample period is taken as a static gain
_STIFF_FRACTION = 1e-6
#: largest delay ring buffer (samples) a predictor will allocate
MAX_DELAY_SAMPLES = 10_000_000


# --------------------------------------------------------------------------- parameters
class SecondOrder(BaseModel):
    """Second-order factor ``1/(1 + 2ζ·Tw·s + (Tw·s)²)`` (eq. A7)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)   # every number finite

    Tw_s: float = Field(gt=0, le=1e9, description="time constant Tw [s]")
    zeta: float = Field(gt=0, le=1e12, description="damping ratio ζ (dimensionless)")


class TransferPath(BaseModel):
    """Gain/zero/pole/delay transfer function (eqs. A1–A4, A6, A7, A9).

    ``G(s) = K·Π(1+Tz·s)·exp(−Td·s) / (s^integrators·Π(1+Tp·s)·[second order])``.

    Units: ``K`` is drift per source unit (per K for temperature paths, per W for heat
    paths), per second for each integrator, in the set's output unit (nm times
    :attr:`DriftParams.output_scale_nm`). Time constants and delay in seconds. Zero time
    constants may be negative (non-minimum-phase zeros, e.g. G_xT of Table A1); pole
    time constants must be positive (stable). The transfer function must be proper.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)   # every number finite

    form: Literal["tf"] = "tf"
    K: float = Field(0.0, description="gain K (output unit per source unit [per s per integrator])")
    zeros_s: list[float] = Field(default_factory=list, description="zero time constants Tz [s]")
    poles_s: list[float] = Field(default_factory=list, description="pole time constants Tp [s], > 0")
    integrators: int = Field(0, ge=0, le=2, description="number of 1/s factors")
    second_order: SecondOrder | None = None
    delay_s: float = Field(0.0, ge=0, le=1e6, description="pure delay Td [s]")

    @field_validator("zeros_s", "poles_s")
    @classmethod
    def _finite(cls, v: list[float], info) -> list[float]:
        for i, x in enumerate(v):
            if not math.isfinite(x) or abs(x) > 1e12:
                raise ValueError(f"{info.field_name}[{i}] = {x!r}; must be finite and |value| <= 1e12 s")
        if info.field_name == "poles_s":
            for i, x in enumerate(v):
                if x <= 0:
                    raise ValueError(f"poles_s[{i}] = {x!r} s; pole time constants must be > 0 (stable)")
        return v

    @model_validator(mode="after")
    def _proper(self) -> "TransferPath":
        n_den = len(self.poles_s) + self.integrators + (2 if self.second_order else 0)
        if len(self.zeros_s) > n_den:
            raise ValueError(f"zeros_s: {len(self.zeros_s)} zeros but only {n_den} poles; "
                             "the transfer function must be proper (zeros <= poles)")
        return self


class StateSpacePath(BaseModel):
    """Discrete state space identified at period ``Ts_s`` (eqs. A5, A8).

    ``x[k+1] = A·x[k] + B·u[k]``, ``y[k] = C·x[k] + D·u[k]`` with ``u`` the source (K or W)
    averaged over one period ``Ts_s`` and ``y`` in the set's output unit. ``K_innov`` is
    the identified innovation gain, kept for the record; prediction uses ``e = 0``.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)   # every number finite

    form: Literal["ss"] = "ss"
    A: list[list[float]]
    B: list[float]
    C: list[float]
    D: float = 0.0
    K_innov: list[float] | None = None
    Ts_s: float = Field(1.0, gt=0, le=1e5, description="sample period of the identified model [s]")
    delay_s: float = Field(0.0, ge=0, le=1e6, description="pure delay [s]")

    @model_validator(mode="after")
    def _shapes(self) -> "StateSpacePath":
        n = len(self.A)
        if n == 0 or n > 20:
            raise ValueError(f"A: {n} states; allowed 1..20")
        if any(len(row) != n for row in self.A):
            raise ValueError("A: must be square")
        if len(self.B) != n or len(self.C) != n:
            raise ValueError(f"B, C: need {n} entries each (as many as A has rows)")
        vals = [v for row in self.A for v in row] + list(self.B) + list(self.C) + [self.D]
        if not all(math.isfinite(v) for v in vals):
            raise ValueError("A, B, C, D: all entries must be finite")
        return self


Path_ = Annotated[Union[TransferPath, StateSpacePath], Field(discriminator="form")]


class DriftPaths(BaseModel):
    """The drift paths ``G_<axis><source>``; a missing path contributes nothing.

    The paper gives xT, yT, zT, xQx, yQx, zQx, xQy, yQy, zQy; xQz, yQz, zQz are
    extensions (the paper treats the z voltage as independent and gives no function).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)   # every number finite

    xT: Path_ | None = None
    yT: Path_ | None = None
    zT: Path_ | None = None
    xQx: Path_ | None = None
    yQx: Path_ | None = None
    zQx: Path_ | None = None
    xQy: Path_ | None = None
    yQy: Path_ | None = None
    zQy: Path_ | None = None
    xQz: Path_ | None = None
    yQz: Path_ | None = None
    zQz: Path_ | None = None


class DriftParams(BaseModel):
    """Everything the drift predictor needs; JSON-serialisable (``kind`` = ``"drift"``).

    * ``paths`` — transfer functions from sources to drift (see :class:`DriftPaths`);
    * ``heat`` — eq. 8 coefficients per axis (:class:`afmctl.compensators.heat.AxisHeat`);
    * ``output_scale_nm`` — nm per output unit of the paths (1 when the paths give nm;
      1e9 for Table A1, whose outputs we read as metres);
    * ``doubts`` — free-text notes on doubtful entries (Table A1 has several).

    ``DriftParams.named("physical_tube" | "table_a1")`` gives the shipped sets;
    ``params.predictor(dt_s)`` builds a :class:`DriftPredictor`.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)   # every number finite

    kind: Literal["drift"] = "drift"
    name: str = "custom"
    description: str = ""
    output_scale_nm: float = Field(1.0, gt=0, le=1e12, description="nm per path output unit")
    paths: DriftPaths = Field(default_factory=DriftPaths)
    heat: AxisHeat = Field(default_factory=AxisHeat)
    doubts: list[str] = Field(default_factory=list)

    # ------------------------------------------------------------------ named sets
    @classmethod
    def named(cls, name: str) -> "DriftParams":
        """A shipped parameter set: ``"physical_tube"`` or ``"table_a1"``."""
        builders: dict[str, Callable[[], DriftParams]] = {"physical_tube": physical_tube_params,
                                                          "table_a1": table_a1_params}
        try:
            return builders[name]()
        except KeyError:
            raise ModelError(f"params: unknown drift parameter set {name!r}; "
                             f"allowed: {', '.join(sorted(builders))} or a JSON file") from None

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return ("physical_tube", "table_a1")

    # ------------------------------------------------------------------ I/O
    @classmethod
    def from_dict(cls, data: object, where: str = "drift params") -> "DriftParams":
        if not isinstance(data, dict):
            raise ModelError(f"{where}: expected a JSON object with kind 'drift'")
        try:
            return cls.model_validate(data)
        except ValidationError as err:
            raise ModelError(format_validation_error(err, where)) from None

    @classmethod
    def load(cls, path: str | Path) -> "DriftParams":
        """Read a JSON file written by :meth:`save` (or by hand)."""
        return cls.from_dict(read_json_file(path, "drift parameter file"), where=str(path))

    @classmethod
    def from_spec(cls, spec: str | Path, overrides: dict[str, Any] | None = None,
                  where: str = "params") -> "DriftParams":
        """The one drift-parameter loader: a named set (:meth:`names`) or a JSON file, with
        field ``overrides`` merged in. Errors are one-line :class:`ModelError` naming ``where``
        (the option or config field) and the file."""
        spec = str(spec)
        if spec in cls.names():
            if not overrides:
                return cls.named(spec)
            data, origin = cls.named(spec).model_dump(), where
        elif Path(spec).exists():
            data, origin = read_json_file(spec, "drift parameter file"), spec
        else:
            raise ModelError(f"{where}: {spec!r} is neither a file nor a named set "
                             f"({', '.join(cls.names())})")
        if overrides:
            if not isinstance(data, dict):
                raise ModelError(f"{origin}: expected a JSON object with kind 'drift'")
            data = {**data, **overrides}
        return cls.from_dict(data, where=origin)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.model_dump(mode="json"), indent=2) + "\n", encoding="utf-8")

    def scaled(self, factor: float) -> "DriftParams":
        """A copy with every path gain multiplied by ``factor`` (e.g. 1.3 for "30 % off")."""
        p = self.model_copy(deep=True)
        for name in PATH_NAMES:
            path = getattr(p.paths, name)
            if isinstance(path, TransferPath):
                path.K *= factor
            elif isinstance(path, StateSpacePath):
                path.C = [c * factor for c in path.C]
                path.D *= factor
        p.name = f"{self.name}*{factor:g}"
        return p

    # ------------------------------------------------------------------ predictor
    def predictor(self, dt_s: float) -> "DriftPredictor":
        """A streaming predictor at loop period ``dt_s`` [s] (see :class:`DriftPredictor`)."""
        return DriftPredictor(self, dt_s)


# --------------------------------------------------------------------------- named sets
def physical_tube_params(alpha_per_K: float = 1.0e-6, length_m: float = 0.040,
                         outer_diameter_m: float = 6.35e-3, asymmetry_x: float = 0.016,
                         asymmetry_y: float = 0.0095, tau_ambient_s: float = 120.0,
                         R_th_K_per_W: float = 125.0, tau_heat_s: float = 146.0) -> DriftParams:
    """A simple physical set for a 40 mm PZT tube (the default for the simulator).

    * axial (z): thermal expansion ``α·L`` per kelvin of tube temperature
      (α = 1e-6 /K, within Table 2's 1–5e-6 for PZT-5H; 40 mm → 40 nm/K);
    * lateral (x, y): a fraction ``a`` of the axial expansion differs between opposite
      sides of the tube and bends it; the free end moves ``a·α·L²/(2·d_out)`` per kelvin
      (≈126 nm/K per unit asymmetry); a = 1.6 % (x) and 0.95 % (y) give 2.0 and 1.2 nm/K,
      which reproduces the nonlinearities paper's ≈3.3 nm for 2 °C over a 10 min scan;
    * the tube follows the ambient with a first-order lag ``τ_ambient`` (120 s);
    * heat (eq. 8) warms the tube through a thermal resistance ``R_th`` (125 K/W: h≈10
      W/m²K on the 8 cm² outer surface) with time constant ``τ_heat`` = m·c·R_th (2.8 g
      of PZT, c = 420 J/(kg·K) → ≈146 s). Heat in the x (y) quadrants bends the tube in x
      (y) as a fully asymmetric expansion and lengthens it by half; z heat lengthens it.
    """
    axial = alpha_per_K * length_m * 1e9                                  # nm/K
    bend = alpha_per_K * length_m ** 2 / (2.0 * outer_diameter_m) * 1e9  # nm/K per unit asymmetry

    def lag(K: float, tau: float) -> TransferPath:
        return TransferPath(K=K, poles_s=[tau])

    tube = TubeGeometry(length_m=length_m, outer_diameter_m=outer_diameter_m)
    heat = HeatParams(tube=tube)
    paths = DriftPaths(
        xT=lag(asymmetry_x * bend, tau_ambient_s),
        yT=lag(asymmetry_y * bend, tau_ambient_s),
        zT=lag(axial, tau_ambient_s),
        xQx=lag(bend * R_th_K_per_W, tau_heat_s),
        zQx=lag(0.5 * axial * R_th_K_per_W, tau_heat_s),
        yQy=lag(bend * R_th_K_per_W, tau_heat_s),
        zQy=lag(0.5 * axial * R_th_K_per_W, tau_heat_s),
        zQz=lag(axial * R_th_K_per_W, tau_heat_s),
    )
    return DriftParams(
        name="physical_tube",
        description=(f"40 mm PZT tube: α={alpha_per_K:g}/K, L={length_m:g} m, d_out={outer_diameter_m:g} m, "
                     f"lateral asymmetry x={asymmetry_x:g}, y={asymmetry_y:g}, τ_ambient={tau_ambient_s:g} s, "
                     f"R_th={R_th_K_per_W:g} K/W, τ_heat={tau_heat_s:g} s; outputs in nm"),
        output_scale_nm=1.0,
        paths=paths,
        heat=AxisHeat(x=heat, y=heat, z=heat),
    )


#: Doubts about Table A1 / eqs. A1–A11 (also in docs/DRIFT.md).
TABLE_A1_DOUBTS = [
    "Units are not stated. We read K as metres per kelvin (temperature paths) and metres "
    "per watt (heat paths), time constants in seconds; output_scale_nm = 1e9.",
    "G_zT: K = 7.7e-3 with Tz/Tp1 = 6327.3/84732.9 gives ~0.6 mm/K within minutes if read "
    "in metres, against the paper's ~100 nm (Fig. 11): K or its exponent is probably damaged.",
    "G_yT: K = 7.35e-17 makes the y response to temperature negligible (~1e-4 nm/K·s), "
    "contrary to the ~100 nm the paper attributes to ambient temperature in the XY plane.",
    "G_zQx: K printed '9454e-14' (decimal point lost?); used as printed = 9.454e-11. "
    "G_xQy: K printed '7781e-12' → 7.781e-9 as printed. G_zQy: K printed '8536e-8' → "
    "8.536e-5 as printed. Each may instead be 9.454e-14, 7.781e-12, 8.536e-8.",
    "G_xQy (eq. A7) is printed 'K/(s((1+2ζTw)s+(Tw s)^2))'; read as "
    "K/(s·(1 + 2ζ·Tw·s + (Tw·s)^2)) with Tw = 0.001 s and ζ = 16.1e7 as printed (an "
    "extremely overdamped pair: time constants ~3.2e5 s and ~3e-12 s).",
    "Table A1's Tp = 0.001 s entries look like placeholders for 'no pole' (identification "
    "toolbox lower bound); kept as printed.",
    "Td: 0 for xT, yT, zT, 30 s for zQy; the other rows print '{' (no delay).",
    "G_yQx, G_yQy (eqs. A10, A11): the sample period Ts is not stated; Ts = 1 s assumed. "
    "The sign of B_yQx[0] is taken + (2.26e-10): the controllability matrix A12, whose "
    "first column is B and whose other columns are A·B, A²·B, confirms A10's A and this B "
    "to the printed digits. The signs of C_yQx are doubtful (C[0] = -5.25e-13 as printed).",
    "A_yQx has an eigenvalue 1.000108 (slightly unstable at Ts = 1 s: ×1.43 per hour); "
    "probably rounding of an integrator-like pole. Kept as printed.",
    "Eq. 8 mixes a power (S_DE·V·V̇, W) and an energy (S_EE·V², J); S_EE is used as W/V².",
]


def table_a1_params(Ts_s: float = 1.0) -> DriftParams:
    """The drift paper's Appendix (eqs. A1–A11, Table A1) as printed, with the reading
    and doubts listed in :data:`TABLE_A1_DOUBTS` (stored in ``params.doubts``):

    * units unstated — K read as m/K and m/W, times in s (``output_scale_nm = 1e9``);
    * G_zT gives ~0.6 mm/K read in metres (paper: ~100 nm) — K probably damaged;
      G_yT (K = 7.35e-17) is negligible, contrary to the paper's XY ambient drift;
    * K of G_zQx '9454e-14', G_xQy '7781e-12', G_zQy '8536e-8' used as printed (a
      decimal point may be lost);
    * eq. A7 read as ``K/(s·(1 + 2ζTw·s + (Tw·s)²))`` with ζ = 16.1e7 as printed;
    * Ts of A10/A11 not stated (``Ts_s`` assumed 1 s); B_yQx[0] taken +2.26e-10 (A12
      confirms A and B); the signs of C_yQx are doubtful; A_yQx has an eigenvalue
      1.000108 (slightly unstable);
    * eq. 8 mixes W and J: S_EE used as W/V².
    """
    A_yQx = [[1.0001, 0.00063, 0.00054], [0.0040, 0.90031, -0.858], [0.0060, -0.0823, -0.465]]
    A_yQy = [[0.9997, 0.000295, 0.00045], [0.0062, 0.98074, -0.478], [0.000947, -0.0083, -0.355]]
    paths = DriftPaths(
        xT=TransferPath(K=5.8e-9, poles_s=[0.001, 907.8], zeros_s=[-6809.4], delay_s=0.0),
        yT=TransferPath(K=7.35e-17, integrators=1, poles_s=[0.001, 0.001], zeros_s=[6335.1], delay_s=0.0),
        zT=TransferPath(K=7.7e-3, poles_s=[84732.9, 3.1437], zeros_s=[6327.3], delay_s=0.0),
        xQx=TransferPath(K=9.075e-11, poles_s=[0.001, 213.33, 0.001], zeros_s=[52.224]),
        yQx=StateSpacePath(A=A_yQx, B=[2.26e-10, -2.65e-7, -4.52e-7], C=[-5.25e-13, -7.62e-17, 1.06e-17],
                           D=0.0, K_innov=[1.82e12, -1.11e14, 1.64e13], Ts_s=Ts_s),
        zQx=TransferPath(K=9454e-14, integrators=1, poles_s=[0.001, 28544.2, 0.001], zeros_s=[3182.2]),
        xQy=TransferPath(K=7781e-12, integrators=1, second_order=SecondOrder(Tw_s=0.001, zeta=16.1e7)),
        yQy=StateSpacePath(A=A_yQy, B=[4.61e-8, -3.88e-5, -0.00011], C=[9.97e-13, -1.89e-16, 3.45e-18],
                           D=0.0, K_innov=[1.12e12, 2.47e14, -6.19e12], Ts_s=Ts_s),
        zQy=TransferPath(K=8536e-8, poles_s=[0.001, 13.05e5, 55779.0], zeros_s=[1563066.0], delay_s=30.0),
    )
    return DriftParams(
        name="table_a1",
        description=("Korayem & Sadeghzadeh 2010, Appendix eqs. A1-A11 and Table A1 as printed "
                     "(AutoProbe CP-R); outputs read as metres. See doubts."),
        output_scale_nm=1e9,
        paths=paths,
        heat=AxisHeat(x=HeatParams(tube=TubeGeometry()), y=HeatParams(tube=TubeGeometry()),
                      z=HeatParams(tube=TubeGeometry())),
        doubts=list(TABLE_A1_DOUBTS),
    )


# --------------------------------------------------------------------------- discretisation
def _series(s1: tuple, s2: tuple) -> tuple:
    """Series connection ``s2 ∘ s1`` of SISO state-space tuples (A, B, C, D)."""
    A1, B1, C1, D1 = s1
    A2, B2, C2, D2 = s2
    n1, n2 = A1.shape[0], A2.shape[0]
    A = np.zeros((n1 + n2, n1 + n2))
    A[:n1, :n1] = A1
    A[n1:, n1:] = A2
    A[n1:, :n1] = np.outer(B2, C1)
    B = np.concatenate([B1, B2 * D1])
    C = np.concatenate([D2 * C1, C2])
    D = D2 * D1
    return A, B, C, D


def _lag(tp: float, tz: float | None) -> tuple:
    """``(1 + tz·s)/(1 + tp·s)`` (tz None → ``1/(1 + tp·s)``)."""
    A = np.array([[-1.0 / tp]])
    B = np.array([1.0 / tp])
    if tz is None:
        return A, B, np.array([1.0]), 0.0
    return A, B, np.array([1.0 - tz / tp]), tz / tp


def _integrator(tz: float | None) -> tuple:
    """``(1 + tz·s)/s``."""
    return np.array([[0.0]]), np.array([1.0]), np.array([1.0]), 0.0 if tz is None else float(tz)


def _continuous_ss(path: TransferPath, dt_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Continuous state space (A, B, C, D) of a :class:`TransferPath` without its delay."""
    zeros = list(path.zeros_s)
    lags = list(path.poles_s)
    if path.second_order is not None:
        tw, z = path.second_order.Tw_s, path.second_order.zeta
        if z >= 1.0:
            t_big = tw * (z + math.sqrt(z * z - 1.0))
            t_small = tw * tw / t_big
            lags += [t_big, t_small]
            osc = None
        else:
            osc = (tw, z)
    else:
        osc = None
    sys: tuple = (np.zeros((0, 0)), np.zeros(0), np.zeros(0), 1.0)
    # pair zeros with lags, slowest lag first, then with integrators
    lags.sort(reverse=True)
    for tp in lags:
        tz = zeros.pop(0) if zeros else None
        if tp < _STIFF_FRACTION * dt_s:
            if tz is not None:  # a stiff lag with a zero: keep the zero for a slower section
                zeros.insert(0, tz)
            continue
        sys = _series(sys, _lag(tp, tz))
    for _ in range(path.integrators):
        tz = zeros.pop(0) if zeros else None
        sys = _series(sys, _integrator(tz))
    if osc is not None:
        tw, z = osc
        # x1' = x2, x2' = (u − x1 − 2ζ·Tw·x2)/Tw²; remaining zeros (≤2) as b0 + b1·s + b2·s²
        A = np.array([[0.0, 1.0], [-1.0 / tw ** 2, -2.0 * z / tw]])
        B = np.array([0.0, 1.0 / tw ** 2])
        num = np.array([1.0])
        while zeros:
            num = np.convolve(num, [zeros.pop(0), 1.0])  # descending powers: tz·s + 1
        num = num[::-1]  # ascending: b0, b1, b2
        b = np.zeros(3)
        b[:num.size] = num
        # y = b0·x1 + b1·x2 + b2·x2' ; x2' = (u − x1 − 2ζTw x2)/Tw²
        C = np.array([b[0] - b[2] / tw ** 2, b[1] - b[2] * 2.0 * z / tw])
        D = b[2] / tw ** 2
        sys = _series(sys, (A, B, C, D))
    if zeros:
        # only possible when stiff lags were dropped: pure zeros left would make it improper
        raise ModelError(f"zeros_s: {len(path.zeros_s)} zeros cannot be realised with the remaining "
                         f"poles at dt_s={dt_s:g} s (lags faster than {_STIFF_FRACTION:g}·dt_s are static)")
    A, B, C, D = sys
    return A, B * 1.0, C * path.K, D * path.K


def _zoh(A: np.ndarray, B: np.ndarray, C: np.ndarray, D: float, dt_s: float) -> tuple:
    """Exact zero-order-hold discretisation: ``expm([[A, B], [0, 0]]·dt) = [[Ad, Bd], [0, 1]]``
    (what ``scipy.signal.cont2discrete(..., method="zoh")`` computes)."""
    n = A.shape[0]
    if n == 0:
        return A, B, C, D
    from scipy.linalg import expm
    M = np.zeros((n + 1, n + 1))
    M[:n, :n] = A * dt_s
    M[:n, n] = B * dt_s
    E = expm(M)
    return E[:n, :n].copy(), E[:n, n].copy(), C.copy(), float(D)


class DiscreteSystem:
    """The predictor's assembled discrete system (plain arrays, shared by kernel and
    reference). Fast block: block-diagonal ``Ad`` (n×n), ``Bd`` (n×P), ``Cd`` (3×n),
    ``Dd`` (3×P) for P continuous paths with input channel ``ch`` and delay ``delay``
    (samples). Slow block: Q state-space paths padded to ``k`` states, each with channel,
    delay, decimation ``m`` and output axis."""

    def __init__(self, params: DriftParams, dt_s: float) -> None:
        blocks, chans, delays = [], [], []
        slow = []
        for name in PATH_NAMES:
            path = getattr(params.paths, name)
            if path is None:
                continue
            axis = AXES.index(name[0])
            ch = SOURCES.index(name[1:])
            d = int(round(path.delay_s / dt_s))
            if d > MAX_DELAY_SAMPLES:
                raise ModelError(f"paths.{name}.delay_s: {path.delay_s} s is {d} samples at dt_s={dt_s:g}; "
                                 f"at most {MAX_DELAY_SAMPLES} samples")
            if isinstance(path, TransferPath):
                if path.K == 0.0:
                    continue
                A, B, C, D = _zoh(*_continuous_ss(path, dt_s), dt_s)
                blocks.append((A, B, C, D, axis))
                chans.append(ch)
                delays.append(d)
            else:
                m = max(1, int(round(path.Ts_s / dt_s)))
                A = np.asarray(path.A, dtype=np.float64)
                rho = float(np.max(np.abs(np.linalg.eigvals(A))))
                if rho > 1.0:
                    log.warning("paths.%s: spectral radius %.6f > 1 (unstable as given); kept", name, rho)
                slow.append((A, np.asarray(path.B, float), np.asarray(path.C, float), float(path.D), axis, ch, d, m))
        n = sum(b[0].shape[0] for b in blocks)
        P = len(blocks)
        self.Ad = np.zeros((n, n))
        self.Bd = np.zeros((n, max(P, 1)))
        self.Cd = np.zeros((3, n))
        self.Dd = np.zeros((3, max(P, 1)))
        self.row_lo = np.zeros(n, dtype=np.int64)
        self.row_hi = np.zeros(n, dtype=np.int64)
        i0 = 0
        for p, (A, B, C, D, axis) in enumerate(blocks):
            k = A.shape[0]
            self.Ad[i0:i0 + k, i0:i0 + k] = A
            self.Bd[i0:i0 + k, p] = B
            self.Cd[axis, i0:i0 + k] = C
            self.Dd[axis, p] = D
            self.row_lo[i0:i0 + k] = i0
            self.row_hi[i0:i0 + k] = i0 + k
            i0 += k
        self.n_paths = P
        self.ch = np.array(chans, dtype=np.int64)
        self.delay = np.array(delays, dtype=np.int64)
        Q = len(slow)
        kmax = max([s[0].shape[0] for s in slow], default=1)
        self.SA = np.zeros((max(Q, 1), kmax, kmax))
        self.SB = np.zeros((max(Q, 1), kmax))
        self.SC = np.zeros((max(Q, 1), kmax))
        self.SD = np.zeros(max(Q, 1))
        self.s_axis = np.zeros(max(Q, 1), dtype=np.int64)
        self.s_ch = np.zeros(max(Q, 1), dtype=np.int64)
        self.s_delay = np.zeros(max(Q, 1), dtype=np.int64)
        self.s_m = np.ones(max(Q, 1), dtype=np.int64)
        for q, (A, B, C, D, axis, ch, d, m) in enumerate(slow):
            k = A.shape[0]
            self.SA[q, :k, :k] = A
            self.SB[q, :k] = B
            self.SC[q, :k] = C
            self.SD[q] = D
            self.s_axis[q], self.s_ch[q], self.s_delay[q], self.s_m[q] = axis, ch, d, m
        self.n_slow = Q
        self.ring_len = int(max([0] + delays + [s[6] for s in slow])) + 1
        self.n_states = n
        self.kmax = kmax


@functools.lru_cache(maxsize=32)
def _discrete_system(params_json: str, dt_s: float) -> DiscreteSystem:
    """Cached discretisation (predictors of the same parameters and period share the
    read-only matrices; each predictor has its own state)."""
    sysd = DiscreteSystem(DriftParams.model_validate_json(params_json), dt_s)
    for v in vars(sysd).values():
        if isinstance(v, np.ndarray):
            v.flags.writeable = False
    return sysd


class _State:
    """Mutable predictor state (arrays mutated in place by the kernel)."""

    def __init__(self, sysd: DiscreteSystem) -> None:
        self.x = np.zeros(sysd.n_states)
        self.xnew = np.zeros(sysd.n_states)
        self.ueff = np.zeros(max(sysd.n_paths, 1))
        self.ring = np.zeros((4, sysd.ring_len))
        self.xs = np.zeros((max(sysd.n_slow, 1), sysd.kmax))
        self.xs_new = np.zeros(sysd.kmax)
        self.acc = np.zeros(max(sysd.n_slow, 1))
        self.cnt = np.zeros(max(sysd.n_slow, 1), dtype=np.int64)
        # ints: [head, have_ref, have_prev]; floats: [T_ref]; previous voltages (3,)
        self.ints = np.zeros(3, dtype=np.int64)
        self.T_ref = np.zeros(1)
        self.u_prev = np.zeros(3)
        self.hg = np.zeros(3)


# --------------------------------------------------------------------------- the kernel
def _drift_loop(T, U, out, dt, s_de, s_ee, scale,
                Ad, Bd, Cd, Dd, row_lo, row_hi, ch, delay, n_paths,
                SA, SB, SC, SD, s_axis, s_ch, s_delay, s_m, n_slow,
                x, xnew, ueff, ring, xs, xs_new, acc, cnt, ints, T_ref, u_prev, hg):
    """One pass over N samples; see the module docstring. Pure loops so that the numba
    kernel and the python reference do the same arithmetic in the same order."""
    n = x.shape[0]
    L = ring.shape[1]
    kmax = xs.shape[1]
    for i in range(T.shape[0]):
        if ints[1] == 0:
            T_ref[0] = T[i]
            ints[1] = 1
        dT = T[i] - T_ref[0]
        for a in range(3):
            v = U[i, a]
            vp = v
            if ints[2] == 1:
                vp = u_prev[a]
            v2 = v * v
            vvdot = (v2 - vp * vp) / (2.0 * dt)
            hg[a] = s_de[a] * vvdot - s_ee[a] * v2
            u_prev[a] = v
        ints[2] = 1
        h = ints[0] + 1
        if h >= L:
            h = 0
        ints[0] = h
        ring[0, h] = dT
        ring[1, h] = hg[0]
        ring[2, h] = hg[1]
        ring[3, h] = hg[2]
        for p in range(n_paths):
            j = h - delay[p]
            if j < 0:
                j += L
            ueff[p] = ring[ch[p], j]
        for r in range(3):
            y = 0.0
            for j in range(n):
                y += Cd[r, j] * x[j]
            for p in range(n_paths):
                y += Dd[r, p] * ueff[p]
            out[i, r] = y
        for j in range(n):
            s = 0.0
            for k in range(row_lo[j], row_hi[j]):
                s += Ad[j, k] * x[k]
            for p in range(n_paths):
                s += Bd[j, p] * ueff[p]
            xnew[j] = s
        for j in range(n):
            x[j] = xnew[j]
        for q in range(n_slow):
            j = h - s_delay[q]
            if j < 0:
                j += L
            u = ring[s_ch[q], j]
            y = SD[q] * u
            for k in range(kmax):
                y += SC[q, k] * xs[q, k]
            out[i, s_axis[q]] += y
            acc[q] += u
            cnt[q] += 1
            if cnt[q] >= s_m[q]:
                avg = acc[q] / s_m[q]
                for r in range(kmax):
                    s = 0.0
                    for k in range(kmax):
                        s += SA[q, r, k] * xs[q, k]
                    xs_new[r] = s + SB[q, r] * avg
                for r in range(kmax):
                    xs[q, r] = xs_new[r]
                acc[q] = 0.0
                cnt[q] = 0
        for r in range(3):
            out[i, r] = out[i, r] * scale


_drift_kernel = numba.njit(cache=True, nogil=True)(_drift_loop)


# --------------------------------------------------------------------------- predictor
def _temperature_C(name: str, value: object) -> float:
    """One temperature [°C] as a float, or ModelError naming ``name`` and the range."""
    try:
        T = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        T = math.nan
    if isinstance(value, (str, bytes, bool)) or not (T_MIN_C <= T <= T_MAX_C):  # also NaN
        raise ModelError(f"{name}: {value!r}; temperature must be a finite number in "
                         f"{T_MIN_C:g}..{T_MAX_C:g} °C")
    return T


def _float_array(name: str, value: object) -> np.ndarray:
    """``value`` as a float64 array; ModelError unless it holds real numbers (no text,
    no booleans, no objects)."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "iuf":
        raise ModelError(f"{name}: {value!r:.60} is not an array of numbers (dtype {arr.dtype})")
    return arr.astype(np.float64, copy=False)


class DriftPredictor:
    """Streaming drift prediction at a fixed loop period ``dt_s`` [s].

    ``step(T_C, u_V)`` takes the ambient temperature [°C] and the three commanded
    voltages [V] (x, y, z) of one sample and returns the predicted drift [nm] (3,);
    ``block(T_C (N,), u_V (N, 3))`` does N samples with carried state and gives exactly
    the per-sample result. The drift is driven by the change of T from its value at
    :meth:`reset` (``T_ref_C``) or, when none is given, from the first sample.
    O(1) per sample (state size independent of history; delays are ring buffers).
    """

    def __init__(self, params: DriftParams, dt_s: float) -> None:
        if not (isinstance(dt_s, (int, float)) and math.isfinite(dt_s) and 1e-7 <= dt_s <= 1e4):
            raise ModelError(f"dt_s: {plain_repr(dt_s)} s; allowed 1e-7..1e4 s")
        self.params = params
        self.dt_s = float(dt_s)
        self.system = _discrete_system(params.model_dump_json(), self.dt_s)
        s_de, s_ee = params.heat.coefficients()
        self._s_de, self._s_ee = s_de, s_ee
        self._scale = float(params.output_scale_nm)
        self._state = _State(self.system)
        self._T1 = np.zeros(1)
        self._U1 = np.zeros((1, 3))
        self._out1 = np.zeros((1, 3))
        self._step_args = self._args(self._T1, self._U1, self._out1)
        self.reset()

    def reset(self, T_ref_C: float | None = None) -> None:
        """Zero the state. ``T_ref_C`` [°C] is the reference temperature (default: the
        first sample's temperature)."""
        st = self._state
        for arr in (st.x, st.xnew, st.ueff, st.ring, st.xs, st.xs_new, st.acc, st.T_ref, st.u_prev, st.hg):
            arr[...] = 0.0
        st.cnt[...] = 0
        st.ints[...] = 0
        if T_ref_C is not None:
            st.T_ref[0] = _temperature_C("T_ref_C", T_ref_C)
            st.ints[1] = 1

    @property
    def heat_W(self) -> np.ndarray:
        """Heat generated (eq. 8) at the last sample, per axis [W]."""
        return self._state.hg.copy()

    @property
    def T_ref_C(self) -> float | None:
        return float(self._state.T_ref[0]) if self._state.ints[1] else None

    def _args(self, T: np.ndarray, U: np.ndarray, out: np.ndarray) -> tuple:
        s, st = self.system, self._state
        return (T, U, out, self.dt_s, self._s_de, self._s_ee, self._scale,
                s.Ad, s.Bd, s.Cd, s.Dd, s.row_lo, s.row_hi, s.ch, s.delay, s.n_paths,
                s.SA, s.SB, s.SC, s.SD, s.s_axis, s.s_ch, s.s_delay, s.s_m, s.n_slow,
                st.x, st.xnew, st.ueff, st.ring, st.xs, st.xs_new, st.acc, st.cnt, st.ints, st.T_ref,
                st.u_prev, st.hg)

    def step(self, T_C: float, u_V: np.ndarray) -> np.ndarray:
        """One sample: temperature [°C], voltages (3,) [V] → drift (3,) [nm]."""
        T = _temperature_C("T_C", T_C)
        try:
            if len(u_V) != 3:
                raise TypeError
            ux, uy, uz = float(u_V[0]), float(u_V[1]), float(u_V[2])
        except (TypeError, ValueError, IndexError):
            raise ModelError(f"u_V: {u_V!r}; need 3 finite voltages [V] (x, y, z)") from None
        if not (math.isfinite(ux) and math.isfinite(uy) and math.isfinite(uz)):
            raise ModelError(f"u_V: {u_V!r}; need 3 finite voltages [V] (x, y, z)")
        self._T1[0] = T
        U1 = self._U1
        U1[0, 0] = ux
        U1[0, 1] = uy
        U1[0, 2] = uz
        _drift_kernel(*self._step_args)
        return self._out1[0].copy()

    def block(self, T_C: np.ndarray, u_V: np.ndarray | None = None) -> np.ndarray:
        """N samples: temperatures (N,) [°C], voltages (N, 3) [V] (None → 0 V) → drift
        (N, 3) [nm], with carried state."""
        T = np.ascontiguousarray(check_finite("T_C", _float_array("T_C", T_C)).reshape(-1))
        if T.size and not (T_MIN_C <= T.min() and T.max() <= T_MAX_C):
            i = int(np.flatnonzero((T < T_MIN_C) | (T > T_MAX_C))[0])
            raise ModelError(f"T_C: {float(T[i])!r} °C at index {i}; allowed {T_MIN_C:g}..{T_MAX_C:g} °C")
        if u_V is None:
            U = np.zeros((T.shape[0], 3))
        else:
            U = np.ascontiguousarray(check_finite("u_V", _float_array("u_V", u_V)))
            if U.ndim != 2 or U.shape != (T.shape[0], 3):
                raise ModelError(f"u_V: shape {U.shape}; need ({T.shape[0]}, 3) to match T_C")
        out = np.empty((T.shape[0], 3))
        if T.shape[0]:
            _drift_kernel(*self._args(T, U, out))
        return out

    def reference_block(self, T_C: np.ndarray, u_V: np.ndarray | None = None) -> np.ndarray:
        """The same as :meth:`block` in plain python (slow; for tests)."""
        T = np.ascontiguousarray(np.asarray(T_C, dtype=np.float64).reshape(-1))
        U = np.zeros((T.shape[0], 3)) if u_V is None else np.ascontiguousarray(np.asarray(u_V, dtype=np.float64))
        out = np.empty((T.shape[0], 3))
        _drift_loop(*self._args(T, U, out))
        return out


def drift_reference(params: DriftParams, dt_s: float, T_C: np.ndarray, u_V: np.ndarray | None = None) -> np.ndarray:
    """Plain-python prediction from a fresh state (the reference beside the numba kernel)."""
    return DriftPredictor(params, dt_s).reference_block(T_C, u_V)


# --------------------------------------------------------------------------- gain fitting
def path_responses(params: DriftParams, predict) -> dict[str, np.ndarray]:
    """Response (N,) on its own axis of every path of ``params`` with unit gain (K = 1
    for a transfer function; the state-space path as given), computed by
    ``predict(one_path_params) -> (N, 3)`` — e.g. ``lambda p: p.predictor(dt).block(T, U)``."""
    out: dict[str, np.ndarray] = {}
    for name in PATH_NAMES:
        path = getattr(params.paths, name)
        if path is None:
            continue
        unit = path.model_copy(deep=True)
        if isinstance(unit, TransferPath):
            unit.K = 1.0
        one = params.model_copy(deep=True)
        one.paths = DriftPaths(**{name: unit})
        out[name] = np.asarray(predict(one))[:, AXES.index(name[0])]
    return out


def fit_gains(params: DriftParams, responses: dict[str, np.ndarray], measured_nm: np.ndarray
              ) -> tuple[DriftParams, np.ndarray]:
    """Least-squares gains of the paths (their structures and time constants kept) so that
    the predicted drift matches ``measured_nm`` (N, 3) [nm]; NaN columns are axes that
    were not measured and keep their gains. The drift is linear in every path gain, so
    this is an ordinary linear least-squares problem per axis. A path whose response is
    zero (e.g. a heat path when no voltage was applied) keeps its gain.

    Returns ``(fitted params, rms residual per axis [nm])``.
    """
    meas = np.asarray(measured_nm, dtype=np.float64)
    fitted = params.model_copy(deep=True)
    rms = np.full(3, np.nan)
    for a, axis in enumerate(AXES):
        col = meas[:, a]
        if not np.all(np.isfinite(col)):
            continue
        names = [n for n in responses if n[0] == axis]
        basis = [responses[n] for n in names]
        keep = [i for i, b in enumerate(basis) if np.max(np.abs(b)) > 0.0]
        if not keep:
            rms[a] = float(np.sqrt(np.mean(col * col)))
            continue
        M = np.column_stack([basis[i] for i in keep])
        # scale columns for conditioning
        scale = np.max(np.abs(M), axis=0)
        g, *_ = np.linalg.lstsq(M / scale, col, rcond=None)
        g = g / scale
        for i, gi in zip(keep, g):
            path = getattr(fitted.paths, names[i])
            if isinstance(path, TransferPath):
                path.K = float(gi)
            else:
                path.C = [c * float(gi) for c in path.C]
                path.D = path.D * float(gi)
        res = col - M @ g
        rms[a] = float(np.sqrt(np.mean(res * res)))
    fitted.name = f"{params.name}-fitted"
    return fitted, rms
