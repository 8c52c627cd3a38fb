"""Fits that must not fail silently (issue #24, item 4).

A fitted model is *failed* — reported with the reason in one line, never selected by
``--model auto``, never written by ``afmctl identify`` without ``--force`` — when

* its training error exceeds that of the straight line ``y = a·u + b`` fitted by least
  squares on the same samples (every hysteresis model contains the line: a fit worse than it
  has diverged or stopped in a wrong minimum);
* its optimiser did not converge (iteration budget spent);
* a parameter sits on a bound that only limits the search (the optimum lies outside the
  region the model is trusted in).

The kinds record the last two themselves while fitting (:func:`note_problem` on the model;
not saved in the model file); :func:`fit_problems` collects them over a chain's stages and
:func:`failure_reason` adds the comparison with the line.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

#: a model fails when its training RMS exceeds the line's by more than this factor (the line
#: itself is in every kind's model set; 1 % slack for the averaging of the static stages)
LINEAR_SLACK = 1.01


#: errors below this [nm] are numerical noise, not a worse fit (a straight line fits data that
#: is one to 1e-12 nm; a model may then reach only 1e-11)
FLOOR_NM = 1e-3

def note_problem(model: Any, text: str) -> None:
    """Record one fit problem (a short clause, e.g. "bouc-wen: h_sat on its lower bound")."""
    problems = getattr(model, "_fit_problems", None)
    if problems is not None and text not in problems:
        problems.append(text)


def fit_problems(model: Any) -> list[str]:
    """The problems recorded on ``model`` and (a chain) on each of its stages."""
    out = list(getattr(model, "_fit_problems", None) or [])
    stages = getattr(model, "stages", None)
    if callable(stages) and getattr(model, "kind", "") == "chain":
        for stage in stages():
            out += [p for p in fit_problems(stage) if p not in out]
    return out


def linear_fit_rms(u_V: np.ndarray, y_nm: np.ndarray) -> float:
    """RMS residual [nm] of the least-squares line ``y = a·u + b`` on these samples."""
    u = np.asarray(u_V, dtype=float).ravel()
    y = np.asarray(y_nm, dtype=float).ravel()
    if u.size < 2 or not np.ptp(u) > 0:
        return float(np.std(y))
    A = np.column_stack([u, np.ones_like(u)])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    return float(np.sqrt(np.mean((A @ coef - y) ** 2)))


def failure_reason(model: Any, train_rms_nm: float, linear_rms_nm: float) -> str | None:
    """One line saying why the fit failed, or None when it did not (module docstring).
    ``train_rms_nm``: the model's RMS error on its training samples [nm];
    ``linear_rms_nm``: the line's on the same samples (:func:`linear_fit_rms`)."""
    reasons = []
    if not math.isfinite(train_rms_nm):
        reasons.append("the prediction on the training data is not finite")
    elif train_rms_nm > LINEAR_SLACK * linear_rms_nm + FLOOR_NM:
        reasons.append(f"training error {train_rms_nm:.4g} nm RMS exceeds the straight line's "
                       f"{linear_rms_nm:.4g} nm (diverged)")
    reasons += fit_problems(model)
    return "; ".join(reasons) if reasons else None
