"""Loop timing of afmctl.control.controller.Controller: lateness p50/p99/max and missed deadlines.

Runs the controller at ``--rate`` Hz (1 kHz default) for ``--seconds`` (60 s default) over
a raster scan through the whole chain — drift predictor (physical_tube), PI inverse model
per axis (identified from the default simulated scanner), safety layer — into an
amplifier, with the run log and the dispatcher running as in service. Amplifiers:

* ``memory`` (default): :class:`afmctl.simulation.link.RecordingAmplifier`, the loop's own cost;
* ``can``: the real CAN driver on the python-can virtual bus with the simulated CAN
  amplifier (and a recording load) in the same process.

Targets (docs/CONTROLLER.md): at 1 kHz, p99 lateness ≤ 200 µs and no deadline missed by
more than half a period. The result table replaces the ``bench:loop`` section of
docs/BENCHMARKS.md (``--no-write`` to only print it).

    .venv/bin/python benchmarks/bench_loop.py                 # 60 s at 1 kHz, memory amplifier, SCHED_FIFO 10
    .venv/bin/python benchmarks/bench_loop.py --seconds 10 --amp can --rt 0
"""
from __future__ import annotations

import argparse
import contextlib
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sections import write_section as _write_section  # noqa: E402  (benchmarks/sections.py)


def _pi_models(d: Path) -> dict[str, Path]:
    from afmctl.simulation.link import identify_pi_models
    return identify_pi_models(d, "xyz", 1e-3, n=300)


def run_once(rate: float, seconds: float, amp_kind: str, tmp: Path, models: dict[str, Path],
             rt: int | None = None, zenoh: str = "off", cpu: str = "auto") -> dict:
    """One timed run; ``zenoh``: ``off``, ``inproc`` (ZenohBridge in this process) or
    ``child`` (the bridge in a child process, afmctl.zenoh_api.process) — with a subscriber in
    another process receiving every setpoint batch. ``cpu``: ``loop.cpu`` (auto, none or a
    CPU number); this thread (and so the subscriber process) keeps off the loop's CPU, as in
    ``afmctl run``."""
    from afmctl.control import cpu_pinning
    from afmctl.config import load_config
    from afmctl.control.controller import Controller
    from afmctl.control.hardware import open_driver
    from afmctl.simulation.link import RecordingAmplifier
    comp = "".join(f'[compensation.{a}]\nmodel = "{p}"\n' for a, p in models.items())
    line_rate = 2.0
    lines = max(1, int(round(seconds * line_rate)))
    channel = f"afmctl-bench-{os.getpid()}"
    text = f"""
[scanner]
name = "bench"
[amplifier]
driver = "can"
port = "virtual:{channel}"
[simulation]
enabled = true
[loop]
rate_Hz = {rate}
{f"realtime_priority = {rt}" if rt else ""}
cpu = {cpu if cpu.isdigit() else repr(cpu).replace("'", '"')}
[compensation.drift]
enabled = true
params = "physical_tube"
{comp}
[safety]
slew_V_per_s = 5000
ramp_V_per_s = 2000
[runlog]
dir = "{tmp}"
fsync = true
[trajectory]
kind = "raster"
x0_nm = 1000
y0_nm = 1000
z_nm = 500
width_nm = 5000
height_nm = 5000
lines = {lines}
line_rate_Hz = {line_rate}
"""
    cfg = load_config(text=text)
    cpu_pinning.pin_this_thread(cpu_pinning.plan_for(cfg.loop).others)
    server = None
    if amp_kind == "memory":
        amp = RecordingAmplifier()
    else:
        from afmctl.sim_backend.testing import serve_can
        server = serve_can(channel)
        server.__enter__()
        amp = open_driver(cfg, cfg.amplifier.port)
    received = None
    try:
        ctl = Controller(cfg, amp)
        with _zenoh_side(ctl, cfg, zenoh) as counter:
            ctl.start(cfg.trajectory)
            ctl.wait(seconds * 3 + 30)
            ctl.close()
        received = counter.get("result")
    finally:
        amp.close()
        if server is not None:
            server.__exit__(None, None, None)
    st = ctl.stats()
    if received is not None and (received["samples"] != st["samples"] or received["gaps"]):
        raise RuntimeError(f"the subscriber did not receive every batch: {received} of {st['samples']} samples")
    period = 1.0 / rate
    return {"zenoh": zenoh, "received": received, "p50_us": st["lateness_p50_s"] * 1e6, "p99_us": st["lateness_p99_s"] * 1e6,
            "max_us": st["lateness_max_s"] * 1e6, "missed": st["missed_deadlines"],
            "work_p50_us": st["work_p50_s"] * 1e6, "work_p99_us": st["work_p99_s"] * 1e6,
            "ticks": st["ticks"], "samples": st["samples"], "half_period_us": period / 2 * 1e6,
            "overruns": st["overruns"], "slew_limited": st["slew_limited"]}


