"""Robust refinement of a camera pose from 2-D/3-D correspondences (after the P3P bank).

``refine_pose`` is the hook the relocalizer calls. Until the project's robust pose solver
(``loopmodel/pose/``, virtual visual servoing with M-estimators) is on main, it runs the
small Huber-IRLS Gauss-Newton below on tangent-plane ray errors; swap it by passing another
``PoseRefiner`` to :func:`loopmodel.loop.pnp.solve_pnp_bank`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import se3_exp

F64 = NDArray[np.float64]

#: (cam_from_world 4x4, unit rays (N, 3) in the camera frame, points (N, 3) in the world
#: frame [m], angular noise scale [rad]) -> refined cam_from_world.
PoseRefiner = Callable[[F64, F64, F64, float], F64]


def _tangent_basis(b: F64) -> tuple[F64, F64]:
    """Two unit vectors perpendicular to each unit ray (N, 3)."""
    helper = np.where(np.abs(b[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(b, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(b, e1)
    return e1, e2


def refine_pose_irls(
    cam_from_world: F64,
    rays_in_cam: F64,
    p_in_world: F64,
    sigma_rad: float,
    iterations: int = 10,
) -> F64:
    """Huber-weighted Gauss-Newton on the ray errors (radians, tangent plane of each ray).

    Returns the refined 4x4 ``cam_from_world``; the input is returned unchanged when there
    are fewer than 3 correspondences.
    """
    T = np.asarray(cam_from_world, dtype=float).copy()
    b = np.asarray(rays_in_cam, dtype=float).reshape(-1, 3)
    P = np.asarray(p_in_world, dtype=float).reshape(-1, 3)
    if b.shape[0] < 3:
        return T
    e1, e2 = _tangent_basis(b)
    k = 1.345 * max(sigma_rad, 1e-12)
    for _ in range(iterations):
        X = P @ T[:3, :3].T + T[:3, 3]
        rho = np.linalg.norm(X, axis=1)
        xh = X / rho[:, None]
        r = np.stack([np.sum(e1 * xh, axis=1), np.sum(e2 * xh, axis=1)], axis=1)  # (N, 2)
        # d xh / dX = (I - xh xh^T) / rho ; dX / d(v, w) = [I, -[X]x] (left perturbation).
        Pm = (np.eye(3)[None] - xh[:, :, None] * xh[:, None, :]) / rho[:, None, None]
        E = np.stack([e1, e2], axis=1)  # (N, 2, 3)
        A = E @ Pm  # (N, 2, 3)
        Xx = np.zeros((X.shape[0], 3, 3))
        Xx[:, 0, 1], Xx[:, 0, 2] = -X[:, 2], X[:, 1]
        Xx[:, 1, 0], Xx[:, 1, 2] = X[:, 2], -X[:, 0]
        Xx[:, 2, 0], Xx[:, 2, 1] = -X[:, 1], X[:, 0]
        J = np.concatenate([A, -A @ Xx], axis=2)  # (N, 2, 6)
        norm = np.linalg.norm(r, axis=1)
        w = np.where(norm <= k, 1.0, k / np.maximum(norm, 1e-300))
        Jw = J * w[:, None, None]
        Hm = np.einsum("nki,nkj->ij", Jw, J)
        g = np.einsum("nki,nk->i", Jw, r)
        try:
            delta = -np.linalg.solve(Hm + 1e-12 * np.trace(Hm) * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        T = se3_exp(delta) @ T
        if np.linalg.norm(delta) < 1e-10:
            break
    return T


#: The refiner used by default (replace with the loopmodel.pose solver once it is merged).
refine_pose: PoseRefiner = refine_pose_irls
