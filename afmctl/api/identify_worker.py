"""Identification in a process of its own, started while the device still plays (#38).

``afmctl calibrate`` hands an axis's recording to an :class:`IdentifyWorker` as soon as the
excitation is recorded: the fit then runs while the validation (and the next axis) plays,
on the other core, without taking the calibrating process's interpreter lock from the
device's read-back or an in-process simulator. The worker is a ``spawn`` process (no copy of
the caller's threads, sockets or serial ports); :meth:`IdentifyWorker.close` ends it at once,
so a stop or a lost link never waits for a fit. The result is what
:func:`afmctl.api.identify.identify` returns for the same CSV file and options, bit for bit.
"""
from __future__ import annotations

import logging
import multiprocessing
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import AfmctlError

log = logging.getLogger(__name__)

#: how often a wait for a result looks for Ctrl-C and a dead worker [s]
POLL_S = 0.2


def serve(conn: Any) -> None:
    """The worker's loop: ``(key, kind, csv, params, columns)`` in, ``(key, ok, result or
    error)`` out, until ``None`` or the caller's end of the pipe closes. ``columns``: the
    recording's ``t,u,y[,v][,measured]`` arrays, the values the CSV ``csv`` holds (it is written to the
    full float precision, :func:`~afmctl.data.datafiles.write_csv`); None: read the CSV.
    Ctrl-C is the caller's to handle (it ends this process when it stops)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from .identify import identify
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        key, kind, csv, params, columns = job
        try:
            if columns is None:
                conn.send((key, True, identify(kind, csv, **params)))
            else:
                conn.send((key, True, identify(kind, t_s=columns["t"], u_V=columns["u"], y_nm=columns["y"],
                                               v_V=columns.get("v"), measured=columns.get("measured"), name=csv,
                                               **params)))
        except Exception as err:            # noqa: BLE001 - every failure goes back as one line
            conn.send((key, False, err if isinstance(err, AfmctlError) else AfmctlError(" ".join(str(err).split()))))


class IdentifyWorker:
    """One spawned process fitting the recordings handed to it, in turn. ``submit`` returns
    at once; ``result`` waits (Ctrl-C reaches the caller while it waits) and raises what
    the fit raised; ``close`` ends the process, a fit still running included."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=serve, args=(child,), name="afmctl-identify", daemon=True)
        self._proc.start()
        child.close()
        self._done: dict[str, tuple[bool, Any]] = {}
        self._running = 0                   # jobs submitted and not answered

    def submit(self, key: str, kind: str, csv: str | Path, params: dict[str, Any],
               columns: dict[str, Any] | None = None) -> None:
        """Fit ``kind`` to the recording ``csv`` with ``params`` (as ``identify``); with
        ``columns`` (its ``t,u,y[,v]`` arrays, exactly what the CSV holds) the fit need not
        wait for the file, and reads none."""
        self._conn.send((key, kind, str(csv), dict(params), columns))
        self._running += 1

    def result(self, key: str, stop: Callable[[], bool] | None = None) -> Any:
        """The :class:`~afmctl.api.identify.Identified` of job ``key``; ``KeyboardInterrupt``
        once ``stop()`` says so (another thread's stop: zenoh ``stop``)."""
        while key not in self._done:
            if stop is not None and stop():
                raise KeyboardInterrupt
            if self._conn.poll(POLL_S):
                k, ok, value = self._conn.recv()
                self._done[k] = (ok, value)
                self._running -= 1
            elif not self._proc.is_alive():
                raise AfmctlError(f"afmctl calibrate: the identification process ended (exit code "
                                  f"{self._proc.exitcode}) before it answered")
        ok, value = self._done.pop(key)
        if ok:
            return value
        raise value

    def close(self) -> None:
        """End the worker: at once when a fit is still running."""
        if self._proc.is_alive() and not self._running:
            try:
                self._conn.send(None)
                self._proc.join(1.0)
            except OSError:
                pass
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(2.0)
        self._conn.close()

    def __enter__(self) -> IdentifyWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["IdentifyWorker", "serve"]
