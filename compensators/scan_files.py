"""Scan files for image-based identification (``afmctl identify --from-images``) and for drift
measurement (``afmctl drift measure``).

Two kinds of input:

* the simulator's ``.npz`` layout (arrays of :data:`~afmctl.compensators.image_identify.REQUIRED_ARRAYS`,
  written by ``afmctl.sim_backend.image_scans``), read by :func:`load_scans_npz`;
* AFM image files, one scan range per file, read with the formats' own libraries:
  Gwyddion ``.gwy`` (gwyfile), Gwyddion Simple Field ``.gsf`` (gsffile), TIFF ``.tif/.tiff``
  (tifffile), Asylum Research Igor binary wave ``.ibw`` (igor2), Bruker Nanoscope v5–v9
  ``.spm`` / ``.000``–``.999`` (Gwyddion's Nanoscope importer, through gwyddionpy). Trace and
  retrace channels, the scan size [nm] and the line rate [Hz] come from the file's metadata
  (see :func:`read_scan_image`).

An image file does not record the voltages of its pixels: the scan's lowest voltage
``scan_u_min_V`` and the nominal gain ``gain_nm_per_V`` (with which the instrument turned
voltages into its scan size) give pixel i of a line of P pixels the voltage
``u_min + i·(scan_size / gain)/(P − 1)``, the ramp of the simulator's scans.
"""
from __future__ import annotations

import logging
import re
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .base import ModelError
from .input_checks import number_option

log = logging.getLogger(__name__)

#: suffixes of the image files read (Nanoscope files also as ``.000``–``.999``: :func:`is_image_file`)
IMAGE_SUFFIXES = (".gwy", ".gsf", ".tif", ".tiff", ".ibw", ".spm")
_NANOSCOPE_NUMBERED = re.compile(r"^\.\d{3}$")
_RATE_KEYS = re.compile(r"(line|scan)[ _]?rate", re.IGNORECASE)


@dataclass
class ScanImage:
    """One AFM image: heights [nm] as (lines, pixels); retrace may be absent."""

    path: str
    trace_nm: np.ndarray
    retrace_nm: np.ndarray | None
    scan_size_nm: float
    line_rate_Hz: float | None
    #: extent along the slow axis [nm]; None: square pixels
    scan_height_nm: float | None = None
    #: the file holds only a retrace channel, given as ``trace_nm`` (enough for drift measurement)
    only_retrace: bool = False

    def pixel_nm(self) -> tuple[float, float]:
        """Pixel size ``(along y / rows, along x / columns)`` [nm]."""
        lines, px = self.trace_nm.shape
        pxx = self.scan_size_nm / px
        return (self.scan_height_nm / lines if self.scan_height_nm else pxx), pxx


