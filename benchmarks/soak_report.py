"""The soak's figures (benchmarks/soak.py): run logs and amplifier records read back after the
soak, the safety properties checked, the JSON and the markdown table.

The amplifier records are read in chunks (an hour of a 10 kHz wave is tens of millions of
rows); each record row is put on the wall clock (the simulator's clock starts when it
prints its link) and compared with the run whose process was alive then.
"""
from __future__ import annotations

import itertools
import json
from dataclasses import asdict
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from soak_checks import RESOLUTION_V, dedup, log_steps, match_received, read_log, rss_slope_kB_per_h

CHUNK_ROWS = 500_000


def amp_chunks(path: Path, wall0: float):
    """(wall [s], rows (n, 3) [V]) of a record segment, in chunks, the last row of each tick only
    (a tick cut by a chunk boundary is held back to the next chunk)."""
    carry: list[str] = []
    with open(path, encoding="utf-8") as fh:
        next(fh, None)
        while True:
            lines = carry + list(itertools.islice(fh, CHUNK_ROWS))
            final = len(lines) == len(carry)
            if not lines:
                return
            try:
                a = np.loadtxt(lines, delimiter=",", ndmin=2)
            except ValueError:                     # a torn last line of a killed simulator
                a = np.loadtxt(lines[:-1], delimiter=",", ndmin=2) if len(lines) > 1 else np.zeros((0, 4))
                final = True
            if len(a) == 0:
                return
            t = a[:, 0]
            other = np.flatnonzero(t != t[-1])      # hold back the rows of the last tick (not in time
            n = len(a) if final or not len(other) else int(other[-1]) + 1   # order: SVA and wave rows interleave)
            carry = [] if final else lines[n:]
            a, t = a[:n], t[:n]
            last = np.ones(len(t), bool)
            last[:-1] = t[1:] != t[:-1]
            yield wall0 + t[last], a[last, 1:4]
            if final:
                return


def first_send_wall(r) -> float | None:
    """Wall time [s] a run could first have sent a setpoint (its first ``ramp`` event), None if never."""
    if not r.log.exists():
        return None
    from afmctl.control.runlog import RunLogReader
    walls = [e["wall_time"] for e in RunLogReader(r.log).events() if e.get("event") in ("ramp", "ramp-done", "resume")]
    return min(walls) if walls else None


def _amp_side(amp, runs, bound_V: float, finish) -> tuple[float, int, list[float]]:
    """Largest step the amplifier applied (from power-on 0 V in every segment), rows applied, and
    the wall times of the first 20 steps above ``bound_V``. ``runs``: (run, first send wall time)
    in order; a row belongs to the run that began sending last before it (what a device plays
    out after its run ended belongs to that run; a run that never sent gets no row);
    ``finish(run, rows)`` gets each run's rows once no later row can belong to it (memory stays
    bounded by one run)."""
    worst, n_rows = 0.0, 0
    per_run: dict[int, list[np.ndarray]] = {r.index: [] for r, _ in runs}
    done: set[int] = set()
    steps_at: list[float] = []
    sending = [(r, w) for r, w in runs if w is not None]

    def _flush(upto_wall: float) -> None:
        for r, w in runs:
            later = [w2 for _, w2 in sending if w is not None and w2 > w] or [np.inf]
            nxt = min(later) if w is not None else -np.inf
            if r.index not in done and nxt + 2.0 < upto_wall:
                done.add(r.index)
                rows = per_run.pop(r.index)
                finish(r, np.vstack(rows) if rows else np.zeros((0, 3)))

    for path, wall0 in zip(amp.segments, amp.starts_wall):
        prev = np.zeros((1, 3))
        for wall, rows in amp_chunks(path, wall0):
            if not len(rows):
                continue
            d = np.abs(np.diff(np.vstack([prev, rows]), axis=0)).max(axis=1)
            worst = max(worst, float(d.max()))
            steps_at += [float(w) for w in wall[d > bound_V]][:20 - len(steps_at)]
            prev = rows[-1:]
            n_rows += len(rows)
            for k, (r, w) in enumerate(sending):
                nxt = sending[k + 1][1] if k + 1 < len(sending) else np.inf
                sel = (wall >= w) & (wall < nxt)
                if sel.any() and r.index not in done:
                    per_run[r.index].append(rows[sel].astype(np.float32))
            _flush(float(wall[-1]))
    _flush(np.inf)
    return worst, n_rows, steps_at


