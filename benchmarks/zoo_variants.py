"""``../shared/plants/check.py``'s workflow on two scanners built from ``zoo.py``'s parts
but not among its plants: an outside check beside the zoo's own three, not a target.

- ``amp300``: issue #36/#37's amplifier-first scanner — a 300 Hz amplifier (60 kV/s) before
  an asymmetric generalised Prandtl–Ishlinskii loop, a 650 Hz mode with ζ 0.04, 3 nm noise;
- ``lowmode``: a fast amplifier (3 kHz), a lumpy Preisach plane, a low, lightly damped
  420 Hz mode with ζ 0.015 and a one-sample delay, 2 nm noise.

    .venv/bin/python benchmarks/zoo_variants.py --plants amp300,lowmode [--only speed|learn]
        [--recording excite|lab|lab-no-v] [--keep DIR]

Takes every option of check.py (``--help`` lists them) and prints what it prints.
"""
from __future__ import annotations

import sys
from pathlib import Path

PLANTS_DIR = Path(__file__).resolve().parent.parent.parent / "shared" / "plants"


def main() -> None:
    sys.path.insert(0, str(PLANTS_DIR))
    import check  # noqa: PLC0415  (../shared/plants/check.py)
    import zoo    # noqa: PLC0415
    from zoo import FS_HZ, GeneralisedPI, LumpyPreisach, Plant  # noqa: PLC0415

    zoo.PLANTS.clear()
    zoo.PLANTS.update({
        "amp300": lambda: Plant("amp300", FS_HZ, (300.0, 6.0e4), GeneralisedPI(n=12, asym=0.2, cubic=0.08),
                                ((0.04, 0.8, 8.0), (0.012, 0.01, 0.015)), [(650.0, 0.04)], 0, 3.0, seed=7),
        "lowmode": lambda: Plant("lowmode", FS_HZ, (3000.0, 2.0e5), LumpyPreisach(),
                                 ((0.05, 0.5, 5.0), (0.01, 0.01, 0.01)), [(420.0, 0.015)], 1, 2.0, seed=3),
    })
    check.PLANTS = zoo.PLANTS
    sys.argv = [str(PLANTS_DIR / "check.py"), *sys.argv[1:]]
    check.main()


if __name__ == "__main__":
    main()
