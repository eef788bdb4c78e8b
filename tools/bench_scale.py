"""Benchmark ``scale``: cost growth of the pipeline over a long realistic multi-loop scan.

Full run: a 5,000-frame realistic scan (the ``modeler`` preset stretched to 200 s: four
sweeps, a loop closure, a second orbit; generated once into ``~/.cache/loopmodel``, slow);
``--quick``: the 1,200-frame realistic modeler scan of ``sim-loop --quick`` at every 2nd frame.
The pipeline runs with its own configuration (iSAM2 back end, loop stage, meshing).

Keys: ``frames``; ``frame_ms_last_over_first``: median per-frame time over the last N frames
divided by that over the first N (N = 500, quick 200; a frame's time is the interval between
the pipeline's requests for consecutive frames, so it includes the loop stage and back end);
``backend_ms_by_keyframes``: median back-end update time (``add_keyframe``, timed around the
pipeline's own back end) per block of 20 keyframes, as [keyframes, ms] pairs;
``loop_opt_ms_by_keyframes``: each verified loop's optimisation time with the number of
keyframes at that moment; ``peak_rss_mib``; ``write_s``: from the last frame to the end of
the run minus the final refinement (meshing and writing the results folder).
"""

from __future__ import annotations

import logging
import resource
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from loopmodel.config import Config

CACHE = Path.home() / ".cache" / "loopmodel"


class _Timed:
    """A sequence whose ``frames()`` records the time at which each frame is requested."""

    def __init__(self, seq: Any, stride: int) -> None:
        self._seq, self._stride = seq, stride
        self.stamps: list[float] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._seq, name)

    def __len__(self) -> int:
        return (len(self._seq) + self._stride - 1) // self._stride

    def frames(self) -> Any:
        for i, f in enumerate(self._seq.frames()):
            if i % self._stride == 0:
                self.stamps.append(time.perf_counter())
                yield f


def run(quick: bool = False) -> dict[str, Any]:
    import sys

    logging.basicConfig(level=logging.WARNING)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bench_sim_loop as sl

    import loopmodel.pipeline as pl
    from loopmodel.io.sequence import open_sequence

    config = Config()
    if quick:
        path, stride, window = sl._ensure(CACHE / "modeler_1200.mcap", "modeler", frames=1200), 2, 200
    else:
        path, stride, window = sl._ensure(CACHE / "modeler_5000.mcap", "modeler", frames=5000), 1, 500
    seq = _Timed(open_sequence(path, config.sequence), stride)
    kf_count = [0]
    backend_ms: list[tuple[int, float]] = []
    make = pl.create_backend

    def timed_backend(*args: Any, **kwargs: Any) -> Any:
        backend = make(*args, **kwargs)
        inner = backend.add_keyframe

        def add_keyframe(keyframe: Any) -> Any:
            t0 = time.perf_counter()
            out = inner(keyframe)
            kf_count[0] += 1
            backend_ms.append((kf_count[0], (time.perf_counter() - t0) * 1e3))
            return out

        backend.add_keyframe = add_keyframe
        return backend

    from loopmodel.listener import RunListener

    kf_at_frame: dict[int, int] = {}

    class _KeyframeCount(RunListener):
        def on_keyframe(self, keyframe: Any, result: Any) -> None:
            kf_at_frame[int(result.frame_index)] = kf_count[0]

    pl.create_backend = timed_backend  # type: ignore[assignment]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            out = pl.run_pipeline(seq, config, tmp, "scale", listeners=[_KeyframeCount()])
            t_end = time.perf_counter()
    finally:
        pl.create_backend = make  # type: ignore[assignment]
    stamps = np.array(seq.stamps)
    dt = np.diff(stamps) * 1e3
    n = min(window, dt.size // 2)
    ratio = float(np.median(dt[-n:]) / np.median(dt[:n])) if n > 0 else None
    blocks = []
    if backend_ms:
        kfs = np.array([k for k, _ in backend_ms])
        ms = np.array([m for _, m in backend_ms])
        for start in range(0, int(kfs.max()), 20):
            sel = (kfs > start) & (kfs <= start + 20)
            if np.any(sel):
                blocks.append([start + 20, round(float(np.median(ms[sel])), 2)])
    frames_sorted = sorted(kf_at_frame)
    loops = []
    for e in out.metrics.get("loop_events", []):
        if e.get("type") != "loop":
            continue
        before = [f for f in frames_sorted if f <= e["frame"]]
        loops.append([kf_at_frame[before[-1]] if before else 0, round(float(e.get("optimise_ms", 0.0)), 1)])
    tail_s = t_end - stamps[-1] if stamps.size else 0.0
    refine = float(out.metrics.get("final_refine_s") or 0.0)
    return {
        "dataset": f"realistic modeler scan {path.name}" + (f", every {stride}nd frame" if stride > 1 else ""),
        "frames": len(out.frames),
        "keyframes": kf_count[0],
        "frame_ms_first_median": round(float(np.median(dt[:n])), 2) if n > 0 else None,
        "frame_ms_last_median": round(float(np.median(dt[-n:])), 2) if n > 0 else None,
        "frame_ms_last_over_first": round(ratio, 3) if ratio is not None else None,
        "backend_ms_by_keyframes": blocks,
        "loop_opt_ms_by_keyframes": loops,
        "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "write_s": round(max(tail_s - refine, 0.0), 2),
        "final_refine_s": round(refine, 2),
        "wall_s": round(t_end - t0, 1),
    }
