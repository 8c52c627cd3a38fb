"""What calibrating on the device costs against one continuous recording (issue 38).

On the simulated PI E-727 served over TCP (``afmctl sim --protocol gcs --tcp``, its own
process: the scanner advances on the wall clock, the wave generator plays on the servo
clock, the data recorder records the scanner's position sensor and its amplifier stage's
output), as a user runs it:

1. ``afmctl calibrate --config cal.toml --out cal.json --axes x --kind KIND`` — the
   excitation of ``afmctl excite --kind all`` for the E-727's 0–120 V at ``loop.rate_Hz``
   (10 kHz), played and recorded in pieces of at most the recorder's 87,381 points a signal, the
   pieces joined with the holds between them; its wall time against the excitation's;
2. the reference: the *same* excitation played in one go through a fresh copy of the
   same simulated scanner (the same device-timed play, the same position sensor sampled at
   the recorder's instants, the piezo voltage beside it), written as ``t,u,y,v`` and
   identified by ``afmctl identify --model KIND``;
3. both models through ``afmctl run`` (the real Controller, the simulated amplifier of the
   speed ladder, :func:`afmctl.reports.speed_ladder.controller_errors_nm`): 4 µm raster
   lines at 1, 10 and 50 lines/s; the x error over the central 80 % of every trace and
   retrace, max and RMS in % of the line.

The acceptance of issue 38: calibrate's raster errors within 10 % (or 0.05 % of the range,
whichever is larger) of the continuous recording's.

    .venv/bin/python benchmarks/calibrate_join.py [--kind auto] [--rates 1 10 50]
        [--short] [--work DIR] [--no-write]

Writes its section of docs/BENCHMARKS.md between ``<!-- bench:calibrate_join -->``
markers. Takes about 10 minutes (the full excitation is 53 s; two identifications).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from afmctl.control.calibrate_pieces import excitation_all  # noqa: E402
from afmctl.data.datafiles import write_csv  # noqa: E402
from afmctl.data.excitation import ExcitationSpec  # noqa: E402
from afmctl.reports import speed_ladder as sl  # noqa: E402
from afmctl.sim_backend.scanner import DriftConfig, Scanner, default_scanner_config  # noqa: E402
from sections import write_section  # noqa: E402  (benchmarks/sections.py)

NAME = "calibrate_join"
SERVO_S = 50e-6
SLEW_V_PER_S = 1.0e4          # the default scanner's amplifier
#: the devices: loop.rate_Hz (the table and recorder rate) and how the simulator is reached
DEVICES = {
    "gcs-tcp": {"rate_Hz": 10_000.0, "what": "the simulated E-727 over TCP (`afmctl sim --protocol gcs --tcp`, "
                                             "its own process)"},
    "nv200": {"rate_Hz": 2_000.0, "what": "the simulated sensored NV200 on a pty at its 115200 baud "
                                          "(`[simulation] enabled`, in the calibrating process)"},
    "can": {"rate_Hz": 10_000.0, "what": "the simulated CAN amplifier on python-can's virtual bus, CAN FD "
                                         "(`[simulation] enabled`, in the calibrating process)"},
}
#: a short excitation (a first look; not the acceptance figure)
SHORT = {"dwell_s": 0.5, "gap_s": 0.2, "periods": 4, "f_min_Hz": 20.0, "sweep_V_per_s": 300.0}


def scanner_config():
    """The default simulated scanner without thermal drift (what is compared is the join)."""
    return default_scanner_config().model_copy(update={"drift": DriftConfig(kind="none")})


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def sim_toml(work: Path) -> Path:
    path = work / "sim.toml"
    path.write_text('[amplifier]\nprotocol = "gcs"\n[scanner.drift]\nkind = "none"\n', encoding="utf-8")
    return path


def cal_toml(work: Path, device: str, port: int | None = None) -> Path:
    """The calibration's configuration for ``device`` (:data:`DEVICES`)."""
    link = {"gcs-tcp": f'driver = "gcs"\nport = "socket://127.0.0.1:{port}"',
            "nv200": 'driver = "nv200"', "can": 'driver = "can"\nport = "virtual:bench-calibrate"'}[device]
    options = "fd = true\n" if device == "can" else ""
    simulated = ""
    if device != "gcs-tcp":
        scanner = sl.write_scanner_json(scanner_config(), work / "scanner.json")
        sensor = '[simulation.device]\nsensor = "strain gauge"\n' if device == "nv200" else ""
        simulated = f'[simulation]\nenabled = true\nscanner = "{scanner}"\n{sensor}'
    path = work / "cal.toml"
    path.write_text(f"""
[scanner]
name = "bench"
[amplifier]
{link}
output = "wave"
slew_V_per_s = {SLEW_V_PER_S!r}
[amplifier.options]
timeout_s = 5.0
{options}[loop]
rate_Hz = {DEVICES[device]["rate_Hz"]!r}
[safety]
slew_V_per_s = {SLEW_V_PER_S!r}
ramp_V_per_s = 2000.0
[trajectory]
line_rate_Hz = 10.0
[runlog]
dir = "{work / 'runs'}"
fsync = false
{simulated}""", encoding="utf-8")
    return path


