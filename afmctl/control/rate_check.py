"""Is the loop fast enough for the scanner's first structural mode?

The loop holds each voltage for one period (a zero-order hold): a ramp becomes a staircase,
a ramp plus a sawtooth at the loop rate. With the mode above the loop's Nyquist frequency
(rate / 2) the sawtooth drives the mode near its peak, and a position sampled once per
period catches the ringing at the same phase each time: it reads as a lag growing with the
line speed, and no inverse at that rate can take it out. Measured through ``afmctl run``
(``benchmarks/loop_preview.py --loop-rates 1000 2000 5000 --rates 4``: the default simulated
scanner, mode 1 kHz, Q 20; the demo's models; 4 µm lines at 4 lines/s, central 80 % after
the first line, max / RMS): ``preisach+creep`` 4.39 / 3.03 % at a 1 kHz loop, 0.22 / 0.12 %
at 2 kHz, 0.08 / 0.03 % at 5 kHz; ``preisach+creep+dynamics`` 7.32 / 4.73 %, 0.03 / 0.01 %
and 0.04 / 0.01 %.

The mode comes from where afmctl knows it: the axis model's dynamics stage, else the
simulated scanner's configuration when the run drives one (``[simulation] enabled``). A
real stage compensated without a dynamics stage has no mode afmctl knows: nothing is said."""
from __future__ import annotations

from typing import Any

from afmctl.compensators.dynamics import first_mode_Hz

#: warn below this many loop periods per mode period (the mode above the Nyquist frequency)
WARN_RATIO = 2.0
#: the rate advised, in mode frequencies
ADVISED_RATIO = 5.0
#: an identified mode is an estimate (the demo's model puts the simulated scanner's 1000 Hz
#: mode at 1001-1002 Hz): a loop within this share below WARN_RATIO × the mode is not warned
MODE_TOL = 0.01


def _model_mode_Hz(model: Any) -> float | None:
    """The first mode [Hz] of the axis model's dynamics (a dynamics model, or a chain's stage)."""
    kind = getattr(model, "kind", "")
    dyn = model if kind == "dynamics" else getattr(model, "dynamics", None) if kind == "chain" else None
    if dyn is None:
        return None
    return first_mode_Hz(dyn.poles()) or None


def _simulated_mode_Hz(scanner: Any, axis: str) -> float | None:
    """The simulated scanner's lowest mode [Hz] on ``axis`` (None: no scanner, or no mode)."""
    spec = getattr(scanner, axis, None) if scanner is not None else None
    if spec is None:
        return None
    modes = [m.resonance_Hz for m in ([spec.dynamics] if spec.dynamics else []) + list(spec.extra_modes)]
    return min(modes) if modes else None


def mode_warnings(config: Any, models: list[Any], simulated: Any = None) -> list[str]:
    """One line per lateral axis whose loop rate is below WARN_RATIO × its first mode
    (``models``: per axis x, y, z the model or None; ``simulated``: the simulated scanner's
    configuration, a :class:`afmctl.sim_backend.config.ScannerConfig`, or None for a real
    stage). Empty for ``output = "wave"`` (the amplifier plays on its own clock)."""
    if config.amplifier.output == "wave":
        return []
    rate = float(config.loop.rate_Hz)
    lines = []
    for axis, model in zip(("x", "y"), models):
        mode, source = _model_mode_Hz(model), "the model's"
        if mode is None:
            mode, source = _simulated_mode_Hz(simulated, axis), "the simulated scanner's"
        if axis not in config.scanner.axes or mode is None or rate >= WARN_RATIO * mode * (1.0 - MODE_TOL):
            continue
        lines.append(f"loop.rate_Hz {rate:g} Hz is below twice the first mode of axis {axis} ({mode:.4g} Hz, "
                     f"{source}): each held step rings the mode, which reads as a lag growing with the line "
                     f"speed and no inverse at this rate takes out; set loop.rate_Hz to {ADVISED_RATIO * mode:.4g} "
                     f"or more ({WARN_RATIO * mode:.4g} at least)")
    return lines
