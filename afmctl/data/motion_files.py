"""A measured motion as a file: what an external sensor (a DAQ beside an amplifier without a
data recorder, e.g. the MDT693B) gives, read into the same
:class:`~afmctl.drivers.recording.Recording` a device's recorder returns, so that whatever
learns from a recording takes either.

Format (CSV with a header row, see :mod:`afmctl.datafiles`):

* ``t,y`` — time [s] and the measured position [nm] of one axis (``axis``, default x);
* ``t,x,y,z`` (any of the three) — the positions [nm] per axis;
* optional voltage columns: ``u`` with ``t,y``, ``ux,uy,uz`` with per-axis positions [V].

``t`` counts from the wave start (the first table point output at t = 0), as a device's
recording does; if the DAQ's clock starts elsewhere, that offset is what the learner's
alignment estimate reports. Samples must be uniformly spaced (the period is their median
step). :func:`write_motion_csv` writes a recording in the same format (so a device's
recording can be kept and replayed through ``afmctl learn step --measured``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .datafiles import read_csv, uniform_period, write_csv
from ..drivers.recording import Recording
from ..errors import AfmctlError

_AXES = ("x", "y", "z")


def _header(path: Path) -> list[str]:
    try:
        with path.open(encoding="utf-8-sig") as f:
            first = f.readline()
    except OSError as err:
        raise AfmctlError(f"{path}: cannot open ({err.strerror})") from None
    return [h.strip() for h in first.strip().split(",")]


def read_motion_csv(path: str | Path, axis: str = "x") -> Recording:
    """Read a measured motion (``t,y`` or ``t,x,y,z`` in nm, optional ``u``/``ux..uz`` in V)
    as a :class:`Recording`; bad files raise :class:`~afmctl.errors.AfmctlError` naming the
    file, the column and the row."""
    p = Path(path)
    if axis not in _AXES:
        raise AfmctlError(f"{p}: axis {axis!r}: allowed x, y, z")
    names = _header(p)
    per_axis = [a for a in _AXES if a in names and (a != "y" or "x" in names or "z" in names)]
    if per_axis:
        volts = [f"u{a}" for a in per_axis if f"u{a}" in names]
        cols = read_csv(p, ["t", *per_axis], min_rows=2, optional=volts)
        y = {a: cols[a] for a in per_axis}
        u = {c[1:]: cols[c] for c in volts}
    else:
        if "y" not in names:
            raise AfmctlError(f"{p}: header {','.join(names) or '(nothing)'} has no position column; expected "
                              "t,y (one axis, nm) or t,x,y,z (nm per axis)")
        cols = read_csv(p, ["t", "y"], min_rows=2, optional=["u"])
        y = {axis: cols["y"]}
        u = {axis: cols["u"]} if "u" in cols else {}
    period = uniform_period(cols["t"], str(p))
    return Recording(cols["t"], y, u, period, f"file {p.name}")


def write_motion_csv(path: str | Path, recording: Recording) -> None:
    """Write ``recording`` as ``t,y[,u]`` (one axis: the file does not say which; the
    reader's ``axis`` does) or ``t,<axes>[,u<axes>]`` (several)."""
    axes = [a for a in _AXES if a in recording.y_nm]
    if not axes:
        raise AfmctlError(f"{path}: the recording holds no position to write")
    cols: dict[str, np.ndarray] = {"t": np.asarray(recording.t_s)}
    if len(axes) == 1:
        cols["y"] = recording.y_nm[axes[0]]
        if axes[0] in recording.u_V:
            cols["u"] = recording.u_V[axes[0]]
    else:
        cols.update({a: recording.y_nm[a] for a in axes})
        cols.update({f"u{a}": recording.u_V[a] for a in axes if a in recording.u_V})
    write_csv(path, cols)
