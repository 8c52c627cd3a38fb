"""Hardware-in-the-loop, live: the simulated tip follows the target while `afmctl run` scans.

``afmctl sim`` (MDT693B on a real pty, the default simulated scanner as its load, the true
tip published on zenoh ``afm/<scanner>/sim/tip``) and ``afmctl run`` (PI compensators
identified from the simulated scanner) in two processes; this test subscribes to the tip
from a real zenoh session on loopback and compares the positions received DURING the raster
with the run's targets. Issue 7 acceptance: "the simulated tip follows the target within the
compensator's accuracy" — measured live, not by an offline replay.
"""
from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from afmctl.config import load_config
from afmctl.control.runlog import RunLogReader
from afmctl.testing import stop_process

import zenoh

pytestmark = pytest.mark.timeout(120)

SCANNER = "livetip"
RATE_HZ = 200            # controller loop rate [Hz]
LINES = 4
LINE_RATE_HZ = 4
WIDTH_NM, HEIGHT_NM, X0_NM, Y0_NM = 6000.0, 4000.0, 1000.0, 1000.0
NM_PER_V = 80.0


def _config_text(tmp_path, port: str, models: dict) -> str:
    comp = "".join(f'[compensation.{a}]\nmodel = "{p}"\n' for a, p in models.items())
    return f"""
[scanner]
name = "hil-live"
[scanner.calibration.x]
nm_per_V = {NM_PER_V}
[scanner.calibration.y]
nm_per_V = {NM_PER_V}
[scanner.calibration.z]
nm_per_V = 13.333
[amplifier]
driver = "mdt693b"
port = "{port}"
slew_V_per_s = 3000
[loop]
rate_Hz = {RATE_HZ}
[safety]
slew_V_per_s = 3000
ramp_V_per_s = 600
watchdog_s = 0.2
[runlog]
dir = "{tmp_path}"
fsync = false
[simulation]
enabled = false
[trajectory]
kind = "raster"
x0_nm = {X0_NM}
y0_nm = {Y0_NM}
width_nm = {WIDTH_NM}
height_nm = {HEIGHT_NM}
lines = {LINES}
line_rate_Hz = {LINE_RATE_HZ}
{comp}
"""