def start_sim(work: Path, port: int) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "afmctl", "sim", "--config", str(sim_toml(work)),
                             "--tcp", f"127.0.0.1:{port}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    proc.stdout.readline()              # the endpoint line: it listens
    return proc


def stop_sim(proc: subprocess.Popen | None) -> None:
    if proc is None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def calibrate(work: Path, device: str, kind: str, short: bool) -> dict:
    """``afmctl calibrate`` on the simulated ``device``; its wall time and output."""
    port = free_port() if device == "gcs-tcp" else None
    sim = start_sim(work, port) if port is not None else None
    try:
        extra = [f"--{k.replace('_', '-')}={v}" for k, v in SHORT.items()] if short else []
        t0 = time.monotonic()
        res = subprocess.run([sys.executable, "-m", "afmctl", "calibrate", "--config", str(cal_toml(work, device, port)),
                              "--out", str(work / "cal.json"), "--axes", "x", "--kind", kind,
                              "--report", str(work / "rep"), *extra], capture_output=True, text=True)
        wall = time.monotonic() - t0
    finally:
        stop_sim(sim)
    if res.returncode != 0:
        raise SystemExit(f"afmctl calibrate failed ({res.returncode}):\n{res.stderr[-3000:]}")
    print(res.stdout, flush=True)
    summary = json.loads((work / "rep" / "calibration.json").read_text())
    return {"wall_s": wall, "stdout": res.stdout, "summary": summary}


def continuous_recording(work: Path, excitation: dict, u_range_V: tuple[float, float]) -> Path:
    """The same excitation (``excitation``: the ExcitationSpec fields calibrate stored in the
    provenance; ``u_range_V``: its range) played in one go through a fresh copy of the
    scanner (module docstring, step 2): ``t,u,y,v`` at the recorder's instants."""
    spec = ExcitationSpec(u_min_V=u_range_V[0], u_max_V=u_range_V[1], **excitation)
    u = excitation_all(spec).u_V
    scanner = Scanner(scanner_config())
    dt = 1.0 / spec.rate_Hz
    scanner.apply({"x": float(u[0]), "y": 0.0, "z": 0.0}, 0.0)
    scanner.advance(2.0)                           # the settle hold calibrate keeps
    t0 = 2.0 + SERVO_S
    cap = scanner.capture_sensor(t0, dt, len(u))
    t = t0 + np.arange(len(u)) * dt
    rows = np.zeros((len(u), 3))
    rows[:, 0] = u
    for k in range(0, len(u), 8192):
        scanner.play(t[k:k + 8192], rows[k:k + 8192])
    scanner.advance(t[-1] + 2 * dt)
    path = work / "continuous.csv"
    write_csv(path, {"t": t - t0, "u": u, "y": cap.y_nm[:, 0], "v": cap.v_V[:, 0]})
    return path


