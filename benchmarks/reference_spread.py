"""How much the reference of ``benchmarks/calibrate_join.py`` varies with the sensor's noise
(issue 38): the *same* continuous recording made again with other noise seeds of the simulated
scanner, each identified by ``afmctl identify`` and run through ``afmctl run`` as the
benchmark runs its models (4 µm raster lines, x error over the central 80 %, % of the line).

``calibrate_join.py`` compares calibrate's model with one continuous recording made with the
scanner's default seed; a calibration meets another noise realisation (its pieces start when
the host gets there). This shows the spread of the reference itself.

    .venv/bin/python benchmarks/reference_spread.py WORK [--seeds 1 2 3] [--rates 10]
        [--kind auto]

``WORK``: a ``calibrate_join.py --work`` folder (its ``cal.json`` gives the excitation and
the range). Prints one line per seed.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

import calibrate_join as cj  # noqa: E402  (benchmarks/calibrate_join.py)


def seeded_reference(work: Path, seed: int, kind: str, rates: list[float]) -> dict[float, dict[str, float]]:
    """The continuous recording with the scanner's noise seed ``seed``, identified and run."""
    prov = json.loads((work / "cal.json").read_text())["provenance"]
    base = cj.scanner_config
    folder = work / f"seed{seed}"
    folder.mkdir(exist_ok=True)
    cj.scanner_config = lambda: base().model_copy(update={"seed": seed})      # the recording's scanner only
    try:
        csv = cj.continuous_recording(folder, prov["excitation"], tuple(prov["axes"]["x"]["u_range_V"]))
    finally:
        cj.scanner_config = base
    model = folder / f"continuous-seed{seed}.json"
    cj.identify(csv, kind, model)
    return cj.raster_errors(folder, model, rates)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--rates", type=float, nargs="+", default=[10.0])
    ap.add_argument("--kind", default="auto")
    args = ap.parse_args()
    print(f"default seed {cj.scanner_config().seed}: see {args.work}/continuous.json")
    for seed in args.seeds:
        errs = seeded_reference(args.work, seed, args.kind, args.rates)
        print(f"seed {seed}: " + ", ".join(f"{r:g} lines/s max {e['max_pct']:.3f} / RMS {e['rms_pct']:.3f} %"
                                           for r, e in errs.items()), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
