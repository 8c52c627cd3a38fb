"""``--model auto``: pick a model structure by its prediction error on held-out data.

Each candidate (a hysteresis kind alone or a chain, see :mod:`.chain`) is identified on
the first ``1 − holdout_fraction`` of the record, then run forward over the *whole* record
(its memory carries from the training part into the held-out part, as it would on the
instrument) and scored on the held-out samples whose input lies inside the training part's input range: RMS and max
|prediction − measured| [nm] and in % of the held-out span. The candidate with the lowest held-out max error wins
(ties: RMS); it is re-identified on the whole record and carries the table in its
``selection`` field.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from .base import ModelError, check_finite
from .chain import ChainModel, parse_structure

log = logging.getLogger(__name__)

#: candidates tried by default (fast ones first); "+dynamics" variants are added when the
#: dynamics kind is installed and the caller asks for them
DEFAULT_CANDIDATES: tuple[str, ...] = ("pi", "pi+creep", "epi", "preisach", "preisach+creep",
                                       "bouc-wen", "bouc-wen+creep")


def _fit(structure: str, t: np.ndarray, u: np.ndarray, y: np.ndarray, options: dict[str, Any]) -> ChainModel:
    return ChainModel.identify(t, u, y, structure=structure, **options)


def scored_samples(u_V: np.ndarray, split: int) -> np.ndarray:
    """Held-out samples whose input lies inside the training part's input range (no model
    can be asked to extrapolate past what it was identified on): a boolean mask over
    ``u_V[split:]``."""
    lo, hi = float(np.min(u_V[:split])), float(np.max(u_V[:split]))
    return (u_V[split:] >= lo) & (u_V[split:] <= hi)


def score_candidate(structure: str, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, split: int,
                    options: dict[str, Any] | None = None) -> dict[str, Any]:
    """Identify ``structure`` on samples ``[:split]``, predict all, score ``[split:]``.

    Returns a table row: ``structure``, ``heldout_rms_nm``, ``heldout_max_nm``,
    ``heldout_rms_pct``, ``heldout_max_pct`` (% of the held-out span), ``train_rms_nm``;
    or ``structure`` and ``error`` (one line) when the fit fails."""
    parse_structure(structure)
    try:
        model = _fit(structure, t_s[:split], u_V[:split], y_nm[:split], options or {})
        dt = float(np.median(np.diff(t_s)))
        pred = model.forward(dt).block(np.ascontiguousarray(u_V))
    except (ModelError, ValueError, np.linalg.LinAlgError) as err:
        return {"structure": structure, "error": " ".join(str(err).split())}
    if not np.all(np.isfinite(pred)):
        return {"structure": structure, "error": "the model's prediction is not finite"}
    e_test = (pred[split:] - y_nm[split:])[scored_samples(u_V, split)]
    e_train = pred[:split] - y_nm[:split]
    span = float(np.ptp(y_nm[split:])) or 1.0
    rms = float(np.sqrt(np.mean(e_test ** 2)))
    peak = float(np.max(np.abs(e_test)))
    return {"structure": structure, "heldout_rms_nm": round(rms, 4), "heldout_max_nm": round(peak, 4),
            "heldout_rms_pct": round(100.0 * rms / span, 4), "heldout_max_pct": round(100.0 * peak / span, 4),
            "train_rms_nm": round(float(np.sqrt(np.mean(e_train ** 2))), 4)}


def _key(row: dict[str, Any]) -> tuple[float, float]:
    if "error" in row:
        return (math.inf, math.inf)
    return (row["heldout_max_nm"], row["heldout_rms_nm"])


def select_model(t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, candidates: Sequence[str] = DEFAULT_CANDIDATES,
                 holdout_fraction: float = 0.3, options: dict[str, Any] | None = None,
                 ) -> tuple[ChainModel, list[dict[str, Any]]]:
    """Score every candidate (module docstring), refit the best on all the data.

    ``t_s`` [s] uniformly sampled, ``u_V`` [V], ``y_nm`` [nm]. Returns the best model (its
    ``selection`` field holds the table, best first) and the table."""
    t = check_finite("t_s", t_s).ravel()
    u = np.ascontiguousarray(check_finite("u_V", u_V).ravel())
    y = np.ascontiguousarray(check_finite("y_nm", y_nm).ravel())
    if not 0.05 <= holdout_fraction <= 0.5:
        raise ModelError(f"holdout_fraction: {holdout_fraction}; allowed 0.05 … 0.5")
    if not candidates:
        raise ModelError("candidates: none given")
    split = int(round(t.size * (1.0 - holdout_fraction)))
    if split < 64 or t.size - split < 16:
        raise ModelError(f"data: {t.size} samples are too few to hold out {holdout_fraction:.0%} for scoring")
    inside = float(np.mean(scored_samples(u, split)))
    if inside < 0.5:
        raise ModelError(f"data: only {inside:.0%} of the held-out last {holdout_fraction:.0%} lies inside the input "
                         "range of the rest; excite the full voltage range early in the record")
    table = []
    for structure in candidates:
        row = score_candidate(structure, t, u, y, split, options)
        log.info("auto: %s → %s", structure, row)
        table.append(row)
    table.sort(key=_key)
    if "error" in table[0]:
        raise ModelError("data: no candidate could be identified; " + "; ".join(
            f"{r['structure']}: {r['error']}" for r in table))
    best = _fit(table[0]["structure"], t, u, y, options or {})
    best.selection = table
    return best, table
