"""Benchmark ``frontend``: the stereo keyframe front end on the real KITTI clip.

Keys (BENCHMARKS.md): frames, track_ms_median, track_ms_p95 (per-frame tracking: KLT,
robust pose, keyframe decision), keyframe_ms_median (keyframe creation: detection, stereo
row search, triangulation, local hybrid BA), fps (frames / time spent in
``FrontEnd.process``; image decoding excluded, ``fps_with_io`` includes it), ate_rmse_m
(SE(3)-aligned), drift_pct (final position error / path length x 100), peak_rss_mib,
sim3_scale (truth / estimate, Umeyama) and step_scale_last_over_first (the per-step scale of the
last quarter of the steps over the first's, :mod:`loopmodel.eval.trajectory_metrics`; issue 36), and
``street_*``: the same figures on the simulated street scan of issue 36 (:func:`_run_street`).
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
    from loopmodel.eval.of_run import trajectory_errors
    from loopmodel.frontend import FrontEnd
    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import _online_trajectory, frontend_metrics

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
    err = trajectory_errors(_online_trajectory(results), seq.ground_truth)
    # each keyframe as handed (local_ba_beside: with the next frame; the last one after the frames)
    handed = [r.keyframe for r in results if r.keyframe is not None] + fe.finish_keyframes()
    ba = [kf.ba_info["ba_ms"] for kf in handed if "ba_ms" in kf.ba_info]  # (the first keyframe has no BA)
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
    out.update(_run_street(quick))
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


def _run_street(quick: bool) -> dict[str, Any]:
    """The simulated street scan of issue 36 (``loopmodel.sim.street``) with ``configs/kitti.yaml``.

    Foliage and a fence over much of the view, far facades and hills, a car ahead and an oncoming
    one; the view opens half-way and the right image's principal point is 0.5 px off the recorded
    calibration. Keys ``street_*``: SE(3) and Sim(3) ATE, ``sim3_scale`` (truth / estimate),
    ``step_scale_last_over_first``, the front end's estimated disparity offset, and the keyframe
    matches' disparity error against the simulator's true disparity (median, share beyond 1 px).
    ``--quick``: 30 frames at 1 m per frame instead of 50 at 2 m.
    """
    from loopmodel.config import load_config
    from loopmodel.eval.trajectory_metrics import align
    from loopmodel.frontend import FrontEnd
    from loopmodel.sim.street import StreetConfig, StreetScene

    sc = StreetConfig(frames=30 if quick else 50, speed_m_per_frame=1.0 if quick else 2.0,
                      open_from_m=15.0 if quick else 50.0, lead_speed_ratio=0.97, lead_start_m=16.0, seed=2,
                      right_cx_error_px=0.5)
    scene = StreetScene.build(sc)
    fe = FrontEnd(scene.calibration, load_config(ROOT / "configs" / "kitti.yaml").frontend)
    res, err = [], []
    for i in range(sc.frames):
        f = scene.render(i)
        r = fe.process(f.frame)
        res.append(r)
        if r.keyframe is not None:
            sp = r.keyframe.stereo_px
            u, v = np.rint(sp[:, 0]).astype(int), np.rint(sp[:, 2]).astype(int)
            # the stored right columns are corrected by the estimated offset: compare the raw match
            raw_d = sp[:, 0] - sp[:, 1] - r.keyframe.ba_info.get("disparity_offset_applied_px", 0.0)
            err.append(raw_d + sc.right_cx_error_px - f.disparity_px[v, u])
    gt = scene.ground_truth()
    est = np.stack([r.world_from_cam for r in res])
    out: dict[str, Any] = {"street_frames": len(res), "street_lost_frames": sum(not r.ok for r in res),
                           "street_keyframes": sum(r.is_keyframe for r in res)}
    for mode in ("se3", "sim3"):
        a = align(gt.world_from_cam, est, mode)
        d = a.apply(est)[:, :3, 3] - gt.world_from_cam[:, :3, 3]
        out[f"street_ate_{mode}_m"] = round(float(np.sqrt(np.mean(np.sum(d * d, axis=1)))), 4)
    out.update(_scale_keys(res, gt, "street_"))
    out["street_disparity_offset_px"] = round(float(getattr(fe, "_offset_px", 0.0)), 3)
    e = np.concatenate(err) if err else np.zeros(0)
    out["street_disp_err_median_px"] = round(float(np.median(e)), 3) if e.size else None
    out["street_disp_err_over_1px"] = round(float(np.mean(np.abs(e) > 1.0)), 4) if e.size else None
    return out


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
