"""The P3P bank.

P3P hypotheses from minimal samples, scored with early exit, then robust refinement.

Profiled on the fountain queries (cProfile), the former batch version spent its time in
numpy call overhead (stacked companion matrices, array temporaries for a few dozen
hypotheses) and in the general pose solver, far more than in arithmetic. The bank therefore
runs as compiled kernels (:mod:`loopmodel.loop.p3p_kernels`): each minimal sample goes
through the scalar Grunert solver, every pose is scored (MSAC cost on ray errors) over the
correspondences in a random order and abandoned as soon as its cost exceeds the best one's
(preemptive scoring that cannot change the winner), and sampling stops at the usual RANSAC
bound for the best inlier ratio so far (adaptive sample count). The best pose is refined on
its inliers (robust Gauss-Newton on ray errors, or a given :data:`PoseRefiner`), inliers are
re-selected and the pose refined again.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import InputError
from loopmodel.loop.p3p_kernels import inlier_mask, ransac_p3p, refine_rays
from loopmodel.loop.refine import PoseRefiner

F64 = NDArray[np.float64]

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


def solve_pnp_bank(
    rays_in_cam: F64,
    p_in_world: F64,
    threshold_rad: float,
    rng: np.random.Generator | None = None,
    max_samples: int = 4096,
    confidence: float = 0.999,
    min_inliers: int = 6,
    refiner: PoseRefiner | None = None,
) -> PnPResult | None:
    """Camera pose from M 2-D/3-D correspondences with outliers.

    ``rays_in_cam``: (M, 3) unit rays of the observed features (camera frame, e.g. from
    ``CentralCamera.lift``); ``p_in_world``: (M, 3) points (metres); ``threshold_rad``: the
    inlier bound on the ray angle (a pixel threshold divided by the focal length).
    ``refiner``: the final refinement; ``None``: robust Gauss-Newton on the ray errors
    (any central camera). Returns ``None`` when fewer than ``min_inliers`` support the
    best pose.
    """
    rays = np.asarray(rays_in_cam, dtype=float).reshape(-1, 3)
    P = np.asarray(p_in_world, dtype=float).reshape(-1, 3)
    if rays.shape[0] != P.shape[0]:
        raise InputError("solve_pnp_bank", f"{rays.shape[0]} rays but {P.shape[0]} points")
    m = rays.shape[0]
    if m < 3:
        return None
    rays = np.ascontiguousarray(rays / np.linalg.norm(rays, axis=1, keepdims=True))
    P = np.ascontiguousarray(P)
    rng = rng if rng is not None else np.random.default_rng(0)
    thr2 = float(np.sin(threshold_rad) ** 2)
    t0 = time.perf_counter()
    order = rng.permutation(m).astype(np.int64)
    seed = int(rng.integers(2**31 - 1))
    best_R, best_t, best_n, samples, poses = ransac_p3p(rays, P, thr2, int(max_samples), float(confidence), seed, order)
    bank_s = time.perf_counter() - t0
    if best_n < 3:
        return None
    R, t = best_R, best_t
    sigma = threshold_rad / 2.0
    inl = inlier_mask(R, t, rays, P, thr2)
    for _ in range(2):  # refine, re-select the inliers, refine again if they changed
        if inl.sum() < 3:
            break
        if refiner is None:
            R, t = refine_rays(R, t, np.ascontiguousarray(rays[inl]), np.ascontiguousarray(P[inl]), sigma, 10)
        else:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            T = refiner(T, rays[inl], P[inl], sigma)
            R, t = np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3])
        new = inlier_mask(R, t, rays, P, thr2)
        changed = int(np.sum(new != inl))
        inl = new
        if changed <= 0.02 * max(int(inl.sum()), 1):
            break
    total_s = time.perf_counter() - t0
    if inl.sum() < min_inliers:
        return None
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return PnPResult(T, inl, samples, poses, bank_s, total_s)


def warm_up() -> None:
    """Load (or compile) the bank's kernels with one small synthetic solve.

    Their first call in a process costs about 0.9 s of CPU (numba's cache load; measured on the
    shared 2-core machine), which otherwise lands in the frame of the first loop verification.
    """
    rng = np.random.default_rng(0)
    p = rng.uniform(-1.0, 1.0, (12, 3)) + np.array([0.0, 0.0, 5.0])
    solve_pnp_bank(p / np.linalg.norm(p, axis=1, keepdims=True), p, 0.002, rng=np.random.default_rng(1),
                   max_samples=16, min_inliers=3)
