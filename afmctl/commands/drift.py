"""``afmctl drift``: offline thermal-drift prediction and the drift parameter sets."""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)

HELP = "predict thermal drift from temperature (and voltages); fit, show and export drift parameter sets"

DESCRIPTION = """\
Thermal drift of the scanner predicted from the drift paper's transfer functions
(Korayem & Sadeghzadeh 2010, Appendix A1-A11): ambient temperature and the heat the
piezo voltages generate (HG = S_DE*V*dV/dt - S_EE*V^2) -> drift x, y, z in nm.
See docs/DRIFT.md.

  afmctl drift predict --temperature TEMP.csv --out DRIFT.csv
  afmctl drift params --params table_a1 --out my_scanner.json   (edit, then --params my_scanner.json)
  afmctl drift fit --temperature TEMP.csv --drift MEASURED.csv --out my_scanner.json
  afmctl drift measure frame1.gwy frame2.gwy ... --out MEASURED.csv   (drift from images)
"""

MEASURE_DESCRIPTION = """\
Measure the drift from successive AFM frames of the same area: each frame is
phase-correlated with the previous one (sub-pixel, upsampled DFT), the shifts accumulate,
and the tip's drift since the first frame is written (the sample is taken to stay put: if
the tip drifts by +d, features appear at -d).

Inputs:
  IMG...                   two or more frames, in time order: .gwy, .gsf, .tif, Asylum .ibw or Bruker
                           Nanoscope .spm/.000–.999 (trace channel, or the retrace of a retrace-only
                           Nanoscope file; pixel size from the scan size in the file's metadata;
                           each scan line is levelled by its median before the correlation)
  --frame-period-s S       time between frames (s); default: lines / line rate from the
                           file's metadata
Output:
  --out DRIFT.csv          columns t,x,y,dx_px,dy_px (s, nm, nm, px, px): t of each frame
                           from the first, the drift x,y since the first frame, and the
                           content's shift against the previous frame. Feed it to
                           'afmctl drift fit --drift DRIFT.csv'.

Example:
  afmctl drift measure scan_001.gwy scan_002.gwy scan_003.gwy --out drift_xy.csv
"""

PREDICT_DESCRIPTION = """\
Predict drift offline.

Inputs:
  --temperature TEMP.csv   columns t,T (s, degC); the drift is driven by the change of T
                           from the first row. Times must be strictly increasing.
  --voltages VOLTS.csv     optional, columns t,ux,uy,uz (s, V) (a single 'u' column is
                           taken as ux; missing axes are 0 V). Interpolated linearly onto
                           the prediction times; held at its first/last value outside its
                           time range. Without it all voltages are 0 V (no heat).
  --params NAME|FILE       physical_tube (default), table_a1, or a JSON file written by
                           'afmctl drift params'.
Output:
  --out DRIFT.csv          columns t,x,y,z (s, nm), one row per temperature row.

Time steps: if the temperature rows are uniformly spaced (within 1e-6 of the step), the
predictor runs exactly at that step. Otherwise (or with --dt) the temperature is linearly
interpolated onto a uniform grid of step --dt (default: the median step), the predictor
runs on the grid, and the drift is linearly interpolated back to the rows' times.
Gaps up to --max-gap seconds are bridged by that linear interpolation (no jump in the
drift); longer gaps, NaN values and out-of-order or repeated times are rejected.

Example:
  afmctl drift predict --temperature lab_T.csv --voltages volts.csv --out drift.csv --plot drift.png
"""


