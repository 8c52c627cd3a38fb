"""Learned wave tables (``*.afmwave``): a table of voltages learned from the scanner's
measured motion (``afmctl learn``), and the conditions it was learned under.

A learned table is only right for the trajectory, amplifier and models it was learned
with: played with other limits, another loop rate or changed model files it would put the
tip somewhere else. The file therefore keeps, beside the rows of the
:class:`afmctl.control.wave_plan.WaveTable`, a *fingerprint* of what it was learned for —
the trajectory spec and a hash of its target rows, the axes, loop rate, amplifier driver,
voltage limits [V] and slew limit [V/s], and a SHA-256 of every model file the
configuration names — and :func:`check_matches` refuses with one line naming the first
thing that differs. ``[trajectory] kind = "learned"`` plays such a file through
``afmctl run`` (``amplifier.output = "wave"``).

The file is a NumPy ``.npz`` archive (no pickles): arrays ``target_nm``, ``corrected_nm``,
``drift_nm``, ``u_V`` (N, 3) and ``T_C`` (N,), ``meta_json`` (the fingerprint, ``pad``
rows and the learning history as JSON text) and, learned with a creep model,
``history_after_nm`` (D, N, 3) with ``history_after_s`` and ``ended_unix_s`` in the meta
(:mod:`afmctl.control.learned_after`).
"""
from __future__ import annotations

import hashlib
import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config import DEFAULT_SETTLE_S
from ..errors import AfmctlError
from .learned_after import AS_RECORDED_FRESH_S, AsRecorded, HistoryAfter, corrected_for_history
from .wave_plan import WaveTable

#: file format version written into ``meta_json``
FORMAT = 1
_ARRAYS = ("target_nm", "corrected_nm", "drift_nm", "u_V", "T_C")
#: the optional array of :class:`HistoryAfter`'s terms (D, N, 3) [nm]
AFTER_ARRAY = "history_after_nm"


def _sha256_file(path: Path) -> str:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError as err:
        raise AfmctlError(f"{path}: cannot read the model file ({err.strerror or err})") from None


def target_hash(target_nm: np.ndarray) -> str:
    """SHA-256 of the target rows (float64, C order) — the trajectory a table aims at."""
    return hashlib.sha256(np.ascontiguousarray(target_nm, dtype=np.float64).tobytes()).hexdigest()


def model_files(config: Any) -> dict[str, Path]:
    """The model files ``[compensation]`` names: ``scanner_model``, ``x`` / ``y`` / ``z``
    and a drift parameter file (when ``drift.params`` is a file)."""
    comp = config.compensation
    files: dict[str, Path] = {}
    if comp.scanner_model is not None:
        files["scanner_model"] = Path(comp.scanner_model)
    for axis in "xyz":
        if comp.axis(axis).model is not None:
            files[axis] = Path(comp.axis(axis).model)
    if comp.drift.enabled and comp.drift.params.endswith(".json"):
        files["drift"] = Path(comp.drift.params)
    return files


def fingerprint(config: Any, trajectory: dict[str, Any]) -> dict[str, Any]:
    """What a table is learned for (module docstring) under ``config``; ``trajectory``: the
    spec as a dict (``spec.model_dump(mode="json")``)."""
    comp = config.compensation
    return {
        "axes": list(config.scanner.axes),
        "rate_Hz": float(config.loop.rate_Hz),
        "driver": config.amplifier.driver,
        "limits_V": {a: [float(v) for v in config.limits(a)] for a in sorted(config.scanner.axes)},
        "slew_V_per_s": float(config.slew_V_per_s()),
        "settle_s": None if config.amplifier.settle_s is None else float(config.amplifier.settle_s),
        "models": {name: _sha256_file(p) for name, p in sorted(model_files(config).items())},
        "drift": comp.drift.model_dump(mode="json") if comp.drift.enabled else None,
        "trajectory": trajectory,
    }


@dataclass
class LearnedTable:
    """A learned table, its fingerprint and its learning history (one dict per iteration:
    ``iteration``, ``max_pct``, ``rms_pct`` of the scan range, ...), and ``after``: what
    the learning's plays still add to a play after them
    (:mod:`afmctl.control.learned_after`)."""

    table: WaveTable
    learned_for: dict[str, Any]
    target_sha256: str
    history: list[dict[str, Any]] = field(default_factory=list)
    #: the history term the learning's plays leave after them (a model with a creep stage)
    after: HistoryAfter | None = None
    #: the axes learned on a device from their recordings as they are (no creep stage)
    as_recorded: AsRecorded | None = None

    def trajectory_spec(self) -> dict[str, Any]:
        return dict(self.learned_for["trajectory"])


def make_learned(config: Any, table: WaveTable, trajectory: dict[str, Any],
                 history: list[dict[str, Any]] | None = None, after: HistoryAfter | None = None,
                 as_recorded: AsRecorded | None = None) -> LearnedTable:
    """``table`` as learned for ``config`` and the ``trajectory`` spec (a dict) it plays."""
    return LearnedTable(table, fingerprint(config, trajectory), target_hash(table.target_nm), list(history or []),
                        after, as_recorded)


