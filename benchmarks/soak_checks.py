"""The soak's safety checks (benchmarks/soak.py), on files only: run logs and the records of
what the simulated amplifier received.

* :func:`log_steps` — the largest voltage step [V] between consecutive setpoints of one run
  log, each stretch between the controller's (re)starts from a read-back (:data:`CUT_EVENTS`)
  checked on its own; the step from the read-back into a stretch is not in the log (the
  amplifier side sees it);
* :func:`amp_rows` / :func:`amp_steps` — the rows an ``afmctl sim --record`` segment applied,
  one per servo tick or setpoint (the wave generator writes one CSV row per axis update in a
  tick; the last row of a tick is the output), and the largest step between consecutive ones
  from the amplifier's power-on output 0 V;
* :func:`match_received` — which rows the amplifier applied are in the run logs, in order;
* :func:`rss_slope_kB_per_h` — least-squares slope of the RSS samples.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

#: GCS ``SVA``/``WAV`` numbers carry 4 decimals: a value as applied differs from the
#: controller's float by at most half a unit in the last place
RESOLUTION_V = 1e-4


#: events after which the next logged setpoint starts from the output read back, not from the
#: record before it: a (re)start, and a wave stopped or faulted (its played rows are logged
#: conservatively, so the last rows before the stop may be missing)
CUT_EVENTS = ("ramp", "resume", "fault", "wave-stopped", "wave-fault", "stop", "estop")


def read_log(path: Path) -> tuple[np.ndarray, list[dict]]:
    """(u_V rows (n, 3), events) of a run log; a torn tail (a killed run) reads up to the tear."""
    from afmctl.control.runlog import RunLogReader
    r = RunLogReader(path)
    sp = r.setpoints()
    return np.asarray(sp["u_V"], float).reshape(-1, 3), r.events()


def log_steps(u_V: np.ndarray, events: list[dict]) -> float:
    """Largest |Δu| [V] over consecutive records, not across a (re)start from a read-back."""
    if len(u_V) < 2:
        return 0.0
    d = np.abs(np.diff(u_V, axis=0)).max(axis=1)
    cut = sorted({int(e["seq"]) for e in events if e.get("event") in CUT_EVENTS})
    mask = np.ones(len(d), bool)
    for s in cut:               # the step into record ``s`` starts from the read-back, not record s-1
        for k in (s - 1, s):
            if 0 <= k < len(d):
                mask[k] = False
    return float(d[mask].max()) if mask.any() else 0.0


def amp_rows(path: Path) -> np.ndarray:
    """(n, 3) outputs [V] an amplifier record segment applied, the last row of each tick."""
    try:
        a = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except (OSError, ValueError):
        return np.zeros((0, 3))
    if a.size == 0:
        return np.zeros((0, 3))
    t = a[:, 0]
    last = np.ones(len(t), bool)
    last[:-1] = t[1:] != t[:-1]
    return a[last, 1:4]


def amp_steps(rows: np.ndarray) -> float:
    """Largest |Δu| [V] between consecutive applied outputs, from power-on 0 V."""
    if len(rows) == 0:
        return 0.0
    full = np.vstack([np.zeros((1, 3)), rows])
    return float(np.abs(np.diff(full, axis=0)).max())


def dedup(rows: np.ndarray, tol_V: float = RESOLUTION_V / 2) -> tuple[np.ndarray, np.ndarray]:
    """Rows that differ from the one before (a driver sends no unchanged output; a wave value
    held for two servo ticks is one sample); and their indices."""
    if len(rows) == 0:
        return rows, np.zeros(0, int)
    keep = np.ones(len(rows), bool)
    keep[1:] = np.abs(np.diff(rows, axis=0)).max(axis=1) > tol_V
    return rows[keep], np.flatnonzero(keep)


def match_received(received: np.ndarray, logged: np.ndarray, tol_V: float = 1.5 * RESOLUTION_V,
                   window: int = 200_000) -> np.ndarray:
    """For each received row (in order), the index of the logged row it equals (to ``tol_V``)
    at or after the previous match, or -1 when none within ``window`` rows does.

    Both sequences are in time order, so a greedy forward match is the alignment: a stretch
    sent but never applied (the link dropped with it in flight) is skipped in ``logged``.
    """
    out = np.full(len(received), -1, int)
    j = 0
    i = 0
    n, m = len(received), len(logged)
    while i < n and j < m:
        k = min(n - i, m - j)                      # try the present alignment for a whole block
        eq = np.abs(received[i:i + k] - logged[j:j + k]).max(axis=1) <= tol_V
        bad = np.flatnonzero(~eq)
        run = int(bad[0]) if len(bad) else k
        out[i:i + run] = np.arange(j, j + run)
        i, j = i + run, j + run
        if i >= n or j >= m:
            break
        seg = logged[j:j + window]                 # re-align: the next logged row equal to received[i]
        hit = np.flatnonzero(np.abs(seg - received[i]).max(axis=1) <= tol_V)
        if len(hit):
            j += int(hit[0])
        else:
            i += 1                                 # not in the log (within the window)
    return out


def rss_slope_kB_per_h(samples: list[tuple[float, int]], skip_s: float = 60.0) -> float | None:
    """Slope of RSS [kB/h] over the samples after the first ``skip_s`` (start-up: imports,
    JIT, buffers); None with fewer than 10 samples left."""
    if not samples:
        return None
    t = np.array([s[0] for s in samples], float)
    kb = np.array([s[1] for s in samples], float)
    keep = t >= t[0] + skip_s
    if keep.sum() < 10:
        return None
    return float(np.polyfit((t[keep] - t[0]) / 3600.0, kb[keep], 1)[0])
