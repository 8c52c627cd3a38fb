"""Load through one zenoh router: three scanners at 10 kHz setpoints (by default), a subscriber counting
every record (issue 39; docs/ZENOH.md, "A lab").

Each scanner is a process of its own, as ``afmctl run`` is: the Controller at
``loop.rate_Hz`` 10 000 streaming a 50 lines/s raster to the simulated CAN FD amplifier on
python-can's virtual bus (``output = "stream"``: how afmctl drives 10 kHz; a recording
sink, no scanner simulation, as benchmarks/stream_10k.py), its run log, and — in the
*router* phase — the zenoh bridge in its child process (``ZenohBridgeProcess``, what
``afmctl run`` uses) as a client of ``afmctl router`` (a process, default settings:
loopback, default ACL). This process subscribes through the router to every scanner's
``setpoint`` and counts every record. Phases *off* (no zenoh at all) and *router*
alternate ``--reps`` times (same machine state for both).

Measured: records delivered of those the loops made, per scanner (batch sequence gaps);
latency from publish to delivery — from the moment the controller's dispatcher hands a
batch to its sinks (the bridge among them) to the subscriber's callback for the zenoh
message holding it, both on ``time.monotonic()`` of this machine — median and p99 over
messages; and the loops' p99 lateness with the router against zenoh off, as a ratio: of
every tick of every scanner and repetition pooled into one histogram per phase (a rep's p99
on 2 shared cores is bimodal, ~0 or ~200 µs, so the median over reps jumps between the
two), beside the median over scanners and repetitions. The table replaces the ``lab-router`` section of
docs/BENCHMARKS.md (``--no-write``: only print it).

    .venv/bin/python benchmarks/lab_router.py                # 3 scanners, 20 s per phase, 2 repetitions
    .venv/bin/python benchmarks/lab_router.py --seconds 5 --reps 1 --no-write
"""
from __future__ import annotations

import argparse
import bisect
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from sections import write_section  # noqa: E402  (benchmarks/sections.py)

NAME = "lab-router"
SCANNERS = ("lab1", "lab2", "lab3")


# ---------------------------------------------------------------------------- one scanner
class DispatchClock:
    """A controller sink that notes when each setpoint batch is handed out: (first sample,
    records, monotonic time [s])."""

    def __init__(self) -> None:
        self.batches: list[tuple[int, int, float]] = []

    def on_setpoints(self, batch) -> None:
        self.batches.append((int(batch["seq"][0]), len(batch), time.monotonic()))

    def on_drift(self, estimate) -> None:
        pass

    def on_status(self, status) -> None:
        pass


