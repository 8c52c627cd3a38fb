"""CPU the viewer's server side needs per second of a 1 kHz scanner, without zenoh or a page.

Feeds :class:`afmctl.view.scanner_feed.ScannerFeed` what a 1 kHz ``afmctl run`` and an
``afmctl sim --sample ... --publish-rate 500`` publish in one second — 50 setpoint batches of
20 samples (the dispatcher's ~20 ms), 50 drift estimates, 500 tips, 500 image pixels, 1
status — already encoded as on the wire, and builds the 10 frames a page gets per second
(the image every fifth, as JSON). Reports the CPU time per second of data (median of
``--repeats`` runs of ``--seconds`` s of data): below 1 the viewer keeps up; 1/that is the
headroom.

    .venv/bin/python benchmarks/bench_view_feed.py [--seconds 20] [--repeats 5] [--no-write]
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sections import write_section  # noqa: E402

from afmctl.zenoh_api.messages import (SETPOINT_DTYPE, DriftMsg, SimImageMsg, SimTipMsg, StatusMsg,  # noqa: E402
                             encode_setpoints)
from afmctl.view.scanner_feed import ScannerFeed  # noqa: E402


def payloads(seconds: int) -> dict[str, list[bytes]]:
    """One scanner's messages for ``seconds`` s, encoded as on the wire."""
    sp = []
    for k in range(50 * seconds):
        rec = np.zeros(20, SETPOINT_DTYPE)
        rec["seq"] = np.arange(20 * k, 20 * k + 20)
        rec["t_s"] = rec["seq"] * 1e-3
        rec["target_nm"][:, 0] = 4000 + 3000 * np.sin(2 * np.pi * 2 * rec["t_s"])
        rec["target_nm"][:, 1] = 1000 + 100 * rec["t_s"]
        rec["u_V"][:, :2] = rec["target_nm"][:, :2] / 80
        sp.append(encode_setpoints(k, rec))
    t = np.arange(500 * seconds) * 0.002
    x, y = 4000 + 3000 * np.sin(2 * np.pi * 2 * t), 1000 + 100 * t
    return {
        "sp": sp,
        "drift": [DriftMsg(seq=k, t_s=0.02 * k, drift_nm=[0.1, 0.2, 1.0]).to_json_bytes() for k in range(50 * seconds)],
        "tip": [SimTipMsg(seq=k, t_s=t[k], position_nm=[x[k], y[k], 0]).to_json_bytes() for k in range(len(t))],
        "image": [SimImageMsg(seq=k, t_s=t[k], position_nm=[x[k], y[k], 0], height_nm=float(k % 100),
                              sample="grating-2d").to_json_bytes() for k in range(len(t))],
        "status": [StatusMsg(seq=0, scanner="s", t_s=0.0, state="running",
                             stats={"samples": 1, "bridge": {"rejected": 0}}).to_json_bytes()],
    }


def one_run(p: dict[str, list[bytes]], seconds: int) -> float:
    """CPU seconds per second of data."""
    feed = ScannerFeed("s")
    cursor: dict[str, int] = {}
    t0 = time.process_time()
    for k in range(50 * seconds):
        now = 100.0 + 0.02 * k
        feed.on_setpoints(p["sp"][k], now + 0.003)
        feed.on_drift(p["drift"][k])
        for j in range(10):
            feed.on_tip(p["tip"][10 * k + j], now + 0.001 + 0.002 * j)
            feed.on_image(p["image"][10 * k + j])
        if k % 50 == 0:
            feed.on_status(p["status"][0])
        if k % 5 == 0:
            json.dumps(feed.frame(cursor, with_image=k % 25 == 0))
    return (time.process_time() - t0) / seconds


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    p = payloads(args.seconds)
    runs = [one_run(p, args.seconds) for _ in range(args.repeats)]
    med = statistics.median(runs)
    text = f"""## `afmctl view`: server-side CPU per second of a 1 kHz scanner

Command: `.venv/bin/python benchmarks/bench_view_feed.py --seconds {args.seconds} --repeats {args.repeats}`
(CPython {platform.python_version()}, {platform.machine()}; CPU time, so less sensitive to other load than
wall time, but the shared 2-core machine was busy). Per second of data: 1 000 setpoints in 50
batches, 50 drift estimates, 500 tips, 500 image pixels, 1 status, and 10 frames built for one
page (JSON, the image in every fifth).

| CPU per second of data (median of {args.repeats}) | runs | headroom (1 / median) |
|---|---|---|
| {med * 1e3:.0f} ms | {', '.join(f'{r * 1e3:.0f}' for r in runs)} ms | {1 / med:.1f}× |
"""
    print(text)
    if not args.no_write:
        write_section("view-feed", text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
