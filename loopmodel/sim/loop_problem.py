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

from loopmodel.frontend.stereo import triangulate_rectified
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


def _dead_reckoning(
    true_T: list[F64], rng: np.random.Generator, drift_trans_m: float, drift_rot_rad: float
) -> list[F64]:
    """world_from_kf of every keyframe: the true relative motions perturbed (m, rad per step), accumulated."""
    est_T = [true_T[0].copy()]
    for i in range(1, len(true_T)):
        rel = invert_pose(true_T[i - 1]) @ true_T[i]
        noise = np.concatenate([rng.normal(0, drift_trans_m, 3), rng.normal(0, drift_rot_rad, 3)])
        est_T.append(est_T[-1] @ rel @ se3_exp(noise))
    return est_T


def _triangulated(uL: F64, uR: F64, v: F64, fx_px: float, cx: float, cy: float, baseline_m: float) -> F64:
    """(N, 3) points (m) in the left camera frame from measured stereo pixels (disparity at least 1e-3 px)."""
    K = np.array([[fx_px, 0.0, cx], [0.0, fx_px, cy], [0.0, 0.0, 1.0]])
    return triangulate_rectified(np.column_stack([uL, v]), np.maximum(uL - uR, 1e-3), K, baseline_m)


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
    est_T = _dead_reckoning(true_T, rng, drift_trans_m, drift_rot_rad)
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
        p_kf = _triangulated(uL, uR, v, fx_px, cx, cy, baseline_m)
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


@dataclass
class SynthRoundsProblem:
    """A long multi-round keyframe scan for the back end (issue 33): keyframes and loop constraints.

    ``loops`` (query keyframe, old keyframe, ``query_from_old`` 4x4 metres, measured with noise)
    are listed at the query keyframe, in order; the keyframes' poses are dead reckoning.
    """

    keyframes: list[Keyframe]
    loops: list[tuple[int, int, F64]]
    true_world_from_kf: list[F64]