def worker(name: str, endpoint: str, seconds: float, runs: Path, rate_Hz: float, output: str, rt: int,
           phase: float | None = None) -> int:
    """One scanner (the module docstring); prints one JSON line with its figures.
    ``output``: ``stream`` or ``wave`` (the simulated CAN FD amplifier), or ``setpoints``
    (host-timed, one setpoint per tick into a recording amplifier: the loop's own cost);
    ``rt``: ``loop.realtime_priority`` (0: none); ``phase``: ``loop.phase`` (None: unset)."""
    from afmctl.control.controller import Controller
    from afmctl.drivers.can_amp import CANAmplifier
    from afmctl.sim_backend.amplifiers.base import RecordingSink
    from afmctl.sim_backend.testing import serve_can
    from afmctl.testing import make_config
    from afmctl.zenoh_api.settings import ZenohSettings
    channel = f"lab-{name}-{uuid.uuid4().hex[:6]}"
    loop: dict = {"rate_Hz": rate_Hz, **({"realtime_priority": rt} if rt else {}),
                  **({"phase": phase} if phase is not None else {})}
    cfg = make_config(runs, "", loop=loop,
                      amplifier={"driver": "can", "port": f"virtual:{channel}", "output": output,
                                 "slew_V_per_s": 1e5, "low_water_s": 0.1, "high_water_s": 0.2, "options": {"fd": True}},
                      safety={"slew_V_per_s": 1e5, "ramp_V_per_s": 2000},
                      trajectory={"kind": "raster", "x0_nm": 1000.0, "y0_nm": 1000.0, "width_nm": 4000.0,
                                  "height_nm": 800.0, "lines": int(50 * seconds), "line_rate_Hz": 50.0,
                                  "mode": "trace-retrace"},
                      scanner={"name": name, "calibration": {"x": {"nm_per_V": 80.0}, "y": {"nm_per_V": 80.0},
                                                             "z": {"nm_per_V": 13.3}}})
    clock = DispatchClock()
    with serve_can(channel, RecordingSink(max_history=10)):
        if output == "setpoints":
            from afmctl.simulation.link import RecordingAmplifier
            amp = RecordingAmplifier()
        else:
            amp = CANAmplifier.open(f"virtual:{channel}", fd=True)
            amp.connect()
        try:
            with Controller(cfg, amp) as ctl:
                ctl.add_sink(clock)
                bridge = None
                if endpoint != "off":
                    from afmctl.zenoh_api.process import ZenohBridgeProcess
                    zs = ZenohSettings(enabled=True, mode="client", listen=[], connect=[endpoint])
                    bridge = ZenohBridgeProcess(ctl, zs, scanner_name=name)
                    time.sleep(1.0)                       # the subscriber's declaration reaches the service
                ctl.start(cfg.trajectory)
                if not ctl.wait(seconds * 5 + 60):
                    raise SystemExit(f"{name}: the run did not finish")
                st = ctl.stats()
                hist = ctl.lateness_histogram()
                if bridge is not None:
                    bridge.close()
        finally:
            amp.close()
    print(json.dumps({"name": name, "samples": st["samples"], "p50_s": st["lateness_p50_s"],
                      "p99_s": st["lateness_p99_s"], "missed": st["missed_deadlines"],
                      "underruns": (st["stream"] or {}).get("underruns", 0), "batches": clock.batches,
                      "hist": {int(b): int(hist[b]) for b in np.flatnonzero(hist)}}), flush=True)
    return 0


# ---------------------------------------------------------------------------- the subscriber
class Counter:
    """Every setpoint message of every scanner through the router: (first sample, records,
    arrival [s]) per scanner, and batch sequence gaps."""

    def __init__(self, endpoint: str) -> None:
        from afmctl.zenoh_api.session import open_session
        from afmctl.zenoh_api.settings import ZenohSettings
        self.lock = threading.Lock()
        self.messages: dict[str, list[tuple[int, int, float]]] = {s: [] for s in SCANNERS}
        self.gaps = {s: 0 for s in SCANNERS}
        self._last: dict[str, int] = {}
        self.session = open_session(ZenohSettings(mode="client", listen=[], connect=[endpoint]))
        self.sub = self.session.declare_subscriber("afm/*/setpoint", self._on)

    def _on(self, sample) -> None:
        from afmctl.zenoh_api.messages import decode_setpoints
        t = time.monotonic()
        seq, rec = decode_setpoints(sample.payload.to_bytes())
        name = str(sample.key_expr).split("/")[1]
        with self.lock:
            if name in self._last and seq != self._last[name] + 1:
                self.gaps[name] += 1
            self._last[name] = seq
            if len(rec):
                self.messages[name].append((int(rec["seq"][0]), len(rec), t))

    def reset(self) -> None:
        with self.lock:
            self.messages = {s: [] for s in SCANNERS}
            self.gaps = {s: 0 for s in SCANNERS}
            self._last.clear()

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def latencies(batches: list[tuple[int, int, float]], messages: list[tuple[int, int, float]]) -> list[float]:
    """Publish → delivery [s] of each message: its arrival minus the hand-out time of the
    dispatched batch that holds its first record."""
    starts = [b[0] for b in batches]
    out = []
    for first, _n, arrival in messages:
        k = bisect.bisect_right(starts, first) - 1
        if k >= 0 and first < batches[k][0] + batches[k][1]:
            out.append(arrival - batches[k][2])
    return out