def load_scans_npz(path: str | Path) -> dict[str, np.ndarray]:
    """Read a simulator scan file (``GratingScans.save_npz`` or the same arrays by hand);
    :class:`ModelError` with the file name for anything unreadable or incomplete."""
    from .image_identify import check_scans

    p = Path(path)
    try:
        with np.load(p, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except FileNotFoundError:
        raise ModelError(f"{p}: no such scan file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as err:
        # truncated or corrupted archives fail in zipfile/zlib, not with an OSError
        raise ModelError(f"{p}: not a readable .npz scan file ({err})") from None
    try:
        check_scans(data)
    except ModelError as err:
        raise ModelError(f"{p}: {err}") from None
    return data


def is_image_file(path: str | Path) -> bool:
    """True for the suffixes :func:`read_scan_image` reads (:data:`IMAGE_SUFFIXES`, ``.000``–``.999``)."""
    suffix = Path(path).suffix.lower()
    return suffix in IMAGE_SUFFIXES or bool(_NANOSCOPE_NUMBERED.match(suffix))


def read_scan_image(path: str | Path) -> ScanImage:
    """Read one AFM image file by its suffix (:data:`IMAGE_SUFFIXES`; Nanoscope also ``.000``–``.999``)."""
    p = Path(path)
    suffix = p.suffix.lower()
    readers = {".gwy": _read_gwy, ".gsf": _read_gsf, ".tif": _read_tiff, ".tiff": _read_tiff, ".ibw": _read_ibw,
               ".spm": _read_nanoscope}
    if _NANOSCOPE_NUMBERED.match(suffix):
        readers[suffix] = _read_nanoscope
    if suffix not in readers:
        raise ModelError(f"{p}: unknown image format {suffix!r}; allowed: {', '.join(IMAGE_SUFFIXES)}, "
                         ".000–.999 (Nanoscope), .npz")
    if not p.is_file():
        raise ModelError(f"{p}: no such image file")
    try:
        img = readers[suffix](p)
    except ModelError as err:
        raise ModelError(f"{p}: {err}") from None
    except Exception as err:  # noqa: BLE001 - a format library's own error on a damaged file
        detail = " ".join(str(err).split())[:300]   # one line: library messages may span several
        raise ModelError(f"{p}: not a readable {suffix} file ({type(err).__name__}: {detail})") from None
    for name, arr in (("trace", img.trace_nm), ("retrace", img.retrace_nm)):
        if arr is not None and (arr.ndim != 2 or arr.shape[1] < 8 or not np.all(np.isfinite(arr))):
            raise ModelError(f"{p}: {name} channel: expected finite heights of shape (lines, pixels ≥ 8), "
                             f"got {arr.shape}")
    if not (np.isfinite(img.scan_size_nm) and img.scan_size_nm > 0):
        raise ModelError(f"{p}: scan size: {img.scan_size_nm!r} nm; must be a positive number")
    return img


def _channel_role(title: str) -> str | None:
    t = title.lower()
    if "retrace" in t or "backward" in t or t.endswith("(bwd)"):
        return "retrace"
    if "trace" in t or "forward" in t or "height" in t or "topography" in t:
        return "trace"
    return None


def _rate_from(meta: dict[str, Any]) -> float | None:
    for key, value in meta.items():
        if _RATE_KEYS.search(str(key)):
            m = re.search(r"[-+]?\d+(\.\d*)?([eE][-+]?\d+)?", str(value))
            if m:
                return float(m.group(0))
    return None


def _read_gwy(p: Path) -> ScanImage:
    import gwyfile

    obj = gwyfile.load(str(p))
    fields = {}
    for key, title in gwyfile.util.find_datafields(obj):
        role = _channel_role(str(title))
        if role and role not in fields:
            fields[role] = (key, obj[f"/{key}/data"])
    if "trace" not in fields:
        raise ModelError("no trace channel (a channel titled '… trace', 'forward' or 'height')")
    key, tr = fields["trace"]
    meta = obj.get(f"/{key}/meta", {}) or {}
    scale = _si_to_nm(tr.si_unit_z.unitstr if "si_unit_z" in tr else "m")
    retrace = fields.get("retrace", (None, None))[1]
    return ScanImage(str(p), np.asarray(tr.data, dtype=np.float64) * scale,
                     None if retrace is None else np.asarray(retrace.data, dtype=np.float64) * scale,
                     float(tr.xreal) * _si_to_nm(tr.si_unit_xy.unitstr if "si_unit_xy" in tr else "m"),
                     _rate_from(dict(meta)),
                     float(tr.yreal) * _si_to_nm(tr.si_unit_xy.unitstr if "si_unit_xy" in tr else "m"))


def _si_to_nm(unit: str) -> float:
    table = {"m": 1e9, "mm": 1e6, "um": 1e3, "µm": 1e3, "nm": 1.0, "pm": 1e-3, "": 1e9}
    if unit not in table:
        raise ModelError(f"unit {unit!r}: a length unit is needed (m, µm, nm)")
    return table[unit]


def _read_gsf(p: Path) -> ScanImage:
    import gsffile

    data, meta = gsffile.read_gsf(p)
    xy = _si_to_nm(str(meta.get("XYUnits", "m")))
    z = _si_to_nm(str(meta.get("ZUnits", "m")))
    retrace = None
    if "retrace" not in p.name.lower() and "trace" in p.name.lower():
        sib = p.with_name(re.sub("trace", "retrace", p.name, count=1, flags=re.IGNORECASE))
        if sib.is_file():
            retrace = np.asarray(gsffile.read_gsf(sib)[0], dtype=np.float64) * z
    return ScanImage(str(p), np.asarray(data, dtype=np.float64) * z, retrace, float(meta["XReal"]) * xy,
                     _rate_from(meta), float(meta["YReal"]) * xy if "YReal" in meta else None)


def _read_tiff(p: Path) -> ScanImage:
    """Pages: trace, then retrace; heights and the scan size per the JSON description that
    tifffile writes (``scan_size_nm``, ``line_rate_Hz``, ``z_unit``)."""
    import tifffile

    with tifffile.TiffFile(p) as tif:
        pages = [np.asarray(pg.asarray(), dtype=np.float64) for pg in tif.pages]
        meta = tif.shaped_metadata[0] if tif.shaped_metadata else {}
    if "scan_size_nm" not in meta:
        raise ModelError("no 'scan_size_nm' in the TIFF description (tifffile JSON metadata)")
    z = _si_to_nm(str(meta.get("z_unit", "nm")))
    if pages and pages[0].ndim == 3:  # one page holding (channels, lines, pixels)
        pages = list(pages[0])
    h = meta.get("scan_size_y_nm")
    return ScanImage(str(p), pages[0] * z, pages[1] * z if len(pages) > 1 else None,
                     float(meta["scan_size_nm"]), _rate_from(meta), None if h is None else float(h))


def scans_from_images(paths: list[str | Path], *, gain_nm_per_V: Any, period_nm: Any, scan_u_min_V: Any = 0.0,
                      skip_lines: Any = 1) -> dict[str, Any]:
    """Image files (one scan range each) → the arrays of the ``.npz`` scan layout."""
    gain = number_option("gain_nm_per_V", gain_nm_per_V, lo=1e-6, hi=1e6)
    period = number_option("period_nm", period_nm, lo=1e-3, hi=1e7)
    lo = number_option("scan_u_min_V", scan_u_min_V, lo=-1000.0, hi=1000.0)
    images = [read_scan_image(p) for p in paths]
    px = {im.trace_nm.shape for im in images}
    if len(px) != 1:
        raise ModelError(f"{paths[0]}: all images must have the same lines × pixels; got {sorted(px)}")
    ramps, retraces = [], []
    for im in images:
        if im.only_retrace:
            raise ModelError(f"{im.path}: only a retrace channel in the file; image identification needs the "
                             "trace and the retrace of each line")
        if im.retrace_nm is None or im.retrace_nm.shape != im.trace_nm.shape:
            raise ModelError(f"{im.path}: no retrace channel of the trace's shape; both are needed")
        retraces.append(im.retrace_nm[:, ::-1])
        ramps.append(np.linspace(lo, lo + im.scan_size_nm / gain, im.trace_nm.shape[1]))
    ut = np.array(ramps)
    rates = [im.line_rate_Hz for im in images if im.line_rate_Hz is not None]
    return {"period_nm": np.float64(period), "u_trace_V": ut, "u_retrace_V": ut[:, ::-1].copy(),
            "trace_nm": np.array([im.trace_nm for im in images]),
            "retrace_nm": np.array(retraces),
            "skip_lines": np.int64(number_option("skip_lines", skip_lines, lo=0, integer=True)),
            "line_rate_Hz": np.float64(rates[0] if rates else np.nan)}


def identify_from_scan_files(paths: list[str | Path], kind: str = "preisach", n_operators: int | None = None,
                             **options: Any):
    """``afmctl identify --from-images``: one ``.npz`` scan file, or image files (one scan
    range each; options ``gain_nm_per_V``, ``period_nm``, ``scan_u_min_V``, ``skip_lines``)."""
    from .image_identify import identify_from_images

    where = str(paths[0])
    if len(paths) == 1 and str(paths[0]).lower().endswith(".npz"):
        data = load_scans_npz(paths[0])
    else:
        keys = ("gain_nm_per_V", "period_nm", "scan_u_min_V", "skip_lines")
        missing = [k for k in keys[:2] if k not in options]
        if missing:
            raise ModelError(f"{where}: image files need --param {missing[0]}=… (nominal gain nm/V of the scan "
                             "size, grating period nm)")
        data = scans_from_images(list(paths), **{k: options.pop(k) for k in keys if k in options})
    try:
        return identify_from_images(data, kind=kind, n_operators=n_operators, **options)
    except TypeError as err:
        raise ModelError(f"{where}: option not accepted by the image-based identification of {kind!r} ({err})") from None
    except ModelError as err:
        raise ModelError(f"{where}: {err}") from None
    except ValueError as err:  # incl. numpy.linalg.LinAlgError; e.g. an option value of the wrong type
        raise ModelError(f"{where}: the image-based identification failed ({err})") from None


def _asylum_note(note: str) -> dict[str, str]:
    """The ``key: value`` lines of an Asylum wave note (carriage-return or newline separated)."""
    meta = {}
    for line in re.split(r"[\r\n]+", note):
        key, sep, value = line.partition(":")
        if sep:
            meta[key.strip()] = value.strip()
    return meta


def _read_ibw(p: Path) -> ScanImage:
    """Asylum Research ``.ibw``: one 3-D wave (scan points, scan lines, layers) in m, the layer
    names (HeightTrace, HeightRetrace, ...) in the labels of dimension 2, and ``ScanSize`` [m],
    ``ScanRate`` [Hz] (lines per second), optionally ``SlowScanSize`` [m] as ``key: value`` lines in the wave note."""
    from igor2 import binarywave

    wave = binarywave.load(str(p))["wave"]
    data = np.asarray(wave["wData"], dtype=np.float64)
    if data.ndim == 2:
        data = data[:, :, None]
    if data.ndim != 3:
        raise ModelError(f"wave of {data.ndim} dimensions; an Asylum image is (points, lines, layers)")
    labels = [lb.decode("latin-1") if isinstance(lb, bytes) else str(lb) for lb in wave["labels"][2]]
    labels = labels[1:] if len(labels) == data.shape[2] + 1 else labels  # entry 0 names the dimension
    layers: dict[str, np.ndarray] = {}
    for k, name in enumerate(labels[: data.shape[2]]):
        role = _channel_role(name)
        if role and role not in layers and "height" in name.lower():
            layers[role] = data[:, :, k].T  # Igor column-major (points, lines) -> (lines, pixels)
    if "trace" not in layers:
        raise ModelError(f"no HeightTrace layer (layers: {', '.join(labels) or 'none'})")
    note = wave.get("note", b"")
    meta = _asylum_note(note.decode("latin-1") if isinstance(note, bytes) else str(note))
    if "ScanSize" not in meta:
        raise ModelError("no 'ScanSize' line in the wave note")
    size_nm = float(meta["ScanSize"]) * 1e9
    height = float(meta["SlowScanSize"]) * 1e9 if "SlowScanSize" in meta else None  # else square pixels
    rate = float(meta["ScanRate"]) if "ScanRate" in meta else None
    retrace = layers.get("retrace")
    return ScanImage(str(p), layers["trace"] * 1e9, None if retrace is None else retrace * 1e9, size_nm, rate, height)


#: longest time the Gwyddion converter may take for one Nanoscope file [s]
_NANOSCOPE_TIMEOUT_S = 120.0
#: Nanoscope height channels (``\@2:Image Data`` names), the first present is read
_NANOSCOPE_HEIGHTS = ("Height Sensor", "Height")


def _meta_value(meta: dict[str, str], key: str) -> str | None:
    """A header value by its key, ignoring case and a ``n:`` group prefix (``2:Image Data``)."""
    want = key.lower()
    for k, v in meta.items():
        if k.lower() == want or k.lower().partition(":")[2] == want:
            return v.strip().strip('"')
    return None


def _read_nanoscope(p: Path) -> ScanImage:
    """Bruker Nanoscope v5–v9 (``.spm``, ``.000``…): the image data decoded (and scaled to m) by
    Gwyddion's Nanoscope importer through gwyddionpy; per channel its header fields
    ``\\@2:Image Data`` (height channel: "Height Sensor", else "Height"), ``\\Line Direction``
    (Trace / Retrace), ``\\Scan Size`` (→ ``xreal``, ``yreal``) and ``\\Scan Rate`` [Hz, lines per
    second]. Rows top line first (as Gwyddion presents them). The retrace is taken as stored in
    spatial order (left to right) like the trace, as Nanoscope Analysis shows it; no real file
    with both directions was available to confirm this (tests/data/jmarini-nanoscope is retrace only)."""
    install = "pip install 'afmctl[nanoscope]' (Gwyddion's importer; Linux x86-64)"
    try:
        import gwyddionpy
    except ImportError:
        raise ModelError(f"reading Nanoscope files needs gwyddionpy: {install}") from None
    try:
        data = gwyddionpy.load(p, timeout=_NANOSCOPE_TIMEOUT_S)
    except gwyddionpy.ConverterNotFoundError:
        raise ModelError(f"reading Nanoscope files needs Gwyddion's gwyconvert helper: {install}") from None
    found: dict[tuple[str, str], Any] = {}
    for ch in data.channels.values():
        name, direction = _meta_value(ch.meta, "Image Data"), (_meta_value(ch.meta, "Line Direction") or "").lower()
        if name in _NANOSCOPE_HEIGHTS and direction in ("trace", "retrace"):
            found.setdefault((name, direction), ch)
    height = next((h for h in _NANOSCOPE_HEIGHTS if any(k[0] == h for k in found)), None)
    if height is None:
        raise ModelError(f"no height channel ({' or '.join(_NANOSCOPE_HEIGHTS)} with Line Direction Trace/Retrace)")
    trace, retrace = found.get((height, "trace")), found.get((height, "retrace"))
    first: Any = trace if trace is not None else retrace   # one of them is there
    _check_nanoscope_shape(first.meta, np.shape(first.data))
    z, xy = _si_to_nm(first.si_unit_z), _si_to_nm(first.si_unit_xy)
    rate = _meta_value(first.meta, "Scan Rate")
    rate_Hz = None if rate is None else float(rate.split()[0]) if rate.split() else float("nan")
    if rate_Hz is not None and not (np.isfinite(rate_Hz) and rate_Hz > 0):
        raise ModelError(f"Scan Rate: {rate!r}; must be a positive number of Hz")
    return ScanImage(str(p), np.asarray(first.data, dtype=np.float64) * z,
                     None if trace is None or retrace is None else np.asarray(retrace.data, dtype=np.float64) * z,
                     float(first.xreal) * xy, rate_Hz, float(first.yreal) * xy,
                     only_retrace=trace is None)


def _check_nanoscope_shape(meta: dict[str, str], shape: tuple[int, ...]) -> None:
    """The decoded image must have the lines × pixels its header states (``\\Number of lines``,
    ``\\Samps/line``, or the ``\\Valid data len`` pair of a partial capture): a damaged field
    otherwise lets the importer fall back to other header values."""
    def ints(*keys: str) -> set[int]:
        out = set()
        for k in keys:
            v = _meta_value(meta, k)
            if v is not None and v.strip().isdigit():
                out.add(int(v))
        return out

    valid = ints("Valid data len X", "Valid data len Y")
    lines, pixels = ints("Number of lines") | valid, ints("Samps/line") | valid
    if len(shape) != 2 or shape[0] not in lines or shape[1] not in pixels:
        raise ModelError(f"header \\Samps/line {_meta_value(meta, 'Samps/line')!r}, \\Number of lines "
                         f"{_meta_value(meta, 'Number of lines')!r} do not match the decoded image "
                         f"{' × '.join(map(str, shape))}")
