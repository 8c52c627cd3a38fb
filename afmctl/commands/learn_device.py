"""``afmctl learn --config RUN.toml --iterations N --out LEARNED.afmwave``: learning on a
device with a data recorder (:mod:`afmctl.control.learn_run`), its progress line per
iteration, the zenoh ``learn`` key, and the convergence plot."""
from __future__ import annotations

import argparse
import contextlib
import math
import sys
from typing import Any

from .learn_defaults import CENTRAL_PCT

DEVICE_HELP = """\
On a device that records its own motion (a PI GCS controller's data recorder, the NV200's,
the CAN amplifier's; simulated ones with [simulation] enabled = true):

  afmctl learn --config RUN.toml --iterations 10 --out LEARNED.afmwave --plot conv.png

plays the configured trajectory as a wave table (amplifier.output = "wave"), reads the
scanner's measured motion back through the recorder, computes the next table, and repeats:
a progress line per iteration (per learned axis the error max / RMS in nm and in % of
that axis's line, or of its step for a raster's slow axis, over the central 80 % of every
raster line but the first, as afmctl run reports it; the step size). Each axis learns on
its own until its error is at --noise-floor-pct, stops improving, or a guard stops it
(error rising twice; a model whose phase is over 90 deg off); it then plays its best
column, and learning ends when every axis has, or N tables have played. The scanner creeps: each play carries the creep of the plays before it. An
in-process simulator ([simulation] enabled) is brought to rest before every play, as
afmctl run starts on a fresh one. On a device, with a model whose chain has a creep stage,
each recording is first freed of what that creep history adds (the "history term", in nm
on the progress line), so the learned table is right for a play from rest, and afmctl run
takes out what the learning's plays still add when it plays; after the first iteration the
first table plays once more, and what the scanner moved between its two plays beyond the
model's term is measured and added to the term. An axis without a creep stage learns from
its recordings as they are, each play starting 4 s after the one before ended; afmctl run
of the learned table holds the present output until 4 s after the learning's last play,
so its play meets the creep of the plays before it as they did. Played much later (over
10 s, said in one line) it lands off by the creep the plays left. The creep of each approach ramp still runs during the
table while the output holds the first row: with amplifier.settle_s unset every play
holds 2 s first (a shorter hold makes plays repeat less well; afmctl learn says so), and
the learned table records its hold, which afmctl run then keeps.
Every table is checked (limits, slew, device capacity) before it is sent;
Ctrl-C stops (the best table so far is written), a second Ctrl-C is an emergency stop.
The table made of each axis's best measured column is written to --out and played once
more as afmctl run plays it: the last line gives that play's figures (a run's), then each
axis's best play while learning (the smallest of several noisy figures). Play it with

  [trajectory]
  kind = "learned"
  file = "LEARNED.afmwave"

in a run configuration (afmctl run), which refuses it with one line if the trajectory, the
amplifier, its limits or the model files have changed since.
"""

#: most iterations one call plays
MAX_ITERATIONS = 1000


def add_device_arguments(p: argparse.ArgumentParser) -> None:
    """The device loop's options, on the ``learn`` parser itself."""
    g = p.add_argument_group("learning on a device (afmctl learn --config ...)")
    g.add_argument("--config", metavar="RUN.toml", help="run configuration: amplifier (output = 'wave'), "
                   "trajectory to learn, compensation model")
    g.add_argument("--iterations", type=int, default=10, metavar="N",
                   help=f"most tables to play after the first, 1..{MAX_ITERATIONS} (default 10)")
    g.add_argument("--out", dest="learned_out", metavar="LEARNED.afmwave", help="learned table to write")
    g.add_argument("--plot", dest="learned_plot", metavar="CONV.png", help="convergence plot (PNG)")
    g.add_argument("--noise-floor-pct", type=float, default=0.0, metavar="P",
                   help="stop when every learned axis's error over the central part of the lines is at most P %% "
                        "of its line or step (default 0: stop when it no longer improves)")
    g.add_argument("--model-free", action="store_true",
                   help="learn without the configured model (frequency response from the iterations)")
    g.add_argument("--no-history-term", action="store_true",
                   help="learn from the recordings as they are (default: with a model that has a creep stage, "
                        "take out the creep the earlier plays left, so the table is right for afmctl run's "
                        "play from rest)")
    g.add_argument("--rho", type=float, default=None, metavar="RHO",
                   help="largest step size, 0 < RHO <= 2 (default: the law's, 1 (a full inverse step) with a "
                        "model, 0.7 with --model-free or no model)")
    g.add_argument("--central-pct", dest="device_central_pct", type=float, default=CENTRAL_PCT, metavar="P",
                   help="weighted central share of each raster line [%%] (default 80: the part the error is judged on)")