def phase(mode: str, endpoint: str, args: argparse.Namespace, counter: Counter, tmp: Path) -> dict:
    """Three scanners side by side, each its own process; ``mode``: off or router."""
    counter.reset()
    seconds = args.seconds
    procs = [subprocess.Popen([sys.executable, __file__, "--worker", name, "--endpoint",
                               endpoint if mode == "router" else "off", "--seconds", str(seconds),
                               "--rate", str(args.rate), "--output", args.output, "--rt", str(args.rt),
                               "--runs", str(tmp / f"{mode}-{name}"),
                               *(["--phase", f"{k / len(SCANNERS):.6f}"] if args.stagger else [])],
                              stdout=subprocess.PIPE, text=True)
             for k, name in enumerate(SCANNERS)]
    results = {}
    for p in procs:
        out, _ = p.communicate(timeout=seconds * 10 + 180)
        if p.returncode != 0:
            raise SystemExit(f"a scanner process failed (exit {p.returncode})")
        r = json.loads(out.strip().splitlines()[-1])
        results[r["name"]] = r
    time.sleep(0.5)                      # the last messages in flight
    row: dict = {"mode": mode, "p99_us": statistics.median(r["p99_s"] for r in results.values()) * 1e6,
                 "p50_us": statistics.median(r["p50_s"] for r in results.values()) * 1e6,
                 "missed": sum(r["missed"] for r in results.values()),
                 "underruns": sum(r["underruns"] for r in results.values()),
                 "sent": {n: r["samples"] for n, r in results.items()},
                 "hist": pooled([r["hist"] for r in results.values()])}
    if mode == "router":
        with counter.lock:
            msgs = {n: list(m) for n, m in counter.messages.items()}
            row["gaps"] = dict(counter.gaps)
        row["delivered"] = {n: sum(m[1] for m in msgs[n]) for n in SCANNERS}
        lat = [x for n in SCANNERS for x in latencies(results[n]["batches"], msgs[n])]
        row["latency_s"] = sorted(lat)
    return row


def start_router(workdir: Path) -> tuple[subprocess.Popen, str]:
    from afmctl.zenoh_api.settings import free_loopback_endpoint
    endpoint = free_loopback_endpoint()
    proc = subprocess.Popen([sys.executable, "-m", "afmctl", "router", "--listen", endpoint],
                            stdout=subprocess.PIPE, text=True, cwd=workdir)
    assert proc.stdout is not None
    if not proc.stdout.readline().startswith("afmctl router: listening"):
        raise SystemExit("afmctl router did not start")
    return proc, endpoint


def pct(values: list[float], q: float) -> float:
    return values[min(len(values) - 1, int(q * len(values)))] if values else float("nan")


def pooled(hists: list[dict]) -> np.ndarray:
    """Lateness histograms (sparse: bin → count; bins of :mod:`afmctl.control.stats`) added."""
    from afmctl.control import stats as loop_stats
    total = loop_stats.new_histogram()
    for h in hists:
        for b, n in h.items():
            total[int(b)] += n
    return total


def pooled_p99_us(rows: list[dict]) -> float:
    """p99 lateness [µs] of every tick of every scanner in ``rows`` (one distribution)."""
    from afmctl.control import stats as loop_stats
    return loop_stats.percentiles(sum(r["hist"] for r in rows), (0.99,))[0] * 1e6


