"""Rig calibration by virtual visual servoing (seed 002, eq. 16).

The intrinsics ``gamma_j = (px, py, u0, v0, xi)`` of every camera and the rig transforms ``jM1``
(``cam_from_rig[j]``, camera 1 = rig frame, fixed) from known 3-D points seen in several views of a
calibration object (one unknown ``rig_from_ref`` per view).

``ds/dt = L_s v + (ds/dgamma) dgamma/dt``: the pose part is the point interaction matrix of
:mod:`loopmodel.pose.vvs` (here as the Jacobian of a left twist, ``J = -L``); the intrinsic
part is ``du/dgamma = [x, 0, 1, 0, px dx/dxi]``, ``dx/dxi = -x rho / (Z + xi rho)``. All
parameters are updated together by damped, robustly weighted Gauss-Newton (Huber, MAD scale).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import CalibrationError
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import se3_exp
from loopmodel.pose.rig import F64, CameraRig
from loopmodel.pose.robust import Loss, default_cutoff, robust_scale, weights


@dataclass
class CalibrationView:
    """One view of a known object.

    Points ``p_in_ref`` (N x 3, metres, object frame) observed at ``uv_px`` (N x 2) by camera
    ``cam_index`` (N,).
    """

    p_in_ref: F64
    uv_px: F64
    cam_index: NDArray[np.int64]


@dataclass
class RigCalibration:
    """Calibrated rig, per-view poses ``rig_from_ref``, final RMS reprojection error of
    the inliers (pixels) and the number of iterations."""

    rig: CameraRig
    rig_from_ref: list[F64]
    rms_px: float
    iterations: int
    converged: bool


def _gamma_jacobian(cam: CentralCamera, P: F64) -> tuple[F64, F64]:
    """Pixels (K x 2) and their Jacobian (K x 2 x 5) w.r.t. (px, py, u0, v0, xi)."""
    rho = np.linalg.norm(P, axis=1)
    d = P[:, 2] + cam.xi * rho
    x, y = P[:, 0] / d, P[:, 1] / d
    J = np.zeros((P.shape[0], 2, 5))
    J[:, 0, 0] = x
    J[:, 0, 2] = 1.0
    J[:, 0, 4] = -cam.px * x * rho / d
    J[:, 1, 1] = y
    J[:, 1, 3] = 1.0
    J[:, 1, 4] = -cam.py * y * rho / d
    uv = np.column_stack([cam.px * x + cam.u0, cam.py * y + cam.v0])
    return uv, J


def calibrate_rig(
    views: Sequence[CalibrationView],
    rig_init: CameraRig,
    rig_from_ref_init: Sequence[F64],
    estimate_intrinsics: bool = True,
    estimate_extrinsics: bool = True,
    loss: Loss = "huber",
    max_iterations: int = 100,
    tolerance: float = 1e-10,  # on |delta| and on the relative cost decrease
    min_scale_px: float = 0.1,
) -> RigCalibration:
    """Calibrate ``gamma_j`` and ``jM1`` (j >= 2) of an N-camera rig from known points."""
    if len(views) != len(rig_from_ref_init) or not views:
        raise CalibrationError("calibration", "one initial pose per view is needed")
    n_cam = len(rig_init)
    n_g = 5 * n_cam if estimate_intrinsics else 0
    n_e = 6 * (n_cam - 1) if estimate_extrinsics else 0
    n_par = n_g + n_e + 6 * len(views)
    n_obs = sum(len(v.uv_px) for v in views)
    if 2 * n_obs < n_par + 6:
        raise CalibrationError("calibration", f"{n_obs} observations for {n_par} unknowns")
    gammas = [np.array([c.px, c.py, c.u0, c.v0, c.xi], dtype=float) for c in rig_init.cameras]
    extr = [np.asarray(T, dtype=float).copy() for T in rig_init.cam_from_rig]
    poses = [np.asarray(T, dtype=float).copy() for T in rig_from_ref_init]
    c = default_cutoff(loss)

    def evaluate(
        gam: list[F64], ext: list[F64], pos: list[F64], jac: bool
    ) -> tuple[F64, F64 | None]:
        res = np.empty(2 * n_obs)
        J = np.zeros((2 * n_obs, n_par)) if jac else None
        row = 0
        for v, view in enumerate(views):
            T = pos[v]
            p_rig = view.p_in_ref @ T[:3, :3].T + T[:3, 3]
            for j in range(n_cam):
                idx = np.flatnonzero(view.cam_index == j)
                if idx.size == 0:
                    continue
                E = ext[j]
                p_cam = p_rig[idx] @ E[:3, :3].T + E[:3, 3]
                cam = CentralCamera(*gam[j])
                uv, Jg = _gamma_jacobian(cam, p_cam)
                rows = row + 2 * np.arange(idx.size)
                rr = np.empty(2 * idx.size)
                rr[0::2] = uv[:, 0] - view.uv_px[idx, 0]
                rr[1::2] = uv[:, 1] - view.uv_px[idx, 1]
                res[row : row + 2 * idx.size] = rr
                if J is not None:
                    Jp = cam.project_jacobian(p_cam)
                    blocks = []
                    if n_g:
                        blocks.append((5 * j, Jg))
                    if n_e and j > 0:
                        Je = np.concatenate([Jp, np.cross(p_cam[:, None, :], Jp)], axis=2)
                        blocks.append((n_g + 6 * (j - 1), Je))
                    A = Jp @ E[:3, :3]
                    Jv = np.concatenate([A, np.cross(p_rig[idx][:, None, :], A)], axis=2)
                    blocks.append((n_g + n_e + 6 * v, Jv))
                    for col, B in blocks:
                        w = B.shape[2]
                        J[rows, col : col + w] = B[:, 0]
                        J[rows + 1, col : col + w] = B[:, 1]
                row += 2 * idx.size
        return res[:row], (J[:row] if J is not None else None)

    def apply(delta: F64) -> tuple[list[F64], list[F64], list[F64]]:
        gam = [g + delta[5 * j : 5 * j + 5] if n_g else g.copy() for j, g in enumerate(gammas)]
        ext = [extr[0].copy()]
        for j in range(1, n_cam):
            if n_e:
                ext.append(se3_exp(delta[n_g + 6 * (j - 1) : n_g + 6 * j]) @ extr[j])
            else:
                ext.append(extr[j].copy())
        pos = [se3_exp(delta[n_g + n_e + 6 * v : n_g + n_e + 6 * v + 6]) @ T for v, T in enumerate(poses)]
        return gam, ext, pos

    lam = 1e-3
    converged = False
    it = 0
    scale = min_scale_px
    while it < max_iterations:
        it += 1
        r, J = evaluate(gammas, extr, poses, True)
        assert J is not None
        n = np.hypot(r[0::2], r[1::2])
        scale = robust_scale(n, 2, min_scale_px)
        w = np.repeat(weights(n / scale, loss, c), 2)
        Jw = J * w[:, None]
        # einsum (no BLAS threads): a multi-threaded GEMM is very slow on a loaded machine
        H = np.einsum("ij,ik->jk", Jw, J)
        g = np.einsum("ij,i->j", Jw, r)
        cost = float(np.sum(w * r * r))
        improved = False
        for _ in range(10):
            Hd = H + lam * np.diag(np.maximum(np.diag(H), 1e-12))
            try:
                delta = -np.linalg.solve(Hd, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            gam, ext, pos = apply(delta)
            r_new, _ = evaluate(gam, ext, pos, False)
            if np.all(np.isfinite(r_new)) and float(np.sum(w * r_new * r_new)) <= cost:
                gammas, extr, poses = gam, ext, pos
                lam = max(lam * 0.2, 1e-12)
                improved = True
                break
            lam *= 10
        if not improved or float(np.linalg.norm(delta)) < tolerance:
            converged = True
            break
        if cost - float(np.sum(w * r_new * r_new)) < tolerance * max(cost, 1e-30):
            converged = True  # relative cost decrease below the tolerance
            break
    r, _ = evaluate(gammas, extr, poses, False)
    n = np.hypot(r[0::2], r[1::2])
    inl = n < c * scale if loss != "l2" else np.ones_like(n, dtype=bool)
    rms = float(np.sqrt(np.mean(n[inl] ** 2))) if inl.any() else float("inf")
    rig = CameraRig(tuple(CentralCamera(*g) for g in gammas), tuple(extr))
    return RigCalibration(rig, poses, rms, it, converged)