def _first_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices where ``rows`` (N, k) differs from the row before (the first row included)."""
    keep = np.ones(len(rows), bool)
    keep[1:] = np.any(rows[1:] != rows[:-1], axis=1)
    return np.flatnonzero(keep), rows[keep]


def test_live_tip_follows_the_target_within_the_compensators_accuracy(tmp_path):
    from afmctl.zenoh_api.messages import SimTipMsg, decode_json
    from afmctl.simulation.link import identify_pi_models, load_scanner_config, tracking_error
    from afmctl.zenoh_api.settings import ZenohSettings, free_loopback_endpoint
    from afmctl.sim_backend.scanner import Scanner

    (tmp_path / "models").mkdir()
    models = identify_pi_models(tmp_path / "models", "xy", 1e-3)
    endpoint = free_loopback_endpoint()
    record = tmp_path / "received.csv"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    err_path = tmp_path / "sim.stderr"        # a file, not a pipe nobody reads during the run
    err_file = err_path.open("w")
    sim = subprocess.Popen([sys.executable, "-m", "afmctl", "sim", "--protocol", "mdt693b", "--zenoh",
                            "--zenoh-listen", endpoint, "--scanner", SCANNER, "--publish-rate", "200",
                            "--duration", "90", "--record", str(record)],
                           stdout=subprocess.PIPE, stderr=err_file, text=True, env=env)
    lines: queue.Queue[str] = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(ln.rstrip("\n")) for ln in sim.stdout],
                              name="sim-stdout", daemon=True)
    reader.start()
    tips: list[SimTipMsg] = []
    lock = threading.Lock()

    def on_tip(sample) -> None:
        msg = decode_json(sample.payload.to_bytes(), SimTipMsg)
        with lock:
            tips.append(msg)

    def count() -> int:
        with lock:
            return len(tips)

    session = None
    try:
        got: list[str] = []
        deadline = time.monotonic() + 30.0
        while not (got and got[-1].startswith("zenoh:")) and time.monotonic() < deadline:
            try:
                got.append(lines.get(timeout=0.5))
            except queue.Empty:
                assert sim.poll() is None, f"afmctl sim exited: {err_path.read_text()}"
        assert got and got[-1].startswith(f"zenoh: publishing afm/{SCANNER}/sim/tip"), got
        port = got[0]
        assert port.startswith("/"), f"afmctl sim printed {port!r}"

        session = zenoh.open(ZenohSettings(listen=[], connect=[endpoint]).to_zenoh_config())
        sub = session.declare_subscriber(f"afm/{SCANNER}/sim/tip", on_tip)
        deadline = time.monotonic() + 20.0            # the link is up before the run starts
        while count() < 10 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert count() >= 10, "no tip positions arrived over zenoh"

        cfg_path = tmp_path / "live.toml"
        cfg_path.write_text(_config_text(tmp_path, port, models))
        log_path = tmp_path / "run.afmlog"
        run = subprocess.run([sys.executable, "-m", "afmctl", "run", "--config", str(cfg_path), "--log",
                              str(log_path), "--json", "--quiet"], capture_output=True, text=True, timeout=90)
        assert run.returncode == 0, run.stderr
        summary = json.loads(run.stdout)
        assert summary["state"] == "stopped" and summary["errors"] == 0
        n_after = count()                             # a few more ticks: the last setpoints settled
        deadline = time.monotonic() + 10.0
        while count() < n_after + 10 and time.monotonic() < deadline:
            time.sleep(0.02)
        sub.undeclare()
    finally:
        if session is not None:
            session.close()
        stop_process(sim)
        reader.join(timeout=5)
        sim.stdout.close()
        err_file.close()
        err = err_path.read_text()
    assert sim.returncode == 0 and "Traceback" not in err, err

    cfg = load_config(cfg_path)
    log = RunLogReader(log_path)
    sp = log.setpoints()
    assert not log.torn
    np.testing.assert_array_equal(sp["seq"], np.arange(len(sp)))
    ev = {e["event"]: e["seq"] for e in log.events()}
    lo, hi = ev["ramp-done"], ev["end"]
    # plus the ticks the loop advanced the setpoints by for the serial line's delay
    # (afmctl/control/path_delay.py): that many outputs aim at the held start
    advance = log.meta()["path_delay"]["advance_samples"]
    assert hi - lo == LINES * RATE_HZ // LINE_RATE_HZ + 1 + advance

    # ---- the sim clock vs the controller clock: every setpoint reached the amplifier in
    # order (2-decimal MDT format); the k-th distinct output applied at sim time t_rec[k]
    # is the k-th distinct setpoint, sent at controller time t_run[k]
    rec = np.genfromtxt(record, delimiter=",", names=True)
    recv = np.column_stack([rec["x_V"], rec["y_V"], rec["z_V"]])
    sent = np.round(sp["u_V"], 2)
    i_rec, recv_rows = _first_rows(recv)
    i_sent, sent_rows = _first_rows(sent)
    np.testing.assert_allclose(recv_rows, sent_rows, atol=1e-9)
    t_arr = rec["t_s"][i_rec]                          # sim time each distinct output arrived [s]
    t_sent = sp["t_s"][i_sent]                         # controller time it was due [s]
    assert np.all(np.diff(t_arr) >= 0)
    lag = t_arr - t_sent
    offset_s = float(np.median(lag))                   # one constant clock offset for the run
    jitter_s = np.percentile(np.abs(lag - offset_s), [50, 90, 100])

    # ---- the LIVE tip during the raster, against the target at the same (controller) time
    with lock:
        msgs = list(tips)
    seqs = [m.seq for m in msgs]
    assert np.all(np.diff(seqs) > 0), "tip positions out of order"   # drop-oldest: gaps allowed
    t_tip_sim = np.array([m.t_s for m in msgs])
    # Align by time: a tip at sim time t answers the setpoint in force then. The arrival log
    # maps sim time to controller time exactly (linear between arrivals), which stays right
    # when a loaded machine delays the link; a constant offset is only right on average.
    t_tip = np.interp(t_tip_sim, t_arr, t_sent)                  # controller time [s]
    t_tip_const = t_tip_sim - offset_s
    pos = np.array([m.position_nm for m in msgs])
    t_lo, t_hi = sp["t_s"][lo], sp["t_s"][hi - 1]
    during = (t_tip >= t_lo) & (t_tip <= t_hi)
    n_live = int(during.sum())
    # 1 s of raster, sim ticks every 10 ms: nearly all arrive (drop-oldest queue, loopback)
    assert n_live >= 0.6 * (t_hi - t_lo) * 100, n_live
    t_live = t_tip[during]
    target = np.column_stack([np.interp(t_live, sp["t_s"][lo:hi], sp["target_nm"][lo:hi, a]) for a in range(2)])
    live_err = pos[during, :2] - target
    live_max = np.abs(live_err).max(axis=0)
    live_rms = np.sqrt(np.mean(live_err ** 2, axis=0))
    during_c = (t_tip_const >= t_lo) & (t_tip_const <= t_hi)      # the same with the constant offset
    const_err = pos[during_c, :2] - np.column_stack(
        [np.interp(t_tip_const[during_c], sp["t_s"][lo:hi], sp["target_nm"][lo:hi, a]) for a in range(2)])
    const_max, const_rms = np.abs(const_err).max(axis=0), np.sqrt(np.mean(const_err ** 2, axis=0))

    # ---- the compensator's accuracy: the same run replayed offline through a fresh default
    # scanner, one plant step per setpoint (afmctl.simulation.link.tracking_error) ...
    offline = tracking_error(cfg, sp, (lo, hi))
    off_max, off_rms = np.array(offline["max_abs_nm"][:2]), np.array(offline["rms_nm"][:2])
    # ... and at the plant's own time step (each 2-decimal setpoint held for one loop period,
    # as the simulated amplifier does), read at the live tip times: what the sim should show
    scanner_cfg = load_scanner_config(cfg.simulation.scanner)
    rep = int(round(cfg.dt_s / scanner_cfg.dt_s))
    assert rep * scanner_cfg.dt_s == pytest.approx(cfg.dt_s)

    def fine_replay(u_V: np.ndarray) -> np.ndarray:
        y = Scanner(scanner_cfg).run(np.repeat(u_V, rep, axis=0), scanner_cfg.dt_s)
        t_end = sp["t_s"][0] + (np.arange(len(y)) + 1) * scanner_cfg.dt_s
        return np.column_stack([np.interp(t_live, t_end, y[:, a]) for a in range(2)])

    fine = fine_replay(sent)
    fine_rms = np.sqrt(np.mean((fine - target) ** 2, axis=0))
    # no compensation: the linear calibration alone, replayed the same way
    u_lin = np.clip(sp["target_nm"] / np.array([NM_PER_V, NM_PER_V, 13.333]), 0.0, 150.0)
    lin_rms = np.sqrt(np.mean((fine_replay(u_lin) - target) ** 2, axis=0))
    # the exact input the simulated plant got: each recorded output from the sim time it was
    # applied (0 V before), replayed at the plant's time step and read at the tips' sim times
    t_grid = (np.arange(int(rec["t_s"][-1] / scanner_cfg.dt_s) + rep) + 1) * scanner_cfg.dt_s
    held = np.searchsorted(rec["t_s"], t_grid - scanner_cfg.dt_s, side="right") - 1
    u_rec = np.where(held[:, None] >= 0, recv[np.maximum(held, 0)], 0.0)
    y_rec = Scanner(scanner_cfg).run(u_rec, scanner_cfg.dt_s)
    t_sim = t_tip_sim[during]
    assert t_sim[-1] <= t_grid[-1]
    replayed = np.column_stack([np.interp(t_sim, t_grid, y_rec[:, a]) for a in range(2)])
    live_vs_rec_rms = np.sqrt(np.mean((pos[during, :2] - replayed) ** 2, axis=0))
    live_vs_fine_rms = np.sqrt(np.mean((pos[during, :2] - fine) ** 2, axis=0))
    print(f"\nlive tip: clock offset {offset_s * 1e3:.1f} ms, arrival jitter p50/p90/max "
          f"{(jitter_s * 1e3).round(1)} ms; constant-offset alignment: max {const_max.round(0)} rms "
          f"{const_rms.round(0)} nm")
    print(f"live tip: {n_live} tips in the raster; error vs target [nm] "
          f"x,y: live max {live_max.round(0)} rms {live_rms.round(0)}; offline (tracking_error) max "
          f"{off_max.round(0)} rms {off_rms.round(0)}; fine replay rms {fine_rms.round(0)}; uncompensated "
          f"rms {lin_rms.round(0)}; live vs fine replay rms {live_vs_fine_rms.round(0)}, vs replay of the "
          f"received voltages {live_vs_rec_rms.round(1)}")

    # the tip swept the raster: x over the line width, y over the frame height
    assert np.ptp(pos[during, 0]) > 0.9 * WIDTH_NM
    assert np.ptp(pos[during, 1]) > 0.75 * HEIGHT_NM * (LINES - 1) / LINES
    # The live tip IS the plant's response to the voltages the amplifier received, when it
    # received them: the replay agrees to well below one setpoint step (v_max * dt); what is
    # left is the tip's time stamp (taken just before the tick advances the plant).
    v_max = WIDTH_NM * LINE_RATE_HZ * 2                  # nm/s, fast-axis speed (trace, retrace)
    step_nm = v_max * cfg.dt_s                           # the target moves this much per setpoint
    assert np.all(live_vs_rec_rms < 0.5 * step_nm), (live_vs_rec_rms, step_nm)
    # Live vs the compensator's offline accuracy. Margin 2 * step_nm: the amplifier holds
    # each setpoint for a loop period while the (linearly interpolated) target moves on
    # (up to one step), and each voltage step rings the scanner's resonance, which the
    # one-sample-per-setpoint replay cannot see (overshoot up to the step itself).
    assert np.all(live_max <= 1.5 * off_max + 2 * step_nm), (live_max, off_max, step_nm)
    assert np.all(live_rms <= 1.5 * off_rms + step_nm / 2), (live_rms, off_rms, step_nm)
    # ... and far better than the linear calibration alone (no hysteresis model) when the loop
    # kept its time: the safety layer limits each step by the wall time since the last send, so
    # a loaded host's stalled link (arrivals up to 0.4 s late under a CPU hog) holds the output
    # back and the setpoints themselves trail the target (offline 388 vs 268 nm RMS quiet)
    if summary["slew_limited"] <= 2:
        assert np.all(live_rms < 0.7 * lin_rms), (live_rms, lin_rms)
