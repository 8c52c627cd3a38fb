"""The streaming-operator contract every model in afmctl follows.

A streaming operator maps an input sequence to an output sequence sample by sample and
keeps internal state (play-operator positions, Preisach memory, filter states).

* :meth:`StreamingOperator.reset` returns it to its initial state.
* :meth:`StreamingOperator.step` takes one sample and returns one sample.
* :meth:`StreamingOperator.block` takes a 1-D array and returns an array of the same
  length, carrying state across calls, so that feeding a signal in blocks of any size
  gives *exactly* (bit for bit) the per-sample result.

Operators whose behaviour depends on time (creep, drift) are built for a fixed sample
period ``dt_s`` (seconds); operators that are rate-independent (PI, Preisach, Bouc–Wen)
ignore time.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np


class ModelError(ValueError):
    """A model's parameters or its input data are invalid.

    The message names the offending field and the allowed range; the CLI prints it as one
    line without a traceback.
    """


class StreamingOperator(ABC):
    """Stateful single-input single-output operator; see the module docstring."""

    @abstractmethod
    def reset(self) -> None:
        """Return to the initial state."""

    @abstractmethod
    def step(self, x: float) -> float:
        """Process one sample and return one output sample."""

    def block(self, x: np.ndarray) -> np.ndarray:
        """Process a block of samples with carried state.

        The default loops over :meth:`step`; subclasses override it with a vectorised or
        compiled path that must give exactly the same numbers.
        """
        x = np.asarray(x, dtype=np.float64)
        out = np.empty_like(x)
        for i in range(x.shape[0]):
            out[i] = self.step(float(x[i]))
        return out

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.block(x)


class Chain(StreamingOperator):
    """Series connection ``ops[-1](... ops[1](ops[0](x)))``."""

    def __init__(self, *ops: StreamingOperator) -> None:
        self.ops = list(ops)

    def reset(self) -> None:
        for op in self.ops:
            op.reset()

    def step(self, x: float) -> float:
        for op in self.ops:
            x = op.step(x)
        return x

    def block(self, x: np.ndarray) -> np.ndarray:
        y = np.asarray(x, dtype=np.float64)
        for op in self.ops:
            y = op.block(y)
        return y


def stages_of(op: StreamingOperator) -> Iterator[StreamingOperator]:
    """``op`` and every operator inside it (the stages of a :class:`Chain`, the operator a
    delay feeds through its ``op``), depth first."""
    yield op
    inner = getattr(op, "ops", None)
    for sub in (inner if isinstance(inner, list) else [getattr(op, "op", None)]):
        if isinstance(sub, StreamingOperator):
            yield from stages_of(sub)


@contextmanager
def quiet_clamps(*ops: StreamingOperator) -> Iterator[None]:
    """No clamp warning from any stage of ``ops`` while inside (a Preisach stage's
    ``warn_clamps``): for outputs that are never sent or never scored, such as a preview
    inverse's priming or a held-out prediction beyond the training range; the clamps are
    still counted."""
    quiet = [(s, s.warn_clamps) for op in ops for s in stages_of(op) if hasattr(s, "warn_clamps")]
    for s, _ in quiet:
        s.warn_clamps = False
    try:
        yield
    finally:
        for s, before in quiet:
            s.warn_clamps = before


def check_finite(name: str, x: np.ndarray) -> np.ndarray:
    """Return ``x`` as a float64 array, raising :class:`ModelError` naming ``name`` if any
    element is NaN or infinite."""
    arr = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr.ravel()))[0])
        raise ModelError(f"{name}: non-finite value at index {bad}; all values must be finite")
    return arr