def report(rows: list[dict], args: argparse.Namespace) -> str:
    off = [r for r in rows if r["mode"] == "off"]
    on = [r for r in rows if r["mode"] == "router"]
    pool_off, pool_on = pooled_p99_us(off), pooled_p99_us(on)
    p99_off = statistics.median(r["p99_us"] for r in off)
    p99_on = statistics.median(r["p99_us"] for r in on)
    lat = sorted(x for r in on for x in r["latency_s"])
    per = "; ".join(f"{n} {sum(r['delivered'][n] for r in on)} of {sum(r['sent'][n] for r in on)}"
                    f" (gaps {sum(r['gaps'][n] for r in on)})" for n in SCANNERS)
    sent = sum(sum(r["sent"].values()) for r in on)
    delivered = sum(sum(r["delivered"].values()) for r in on)
    each = lambda rs: ", ".join(f"{r['p99_us']:.0f}" for r in rs)  # noqa: E731
    cmd = " ".join(["benchmarks/lab_router.py", *(sys.argv[1:])])
    load = os.getloadavg()[0]
    what = ("into a recording amplifier, one setpoint per tick on the host's clock" if args.output == "setpoints"
            else "to the simulated CAN FD amplifier on the virtual bus, played on its clock")
    late = ("the loop's (tick time against its deadline)" if args.output == "setpoints" else
            "the stream producer's (how late it woke for a top-up of the device FIFO; 101950 µs is the "
            "histogram's last bin, ≥ 102 ms)")
    return f"""## A lab through one zenoh router: three scanners at {args.rate:g} Hz, `output = "{args.output}"` (#39)

`.venv/bin/python {cmd}` — {len(SCANNERS)} scanners, each its own process (Controller at
{args.rate:g} Hz, a 50 lines/s raster {what}, `output = "{args.output}"`, run
log on, `loop.realtime_priority` {args.rt or "off"}, `loop.phase` {"0, 1/3, 2/3 (staggered)" if args.stagger else "unset"}), {args.seconds:g} s per phase, phases *off* (no zenoh) and *router* (the bridge in its child
process as a client of `afmctl router`, a subscriber in another process through the router)
interleaved {args.reps}×; 2 CPUs shared with other work, load average {load:.1f} at the end,
{time.strftime('%Y-%m-%d')}. Lateness is {late}; latency runs from the dispatcher handing a batch out to the subscriber's callback for
the zenoh message holding it (both `time.monotonic()`).

| figure | zenoh off | through the router |
|---|---|---|
| records delivered / made | — | {delivered} / {sent} ({100.0 * delivered / max(sent, 1):.3f} %) |
| per scanner | — | {per} |
| publish → delivery, median / p99 | — | {1e3 * pct(lat, 0.5):.2f} ms / {1e3 * pct(lat, 0.99):.2f} ms ({len(lat)} messages) |
| loop lateness p50 (median over scanners, reps) | {statistics.median(r['p50_us'] for r in off):.1f} µs | {statistics.median(r['p50_us'] for r in on):.1f} µs |
| loop lateness p99 (median over scanners, reps) | {p99_off:.1f} µs | {p99_on:.1f} µs (**{p99_on / p99_off:.2f}×** off) |
| p99 of each rep [µs] | {each(off)} | {each(on)} |
| loop lateness p99, every tick of every scanner and rep pooled | {pool_off:.1f} µs | {pool_on:.1f} µs (**{pool_on / pool_off:.2f}×** off) |
| missed deadlines / device underruns (all scanners) | {sum(r['missed'] for r in off)} / {sum(r['underruns'] for r in off)} | {sum(r['missed'] for r in on)} / {sum(r['underruns'] for r in on)} |

Targets (#39): every record delivered; loop p99 (pooled) with the router ≤ 1.2× zenoh off.
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0, help="run length of each phase [s] (default 20)")
    ap.add_argument("--reps", type=int, default=2, help="interleaved repetitions of off and router (default 2)")
    ap.add_argument("--rate", type=float, default=10_000.0, help="loop rate of each scanner [Hz] (default 10000)")
    ap.add_argument("--rt", type=int, default=10, metavar="PRIO",
                    help="loop.realtime_priority of every scanner, SCHED_FIFO (default 10 as afmctl run on a lab PC; 0: none)")
    ap.add_argument("--output", choices=["stream", "wave", "setpoints"], default="stream",
                    help="amplifier.output (default stream: the simulated CAN FD amplifier's FIFO; setpoints: "
                         "host-timed into a recording amplifier)")
    ap.add_argument("--stagger", action="store_true",
                    help="give the scanners loop.phase 0, 1/3, 2/3: their loops, pinned to one CPU, never spin "
                         "at once (default: each where it starts, so that which loops collide varies by rep)")
    ap.add_argument("--phase", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--no-write", action="store_true", help="do not update docs/BENCHMARKS.md")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--endpoint", help=argparse.SUPPRESS)
    ap.add_argument("--runs", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return worker(args.worker, args.endpoint, args.seconds, args.runs, args.rate, args.output, args.rt,
                      args.phase)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        router, endpoint = start_router(tmp)
        counter = Counter(endpoint)
        try:
            for k in range(args.reps):
                for mode in ("off", "router"):
                    r = phase(mode, endpoint, args, counter, tmp)
                    rows.append(r)
                    print(f"rep {k + 1} {mode:6s}: p99 {r['p99_us']:.1f} us, sent {r['sent']}"
                          + (f", delivered {r['delivered']}, gaps {r['gaps']}" if mode == "router" else ""), flush=True)
        finally:
            counter.close()
            router.terminate()
            router.wait(20)
    text = report(rows, args)
    print(text)
    if not args.no_write:
        write_section(f"{NAME}-{args.output}-{args.rate:g}", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
