"""Benchmark ``frontend``: the stereo keyframe front end on the real KITTI clip.

Keys (BENCHMARKS.md): frames, track_ms_median, track_ms_p95 (per-frame tracking: KLT,
robust pose, keyframe decision), keyframe_ms_median (keyframe creation: detection, stereo
row search, triangulation, local hybrid BA), fps (frames / time spent in
``FrontEnd.process``; image decoding excluded, ``fps_with_io`` includes it), ate_rmse_m
(SE(3)-aligned), drift_pct (final position error / path length x 100), peak_rss_mib.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
KITTI = (ROOT / ".." / "shared" / "data" / "kitti_clip").resolve()


def run(quick: bool = False) -> dict[str, Any]:
    from loopmodel.config import Config
    from loopmodel.frontend import FrontEnd
    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import _ground_truth_errors, _online_trajectory, frontend_metrics

    seq = open_sequence(KITTI)
    cfg = Config().frontend
    frames = list(seq.frames())
    if quick:
        frames = frames[:30]
    # warm-up (imports, OpenCV allocations) on a separate instance
    warm = FrontEnd(seq.calibration, cfg)
    for f in frames[:3]:
        warm.process(f)
    fe = FrontEnd(seq.calibration, cfg)
    results = []
    cpu_ms = []
    t0 = time.perf_counter()
    for f in frames:
        c0 = time.process_time()
        results.append(fe.process(f))
        cpu_ms.append((time.process_time() - c0) * 1e3)
    wall = time.perf_counter() - t0
    cpu = np.array(cpu_ms)
    is_kf = np.array([r.is_keyframe for r in results])
    m = frontend_metrics(results, wall)
    err = _ground_truth_errors(_online_trajectory(results), seq.ground_truth)
    ba = [
        r.keyframe.ba_info["ba_ms"]
        for r in results
        if r.keyframe is not None and r.keyframe.ba_info
    ]
    out: dict[str, Any] = {
        "dataset": "kitti_clip (real KITTI 1226x370)" + (" first 30 frames" if quick else ""),
        "frames": m["frames"],
        "track_ms_median": round(m["track_ms_median"], 2),
        "track_ms_p95": round(m["track_ms_p95"], 2),
        "keyframe_ms_median": round(m["keyframe_ms_median"], 2)
        if m["keyframe_ms_median"]
        else None,
        "fps": round(m["fps"], 2),
        "fps_with_io": round(m["fps_with_io"], 2),
        "ate_rmse_m": round(err.get("ate_rmse_m", float("nan")), 4),
        "drift_pct": round(err.get("drift_pct", float("nan")), 3),
        "lost_frames": m["lost_frames"],
        "keyframes": m["keyframes"],
        "local_ba_ms_median": round(float(np.median(ba)), 2) if ba else None,
        # CPU time of this process (all its threads) per frame: less sensitive to the load
        # other programs put on the machine than the wall-clock keys above
        "track_cpu_ms_median": round(float(np.median(cpu[~is_kf])), 2),
        "keyframe_frame_cpu_ms_median": round(float(np.median(cpu[is_kf])), 2),
        "fps_cpu": round(len(cpu) / (cpu.sum() / 1e3), 2),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "cpu_count": os.cpu_count(),
    }
    return out