@contextlib.contextmanager
def _zenoh_side(ctl, cfg, mode: str):
    """The zenoh bridge of ``mode`` and a subscriber process counting every setpoint batch;
    yields a dict that gets ``result`` (the subscriber's counts) on exit."""
    import subprocess
    out: dict = {}
    if mode == "off":
        yield out
        return
    from afmctl.zenoh_api.settings import loopback_pair
    srv, cli = loopback_pair()
    if mode == "inproc":
        from afmctl.zenoh_api.bridge import ZenohBridge
        bridge = ZenohBridge(ctl, srv, "bench")
    else:
        from afmctl.zenoh_api.process import ZenohBridgeProcess
        bridge = ZenohBridgeProcess(ctl, srv, "bench")
    sub = subprocess.Popen([sys.executable, str(ROOT / "benchmarks" / "zenoh_counter.py"), cli.model_dump_json(),
                            "bench"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        if sub.stdout.readline().strip() != "ready":
            raise RuntimeError("zenoh_counter.py did not start")
        time.sleep(1.0)                      # the subscription reaches the bridge
        yield out
    finally:
        bridge.close()
        text, _ = sub.communicate("", timeout=60)
        v = text.split()
        out["result"] = {"batches": int(v[1]), "samples": int(v[3]), "gaps": int(v[5])}


def bare_loop(rate: float, seconds: float, spin_s: float = 2e-4, rt: int | None = None) -> dict:
    """The floor: the same sleep-then-spin schedule doing nothing, on its own thread."""
    import threading
    out: dict = {}

    def body() -> None:
        if rt:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt))
            except OSError:
                pass
        per = 1.0 / rate
        n = int(seconds * rate)
        late = np.empty(n)
        nxt = time.perf_counter()
        for i in range(n):
            nxt += per
            rem = nxt - time.perf_counter()
            if rem > spin_s:
                time.sleep(rem - spin_s)
            while time.perf_counter() < nxt:
                pass
            late[i] = time.perf_counter() - nxt
        out["late"] = late

    t = threading.Thread(target=body)
    t.start()
    t.join()
    late = out["late"] * 1e6
    return {"p50_us": float(np.median(late)), "p99_us": float(np.percentile(late, 99)),
            "max_us": float(late.max()), "missed": int((late > 0.5e6 / rate).sum()), "ticks": len(late)}


def c_floor(rate: float, seconds: float, rt: int | None, workdir: Path) -> dict | None:
    """The floor without Python: benchmarks/timer_floor.c (clock_nanosleep at absolute
    deadlines, doing nothing), when a C compiler is on the PATH; None otherwise."""
    import shutil
    import subprocess
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        return None
    exe = workdir / "timer_floor"
    subprocess.run([cc, "-O2", "-o", str(exe), str(ROOT / "benchmarks" / "timer_floor.c")], check=True)
    out = subprocess.run([str(exe), f"{rate:g}", f"{seconds:g}", str(rt or 0)], check=True,
                         capture_output=True, text=True).stdout.split()
    vals = dict(zip(out[0::2], out[1::2]))
    return {"rt": vals["rt"] == "1", "ticks": int(vals["ticks"]), "missed": int(vals["missed"]),
            "p50_us": float(vals["p50_us"]), "p99_us": float(vals["p99_us"]), "max_us": float(vals["max_us"])}


def write_section(text: str, name: str = "loop") -> None:
    _write_section(name, text)


def _each(runs: list[dict], key: str) -> str:
    return ", ".join(f"{r[key]:.0f}" for r in runs)


