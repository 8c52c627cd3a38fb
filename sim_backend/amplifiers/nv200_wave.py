"""The arbitrary waveform generator of the simulated NV200, sans-I/O (no thread, no port).

Commands as the vendor's ``nv200`` library (``WaveformGenerator``) issues them: ``gbarb,i,p``
writes buffer slot i (0..1023) with p percent of the range (``gbarb,i`` reads it back),
``goarb`` the index the generator starts at, ``gsarb``/``gearb`` the first and last index of
the loop, ``gcarb`` the cycles (0 = until stopped), ``gtarb`` the sampling factor (a sample
lasts factor x 50 us), ``grun,1``/``grun,0`` run/stop (``grun`` reads 1 while it runs). The
generator drives the output only while ``modsrc`` is 3 (waveform generator).

Playback: started at t0 (the first 50 us tick at or after ``grun,1``), the generator plays
goarb..gearb, then gsarb..gearb for each further cycle; sample k of that sequence is applied
at exactly ``t0 + k * factor * 50 us`` (:meth:`WaveBuffer.run_until` with the unit's clock).
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

BUFFER_SIZE = 1024
BASE_SAMPLE_S = 50e-6
#: parameter -> (lowest, highest) accepted
RANGES = {"goarb": (0, BUFFER_SIZE - 1), "gsarb": (0, BUFFER_SIZE - 1), "gearb": (0, BUFFER_SIZE - 1),
          "gcarb": (0, 65535), "gtarb": (1, 65535), "grun": (0, 1)}


class WaveBuffer:
    """``WaveBuffer(apply)``; ``apply(percent, t_s)`` is called for every played sample."""

    def __init__(self, apply: Callable[[float, float], None]) -> None:
        self.apply = apply
        self.values = [0.0] * BUFFER_SIZE
        self.params = {"goarb": 0, "gsarb": 0, "gearb": 0, "gcarb": 1, "gtarb": 1, "grun": 0}
        self.t0_s = 0.0
        self.k = 0
        self.played = 0

    def set(self, name: str, value: int, now_s: float) -> bool:
        """Set a parameter; False when out of range (the unit answers an error)."""
        lo, hi = RANGES[name]
        if not lo <= value <= hi:
            return False
        if name == "grun":
            self.run_until(now_s)
            if value == 1 and not self.params["grun"]:
                self.t0_s = math.ceil(now_s / BASE_SAMPLE_S - 1e-9) * BASE_SAMPLE_S
                self.k = 0
        elif self.params["grun"] and name != "gcarb":
            return False  # the sequence cannot change under a running generator
        self.params[name] = value
        return True

    def length(self) -> float:
        """Samples in the whole run (inf for gcarb 0)."""
        p = self.params
        first = p["gearb"] - p["goarb"] + 1
        loop = p["gearb"] - p["gsarb"] + 1
        if first < 1 or loop < 1:
            return 0
        return math.inf if p["gcarb"] == 0 else first + (p["gcarb"] - 1) * loop

    def index(self, k: int) -> int:
        """Buffer index of sample k of the run."""
        p = self.params
        first = p["gearb"] - p["goarb"] + 1
        if k < first:
            return p["goarb"] + k
        return p["gsarb"] + (k - first) % (p["gearb"] - p["gsarb"] + 1)

    def sample_time_s(self, k: int) -> float:
        return self.t0_s + k * self.params["gtarb"] * BASE_SAMPLE_S

    def run_until(self, now_s: float) -> int:
        """Apply every sample due at or before ``now_s`` (one ``apply`` each); the generator
        stops after the last."""
        t, values = self.take_due(now_s)
        for tk, vk in zip(t.tolist(), values.tolist()):
            self.apply(vk, tk)
        return len(t)

    def next_due_s(self) -> float | None:
        """When the next sample not yet played falls due [s] (None: the generator is idle)."""
        return self.sample_time_s(self.k) if self.params["grun"] else None

    def take_due(self, now_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Every sample due at or before ``now_s`` as arrays (times [s], buffer values [%]),
        the generator moved past them (what :meth:`run_until` applies one by one)."""
        if not self.params["grun"]:
            return np.zeros(0), np.zeros(0)
        total = self.length()
        step = self.params["gtarb"] * BASE_SAMPLE_S
        end = max(self.k, int(math.floor((now_s - self.t0_s) / step)) + 1) if now_s >= self.t0_s else self.k
        end = int(min(end, total))
        while end < total and self.sample_time_s(end) <= now_s:
            end += 1
        while end > self.k and self.sample_time_s(end - 1) > now_s:
            end -= 1
        k = np.arange(self.k, end)
        p = self.params
        first = p["gearb"] - p["goarb"] + 1
        idx = np.where(k < first, p["goarb"] + k, p["gsarb"] + (k - first) % max(p["gearb"] - p["gsarb"] + 1, 1))
        t = self.t0_s + k * p["gtarb"] * BASE_SAMPLE_S
        values = np.asarray(self.values, dtype=np.float64)[idx] if len(k) else np.zeros(0)
        self.k = end
        self.played += len(k)
        if self.k >= total:
            self.params["grun"] = 0
        return t, values
