"""Robust refinement of a camera pose from 2-D/3-D correspondences (after the P3P bank).

The P3P bank calls a :data:`PoseRefiner`. :func:`project_refiner` wraps the project's
robust pose solver (``loopmodel.pose``, used by the front end as well); ``refine_pose``
(the default when no camera is at hand) is the small Huber-IRLS Gauss-Newton below on
tangent-plane ray errors, which works for any central camera.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import LoopmodelError
from loopmodel.geometry.camera import CentralCamera
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


def project_refiner(camera: CentralCamera) -> PoseRefiner:
    """A :data:`PoseRefiner` backed by the project's robust pose solver
    (``loopmodel.pose.refine_pose``: LM with a Huber loss at the given noise scale) for
    images of ``camera``; the rays are projected back to pixels for it. Falls back to
    :func:`refine_pose_irls` when ``loopmodel.pose`` is not installed in this build."""
    try:
        from loopmodel.pose import CameraRig, PointTerm, PoseOptions
        from loopmodel.pose import refine_pose as vvs_refine
    except ImportError:
        return refine_pose_irls
    rig = CameraRig.single(camera)
    f = max(camera.px, camera.py)

    def refine(cam_from_world: F64, rays_in_cam: F64, p_in_world: F64, sigma_rad: float) -> F64:
        if rays_in_cam.shape[0] < 3:
            return cam_from_world
        uv = camera.project(rays_in_cam)
        opts = PoseOptions(loss="huber", fixed_scale=max(sigma_rad * f, 1e-3))
        try:
            res = vvs_refine(PointTerm(rig, p_in_world, uv), cam_from_world, opts)
        except LoopmodelError:
            return refine_pose_irls(cam_from_world, rays_in_cam, p_in_world, sigma_rad)
        return np.asarray(res.rig_from_ref, dtype=float)

    return refine
