"""Work on a thread beside the tracking thread (issue 33).

The front end's keyframe work is numpy and OpenCV calls that release the GIL on their large arrays,
so a second thread uses the second core without a process's copying.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class Beside(Generic[T]):
    """``fn(*args)`` on a thread beside the caller (at once on the caller's when not ``threaded``).

    :meth:`result` waits for it and returns its value (or raises its exception).
    """

    def __init__(self, threaded: bool, fn: Callable[..., T], *args: Any) -> None:
        self._value: T | None = None
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        if threaded:
            self._thread = threading.Thread(target=self._run, args=(fn, args), name="keyframe-stereo", daemon=True)
            self._thread.start()
        else:
            self._run(fn, args)

    def _run(self, fn: Callable[..., T], args: tuple[Any, ...]) -> None:
        try:
            self._value = fn(*args)
        except BaseException as exc:  # re-raised on the caller's thread
            self._error = exc

    def result(self) -> T:
        """The value of ``fn(*args)`` once it is done."""
        if self._thread is not None:
            self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value  # type: ignore[return-value]