def _run_match(r, received: np.ndarray, logged: np.ndarray, events: list[dict]) -> dict[str, Any]:
    """Received rows of one run against its log: in the log, and the rest explained or not."""
    rec, _ = dedup(received)
    log_d, _ = dedup(logged)
    m = match_received(rec, log_d)
    hit = np.flatnonzero(m >= 0)
    unmatched = np.flatnonzero(m < 0)
    last = int(hit[-1]) if len(hit) else -1
    names = {e.get("event") for e in events}
    tail = unmatched[unmatched > last]
    explained = 0
    why = ""
    if len(tail) and ("runlog-error" in names or r.rc == 3):
        explained, why = len(tail), "after the run-log error (the safe ramp; nothing can be logged)"
    elif len(tail) and "wave-fault" in names:
        explained, why = len(tail), "the rest of the wave table, played out after a link error (not logged)"
    elif len(tail) and "wave-stopped" in names:
        explained, why = len(tail), "wave rows played before a stop, after the last logged row (logged conservatively)"
    if len(tail) and last < 0 and len(rec) - len(tail) == 0 and not why:
        why = "no logged row reached the amplifier"
    return {"run": r.index, "rc": r.rc, "received": int(len(rec)), "in_log": int(len(hit)),
            "not_in_log": int(len(unmatched)),
            "explained": int(explained), "why": why, "logged": int(len(log_d)),
            "logged_not_received": int(len(log_d) - len(hit))}


def _rss(runs) -> dict[str, Any]:
    """RSS of the longest run: first and last sample [MB] and slope [MB/h]."""
    longest = max(runs, key=lambda r: ((r.end_wall or r.start_wall) - r.start_wall, len(r.rss_kB)), default=None)
    if longest is None or not longest.rss_kB:
        return {}
    slope = rss_slope_kB_per_h(longest.rss_kB)
    return {"run": longest.index, "minutes": round((longest.rss_kB[-1][0] - longest.rss_kB[0][0]) / 60, 1),
            "start_MB": round(longest.rss_kB[0][1] / 1024, 1),
            "after_1min_MB": round(next((kb for t, kb in longest.rss_kB if t >= longest.rss_kB[0][0] + 60),
                                        longest.rss_kB[-1][1]) / 1024, 1),
            "end_MB": round(longest.rss_kB[-1][1] / 1024, 1),
            "slope_MB_per_h": None if slope is None else round(slope / 1024, 2),
            "max_MB_any_run": round(max(kb for r in runs for _, kb in r.rss_kB) / 1024, 1)}


