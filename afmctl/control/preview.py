"""Preview horizon of the compensation pipeline: one latency for all three axes.

A chain with a dynamics stage inverts with a *preview* inverse (Zou & Devasia's
preview-based stable inversion; :class:`afmctl.compensators.dynamics_inverse.PreviewInverse`):
its output at sample k is the voltage the scanner needs at sample k − L, L =
``latency_samples``. Axes may have different L (or none). :func:`equalise_latency` delays
the input of every axis whose latency is shorter than the longest one, so that all three
outputs aim at the same target sample; the pipeline's latency is then that longest L.

The loop (:mod:`afmctl.control.machine`) reads the trajectory L samples ahead of what it
emits: it feeds the first sample L extra times before the first output (the scanner held
at the start of the trajectory), feeds the last sample L extra times after the end (the
last L outputs), and records each output beside the target it aims at.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from afmctl.compensators.base import StreamingOperator


class DelayLine(StreamingOperator):
    """``y[k] = x[k − n]`` (``initial`` before the first input); unit-free (nm in, nm out)."""

    def __init__(self, n: int, initial: float = 0.0) -> None:
        if int(n) < 0:
            raise ValueError(f"delay: n = {n!r}; need ≥ 0 samples")
        self.n = int(n)
        self.initial = float(initial)
        self._buf = [self.initial] * self.n
        self._i = 0

    def reset(self) -> None:
        self._buf = [self.initial] * self.n
        self._i = 0

    def step(self, x: float) -> float:
        if self.n == 0:
            return x
        i = self._i
        y = self._buf[i]
        self._buf[i] = x
        self._i = i + 1 if i + 1 < self.n else 0
        return y

    def block(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        if self.n == 0:
            return x.copy()
        n, k = self.n, x.shape[0]
        past = np.asarray(self._buf[self._i:] + self._buf[:self._i], dtype=np.float64)  # oldest first
        joined = np.concatenate([past, x])
        out = joined[:k].copy()
        self._buf = joined[-n:].tolist()
        self._i = 0
        return out


class Delayed(StreamingOperator):
    """``op`` fed its input ``delay`` samples late; ``latency_samples`` = op's + delay."""

    def __init__(self, op: StreamingOperator, delay: int) -> None:
        self.op = op
        self.delay = DelayLine(delay)
        self.latency_samples = int(getattr(op, "latency_samples", 0)) + int(delay)

    def reset(self) -> None:
        self.delay.reset()
        self.op.reset()

    def step(self, x: float) -> float:
        return self.op.step(self.delay.step(x))

    def block(self, x: np.ndarray) -> np.ndarray:
        return self.op.block(self.delay.block(x))


def latency_of(op: StreamingOperator) -> int:
    """Samples by which ``op``'s output lags its input (0 for an operator without preview)."""
    return int(getattr(op, "latency_samples", 0))


def equalise_latency(inverses: Sequence[StreamingOperator]) -> tuple[list[StreamingOperator], int]:
    """The per-axis inverses with every shorter latency padded to the longest one (their
    input delayed), and that latency L [samples]; unchanged when no axis has a preview."""
    lat = [latency_of(op) for op in inverses]
    L = max(lat, default=0)
    return [op if n == L else Delayed(op, L - n) for op, n in zip(inverses, lat)], L
