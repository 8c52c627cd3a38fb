"""What the page shows of one scanner: decimated, bounded streams built from its zenoh
messages (keys and payloads: docs/ZENOH.md)."""
from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from ..zenoh_api.messages import (DriftMsg, LearnMsg, SimImageMsg, SimTipMsg, StatusMsg, decode_json,
                                  decode_setpoints)
from .align import ClockOffset, TargetHistory
from .image import HeightImage
from .ring import Ring

log = logging.getLogger(__name__)

#: seconds of tips that may wait for the setpoints they are compared with
TIP_WAIT_S = 2.0
#: the image covers the targets' x–y extent plus this fraction of it on each side
IMAGE_MARGIN = 0.1
#: window of the tracking-error summary [s]
ERROR_WINDOW_S = 2.0
#: most learning iterations kept (one learning run; a new run starts at iteration 0)
MAX_LEARN_ROWS = 1000


def _r(values: Any, nd: int = 3) -> list[float | None]:
    """Rounded floats for JSON (NaN/inf → None)."""
    return [round(float(v), nd) if math.isfinite(v) else None for v in np.asarray(values, float).ravel()]


class Decimator:
    """Keep the first sample of every ``period_s`` bucket of sender time [s]."""

    def __init__(self, rate_Hz: float) -> None:
        self.period_s = 1.0 / rate_Hz
        self._last = -math.inf

    def keep(self, t_s: np.ndarray) -> np.ndarray:
        b = np.floor(np.asarray(t_s, float) / self.period_s)
        if len(b) and b[0] < self._last - 1:              # sender restarted
            self._last = -math.inf
        prev = np.concatenate([[self._last], b[:-1]])
        if len(b):
            self._last = float(b[-1])
        return b != prev