def analyse_leg(spec, leg, amp, faults, soak_end: float, t0: float) -> tuple[dict[str, Any], list[str]]:
    """One leg's figures and its violations."""
    bad: list[str] = []
    runs = list(leg.runs)
    bound = spec.step_bound_V
    log_worst, match_tot = [0.0], {"received": 0, "in_log": 0, "not_in_log": 0, "explained": 0, "logged": 0,
                                   "logged_not_received": 0}
    whys: set[str] = set()
    details: list[dict[str, Any]] = []
    summaries = {"missed_deadlines": 0, "samples": 0, "underruns": 0, "faults": 0, "reconnects": 0, "slew_limited": 0}

    def finish(r, got: np.ndarray) -> None:
        u, events = read_log(r.log) if r.log.exists() else (np.zeros((0, 3)), [])
        s = log_steps(u, events)
        log_worst[0] = max(log_worst[0], s)
        if s > bound + 1e-9:
            bad.append(f"{spec.name} run {r.index}: a logged step of {s:.6g} V > {bound:g} V per sample")
        m = _run_match(r, got, u, events)
        m.update(start_s=round(r.start_wall - t0, 1), end_s=None if r.end_wall is None else round(r.end_wall - t0, 1),
                 largest_logged_step_V=round(s, 6), stderr=r.stderr_tail[-2:])
        details.append(m)
        for k in match_tot:
            match_tot[k] += m[k]
        if m["why"]:
            whys.add(m["why"])
        if m["not_in_log"] > m["explained"]:
            bad.append(f"{spec.name} run {r.index} (started at {m['start_s']} s): {m['not_in_log'] - m['explained']} "
                       "outputs the amplifier applied are not in the run log")
        for k in summaries:
            v = (r.summary or {}).get(k)
            if k == "underruns":
                v = ((r.summary or {}).get("stream") or {}).get("underruns")
            summaries[k] += int(v or 0)
        bad.extend(_run_violations(spec, r, faults, soak_end))

    amp_worst, amp_rows_n, steps_at = _amp_side(amp, [(r, first_send_wall(r)) for r in runs],
                                                bound + RESOLUTION_V + 1e-9, finish)
    log_worst = log_worst[0]
    if amp_worst > bound + RESOLUTION_V + 1e-9:
        bad.append(f"{spec.name}: the amplifier applied a step of {amp_worst:.6g} V > {bound:g} V per sample, first at "
                   + ", ".join(f"{w - t0:.2f}" for w in steps_at[:5]) + " s")
    rcs: dict[str, int] = {}
    for r in runs:
        rcs[str(r.rc)] = rcs.get(str(r.rc), 0) + 1
    out = {"output": spec.output, "rate_Hz": spec.rate_Hz, "slew_V_per_s": spec.slew_V_per_s,
           "step_bound_V": bound, "largest_logged_step_V": round(log_worst, 6),
           "largest_applied_step_V": round(amp_worst, 6), "amp_rows": amp_rows_n, "runs": len(runs),
           "exit_codes": rcs, "amp_segments": len(amp.segments), **match_tot, "not_in_log_why": sorted(whys),
           **summaries, "rss": _rss(runs),
           "stop_s": [round(r.stop_s, 2) for r in runs if r.stop_s is not None],
           "steps_above_limit_at_s": [round(w - t0, 3) for w in steps_at], "run_details": details}
    return out, bad


def _run_violations(spec, r, faults, soak_end: float) -> list[str]:
    """A run that did not stop on SIGTERM, or ended on its own outside every fault's window."""
    if r.killed:
        return [f"{spec.name} run {r.index}: still running {r.stop_s or 0:.0f}+ s after SIGTERM (SIGKILLed)"]
    if r.end_wall is None or r.stop_s is not None:
        return []
    in_fault = any(f.wall <= r.end_wall and (i + 1 >= len(faults) or r.end_wall <= faults[i + 1].wall)
                   for i, f in enumerate(faults))
    if r.rc != 0 and not in_fault:
        return [f"{spec.name} run {r.index}: exit {r.rc} with no fault injected ({(r.stderr_tail or [''])[-1]})"]
    if r.rc == 0 and spec.output == "setpoints" and r.end_wall < soak_end - 1:
        return [f"{spec.name} run {r.index}: ended (exit 0) before the soak asked it to"]
    return []


