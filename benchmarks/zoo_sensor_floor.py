"""What a plant's sensor leaves to learning: ``check.py``'s learn on a reference scanner as
it is and with its sensor noise switched off (the same identified model), and the error its
sensor's lag alone leaves on the raster.

``../shared/plants/check.py`` learns from the *measured* position and scores the *true* tip.
A sensor that low-pass-filters the tip delays the measurement by its group delay ``τ``;
learning that makes the measurement follow the target leaves the tip ahead of it by
``v·τ`` on a line of speed ``v``: ``τ / T_trace`` of the line (check.py's raster at ``r``
lines/s sweeps each way in ``T_trace = 1/(2r)``). Input → measured recordings
cannot tell that delay from the scanner's own, so neither identification nor learning can
take it out without being told the sensor's response. This script measures it.

    .venv/bin/python benchmarks/zoo_sensor_floor.py --plant lumpy-noisy --work DIR

Needs ``DIR/<plant>/model.json`` (``check.py --keep DIR --plants <plant>`` writes it) for
the chain (each pass learns in a folder of its own beside it); prints the per-iteration max % at 50 | 100 lines/s, with and without noise, and
the lag floor ``100·τ·2r`` % (τ: the sensor filter's group delay at 0 Hz).
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np
from scipy import signal

SHARED = Path(__file__).resolve().parent.parent.parent / "shared" / "plants"
sys.path.insert(0, str(SHARED))


def sensor_delay_s(p) -> float:
    """The group delay at 0 Hz [s] of the plant's sensor filter (the one ``zoo.Plant.run``
    applies), 0 without one."""
    if not p.sensor_fc:
        return 0.0
    b, a = signal.butter(2, p.sensor_fc / (p.fs / 2))
    _, gd = signal.group_delay((b, a), w=[1e-6])
    return float(gd[0]) / p.fs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--plant", default="lumpy-noisy")
    ap.add_argument("--work", type=Path, required=True)
    a = ap.parse_args()
    import check
    import zoo
    d = a.work / a.plant
    tau = sensor_delay_s(zoo.plant(a.plant))
    print(f"{a.plant}: sensor group delay {tau * 1e6:.1f} µs: the lag alone leaves "
          f"{100 * tau * 2 * 50:.2f} | {100 * tau * 2 * 100:.2f} % of the line at 50 | 100 lines/s")
    original = zoo.plant
    for noise in (True, False):
        def chosen(name, _keep=noise):
            p = original(name)
            if not _keep:
                p.noise = 0.0
            return p
        check.plant = chosen
        run = d / ("with-noise" if noise else "without-noise")   # its own state files
        run.mkdir(parents=True, exist_ok=True)
        shutil.copy(d / "model.json", run / "model.json")
        for mode, its in (("chain", 10), ("none", 20)):
            traces = check.learn(a.plant, str(run), mode, its)
            print(f"{a.plant} ({'with' if noise else 'without'} its sensor noise) learn ({mode}, {its} iterations), "
                  "max % at 50 | 100 lines/s: " + " | ".join(" -> ".join(f"{m:.2f}" for m in (tr[0], *tr[-3:]))
                                                             for tr in traces), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
