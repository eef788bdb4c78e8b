"""Synthetic loop-closure problems of a given size (tests and benchmarks).

A stereo camera circles an object (features on a sphere), looking at its centre; every
keyframe triangulates its own feature set (stereo pixels with noise), the next keyframe
observes that set monocularly (seed 004's hybrid keyframe residuals), and the last keyframe
re-observes the first set (the loop). The dead-reckoning keyframe poses are the true ones
perturbed by an accumulating random walk, so the loop has something to correct.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import Y_DOWN_UP, invert_pose, look_at, se3_exp
from loopmodel.loop.global_ba import LoopObservations
from loopmodel.types import Keyframe

F64 = NDArray[np.float64]


@dataclass
class SynthLoopProblem:
    keyframes: list[Keyframe]
    loops: list[LoopObservations]
    true_world_from_kf: list[F64]
    fx_px: float
    cx_px: float
    cy_px: float
    baseline_m: float


def orbit_problem(
    n_keyframes: int = 44,
    features_per_kf: int = 41,
    radius_m: float = 0.5,
    object_radius_m: float = 0.15,
    noise_px: float = 0.5,
    drift_rot_rad: float = 0.004,
    drift_trans_m: float = 0.004,
    seed: int = 0,
    fx_px: float = 500.0,
    baseline_m: float = 0.05,
) -> SynthLoopProblem:
    """An orbit of ``n_keyframes`` keyframes (one full turn), ``features_per_kf`` new features each.

    The last keyframe closes the loop on the first feature set.
    """
    rng = np.random.default_rng(seed)
    cx, cy = 319.5, 239.5
    centre = np.zeros(3)
    true_T = []
    for i in range(n_keyframes):
        a = 2 * np.pi * i / n_keyframes
        eye = np.array([radius_m * np.sin(a), 0.05 * np.sin(3 * a), -radius_m * np.cos(a)])
        true_T.append(look_at(eye, centre, Y_DOWN_UP))
    # dead reckoning: the true relative motions perturbed, accumulated
    est_T = [true_T[0].copy()]
    for i in range(1, n_keyframes):
        rel = invert_pose(true_T[i - 1]) @ true_T[i]
        noise = np.concatenate([rng.normal(0, drift_trans_m, 3), rng.normal(0, drift_rot_rad, 3)])
        est_T.append(est_T[-1] @ rel @ se3_exp(noise))
    kfs: list[Keyframe] = []
    next_lid = 0
    sets: list[tuple[NDArray[np.int64], F64]] = []
    for i in range(n_keyframes):
        T = true_T[i]
        cam_from_world = invert_pose(T)
        # points on the visible half of the sphere
        pts: list[F64] = []
        while len(pts) < features_per_kf:
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            p = centre + object_radius_m * d
            pc = cam_from_world[:3, :3] @ p + cam_from_world[:3, 3]
            if np.dot(d, T[:3, 3] - p) > 0.2 * np.linalg.norm(T[:3, 3] - p) and pc[2] > 0.1:
                pts.append(p)
        P = np.array(pts)
        pc = P @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        uL = fx_px * pc[:, 0] / pc[:, 2] + cx + rng.normal(0, noise_px, len(P))
        uR = fx_px * (pc[:, 0] - baseline_m) / pc[:, 2] + cx + rng.normal(0, noise_px, len(P))
        v = fx_px * pc[:, 1] / pc[:, 2] + cy + rng.normal(0, noise_px, len(P))
        disp = np.maximum(uL - uR, 1e-3)
        z = fx_px * baseline_m / disp
        p_kf = np.column_stack([(uL - cx) * z / fx_px, (v - cy) * z / fx_px, z])
        ids = np.arange(next_lid, next_lid + len(P), dtype=np.int64)
        next_lid += len(P)
        sets.append((ids, P))
        mono = np.zeros((0, 3))
        if i > 0:
            pid, pP = sets[i - 1]
            q = pP @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
            ok = q[:, 2] > 0.05
            uv = fx_px * q[ok, :2] / q[ok, 2:] + [cx, cy] + rng.normal(0, noise_px, (ok.sum(), 2))
            mono = np.column_stack([pid[ok].astype(float), uv])
        kfs.append(Keyframe(i, i, est_T[i], ids, p_kf, np.column_stack([uL, uR, v]), mono))
    # loop: the last keyframe re-observes the first set
    last_cfw = invert_pose(true_T[-1])
    ids0, P0 = sets[0]
    q = P0 @ last_cfw[:3, :3].T + last_cfw[:3, 3]
    ok = q[:, 2] > 0.05
    uv = fx_px * q[ok, :2] / q[ok, 2:] + [cx, cy] + rng.normal(0, noise_px, (ok.sum(), 2))
    loops = [LoopObservations(n_keyframes - 1, ids0[ok], uv)]
    return SynthLoopProblem(kfs, loops, true_T, fx_px, cx, cy, baseline_m)