FIT_DESCRIPTION = """\
Fit the gains of every drift path to a measured drift, keeping the paths' structures,
time constants and delays (the drift is linear in the gains: least squares per axis).

Inputs:
  --temperature TEMP.csv   t,T (s, degC), as for 'predict'
  --drift MEASURED.csv     t and any of x,y,z (s, nm): measured drift, e.g. from a
                           position sensor or from image registration. Taken relative to
                           its value at its first row; rows outside the temperature time
                           range are ignored. An axis without a column keeps its gains.
  --voltages VOLTS.csv     optional t,ux,uy,uz (s, V): without it the heat paths cannot be
                           fitted and keep their gains (as does any path whose input never
                           changed).
  --params NAME|FILE       the starting set (default physical_tube).
Output:
  --out FITTED.json        the fitted set; use it with 'predict --params FITTED.json' or in
                           the controller's configuration. The residual per axis is printed.

Example:
  afmctl drift fit --temperature lab_T.csv --drift sensor.csv --out my_scanner.json
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("drift", help=HELP, description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="drift_cmd", metavar="ACTION")
    pp = sub.add_parser("predict", help="temperature (and voltages) -> drift CSV", description=PREDICT_DESCRIPTION,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    pp.add_argument("--temperature", required=True, metavar="TEMP.csv", help="CSV with columns t,T (s, °C)")
    pp.add_argument("--voltages", metavar="VOLTS.csv", help="CSV with columns t,ux,uy,uz (s, V)")
    pp.add_argument("--params", default="physical_tube", metavar="NAME|FILE",
                    help="drift parameter set: physical_tube (default), table_a1, or a JSON file")
    pp.add_argument("--out", required=True, metavar="DRIFT.csv", help="output CSV t,x,y,z (s, nm)")
    pp.add_argument("--dt", type=float, default=None, metavar="SECONDS",
                    help="prediction step in s (default: the temperature file's median step)")
    pp.add_argument("--max-gap", type=float, default=600.0, metavar="SECONDS",
                    help="longest step between temperature rows that is bridged (default 600 s)")
    pp.add_argument("--plot", metavar="PNG", help="also plot the drift to this PNG file")
    pp.set_defaults(func=run_predict)
    pf = sub.add_parser("fit", help="fit the path gains of a parameter set to a measured drift",
                        description=FIT_DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    pf.add_argument("--temperature", required=True, metavar="TEMP.csv", help="CSV with columns t,T (s, °C)")
    pf.add_argument("--drift", required=True, metavar="MEASURED.csv",
                    help="CSV with column t and any of x,y,z: measured drift (s, nm)")
    pf.add_argument("--voltages", metavar="VOLTS.csv", help="CSV with columns t,ux,uy,uz (s, V)")
    pf.add_argument("--params", default="physical_tube", metavar="NAME|FILE",
                    help="starting parameter set whose structures are kept (default physical_tube)")
    pf.add_argument("--out", required=True, metavar="FITTED.json", help="fitted parameter set (JSON)")
    pf.add_argument("--dt", type=float, default=None, metavar="SECONDS", help="prediction step (as for predict)")
    pf.add_argument("--max-gap", type=float, default=600.0, metavar="SECONDS",
                    help="longest bridged step between temperature rows (default 600 s)")
    pf.set_defaults(func=run_fit)
    pm = sub.add_parser("measure", help="drift between successive AFM frames of the same area (nm)",
                        description=MEASURE_DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    pm.add_argument("images", nargs="+", metavar="IMG", help="frames in time order (.gwy, .gsf, .tif, .ibw, Nanoscope .spm/.000–.999)")
    pm.add_argument("--out", required=True, metavar="DRIFT.csv", help="output CSV t,x,y,dx_px,dy_px")
    pm.add_argument("--frame-period-s", type=float, default=None, metavar="S",
                    help="time between frames in s (default: lines / line rate from the metadata)")
    pm.set_defaults(func=run_measure)
    pq = sub.add_parser("params", help="print or export a drift parameter set as JSON",
                        description="Print a drift parameter set (or write it with --out) to edit every "
                                    "coefficient. Example: afmctl drift params --params table_a1 --out a1.json")
    pq.add_argument("--params", default="physical_tube", metavar="NAME|FILE",
                    help="physical_tube (default), table_a1, or a JSON file to validate")
    pq.add_argument("--out", metavar="FILE.json", help="write here instead of printing")
    pq.set_defaults(func=run_params)
    p.set_defaults(func=lambda args: _no_action(p))


def _no_action(parser: argparse.ArgumentParser) -> int:
    parser.print_help()
    return 0


def load_params(spec: str):
    """A named set or a JSON file (``ModelError`` otherwise)."""
    from afmctl.compensators.drift import DriftParams
    return DriftParams.from_spec(spec, where="--params")


def run_params(args: argparse.Namespace) -> int:
    import json
    params = load_params(args.params)
    text = json.dumps(params.model_dump(mode="json"), indent=2) + "\n"
    if args.out:
        try:
            Path(args.out).write_text(text, encoding="utf-8")
        except OSError as err:
            from ..errors import AfmctlError
            raise AfmctlError(f"{args.out}: cannot write ({err.strerror})") from None
    else:
        print(text, end="")
    return 0


def _read_voltages(path: str):
    import numpy as np

    from ..data.datafiles import read_csv
    from ..errors import AfmctlError
    cols = read_csv(path, ["t"], optional=["ux", "uy", "uz", "u"])
    if not any(c in cols for c in ("ux", "uy", "uz", "u")):
        raise AfmctlError(f"{path}: missing voltage columns; need ux,uy,uz (V) (or u for x only)")
    n = cols["t"].shape[0]
    ux = cols.get("ux", cols.get("u", np.zeros(n)))
    U = np.column_stack([ux, cols.get("uy", np.zeros(n)), cols.get("uz", np.zeros(n))])
    return cols["t"], U


def predict_file(t_s, T_C, params, *, dt_s=None, volts=None, max_gap_s=600.0, where="temperature"):
    """Drift (N, 3) [nm] at the rows' times ``t_s`` (see the ``predict`` help for the
    resampling rules). ``volts`` is ``(t_V, u_V (M, 3))`` or None."""
    import numpy as np

    from afmctl.compensators.base import ModelError
    from afmctl.compensators.temperature import check_temperature_series, resample_uniform

    t = np.asarray(t_s, dtype=np.float64)
    T = np.asarray(T_C, dtype=np.float64)
    check_temperature_series(t, T, where=where, max_gap_s=max_gap_s)
    if dt_s is not None and not (dt_s > 0 and np.isfinite(dt_s)):
        raise ModelError(f"--dt: {float(dt_s)!r} s; must be a positive number of seconds")
    n = t.shape[0]
    if n == 1:
        return np.zeros((1, 3))
    steps = np.diff(t)
    dt = float(np.median(steps)) if dt_s is None else float(dt_s)
    uniform = dt_s is None and np.max(np.abs(steps - dt)) <= 1e-6 * dt
    if uniform:
        grid, T_grid = t, T
    else:
        grid, T_grid = resample_uniform(t, T, dt)
        log.info("temperature resampled onto %d uniform samples of %g s", grid.shape[0], dt)
    if volts is not None:
        tv, U = volts
        U_grid = np.column_stack([np.interp(grid, tv, U[:, j]) for j in range(3)])
        if tv[0] > grid[0] or tv[-1] < grid[-1]:
            log.warning("voltages cover %g..%g s, temperature %g..%g s: voltages held outside their range",
                        tv[0], tv[-1], grid[0], grid[-1])
    else:
        U_grid = np.zeros((grid.shape[0], 3))
    pred = params.predictor(dt)
    d = pred.block(T_grid, U_grid)
    if uniform:
        return d
    return np.column_stack([np.interp(t, grid, d[:, j]) for j in range(3)])


def run_predict(args: argparse.Namespace) -> int:
    import numpy as np

    from ..data.datafiles import read_csv, write_csv

    params = load_params(args.params)
    if not (args.max_gap > 0):
        from ..errors import AfmctlError
        raise AfmctlError(f"--max-gap: {args.max_gap!r} s; must be > 0")
    cols = read_csv(args.temperature, ["t", "T"])
    volts = _read_voltages(args.voltages) if args.voltages else None
    d = predict_file(cols["t"], cols["T"], params, dt_s=args.dt, volts=volts, max_gap_s=args.max_gap,
                     where=str(args.temperature))
    write_csv(args.out, {"t": cols["t"], "x": d[:, 0], "y": d[:, 1], "z": d[:, 2]})
    log.info("wrote %d rows to %s (params %s)", d.shape[0], args.out, params.name)
    peak = np.max(np.abs(d), axis=0)
    print(f"drift predict: {d.shape[0]} rows over {float(cols['t'][-1] - cols['t'][0]):.4g} s, params {params.name}; "
          f"peak |x| {peak[0]:.4g} nm, |y| {peak[1]:.4g} nm, |z| {peak[2]:.4g} nm -> {args.out}")
    if args.plot:
        _plot(args.plot, cols["t"], cols["T"], d, params.name)
    return 0


def run_measure(args: argparse.Namespace) -> int:
    import numpy as np

    from ..data.datafiles import write_csv
    from ..inputs.drift_images import FrameDriftMeter
    from ..errors import AfmctlError
    from afmctl.compensators.scan_files import read_scan_image

    if len(args.images) < 2:
        raise AfmctlError("IMG: at least two frames are needed to measure a drift")
    imgs = [read_scan_image(p) for p in args.images]
    shapes = {im.trace_nm.shape for im in imgs}
    if len(shapes) != 1:
        raise AfmctlError(f"{args.images[0]}: all frames must have the same lines × pixels; got {sorted(shapes)}")
    period = args.frame_period_s
    if period is None:
        if imgs[0].line_rate_Hz is None or not imgs[0].line_rate_Hz > 0:
            raise AfmctlError(f"{args.images[0]}: no line rate in the metadata; give --frame-period-s")
        period = imgs[0].trace_nm.shape[0] / imgs[0].line_rate_Hz
    if not (np.isfinite(period) and 0 < period <= 1e6):
        raise AfmctlError(f"--frame-period-s: {period!r} s is outside the allowed range (0, 1e6] s")
    meter = FrameDriftMeter(imgs[0].pixel_nm(), level_lines=True)
    for k, im in enumerate(imgs):
        meter.add(im.trace_nm, k * period)
    f = meter.frames
    write_csv(args.out, {"t": np.array([d.t_s for d in f]), "x": np.array([d.drift_nm[0] for d in f]),
                         "y": np.array([d.drift_nm[1] for d in f]), "dx_px": np.array([d.step_px[1] for d in f]),
                         "dy_px": np.array([d.step_px[0] for d in f])})
    print(f"drift measure: {len(f)} frames, {f[-1].t_s:.4g} s; drift since the first frame x {f[-1].drift_nm[0]:.4g} nm, "
          f"y {f[-1].drift_nm[1]:.4g} nm (pixel {imgs[0].pixel_nm()[1]:.4g} × {imgs[0].pixel_nm()[0]:.4g} nm) -> {args.out}")
    return 0


def run_fit(args: argparse.Namespace) -> int:
    import numpy as np

    from ..data.datafiles import read_csv
    from ..errors import AfmctlError
    from afmctl.compensators.drift import AXES, fit_gains, path_responses

    params = load_params(args.params)
    cols = read_csv(args.temperature, ["t", "T"], min_rows=2)
    meas = read_csv(args.drift, ["t"], optional=list(AXES))
    present = [a for a in AXES if a in meas]
    if not present:
        raise AfmctlError(f"{args.drift}: missing drift columns; need at least one of x,y,z (nm)")
    volts = _read_voltages(args.voltages) if args.voltages else None
    t_T = cols["t"]
    inside = (meas["t"] >= t_T[0]) & (meas["t"] <= t_T[-1])
    if np.count_nonzero(inside) < 2:
        raise AfmctlError(f"{args.drift}: column t: fewer than 2 rows within the temperature file's time range "
                          f"{t_T[0]:g}..{t_T[-1]:g} s")
    tm = meas["t"][inside]
    measured = np.full((tm.size, 3), np.nan)
    for a in present:
        col = meas[a][inside]
        measured[:, AXES.index(a)] = col - col[0]

    def predict(one):
        d = predict_file(t_T, cols["T"], one, dt_s=args.dt, volts=volts, max_gap_s=args.max_gap,
                         where=str(args.temperature))
        at = np.column_stack([np.interp(tm, t_T, d[:, j]) for j in range(3)])
        return at - at[0]

    responses = path_responses(params, predict)
    fitted, rms = fit_gains(params, responses, measured)
    try:
        fitted.save(args.out)
    except OSError as err:
        raise AfmctlError(f"{args.out}: cannot write ({err.strerror})") from None
    for name in responses:
        old, new = getattr(params.paths, name), getattr(fitted.paths, name)
        g_old = getattr(old, "K", None)
        g_new = getattr(new, "K", None)
        if g_old is not None:
            print(f"G_{name}: K {g_old:.6g} -> {g_new:.6g}")
        else:
            print(f"G_{name}: state-space output scaled by {new.C[0] / old.C[0] if old.C[0] else float('nan'):.6g}")
    for a, r in zip(AXES, rms):
        if np.isfinite(r):
            print(f"residual {a}: {r:.4g} nm rms")
    return 0


def _plot(path: str, t, T, d, name: str) -> None:
    from ..figures import pyplot, save_figure
    plt = pyplot()
    fig, (a1, a2) = plt.subplots(2, 1, sharex=True, figsize=(7, 5))
    a1.plot(t, T, color="tab:red")
    a1.set_ylabel("T [°C]")
    for j, ax in enumerate("xyz"):
        a2.plot(t, d[:, j], label=ax)
    a2.set_xlabel("t [s]")
    a2.set_ylabel("drift [nm]")
    a2.legend()
    a1.set_title(f"predicted drift ({name})")
    fig.tight_layout()
    save_figure(fig, path)