def rounds_problem(
    n_keyframes: int = 300,
    per_round: int = 25,
    features_per_kf: int = 300,
    local_map_kf: int = 4,
    loop_every_kf: int = 12,
    radius_m: float = 0.65,
    object_radius_m: float = 0.15,
    noise_px: float = 0.5,
    drift_rot_rad: float = 0.001,
    drift_trans_m: float = 0.001,
    loop_noise: float = 0.002,
    seed: int = 0,
    fx_px: float = 500.0,
    baseline_m: float = 0.06,
    revisit_points: int = 0,
) -> SynthRoundsProblem:
    """Rounds of ``per_round`` keyframes around a cylinder (radius ``object_radius_m``, 0.5 m tall).

    Each round at its own height and distance (world z up, object on z = 0); each keyframe
    triangulates ``features_per_kf`` new points of the surface it faces (stereo pixels with
    ``noise_px``) and observes the points of the ``local_map_kf`` keyframes before it
    monocularly (the front end's local map). From the second round on, every ``loop_every_kf``-th
    keyframe has a loop constraint to the keyframe of the previous round nearest in azimuth
    (its true relative pose perturbed by ``loop_noise`` rad and m). With ``revisit_points``, from
    the second round on each keyframe also observes monocularly up to that many points of the
    previous round's keyframe nearest in azimuth (the real scan's local map finds the old map's
    points when a round passes the views of an earlier one).
    """
    rng = np.random.default_rng(seed)
    cx, cy = 319.5, 239.5
    heights = (0.35, 0.49, 0.25, 0.42, 0.3)
    radii = (1.0, 1.2, 0.9, 1.35, 1.1)
    true_T: list[F64] = []
    azimuth: list[float] = []
    for i in range(n_keyframes):
        r, u = divmod(i, per_round)
        a = 2 * np.pi * u / per_round + 0.3 * r
        d = radius_m * radii[r % len(radii)]
        eye = np.array([d * np.cos(a), d * np.sin(a), heights[r % len(heights)]])
        true_T.append(look_at(eye, np.array([0.0, 0.0, 0.22])))
        azimuth.append(a)
    est_T = _dead_reckoning(true_T, rng, drift_trans_m, drift_rot_rad)

    def project(T: F64, P: F64) -> tuple[F64, NDArray[np.bool_]]:
        cfw = invert_pose(T)
        pc = P @ cfw[:3, :3].T + cfw[:3, 3]
        uv = fx_px * pc[:, :2] / pc[:, 2:] + [cx, cy]
        ok = (pc[:, 2] > 0.1) & (np.abs(uv[:, 0] - cx) < cx) & (np.abs(uv[:, 1] - cy) < cy)
        return np.column_stack([uv, pc[:, 2]]), ok

    kfs: list[Keyframe] = []
    sets: list[tuple[NDArray[np.int64], F64]] = []
    next_lid = 0
    for i in range(n_keyframes):
        T = true_T[i]
        eye = T[:3, 3]
        # points on the facing side of the cylinder, in view
        pts = np.zeros((0, 3))
        while pts.shape[0] < features_per_kf:
            phi = np.arctan2(eye[1], eye[0]) + rng.uniform(-1.2, 1.2, 4 * features_per_kf)
            z = rng.uniform(0.0, 0.5, phi.size)
            P = np.column_stack([object_radius_m * np.cos(phi), object_radius_m * np.sin(phi), z])
            _, ok = project(T, P)
            pts = np.vstack([pts, P[ok]])
        P = pts[:features_per_kf]
        uvz, _ = project(T, P)
        z = uvz[:, 2]
        uL = uvz[:, 0] + rng.normal(0, noise_px, len(P))
        uR = uvz[:, 0] - fx_px * baseline_m / z + rng.normal(0, noise_px, len(P))
        v = uvz[:, 1] + rng.normal(0, noise_px, len(P))
        p_kf = _triangulated(uL, uR, v, fx_px, cx, cy, baseline_m)
        ids = np.arange(next_lid, next_lid + len(P), dtype=np.int64)
        next_lid += len(P)
        mono = []
        for pid, pP in sets[max(0, i - local_map_kf) : i]:
            q, ok = project(T, pP)
            uv = q[ok, :2] + rng.normal(0, noise_px, (int(ok.sum()), 2))
            mono.append(np.column_stack([pid[ok].astype(float), uv]))
        if revisit_points > 0 and i >= per_round:
            r = i // per_round
            j = min(
                range((r - 1) * per_round, r * per_round),
                key=lambda k: abs(np.angle(np.exp(1j * (azimuth[k] - azimuth[i])))),
            )
            pid, pP = sets[j]
            q, ok = project(T, pP)
            sel = np.flatnonzero(ok)[:revisit_points]
            uv = q[sel, :2] + rng.normal(0, noise_px, (sel.size, 2))
            mono.append(np.column_stack([pid[sel].astype(float), uv]))
        sets.append((ids, P))
        prev_from_kf = invert_pose(est_T[i - 1]) @ est_T[i] if i else None
        kfs.append(
            Keyframe(
                i, i * 100_000_000, est_T[i], ids, p_kf, np.column_stack([uL, uR, v]),
                np.vstack(mono) if mono else np.zeros((0, 3)), frame_index=i,
                prev_keyframe_id=i - 1 if i else None, kf_prev_from_kf=prev_from_kf,
            )
        )
    loops: list[tuple[int, int, F64]] = []
    for i in range(per_round, n_keyframes, loop_every_kf):
        r = i // per_round
        old = range((r - 1) * per_round, r * per_round)
        j = min(old, key=lambda k: abs(np.angle(np.exp(1j * (azimuth[k] - azimuth[i])))))
        noise = rng.normal(0, loop_noise, 6)
        loops.append((i, j, invert_pose(true_T[i]) @ true_T[j] @ se3_exp(noise)))
    return SynthRoundsProblem(kfs, loops, true_T)