def identify(data: Path, kind: str, out: Path) -> float:
    t0 = time.monotonic()
    res = subprocess.run([sys.executable, "-m", "afmctl", "identify", "--model", kind, "--data", str(data),
                          "--out", str(out)], capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"afmctl identify failed:\n{res.stderr[-3000:]}")
    return time.monotonic() - t0


def x_model(path: Path) -> dict:
    """The x model of a model file (calibrate writes a scanner file for the 3-axis E-727)."""
    data = json.loads(path.read_text())
    return data["axes"]["x"] if data.get("kind") == "scanner" else data


def scanner_file(model: Path, out: Path) -> Path:
    """A scanner file with ``model``'s x model on x (y and z: the linear calibration)."""
    from afmctl.compensators.models import model_from_dict, save_model
    from afmctl.compensators.scanner_model import ScannerModel
    save_model(ScannerModel(axes={"x": model_from_dict(x_model(model))}), out)
    return out


def raster_errors(work: Path, model: Path, rates: list[float]) -> dict[float, dict[str, float]]:
    """x errors of 4 µm raster lines through ``afmctl run`` (module docstring, step 3)."""
    folder = work / f"run-{model.stem}"
    folder.mkdir(exist_ok=True)
    scanner_json = sl.write_scanner_json(scanner_config(), work / "scanner.json")
    gain = Scanner(scanner_config()).nominal_gain_nm_per_V().tolist()
    chain = scanner_file(model, work / f"scanner-{model.stem}.json")
    dynamics = "dynamics" in str(x_model(model).get("structure", ""))
    out = {}
    for rate in rates:
        wave = ""
        if rate in sl.WAVE_RATE_HZ:
            loop_Hz, wave = sl.WAVE_RATE_HZ[rate], sl.WAVE_FD_TOML
        else:
            loop_Hz = (sl.PREVIEW_RATE_HZ if dynamics else sl.CONTROLLER_RATE_HZ).get(rate, 10_000.0 if dynamics
                                                                                        else 2000.0)
        err, _info = sl.controller_errors_nm(folder, scanner_json, chain, rate, loop_Hz, gain,
                                             lines=2 if not wave else 4, amplifier_toml=wave)
        e = sl.error_pct(err[:, :1])
        out[rate] = {"max_pct": e["max_error_pct"], "rms_pct": e["rms_error_pct"]}
        print(f"  {model.stem} {rate:g} lines/s: {out[rate]}", flush=True)
    return out


def verdict(cal: dict[str, float], ref: dict[str, float]) -> str:
    """Within 10 % of the reference's max error, or 0.05 % of the range (the line), whichever is larger."""
    allowed = max(0.1 * ref["max_pct"], 0.05)
    return "yes" if cal["max_pct"] - ref["max_pct"] <= allowed else "no"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="gcs-tcp", choices=list(DEVICES))
    ap.add_argument("--kind", default="auto")
    ap.add_argument("--rates", type=float, nargs="+", default=[1.0, 10.0, 50.0])
    ap.add_argument("--short", action="store_true", help="a short excitation (a first look)")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="calibrate-join-"))
    work.mkdir(parents=True, exist_ok=True)
    print("work:", work, flush=True)
    cal = calibrate(work, args.device, args.kind, args.short)
    prov = json.loads((work / "cal.json").read_text())["provenance"]
    cont = continuous_recording(work, prov["excitation"], tuple(prov["axes"]["x"]["u_range_V"]))
    ident_s = identify(cont, args.kind, work / "continuous.json")
    chosen = {name: x_model(work / f"{name}.json") for name in ("cal", "continuous")}
    errs = {name: raster_errors(work, work / f"{name}.json", args.rates) for name in ("cal", "continuous")}
    text = report(args, cal, prov, chosen, errs, ident_s, work)
    print(text)
    if not args.no_write:
        write_section(NAME if args.device == "gcs-tcp" else f"{NAME}_{args.device}", text)
    return 0


