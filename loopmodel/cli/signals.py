"""Signal handling of the long commands.

SIGTERM behaves like Ctrl-C, so temporary files are removed by the ``atomic_path`` cleanup and the
command exits 130.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """While inside, SIGTERM raises ``KeyboardInterrupt`` in the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum: int, frame: object) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def caused_by_interrupt(exc: BaseException) -> bool:
    """Whether ``exc`` is or comes from a Ctrl-C or SIGTERM.

    An interrupt can surface as another exception: an ImportError "initialization failed" wrapping
    it, or an error raised by a clean-up that ran because of it (its ``__context__``).
    """
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, KeyboardInterrupt):
            return True
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return False
