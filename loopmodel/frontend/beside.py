"""Work on a thread beside the tracking thread (issue 33).

The front end's keyframe work is numpy and OpenCV calls that release the GIL on their large arrays,
so a second thread uses the second core without a process's copying.

The threads are kept and reused (fe11): starting a thread made the caller wait for it to start
(``Thread.start`` returns once the new thread runs) and then for the interpreter, which the new
thread held for up to the switch interval (5 ms) when its work began with Python code, as the local
BA's does. Handing a job to an idle thread returns at once; a new thread is started only when every
kept one is busy (a job never waits behind another, so a job may wait for jobs it started itself).
"""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable
from typing import Any, Generic, TypeVar

T = TypeVar("T")

_IDLE: list[_Worker] = []  # kept threads waiting for a job
_IDLE_LOCK = threading.Lock()


def _forget_after_fork() -> None:
    """A forked child has none of the parent's threads: it keeps none (and a fresh lock)."""
    global _IDLE_LOCK
    _IDLE.clear()
    _IDLE_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_after_fork)


class _Worker:
    """A daemon thread that runs the jobs handed to it, one at a time, then waits in :data:`_IDLE`."""

    def __init__(self) -> None:
        self._jobs: queue.SimpleQueue[Callable[[], None]] = queue.SimpleQueue()
        threading.Thread(target=self._loop, name="keyframe-stereo", daemon=True).start()

    def hand(self, job: Callable[[], None]) -> None:
        self._jobs.put(job)

    def _loop(self) -> None:
        while True:
            self._jobs.get()()
            with _IDLE_LOCK:
                _IDLE.append(self)


def _worker() -> _Worker:
    """An idle kept thread, or a new one."""
    with _IDLE_LOCK:
        if _IDLE:
            return _IDLE.pop()
    return _Worker()


class Beside(Generic[T]):
    """``fn(*args)`` on a thread beside the caller (at once on the caller's when not ``threaded``).

    :meth:`result` waits for it and returns its value (or raises its exception).
    """

    def __init__(self, threaded: bool, fn: Callable[..., T], *args: Any) -> None:
        self._value: T | None = None
        self._error: BaseException | None = None
        self._done: threading.Event | None = None
        self._claim = threading.Lock()  # taken by the one thread that runs fn (result's run_here)
        self.ran_here = False  # result(run_here=True) ran it on the caller's thread
        self._job = (fn, args)
        if threaded:
            self._done = threading.Event()
            _worker().hand(self._begin)
        else:
            self._run(fn, args)

    def _begin(self) -> None:
        if self._claim.acquire(blocking=False):  # else the caller has run it (result(run_here=True))
            self._run(*self._job)

    def _run(self, fn: Callable[..., T], args: tuple[Any, ...]) -> None:
        try:
            self._value = fn(*args)
        except BaseException as exc:  # re-raised on the caller's thread
            self._error = exc
        finally:
            if self._done is not None:
                self._done.set()

    def result(self, run_here: bool = False) -> T:
        """The value of ``fn(*args)`` once it is done.

        ``run_here``: a job the thread beside has not begun yet (its core busy with other work) is run
        on the caller's thread instead of waited for, and the thread skips it (cpu15): the same value.
        """
        if self._done is not None:
            if run_here and self._claim.acquire(blocking=False):
                self.ran_here = True
                self._run(*self._job)
            self._done.wait()
        if self._error is not None:
            raise self._error
        return self._value  # type: ignore[return-value]