def _structure(model: dict) -> str:
    """``amplifier+preisach+creep+dynamics`` for a chain, else the kind."""
    if model.get("kind") != "chain":
        return str(model.get("kind"))
    return "+".join(model[s]["kind"] for s in ("amplifier", "hysteresis", "creep", "dynamics")
                    if isinstance(model.get(s), dict))


def report(args, cal: dict, prov: dict, chosen: dict, errs: dict, ident_s: float, work: Path) -> str:
    summary = cal["summary"]
    exc_s = float(summary["excitation_s"])
    m = re.search(r"on the device ([\d.]+) s for ([\d.]+) s of excitation and ([\d.]+) s of validation",
                  cal["stdout"])
    device_s, val_s = (float(m.group(1)), float(m.group(3))) if m else (float("nan"), float("nan"))
    axis = prov["axes"]["x"]
    cmd = "`.venv/bin/python benchmarks/calibrate_join.py" \
        + (f" --device {args.device}" if args.device != "gcs-tcp" else "") \
        + (f" --kind {args.kind}" if args.kind != "auto" else "") + (" --short" if args.short else "") + "`"
    lo, hi = axis["u_range_V"]
    with open(work / "rep" / "cal.x-recording.csv", encoding="utf-8") as f:
        joined = sum(1 for _ in f) - 1
    lines = [
        f"## `afmctl calibrate` against one continuous recording (#38): {args.device}",
        "",
        f"{cmd} — {time.strftime('%Y-%m-%d')}, CPython {platform.python_version()}, shared 2-core machine "
        f"(load average {os.getloadavg()[0]:.1f} at the end).",
        "",
        f"{DEVICES[args.device]['what'][0].upper()}{DEVICES[args.device]['what'][1:]}, the default scanner without "
        f"thermal drift, axis x, {lo:g}–{hi:g} V, `loop.rate_Hz` {DEVICES[args.device]['rate_Hz'] / 1000:g} kHz, "
        f"`--kind {args.kind}`; the excitation "
        f"{exc_s:.1f} s ({axis['samples']:,} rows) in {axis['pieces']} pieces of at most {axis['piece_rows']:,} rows; "
        f"the joined recording, holds between the pieces included, {joined:,} rows. "
        "The reference: the same excitation played in one go through a fresh copy of the scanner, recorded at "
        "the same instants, identified by `afmctl identify`. Raster: 4 µm lines through `afmctl run` (the speed "
        "ladder's Controller path), x error over the central 80 % of every trace and retrace, % of the line.",
        "",
        f"Time: `afmctl calibrate` {cal['wall_s']:.1f} s in all for {exc_s:.1f} s of excitation "
        f"({100 * (cal['wall_s'] / exc_s - 1):+.0f} %); on the device {device_s:.1f} s for "
        f"{exc_s + val_s:.1f} s of excitation and validation ({100 * (device_s / (exc_s + val_s) - 1):+.0f} %), "
        f"the rest (identification, validation, files) {cal['wall_s'] - device_s:.1f} s; "
        f"`afmctl identify` on the continuous recording {ident_s:.1f} s.",
        "",
        f"Models: calibrate `{_structure(chosen['cal'])}`, continuous `{_structure(chosen['continuous'])}`. "
        f"Calibrate's held-out validation on its second play: "
        + ", ".join(f"{p} max {v['max_pct']:.2f} / RMS {v['rms_pct']:.2f} %"
                    for p, v in summary["axes"]["x"]["validation"].items()) + ".",
        "",
        "| lines/s | calibrate max / RMS [%] | continuous max / RMS [%] | calibrate's max no worse by over 10 % (or 0.05 % of the line) |",
        "|---|---|---|---|",
    ]
    for rate in args.rates:
        c, r = errs["cal"][rate], errs["continuous"][rate]
        lines.append(f"| {rate:g} | {c['max_pct']:.3f} / {c['rms_pct']:.3f} | {r['max_pct']:.3f} / "
                     f"{r['rms_pct']:.3f} | {verdict(c, r)} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
