"""What the zenoh bridge accepts on ``trajectory`` and ``temperature`` (docs/ZENOH.md):
the zenoh callbacks check the size, decode and validate and queue the message; the
bridge's worker then checks the sequence number and the scan range and hands it to the
controller. A message that fails any check never reaches the controller."""
from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from .jsonvalues import one_line
from .ledger import BridgeLedger
from .messages import MessageError, TemperatureMsg, decode_json, decode_trajectory
from .settings import ZenohSettings

log = logging.getLogger(__name__)

#: an item for the bridge's worker queue: (kind, item); returns False when the queue is full
Enqueue = Callable[[tuple[str, Any]], bool]
#: count, report and publish a rejected message: (source, one-line message)
Reject = Callable[[str, str], None]

LEAVES = ("trajectory", "temperature")


class InputSubscribers:
    """The ``trajectory`` and ``temperature`` subscribers of one scanner.

    ``keys``: leaf -> zenoh key; ``enqueue`` puts an item on the worker's queue (never
    blocks); ``position_range_nm``: axis -> (lo, hi) [nm] a trajectory must stay in.
    """

    def __init__(self, session: Any, keys: Mapping[str, str], settings: ZenohSettings, controller: Any,
                 position_range_nm: Mapping[str, tuple[float, float]], ledger: BridgeLedger,
                 enqueue: Enqueue) -> None:
        self.settings = settings
        self.controller = controller
        self.position_range_nm = position_range_nm
        self._ledger = ledger
        self._enqueue = enqueue
        self._subs = [session.declare_subscriber(keys[leaf], functools.partial(self._on_sample, leaf))
                      for leaf in LEAVES]

    def undeclare(self) -> None:
        for sub in self._subs:
            sub.undeclare()

    # ------------------------------------------------------------------ zenoh callbacks (never block)
    def _payload(self, sample: Any, leaf: str) -> bytes | None:
        data = sample.payload.to_bytes()
        if len(data) > self.settings.max_message_bytes:
            self._enqueue(("reject", (leaf,
                           f"payload: {len(data)} bytes; allowed at most {self.settings.max_message_bytes}")))
            return None
        return bytes(data)

    def _on_sample(self, leaf: str, sample: Any) -> None:
        """zenoh callback of ``trajectory`` and ``temperature``: size check, decode and
        validate here, then queue for the worker (never blocks)."""
        data = self._payload(sample, leaf)
        if data is None:
            return
        try:
            if leaf == "trajectory":
                msg: Any = decode_trajectory(data, self.settings.max_message_bytes)
            else:
                msg = decode_json(data, TemperatureMsg, self.settings.max_message_bytes)
        except MessageError as err:
            self._enqueue(("reject", (leaf, str(err))))
            return
        except Exception as err:  # a decoder bug must still end as an error on status
            log.exception("decoding a %s payload failed", leaf)
            self._enqueue(("reject", (leaf, f"payload: cannot be decoded ({one_line(err)})")))
            return
        self._enqueue((leaf, msg))

    # ------------------------------------------------------------------ worker
    def handle(self, leaf: str, msg: Any, reject: Reject) -> None:
        """Worker thread: hand a decoded ``trajectory`` / ``temperature`` message to the
        controller; a refusal goes to ``reject`` and the service keeps running."""
        self._ledger.check_seq(leaf, msg.seq)
        try:
            if leaf == "trajectory":
                positions = msg.positions(self.settings.max_segment_samples)
                check_range(positions, self.position_range_nm)
                self.controller.submit_segment(positions, msg.dt_s)
            else:
                self.controller.set_temperature(msg.t_s, msg.T_C)
        except Exception as err:  # refused by the controller: report, keep running
            reject(leaf, one_line(err))
            return
        self._ledger.count("accepted")


def check_range(positions_nm: np.ndarray, position_range_nm: Mapping[str, tuple[float, float]]) -> None:
    """Raise :class:`MessageError` naming the first sample of ``positions_nm`` (N, 3) [nm]
    outside its axis' ``position_range_nm`` (axis -> (lo, hi) [nm]; a missing axis is free)."""
    for i, axis in enumerate(("x", "y", "z")):
        rng = position_range_nm.get(axis)
        if rng is None:
            continue
        lo, hi = rng
        col = positions_nm[:, i]
        bad = (col < lo) | (col > hi)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise MessageError(f"positions_nm: sample {k}: {axis} = {col[k]:.6g} nm outside the scan range "
                               f"{lo:.6g}..{hi:.6g} nm")


def position_range_from_config(config: Any, margin: float = 0.1) -> dict[str, tuple[float, float]]:
    """Allowed target range per driven axis [nm]: the voltage limits through the linear
    calibration (``scanner.calibration``), widened by ``margin`` of the span on each side
    (hysteresis models bend the map a little). Empty when ``config`` is not an afmctl Config."""
    try:
        axes = list(config.scanner.axes)
        out = {}
        for axis in axes:
            lo_V, hi_V = config.limits(axis)
            spec = config.scanner.axis_spec(axis)
            a = (lo_V - spec.offset_V) * spec.nm_per_V
            b = (hi_V - spec.offset_V) * spec.nm_per_V
            lo, hi = min(a, b), max(a, b)
            pad = margin * (hi - lo)
            out[axis] = (lo - pad, hi + pad)
        return out
    except AttributeError:
        return {}
