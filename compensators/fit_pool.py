"""Fits in worker processes, with the caller's order and results (#38).

``--model auto`` fits a dozen candidates, folds and a final refit that do not depend on each
other's results; each runs on one core (numba kernels, scipy's least squares; OpenBLAS's
threads gained nothing: the E-727 calibrate recording took 50.2 s with one thread, 53.1 s
with two). :class:`FitPool` runs such tasks in ``jobs`` forked worker processes:

- :meth:`FitPool.submit` queues a task under a key; it may be speculative (a refit of the
  likely winner while its held-out score is still being computed). With ``jobs == 1`` nothing
  runs until :meth:`FitPool.result` asks for the key, so a speculative task that is never
  asked for costs nothing and the order of work is the caller's.
- :meth:`FitPool.result` returns the task's value, computed by the same function on the same
  arguments in whichever process ran it: the same model bit for bit (tests/test_fit_pool.py).
- The record is handed over once, by the fork (``shared``), not pickled per task; a task is
  ``fn(shared, *args)`` with ``fn`` a module-level function.

A worker ignores Ctrl-C (the caller's to handle) and ends when its parent ends (a stopped or
killed calibration never leaves one fitting); :meth:`FitPool.close` ends them at once.
"""
from __future__ import annotations

import ctypes
import logging
import math
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Hashable
from multiprocessing.connection import wait
from typing import Any

log = logging.getLogger(__name__)

#: how often a worker looks whether its parent is still there [s]
PARENT_POLL_S = 0.5
#: how long :meth:`FitPool.close` lets an idle worker end by itself [s] (a busy one is killed)
CLOSE_WAIT_S = 0.2

_SHARED: dict[str, Any] = {}


def _watch_parent(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(PARENT_POLL_S)
    os._exit(1)


def _ended(pid: int) -> bool:
    """Whether worker ``pid`` has ended (reaped here, or before)."""
    try:
        return os.waitpid(pid, os.WNOHANG)[0] != 0
    except ChildProcessError:
        return True


#: the OpenBLAS builds' thread setters (numpy's and scipy's wheels bundle their own builds)
BLAS_THREAD_SETTERS = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
                       "openblas_set_num_threads64_", "openblas_set_num_threads")


def one_blas_thread() -> int:
    """Limit every OpenBLAS loaded in this process to one thread; returns how many were found.
    A worker's BLAS threads would otherwise compete with the other workers' (OpenBLAS threads
    spin while they wait: two workers with two threads each took 46 s where one thread each
    took 18 s, two-modes' record). Linux (reads ``/proc/self/maps``); elsewhere 0."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as maps:
            paths = {line.split()[-1] for line in maps if "openblas" in line.lower() and "/" in line}
    except OSError:
        return 0
    found = 0
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in BLAS_THREAD_SETTERS:
            setter = getattr(lib, name, None)
            if setter is not None:
                setter(ctypes.c_int(1))
                found += 1
                break
    return found


def _serve(conn: Any, parent: int) -> None:
    """A worker's loop: ``(key, fn, args)`` in, ``(key, ok, value or exception)`` out."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    one_blas_thread()
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            os._exit(0)
        if job is None:
            os._exit(0)
        key, fn, args = job
        try:
            conn.send((key, True, fn(_SHARED, *args)))
        except BaseException as err:     # noqa: BLE001 - the caller raises it
            conn.send((key, False, err))


class FitPool:
    """``jobs`` worker processes (forked, each holding ``shared``), or none for ``jobs == 1``
    or where ``fork`` is not available. Use as a context manager."""

    def __init__(self, jobs: int, shared: dict[str, Any]) -> None:
        self.shared = shared
        self._tasks: dict[Hashable, tuple[Callable[..., Any], tuple[Any, ...]]] = {}
        self._queue: list[Hashable] = []
        self._done: dict[Hashable, tuple[bool, Any]] = {}
        self._busy: dict[Any, Hashable | None] = {}
        self._pids: list[int] = []
        jobs = int(jobs)
        if jobs > 1 and "fork" in multiprocessing.get_all_start_methods():
            self._start(jobs)

    @property
    def jobs(self) -> int:
        """Processes fitting at once (1: the caller's own, in the caller's order)."""
        return max(1, len(self._pids))

    def _start(self, jobs: int) -> None:
        # os.fork rather than multiprocessing.Process: the caller may itself be a daemonic
        # worker process (afmctl calibrate's identification), which may not have children
        # of multiprocessing's own
        _SHARED.clear()
        _SHARED.update(self.shared)
        parent = os.getpid()
        try:
            for _ in range(jobs):
                mine, theirs = multiprocessing.Pipe()
                pid = os.fork()
                if pid == 0:                 # pragma: no cover - the worker's side
                    try:
                        mine.close()
                        _serve(theirs, parent)
                    finally:
                        os._exit(0)
                theirs.close()
                self._pids.append(pid)
                self._busy[mine] = None
        finally:
            _SHARED.clear()
        log.info("fit pool: %d worker processes", jobs)

    def submit(self, key: Hashable, fn: Callable[..., Any], *args: Any) -> None:
        """Queue ``fn(shared, *args)`` under ``key`` (a second submit of a key is ignored)."""
        if key in self._tasks:
            return
        self._tasks[key] = (fn, args)
        self._queue.append(key)
        self._pump()

    def result(self, key: Hashable, fn: Callable[..., Any] | None = None, *args: Any) -> Any:
        """The value of task ``key`` (submitted now with ``fn`` and ``args`` when it was not);
        raises what the task raised."""
        if key not in self._tasks:
            if fn is None:
                raise KeyError(key)
            self.submit(key, fn, *args)
        if not self._pids:
            if key not in self._done:
                self._queue.remove(key)
                task, task_args = self._tasks[key]
                self._done[key] = (True, task(self.shared, *task_args))
        else:
            if key in self._queue:        # the caller waits on it: it goes before speculation
                self._queue.remove(key)
                self._queue.insert(0, key)
            while key not in self._done:
                self._pump()
                self._receive()
        ok, value = self._done[key]
        if not ok:
            raise value
        return value

    def _pump(self) -> None:
        for conn, running in self._busy.items():
            if running is None and self._queue:
                key = self._queue.pop(0)
                fn, args = self._tasks[key]
                conn.send((key, fn, args))
                self._busy[conn] = key

    def _receive(self) -> None:
        running = [c for c, k in self._busy.items() if k is not None]
        if not running:
            raise RuntimeError("fit pool: nothing running and the result not done")
        ready: list[Any] = wait(running, timeout=1.0)
        for conn in ready:
            try:
                key, ok, value = conn.recv()
            except (EOFError, OSError):
                raise RuntimeError("fit pool: a worker process ended before it answered") from None
            self._done[key] = (ok, value)
            self._busy[conn] = None
        if any(_ended(pid) for pid in self._pids):
            raise RuntimeError("fit pool: a worker process ended before it answered")

    def close(self) -> None:
        """End the workers, a fit still running included."""
        for conn in self._busy:
            try:
                conn.send(None)
            except OSError:
                pass
            conn.close()
        end = time.monotonic() + CLOSE_WAIT_S
        for pid in self._pids:
            while not _ended(pid):
                if time.monotonic() > end:
                    os.kill(pid, signal.SIGKILL)
                    end = math.inf
                time.sleep(0.01)
        self._pids.clear()
        self._busy.clear()

    def __enter__(self) -> FitPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["FitPool"]