def _check_args(args: argparse.Namespace) -> None:
    from ..errors import AfmctlError
    if not args.learned_out:
        raise AfmctlError("--out LEARNED.afmwave is required with --config")
    if not 1 <= args.iterations <= MAX_ITERATIONS:
        raise AfmctlError(f"--iterations {args.iterations}: allowed 1..{MAX_ITERATIONS}")
    if not (math.isfinite(args.noise_floor_pct) and 0.0 <= args.noise_floor_pct <= 100.0):
        raise AfmctlError(f"--noise-floor-pct {args.noise_floor_pct:g}: allowed 0..100 %")
    if args.rho is not None and not (math.isfinite(args.rho) and 0.0 < args.rho <= 2.0):
        raise AfmctlError(f"--rho {args.rho:g}: allowed 0 < RHO <= 2")
    if not (math.isfinite(args.device_central_pct) and 0.0 < args.device_central_pct <= 100.0):
        raise AfmctlError(f"--central-pct {args.device_central_pct:g}: allowed 0 < P <= 100 %")


def progress_line(report: Any) -> str:
    """One line per iteration: each learned axis's error over the judged part (nm and % of
    its line or step, :func:`afmctl.data.axis_errors.axis_errors`), the next step's size,
    the state."""
    if report.judged is None:
        return f"afmctl: learn {report.iteration:3d}: {report.state}: {report.detail}"
    step = f"; step {report.rho:.2f}" if report.rho is not None and report.state == "learning" else ""
    tail = (f"; {report.state}: {report.detail}" if report.state != "learning"
            else f"; {report.detail}" if report.detail else "")
    history = f"; history term {report.history_nm:.1f} nm" if report.history_nm else ""
    if report.history_nm and report.history_offset_nm:
        history += f" ({report.history_offset_nm:+.1f} nm of it measured by replaying the first table)"
    return f"afmctl: learn {report.iteration:3d}: {report.judged.text()}{step}{history}{tail}"


def part_line(report: Any) -> str | None:
    """Once, before the first progress line: what the figures cover and how they are taken."""
    if report.judged is None:
        return None
    return (f"afmctl: learn: errors per axis over {report.judged.part}, measured by the device's recorder"
            + (" less the history term" if report.history_nm else "")
            + "; % of each axis's line (the fast axis) or step (a slow axis's move per line)")


def final_line(out: str, run: Any) -> str:
    """The last line: where the table went, the figures of its last play (step ``replay``:
    what ``afmctl run`` reproduces) and each axis's best play while learning."""
    best = f"each axis's best play while learning: {run.book.best_text()}"
    if run.replayed is not None:
        what = f"played once more as afmctl run plays it: {run.replayed.text(', ')}; {best}"
    else:
        what = best
    return (f"afmctl: learned table {out}, {what}; play it with [trajectory] kind = \"learned\" (afmctl run reports "
            "the figures of the play once more)")


def plot_convergence(reports: list[Any], path: str) -> None:
    """Error per iteration (log scale), whole table and central part of each line."""
    from ..figures import pyplot, save_figure
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    its = [r.iteration for r in reports if r.summary()["max_pct"] is not None]
    for key, label in (("max_pct", "max, whole table"), ("central_max_pct", "max, central 80 % of each line"),
                       ("central_rms_pct", "RMS, central 80 %")):
        vals = [r.summary()[key] for r in reports if r.summary()["max_pct"] is not None]
        if all(v is not None for v in vals) and vals:
            ax.semilogy(its, vals, "o-", label=label)
    ax.set_xlabel("iteration (0: the model's table)")
    ax.set_ylabel("worst axis: error [% of its span; central: of its line or step]")
    ax.set_title("afmctl learn: convergence")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path, "--plot")


