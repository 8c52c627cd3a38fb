"""A zenoh subscriber in its own process that counts setpoint batches (bench_loop.py).

    python benchmarks/zenoh_counter.py SETTINGS_JSON SCANNER [SLOW_S]

Connects with the client settings (JSON of afmctl.zenoh_api.settings.ZenohSettings), subscribes
to ``<prefix>/<scanner>/setpoint``, prints ``ready`` and, when its stdin closes, one line
``batches N samples M gaps G`` (G = batch sequence gaps). ``SLOW_S``: sleep that long in
every callback (a slow subscriber).
"""
from __future__ import annotations

import sys
import time


def main() -> int:
    import zenoh

    from afmctl.zenoh_api.messages import decode_setpoints
    from afmctl.zenoh_api.bridge import open_session
    from afmctl.zenoh_api.settings import ZenohSettings
    settings = ZenohSettings.model_validate_json(sys.argv[1])
    scanner = sys.argv[2]
    slow_s = float(sys.argv[3]) if len(sys.argv) > 3 else 0.0
    count = {"batches": 0, "samples": 0, "gaps": 0, "last": None}

    def on_sample(sample: zenoh.Sample) -> None:
        seq, rec = decode_setpoints(sample.payload.to_bytes())
        if count["last"] is not None and seq != count["last"] + 1:
            count["gaps"] += 1
        count["last"] = seq
        count["batches"] += 1
        count["samples"] += len(rec)
        if slow_s:
            time.sleep(slow_s)

    session = open_session(settings)
    sub = session.declare_subscriber(settings.key(scanner, "setpoint"), on_sample)
    print("ready", flush=True)
    sys.stdin.read()
    time.sleep(0.5)            # the last batches in flight
    print(f"batches {count['batches']} samples {count['samples']} gaps {count['gaps']}", flush=True)
    sub.undeclare()
    session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
