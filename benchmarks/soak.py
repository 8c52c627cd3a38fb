"""Soak: continuous rasters through ``afmctl run`` for hours, with faults injected on a seeded schedule.

Two legs, each an ``afmctl run`` process (started again whenever one ends) driving its own
simulated PI E-727 (``afmctl sim --protocol gcs --tcp``, a separate process that records
every output it applies, ``--record``) through a loopback TCP forwarder owned by the soak:

* ``setpoints`` — host-timed setpoints at 1 kHz, one long raster (``repeat`` frames);
* ``wave`` — device-timed output at 10 kHz: ``output = "wave"``, a raster table played by the
  E-727's wave generator on its servo clock (20 kHz / 2), one run after another.

Both runs publish on zenoh (loopback listeners); a zenoh subscriber process (soak_peer.py)
and ``afmctl view`` are connected to both. Faults, every ``--fault-every-s`` (± 25 %, seeded),
kinds in a seeded order that visits every kind once per round, each hitting both legs:

* ``link_lost``   — the forwarder closes the driver's TCP connection (the link dropped);
* ``amp_restart`` — the simulated amplifier process SIGKILLed, restarted ``--amp-down-s``
  later (a new process: power-on output 0 V, a new record segment);
* ``zenoh_peer``  — the zenoh subscriber process SIGKILLed and started again;
* ``disk_full``   — RLIMIT_FSIZE of the ``afmctl run`` process lowered to its run log's size
  (``resource.prlimit``; Python ignores SIGXFSZ, so the log's next write fails with EFBIG),
  lifted ``--disk-full-s`` later;
* ``viewer_stop`` — ``afmctl view`` SIGSTOPped for ``--viewer-stop-s``, then SIGCONTed.

Checked (exit status 1 when any fails): the largest step between consecutive setpoints in
every run log and, independently, between consecutive outputs the amplifier applied, within
the slew limit per sample (+ the E-727's 1e-4 V number resolution on the amplifier side);
every fault recovered or ended safely as configured (exit 3 after disk full, exit 1 = fault
for a link lost during a wave play; the leg then starts the next run), the runs keep driving
the amplifier afterwards; every output the amplifier applied is in a run log, except the
ramp to the safe value after a run-log error (nothing can be logged then) — counted apart;
SIGTERM at the end stops every run within ``--stop-timeout-s``; no run ends otherwise.
Reported besides: RSS of the ``afmctl run`` processes at start and end and its slope,
underruns/missed deadlines from the run summaries.

    nice -n 10 .venv/bin/python benchmarks/soak.py [--duration-s 3600] [--fault-every-s 180]
        [--out DIR] [--legs setpoints wave] [--faults KIND ...] [--seed 22] [--write-doc]

Writes DIR/soak.json and DIR/soak.md (the table) and keeps the run logs and records in DIR
(about 75 MB per minute with both legs: 13 minutes left 0.96 GB, an hour ≈ 4.5 GB; without
--out they go to a temporary folder, removed at the end). ``--reanalyse --out DIR`` reads a
soak's files again (DIR/soak-state.json) without soaking.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import resource
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import soak_report  # noqa: E402  (benchmarks/soak_report.py)
from soak_procs import Amp, Leg, Peer, TcpProxy, Viewer, free_port  # noqa: E402

KINDS = ("link_lost", "amp_restart", "zenoh_peer", "disk_full", "viewer_stop")
#: exit statuses of a run that end a fault safely, per leg output and fault kind
#: (exit 1: the run ended in fault, the device holds; exit 2: the amplifier could not be opened
#: at start — nothing was sent; exit 3: the run log could not be written, the output ramped to
#: the safe value); 0 is a wave run's normal end
SAFE_END = {
    "setpoints": {"disk_full": {3}, "amp_restart": {2}},
    "wave": {"link_lost": {0, 1, 2}, "amp_restart": {0, 1, 2}, "disk_full": {0, 3}, "zenoh_peer": {0},
             "viewer_stop": {0}},
}


@dataclass
class LegSpec:
    """One leg: how ``afmctl run`` reaches the amplifier, its rate and raster."""
    name: str
    output: str                 # setpoints | wave
    rate_Hz: float
    slew_V_per_s: float         # safety.slew_V_per_s
    line_rate_Hz: float
    lines: int
    repeat: int
    reply_timeout_s: float = 0.5     # amplifier.options timeout_s (the driver's default 0.5 s)

    @property
    def step_bound_V(self) -> float:
        """Largest step between consecutive samples the controller may emit [V]."""
        return self.slew_V_per_s / self.rate_Hz


LEGS = {
    "setpoints": LegSpec("setpoints", "setpoints", 1000.0, 2000.0, 4.0, 16, 100_000),
    "wave": LegSpec("wave", "wave", 10_000.0, 20_000.0, 2.0, 16, 1, reply_timeout_s=5.0),
}


def config_text(spec: LegSpec, port_url: str, zenoh_port: int, logdir: Path) -> str:
    """The ``afmctl run`` configuration of a leg (gcs driver over the soak's TCP forwarder)."""
    output = f'output = "{spec.output}"\n' if spec.output != "setpoints" else ""
    # a wave upload is 3 x 80,001 numbers through the simulator's Python parser: on a loaded 2-core
    # machine its closing ERR? reply can take longer than the driver's default 0.5 s
    options = f"[amplifier.options]\ntimeout_s = {spec.reply_timeout_s:g}\n"
    return f"""# written by benchmarks/soak.py
[scanner]
name = "soak-{spec.name}"
[scanner.calibration.x]
nm_per_V = 80.0
[scanner.calibration.y]
nm_per_V = 80.0
[scanner.calibration.z]
nm_per_V = 13.333
[amplifier]
driver = "gcs"
port = "{port_url}"
slew_V_per_s = {spec.slew_V_per_s * 1.5:g}
{output}{options}[loop]
rate_Hz = {spec.rate_Hz:g}
[safety]
slew_V_per_s = {spec.slew_V_per_s:g}
ramp_V_per_s = 500
watchdog_s = 0.2
on_finish = "safe"
reconnect_interval_s = 0.2
max_reconnects = 1000
[runlog]
dir = "{logdir}"
fsync = false
[trajectory]
kind = "raster"
x0_nm = 1000
y0_nm = 1000
width_nm = 6000
height_nm = 4000
lines = {spec.lines}
line_rate_Hz = {spec.line_rate_Hz:g}
mode = "trace-retrace"
repeat = {spec.repeat}
[zenoh]
enabled = true
listen = ["tcp/127.0.0.1:{zenoh_port}"]
"""


def schedule(duration_s: float, every_s: float, kinds: list[str], seed: int,
             settle_s: float) -> list[tuple[float, str]]:
    """(time [s from the start], kind) of every fault: gaps every_s × U(0.75, 1.25), the kinds
    in a seeded order that visits each once per round; none in the last ``settle_s``."""
    rng = random.Random(seed)
    out: list[tuple[float, str]] = []
    t, order = 0.0, []
    while True:
        t += every_s * rng.uniform(0.75, 1.25)
        if t > duration_s - settle_s:
            return out
        if not order:
            order = list(kinds)
            rng.shuffle(order)
        out.append((round(t, 3), order.pop(0)))


@dataclass
class Fault:
    """One injected fault and what became of it."""
    index: int
    kind: str
    t_s: float                       # from the soak's start
    wall: float = 0.0
    lifted_wall: float = float("inf")   # amplifier back / limit lifted / SIGCONT
    outcome: dict = field(default_factory=dict)   # per leg (and peer/viewer): text
    targets: list[str] | None = None              # the legs it hit (None: every leg)
    ok: bool = True


class Soak:
    """The processes of a soak and its fault injection."""

    def __init__(self, args: argparse.Namespace, work: Path) -> None:
        self.args, self.work = args, work
        self.t0 = time.time()
        self.stop_wall = self.t0
        self.specs = [LEGS[n] for n in args.legs]
        self.proxies = {s.name: TcpProxy() for s in self.specs}
        self.amps = {s.name: Amp(work, s.name, self.proxies[s.name]) for s in self.specs}
        self.zports = {s.name: free_port() for s in self.specs}
        self.legs: dict[str, Leg] = {}
        self.peer: Peer | None = None
        self.viewer: Viewer | None = None
        self.faults: list[Fault] = []
        self.pending: list[Fault] = []           # injected, not judged yet
        self.growth: dict[str, float] = {s.name: 0.0 for s in self.specs}   # last wall time a record grew

    def start(self) -> None:
        endpoints = [f"tcp/127.0.0.1:{p}" for p in self.zports.values()]
        for spec in self.specs:
            self.amps[spec.name].start()
            cfg = self.work / f"{spec.name}.toml"
            cfg.write_text(config_text(spec, self.proxies[spec.name].url, self.zports[spec.name], self.work),
                           encoding="utf-8")
            leg = Leg(spec.name, cfg, self.work, self.amps[spec.name], self.args.duration_s + 600)
            self.legs[spec.name] = leg
            leg.start()
        self.peer = Peer(endpoints)
        self.peer.start()
        self.viewer = Viewer(endpoints)
        self._wait_driving(self.args.start_timeout_s)

    def _wait_driving(self, timeout_s: float) -> None:
        """Wait until every leg's amplifier has received setpoints; the soak's clock starts then."""
        t_end = time.time() + timeout_s
        base = {n: a.record_bytes() for n, a in self.amps.items()}
        while time.time() < t_end:
            self.watch(time.time() + 0.5)
            if all(self.growth[n] > 0 and self.amps[n].record_bytes() > base[n] for n in self.amps):
                self.t0 = time.time()
                return
        raise RuntimeError(f"the legs did not reach their amplifiers within {timeout_s:g} s: "
                           + "; ".join(f"{n}: {leg.runs[-1].stderr_tail[-1:] if leg.runs else 'no run'}"
                                       for n, leg in self.legs.items()))

    def watch(self, until_wall: float) -> None:
        """Sleep until ``until_wall``, noting when each amplifier record grows, and judge the
        faults whose outcome is known."""
        last = {n: a.record_bytes() for n, a in self.amps.items()}
        while time.time() < until_wall:
            time.sleep(min(0.5, max(0.0, until_wall - time.time())))
            for n, a in self.amps.items():
                b = a.record_bytes()
                if b != last[n]:
                    self.growth[n], last[n] = time.time(), b
            self.judge_ready()

    # -- the faults ---------------------------------------------------------------------------
    def inject(self, f: Fault) -> None:
        f.wall = time.time()
        a = self.args
        if f.kind == "link_lost":
            for p in self.proxies.values():
                p.drop()
        elif f.kind == "amp_restart":
            for amp in self.amps.values():
                amp.kill()
            self.watch(time.time() + a.amp_down_s)
            for amp in self.amps.values():
                amp.start()
        elif f.kind == "zenoh_peer":
            self.peer.kill()
            self.watch(time.time() + 1.0)
            self.peer.start()
        elif f.kind == "disk_full":
            self._disk_full(f, a.disk_full_s)
        elif f.kind == "viewer_stop":
            self.viewer.sigstop()
            self.watch(time.time() + a.viewer_stop_s)
            self.viewer.sigcont()
        f.lifted_wall = time.time()

    def _disk_full(self, f: Fault, hold_s: float) -> None:
        """Cap RLIMIT_FSIZE of one leg's run (the legs take turns, so that a run of each lives
        twice as long between these; ``f.targets``), lift it after ``hold_s``."""
        k = sum(g.kind == "disk_full" for g in self.faults[:f.index])
        names = list(self.legs)
        f.targets = [names[k % len(names)]]
        limited = []
        for leg in (self.legs[n] for n in f.targets):
            rec, proc = leg.current, leg.proc
            if rec is None or proc is None or proc.poll() is not None:
                continue
            try:
                size = max(1, rec.log.stat().st_size)
                soft, hard = resource.prlimit(proc.pid, resource.RLIMIT_FSIZE)
                resource.prlimit(proc.pid, resource.RLIMIT_FSIZE, (size, hard))
                limited.append((proc, soft, hard))
            except (OSError, ProcessLookupError):
                continue
        self.watch(time.time() + hold_s)
        for proc, soft, hard in limited:
            try:
                resource.prlimit(proc.pid, resource.RLIMIT_FSIZE, (soft, hard))
            except (OSError, ProcessLookupError):
                pass          # the run ended (as it should: exit 3)

    # -- what became of a fault ---------------------------------------------------------------
    def _recovered(self, f: Fault) -> bool:
        """Every leg drives its amplifier again after the fault was lifted (and the peer receives,
        the viewer is running)."""
        ok = all(self.growth[n] > f.lifted_wall + 0.6 for n in self.legs)
        if f.kind == "zenoh_peer":
            ok &= self.peer.messages > 0
        return ok

    def judge_ready(self, final: bool = False) -> None:
        """Judge every pending fault that recovered, or waited ``--recover-s`` for it, or all at the end."""
        for f in list(self.pending):
            if final or self._recovered(f) or time.time() > f.lifted_wall + self.args.recover_s:
                self.pending.remove(f)
                self.classify(f)
                _progress(self, f)

    def classify(self, f: Fault) -> None:
        """Judge fault ``f``: the runs that ended after it (before the next fault) and whether the
        legs drive their amplifiers again."""
        nxt = next((g.wall for g in self.faults if g.index == f.index + 1), float("inf"))
        for name, leg in self.legs.items():
            f.outcome[name], ok = self._leg_outcome(f, name, leg, nxt)
            if f.targets is not None and name not in f.targets:
                f.outcome[name] = "(not hit) " + f.outcome[name]
            f.ok &= ok
        if f.kind == "zenoh_peer":
            ok = self.peer.messages > 0
            f.outcome["peer"] = (f"restarted, {self.peer.messages} messages since" if ok
                                 else "restarted, received nothing since: FAILED")
            f.ok &= ok
        if f.kind == "viewer_stop":
            ok = self.viewer.proc.poll() is None and self.viewer.serves()
            f.outcome["viewer"] = "SIGCONT, page serves" if ok else "viewer did not come back: FAILED"
            f.ok &= ok

    def _leg_outcome(self, f: Fault, name: str, leg: Leg, until: float) -> tuple[str, bool]:
        spec = LEGS[name]
        ended = [r for r in leg.runs if r.end_wall is not None and f.wall <= r.end_wall < until]
        safe = SAFE_END[spec.output].get(f.kind, set())
        bad = [r.rc for r in ended if r.rc not in safe]
        if bad:
            return f"run exit {bad} (allowed {sorted(safe) or 'none'}): FAILED", False
        driving = self.growth[name] > f.lifted_wall + 0.6
        if not driving:
            return (f"nothing reached the amplifier in the {self.args.recover_s:g} s after the fault: FAILED "
                    f"(state: {self._leg_state(leg)})"), False
        if any(r.rc not in (0, None) for r in ended):
            rcs = sorted({r.rc for r in ended})
            return f"ended safely (exit {rcs}), next run drives the amplifier", True
        return "recovered (run continued)" if not ended else "recovered (runs ended normally)", True

    @staticmethod
    def _leg_state(leg: Leg) -> str:
        rec = leg.current
        if rec is None:
            return "no run"
        tail = rec.stderr_tail[-1] if rec.stderr_tail else "no output"
        return f"run {rec.index} alive since {time.time() - rec.start_wall:.0f} s, last line: {tail[:160]}"

    def run(self) -> None:
        a = self.args
        plan = schedule(a.duration_s, a.fault_every_s, a.faults, a.seed, a.settle_s)
        self.start()
        for i, (t, kind) in enumerate(plan):
            self.watch(self.t0 + t)
            f = Fault(i, kind, round(time.time() - self.t0, 1))
            self.faults.append(f)
            self.inject(f)
            self.pending.append(f)
        self.watch(self.t0 + a.duration_s)
        while self.pending and time.time() < max(f.lifted_wall for f in self.pending) + a.recover_s:
            self.watch(time.time() + 0.5)
        self.judge_ready(final=True)

    def close(self) -> None:
        self.stop_wall = time.time()
        for leg in self.legs.values():
            leg.stop(self.args.stop_timeout_s)
        if self.viewer is not None:
            self.viewer.close()
        if self.peer is not None:
            self.peer.close()
        for amp in self.amps.values():
            amp.close()
        for p in self.proxies.values():
            p.close()


def _progress(soak: Soak, f: Fault) -> None:
    print(f"[{time.time() - soak.t0:7.1f} s] fault {f.index + 1} {f.kind} at {f.t_s:.1f} s: "
          + "; ".join(f"{k}: {v}" for k, v in f.outcome.items()), flush=True)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration-s", type=float, default=3600.0, help="how long to soak [s] (default 3600)")
    ap.add_argument("--fault-every-s", type=float, default=180.0,
                    help="mean time between faults [s] (each gap ±25 %%, seeded; default 180)")
    ap.add_argument("--faults", nargs="+", choices=KINDS, default=list(KINDS), help="kinds to inject (default all)")
    ap.add_argument("--legs", nargs="+", choices=list(LEGS), default=list(LEGS),
                    help="setpoints (1 kHz host-timed) and/or wave (10 kHz device-timed); default both, concurrently")
    ap.add_argument("--seed", type=int, default=22, help="seed of the fault schedule (default 22)")
    ap.add_argument("--out", type=Path, default=None, help="folder for soak.json, soak.md, run logs, records "
                    "(default a temporary folder, removed)")
    ap.add_argument("--amp-down-s", type=float, default=2.0, help="amplifier off before its restart [s]")
    ap.add_argument("--disk-full-s", type=float, default=5.0, help="how long the run log's file size is capped [s]")
    ap.add_argument("--viewer-stop-s", type=float, default=20.0, help="how long afmctl view is SIGSTOPped [s]")
    ap.add_argument("--recover-s", type=float, default=60.0,
                    help="a leg must drive its amplifier again this soon after a fault is lifted [s] (default 60)")
    ap.add_argument("--settle-s", type=float, default=20.0, help="no fault in the last S seconds (default 20)")
    ap.add_argument("--stop-timeout-s", type=float, default=15.0,
                    help="a run must exit this soon after SIGTERM at the end [s] (default 15)")
    ap.add_argument("--start-timeout-s", type=float, default=180.0,
                    help="the legs must reach their amplifiers this soon after start [s]; the soak's clock "
                         "(and the fault schedule) starts when they have")
    ap.add_argument("--reanalyse", action="store_true",
                    help="do not soak: analyse again what a soak left in --out (its soak-state.json)")
    ap.add_argument("--write-doc", action="store_true", help="put the table into docs/BENCHMARKS.md (section soak)")
    args = ap.parse_args(argv)
    if not args.duration_s > 0 or not args.fault_every_s > 0:
        ap.error("--duration-s and --fault-every-s must be positive")
    if args.reanalyse and args.out is None:
        ap.error("--reanalyse needs --out DIR (the folder of a soak)")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="afmctl-soak-") as tmp:
        work = (args.out or Path(tmp)).resolve()
        work.mkdir(parents=True, exist_ok=True)
        if args.reanalyse:
            soak = soak_report.load_state(work / "soak-state.json", args)
        else:
            soak = Soak(args, work)
            soak.command = "benchmarks/soak.py " + " ".join(argv if argv is not None else sys.argv[1:])
            print(f"soak: {args.duration_s:g} s, legs {', '.join(args.legs)}, faults every ~{args.fault_every_s:g} s "
                  f"(seed {args.seed}), files in {work}", flush=True)
            try:
                soak.run()
            finally:
                soak.close()
                soak.load_end = os.getloadavg()[0]
                soak_report.save_state(soak, work / "soak-state.json")
        result = soak_report.analyse(soak, LEGS)
        result["command"] = soak.command
        table = soak_report.markdown(result)
        print(table)
        (work / "soak.json").write_text(json.dumps(result, indent=2, default=str), encoding="utf-8")
        (work / "soak.md").write_text(table, encoding="utf-8")
        if args.write_doc:
            soak_report.write_doc(result, table)
        for v in result["violations"]:
            print(f"VIOLATION: {v}", file=sys.stderr)
        return 1 if result["violations"] else 0


if __name__ == "__main__":
    sys.exit(main())