def analyse(soak, legs_spec) -> dict[str, Any]:
    """Everything the soak measured, and ``violations`` (empty: every check held)."""
    end = soak.stop_wall
    result: dict[str, Any] = {"hours": round((end - soak.t0) / 3600, 3), "load_end": getattr(soak, "load_end", None),
                              "seed": soak.args.seed,
                              "fault_every_s": soak.args.fault_every_s, "legs": {}, "faults": [], "violations": []}
    for f in soak.faults:
        result["faults"].append({"n": f.index + 1, "kind": f.kind, "t_s": f.t_s, "ok": f.ok, **f.outcome})
        if not f.ok:
            result["violations"].append(f"fault {f.index + 1} {f.kind} at {f.t_s} s: {f.outcome}")
    for name, leg in soak.legs.items():
        figures, bad = analyse_leg(legs_spec[name], leg, soak.amps[name], soak.faults, soak.stop_wall,
                                 soak.t0)
        result["legs"][name] = figures
        result["violations"] += bad
    kinds: dict[str, list[int]] = {}
    for f in soak.faults:
        kinds.setdefault(f.kind, [0, 0])
        kinds[f.kind][0] += 1
        kinds[f.kind][1] += int(f.ok)
    result["faults_by_kind"] = {k: {"injected": n, "survived": ok} for k, (n, ok) in kinds.items()}
    return result


