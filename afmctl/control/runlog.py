"""Crash-safe run logs: every setpoint, drift estimate and state change of a run.

File format (``*.afmlog``, little-endian)
------------------------------------------

::

    header:  b"AFMLOG01"  u32 meta_len  u32 crc32(meta)  meta (UTF-8 JSON)
    chunk*:  b"CHNK"  u8 kind  3 zero bytes  u32 payload_len  u32 n_records  u32 crc  payload

    crc = crc32(payload, start=crc32(u8 kind, u32 n_records))

``kind`` 1 = setpoints (numpy records of :data:`SETPOINT_DTYPE`), 2 = drift
(:data:`DRIFT_DTYPE`), 3 = events (UTF-8 JSON array of objects), 4 = end (UTF-8 JSON
``{"setpoints": n}``, written last by :meth:`RunLogWriter.close`: a log without it was not
closed — the process was killed or a write failed — and is reported incomplete by
``RunLogReader.complete``; readers skip kinds they do not know). Chunks are appended
whole by one writer thread and the file is flushed (and by default fsync'ed) at least every
``flush_interval_s`` (≤ 0.1 s). A crash can tear only the last chunk; the reader stops at
the first chunk that is short or fails its CRC and reports where (``RunLogReader.torn``),
so every record flushed before the crash reads back.

Setpoint records: ``seq`` (sample number, uint64), ``t_s`` (controller time since start,
s), ``target_nm`` (3,), ``corrected_nm`` (3,) (target minus drift estimate), ``u_V`` (3,)
(the voltages sent, after the safety layer; 0 on undriven axes).
Drift records: ``seq``, ``t_s``, ``T_C`` (°C), ``drift_nm`` (3,), ``std_nm`` (3,) (the Kalman
filter's standard deviation [nm]; NaN when the filter is off).
Events: ``{"seq", "t_s", "wall_time", "state", "event", "detail"}``.
"""
from __future__ import annotations

import json
import logging
import os
import queue
import struct
import threading
import time
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import AfmctlError

log = logging.getLogger(__name__)

MAGIC = b"AFMLOG01"
CHUNK_MAGIC = b"CHNK"
_HEAD = struct.Struct("<II")          # meta_len, crc
_CHUNK = struct.Struct("<4sB3sIII")    # magic, kind, pad, payload_len, n_records, crc
KIND_SETPOINTS, KIND_DRIFT, KIND_EVENTS, KIND_END = 1, 2, 3, 4
MAX_CHUNK_BYTES = 64 * 1024 * 1024

SETPOINT_DTYPE = np.dtype([("seq", "<u8"), ("t_s", "<f8"), ("target_nm", "<f8", (3,)),
                           ("corrected_nm", "<f8", (3,)), ("u_V", "<f8", (3,))])
DRIFT_DTYPE = np.dtype([("seq", "<u8"), ("t_s", "<f8"), ("T_C", "<f8"), ("drift_nm", "<f8", (3,)),
                        ("std_nm", "<f8", (3,))])
_DTYPES = {KIND_SETPOINTS: SETPOINT_DTYPE, KIND_DRIFT: DRIFT_DTYPE}


def encode_header(meta: dict[str, Any]) -> bytes:
    body = json.dumps(meta, default=str).encode("utf-8")
    return MAGIC + _HEAD.pack(len(body), zlib.crc32(body)) + body


def chunk_crc(kind: int, n_records: int, payload: bytes) -> int:
    """CRC-32 over kind, record count and payload."""
    return zlib.crc32(payload, zlib.crc32(struct.pack("<BI", kind, n_records)))


def encode_chunk(kind: int, payload: bytes, n_records: int) -> bytes:
    return _CHUNK.pack(CHUNK_MAGIC, kind, b"\0\0\0", len(payload), n_records,
                       chunk_crc(kind, n_records, payload)) + payload


class RunLogWriteError(AfmctlError):
    """The run log could not be written (disk full, its directory vanished, ...)."""


