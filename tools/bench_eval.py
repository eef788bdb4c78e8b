"""Benchmark of ``loopmodel eval``.

KITTI 00 (4,541 poses, ORB-SLAM2 estimate against ground truth) evaluated end to end with every
picture, report and metrics file.

Two timings: ``eval_s`` for a results folder (online = the ORB estimate, final = the same
estimate, keyframes every 5th pose, two loop-closure events) against the ground-truth file,
which evaluates three trajectories and draws all plots; ``eval_ref_est_s`` for
``--ref GT --est EST``. Both include reading the files and writing the outputs. Target:
``eval_s`` <= 5 s.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from shared_data import SHARED_DATA

SHARED = SHARED_DATA / "trajectories"


def run(quick: bool = False) -> dict:
    from loopmodel.config import EvalConfig
    from loopmodel.eval import report as rep
    from loopmodel.io.trajectory_io import read_trajectory, write_trajectory
    from loopmodel.types import Trajectory

    gt_path = (SHARED / "KITTI_00_gt.txt").resolve()
    est_path = (SHARED / "KITTI_00_ORB.txt").resolve()
    times = SHARED / "KITTI_00_gt_times.txt"
    t_ns = np.array([round(float(x) * 1e9) for x in times.read_text().split()], dtype=np.int64)
    tmp = Path(tempfile.mkdtemp(prefix="bench_eval_"))
    try:
        # a results folder made of the real files (TUM with the real KITTI times)
        gt = read_trajectory(gt_path, "kitti", timestamps_ns=t_ns)
        est = read_trajectory(est_path, "kitti", timestamps_ns=t_ns, check=False)
        run_dir = tmp / "kitti00_run"
        write_trajectory(tmp / "gt.tum", gt)
        write_trajectory(run_dir / "trajectory_online.tum", est)
        write_trajectory(run_dir / "trajectory_final.tum", est)
        write_trajectory(
            run_dir / "keyframes.tum", Trajectory(est.timestamps_ns[::5], est.world_from_cam[::5])
        )
        events = [
            {"timestamp_ns": int(t_ns[4450]), "match_timestamp_ns": int(t_ns[10]), "inliers": 100},
            {"frame": 2500, "match_frame": 500, "inliers": 80},
        ]
        (run_dir / "metrics.json").write_text(json.dumps({"loop_closures": events}))
        cfg = EvalConfig()

        t0 = time.perf_counter()
        run_data = rep.load_run(run_dir)
        g = rep.load_ground_truth(tmp / "gt.tum")
        ev = rep.evaluate_run(run_data, g, cfg)
        rep.write_outputs(ev, tmp / "out_run")
        eval_s = time.perf_counter() - t0

        t0 = time.perf_counter()
        ref = rep.load_ground_truth(gt_path)
        e = rep.load_trajectory_file(est_path)
        ev2 = rep.evaluate_run(rep.plain_run(e), ref, cfg)
        rep.write_outputs(ev2, tmp / "out_ref_est")
        eval_ref_est_s = time.perf_counter() - t0
        fin = ev.metrics["trajectories"]["final"]
        return {
            "poses": int(len(est)),
            "eval_s": round(eval_s, 3),
            "eval_ref_est_s": round(eval_ref_est_s, 3),
            "plots": len(ev.plots),
            "ate_rmse_m": round(ev2.metrics["ate_rmse_m"], 6),
            "kitti_t_err_pct": round(fin["kitti_segments"]["t_err_pct"], 4),
            "target_eval_s": 5.0,
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
