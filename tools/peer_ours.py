"""Our CLI under the peer harness's ``ours_timing.py``, behind a ``__main__`` guard.

``ours_timing.py`` runs the CLI when it is imported. Our worker processes are started with
``spawn``, which imports the parent's main script again in every child: run directly, each worker
re-ran the whole command and died (``BrokenProcessPool`` in the laser extraction, "the back-end
worker stopped unexpectedly"). Run through this file, a child imports it as ``__mp_main__`` and does
nothing. Usage: ``python tools/peer_ours.py PEER_DIR run ...`` (the CLI's own arguments after the folder).
"""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

if __name__ == "__main__":
    harness = Path(sys.argv[1]) / "ours_timing.py"
    sys.argv = [str(harness), *sys.argv[2:]]
    import loopmodel.pipeline as pipeline

    if not hasattr(pipeline._Run, "frame_ms"):
        # the harness reads the per-frame times as _Run.frame_ms; they now live in _Run.times
        # (without this every run ended "'_Run' object has no attribute 'frame_ms'", exit 1)
        pipeline._Run.frame_ms = property(lambda self: self.times.frame_ms)  # type: ignore[attr-defined]
    # not run_name="__main__": runpy would then stand the harness in for __main__, and spawned
    # children would import (and run) it again; it runs on import under any name
    runpy.run_path(str(harness), run_name="ours_timing")
