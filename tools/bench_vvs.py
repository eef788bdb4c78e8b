"""Benchmark ``vvs`` (seed 002): model-based tracking of a box from rendered images of the
4-mirror omnidirectional stereo sensor, and of its two widest-baseline mirrors only.

Each of ``scenarios`` seeded scenarios (:func:`loopmodel.sim.omni_images.omni_scenario`:
clutter behind random mirrors, random hand-held motion) is rendered once per frame; the
moving-edge search runs on the images and tracking starts from a pose 6 deg / 2.5 cm off the
truth. A frame is lost when the tracker fails or is off by more than 5 deg / 50 mm.

Keys (BENCHMARKS.md): input (``images``), frames, scenarios, init_rot_err_deg, iter_ms_median,
me_search_ms_median, frame_ms_median, rot_err_deg_median, pos_err_mm_median (4 mirrors, all
frames of all scenarios), lost_frames_4_mirrors, lost_frames_2_mirrors (totals),
four_beats_two_fraction (the share of scenarios where 4 mirrors lose fewer frames than 2;
ties where neither loses a frame are counted separately as ``both_lose_none``), and the
per-scenario distribution; plus the timing of one robust pose update for 4 cameras x 100
point-to-conic features. ``--quick``: 4 scenarios of 30 frames (20 of 60 otherwise).
"""

from __future__ import annotations

import os
import time

import numpy as np

from loopmodel.geometry.se3 import se3_exp
from loopmodel.pose.tracking import PolyhedronModel, sample_model_edges
from loopmodel.pose.vvs import LineTerm, VvsOptions, vvs_pose
from loopmodel.sim.omni import BOX_SIZE_M, box_trajectory, omni_sensor


def _pose_update_timing(repeats: int) -> dict[str, float]:
    """One robust VVS pose update (Tukey, from a pose 2 deg / 1 cm off) with 4 cameras x
    100 edge points (0.3 px noise, 10 % outliers)."""
    sensor = omni_sensor()
    model = PolyhedronModel.box(BOX_SIZE_M)
    rig = sensor.rig()
    rng = np.random.default_rng(0)
    T = box_trajectory(312)[60]
    s = sample_model_edges(rig, model, T, 2.0)
    idx = np.concatenate([rng.choice(np.flatnonzero(s.cam_index == j), 100, replace=False) for j in range(4)])
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
    from loopmodel.sim.omni_images import omni_scenario, track_scenario

    n_scen, n_frames = (4, 30) if quick else (20, 60)
    t0 = time.perf_counter()
    per = []
    rot4, pos4, it4, fr4, se4 = [], [], [], [], []
    init_rot = []
    for seed in range(n_scen):
        sc = omni_scenario(seed, n_frames)
        (r4, r2), ir, _ = track_scenario(sc)
        init_rot.append(ir)
        rot4.append(r4.rot_err_deg)
        pos4.append(r4.pos_err_mm)
        it4.append(r4.iter_ms)
        fr4.append(r4.frame_ms)
        se4.append(r4.search_ms)
        per.append(
            {
                "seed": seed,
                "clutter_behind_mirrors": list(sc.clutter_mirrors),
                "lost_4": int(r4.lost.sum()),
                "lost_2": int(r2.lost.sum()),
                "rot_err_deg_median_4": round(float(np.median(r4.rot_err_deg)), 3),
                "rot_err_deg_median_2": round(float(np.median(r2.rot_err_deg)), 3),
                "pos_err_mm_median_4": round(float(np.median(r4.pos_err_mm)), 2),
                "pos_err_mm_median_2": round(float(np.median(r2.pos_err_mm)), 2),
            }
        )
        print(per[-1], flush=True)
    lost4 = np.array([p["lost_4"] for p in per])
    lost2 = np.array([p["lost_2"] for p in per])
    out: dict = {
        "input": "images",
        "dataset": f"rendered 4-mirror omni-stereo images (xi=1, 1024x1024), {n_scen} seeded scenarios"
        f" x {n_frames} frames",
        "frames": int(n_scen * n_frames),
        "scenarios": n_scen,
        "init_rot_err_deg": round(float(np.min(init_rot)), 2),
        "init_pos_err_m": 0.025,
        "iter_ms_median": round(float(np.nanmedian(np.concatenate(it4))), 3),
        "me_search_ms_median": round(float(np.median(np.concatenate(se4))), 2),
        "frame_ms_median": round(float(np.median(np.concatenate(fr4))), 2),
        "rot_err_deg_median": round(float(np.median(np.concatenate(rot4))), 4),
        "pos_err_mm_median": round(float(np.median(np.concatenate(pos4))), 3),
        "rot_err_deg_p95": round(float(np.percentile(np.concatenate(rot4), 95)), 4),
        "pos_err_mm_p95": round(float(np.percentile(np.concatenate(pos4), 95)), 3),
        "lost_frames_4_mirrors": int(lost4.sum()),
        "lost_frames_2_mirrors": int(lost2.sum()),
        "four_beats_two_fraction": round(float(np.mean(lost4 < lost2)), 3),
        "four_ties_two_fraction": round(float(np.mean(lost4 == lost2)), 3),
        "both_lose_none": int(np.sum((lost4 == 0) & (lost2 == 0))),
        "lost_frames_4_by_scenario": lost4.tolist(),
        "lost_frames_2_by_scenario": lost2.tolist(),
        "scenario_results": per,
        "tracking_s": round(time.perf_counter() - t0, 1),
    }
    out.update(_pose_update_timing(30 if quick else 100))
    out["load_average_1min"] = round(os.getloadavg()[0], 2)
    return out