def save_learned(path: str | Path, learned: LearnedTable) -> Path:
    """Write ``learned`` to ``path`` (``.afmwave``; written to a temporary name, then moved,
    so that a crash never leaves half a table)."""
    path = Path(path)
    t = learned.table
    meta = {"format": FORMAT, "pad": int(t.pad), "learned_for": learned.learned_for,
            "target_sha256": learned.target_sha256, "history": learned.history, "report": list(t.report)}
    if learned.after is not None:
        meta["history_after_s"] = list(learned.after.delays_s)
        meta["ended_unix_s"] = learned.after.ended_unix_s
    if learned.as_recorded is not None:
        meta["as_recorded"] = {"axes": list(learned.as_recorded.axes),
                               "ended_unix_s": learned.as_recorded.ended_unix_s,
                               "rest_s": learned.as_recorded.rest_s}
    tmp = path.with_name(path.name + ".part")
    try:
        # Any: numpy's stubs would match **arrays against savez's allow_pickle: bool
        arrays: dict[str, Any] = {name: np.asarray(getattr(t, name), dtype=np.float64) for name in _ARRAYS}
        if learned.after is not None:
            arrays[AFTER_ARRAY] = np.asarray(learned.after.term_nm, dtype=np.float64)
        with open(tmp, "wb") as fh:
            np.savez(fh, meta_json=np.array(json.dumps(meta)), **arrays)
        tmp.replace(path)
    except OSError as err:
        raise AfmctlError(f"{path}: cannot write the learned table ({err.strerror or err})") from None
    return path


