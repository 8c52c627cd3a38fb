"""Steps in a recorded command voltage and the transients after them.

A lab's recording is often pieced together from separate waveforms (a slow triangle, then a
fast one starting at another voltage, then a chirp around mid-range): where one piece ends
and the next begins the command jumps. No amplifier follows a jump: its slew limit turns it
into a ramp of milliseconds and the scanner's structural modes ring for tens of
milliseconds after it (Q 60 at 2.2 kHz decays in ≈ 45 ms). For those samples the recorded
voltage is not what the piezo saw, and a static fit that takes them at face value bends its
hysteresis and creep stages to explain a transient (measured, #24: a soft plant's 3 % creep
identified as 14 % from a user-style record with three such joins; 3.5 % with the joins left
out).

:func:`step_transients` marks the samples within :data:`STEP_SETTLE_S` after every jump; the
chain's static stages leave them out of their fit (their memory still runs through them).
"""
from __future__ import annotations

import numpy as np

#: a jump: one sample's change of the command larger than this many times the record's 99th
#: percentile of sample-to-sample changes (a chirp or a triangle within the amplifier's slew
#: rate never does it) ...
JUMP_FACTOR = 10.0
#: ... and larger than this fraction of the command's span
JUMP_MIN_FRACTION = 0.02
#: the samples after a jump left out of static fits [s]: the amplifier's slew and the
#: structural modes' ringing (five decay times of a Q 60 mode at 2 kHz)
STEP_SETTLE_S = 0.05


def jumps(u_V: np.ndarray) -> np.ndarray:
    """Indices ``k`` of the samples where the command jumps (``u[k] − u[k−1]``, module
    docstring); empty for a record without jumps."""
    u = np.asarray(u_V, dtype=float).ravel()
    if u.size < 3:
        return np.zeros(0, dtype=np.int64)
    d = np.abs(np.diff(u))
    span = float(np.ptp(u))
    limit = max(JUMP_FACTOR * float(np.percentile(d, 99.0)), JUMP_MIN_FRACTION * span)
    if not limit > 0:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(d > limit) + 1


def step_transients(u_V: np.ndarray, dt_s: float, settle_s: float = STEP_SETTLE_S) -> np.ndarray:
    """Boolean mask, one per sample of ``u_V`` (sampled every ``dt_s`` [s]): True within
    ``settle_s`` [s] after a jump of the command (:func:`jumps`), from the jump's sample on."""
    u = np.asarray(u_V, dtype=float).ravel()
    mask = np.zeros(u.size, dtype=bool)
    n = max(1, int(round(settle_s / dt_s)))
    for k in jumps(u):
        mask[k:k + n] = True
    return mask
