"""A zenoh subscriber in its own process for the soak (benchmarks/soak.py): a peer on loopback.

    python benchmarks/soak_peer.py ENDPOINT [ENDPOINT ...]

Joins zenoh as a peer that listens on nothing and connects to the given endpoints (the
``afmctl run`` processes' zenoh API), subscribes to ``afm/*/setpoint`` and ``afm/*/status``
and prints ``messages N`` once a second (N counted since this process started) until it is
killed. The soak kills it (SIGKILL) and starts it again: a zenoh peer restarting.
"""
from __future__ import annotations

import sys
import threading
import time


def main() -> int:
    from afmctl.zenoh_api.bridge import open_session
    from afmctl.zenoh_api.settings import ZenohSettings
    settings = ZenohSettings(enabled=True, mode="peer", listen=[], connect=sys.argv[1:])
    count = [0]
    lock = threading.Lock()

    def on_sample(sample) -> None:  # noqa: ARG001
        with lock:
            count[0] += 1

    session = open_session(settings)
    subs = [session.declare_subscriber(f"{settings.prefix}/*/{topic}", on_sample) for topic in ("setpoint", "status")]
    print("ready", flush=True)
    try:
        while True:
            time.sleep(1.0)
            with lock:
                n = count[0]
            print(f"messages {n}", flush=True)
    finally:
        for s in subs:
            s.undeclare()
        session.close()


if __name__ == "__main__":
    sys.exit(main())
