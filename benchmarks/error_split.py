"""Where the speed ladder's error comes from: the same models, played through plants that
leave out one cause at a time.

Identifies the models exactly as ``benchmarks/speed_ladder.py`` does (CLI: ``excite --kind
all`` → default simulated scanner → identify), then, per line rate, the max / RMS error [% of the
4 µm line, central 80 % of every trace and retrace] of the chain's offline inverse
(``ChainModel.inverse_within_limits``, what ``afmctl compensate`` runs) on:

* ``static plant``      — the default scanner without its structural mode and with an ideal
  amplifier, compensated by the static chain (preisach+creep): the hysteresis/creep model floor;
* ``full``              — the default scanner, the full chain within 0–150 V and 10 kV/s
  (the speed ladder's ``preisach+creep+dynamics`` row);
* ``exact static``      — the default scanner whose hysteresis and creep are replaced by the
  identified static chain itself (``ExternalModelConfig``): what the dynamics inverse and the
  slew limit alone leave;
* ``exact static, band limit`` — the same, with the slew limit met by lowering the band
  limit of the whole dynamics inverse (the behaviour before turnaround rounding).

    .venv/bin/python benchmarks/error_split.py [--rates 16 50]

Prints the table and writes it between the ``<!-- bench:error_split -->`` markers of
docs/BENCHMARKS.md (``--no-write``: print only). About 1 minute.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

import speed_ladder as sl  # noqa: E402
from afmctl.compensators.dynamics_limits import invert_within_limits  # noqa: E402
from afmctl.compensators.models import load_model  # noqa: E402
from afmctl.sim_backend.config import ExternalModelConfig  # noqa: E402
from afmctl.sim_backend.scanner import Scanner, default_scanner_config  # noqa: E402
from sections import write_section  # noqa: E402  (benchmarks/sections.py)

NOTE = ("Reading: `static plant` is the hysteresis+creep model's own floor; `exact static` is what the "
        "dynamics inverse and the slew limit leave when the static model is exact; the gap between `static "
        "plant` and `full` is the static model's remaining error at the turnarounds ringing through the "
        "1 kHz mode (Q 20). The last two columns compare rounding only the turnarounds (the default) with "
        "lowering the whole band limit when the slew limit is met.")


def play(u_V: np.ndarray, static_plant: bool = False, exact_static: dict | None = None) -> np.ndarray:
    """True x [nm] of a fresh default scanner, optionally without mode and amplifier
    limits, or with its hysteresis+creep replaced by the model ``exact_static``."""
    cfg = default_scanner_config()
    if static_plant:
        cfg.x.dynamics = None
        cfg.x.amplifier.slew_V_per_s, cfg.x.amplifier.bandwidth_Hz, cfg.x.amplifier.bits = None, None, 0
    if exact_static is not None:
        cfg.x.hysteresis, cfg.x.creep = ExternalModelConfig(model=exact_static), None
    U = np.zeros((u_V.size, 3))
    U[:, 0] = u_V
    return Scanner(cfg).run(U, sl.DT_S)[:, 0]


def split(rate_Hz: float, static, full) -> dict[str, str]:
    lines = sl.LINES.get(int(rate_Hz), 4)
    tgt, start, n = sl.raster(rate_Hz, lines)

    def err(y: np.ndarray) -> str:
        e = sl.line_error_pct(y, tgt, start, n, lines)
        return f"{e['max_error_pct']:.2f} / {e['rms_error_pct']:.2f}"

    lo, hi = sl.LIMITS_V
    exact = json.loads(static.model_dump_json())
    row = {"static plant": err(play(static.inverse_within_limits(tgt, sl.DT_S, lo, hi).u_V, static_plant=True)),
           "full": err(play(full.inverse_within_limits(tgt, sl.DT_S, lo, hi, sl.SLEW_V_PER_S).u_V))}
    for label, first in (("exact static", True), ("exact static, band limit", False)):
        res = invert_within_limits(full.dynamics, tgt, sl.DT_S, lambda: full.static_inverse(sl.DT_S), lo, hi,
                                   sl.SLEW_V_PER_S, round_first=first)
        row[label] = err(play(res.u_V, exact_static=exact))
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rates", type=float, nargs="+", default=[1, 16, 50], help="line rates [lines/s]")
    ap.add_argument("--no-write", action="store_true", help="do not update docs/BENCHMARKS.md")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="split-") as tmp:
        paths = sl.identify(Path(tmp))
        static, full = load_model(paths["chain"]), load_model(paths["chain_dyn"])
        rows = {r: split(r, static, full) for r in args.rates}
    cols = list(next(iter(rows.values())))
    tab = "| lines/s | " + " | ".join(cols) + " |\n|---|" + "---|" * len(cols) + "\n" + "".join(
        f"| {r:g} | " + " | ".join(row[c] for c in cols) + " |\n" for r, row in rows.items())
    print(tab)
    if not args.no_write:
        write_section("error_split", "## Speed ladder error split (where the offline error comes from)\n\n"
                      "`.venv/bin/python benchmarks/error_split.py`: the speed ladder's models (same CLI "
                      "identification), max / RMS error, % of the 4 µm line, central 80 %, on plants that "
                      "leave out one cause at a time (see the script's docstring).\n\n" + tab + "\n" + NOTE)
    return 0


if __name__ == "__main__":
    sys.exit(main())
