"""Work on a thread beside the tracking thread (issue 33).

The front end's keyframe work is numpy, OpenCV and numba (``nogil``) calls that release the GIL on
their large arrays, so a second thread uses the second core without a process's copying. The threads
are kept and reused: starting one per task cost the tracking thread a wait for the new thread's first
run each time (about ten a keyframe on the KITTI clip, each a GIL hand-over; fe7).
"""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class _Worker:
    """One kept thread: runs the tasks put to it, then waits idle for the next."""

    def __init__(self) -> None:
        self.tasks: queue.SimpleQueue[Beside[Any]] = queue.SimpleQueue()
        self.thread = threading.Thread(target=self._loop, name="frontend-beside", daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while True:
            self.tasks.get()._execute(self)


_IDLE: list[_Worker] = []  # kept threads waiting for a task (a task that waits on another gets a new one)
_IDLE_LOCK = threading.Lock()


def _forget_workers() -> None:
    """In a forked child the parent's threads do not exist."""
    global _IDLE_LOCK
    _IDLE.clear()
    _IDLE_LOCK = threading.Lock()


os.register_at_fork(after_in_child=_forget_workers)


class Beside(Generic[T]):
    """``fn(*args)`` on a kept thread beside the caller (at once on the caller's when not ``threaded``).

    :meth:`result` waits for it and returns its value (or raises its exception). A task may start
    others and wait for them: an idle kept thread takes each, else a new one is started (and kept).
    """

    def __init__(self, threaded: bool, fn: Callable[..., T], *args: Any) -> None:
        self._value: T | None = None
        self._error: BaseException | None = None
        self._fn, self._args = fn, args
        self._done: threading.Event | None = None
        if threaded:
            self._done = threading.Event()
            with _IDLE_LOCK:
                worker = _IDLE.pop() if _IDLE else None
            (worker or _Worker()).tasks.put(self)
        else:
            self._run()

    def _run(self) -> None:
        try:
            self._value = self._fn(*self._args)
        except BaseException as exc:  # re-raised on the caller's thread
            self._error = exc
        self._fn, self._args = None, ()  # type: ignore[assignment]  # no references kept by an idle thread

    def _execute(self, worker: _Worker) -> None:
        """On ``worker``'s thread: run, rejoin the idle threads, then tell the caller."""
        self._run()
        with _IDLE_LOCK:
            _IDLE.append(worker)
        assert self._done is not None
        self._done.set()

    def result(self) -> T:
        """The value of ``fn(*args)`` once it is done."""
        if self._done is not None:
            self._done.wait()
        if self._error is not None:
            raise self._error
        return self._value  # type: ignore[return-value]
