"""How long a stop takes from each phase of the setpoint loop: ``stop()`` to ``wait()``
returning, against the bound docs/CONTROLLER.md states (one period + the finish ramp + one
driver call + the dispatcher's last pass). Uses the real controller with the checking
RecordingAmplifier, driven into each phase as tests/test_stop_bound.py does.

    .venv/bin/python benchmarks/stop_latency.py [--repeats 3]
"""
from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import tempfile
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "tests"))

import test_stop_bound as t  # noqa: E402

from afmctl.control.transitions import Phase  # noqa: E402

PHASES = (Phase.RAMP, Phase.RUN, Phase.HOLD, Phase.FINISH, Phase.RETRY, Phase.RECONNECT)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3, help="runs per phase (default 3)")
    n = ap.parse_args().repeats
    print(f"{'phase':10s} {'median ms':>10s} {'max ms':>8s} {'bound ms':>9s}  ended in")
    for phase in PHASES:
        rows = []
        for _ in range(n):
            ctl, amp = t._running_in(pathlib.Path(tempfile.mkdtemp()), phase)
            bound = t.stop_bound_s(ctl, "stop")
            t0 = time.perf_counter()
            ctl.stop()
            ended = ctl.wait(bound + 10.0)
            dt = time.perf_counter() - t0
            amp.release.set()
            ctl.close()
            rows.append((dt, bound, ended, ctl._fsm.phase.value))
        med = statistics.median(r[0] for r in rows)
        print(f"{phase.value:10s} {med * 1e3:10.1f} {max(r[0] for r in rows) * 1e3:8.1f} "
              f"{max(r[1] for r in rows) * 1e3:9.1f}  {','.join(sorted({r[3] for r in rows}))}"
              f"{'' if all(r[2] for r in rows) else '  NOT ENDED'}")


if __name__ == "__main__":
    main()
