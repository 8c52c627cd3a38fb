"""``afmctl identify``: fit a hysteresis/creep model to measured data (generic over the
model kinds registered in :data:`afmctl.compensators.models.KINDS`)."""
from __future__ import annotations

import argparse
import logging

from .identify_io import _fitted, _plot, _refuse_failed, _save, parse_params  # noqa: F401 - parse_params: public

log = logging.getLogger(__name__)

HELP = "fit a hysteresis/creep model (pi, epi, creep, preisach, bouc-wen, rate-pi, rate-bouc-wen) to measured data"

DESCRIPTION = """\
Fit a model of the scanner to measured data and write it as a JSON model file.

Input:
  --data DATA.csv   header row and columns t,u,y: time (s, strictly increasing), the
                    voltage sent to the amplifier (V) and the measured displacement (nm);
                    optional column v: the voltage at the piezo (V; an amplifier's monitor
                    output or a controller's recorder channel): a chain or auto then
                    identifies the amplifier stage before the hysteresis from it;
                    optional column measured: 1 where y was measured, 0 where it was not
                    (afmctl calibrate's holds between recorded pieces, y interpolated):
                    those rows are left out of the fit and the scores, the model's memory
                    and creep run through them (kinds pi, preisach, creep and every chain;
                    the others say so in a note). Other columns are ignored.
                    Excite the scanner over the range you will use: a decaying triangle
                    (nested loops) for hysteresis models, and holds/staircases of a few
                    seconds for the creep-aware kinds (epi, creep; non-uniform samples are
                    resampled for them).
  --from-images F…  instead of --data: a .npz scan file (docs/SIM.md) or grating images,
                    one .gwy/.gsf/.tif/.ibw or Bruker Nanoscope .spm/.000… per scan range, each
                    with trace and retrace, e.g. --from-images r150.gwy r140.gwy …
                    --param gain_nm_per_V=80 --param period_nm=278 (docs/REALDATA.md)
  --from-images SLOW.npz FAST.npz with --model dynamics, preisach+dynamics,
                    preisach+creep or preisach+creep+dynamics: without a sensor, the
                    linear dynamics from grating scans at several line rates (phase lag
                    and ringing in trace vs retrace) and the creep from the slow scans
                    (docs/SIM.md). Each .npz records line_rate_Hz (lines/s, one per scan
                    range or one for all, > 0 … 10000); ranges at <= 2 lines/s (--param
                    static_max_Hz=…) give the Preisach (+creep) stages, the faster ones
                    (e.g. 10 … 100) the dynamics. --param gain_nm_per_V=… (dynamics
                    without slow scans: a linear static part), n_modes (auto), n_lags
                    (1), f_max_Hz (3000), static_error_nm (1: harmonics weaker than
                    this are not used)
Model kinds (--model):
  pi        Prandtl-Ishlinskii: play operators, constrained least squares (always invertible)
  epi       extended PI: PI + inflexion creep C(u,t) = (1-exp(-lambda t)) a b^u, needs dwells
  creep     linear creep (bank of first-order lags), no hysteresis
  preisach  classical Preisach on an (alpha, beta) grid: asymmetric loops, exact inverse
  bouc-wen  Bouc-Wen differential model, nonlinear least squares
  rate-pi   rate-dependent PI: thresholds grow with the input's smoothed rate (loops
            that widen with the scan rate); needs sweeps at several rates
  rate-bouc-wen
            Bouc-Wen whose amplitude A grows with the input's smoothed rate: loops that
            widen with the scan rate and stay put while the input rests; needs sweeps
            at several rates
  dynamics  linear dynamics (amplifier bandwidth, structural modes, delay), unit DC gain,
            from the record's fast parts (afmctl's multisine, a chirp within the
            amplifier's slew limit, triangles at 10 Hz and up; the parts used are
            printed): frequency response (Welch) fitted by modes + lags + delay
  amplifier the amplifier stage alone: bandwidth and slew (current) limit, from column v
  [amplifier+]KIND[+creep][+dynamics]
            a chain (kind chain): the amplifier stage before the piezo (its bandwidth and
            slew limit; from column v, or without it the lag below the first mode that the
            dynamics find: amplifier+KIND[+creep]+dynamics), hysteresis KIND (pi, epi,
            preisach, bouc-wen, rate-pi, rate-bouc-wen) on the piezo voltage, then
            linear creep, then linear dynamics, identified jointly (Hammerstein):
            hysteresis and creep on every sample (preisach; other kinds on block means
            at <= 2 kHz) less the 50 ms after each jump of the command (preisach: and
            less the fast parts when the slow rest covers the range), the dynamics
            from the record's fast parts, then the static stages again on the record
            through the dynamics' inverse while that helps; uniform samples needed
  auto      fit every candidate chain on the first 70 % of the data after the burn-in,
            score each by its prediction error on the last 30 % (held out; the models
            run over the whole record, so the burn-in sets their memory), print the
            table and keep the best (re-fitted on all the data); the table is
            stored in the model file. The leading candidates are also fitted on
            shorter prefixes and scored on the input cycles after each (folds spread
            through the record); a richer model (preisach > pi/bouc-wen, +creep,
            +dynamics) must lower the mean held-out RMS over the folds by >= 5 % and
            win most folds, else the simplest adequate one is kept; the table shows
            the folds' spread and why the winner won. A fit that failed (training
            error above a straight line's, optimiser not converged, a parameter on
            its bound) is listed as failed and never selected. A record without a hold
            after a step (>= 0.1 s) does not try epi, nor +creep unless it sweeps at
            several rates ('not tried' rows: creep would fit the hysteresis misfit);
            rate-pi is tried only when named in candidates, and
            neither it nor rate-bouc-wen+creep on a record at a single rate; when
            only the held-out part sweeps fast over the range (excite puts its fast
            triangles last), the rate candidates take their growth from a fit of
            the whole record, as the +dynamics stage takes its modes. Excite the full voltage range in the
            first 70 % ('afmctl excite --kind all' does). The best is then tried
            +dynamics when the record has fast parts (record at a rate that resolves
            the scanner's resonance, e.g. 50 kHz; the delay is then fitted by the
            dynamics stage, not shifted ahead of the hysteresis fit). With column v
            every candidate gets the amplifier stage fitted to it; without it, the
            winner's dynamics' lag below the first mode becomes an amplifier stage
            before the hysteresis, the winner and the next +dynamics candidate are
            scored behind it (amplifier+…), and the best is kept if it predicts the
            held-out part better.
            --param 'candidates=["pi","preisach+creep"]', holdout_fraction=0.3,
            criterion=rms|max, with_dynamics=false, jobs=2 (fit the candidates in two
            worker processes: the same model, about half the time on two cores)
Real recordings (--data):
  --burn-in auto    samples until the input has passed both its extremes only set the model's
                    memory (the state the recording started in is unknown); 'none' or SECONDS
  --force           write the model even when its fit failed (otherwise refused, exit 2)
  --delay auto      the sensor's delay (whole samples, estimated; stored as delay_s); or SECONDS
  spikes            isolated outliers of y are replaced by their running median (--keep-spikes)
  units             u within ±1000 V, y within ±1 mm; y in µm is refused unless --y-unit um
  excitation        the output says what the input cannot identify and what to record
                    instead (afmctl excite --kind static|creep|dynamics)
Options:
  --operators N     pi/epi/rate-pi: play operators (default 13, max 1000); creep: lags (default 4);
                    preisach: grid levels (default 32; nnls up to 64, for up to 512;
                      in a preisach+creep chain 64, fitted jointly with the creep lags);
                    bouc-wen, rate-bouc-wen: ignored
  --param KEY=VALUE model-specific options, VALUE parsed as JSON when possible:
                    pi, epi, rate-pi: thresholds=[0,10,...] (V), min_slope_fraction (1e-3), max_rows
                    rate-pi: rate_tau_s, rate_gain_s_per_V (fix them; default searched)
                    rate-bouc-wen: as bouc-wen, and rate_tau_s; rate_gain_s_per_V with
                      rate_max_V_per_s (fix the growth; default fitted)
                    epi: min_dwell_samples (10), dwell_tol_V (0)
                    creep: tau_min_s, tau_max_s (time-constant range, s)
                    preisach: u_min_V, u_max_V (grid range, default the data range),
                      method=auto|for|nnls, smoothing (1e-2), max_rows, memory_depth,
                      prior=pi|none (nnls: what the data do not determine — e.g. the inside
                      of the plane after full-range cycles — takes a PI-like density fitted
                      on the same data), prior_weight (1e-4)
                    bouc-wen: n (fix the exponent), max_rows (20000), u0_V, jacobian
                      (sensitivities; 2-point: finite differences, slower)
                    dynamics: n_modes (auto: 1-3 as the response shows), n_lags (1), segment=auto|all, nperseg,
                      f_min_Hz, f_max_Hz, min_coherence (0.9)
                    e.g. --param min_slope_fraction=1e-3 --param 'thresholds=[0,10,20,30]'
Output:
  --out MODEL.json  the fitted model (a 'kind' field plus its parameters); a summary and
                    the fit residual are printed. --plot FIT.png draws data and fit.

Examples:
  afmctl identify --model pi --data sweep.csv --out pi.json --operators 13
  afmctl identify --model preisach --data sweep.csv --out pre.json --param u_min_V=0 --param u_max_V=150
  afmctl identify --model auto --data recording.csv --out best.json   # prints the held-out table
  afmctl compensate --model pi.json --target path.csv --out volts.csv
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("identify", help=HELP, description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", required=True, metavar="KIND",
                   help="model kind: pi, epi, creep, preisach, bouc-wen, rate-pi, rate-bouc-wen, dynamics, amplifier, a chain "
                   "[amplifier+]KIND[+creep][+dynamics], "
                        "or auto")
    p.add_argument("--data", metavar="DATA.csv", help="CSV with columns t,u,y (s, V, nm)")
    p.add_argument("--from-images", metavar="SCANS", nargs="+",
                   help="instead of --data: identify without a position sensor from AFM images of a "
                        "calibration grating: one .npz of line images + voltage ramps (docs/SIM.md), or "
                        "image files, one scan range each (.gwy, .gsf, .tif, Asylum .ibw, Bruker Nanoscope .spm/.000–.999; "
                        "each with trace and retrace; "
                        "needs --param gain_nm_per_V=… --param period_nm=…, optional scan_u_min_V, skip_lines)")
    p.add_argument("--out", required=True, metavar="MODEL.json", help="where to write the fitted model")
    p.add_argument("--operators", type=int, default=None, metavar="N",
                   help="number of operators (PI plays, creep lags, ...); default depends on the kind")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="model-specific option (repeatable); VALUE is parsed as JSON when possible")
    p.add_argument("--plot", metavar="FIT.png", help="also draw the data and the model's output")
    p.add_argument("--y-unit", default="nm", metavar="nm|um", help="unit of the data's y column (default nm)")
    p.add_argument("--burn-in", default="auto", metavar="auto|none|SECONDS",
                   help="samples that only set the model's memory (default auto: until the input has "
                        "passed both its extremes, when the record does not start at its lowest voltage)")
    p.add_argument("--delay", default="auto", metavar="auto|SECONDS",
                   help="input-output delay of the sensor (default auto: estimated, whole samples)")
    p.add_argument("--keep-spikes", action="store_true",
                   help="do not replace isolated outliers of y (Hampel filter) before fitting")
    p.add_argument("--force", action="store_true",
                   help="write the model even when its fit failed (training error above the straight line's, "
                        "optimiser not converged, a parameter on its bound); without it such a fit is refused "
                        "with the reason, exit status 2")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import AfmctlError
    from afmctl.compensators.models import model_class

    from .identify_images import run_from_rate_images, wants_rates
    if wants_rates(args):
        return run_from_rate_images(args)
    if args.model == "auto" or "+" in args.model:
        from .identify_chain import run_chain
        return run_chain(args)
    model_class(args.model)
    if getattr(args, "from_images", None) is not None:
        if args.data is not None:
            raise AfmctlError("--data: give either --data DATA.csv or --from-images SCANS, not both")
        return _run_from_images(args)
    fitted = _fitted(args)
    _refuse_failed(args, fitted)
    _save(fitted.model, args.out)
    _report(args, fitted)
    return 0


def _run_from_images(args: argparse.Namespace) -> int:
    """``--from-images``: identification without a position sensor (docs/SIM.md)."""
    from afmctl.compensators.scan_files import identify_from_scan_files

    model = identify_from_scan_files(args.from_images, args.model, n_operators=args.operators,
                                     **parse_params(args.param))
    _save(model, args.out)
    print(model.summary())
    print(f"written          : {args.out}")
    return 0


def _report(args: argparse.Namespace, fitted) -> None:
    """Summary, residual after the burn-in, data notes and the excitation check."""
    model, k = fitted.model, fitted.fit_from
    print(model.summary())
    if model.delay_s:
        print(f"delay            : {model.delay_s:.6g} s (delay_s; used by model predict/validate — "
              "compensate and run do not yet send the voltages that much earlier)")
    print(f"fit residual     : {fitted.residual()}")
    for note in fitted.notes:
        print(f"data             : {note}")
    for note in fitted.excitation:
        print(f"excitation       : {note}")
    print(f"written          : {args.out}")
    if args.plot:
        _plot(args.plot, fitted.t_s[k:], fitted.u_V[k:], fitted.y_nm[k:], fitted.y_fit_nm[k:], args.model)
        print(f"plot             : {args.plot}")
