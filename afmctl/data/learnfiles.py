"""The files of ``afmctl learn step``: target, sent and measured CSVs, the model, the
iteration state (JSON), and the learner's settings from the command line. Every bad input
is one :class:`~afmctl.errors.AfmctlError` line naming the file or option and what is
allowed."""
from __future__ import annotations

import argparse
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .datafiles import read_csv, uniform_period
from ..errors import AfmctlError

#: limits when neither --limits nor the model file gives a voltage range [V]
FALLBACK_LIMITS_V = (0.0, 150.0)


@dataclass(frozen=True)
class LearnInputs:
    """One iteration's data on the target's rows: ``t_s`` [s], ``dt_s`` [s], ``target_nm``,
    ``sent_V``, ``measured_nm`` and the ``model`` (None: model-free)."""

    t_s: np.ndarray
    dt_s: float
    target_nm: np.ndarray
    sent_V: np.ndarray
    measured_nm: np.ndarray
    model: Any


def load_inputs(args: argparse.Namespace) -> LearnInputs:
    """Read and cross-check --target, --sent, --measured and --model."""
    tgt = read_csv(args.target, ("t", "y"), min_rows=8)
    t = tgt["t"]
    dt = uniform_period(t, str(args.target))
    sent = read_csv(args.sent, ("t", "u"), min_rows=8)
    if sent["t"].size != t.size or np.max(np.abs(sent["t"] - t)) > 1e-3 * dt:
        raise AfmctlError(f"{args.sent}: {sent['t'].size} rows at t {sent['t'][0]:g} … {sent['t'][-1]:g} s; need the "
                          f"target's {t.size} rows at the same times ({t[0]:g} … {t[-1]:g} s)")
    meas = read_csv(args.measured, ("t", "y"), min_rows=8)
    measured = _on_target_rows(meas["t"], meas["y"], t, dt, str(args.measured))
    model = _model(args) if args.model else None
    return LearnInputs(t, dt, tgt["y"], sent["u"], measured, model)


def _on_target_rows(tm: np.ndarray, ym: np.ndarray, t: np.ndarray, dt: float, where: str) -> np.ndarray:
    """The recording on the target's rows: as it is when the times match, else linearly
    interpolated (a recording that started late or runs at another rate), which needs it
    to cover the target's time span (half a sample of slack at either end)."""
    if tm.size == t.size and np.max(np.abs(tm - t)) <= 1e-3 * dt:
        return ym
    if tm[0] > t[0] + 0.5 * dt or tm[-1] < t[-1] - 0.5 * dt:
        raise AfmctlError(f"{where}: the recording covers t {tm[0]:g} … {tm[-1]:g} s; it must cover the target's "
                          f"{t[0]:g} … {t[-1]:g} s (same clock as the table; a trigger offset shows in t)")
    return np.interp(t, tm, ym)


def _model(args: argparse.Namespace) -> Any:
    from afmctl.compensators.models import load_model

    model: Any = load_model(args.model)
    if model.kind == "scanner":
        if not args.axis:
            raise AfmctlError(f"--axis: {args.model} is a scanner model; choose the axis with --axis x|y|z")
        model = model.axis(args.axis)
        if model is None:
            raise AfmctlError(f"--axis: {args.model} has no model for axis {args.axis}")
    elif args.axis:
        raise AfmctlError(f"--axis: {args.model} is a single-axis model (kind {model.kind}); drop --axis")
    if model.kind == "dynamics":
        raise AfmctlError(f"{args.model}: field kind: a 'dynamics' model maps nm to nm, not volts to nm; give a chain "
                          "(e.g. preisach+creep+dynamics) or a hysteresis model")
    return model


def settings_from_args(args: argparse.Namespace, model: Any):
    """The learner's settings from the options; ``(settings, where the limits come from)``."""
    from afmctl.compensators.learning import LearnSettings

    checks = [("--step-size", args.step_size, args.step_size is None or 0 < args.step_size <= 2, "0 < RHO ≤ 2"),
              ("--central-pct", args.central_pct, 0 < args.central_pct <= 100, "0 < P ≤ 100 (%)"),
              ("--q-cutoff-Hz", args.q_cutoff_Hz, args.q_cutoff_Hz is None or args.q_cutoff_Hz > 0, "> 0 Hz"),
              ("--slew-V-per-s", args.slew_V_per_s, args.slew_V_per_s is None or args.slew_V_per_s > 0, "> 0 V/s")]
    for name, value, ok, allowed in checks:
        if value is not None and (not math.isfinite(float(value)) or not ok):
            raise AfmctlError(f"{name}: {value}; allowed {allowed}")
    lo, hi, source = _limits(args.limits, model)
    return LearnSettings(rho_max=args.step_size, q_cutoff_Hz=args.q_cutoff_Hz, central_pct=args.central_pct,
                         lines_only=args.lines_only, periodic=args.periodic, u_min_V=lo, u_max_V=hi,
                         slew_V_per_s=args.slew_V_per_s, align=args.align,
                         judge_lines=parse_judged_lines(getattr(args, "judge_lines", None))), source


def parse_judged_lines(text: str | None) -> tuple[int, ...] | None:
    """``--judge-lines`` (e.g. ``2-6`` or ``1,3,5-8``: raster lines, 1-based) as line numbers;
    None when not given. A bad list is one :class:`AfmctlError` line."""
    if text is None:
        return None
    out: list[int] = []
    try:
        for part in text.split(","):
            a, _, b = part.strip().partition("-")
            lo, hi = int(a), int(b) if b else int(a)
            if lo < 1 or hi < lo or hi - lo > 100_000:
                raise ValueError
            out.extend(range(lo, hi + 1))
    except ValueError:
        raise AfmctlError(f"--judge-lines: {text!r}; allowed raster line numbers from 1, e.g. 2-6 or 1,3,5-8") from None
    return tuple(out)


def _limits(given, model) -> tuple[float, float, str]:
    if given:
        lo, hi = float(given[0]), float(given[1])
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise AfmctlError(f"--limits: {given[0]} {given[1]}; need finite LO < HI (V)")
        return lo, hi, "--limits"
    known = model.voltage_range_V() if model is not None else None
    if known is not None:
        return float(known[0]), float(known[1]), "the model's voltage range"
    return (*FALLBACK_LIMITS_V, "no --limits and no model range: the default")


def load_state(path: str | None):
    """The state in ``path`` (None when no path or no file yet)."""
    from afmctl.compensators.learning import LearnState
    from afmctl.compensators.textfiles import read_json_file

    if not path or not Path(path).exists():
        return None
    data = read_json_file(path, "learning state file")
    if not isinstance(data, dict):
        raise AfmctlError(f"{path}: a learning state file holds a JSON object; delete it to start afresh")
    try:
        return LearnState.from_dict(data)
    except ValueError as err:
        raise AfmctlError(f"{path}: {err}") from None


def save_state(path: str, state) -> None:
    """Write the state atomically (a temporary file renamed over the old one)."""
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    try:
        tmp.write_text(json.dumps(state.to_dict()), encoding="utf-8")
        os.replace(tmp, p)
    except OSError as err:
        raise AfmctlError(f"{p}: cannot write the learning state ({err.strerror or err})") from None
