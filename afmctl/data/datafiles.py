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

    A plain rectangle of numbers (the files afmctl and most instruments write) is parsed in
    one vectorised pass; anything else — quotes, blank cells or lines, ragged rows, words,
    non-finite values — goes through the row-by-row reader, which names the row and column
    of the first problem. Both give the same numbers (``tests/test_datafiles.py``).
    """
    p = Path(path)
    try:
        f = p.open(newline="", encoding="utf-8-sig")  # a spreadsheet's BOM is accepted
    except OSError as err:
        raise AfmctlError(f"{p}: cannot open ({err.strerror})") from None
    with f:
        try:
            header_line = f.readline()
            body = f.read()
        except UnicodeDecodeError as err:
            raise AfmctlError(f"{p}: not a readable CSV file ({err})") from None
    names, wanted = _header(p, header_line, columns, optional)
    table = _plain_table(body, len(names))
    if table is None:
        arr = _careful_rows(p, header_line + body, names, wanted)
        out = {c: arr[:, k].copy() for k, c in enumerate(wanted)}
    else:
        out = {c: table[:, names.index(c)].copy() for c in wanted}
    n_rows = next(iter(out.values())).shape[0]
    if n_rows < min_rows:
        raise AfmctlError(f"{p}: {n_rows} data row(s); at least {min_rows} required")
    if time_column is not None and time_column in out and n_rows > 1:
        _check_time(p, out[time_column], time_column, strictly_increasing)
    return out


def _header(p: Path, header_line: str, columns: Sequence[str],
            optional: Sequence[str]) -> tuple[list[str], list[str]]:
    """The header's column names and the wanted ones (``columns`` + present ``optional``)."""
    try:
        header = next(csv.reader([header_line]), []) if header_line else None
    except csv.Error as err:
        raise AfmctlError(f"{p}: not a readable CSV file ({err})") from None
    if header is None:
        raise AfmctlError(f"{p}: empty file; expected a header row with columns {','.join(columns)}")
    names = [h.strip() for h in header]
    missing = [c for c in columns if c not in names]
    if missing:
        raise AfmctlError(f"{p}: missing column(s) {','.join(missing)}; header has {','.join(names) or '(nothing)'}; "
                          f"required: {','.join(columns)}")
    return names, list(columns) + [c for c in optional if c in names]


def _plain_table(body: str, n_cols: int) -> np.ndarray | None:
    """``body`` as an (rows, n_cols) array when it is a plain rectangle of finite numbers:
    every line ``n_cols − 1`` commas, no quotes, every cell one number. None otherwise."""
    import warnings
    if not body or '"' in body or "x" in body or "X" in body:
        return None                                         # quotes; C's strtod would read hex
    raw = np.frombuffer(body.encode("utf-8"), dtype=np.uint8)
    ends = np.flatnonzero(raw == ord("\n"))
    if ends.size == 0 or ends[-1] != raw.size - 1:
        ends = np.append(ends, raw.size)                    # a last line without its newline
    commas = np.flatnonzero(raw == ord(","))              # each line's commas: those before its end
    per_line = np.diff(np.concatenate([[0], np.searchsorted(commas, ends)]))
    if per_line.size == 0 or np.any(per_line != n_cols - 1):
        return None                                         # ragged rows or blank lines
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            values = np.fromstring(body.replace(",", " "), dtype=np.float64, sep=" ")
        except (DeprecationWarning, ValueError):
            return None                                     # a cell that is not a number
    if values.size != per_line.size * n_cols or not np.all(np.isfinite(values)):
        return None
    return values.reshape(per_line.size, n_cols)


def _careful_rows(p: Path, text: str, names: list[str], wanted: list[str]) -> np.ndarray:
    """Row by row, the wanted columns; the first problem raised with its row and column."""
    import io
    reader = csv.reader(io.StringIO(text, newline=""))
    next(reader)
    idx = {c: names.index(c) for c in wanted}
    rows: list[list[float]] = []
    try:
        for lineno, row in enumerate(reader, start=2):
            if not row or all(not cell.strip() for cell in row):
                continue
            rows.append([_cell(p, lineno, c, row, idx[c]) for c in wanted])
    except csv.Error as err:
        raise AfmctlError(f"{p}: not a readable CSV file ({err})") from None
    return np.array(rows, dtype=np.float64).reshape(len(rows), len(wanted))


def _cell(p: Path, lineno: int, c: str, row: list[str], j: int) -> float:
    if j >= len(row):
        raise AfmctlError(f"{p}: row {lineno}: column {c} is missing")
    cell = row[j].strip()
    try:
        v = float(cell)
    except ValueError:
        raise AfmctlError(f"{p}: row {lineno}: column {c}: {cell!r} is not a number") from None
    if not math.isfinite(v):
        raise AfmctlError(f"{p}: row {lineno}: column {c}: {cell!r} is not finite; values must be finite numbers")
    return v


def _check_time(p: Path, t: np.ndarray, name: str, strictly_increasing: bool) -> None:
    d = np.diff(t)
    bad = np.flatnonzero(d <= 0) if strictly_increasing else np.flatnonzero(d < 0)
    if bad.size:
        i = int(bad[0])
        raise AfmctlError(f"{p}: column {name}: time must be strictly increasing; "
                          f"row {i + 3} ({float(t[i + 1])!r}) follows {float(t[i])!r}")


#: rows :func:`write_csv` formats at a time
WRITE_ROWS = 65536


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
            csv.writer(f).writerow(names)
            for k in range(0, n.pop(), WRITE_ROWS):     # the rows csv.writer would write, a block at a time
                cells = [map(repr, a[k:k + WRITE_ROWS].tolist()) for a in arrays]
                f.write("".join(",".join(row) + "\r\n" for row in zip(*cells)))
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