class RunLogWriter:
    """Append records from any thread; a writer thread writes chunks and flushes.

    ``write_setpoints`` / ``write_drift`` take structured arrays of the module dtypes (copied
    into the queue as is), ``write_event`` a JSON-able dict. :attr:`flushed` counts the
    setpoint records known to be on disk (flushed). Use as a context manager or call
    :meth:`close` (flushes everything, then writes the end chunk).

    A failed write (an OSError of the file, or the file no longer at :attr:`path` because
    its directory vanished) sets :attr:`error` (a :class:`RunLogWriteError` naming the file
    and the cause); from then on nothing more is written — the file keeps every chunk
    flushed before the error, readable, and no end chunk — and records handed over are
    dropped. A log whose file vanished is copied back to :attr:`path` (its directory
    recreated) when that is possible. The controller polls :attr:`error` and stops the run.
    """

    def __init__(self, path: str | Path, meta: dict[str, Any] | None = None, *,
                 flush_interval_s: float = 0.05, fsync: bool = True,
                 realtime_priority: int | None = None) -> None:
        if not (0 < flush_interval_s <= 0.1):
            raise AfmctlError(f"runlog.flush_interval_s: {flush_interval_s!r} must be in (0, 0.1] s")
        self.path = Path(path)
        self.flush_interval_s = float(flush_interval_s)
        self.fsync = fsync
        self.realtime_priority = realtime_priority
        m = dict(meta or {})
        m.setdefault("format", "afmlog/1")
        m.setdefault("created_wall_time", time.time())
        m["setpoint_dtype"] = SETPOINT_DTYPE.descr
        m["drift_dtype"] = DRIFT_DTYPE.descr
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # unbuffered (every byte written is on the file or the write raised) and readable
            # (a vanished file is copied back)
            self._f = open(self.path, "xb+", buffering=0)
            self._write_all(encode_header(m))
            st = os.fstat(self._f.fileno())
        except OSError as err:
            raise AfmctlError(f"runlog: cannot create {self.path} ({err.strerror or err})") from None
        self._inode = (st.st_dev, st.st_ino)
        self._bytes_ok = self._f.tell()        # bytes known to be whole chunks on disk
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._closed = False
        self.flushed = 0          # setpoint records flushed
        self.written = 0          # setpoint records handed to write()
        self.error: RunLogWriteError | None = None
        self._thread = threading.Thread(target=self._run, name="afmctl-runlog", daemon=True)
        self._thread.start()

    # ---------------------------------------------------------------- producers
    def write_setpoints(self, records: np.ndarray) -> None:
        if len(records) and self.error is None:
            self._q.put((KIND_SETPOINTS, np.ascontiguousarray(records, dtype=SETPOINT_DTYPE)))

    def write_drift(self, records: np.ndarray) -> None:
        if len(records) and self.error is None:
            self._q.put((KIND_DRIFT, np.ascontiguousarray(records, dtype=DRIFT_DTYPE)))

    def write_event(self, event: dict[str, Any]) -> None:
        if self.error is None:
            self._q.put((KIND_EVENTS, event))

    # ---------------------------------------------------------------- writer thread
    def _run(self) -> None:
        if self.realtime_priority is not None:  # see afmctl.control.controller: no GIL priority inversion
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.realtime_priority))
            except (AttributeError, OSError):
                pass
        pending: list[tuple[int, Any]] = []
        next_flush = time.monotonic() + self.flush_interval_s
        stop = False
        while not stop:
            stop = self._collect(pending, max(0.0, next_flush - time.monotonic()))
            if stop or time.monotonic() >= next_flush:
                if self.error is None:
                    self._write_guarded(pending)
                pending = []
                next_flush = time.monotonic() + self.flush_interval_s
        if self.error is None:
            self._write_guarded([(KIND_END, None)])
        try:
            self._f.close()
        except OSError:   # data that could not be flushed: the error is already recorded
            pass

    def _collect(self, pending: list[tuple[int, Any]], timeout_s: float) -> bool:
        """Move queued items into ``pending`` (waiting up to ``timeout_s``); True at close."""
        try:
            item = self._q.get(timeout=timeout_s)
            while True:
                if item is None:
                    return True
                pending.append(item)
                item = self._q.get_nowait()
        except queue.Empty:
            return False

    def _write_guarded(self, items: list[tuple[int, Any]]) -> None:
        """Write ``items``; on failure record :attr:`error` and write nothing more."""
        try:
            self._write(items)
            self._check_still_there()
        except OSError as err:
            self._fail(f"run log {self.path}: write failed ({err.strerror or err}); "
                       f"{self.flushed} setpoint records before it are kept")
        except RunLogWriteError as err:
            self._fail(str(err))

    def _fail(self, message: str) -> None:
        self.error = RunLogWriteError(message)
        log.error("%s", message)
        try:   # cut a torn tail so that the file ends at its last whole chunk
            os.ftruncate(self._f.fileno(), self._bytes_ok)
        except (OSError, ValueError):
            pass

    def _check_still_there(self) -> None:
        """The file must still be :attr:`path` (a removed directory leaves writes succeeding
        into an unlinked file); if it vanished, copy what was written back to the path."""
        try:
            st = os.stat(self.path)
            if (st.st_dev, st.st_ino) == self._inode:
                return
        except OSError:
            pass
        where = "its records could not be saved"
        try:
            data = os.pread(self._f.fileno(), self._bytes_ok, 0)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            where = f"{self.flushed} setpoint records before it were copied back to {self.path}"
        except OSError as err:
            where += f" ({err.strerror or err})"
        raise RunLogWriteError(f"run log {self.path}: the file or its directory vanished; {where}")

    def _write(self, items: list[tuple[int, Any]]) -> None:
        if not items:
            return
        n_sp = 0
        # merge consecutive items of one kind into one chunk
        out = bytearray()
        i = 0
        while i < len(items):
            kind = items[i][0]
            j = i
            while j < len(items) and items[j][0] == kind:
                j += 1
            group = [it[1] for it in items[i:j]]
            if kind == KIND_EVENTS:
                payload = json.dumps(group, default=str).encode("utf-8")
                out += encode_chunk(kind, payload, len(group))
            elif kind == KIND_END:
                out += encode_chunk(kind, json.dumps({"setpoints": self.flushed}).encode("utf-8"), 1)
            else:
                arr = np.concatenate(group) if len(group) > 1 else group[0]
                step = max(1, MAX_CHUNK_BYTES // arr.dtype.itemsize)
                for k in range(0, len(arr), step):
                    part = arr[k:k + step]
                    out += encode_chunk(kind, part.tobytes(), len(part))
                if kind == KIND_SETPOINTS:
                    n_sp += len(arr)
            i = j
        self._write_all(out)
        if self.fsync:
            os.fsync(self._f.fileno())
        self._bytes_ok += len(out)
        self.flushed += n_sp

    def _write_all(self, data: bytes | bytearray) -> None:
        """Write all of ``data`` to the unbuffered file (a short write is continued)."""
        view = memoryview(data)
        while len(view):
            n = self._f.write(view)
            if not n:
                raise OSError(28, "no space left on device (write made no progress)")
            view = view[n:]

    def close(self) -> None:
        """Flush everything queued, write the end chunk and close the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._q.put(None)
        self._thread.join(timeout=10)

    def __enter__(self) -> "RunLogWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RunLogReader:
    """Read a run log written by :class:`RunLogWriter` (or one torn by a crash).

    ``setpoints()`` → structured array of :data:`SETPOINT_DTYPE`, ``drift()`` → of
    :data:`DRIFT_DTYPE`, ``events()`` → list of dicts, ``meta()`` → the header dict.
    ``torn`` is True when reading stopped at a short or corrupt chunk (at byte
    ``valid_bytes``); ``closed`` when the writer's end chunk was read; ``complete`` when
    closed and not torn (a killed writer leaves a log that is not torn, yet not complete).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            data = self.path.read_bytes()
        except OSError as err:
            raise AfmctlError(f"{self.path}: cannot read run log ({err.strerror})") from None
        if len(data) < len(MAGIC) + _HEAD.size or data[:len(MAGIC)] != MAGIC:
            raise AfmctlError(f"{self.path}: not an afmctl run log (missing header {MAGIC!r})")
        meta_len, crc = _HEAD.unpack_from(data, len(MAGIC))
        pos = len(MAGIC) + _HEAD.size
        body = data[pos:pos + meta_len]
        if len(body) != meta_len or zlib.crc32(body) != crc:
            raise AfmctlError(f"{self.path}: run log header is damaged")
        try:
            self._meta = json.loads(body.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise AfmctlError(f"{self.path}: run log header is not valid JSON") from None
        if not isinstance(self._meta, dict):
            raise AfmctlError(f"{self.path}: run log header must be a JSON object, "
                              f"got {type(self._meta).__name__}")
        pos += meta_len
        view = memoryview(data)   # chunk payloads are read without copying
        parts: dict[int, list[np.ndarray]] = {KIND_SETPOINTS: [], KIND_DRIFT: []}
        self._events: list[dict[str, Any]] = []
        self.torn = False
        self.closed = False     # the writer's end chunk was read
        self.n_chunks = 0
        while pos < len(data):
            if pos + _CHUNK.size > len(data):
                self.torn = True
                break
            magic, kind, pad, plen, nrec, ccrc = _CHUNK.unpack_from(data, pos)
            start = pos + _CHUNK.size
            payload = view[start:start + plen]
            if (magic != CHUNK_MAGIC or pad != b"\0\0\0" or len(payload) != plen
                    or chunk_crc(kind, nrec, payload) != ccrc):
                self.torn = True
                break
            if kind in _DTYPES:
                dt = _DTYPES[kind]
                if plen != nrec * dt.itemsize:
                    self.torn = True
                    break
                parts[kind].append(np.frombuffer(payload, dtype=dt))
            elif kind == KIND_EVENTS:
                try:
                    evs = json.loads(bytes(payload).decode("utf-8"))
                except (UnicodeDecodeError, json.JSONDecodeError):
                    evs = None
                if not (isinstance(evs, list) and len(evs) == nrec and all(isinstance(e, dict) for e in evs)):
                    self.torn = True   # a chunk that is not what a writer writes: stop here
                    break
                self._events.extend(evs)
            elif kind == KIND_END:
                self.closed = True
            # unknown kinds are skipped (forward compatible)
            pos = start + plen
            self.n_chunks += 1
        self.valid_bytes = pos
        self._sp = np.concatenate(parts[KIND_SETPOINTS]) if parts[KIND_SETPOINTS] else np.zeros(0, SETPOINT_DTYPE)
        self._dr = np.concatenate(parts[KIND_DRIFT]) if parts[KIND_DRIFT] else np.zeros(0, DRIFT_DTYPE)

    @property
    def complete(self) -> bool:
        """Whether the log was closed by its writer and reads whole to its end."""
        return self.closed and not self.torn

    def meta(self) -> dict[str, Any]:
        return dict(self._meta)

    def setpoints(self) -> np.ndarray:
        return self._sp

    def drift(self) -> np.ndarray:
        return self._dr

    def events(self) -> list[dict[str, Any]]:
        return list(self._events)

    def summary(self) -> dict[str, Any]:
        """Counts, duration, voltage ranges and the states visited."""
        sp = self._sp
        out: dict[str, Any] = {"path": str(self.path), "samples": int(len(sp)), "drift_records": int(len(self._dr)),
                               "events": len(self._events), "torn": self.torn,
                               "complete": self.complete}
        if len(sp):
            out["seq_first"] = int(sp["seq"][0])
            out["seq_last"] = int(sp["seq"][-1])
            out["seq_gaps"] = int(np.count_nonzero(np.diff(sp["seq"].astype(np.int64)) != 1))
            out["duration_s"] = float(sp["t_s"][-1] - sp["t_s"][0])
            out["u_min_V"] = [float(v) for v in sp["u_V"].min(axis=0)]
            out["u_max_V"] = [float(v) for v in sp["u_V"].max(axis=0)]
        if len(self._dr):
            out["drift_max_abs_nm"] = [float(v) for v in np.abs(self._dr["drift_nm"]).max(axis=0)]
        states: list[str] = []
        for e in self._events:
            s = e.get("state")
            s = str(s) if s else None
            if s and (not states or states[-1] != s):
                states.append(s)
        out["states"] = states
        return out
