"""Our CLI under the peer harness's ``ours_timing.py``, behind a ``__main__`` guard.

``ours_timing.py`` runs the CLI when it is imported. Our worker processes are started with
``spawn``, which imports the parent's main script again in every child: run directly, each worker
re-ran the whole command and died (``BrokenProcessPool`` in the laser extraction, "the back-end
worker stopped unexpectedly"). Run through this file, a child imports it as ``__mp_main__`` and does
nothing. Usage: ``python tools/peer_ours.py PEER_DIR run ...`` (the CLI's own arguments after the folder).

The harness's ``cpu_ms_per_frame`` is this process's CPU time (all its threads) from the first
frame to the last. Our back end, loop detection and live mesh run in worker *processes*, which it
does not see, while ORB-SLAM3's local mapping and loop closing are threads of its one process and
are in its figure. So this wrapper also keeps ``cpu_ms_per_frame_workers``: the CPU time of every
descendant process over the same span (``/proc``, user + system, plus the children already
reaped), so that the bench can compare like with like.
"""

from __future__ import annotations

import os
import resource
import runpy
import sys
from pathlib import Path
from typing import Any


def _descendants(pid: int) -> list[int]:
    """The process ids below ``pid`` (children, theirs, ...), from ``/proc``."""
    found, todo, seen = [], [pid], set()
    while todo:
        p = todo.pop()
        try:
            for task in Path(f"/proc/{p}/task").iterdir():
                for child in (task / "children").read_text().split():
                    if int(child) not in seen:
                        seen.add(int(child))
                        found.append(int(child))
                        todo.append(int(child))
        except OSError:
            continue
    return found


WALK_EVERY = 25
"""The process tree is walked again every this many frames (a worker started meanwhile); else its pids are re-read."""
_tree: dict[str, Any] = {"pids": [], "calls": 0}


def _descendants_cpu_s() -> float:
    """User + system CPU seconds of this process's descendant processes (living and reaped).

    Walking ``/proc`` for the tree took about a tenth of the tracking thread's time between frames
    (orb13, py-spy on the orbit), twice a frame: the tree is walked again every :data:`WALK_EVERY`
    calls, the known pids' ``stat`` files read otherwise.
    """
    if _tree["calls"] % WALK_EVERY == 0:
        _tree["pids"] = _descendants(os.getpid())
    _tree["calls"] += 1
    tick_hz = float(os.sysconf("SC_CLK_TCK"))
    total_s = 0.0
    for pid in _tree["pids"]:
        try:  # fields after the command's closing parenthesis; utime, stime, cutime, cstime are 14-17
            with open(f"/proc/{pid}/stat", "rb") as f:
                fields = f.read().rsplit(b")", 1)[1].split()
        except OSError:
            continue  # it ended between the walk and the read; once reaped, RUSAGE_CHILDREN has it
        total_s += sum(int(v) for v in fields[11:15]) / tick_hz
    reaped = resource.getrusage(resource.RUSAGE_CHILDREN)
    return total_s + reaped.ru_utime + reaped.ru_stime


if __name__ == "__main__":
    harness = Path(sys.argv[1]) / "ours_timing.py"
    sys.argv = [str(harness), *sys.argv[2:]]
    import loopmodel.pipeline as pipeline

    if not hasattr(pipeline._Run, "frame_ms"):
        # the harness reads the per-frame times as _Run.frame_ms; they now live in _Run.times
        # (without this every run ended "'_Run' object has no attribute 'frame_ms'", exit 1)
        pipeline._Run.frame_ms = property(lambda self: self.times.frame_ms)  # type: ignore[attr-defined]
    workers: dict[str, float] = {}
    step, metrics = pipeline._Run.step, pipeline._Run._metrics

    def _step(self: Any, frame: Any) -> Any:
        if "cpu0" not in workers:  # (setdefault would walk /proc every frame for nothing)
            workers["cpu0"] = _descendants_cpu_s()
        out = step(self, frame)
        workers["cpu1"] = _descendants_cpu_s()
        return out

    def _metrics(self: Any, *args: Any, **kwargs: Any) -> Any:
        m = metrics(self, *args, **kwargs)
        if "cpu0" in workers:
            frames = max(len(self.times.frame_ms), 1)
            m["cpu_ms_per_frame_workers"] = 1e3 * (workers["cpu1"] - workers["cpu0"]) / frames
        return m

    # installed before the harness wraps the same two methods (it calls these)
    pipeline._Run.step, pipeline._Run._metrics = _step, _metrics  # type: ignore[method-assign]
    # not run_name="__main__": runpy would then stand the harness in for __main__, and spawned
    # children would import (and run) it again; it runs on import under any name
    runpy.run_path(str(harness), run_name="ours_timing")
