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

:func:`unexplained` marks the stretches of a residual that are large: 20 ms windows several
times the record's typical one. The chain applies it to its residual above the band its
dynamics were identified in (:func:`afmctl.compensators.chain.refine_with_dynamics`): a
structural mode above the recorded band rings after every corner of a fast triangle,
phase-locked to it, so a static fit that keeps those rows bends the hysteresis density along
the triangle's branches (measured, #24: a 2.2 kHz Q 60 mode past a user-style record's
2 kHz chirp; its 40 Hz triangles left out of the static refit took the 1 line/s raster from
0.91 to 0.49 % max).
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


#: :func:`unexplained`: residual windows [s] ...
UNEXPLAINED_WINDOW_S = 0.02
#: ... whose RMS is above this many times the median window's ...
UNEXPLAINED_FACTOR = 3.0
#: ... and above this fraction of the output's span (a noise-free record's median is tiny)
UNEXPLAINED_FLOOR = 1e-3
#: gaps of up to twice this many windows between marked ones are marked too, and this many
#: windows on either side of a marked run (the ringing of a fast part is phase-locked to it
#: and some windows fall below the threshold between its peaks)
UNEXPLAINED_MARGIN = 2
#: when more than this share of the record is unexplained the model is wrong, not the
#: record: nothing is marked
UNEXPLAINED_MAX_SHARE = 0.2


def unexplained(residual_nm: np.ndarray, dt_s: float, span_nm: float) -> np.ndarray:
    """Boolean mask, one per sample of ``residual_nm`` (a model's output minus the recorded
    one [nm], sampled every ``dt_s`` [s]): True in the :data:`UNEXPLAINED_WINDOW_S` windows
    whose RMS exceeds both :data:`UNEXPLAINED_FACTOR` × the median window's and
    :data:`UNEXPLAINED_FLOOR` × ``span_nm`` (module docstring), gaps between them and margins
    around them filled (:data:`UNEXPLAINED_MARGIN`). All False when no window does, or when
    more than :data:`UNEXPLAINED_MAX_SHARE` of the record would be marked."""
    from scipy.ndimage import binary_closing, binary_dilation

    r = np.asarray(residual_nm, dtype=float).ravel()
    w = max(1, int(round(UNEXPLAINED_WINDOW_S / dt_s)))
    n = r.size // w
    mask = np.zeros(r.size, dtype=bool)
    if n < 4:
        return mask
    rms = np.sqrt(np.mean(r[:n * w].reshape(n, w) ** 2, axis=1))
    bad = rms > max(UNEXPLAINED_FACTOR * float(np.median(rms)), UNEXPLAINED_FLOOR * float(span_nm))
    if bad.any():
        reach = np.ones(2 * UNEXPLAINED_MARGIN + 1, dtype=bool)
        bad = binary_dilation(binary_closing(bad, reach, border_value=0), reach)
    if not bad.any() or bad.mean() > UNEXPLAINED_MAX_SHARE:
        return mask
    mask[:n * w] = np.repeat(bad, w)
    return mask