class ScannerFeed:
    """Bounded, decimated state of one scanner, fed by zenoh callbacks (any thread).

    Streams (each a :class:`Ring` of rows, oldest dropped): ``setpoints`` rows
    ``[t_s, target x/y/z nm, u x/y/z V]``; ``tips`` rows ``[t_s, tip x/y/z nm, error x/y/z nm]``
    on the controller's clock (error None when no target is known at that time);
    ``drift`` rows ``[t_s, drift x/y/z nm, 1σ x/y/z nm or None]``; ``learn`` rows
    ``[iteration, max %, RMS %, central max %, central RMS %, step]`` of the latest learning
    run (``afmctl learn``; errors in % of the range) and ``learn_state`` its last state and
    detail. ``status``: the last status message. ``image``: :class:`HeightImage`.
    """

    def __init__(self, name: str, display_rate_Hz: float = 200.0, history_s: float = 30.0) -> None:
        n = max(1, int(display_rate_Hz * history_s))
        self.name = name
        self.setpoints, self.tips, self.drift = Ring(n), Ring(n), Ring(n)
        self.status: dict[str, Any] | None = None
        self.learn = Ring(MAX_LEARN_ROWS)
        self.learn_state: dict[str, Any] | None = None
        self._learn_run = 0                                # bumped when a new learning run starts
        self.image = HeightImage()
        self.counts = {k: 0 for k in ("setpoint_batches", "setpoint_samples", "seq_gaps", "tips", "drift",
                                      "status", "image", "learn", "rejected")}
        self.last_rejected: str | None = None
        #: presence: True while its liveliness token is alive, False once it went away,
        #: None when none was ever seen (a service without presence, or not yet)
        self.alive: bool | None = None
        self.alive_changed_s: float | None = None       # time.time() of the last change
        self._lock = threading.Lock()
        self._sp_dec, self._tip_dec = Decimator(display_rate_Hz), Decimator(display_rate_Hz)
        self._sp_clock, self._tip_clock = ClockOffset(), ClockOffset()
        self._targets = TargetHistory(keep_s=TIP_WAIT_S + 3.0)
        self._pending: deque[tuple[float, float, np.ndarray]] = deque(maxlen=n)
        # (controller time [s], error x, y [nm]) of the latest tips with a target: the summary
        self._errors: deque[tuple[float, float, float]] = deque(maxlen=max(1, int(display_rate_Hz * ERROR_WINDOW_S)))
        self._next_batch: int | None = None
        self._t_last = -math.inf                           # newest controller time [s]
        self._range_nm = np.array([[math.inf] * 2, [-math.inf] * 2])   # min, max target x, y

    # ------------------------------------------------------------------ input
    def reject(self, what: str, err: Exception) -> None:
        with self._lock:
            self.counts["rejected"] += 1
            self.last_rejected = f"{what}: {err}"
        log.debug("%s: rejected %s: %s", self.name, what, err)

    def set_alive(self, alive: bool) -> None:
        """The scanner's liveliness token came (True) or went away (False)."""
        with self._lock:
            self.alive = alive
            self.alive_changed_s = time.time()

    def on_setpoints(self, payload: bytes, arrival_s: float | None = None) -> None:
        seq, rec = decode_setpoints(payload)
        arrival_s = time.monotonic() if arrival_s is None else arrival_s
        with self._lock:
            if self._next_batch is not None and seq > self._next_batch:
                self.counts["seq_gaps"] += 1
            self._next_batch = seq + 1
            self.counts["setpoint_batches"] += 1
            self.counts["setpoint_samples"] += len(rec)
            if not len(rec):
                return
            t = rec["t_s"].astype(float)
            if t[0] < self._t_last - 1.0:                  # the controller restarted
                self._range_nm = np.array([[math.inf] * 2, [-math.inf] * 2])
                self._errors.clear()
            self._t_last = float(t[-1])
            xy = rec["target_nm"][:, :2]
            self._range_nm = np.vstack([np.minimum(self._range_nm[0], xy.min(axis=0)),
                                        np.maximum(self._range_nm[1], xy.max(axis=0))])
            margin = IMAGE_MARGIN * (self._range_nm[1] - self._range_nm[0])
            self.image.set_area(self._range_nm + np.array([-margin, margin]))
            self._sp_clock.update(arrival_s, float(t[-1]))
            self._targets.add(t, rec["target_nm"])
            keep = self._sp_dec.keep(t)
            rows = np.column_stack([t[keep], rec["target_nm"][keep], rec["u_V"][keep]])
            self.setpoints.extend([_r(r) for r in rows])
            self._resolve_tips(arrival_s)

    def on_tip(self, payload: bytes, arrival_s: float | None = None) -> None:
        msg = decode_json(payload, SimTipMsg)
        arrival_s = time.monotonic() if arrival_s is None else arrival_s
        with self._lock:
            self.counts["tips"] += 1
            self._tip_clock.update(arrival_s, msg.t_s)
            if self._tip_dec.keep(np.array([msg.t_s]))[0]:
                self._pending.append((arrival_s, msg.t_s, np.asarray(msg.position_nm, float)))
            self._resolve_tips(arrival_s)

    def on_drift(self, payload: bytes) -> None:
        msg = decode_json(payload, DriftMsg)
        std = msg.std_nm if msg.std_nm is not None else [math.nan] * 3
        with self._lock:
            self.counts["drift"] += 1
            self.drift.extend([_r([msg.t_s, *msg.drift_nm, *std])])

    def on_status(self, payload: bytes) -> None:
        msg = decode_json(payload, StatusMsg)
        with self._lock:
            self.counts["status"] += 1
            self.status = msg.model_dump(mode="json", by_alias=True)

    def on_learn(self, payload: bytes) -> None:
        msg = decode_json(payload, LearnMsg)
        with self._lock:
            self.counts["learn"] += 1
            last = self.learn_state
            if last is not None and msg.iteration <= last["iteration"]:   # a new learning run
                self._learn_run += 1
                self.learn = Ring(MAX_LEARN_ROWS)
            self.learn_state = {"iteration": msg.iteration, "state": msg.state, "detail": msg.detail,
                                "run": self._learn_run}
            nan = math.nan
            self.learn.extend([_r([msg.iteration, msg.max_pct, msg.rms_pct,
                                   nan if msg.central_max_pct is None else msg.central_max_pct,
                                   nan if msg.central_rms_pct is None else msg.central_rms_pct,
                                   nan if msg.step is None else msg.step], 4)])

    def on_image(self, payload: bytes) -> None:
        msg = decode_json(payload, SimImageMsg)
        with self._lock:
            self.counts["image"] += 1
            self.image.add(msg.position_nm[0], msg.position_nm[1], msg.height_nm, msg.sample)

    # ------------------------------------------------------------------ tracking error
    def _resolve_tips(self, now_s: float) -> None:
        """Move waiting tips to ``tips`` once the targets at their time have arrived."""
        sp, tip = self._sp_clock.offset_s, self._tip_clock.offset_s
        span = self._targets.span_s
        ready: list[tuple[float, np.ndarray, bool]] = []
        while self._pending:
            arrival, t_tip, pos = self._pending[0]
            if sp is None or tip is None or span is None:
                if now_s - arrival < TIP_WAIT_S:
                    break                                   # no controller yet: wait a little
                t_ctrl = math.nan                           # none at all: the tip alone
            else:
                t_ctrl = t_tip + tip - sp
                if t_ctrl > span[1] and now_s - arrival < TIP_WAIT_S:
                    break                                   # its targets are still on the way
            self._pending.popleft()
            ready.append((t_tip if math.isnan(t_ctrl) else t_ctrl, pos, math.isnan(t_ctrl)))
        if not ready:
            return
        t = np.array([r[0] for r in ready])
        target = self._targets.at(t)                        # one interpolation for the lot
        target[[r[2] for r in ready]] = np.nan
        err = np.array([r[1] for r in ready]) - target
        self.tips.extend([_r([t[k], *r[1], *err[k]]) for k, r in enumerate(ready)])
        ok = np.isfinite(err[:, 0]) & np.isfinite(err[:, 1])
        self._errors.extend(zip(t[ok].tolist(), err[ok, 0].tolist(), err[ok, 1].tolist()))

    def tracking_summary(self) -> dict[str, Any]:
        """RMS tracking error [nm] over the last ``ERROR_WINDOW_S`` of tips, per axis x, y,
        and in % of the scan range (the targets' extent since the controller started)."""
        with self._lock:
            a = np.array(self._errors, float).reshape(-1, 3)
        if len(a):
            a = a[a[:, 0] >= a[-1, 0] - ERROR_WINDOW_S]
        if not len(a):
            return {"rms_nm": [None, None], "rms_pct": [None, None], "range_nm": [None, None], "n": 0}
        rms = np.sqrt(np.mean(a[:, 1:3] ** 2, axis=0))
        with self._lock:
            rng = self._range_nm[1] - self._range_nm[0]
        with np.errstate(invalid="ignore", divide="ignore"):
            pct = np.where(rng > 0, 100.0 * rms / rng, np.nan)
        return {"rms_nm": _r(rms, 2), "rms_pct": _r(pct, 3), "range_nm": _r(rng, 1), "n": len(a)}

    # ------------------------------------------------------------------ output
    def frame(self, cursor: dict[str, int], with_image: bool) -> dict[str, Any]:
        """What a page has not seen yet (``cursor``: stream → next index, updated here)."""
        out: dict[str, Any] = {}
        for key in ("setpoints", "tips", "drift"):
            rows, cursor[key] = getattr(self, key).since(cursor.get(key, 0))
            out[key] = rows
        with self._lock:
            run = self.learn_state["run"] if self.learn_state else 0
            if cursor.get("learn_run", 0) != run:          # a new learning run: from its start
                cursor["learn"], cursor["learn_run"] = 0, run
            out["learn"], cursor["learn"] = self.learn.since(cursor.get("learn", 0))
            out["learn_state"] = self.learn_state
            out["status"] = self.status
            out["alive"] = self.alive
            out["alive_changed_s"] = self.alive_changed_s
            out["counts"] = dict(self.counts)
            out["last_rejected"] = self.last_rejected
            out["offsets_s"] = {"setpoint": self._sp_clock.offset_s, "tip": self._tip_clock.offset_s}
            if with_image:
                out["image"] = self.image.grid()
        out["tracking"] = self.tracking_summary()
        return out
