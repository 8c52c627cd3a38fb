"""What the zenoh bridge publishes: ``setpoint`` (binary batches), ``drift`` and ``status``
(JSON), each with its own sequence number, reliable with blocking congestion control, so
a slow subscriber slows the controller's dispatcher, never the loop, and no sample is
dropped (docs/ZENOH.md, *Keys*)."""
from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from .jsonvalues import jsonable, one_line
from .ledger import BridgeLedger
from .messages import DriftMsg, StatusMsg, encode_setpoints
from .settings import ZenohSettings


class RecordPublishers:
    """The ``setpoint``, ``drift`` and ``status`` publishers of one scanner and their
    sequence numbers. Called by the controller's dispatcher thread (and the bridge's
    worker for ``status``); ``closed`` set means publish nothing.

    ``keys``: leaf -> zenoh key; ``ledger``: its lock guards the sequence numbers and the
    publishers, its counters get ``setpoint_batches`` / ``setpoint_samples``.
    """

    def __init__(self, session: Any, keys: Mapping[str, str], settings: ZenohSettings,
                 ledger: BridgeLedger, closed: threading.Event) -> None:
        import zenoh
        block = zenoh.CongestionControl.BLOCK
        reliable = zenoh.Reliability.RELIABLE
        self.settings = settings
        self._ledger = ledger
        self._lock = ledger.lock
        self._closed = closed
        self._seq = {"setpoint": 0, "drift": 0, "status": 0}
        self._last_setpoint: tuple[int, list[float]] | None = None   # (sample seq, u_V) of the last record
        self.last_status: bytes | None = None       # the last status payload (the status queryable's answer)
        self._pub: dict[str, Any] = {}
        self._pub["setpoint"] = session.declare_publisher(keys["setpoint"], congestion_control=block,
                                                          reliability=reliable, priority=zenoh.Priority.DATA_HIGH)
        for leaf in ("drift", "status"):
            self._pub[leaf] = session.declare_publisher(keys[leaf], congestion_control=block,
                                                        reliability=reliable)

    def undeclare(self) -> None:
        """Undeclare the publishers (after ``closed`` is set)."""
        with self._lock:
            for pub in self._pub.values():
                pub.undeclare()

    def status_seq(self) -> int:
        """The sequence number the next ``status`` message gets."""
        with self._lock:
            return self._seq["status"]

    def setpoints(self, batch: np.ndarray) -> None:
        """Publish a setpoint batch (split into ``settings.setpoint_batch`` records)."""
        step = self.settings.setpoint_batch
        counters = self._ledger.counters
        with self._lock:
            if self._closed.is_set():
                return
            for start in range(0, len(batch), step):
                part = batch[start:start + step]
                payload = encode_setpoints(self._seq["setpoint"], part)
                self._pub["setpoint"].put(payload)
                self._seq["setpoint"] += 1
                counters["setpoint_batches"] += 1
                counters["setpoint_samples"] += len(part)
            last = batch[-1]
            self._last_setpoint = (int(last["seq"]), [float(v) for v in last["u_V"]])

    def drift(self, estimate: Any) -> str | None:
        """Publish a drift estimate (see :func:`drift_fields`); returns why it was not
        published (NaN/inf from the controller), or None."""
        msg_fields = drift_fields(estimate)
        with self._lock:
            if self._closed.is_set():
                return None
            inputs = msg_fields["inputs"]
            # the drift predictor's inputs: the temperature and the voltages of the sample
            # the estimate belongs to (its heat term); the controller sends them in this order
            if self._last_setpoint is not None and "u_V" not in inputs \
                    and inputs.get("seq") == self._last_setpoint[0]:
                inputs["u_V"] = self._last_setpoint[1]
            if msg_fields["T_C"] is not None:
                inputs.setdefault("T_C", msg_fields["T_C"])
            try:
                payload = DriftMsg(seq=self._seq["drift"], **msg_fields).to_json_bytes()
            except ValueError as err:   # NaN/inf from the controller: say so, publish nothing wrong
                return f"drift estimate not published: {one_line(err)}"
            self._pub["drift"].put(payload)
            self._seq["drift"] += 1
            return None

    def status(self, msg: StatusMsg) -> None:
        """Publish ``msg`` on ``status`` with the next status sequence number."""
        with self._lock:
            if self._closed.is_set():
                return
            msg = msg.model_copy(update={"seq": self._seq["status"]})
            self.last_status = msg.to_json_bytes()
            self._pub["status"].put(self.last_status)
            self._seq["status"] += 1


def drift_fields(estimate: Any) -> dict[str, Any]:
    """DriftMsg fields from whatever the controller hands over: a dict/object with
    ``drift_nm`` or ``estimate_nm`` [nm] (optionally ``std_nm``, ``t_s`` [s], ``T_C`` [°C];
    the other dict entries become ``inputs``), or an array (3,) [nm]."""
    def get(name: str) -> Any:
        if isinstance(estimate, Mapping):
            return estimate.get(name)
        return getattr(estimate, name, None)

    if isinstance(estimate, (np.ndarray, list, tuple)):        # a bare vector: only the drift [nm]
        return {"t_s": time.time(), "drift_nm": [float(v) for v in np.asarray(estimate, float).reshape(3)],
                "std_nm": None, "T_C": None, "inputs": {}}
    drift = get("drift_nm")
    if drift is None:
        drift = get("estimate_nm")
    std = get("std_nm")
    t_s = get("t_s")
    T_C = get("T_C")
    known = {"drift_nm", "estimate_nm", "std_nm", "t_s", "T_C"}
    inputs = {}
    if isinstance(estimate, Mapping):
        inputs = {k: v for k, v in estimate.items() if k not in known}
    return {
        "t_s": float(t_s) if t_s is not None else time.time(),
        "drift_nm": [float(v) for v in np.asarray(drift, float).reshape(3)],
        "std_nm": None if std is None else [float(v) for v in np.asarray(std, float).reshape(3)],
        "T_C": None if T_C is None else float(T_C),
        "inputs": jsonable(inputs),
    }
