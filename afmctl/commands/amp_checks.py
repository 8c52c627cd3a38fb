"""``afmctl amp``'s checks before anything is sent — limits and ``--max-step`` on a file's rows
or on ``set``'s values — each refusal one line that says what it measured and names the fix
in the command line's terms (the driver checks everything again below them)."""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from ..errors import AfmctlError


def round_up(step_V: float) -> str:
    """A ``--max-step`` [V] just above ``step_V``: rounded up to 0.1 V."""
    return f"{math.ceil(step_V * 10.0 - 1e-9) / 10.0:g}"


def _limit_source(amp, axis: str, lo: float, hi: float) -> str:
    """Where the limits of ``axis`` come from: the device's own range or ``--limit``."""
    dev = amp.device_limits.get(axis)
    if dev is not None and dev.min_V == lo and dev.max_V == hi:
        return "the device's own range, shown by afmctl amp ... info"
    return "the device's range narrowed by --limit"


def check_rows(amp, loaded, path: str) -> None:
    """Refuse a file (``loaded`` from ``amp._load_stream``) with a value outside the limits
    or a step over ``amp.max_step_V`` — from the present output to the first row, or
    between rows; AfmctlError naming row, column, what was measured and the fix."""
    import numpy as np

    axes, values, columns, _ = loaded
    lim = amp.limits
    for k, (axis, col) in enumerate(zip(axes, columns)):
        if axis not in lim:
            raise AfmctlError(f"{path}: column {col}: axis {axis} is not driven by {amp.name} "
                              f"(axes: {', '.join(amp.axes)}; choose one with --axis)")
        lo, hi = lim[axis].min_V, lim[axis].max_V
        bad = np.flatnonzero((values[:, k] < lo) | (values[:, k] > hi))
        if bad.size:
            i = int(bad[0])
            raise AfmctlError(
                f"{path}: row {i + 2}: column {col}: {values[i, k]:g} V is outside the limits [{lo:g}, {hi:g}] V "
                f"of axis {axis} ({bad.size} row(s) outside; {_limit_source(amp, axis, lo, hi)}); nothing was "
                f"sent. Make the file fit: afmctl compensate ... --limits {lo:g} {hi:g} --clip")
        step = amp.max_step_V
        if step is not None:
            _check_steps(amp, axis, col, values[:, k], step, path)


def _check_steps(amp, axis: str, col: str, column_V, step_V: float, path: str) -> None:
    import numpy as np

    start = amp.last_output.get(axis)
    if start is not None and abs(column_V[0] - start) > step_V + _readback_tolerance(amp):
        jump = abs(column_V[0] - start)
        raise AfmctlError(
            f"{path}: row 2: column {col}: the file starts at {column_V[0]:g} V, {jump:g} V from the present "
            f"output of axis {axis} ({start:g} V), over --max-step {step_V:g} V (the largest step from one "
            f"output to the next); nothing was sent. Move axis {axis} there first (afmctl amp ... set "
            f"{axis}={column_V[0]:.4g}, in steps of at most {step_V:g} V), start the file at the "
            f"present output, or allow the jump with --max-step {round_up(jump)}")
    steps = np.abs(np.diff(column_V))
    big = np.flatnonzero(steps > step_V)
    if big.size:
        i = int(big[0])
        raise AfmctlError(
            f"{path}: row {i + 3}: column {col}: step of {steps[i]:g} V from the row before on axis {axis} "
            f"exceeds --max-step {step_V:g} V; nothing was sent. Allow it with --max-step "
            f"{round_up(float(steps.max()))} (the file's largest step), or make the steps smaller "
            f"(afmctl compensate ... --slew-V-per-s S keeps them under S times the row spacing)")


def check_wrap(first_V: Sequence[float], last_V: Sequence[float], columns: Sequence[str], step_V: float,
               path: str) -> None:
    """Refuse ``--cycles`` > 1 when the wrap from the last row to the first is over ``--max-step``."""
    for col, a, b in zip(columns, first_V, last_V):
        wrap = abs(a - b)
        if wrap > step_V:
            raise AfmctlError(
                f"{path}: column {col}: the wrap from the last row to the first is {wrap:g} V ({b:g} V -> "
                f"{a:g} V), over --max-step {step_V:g} V; nothing was sent. End the file where it starts, "
                f"play it once (--cycles 1), or allow the wrap with --max-step {round_up(wrap)}")


def check_set(amp, values: Mapping[str, float]) -> None:
    """Refuse ``set AXIS=V ...`` outside the limits or over ``--max-step`` from the present
    output, naming the fix."""
    lim = amp.limits
    for axis, v in values.items():
        if axis not in lim:
            raise AfmctlError(f"set {axis}={v:g}: axis {axis} is not driven by {amp.name} "
                              f"(axes: {', '.join(amp.axes)}); nothing was sent")
        lo, hi = lim[axis].min_V, lim[axis].max_V
        if not lo <= v <= hi:
            raise AfmctlError(f"set {axis}={v:g}: {v:g} V is outside the limits [{lo:g}, {hi:g}] V of axis {axis} "
                              f"({_limit_source(amp, axis, lo, hi)}); nothing was sent")
        start, step = amp.last_output.get(axis), amp.max_step_V
        if step is not None and start is not None and abs(v - start) > step + _readback_tolerance(amp):
            raise AfmctlError(f"set {axis}={v:g}: a step of {abs(v - start):g} V from the present output of axis "
                              f"{axis} ({start:g} V), over --max-step {step:g} V; nothing was sent. Go there in "
                              f"steps of at most {step:g} V, or allow it with --max-step {round_up(abs(v - start))}")


def _readback_tolerance(amp) -> float:
    """Half the read-back resolution [V]: the driver's own step check allows as much."""
    return 0.5 * float(getattr(amp, "readback_resolution_V", 0.0) or 0.0)
