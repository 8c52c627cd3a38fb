"""CSV data files of the command line (see docs/ARCHITECTURE.md, "Files").

* data:    ``t,u,y``      (s, V, nm)
* target:  ``t,y``        (s, nm)
* volts:   ``t,u`` or ``t,ux,uy,uz``  (s, V)
* temperature: ``t,T``    (s, °C)
* drift:   ``t,x,y,z``    (s, nm)

A header row is required; extra columns are ignored. Every problem raises
:class:`~afmctl.errors.AfmctlError` with one line naming the file, the column and the row.
"""
from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..errors import AfmctlError


def read_csv(path: str | Path, columns: Sequence[str], *, min_rows: int = 1,
             time_column: str | None = "t", strictly_increasing: bool = True,
             optional: Sequence[str] = ()) -> dict[str, np.ndarray]:
    """Read the named columns of a CSV file as float64 arrays.

    ``columns`` must all be present; ``optional`` columns are returned when present.
    Values must be finite numbers. If ``time_column`` is given, it must be strictly
    increasing (or non-decreasing when ``strictly_increasing`` is false).
    """
    p = Path(path)
    try:
        f = p.open(newline="", encoding="utf-8-sig")  # a spreadsheet's BOM is accepted
    except OSError as err:
        raise AfmctlError(f"{p}: cannot open ({err.strerror})") from None
    with f:
        reader = csv.reader(f)
        try:
            header = next(reader)
        except StopIteration:
            raise AfmctlError(f"{p}: empty file; expected a header row with columns {','.join(columns)}") from None
        except (csv.Error, UnicodeDecodeError) as err:
            raise AfmctlError(f"{p}: not a readable CSV file ({err})") from None
        names = [h.strip() for h in header]
        missing = [c for c in columns if c not in names]
        if missing:
            raise AfmctlError(f"{p}: missing column(s) {','.join(missing)}; header has {','.join(names) or '(nothing)'}; "
                              f"required: {','.join(columns)}")
        wanted = list(columns) + [c for c in optional if c in names]
        idx = {c: names.index(c) for c in wanted}
        rows: list[list[float]] = []
        try:
            for lineno, row in enumerate(reader, start=2):
                if not row or all(not cell.strip() for cell in row):
                    continue
                vals = []
                for c in wanted:
                    j = idx[c]
                    if j >= len(row):
                        raise AfmctlError(f"{p}: row {lineno}: column {c} is missing")
                    cell = row[j].strip()
                    try:
                        v = float(cell)
                    except ValueError:
                        raise AfmctlError(f"{p}: row {lineno}: column {c}: {cell!r} is not a number") from None
                    if not math.isfinite(v):
                        raise AfmctlError(f"{p}: row {lineno}: column {c}: {cell!r} is not finite; values must be finite numbers")
                    vals.append(v)
                rows.append(vals)
        except (csv.Error, UnicodeDecodeError) as err:
            raise AfmctlError(f"{p}: not a readable CSV file ({err})") from None
    if len(rows) < min_rows:
        raise AfmctlError(f"{p}: {len(rows)} data row(s); at least {min_rows} required")
    arr = np.array(rows, dtype=np.float64).reshape(len(rows), len(wanted))
    out = {c: arr[:, k].copy() for k, c in enumerate(wanted)}
    if time_column is not None and time_column in out and len(rows) > 1:
        d = np.diff(out[time_column])
        bad = np.flatnonzero(d <= 0) if strictly_increasing else np.flatnonzero(d < 0)
        if bad.size:
            i = int(bad[0])
            raise AfmctlError(f"{p}: column {time_column}: time must be strictly increasing; "
                              f"row {i + 3} ({float(out[time_column][i + 1])!r}) follows {float(out[time_column][i])!r}")
    return out


def write_csv(path: str | Path, columns: Mapping[str, np.ndarray]) -> None:
    """Write equal-length arrays as a CSV with a header (full float precision)."""
    names = list(columns)
    arrays = [np.asarray(columns[c], dtype=np.float64) for c in names]
    n = {a.shape[0] for a in arrays}
    if len(n) != 1:
        raise ValueError("write_csv: columns of different lengths")
    p = Path(path)
    try:
        with p.open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(names)
            for row in zip(*arrays):
                w.writerow([repr(float(v)) for v in row])
    except OSError as err:
        raise AfmctlError(f"{p}: cannot write ({err.strerror})") from None


def uniform_period(t_s: np.ndarray, where: str, rel_tol: float = 1e-3) -> float:
    """The sample period of a uniformly sampled time column, or an error naming ``where``."""
    if t_s.shape[0] < 2:
        raise AfmctlError(f"{where}: column t: at least 2 rows are needed to know the sample period")
    d = np.diff(t_s)
    dt = float(np.median(d))
    if np.max(np.abs(d - dt)) > rel_tol * dt:
        raise AfmctlError(f"{where}: column t: samples must be uniformly spaced for this model "
                          f"(period {dt:g} s; found steps from {d.min():g} to {d.max():g} s)")
    return dt
