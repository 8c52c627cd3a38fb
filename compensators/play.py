"""The play (backlash) operator, the building block of the Prandtl–Ishlinskii family.

For threshold ``r ≥ 0`` and previous output ``x(t−T)`` the play operator is (extended-PI
paper, eq. 3 without the creep term)::

    x(t) = max(u(t) − r, min(u(t) + r, x(t − T)))

It is rate-independent: only the order of input values matters, not their timing.
Inputs and outputs share one unit (volts for a forward PI model, nanometres for its
inverse); ``r`` is in that unit as well.
"""
from __future__ import annotations

import numpy as np

from . import _pi_kernels as K
from .base import ModelError, StreamingOperator
from .input_checks import block_samples, finite_sample

_ONE = np.ones(1)


class PlayOperator(StreamingOperator):
    """One play operator with threshold ``threshold`` and initial output ``initial_state``.

    ``step``/``block`` use the compiled PI kernel (a PI operator with one unit weight), so
    block and per-sample results are identical.
    """

    def __init__(self, threshold: float, initial_state: float = 0.0) -> None:
        r = float(threshold)
        if not np.isfinite(r) or r < 0:
            raise ModelError(f"threshold: {threshold!r} must be a finite number ≥ 0")
        x0 = float(initial_state)
        if not np.isfinite(x0):
            raise ModelError(f"initial_state: {initial_state!r} must be finite")
        self._r = np.array([r])
        self._x0 = x0
        self._state = np.array([x0])

    @property
    def threshold(self) -> float:
        return float(self._r[0])

    @property
    def state(self) -> float:
        """Current output ``x(t)`` (same unit as the input)."""
        return float(self._state[0])

    def reset(self) -> None:
        self._state[0] = self._x0

    def step(self, x: float) -> float:
        return K.pi_step(finite_sample("input", x), self._r, _ONE, self._state, 0.0, 0.0)

    def block(self, x: np.ndarray) -> np.ndarray:
        x = block_samples("input", x)
        out = np.empty_like(x)
        K.pi_block(x, self._r, _ONE, self._state, 0.0, 0.0, out)
        return out


def play_reference(u: np.ndarray, r: float, x0: float = 0.0) -> np.ndarray:
    """Textbook play operator written with Python's ``max``/``min`` (test reference)."""
    out = np.empty(len(u))
    x = float(x0)
    for k, v in enumerate(np.asarray(u, dtype=float).tolist()):
        x = max(v - r, min(v + r, x))
        out[k] = x
    return out
