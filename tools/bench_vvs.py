"""Benchmark ``vvs`` (seed 002): VVS model-based tracking of a box with the simulated
4-mirror omnidirectional stereo sensor, and with its two widest-baseline mirrors only.

Keys: frames, iter_ms_median, rot_err_deg_median, pos_err_mm_median (4 mirrors),
lost_frames_4_mirrors, lost_frames_2_mirrors, plus the 2-mirror errors, the first lost
frames, and the timing of one full robust pose update for 4 cameras x 100 point-to-conic
features (wall and CPU time, and its rate in Hz). ``--quick`` tracks frames 200-311 of the
same 312-frame sequence (the part through the inter-reflection zone) instead of all.
"""

from __future__ import annotations

import os
import time

import numpy as np

from loopmodel.geometry.se3 import se3_exp
from loopmodel.pose.tracking import PolyhedronModel, sample_model_edges
from loopmodel.pose.vvs import LineTerm, VvsOptions, vvs_pose
from loopmodel.sim.omni import BOX_SIZE_M, box_trajectory, omni_sensor, simulate_tracking


def _pose_update_timing(repeats: int) -> dict[str, float]:
    """One robust VVS pose update (Tukey, from a pose 2 deg / 1 cm off) with 4 cameras x
    100 edge points (0.3 px noise, 10 % outliers)."""
    sensor = omni_sensor()
    model = PolyhedronModel.box(BOX_SIZE_M)
    rig = sensor.rig()
    rng = np.random.default_rng(0)
    T = box_trajectory(312)[60]
    s = sample_model_edges(rig, model, T, 2.0)
    idx = np.concatenate(
        [rng.choice(np.flatnonzero(s.cam_index == j), 100, replace=False) for j in range(4)]
    )
    uv = s.uv_px[idx] + rng.normal(0, 0.3, (400, 2)) * s.normal_px[idx][:, :1]
    out = rng.random(400) < 0.1
    uv[out] += rng.uniform(-10, 10, (int(out.sum()), 1)) * s.normal_px[idx][out]
    term = LineTerm(rig, model.lines, uv, s.line_index[idx], s.cam_index[idx])
    opt = VvsOptions(huber_warmup=1)
    starts = [se3_exp(rng.normal(0, [0.006] * 3 + [0.02] * 3)) @ T for _ in range(repeats)]
    vvs_pose(term, starts[0], opt)  # warm-up
    wall, cpu, iters, it_ms = [], [], [], []
    for T0 in starts:
        w0, c0 = time.perf_counter(), time.process_time()
        res = vvs_pose(term, T0, opt)
        wall.append(1e3 * (time.perf_counter() - w0))
        cpu.append(1e3 * (time.process_time() - c0))
        iters.append(res.iterations)
        it_ms.append(res.info["iter_ms"])
    return {
        "pose_update_ms_median": round(float(np.median(wall)), 3),
        "pose_update_ms_p95": round(float(np.percentile(wall, 95)), 3),
        "pose_update_cpu_ms_median": round(float(np.median(cpu)), 3),
        "pose_update_hz": round(1e3 / float(np.median(wall)), 1),
        "pose_update_iterations_median": float(np.median(iters)),
        "pose_update_iter_ms_median": round(float(np.median(it_ms)), 3),
    }


def run(quick: bool) -> dict:
    start = 200 if quick else 0
    t0 = time.perf_counter()
    r4 = simulate_tracking((0, 1, 2, 3), 312, start_frame=start)
    r2 = simulate_tracking((0, 3), 312, start_frame=start)
    elapsed = time.perf_counter() - t0

    def first(lost: np.ndarray) -> int:
        k = np.flatnonzero(lost)
        return int(k[0]) + start if k.size else -1

    out: dict = {
        "dataset": "simulated 4-mirror omni-stereo sensor (xi=1), 30x25x20 cm box at 35-75 cm, "
        f"clutter, inter-reflection zones; frames {start}-311 of 312",
        "frames": len(r4.rot_err_deg),
        "iter_ms_median": round(float(np.nanmedian(r4.iter_ms)), 3),
        "iter_ms_p95": round(float(np.nanpercentile(r4.iter_ms, 95)), 3),
        "frame_ms_median": round(float(np.median(r4.frame_ms)), 2),
        "rot_err_deg_median": round(float(np.median(r4.rot_err_deg)), 4),
        "pos_err_mm_median": round(float(np.median(r4.pos_err_mm)), 3),
        "rot_err_deg_p95": round(float(np.percentile(r4.rot_err_deg, 95)), 4),
        "pos_err_mm_p95": round(float(np.percentile(r4.pos_err_mm, 95)), 3),
        "lost_frames_4_mirrors": int(r4.lost.sum()),
        "lost_frames_2_mirrors": int(r2.lost.sum()),
        "first_lost_frame_4_mirrors": first(r4.lost),
        "first_lost_frame_2_mirrors": first(r2.lost),
        "rot_err_deg_median_2_mirrors": round(float(np.median(r2.rot_err_deg)), 4),
        "pos_err_mm_median_2_mirrors": round(float(np.median(r2.pos_err_mm)), 3),
        "edge_points_per_frame_median": float(np.median(r4.num_matched)),
        "tracking_s": round(elapsed, 1),
    }
    out.update(_pose_update_timing(30 if quick else 100))
    out["load_average_1min"] = round(os.getloadavg()[0], 2)
    return out