def markdown(res: dict[str, Any]) -> str:
    """The soak's table (legs) and the fault list."""
    lines = [f"Soak: {res['hours'] * 60:.1f} min ({res['hours']:.3f} h), faults every ~{res['fault_every_s']:g} s "
             f"(seed {res['seed']}); {len(res['faults'])} faults, "
             f"{sum(f['ok'] for f in res['faults'])} recovered or ended safely; "
             f"violations: {len(res['violations']) or 'none'}", "",
             "| leg | runs (exit codes) | largest step logged / applied / limit [V per sample] | applied outputs "
             "in the log (of received) | logged, not received | RSS after 1 min → end [MB] (slope MB/h), "
             "longest run | missed deadlines "
             "/ samples | underruns | stop after SIGTERM [s] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, g in res["legs"].items():
        rss = g["rss"]
        rss_txt = (f"{rss['after_1min_MB']} → {rss['end_MB']} ({rss['slope_MB_per_h']}) over {rss['minutes']} min"
                   if rss else "—")
        codes = ", ".join(f"{k}: {v}" for k, v in sorted(g["exit_codes"].items()))
        under = g["underruns"] if g["output"] != "wave" else "n/a (table uploaded whole)"
        under = "n/a (host-timed)" if g["output"] == "setpoints" else under
        lines.append(f"| {name} ({g['rate_Hz'] / 1e3:g} kHz) | {g['runs']} ({codes}) | {g['largest_logged_step_V']:.4f}"
                     f" / {g['largest_applied_step_V']:.4f} / {g['step_bound_V']:g} | {g['in_log']} of "
                     f"{g['received']} (+{g['explained']} unloggable: {'; '.join(g['not_in_log_why']) or '—'}) | "
                     f"{g['logged_not_received']} of {g['logged']} | {rss_txt} | {g['missed_deadlines']} / "
                     f"{g['samples']} | {under} | {', '.join(map(str, g['stop_s'])) or '—'} |")
    lines += ["", "| # | fault | at [s] | " + " | ".join(res["legs"]) + " | peer / viewer |",
              "|---|---|---|" + "---|" * len(res["legs"]) + "---|"]
    for f in res["faults"]:
        extra = f.get("peer") or f.get("viewer") or ""
        lines.append(f"| {f['n']} | {f['kind']} | {f['t_s']:.0f} | " + " | ".join(f.get(n, "") for n in res["legs"])
                     + f" | {extra} |")
    if res["violations"]:
        lines += ["", "Violations:", *[f"- {v}" for v in res["violations"]]]
    return "\n".join(lines) + "\n"


DOC_INTRO = """\
Continuous rasters through `afmctl run` (its own process, as a user runs it), two legs at
once, each against its own simulated PI E-727 (`afmctl sim --protocol gcs --tcp`, a separate
process that records every output it applies) reached through a loopback TCP forwarder owned
by the soak: **setpoints** — host-timed setpoints at 1 kHz, one raster of 100,000 frames
(16 lines at 4 lines/s, 6 × 4 µm); **wave** — device-timed output at 10 kHz, a 16-line raster
at 2 lines/s uploaded as wave tables and played by the E-727's generator (20 kHz servo / 2),
one run after another. Both runs publish on zenoh (loopback); a zenoh subscriber process and
`afmctl view` are connected to both. Faults on a seeded schedule (each gap ±25 %, every kind
once per round), each hitting both legs (`disk_full`: one leg, in turn): `link_lost` (the forwarder closes the driver's TCP
connection), `amp_restart` (the simulator SIGKILLed, a new one started 2 s later: power-on
output 0 V), `zenoh_peer` (the subscriber SIGKILLed and started again), `disk_full`
(RLIMIT_FSIZE of the `afmctl run` process lowered to its run log's size with
`resource.prlimit` — the log's next write fails with EFBIG — lifted 5 s later), `viewer_stop`
(`afmctl view` SIGSTOPped 20 s, then SIGCONTed). Steps are per sample (slew limit / loop
rate); *applied* is what the amplifier's record shows, checked independently of the log (+
the E-727's 1e-4 V number resolution). *In the log (of received)*: outputs the amplifier
applied found in the run logs in order; *unloggable*: applied after the log failed (the
safe ramp after `disk_full`) or the rest of a wave table played out after a link error.
Missed deadlines count ticks later than half a period — a loaded shared machine, not a
safety figure. RSS: the `afmctl run` process (not its zenoh child), sampled every 2 s; the
slope is a least-squares fit after the first minute of the longest run (a `disk_full` ends a
run, so runs last ≤ two rounds of faults). `(not hit) …`/`recovered` after a `disk_full` on
the wave leg can mean the run wrote nothing while capped (collecting or uploading).
"""


def write_doc(res: dict[str, Any], table: str) -> None:
    """Replace the ``soak`` section of docs/BENCHMARKS.md."""
    import datetime
    from sections import write_section
    load = res.get("load_end")
    load_txt = f", load average {load:.1f} at the end" if load is not None else ""
    body = ("## Soak: rasters through `afmctl run` for hours, with injected faults (#22)\n\n"
            f"`nice -n 10 .venv/bin/python {res['command']}` — ran {res['hours'] * 60:.1f} min "
            f"({res['hours']:.2f} h) on {datetime.date.today().isoformat()}, 2 shared cores{load_txt}.\n\n"
            + DOC_INTRO + "\n" + table)
    write_section("soak", body)


def save_state(soak, path: Path) -> None:
    """What the analysis needs of a soak (runs, record segments, faults, clocks), as JSON."""
    state = {"t0": soak.t0, "stop_wall": soak.stop_wall, "command": soak.command,
             "load_end": getattr(soak, "load_end", None),
             "args": {"seed": soak.args.seed, "fault_every_s": soak.args.fault_every_s},
             "faults": [asdict(f) for f in soak.faults],
             "legs": {n: [asdict(r) for r in leg.runs] for n, leg in soak.legs.items()},
             "amps": {n: {"segments": [str(p) for p in a.segments], "starts_wall": a.starts_wall}
                      for n, a in soak.amps.items()}}
    path.write_text(json.dumps(state, default=str), encoding="utf-8")


def load_state(path: Path, args) -> SimpleNamespace:
    """A stand-in for the soak that wrote ``path`` (:func:`save_state`), for :func:`analyse`."""
    st = json.loads(path.read_text(encoding="utf-8"))
    legs = {}
    for n, runs in st["legs"].items():
        recs = []
        for r in runs:
            r["log"] = Path(r["log"])
            r["rss_kB"] = [tuple(x) for x in r["rss_kB"]]
            recs.append(SimpleNamespace(**r))
        legs[n] = SimpleNamespace(runs=recs)
    amps = {n: SimpleNamespace(segments=[Path(p) for p in a["segments"]], starts_wall=a["starts_wall"])
            for n, a in st["amps"].items()}
    faults = [SimpleNamespace(**f) for f in st["faults"]]
    args = SimpleNamespace(**{**vars(args), **st["args"]})
    return SimpleNamespace(t0=st["t0"], stop_wall=st["stop_wall"], faults=faults, legs=legs, amps=amps, args=args,
                           command=st["command"], load_end=st.get("load_end"))