def load_learned(path: str | Path) -> LearnedTable:
    """Read a ``.afmwave`` file; anything wrong with it is one :class:`AfmctlError` line
    naming the file."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {name: np.array(z[name], dtype=np.float64) for name in _ARRAYS}
            after_nm = np.array(z[AFTER_ARRAY], dtype=np.float64) if AFTER_ARRAY in z.files else None
            meta = json.loads(str(z["meta_json"]))
    except FileNotFoundError:
        raise AfmctlError(f"{path}: no such learned table (write one with afmctl learn)") from None
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError) as err:
        raise AfmctlError(f"{path}: not a learned table (.afmwave from afmctl learn): {err}") from None
    n = len(arrays["u_V"])
    shapes_ok = all(arrays[a].shape == (n, 3) for a in _ARRAYS[:4]) and arrays["T_C"].shape == (n,)
    if n == 0 or not shapes_ok or not all(np.all(np.isfinite(v)) for v in arrays.values()):
        raise AfmctlError(f"{path}: the table's arrays must be finite, (N, 3) per row and N >= 1")
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise AfmctlError(f"{path}: learned-table format {meta.get('format') if isinstance(meta, dict) else '?'}"
                          f" is not {FORMAT} (relearn with this afmctl)")
    pad = int(meta.get("pad", -1))
    if not 0 <= 2 * pad < n:
        raise AfmctlError(f"{path}: pad {pad} rows does not fit a table of {n} rows")
    table = WaveTable(arrays["target_nm"], arrays["corrected_nm"], arrays["drift_nm"], arrays["u_V"],
                      arrays["T_C"], pad, list(meta.get("report", [])))
    return LearnedTable(table, dict(meta["learned_for"]), str(meta["target_sha256"]), list(meta.get("history", [])),
                        _after(path, after_nm, meta, n), _as_recorded(path, meta))


def _as_recorded(path: Path, meta: dict[str, Any]) -> AsRecorded | None:
    """The file's :class:`AsRecorded` (None when it has none); one line naming the file when
    it is malformed."""
    entry = meta.get("as_recorded")
    if entry is None:
        return None
    try:
        axes = tuple(str(a) for a in entry["axes"])
        ended = float(entry["ended_unix_s"])
        rest = float(entry.get("rest_s", 0.0))
    except (KeyError, TypeError, ValueError, AttributeError):
        raise AfmctlError(f"{path}: as_recorded must hold axes and ended_unix_s") from None
    if not set(axes) <= set("xyz") or not np.isfinite(ended):
        raise AfmctlError(f"{path}: as_recorded: axes must be of x, y, z and ended_unix_s finite")
    if not 0.0 <= rest <= AS_RECORDED_FRESH_S:
        raise AfmctlError(f"{path}: as_recorded: rest_s must be 0 to {AS_RECORDED_FRESH_S:g} s, not {rest:g}")
    return AsRecorded(axes, ended, rest)


def _after(path: Path, term_nm: np.ndarray | None, meta: dict[str, Any], n: int) -> HistoryAfter | None:
    """The file's :class:`HistoryAfter` (None when it keeps none); one line naming the file
    when it is malformed."""
    if term_nm is None:
        return None
    try:
        delays = tuple(float(d) for d in meta["history_after_s"])
        ended = float(meta["ended_unix_s"])
    except (KeyError, TypeError, ValueError):
        raise AfmctlError(f"{path}: {AFTER_ARRAY} without history_after_s and ended_unix_s in its meta") from None
    ok = (term_nm.shape == (len(delays), n, 3) and len(delays) >= 1 and np.all(np.isfinite(term_nm))
          and all(b > a for a, b in zip(delays, delays[1:])) and np.isfinite(ended))
    if not ok:
        raise AfmctlError(f"{path}: {AFTER_ARRAY} must be finite, (delays, N, 3) with rising delays")
    return HistoryAfter(delays, term_nm, ended)


def learned_settle_s(learned: LearnedTable) -> float:
    """The settle hold [s] a table was learned with (files from before it was recorded
    were learned with the 0.2 s default)."""
    settle = learned.learned_for.get("settle_s")
    return DEFAULT_SETTLE_S if settle is None else float(settle)


def _differs(name: str, was: Any, now: Any) -> str:
    return f"{name} was {was} when the table was learned, the configuration now has {now}"


def check_matches(path: str | Path, learned: LearnedTable, now: dict[str, Any], target_nm: np.ndarray) -> None:
    """Refuse (one line naming ``path`` and the first difference) a learned table whose
    fingerprint differs from ``now`` (:func:`fingerprint` of the present configuration) or
    whose target rows are not ``target_nm`` (the trajectory regenerated now, padded)."""
    was = learned.learned_for
    for key, label in (("axes", "scanner.axes"), ("rate_Hz", "loop.rate_Hz"), ("driver", "amplifier.driver"),
                       ("limits_V", "the voltage limits [V]"), ("slew_V_per_s", "the slew limit [V/s]"),
                       ("drift", "compensation.drift")):
        if was.get(key) != now.get(key):
            raise AfmctlError(f"{path}: {_differs(label, was.get(key), now.get(key))}; relearn (afmctl learn)")
    # the hold before each play sets the creep the table meets (an unset one plays the
    # table's own: LearnedSource.settle_s)
    settle_was = learned_settle_s(learned)
    if now.get("settle_s") is not None and settle_was != now["settle_s"]:
        raise AfmctlError(f"{path}: {_differs('amplifier.settle_s [s]', settle_was, now['settle_s'])}; "
                          "relearn (afmctl learn)")
    for name in sorted(set(was.get("models", {})) | set(now.get("models", {}))):
        a, b = was.get("models", {}).get(name), now.get("models", {}).get(name)
        if a != b:
            what = "changed" if a and b else ("added" if b else "removed")
            raise AfmctlError(f"{path}: the {name} model file was {what} since the table was learned; "
                              "relearn (afmctl learn)")
    if target_hash(target_nm) != learned.target_sha256 or target_hash(learned.table.target_nm) != learned.target_sha256:
        raise AfmctlError(f"{path}: the trajectory {was.get('trajectory')} no longer gives the rows the table was "
                          "learned for; relearn (afmctl learn)")


class LearnedSource:
    """A learned table as the controller's trajectory source: :meth:`blocks_at` gives the
    rows it aims at (the trajectory without the table's padding), and the wave machine
    plays :meth:`table_for` instead of planning a table (``[trajectory] kind = "learned"``).

    ``learned``: the table; ``path``: where it came from (named in every refusal)."""

    def __init__(self, learned: LearnedTable, path: str | Path = "learned table") -> None:
        self.learned = learned
        self.path = str(path)

    @classmethod
    def from_file(cls, path: str | Path) -> "LearnedSource":
        return cls(load_learned(path), path)

    def settle_s(self, config: Any) -> float:
        """The hold before the table [s]: ``amplifier.settle_s`` when the configuration sets
        it (:meth:`table_for` refuses one that differs from the learning's), else the hold
        the table was learned with."""
        return config.amplifier.hold_s(unset=learned_settle_s(self.learned))

    def targets_nm(self) -> np.ndarray:
        """The trajectory's rows (N, 3) [nm], without the padding."""
        t = self.learned.table
        return t.target_nm[t.pad:len(t) - t.pad]

    def blocks_at(self, dt_s: float, block_samples: int = 256):
        from ..inputs.trajectories import blocks_of
        rate = self.learned.learned_for.get("rate_Hz")
        if rate is None or abs(1.0 / float(rate) - dt_s) > 1e-12 * max(1.0, dt_s):
            raise AfmctlError(f"{self.path}: learned at loop.rate_Hz = {rate}, the configuration now runs "
                              f"at {1.0 / dt_s:g} Hz; relearn (afmctl learn)")
        return blocks_of(self.targets_nm(), block_samples)

    def table_for(self, config: Any) -> WaveTable:
        """The learned table, when the present configuration matches what it was learned for
        (the player then checks every row against its limits and slew, as for any table)."""
        from ..inputs.trajectories import build, collect
        from .wave_plan import padded
        learned = self.learned
        now = fingerprint(config, learned.trajectory_spec())
        try:
            regenerated = collect(build(learned.trajectory_spec(), config.dt_s))
        except AfmctlError as err:
            raise AfmctlError(f"{self.path}: its trajectory cannot be regenerated: {err}") from None
        check_matches(self.path, learned, now, padded(regenerated, learned.table.pad))
        return corrected_for_history(learned.table, learned.after, config, as_recorded=learned.as_recorded)
