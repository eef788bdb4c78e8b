"""The P3P bank: many P3P hypotheses solved and scored at once, then robust refinement.

Minimal samples are drawn in batches; each batch goes through the vectorised Grunert
solver (:mod:`loopmodel.loop.p3p`) and every resulting pose is scored against every
correspondence in one array operation (MSAC cost on ray errors). Batches continue until
the usual RANSAC bound for the best inlier ratio is met. The best pose is refined on its
inliers with the pose refiner (:mod:`loopmodel.loop.refine`), inliers are re-selected and
the pose refined again.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import InputError
from loopmodel.loop.p3p import p3p_grunert
from loopmodel.loop.refine import PoseRefiner, refine_pose

F64 = NDArray[np.float64]

#: Poses scored per array operation (keeps the temporaries in cache).
_CHUNK = 24
#: Correspondences of the preemptive test.
_PRE = 48


@dataclass
class PnPResult:
    """Outcome of :func:`solve_pnp_bank`.

    ``cam_from_world`` is 4x4 (metres), ``inliers`` a boolean mask over the input
    correspondences; ``samples`` minimal samples and ``poses`` candidate poses were scored
    in ``bank_s`` seconds (refinement excluded), ``total_s`` includes refinement.
    """

    cam_from_world: F64
    inliers: NDArray[np.bool_]
    samples: int
    poses: int
    bank_s: float
    total_s: float

    @property
    def n_inliers(self) -> int:
        """Number of inlier correspondences."""
        return int(self.inliers.sum())


def ray_errors(R: F64, t: F64, rays: NDArray[np.floating], p_in_world: NDArray[np.floating]) -> NDArray[np.floating]:
    """Squared sines of the angles between observed unit rays (M, 3) and the directions of
    world points (M, 3) under each of H poses (``R`` (H, 3, 3), ``t`` (H, 3)) -> (H, M).
    Points behind the camera (negative along the observed ray) get an error of 4. The
    arithmetic runs in the dtype of ``p_in_world`` (float32 for fast bulk scoring)."""
    H = R.shape[0]
    dt = p_in_world.dtype
    X = (R.astype(dt).reshape(3 * H, 3) @ p_in_world.T).reshape(H, 3, -1)
    X += t.astype(dt)[:, :, None]
    X0, X1, X2 = X[:, 0], X[:, 1], X[:, 2]
    bx, by, bz = rays[:, 0], rays[:, 1], rays[:, 2]
    dot = X0 * bx + X1 * by + X2 * bz
    c = by * X2 - bz * X1
    s2 = c * c
    c = bz * X0 - bx * X2
    s2 += c * c
    c = bx * X1 - by * X0
    s2 += c * c
    s2 /= np.maximum(X0 * X0 + X1 * X1 + X2 * X2, 1e-30)
    return np.where(dot > 0, s2, 4.0)


def _draw_samples(rng: np.random.Generator, m: int, n: int) -> NDArray[np.int64]:
    """n triples of distinct indices in [0, m)."""
    out = np.empty((0, 3), dtype=np.int64)
    while out.shape[0] < n:
        s = rng.integers(0, m, size=(2 * (n - out.shape[0]) + 8, 3))
        ok = (s[:, 0] != s[:, 1]) & (s[:, 0] != s[:, 2]) & (s[:, 1] != s[:, 2])
        out = np.concatenate([out, s[ok]])
    return out[:n]


def solve_pnp_bank(
    rays_in_cam: F64,
    p_in_world: F64,
    threshold_rad: float,
    rng: np.random.Generator | None = None,
    batch: int = 16,
    max_samples: int = 4096,
    confidence: float = 0.999,
    min_inliers: int = 6,
    refiner: PoseRefiner | None = None,
) -> PnPResult | None:
    """Camera pose from M 2-D/3-D correspondences with outliers.

    ``rays_in_cam``: (M, 3) unit rays of the observed features (camera frame, e.g. from
    ``CentralCamera.lift``); ``p_in_world``: (M, 3) points (metres); ``threshold_rad``: the
    inlier bound on the ray angle (a pixel threshold divided by the focal length).
    Returns ``None`` when fewer than ``min_inliers`` support the best pose.
    """
    rays = np.asarray(rays_in_cam, dtype=float).reshape(-1, 3)
    P = np.asarray(p_in_world, dtype=float).reshape(-1, 3)
    if rays.shape[0] != P.shape[0]:
        raise InputError("solve_pnp_bank", f"{rays.shape[0]} rays but {P.shape[0]} points")
    m = rays.shape[0]
    if m < 3:
        return None
    rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    rng = rng if rng is not None else np.random.default_rng(0)
    refiner = refiner if refiner is not None else refine_pose
    thr2 = float(np.sin(threshold_rad) ** 2)
    t0 = time.perf_counter()
    best_cost = np.inf
    best_R = np.eye(3)
    best_t = np.zeros(3)
    best_n = 0
    samples = 0
    poses = 0
    needed = max_samples
    # Score against a fixed random subset of at most 2000 correspondences per round (the
    # final inlier set uses all of them).
    score_idx = rng.permutation(m)[:2000]
    n_pre = min(_PRE, score_idx.size)
    rays32 = np.ascontiguousarray(rays[score_idx], dtype=np.float32)
    P32 = np.ascontiguousarray(P[score_idx], dtype=np.float32)
    while samples < min(needed, max_samples):
        n = min(max(batch, min(samples, 1024)), max_samples - samples)  # growing batches
        idx = _draw_samples(rng, m, n)
        sol = p3p_grunert(rays[idx], P[idx])
        samples += n
        Rv = sol.R[sol.valid]
        tv = sol.t[sol.valid]
        poses += int(Rv.shape[0])
        # Preemptive test on the first n_pre correspondences (random order): only poses
        # that could plausibly match the best inlier ratio so far are scored on all.
        w_best = best_n / score_idx.size
        if w_best > 0 and score_idx.size > 2 * n_pre and Rv.shape[0]:
            pre_ok = np.zeros(Rv.shape[0], bool)
            for c0 in range(0, Rv.shape[0], 4 * _CHUNK):
                e2p = ray_errors(Rv[c0 : c0 + 4 * _CHUNK], tv[c0 : c0 + 4 * _CHUNK], rays32[:n_pre], P32[:n_pre])
                pre_ok[c0 : c0 + 4 * _CHUNK] = (e2p < thr2).sum(axis=1) >= max(2.0, 0.5 * w_best * n_pre)
            Rv, tv = Rv[pre_ok], tv[pre_ok]
        for c0 in range(0, Rv.shape[0], _CHUNK):
            e2 = ray_errors(Rv[c0 : c0 + _CHUNK], tv[c0 : c0 + _CHUNK], rays32, P32)
            cost = np.minimum(e2, thr2).sum(axis=1)
            k = int(np.argmin(cost))
            if cost[k] < best_cost:
                best_cost = float(cost[k])
                best_R = Rv[c0 + k]
                best_t = tv[c0 + k]
                best_n = int(np.sum(e2[k] < thr2))
        w = best_n / max(score_idx.size, 1)
        if w > 0 and confidence < 1.0:
            p_good = w**3
            needed = int(np.ceil(np.log(1 - confidence) / np.log(max(1e-12, 1 - p_good)))) if p_good < 1 else 0
    bank_s = time.perf_counter() - t0
    if best_n < 3:
        return None
    T = np.eye(4)
    T[:3, :3] = best_R
    T[:3, 3] = best_t
    sigma = threshold_rad / 2.0
    inl = ray_errors(T[None, :3, :3], T[None, :3, 3], rays, P)[0] < thr2
    for _ in range(2):  # refine, re-select the inliers, refine again if they changed
        if inl.sum() < 3:
            break
        T = refiner(T, rays[inl], P[inl], sigma)
        new = ray_errors(T[None, :3, :3], T[None, :3, 3], rays, P)[0] < thr2
        changed = int(np.sum(new != inl))
        inl = new
        if changed <= 0.02 * max(int(inl.sum()), 1):
            break
    total_s = time.perf_counter() - t0
    if inl.sum() < min_inliers:
        return None
    return PnPResult(T, inl, samples, poses, bank_s, total_s)
