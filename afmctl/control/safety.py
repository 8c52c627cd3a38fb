"""The safety layer: the only path from the controller to the amplifier.

Every voltage the controller sends goes through :meth:`SafetyLayer.send` (or a ramp built
on it). Whatever the trajectory, the models, the configuration or the amplifier's replies
say, a value that reaches :meth:`afmctl.drivers.base.Amplifier.set_voltages` is

* finite and inside the voltage limits of its axis — the intersection of the configured
  host limits, the safety limits and the amplifier's own effective limits
  (:attr:`Amplifier.limits`); a non-finite request holds the last value;
* no further from the previous value sent than ``slew_V_per_s · min(elapsed_s, dt_s)``,
  where ``elapsed_s`` is the wall time since that previous value was sent: the slew limit
  holds in volts per second *at the amplifier*, also when a late loop sends a few samples
  in quick succession to catch up (those steps shrink), and no step is ever larger than
  one sample period's worth, however long the output was held.

The first reference value is read back from the device (:meth:`SafetyLayer.sync_from_device`),
so the first output and every resume after a reconnect start where the amplifier really
is: ramps, never jumps. A read-back at most one slew step outside the limits is kept as
the reference (the first value sent is inside the limits and within one step of it); one
further outside, or not a number, is refused (:class:`ReadbackError`).

:class:`Watchdog` trips when the trajectory stream stalls; the controller then holds the
output or ramps to the safe value (``safety.on_stall``).
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence

from ..errors import AfmctlError
from afmctl.drivers.base import Amplifier
from afmctl.drivers.errors import ProtocolError

log = logging.getLogger(__name__)

XYZ = ("x", "y", "z")


class ReadbackError(ProtocolError):
    """The amplifier reported an output the safety layer cannot start from (not a number,
    or outside the limits)."""


class SafetyLayer:
    """Clamp, slew-limit and ramp the voltages of the driven axes, then send them.

    Parameters
    ----------
    amplifier: the link; only this object calls its ``set_voltages``.
    axes: the driven axes (subset of ``x, y, z``).
    limits_V: ``{axis: (min_V, max_V)}`` configured limits [V]; intersected with
        ``amplifier.limits``.
    slew_V_per_s: largest change per second of wall time at the amplifier [V/s].
    dt_s: sample period [s]; the largest change per sample is ``slew_V_per_s · dt_s``, and
        less when the previous sample was sent less than ``dt_s`` ago.
    safe_V: ``{axis: V}`` value to ramp to on stop / estop / stall (clamped into limits).
    clock: monotonic clock [s] that times the sends (tests pass a fake one).
    """

    def __init__(self, amplifier: Amplifier, axes: Sequence[str], limits_V: dict[str, tuple[float, float]],
                 slew_V_per_s: float, dt_s: float, safe_V: dict[str, float] | None = None,
                 clock=time.perf_counter) -> None:
        if not axes:
            raise ValueError("axes: at least one axis must be driven")
        if not (math.isfinite(slew_V_per_s) and slew_V_per_s > 0):
            raise ValueError(f"slew_V_per_s: {slew_V_per_s!r} must be a finite number > 0")
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s: {dt_s!r} must be a finite number > 0")
        self.amplifier = amplifier
        self.axes: tuple[str, ...] = tuple(axes)
        #: index of each driven axis in x, y, z
        self.index: tuple[int, ...] = tuple(XYZ.index(a) for a in self.axes)
        dev = dict(amplifier.limits)
        lo: list[float] = []
        hi: list[float] = []
        for a in self.axes:
            if a not in dev:
                raise AfmctlError(f"scanner.axes: axis {a!r} is not driven by the amplifier "
                                 f"(it has {', '.join(amplifier.axes)})")
            c_lo, c_hi = limits_V.get(a, (dev[a].min_V, dev[a].max_V))
            l_, h_ = max(float(c_lo), float(dev[a].min_V)), min(float(c_hi), float(dev[a].max_V))
            if not (math.isfinite(l_) and math.isfinite(h_) and l_ < h_):
                raise AfmctlError(f"limits of axis {a}: configured [{c_lo:g}, {c_hi:g}] V and device "
                                 f"[{dev[a].min_V:g}, {dev[a].max_V:g}] V leave no range")
            lo.append(l_)
            hi.append(h_)
        self.lo = lo
        self.hi = hi
        self.dt_s = float(dt_s)
        self.slew_V_per_s = float(slew_V_per_s)
        #: largest step per sample [V]: slew · dt, and below the driver's own ``max_step_V``
        #: (if it has one) by a margin for the device's output resolution, so that the
        #: driver never refuses a step (a refusal ends the run, see afmctl.control.controller)
        self.max_step_V = self.slew_V_per_s * self.dt_s
        dev_step = getattr(amplifier, "max_step_V", None)
        if isinstance(dev_step, (int, float)) and math.isfinite(dev_step) and dev_step > 0:
            self.max_step_V = min(self.max_step_V, max(dev_step - max(0.02 * dev_step, 0.01), 0.5 * dev_step))
        safe = safe_V or {}
        self.safe = [min(max(float(safe.get(a, 0.0)), lo[i]), hi[i]) for i, a in enumerate(self.axes)]
        #: last value sent (or read back) per driven axis [V]
        self.last = [min(max(0.0, lo[i]), hi[i]) for i in range(len(self.axes))]
        self.clock = clock
        #: clock time of the last send; -inf: the output has been held "forever"
        self._t_last = -math.inf
        self._cmd: dict[str, float] = {a: 0.0 for a in self.axes}
        #: how many samples had to be slew-limited / clamped / were not finite
        self.slew_limited = 0
        self.clamped = 0
        self.nonfinite = 0

    # ------------------------------------------------------------------ reference
    def sync_from_device(self) -> list[str]:
        """Read the applied voltages back and make them the reference for the next step.

        A read-back at most one slew step outside the limits (device rounding) is clamped
        into them and reported in the returned warnings. A read-back that is not a number
        or further outside raises :class:`ReadbackError`: the controller cannot know where
        the output is and will not move it (it stays in fault and retries).
        """
        warnings: list[str] = []
        got = self.amplifier.get_voltages()
        new = list(self.last)
        for i, a in enumerate(self.axes):
            raw = got.get(a) if isinstance(got, dict) else None
            try:
                v = float(raw)  # type: ignore[arg-type]
            except (TypeError, ValueError):
                v = math.nan
            if not math.isfinite(v):
                raise ReadbackError(f"axis {a}: read-back {raw!r} is not a voltage; not moving the output")
            if v < self.lo[i] or v > self.hi[i]:
                c = min(max(v, self.lo[i]), self.hi[i])
                if abs(v - c) > self.max_step_V:
                    raise ReadbackError(f"axis {a}: read-back {v:g} V is outside the limits "
                                        f"[{self.lo[i]:g}, {self.hi[i]:g}] V; not moving the output")
                warnings.append(f"axis {a}: read-back {v:g} V outside [{self.lo[i]:g}, {self.hi[i]:g}] V; "
                                f"moving it to {c:g} V")
            new[i] = v   # the true output: the first step is measured from here
        self.last[:] = new
        self._t_last = -math.inf   # the device has held this value: a full step is allowed
        for w in warnings:
            log.warning(w)
        return warnings

    # ------------------------------------------------------------------ output
    def max_step(self) -> float:
        """Largest step [V] allowed if a value were sent now: ``slew · min(elapsed, dt)``."""
        el = self.clock() - self._t_last
        if el >= self.dt_s:
            return self.max_step_V
        return min(self.slew_V_per_s * el, self.max_step_V) if el > 0.0 else 0.0

    def limit(self, i: int, v: float, m: float | None = None) -> float:
        """The value axis index ``i`` would get for request ``v`` with largest step ``m``
        [V] (default :meth:`max_step`); no sending."""
        last = self.last[i]
        if m is None:
            m = self.max_step()
        if not (v == v) or v in (math.inf, -math.inf):  # NaN / inf: hold (inside the limits)
            self.nonfinite += 1
            v = last
        if v < self.lo[i]:
            v = self.lo[i]
            self.clamped += 1
        elif v > self.hi[i]:
            v = self.hi[i]
            self.clamped += 1
        if v > last + m:
            v = last + m
            self.slew_limited += 1
        elif v < last - m:
            v = last - m
            self.slew_limited += 1
        # rounding can never leave the interval
        if v < self.lo[i]:
            v = self.lo[i]
        elif v > self.hi[i]:
            v = self.hi[i]
        return v

    def send(self, u_xyz: Sequence[float]) -> None:
        """Send the requested voltages ``u_xyz`` (indexed x, y, z; undriven axes ignored)
        after limiting; :attr:`last` is updated only when the amplifier accepted them."""
        cmd = self._cmd
        now = self.clock()
        el = now - self._t_last
        m = self.max_step_V if el >= self.dt_s else (min(self.slew_V_per_s * el, self.max_step_V) if el > 0.0
                                                     else 0.0)
        new = [self.limit(i, float(u_xyz[k]), m) for i, k in enumerate(self.index)]
        for a, v in zip(self.axes, new):
            cmd[a] = v
        self.amplifier.set_voltages(cmd)
        self.last[:] = new
        self._t_last = now

    def ramp_step(self, target: Sequence[float], rate_V_per_s: float) -> bool:
        """One sample of a ramp towards ``target`` (per driven axis, clamped into the
        limits) at ``rate_V_per_s`` (capped by the slew limit). Returns True when the
        output sent is the target."""
        m = min(min(rate_V_per_s, self.slew_V_per_s) * self.dt_s, self.max_step_V)
        goal = []
        req = []
        for i in range(len(self.axes)):
            t = float(target[i])
            if not math.isfinite(t):
                t = self.last[i]
            t = min(max(t, self.lo[i]), self.hi[i])
            goal.append(t)
            d = t - self.last[i]
            if d > m:
                t = self.last[i] + m
            elif d < -m:
                t = self.last[i] - m
            req.append(t)
        self.send(self.xyz(req))
        return all(self.last[i] == goal[i] for i in range(len(goal)))

    def driven_target(self, u_xyz: Sequence[float]) -> list[float]:
        """The driven-axis part of an x, y, z vector."""
        return [float(u_xyz[k]) for k in self.index]

    def xyz(self, values: Sequence[float], fill: float = 0.0) -> list[float]:
        """A driven-axis vector spread back to x, y, z (``fill`` for undriven axes)."""
        out = [fill, fill, fill]
        for i, k in enumerate(self.index):
            out[k] = values[i]
        return out


class Watchdog:
    """Trips when :meth:`feed` has not been called for ``timeout_s`` seconds (monotonic)."""

    def __init__(self, timeout_s: float, clock=time.perf_counter) -> None:
        if not (timeout_s > 0):
            raise ValueError(f"watchdog timeout_s: {timeout_s!r} must be > 0")
        self.timeout_s = float(timeout_s)
        self.clock = clock
        self._last = clock()

    def feed(self, now: float | None = None) -> None:
        self._last = self.clock() if now is None else now

    def expired(self, now: float | None = None) -> bool:
        t = self.clock() if now is None else now
        return t - self._last > self.timeout_s

    def since(self, now: float | None = None) -> float:
        t = self.clock() if now is None else now
        return t - self._last
