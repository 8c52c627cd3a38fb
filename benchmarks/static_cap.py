"""What capping the block-mean static record costs the candidates it changes (issue 38):
``chain.STATIC_MAX_SAMPLES`` (a long record's PI, EPI, Bouc–Wen and creep stages fitted on at
most that many block means, never below ``STATIC_MIN_RATE_HZ``) against no cap, each
candidate scored as ``--model auto`` scores it (:func:`afmctl.compensators.selection.score_candidate`:
fitted on the first 70 % after the burn-in, held-out RMS / max of the rest), one after the other
in one process.

    .venv/bin/python benchmarks/static_cap.py RECORDING.csv [STRUCTURE ...]

RECORDING.csv: columns t,u,y (e.g. ``afmctl calibrate``'s ``OUT.x-recording.csv``);
STRUCTURE: default ``bouc-wen pi+creep``. Prints the figures; docs/BENCHMARKS.md quotes them.
"""
from __future__ import annotations

import os
import sys
import time

from afmctl.api.identify import prepare
from afmctl.compensators import chain, selection
from afmctl.data.identdata import delayed


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__)
        return 2
    c, _where = prepare("auto", argv[0])
    t, u, y, k0 = c.t_s, delayed(c.t_s, c.u_V, c.delay_s), c.y_nm, c.fit_from
    split = k0 + int(round((t.size - k0) * 0.7))
    parts = selection.dynamics_parts(u, t)
    capped = chain.STATIC_MAX_SAMPLES
    print(f"{t.size:,} rows; load {os.getloadavg()[0]:.1f}", flush=True)
    for structure in argv[1:] or ["bouc-wen", "pi+creep"]:
        for cap in (10**9, capped):
            chain.STATIC_MAX_SAMPLES = cap
            t0 = time.perf_counter()
            row = selection.score_candidate(structure, t, u, y, split, {}, k0, parts=parts)
            print(f"{structure:<16} {'no cap' if cap == 10**9 else f'cap {cap:,}':<12} {time.perf_counter() - t0:7.1f} s  "
                  f"held-out rms {row.get('heldout_rms_nm')} nm, max {row.get('heldout_max_nm')} nm, "
                  f"train rms {row.get('train_rms_nm')} nm {row.get('error', '')}", flush=True)
        chain.STATIC_MAX_SAMPLES = capped
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