def run_device(args: argparse.Namespace) -> int:
    """The device loop (``DEVICE_HELP``); exit 0 when a table was learned, 1 on a fault."""
    from afmctl.compensators.learning import LearnSettings

    from ..config import load_config
    from ..control.learn_run import LearnOptions, LearnRun, settle_advice
    from ..control.learned_table import save_learned
    from ..simulation.link import configured_amplifier, resting, simulated_amplifier
    from .run import _install_signals
    _check_args(args)
    config = as_wave(load_config(args.config))
    advice = settle_advice(config)
    if advice:
        print(f"afmctl: learn: {advice}", file=sys.stderr)
    settings = LearnSettings(rho_max=args.rho, central_pct=args.device_central_pct)
    with contextlib.ExitStack() as stack:
        rest = None
        if config.simulation.enabled:      # afmctl run starts on a fresh simulator: so does every play
            amp, scanner = stack.enter_context(simulated_amplifier(config))
            rest = resting(config, scanner)
        else:
            amp = configured_amplifier(stack, config)
        options = LearnOptions(iterations=args.iterations, noise_floor_pct=args.noise_floor_pct, settings=settings,
                               use_model=not args.model_free, history_term=not args.no_history_term, rest=rest)
        if rest is not None:
            print("afmctl: learn: the in-process simulated scanner is brought to rest before every play, as afmctl "
                  "run starts on a fresh one: no play carries the creep of the ones before", file=sys.stderr)
        publish = _publisher(stack, config)
        seen = {"part": False, "spaced": False, "calibration": False}

        def on_iteration(report: Any) -> None:
            part = part_line(report)
            if part is not None and not seen["part"]:
                seen["part"] = True
                print(part, file=sys.stderr, flush=True)
            spaced = None if seen["spaced"] else spacing_line(run.player.spaced_axes)
            if spaced:
                seen["spaced"] = True
                print(spaced, file=sys.stderr, flush=True)
            if run.after_calibration and not seen["calibration"]:
                seen["calibration"] = True
                print(calibration_line(run.after_calibration), file=sys.stderr, flush=True)
            print(progress_line(report), file=sys.stderr, flush=True)
            if publish is not None:
                publish(report)

        run = LearnRun(config, amp, options, on_iteration=on_iteration)
        # Ctrl-C / SIGTERM: a stop (the best table so far is kept), again: an emergency stop
        _install_signals(stack, run, {"n": 0})
        learned = run.run()
    save_learned(args.learned_out, learned)
    if args.learned_plot:
        plot_convergence(run.reports, args.learned_plot)
    print(final_line(args.learned_out, run), file=sys.stderr)
    return 1 if run.reports[-1].state == "fault" else 0


def calibration_line(ago_s: dict[str, float]) -> str:
    """The line saying which axes' history term starts from the calibration before
    (:meth:`afmctl.control.learn_history.PlayTimeline.resume`)."""
    when = ", ".join(f"{a} {s:.0f} s" for a, s in ago_s.items())
    return (f"afmctl: learn: the calibration that wrote the model ended on this device {when} ago and the scanner "
            f"still creeps from it: the history term starts from what the model says it left")


def spacing_line(axes: tuple[str, ...]) -> str | None:
    """The line saying that the plays of axes learned as recorded are spaced
    (:data:`afmctl.control.learned_after.AS_RECORDED_REST_S`); None without such axes."""
    from ..control.learned_after import AS_RECORDED_REST_S
    if not axes:
        return None
    return (f"afmctl: learn: {', '.join(axes)} learn without a creep stage, from the recordings as they are: every "
            f"play starts {AS_RECORDED_REST_S:g} s after the one before ended, and afmctl run of the learned table "
            f"waits as long after the last, so that each meets the creep of the plays before it alike")


#: drivers whose device plays a table on its own clock and records the motion
WAVE_DRIVERS = ("can", "gcs", "nv200")


def as_wave(config: Any) -> Any:
    """A configuration with host-timed output (``setpoints``, ``stream``) on a device that plays
    tables on its own clock, as ``output = "wave"``: afmctl learn plays every table there and
    measures it with the device's recorder (one line says so); other configurations as they are."""
    if config.amplifier.output == "wave" or config.amplifier.driver not in WAVE_DRIVERS:
        return config
    print(f"afmctl: learn: amplifier.output = '{config.amplifier.output}': learning plays each table on the "
          f"{config.amplifier.driver} amplifier's clock (output = 'wave') and measures it with its recorder; play "
          "the learned table with output = 'wave' (AFMCTL_AMPLIFIER__OUTPUT=wave)", file=sys.stderr)
    return config.model_copy(update={"amplifier": config.amplifier.model_copy(update={"output": "wave"})})


def _publisher(stack: contextlib.ExitStack, config: Any) -> Any:
    """A function publishing each report on ``<prefix>/<scanner>/learn``, or None without zenoh."""
    if not config.zenoh.enabled:
        return None
    from ..zenoh_api.learn import LearnPublisher
    pub = stack.enter_context(LearnPublisher(config.zenoh, config.scanner.name))

    def publish(report: Any) -> None:
        pub.publish(report.iteration, report.summary(), step=report.rho, state=report.state, detail=report.detail)
    return publish
