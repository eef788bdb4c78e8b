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
from shared_data import SHARED_DATA

ROOT = Path(__file__).resolve().parents[1]
KITTI = SHARED_DATA / "kitti_clip"


def run(quick: bool = False) -> dict[str, Any]:
    from loopmodel.config import load_config
    from loopmodel.frontend import FrontEnd
    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import _ground_truth_errors, _online_trajectory, frontend_metrics

    seq = open_sequence(KITTI)
    cfg = load_config(ROOT / "configs" / "kitti.yaml").frontend
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
    # The machine is shared: repeat the (deterministic) run and keep each frame's fastest
    # time, an estimate of the time on an unloaded machine (reported beside the first run).
    repeats = 1 if quick else 3
    best = np.array([r.track_ms + r.keyframe_ms for r in results])
    best_track = np.array([r.track_ms for r in results])
    best_kf = np.array([r.keyframe_ms for r in results])
    for _ in range(repeats - 1):
        fe_r = FrontEnd(seq.calibration, cfg)
        rr = [fe_r.process(f) for f in frames]
        best = np.minimum(best, [r.track_ms + r.keyframe_ms for r in rr])
        best_track = np.minimum(best_track, [r.track_ms for r in rr])
        best_kf = np.minimum(best_kf, [r.keyframe_ms for r in rr])
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
        **_scale_keys(results, seq.ground_truth),
        "lost_frames": m["lost_frames"],
        "keyframes": m["keyframes"],
        "local_ba_ms_median": round(float(np.median(ba)), 2) if ba else None,
        # CPU time of this process (all its threads) per frame: less sensitive to the load
        # other programs put on the machine than the wall-clock keys above
        "track_cpu_ms_median": round(float(np.median(cpu[~is_kf])), 2),
        "keyframe_frame_cpu_ms_median": round(float(np.median(cpu[is_kf])), 2),
        "fps_cpu": round(len(cpu) / (cpu.sum() / 1e3), 2),
        f"track_ms_median_best_of_{repeats}": round(float(np.median(best_track)), 2),
        f"track_ms_p95_best_of_{repeats}": round(float(np.percentile(best_track, 95)), 2),
        f"keyframe_ms_median_best_of_{repeats}": round(float(np.median(best_kf[is_kf])), 2),
        f"fps_best_of_{repeats}": round(len(best) / (best.sum() / 1e3), 2),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "cpu_count": os.cpu_count(),
    }
    sim = _synthetic_sample()
    if sim is not None:
        out.update(_run_synthetic(sim, quick))
    else:
        out["sim_note"] = "no synthetic sample (datasets/sample/scan.mcap or $LOOPMODEL_SIM_SAMPLE)"
    return out


def _scale_keys(results: list[Any], gt: Any, prefix: str = "") -> dict[str, float]:
    """``sim3_scale`` and ``step_scale_last_over_first`` of the frames reported OK (issue 36)."""
    from loopmodel.eval.trajectory_metrics import scale_figures

    ok = [r for r in results if r.ok]
    if gt is None or len(ok) < 3:
        return {}
    fig = scale_figures(gt.timestamps_ns, gt.world_from_cam, np.array([r.timestamp_ns for r in ok]),
                        np.stack([r.world_from_cam for r in ok]))
    return {prefix + k: round(v, 4) for k, v in fig.items()}


def _synthetic_sample() -> Path | None:
    env = os.environ.get("LOOPMODEL_SIM_SAMPLE")
    for p in ([Path(env)] if env else []) + [ROOT / "datasets" / "sample" / "scan.mcap"]:
        if p.is_file():
            return p
    return None


def _run_synthetic(path: Path, quick: bool) -> dict[str, Any]:
    """The synthetic hand-held sample (orbit).

    Drift before any loop closure and the largest pose error of a frame reported OK (world frames
    aligned at the first frame).
    """
    from loopmodel.config import load_config
    from loopmodel.frontend import FrontEnd
    from loopmodel.io.sequence import open_sequence

    seq = open_sequence(path)
    gt = seq.ground_truth
    cfg_file = ROOT / "configs" / "sim.yaml"
    cfg = load_config(cfg_file if cfg_file.is_file() else None).frontend
    fe = FrontEnd(seq.calibration, cfg)
    res = []
    t0 = time.perf_counter()
    for i, f in enumerate(seq.frames()):
        if quick and i >= 150:
            break
        res.append(fe.process(f))
    wall = time.perf_counter() - t0
    out: dict[str, Any] = {"sim_dataset": str(path), "sim_frames": len(res),
                           "sim_lost_frames": sum(not r.ok for r in res),
                           "sim_keyframes": sum(r.is_keyframe for r in res),
                           "sim_fps_with_io": round(len(res) / wall, 2)}
    if gt is None:
        return out
    t_gt = {int(t): k for k, t in enumerate(gt.timestamps_ns)}
    first = res[0]
    if first.timestamp_ns not in t_gt:
        return out
    world_gt_from_world = gt.world_from_cam[t_gt[first.timestamp_ns]] @ np.linalg.inv(first.world_from_cam)
    errs, ok_pos, gt_pos = [], [], []
    for r in res:
        k = t_gt.get(int(r.timestamp_ns))
        if k is None or not r.ok:
            continue
        p = (world_gt_from_world @ r.world_from_cam)[:3, 3]
        errs.append(float(np.linalg.norm(p - gt.world_from_cam[k, :3, 3])))
        ok_pos.append(p)
        gt_pos.append(gt.world_from_cam[k, :3, 3])
    if len(gt_pos) >= 2:
        g = np.array(gt_pos)
        length = float(np.sum(np.linalg.norm(np.diff(g, axis=0), axis=1)))
        out["sim_path_length_m"] = round(length, 3)
        out["sim_drift_pct"] = round(100.0 * errs[-1] / length, 3) if length > 0 else None
        out["sim_max_ok_pose_err_m"] = round(max(errs), 4)
        out["sim_ok_frames_over_5cm"] = int(sum(e > 0.05 for e in errs))
    return out
