"""Benchmark ``mesh``: re-transform and re-mesh 10^6 synthetic laser-stripe points.

Scene: a sphere on a box (open3d primitives), scanned on an orbit by ray casting a light
plane (``loopmodel.mapping.synthetic``); stripes at frame times and between them; frames
hang off keyframes (one per 10 frames). The keyframes start drifted; the timed step is a
correction of every keyframe to ground truth (all stripes re-transformed) plus a full
Poisson re-mesh. Keys: points, remesh_s (median), mesh_err_mm_mean / _p95 (vertices of the
corrected mesh to the ground-truth surface), and more.
"""

from __future__ import annotations

import os
import time

import numpy as np
import open3d as o3d

from loopmodel.config import MappingConfig
from loopmodel.geometry.se3 import invert_pose, se3_exp
from loopmodel.mapping.accuracy import mesh_accuracy
from loopmodel.mapping.stripe_map import StripeMap
from loopmodel.mapping.synthetic import orbit_scan


def _scene() -> o3d.geometry.TriangleMesh:
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.05, 100).translate([0.0, -0.03, 0.0])
    box = o3d.geometry.TriangleMesh.create_box(0.12, 0.08, 0.12).translate([-0.06, 0.02, -0.06])
    return sphere + box


def run(quick: bool = False) -> dict:
    scene = _scene()
    frames, rays, reps = (300, 400, 2) if quick else (700, 1250, 3)
    t0 = time.perf_counter()
    traj, stripes = orbit_scan(scene, frames=frames, stripes_per_frame=2, rays=rays, height_m=-0.12)
    scan_s = time.perf_counter() - t0
    points = int(sum(s.points_in_cam.shape[0] for s in stripes))
    print(f"scan: {len(stripes)} stripes, {points} points, {scan_s:.1f} s", flush=True)

    cfg = MappingConfig()
    kf_every = 10
    gt = traj.world_from_cam
    kf_ids = np.arange(len(traj)) // kf_every
    n_kf = int(kf_ids[-1]) + 1
    # online drift: grows along the path up to ~4 mm and ~0.6 deg at the end
    drift = [se3_exp(np.array([0.004, -0.002, 0.003, 0.006, 0.004, -0.008]) * k / n_kf) for k in range(n_kf)]
    drifted = {k: drift[k] @ gt[k * kf_every] for k in range(n_kf)}
    truth = {k: gt[k * kf_every] for k in range(n_kf)}

    smap = StripeMap(cfg)
    for k in range(n_kf):
        smap.poses.set_keyframe(k, drifted[k])
    for i, (t, T) in enumerate(zip(traj.timestamps_ns, gt, strict=True)):
        k = int(kf_ids[i])
        smap.poses.add_frame(int(t), kf_id=k, kf_from_cam=invert_pose(gt[k * kf_every]) @ T)
    smap.add_many(stripes)

    # warm-up: the mesh with drifted (online) poses
    mesh_before = smap.mesh()
    before = mesh_accuracy(mesh_before, scene)
    print(f"drifted mesh: mean {before.mean_mm:.3f} mm, p95 {before.p95_mm:.3f} mm", flush=True)

    times, retransform, cpu = [], [], []
    mesh = mesh_before
    for _ in range(reps):
        smap.poses.update_keyframes(drifted)
        c0 = time.process_time()
        t0 = time.perf_counter()
        moved = smap.stripes_of_frames(smap.poses.update_keyframes(truth))
        t1 = time.perf_counter()
        mesh = smap.mesh()
        t2 = time.perf_counter()
        cpu.append(time.process_time() - c0)
        assert moved.size == smap.stripe_count
        retransform.append(t1 - t0)
        times.append(t2 - t0)
        print(f"re-transform {t1 - t0:.3f} s, re-mesh {t2 - t1:.3f} s", flush=True)
    after = mesh_accuracy(mesh, scene)
    load1, _, _ = os.getloadavg()
    return {
        "dataset": f"synthetic sphere-on-box orbit scan, {len(stripes)} stripes (ray-cast, noiseless)",
        "points": points,
        "remesh_s": round(float(np.median(times)), 3),
        "remesh_s_p95": round(float(np.percentile(times, 95)), 3),
        "remesh_cpu_s": round(float(np.median(cpu)), 3),
        "retransform_s": round(float(np.median(retransform)), 4),
        "mesh_err_mm_mean": round(after.mean_mm, 4),
        "mesh_err_mm_p95": round(after.p95_mm, 4),
        "mesh_err_before_mm_mean": round(before.mean_mm, 4),
        "mesh_err_before_mm_p95": round(before.p95_mm, 4),
        "completeness_2mm": round(after.completeness, 4),
        "mesh_vertices": after.vertices,
        "voxel_m": cfg.voxel_m,
        "method": cfg.method,
        "reps": reps,
        "load_avg_1min": round(load1, 2),
        "cpus": os.cpu_count(),
    }
