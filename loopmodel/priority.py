"""Scheduling of the run's threads (issue 33).

Work that the tracking thread never waits for (a live-mesh update, the back end's keyframe updates, loop
detection) runs on threads of lowered priority, so on a 2-core machine the tracking thread and its
keyframe threads get the cores first and the workers take what is left between frames.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor

logger = logging.getLogger(__name__)

__all__ = ["low_priority_pool", "lower_switch_interval", "lower_thread_priority"]


def lower_thread_priority(nice: int) -> None:
    """Lower the calling thread's scheduling priority by ``nice`` (0: unchanged; at most 19).

    Linux schedules threads one by one, so only this thread yields (a process's other threads keep
    theirs; raising the priority again would need privileges, lowering it does not). Threads it starts
    later inherit it. Where the thread cannot be named (not Linux) nothing changes.
    """
    if nice <= 0:
        return
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(os.getpriority(os.PRIO_PROCESS, tid) + nice, 19))
    except (OSError, AttributeError):  # no per-thread priority here: the work keeps the process's
        logger.debug("thread priority not lowered")


def low_priority_pool(name: str, nice: int) -> ThreadPoolExecutor:
    """One worker thread named ``name`` whose priority is lowered by ``nice`` when it starts."""
    return ThreadPoolExecutor(1, name, lower_thread_priority, (nice,))


def lower_switch_interval(ms: float) -> None:
    """Lower the interpreter's switch interval to ``ms`` milliseconds (process-wide; only ever lowered; 0: unchanged).

    A thread that gives up the interpreter lock for a compiled or OpenCV call (the tracking thread's KLT,
    the keyframe threads' kernels) waits for it on return while a thread running Python holds it: up to
    the interval (Python's default 5 ms) at each such return, longer when the holder is descheduled.
    """
    if 0 < ms < sys.getswitchinterval() * 1e3:
        sys.setswitchinterval(ms / 1e3)