def zenoh_compare(args: argparse.Namespace) -> int:
    """Lateness with zenoh off / in process / in a child process, interleaved per repetition."""
    modes = [m.strip() for m in args.zenoh.split(",") if m.strip()]
    bad = [m for m in modes if m not in ("off", "inproc", "child")]
    if bad or not modes:
        print(f"bench_loop.py: --zenoh {args.zenoh!r}: modes must be off, inproc or child", file=sys.stderr)
        return 2
    runs: dict[str, list[dict]] = {m: [] for m in modes}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        models = _pi_models(tmp)
        for k in range(args.reps):
            for m in modes:
                r = run_once(args.rate, args.seconds, args.amp, tmp, models, args.rt, zenoh=m, cpu=args.cpu)
                runs[m].append(r)
                print(f"rep {k + 1} zenoh {m:6s}: p50 {r['p50_us']:.1f} us  p99 {r['p99_us']:.1f} us  "
                      f"max {r['max_us']:.1f} us  missed {r['missed']} of {r['ticks']}; work p50 "
                      f"{r['work_p50_us']:.1f} us; subscriber {r['received']}", flush=True)
    med = {m: {k: statistics.median(r[k] for r in runs[m]) for k in ("p50_us", "p99_us", "max_us", "missed",
                                                                     "work_p50_us")} for m in modes}
    base = med.get("off", {}).get("p99_us")
    cmd = (f".venv/bin/python benchmarks/bench_loop.py --zenoh {','.join(modes)} --seconds {args.seconds:g} "
           f"--rate {args.rate:g} --reps {args.reps} --amp {args.amp} --rt {args.rt or 0} --cpu {args.cpu}")
    load = os.getloadavg()[0]
    rows = "\n".join(
        f"| {m} | {med[m]['p50_us']:.1f} µs | {med[m]['p99_us']:.1f} µs | "
        f"{(med[m]['p99_us'] / base) if base else float('nan'):.2f} | {med[m]['max_us']:.0f} µs | "
        f"{med[m]['missed']:g} | {med[m]['work_p50_us']:.1f} µs | "
        f"{_each(runs[m], 'p99_us')} |" for m in modes)
    text = f"""## Control loop timing with the zenoh API

Command: `{cmd}` — medians of {args.reps} repetitions, the modes interleaved in each
repetition (same machine state for each); {platform.python_implementation()} {platform.python_version()},
{os.cpu_count()} CPUs shared with other work, load average {load:.1f} at the end, {time.strftime('%Y-%m-%d')}.
The bench:loop chain at {args.rate:g} Hz; with zenoh the bridge publishes every setpoint batch, drift
estimate and status, and a subscriber in another process (benchmarks/zenoh_counter.py) receives every
setpoint batch (checked: no gap, every sample). *off*: no bridge; *inproc*: `ZenohBridge` in the loop's
process; *child*: `afmctl.zenoh_api.process.ZenohBridgeProcess` (what `afmctl run` uses), the bridge in
its own process fed through a pipe. `loop.cpu` {args.cpu}: {'the loop thread on a CPU of its own, every other thread (dispatcher, feeder, zenoh process, subscriber) on the others' if args.cpu != 'none' else 'no CPU pinning'}; the dispatcher works in the quiet part of the loop period
(`afmctl.control.controller.quiet_window_wait_s`). Target (#14): p99 with zenoh ≤ 1.2 × off and ≤ 150 µs.

| zenoh | lateness p50 | lateness p99 | p99 / off | max | missed | work p50 | p99 of each run [µs] |
|---|---|---|---|---|---|---|---|
{rows}
"""
    print(text)
    if not args.no_write:
        write_section(text, "loop-zenoh")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0, help="duration of each run [s] (default 60)")
    ap.add_argument("--rate", type=float, default=1000.0, help="loop rate [Hz] (default 1000)")
    ap.add_argument("--reps", type=int, default=1, help="repetitions; medians are reported (default 1)")
    ap.add_argument("--amp", choices=["memory", "can"], default="memory", help="amplifier (default memory)")
    ap.add_argument("--cpu", default="auto", metavar="CPU",
                    help="loop.cpu: auto (default: the loop thread on the highest CPU, everything else on the "
                         "others), none (no pinning) or a CPU number")
    ap.add_argument("--rt", type=int, default=10, metavar="PRIO",
                    help="loop.realtime_priority: SCHED_FIFO priority of the loop thread (default 10; needs "
                         "root or CAP_SYS_NICE, otherwise normal scheduling); 0 = normal scheduling")
    ap.add_argument("--no-write", action="store_true", help="do not update docs/BENCHMARKS.md")
    ap.add_argument("--zenoh", metavar="MODES", default=None,
                    help="compare zenoh modes side by side instead, comma-separated of off, inproc (the bridge "
                         "in the loop's process), child (the bridge in its own process), e.g. off,inproc,child: "
                         "each repetition runs every mode in turn with a subscriber process receiving every "
                         "setpoint batch; medians and ratios to off go to the bench:loop-zenoh section")
    args = ap.parse_args(argv)
    args.rt = args.rt or None
    if args.zenoh:
        return zenoh_compare(args)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        models = _pi_models(tmp)
        runs = []
        for k in range(args.reps):
            r = run_once(args.rate, args.seconds, args.amp, tmp, models, args.rt, cpu=args.cpu)
            runs.append(r)
            print(f"run {k + 1}: p50 {r['p50_us']:.1f} us  p99 {r['p99_us']:.1f} us  max {r['max_us']:.1f} us  "
                  f"missed {r['missed']} of {r['ticks']} ticks; work p50 {r['work_p50_us']:.1f} us", flush=True)
        base = bare_loop(args.rate, min(10.0, args.seconds), rt=args.rt)
        print(f"bare sleep+spin loop: p50 {base['p50_us']:.1f} us  p99 {base['p99_us']:.1f} us  "
              f"max {base['max_us']:.1f} us  missed {base['missed']} of {base['ticks']}", flush=True)
        cbase = c_floor(args.rate, args.seconds, args.rt, tmp)
        if cbase is not None:
            print(f"C timer floor: p50 {cbase['p50_us']:.1f} us  p99 {cbase['p99_us']:.1f} us  "
                  f"max {cbase['max_us']:.1f} us  missed {cbase['missed']} of {cbase['ticks']}", flush=True)
    med = {k: statistics.median(r[k] for r in runs)
           for k in ("p50_us", "p99_us", "max_us", "missed", "ticks", "work_p50_us", "work_p99_us",
                     "slew_limited")}
    ok99 = med["p99_us"] <= 200.0
    ok_missed = med["missed"] == 0
    cmd = (f".venv/bin/python benchmarks/bench_loop.py --seconds {args.seconds:g} --rate {args.rate:g} "
           f"--reps {args.reps} --amp {args.amp} --rt {args.rt or 0}")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    text = f"""## Control loop timing

Command: `{cmd}` — median of {args.reps} run(s); {platform.python_implementation()} {platform.python_version()},
{platform.machine()}, {os.cpu_count()} CPUs, load average {load:.1f} at the end, {time.strftime('%Y-%m-%d')}.
Full chain per tick: drift predictor (physical_tube) → PI inverse per axis → safety →
amplifier `{args.amp}`; run log (fsync) and dispatcher running; loop thread
{'SCHED_FIFO priority ' + str(args.rt) + ' (`loop.realtime_priority`)' if args.rt else 'normal scheduling (--rt 0)'}. Lateness = start of a tick
after its absolute deadline; *missed* = more than half a period ({1e6 / args.rate / 2:.0f} µs) late.

| what | rate | median | target |
|---|---|---|---|
| lateness p50 | {args.rate:g} Hz | {med['p50_us']:.1f} µs | |
| lateness p99 | {args.rate:g} Hz | {med['p99_us']:.1f} µs | ≤ 200 µs ({'met' if ok99 else 'NOT met'}) |
| lateness max | {args.rate:g} Hz | {med['max_us']:.1f} µs | |
| missed deadlines | {args.rate:g} Hz | {med['missed']:g} of {med['ticks']:g} ticks | 0 ({'met' if ok_missed else 'NOT met'}) |
| work per tick p50 | {args.rate:g} Hz | {med['work_p50_us']:.1f} µs | (budget {1e6 / args.rate:.0f} µs) |
| work per tick p99 | {args.rate:g} Hz | {med['work_p99_us']:.1f} µs | |
| axis-samples slowed by the slew limit | {args.rate:g} Hz | {med['slew_limited']:g} | (ramps at the slew rate, and ticks right after a late one: a step is at most slew × time since the previous send) |

Floor of this machine at the time: the same sleep-then-spin schedule doing nothing
({min(10.0, args.seconds):g} s, same scheduling): p50 {base['p50_us']:.1f} µs, p99 {base['p99_us']:.1f} µs, max {base['max_us']:.1f} µs,
{base['missed']} of {base['ticks']} ticks more than half a period late. A stall of the whole thread
(another process, the hypervisor) also makes the ticks after it late while the loop catches up.
"""
    if cbase is not None:
        text += f"""
Floor without Python: `benchmarks/timer_floor.c` (a C thread waking at absolute deadlines with
`clock_nanosleep`, doing nothing; {'SCHED_FIFO' if cbase['rt'] else 'normal scheduling'}; {args.seconds:g} s): p50 {cbase['p50_us']:.1f} µs,
p99 {cbase['p99_us']:.1f} µs, max {cbase['max_us']:.1f} µs, **{cbase['missed']} of {cbase['ticks']} ticks more than half a period
late**. Where this is not 0 the machine itself (its hypervisor) stalls threads for longer than half
a period, and no program on it can meet the "no missed deadline" target.
"""
    print(text)
    if not args.no_write:
        write_section(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
