"""Where the device time of ``afmctl calibrate`` goes (issue 38), on the simulated E-727 over
TCP (``afmctl sim --protocol gcs --tcp``, its own process; ``--device can``: the CAN
amplifier on python-can's virtual bus, CAN FD, in the calibrating process), the excitation
and configuration of ``benchmarks/calibrate_join.py`` (axis x, 10 kHz, the full excitation
or ``--short``'s):

the device part of :class:`afmctl.api.calibrate.Calibration` (open, excite, validate, back
to the safe value — the identification is not run), each step's wall time summed over the
pieces: the tables' play (start to the host seeing the generator stopped), the upload, the
recorder read-back after the play and while it plays, the start, the settle hold, ...

    .venv/bin/python benchmarks/calibrate_time.py [--reps N] [--device gcs-tcp|can] [--short]
    .venv/bin/python benchmarks/calibrate_time.py --whole [--kind auto] [--device ...] [--short]

``--whole``: the whole ``afmctl calibrate`` process as a user runs it (the identification
included), timed around the process, and the time line it prints.

Prints the figures (medians over ``--reps``); docs/BENCHMARKS.md quotes them.
"""
from __future__ import annotations

import argparse
import collections
import functools
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

import calibrate_join as cj  # noqa: E402  (benchmarks/calibrate_join.py)
from afmctl.api.calibrate import Calibration  # noqa: E402
from afmctl.control import calibrate_run as cr  # noqa: E402
from afmctl.control import wave_run as wr  # noqa: E402
from afmctl.control.wave_players import TablePlayer  # noqa: E402
from afmctl.control.wave_players import FifoPlayer  # noqa: E402
from afmctl.drivers.can_amp import CANAmplifier  # noqa: E402
from afmctl.drivers.gcs import GCSAmplifier  # noqa: E402

#: what is timed: (class, method, label)
STEPS = [(TablePlayer, "play", "play (start → generator seen stopped)"),
         (FifoPlayer, "arm", "CAN: start the stream, queue the prefill"),
         (FifoPlayer, "play", "CAN: play (the clock's start → the FIFO drained)"),
         (CANAmplifier, "configure_recorder", "CAN: arm the recorder"),
         (CANAmplifier, "read_recorded", "CAN: read-back while it plays (overlapped)"),
         (GCSAmplifier, "upload_wave", "upload (WAV)"),
         (GCSAmplifier, "start_wave", "start (WSL/WGC/WTR/WOS?/WGO)"),
         (GCSAmplifier, "configure_recorder", "arm the recorder"),
         (cr.CalibrationRun, "_read", "read-back after the play"),
         (wr.WaveMachine, "_approach", "approach and settle hold"),
         (wr.WaveMachine, "_collect", "collect the table"),
         (GCSAmplifier, "read_recorded", "read-back while it plays (overlapped)")]


class _DeviceDone(Exception):
    pass


class DeviceOnly(Calibration):
    """The device part only: no identification; stops where the validations would be written."""

    def _fit_later(self, axis, rec):        # noqa: D102
        pass

    def _write_validations(self, joined):   # noqa: D102
        self.joined = joined
        raise _DeviceDone


def timed(totals: dict, counts: dict) -> None:
    for cls, name, label in STEPS:
        if not hasattr(cls, name):
            continue
        f = getattr(cls, name)

        @functools.wraps(f)
        def g(*a, _f=f, _label=label, **k):
            t0 = time.perf_counter()
            try:
                return _f(*a, **k)
            finally:
                totals[_label] += time.perf_counter() - t0
                counts[_label] += 1
        setattr(cls, name, g)


def one_run(work: Path, totals: dict, counts: dict, device: str = "gcs-tcp", short: bool = False) -> dict:
    port = cj.free_port() if device == "gcs-tcp" else None
    sim = cj.start_sim(work, port) if port is not None else None
    try:
        before = dict(totals)
        cal = DeviceOnly(str(cj.cal_toml(work, device, port)), work / "cal.json", axes=["x"], kind="pi",
                         report_dir=work / "rep", excitation=dict(cj.SHORT) if short else None)
        t0 = time.monotonic()
        try:
            cal.run()
        except _DeviceDone:
            pass
        device_s = time.monotonic() - t0
    finally:
        cj.stop_sim(sim)
    rec, val, _ = cal.joined["x"]
    rate = float(cal.config.loop.rate_Hz)
    played = (int(rec.measured.sum()) + int(val.measured.sum())) / rate
    return {"device_s": device_s, "played_s": played, "joined_rows": len(rec.t_s),
            "steps": {k: totals[k] - before.get(k, 0.0) for k in totals}}


def whole(reps: int, kind: str, device: str = "gcs-tcp", short: bool = False) -> int:
    """The whole command (``calibrate_join.calibrate``), ``reps`` times."""
    walls = []
    for _ in range(reps):
        with tempfile.TemporaryDirectory(prefix="calibrate-whole-") as d:
            r = cj.calibrate(Path(d), device, kind, short=short)
        walls.append(r["wall_s"])
        line = next(ln for ln in r["stdout"].splitlines() if ln.startswith("time "))
        print(f"whole afmctl calibrate --kind {kind}: {r['wall_s']:.1f} s around the process; {line.strip()}; "
              f"load {os.getloadavg()[0]:.1f}", flush=True)
    print(f"median of {reps}: {statistics.median(walls):.1f} s")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--whole", action="store_true", help="time the whole afmctl calibrate process")
    ap.add_argument("--kind", default="auto", help="with --whole: the model kind (default auto)")
    ap.add_argument("--device", choices=("gcs-tcp", "can", "nv200"), default="gcs-tcp")
    ap.add_argument("--short", action="store_true", help="the short excitation of calibrate_join.py --short")
    args = ap.parse_args()
    if args.whole:
        return whole(args.reps, args.kind, args.device, args.short)
    totals: dict = collections.defaultdict(float)
    counts: dict = collections.Counter()
    timed(totals, counts)
    runs = []
    for _ in range(args.reps):
        with tempfile.TemporaryDirectory(prefix="calibrate-time-") as d:
            runs.append(one_run(Path(d), totals, counts, args.device, args.short))
        r = runs[-1]
        print(f"device {r['device_s']:.1f} s for {r['played_s']:.1f} s of excitation and validation "
              f"({100 * (r['device_s'] / r['played_s'] - 1):+.0f} %), joined recording {r['joined_rows']:,} rows; "
              f"load {os.getloadavg()[0]:.1f}", flush=True)
    med = statistics.median
    print(f"median of {len(runs)}: device {med(r['device_s'] for r in runs):.1f} s for "
          f"{med(r['played_s'] for r in runs):.1f} s, joined {med(r['joined_rows'] for r in runs):,.0f} rows")
    for label in sorted(runs[0]["steps"], key=lambda k: -runs[0]["steps"][k]):
        print(f"  {med(r['steps'].get(label, 0.0) for r in runs):7.2f} s  {label}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
