"""Local hybrid keyframe bundle adjustment (seed 004, eq. 1).

For one feature set i: its M 3-D points (keyframe i's rectified left camera frame) and the
transform ``f_from_kf`` to the final monocular frame (the left image of keyframe i+1)
are refined together from the left and right projections at keyframe i and the final
left projections. Minimal rotation parameters (a left twist on ``f_from_kf``), Huber loss,
analytic Jacobians, the points eliminated by the Schur complement (a 6x6 reduced system).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import se3_exp

F64 = NDArray[np.float64]


@dataclass
class HybridBAResult:
    """Refined ``f_from_kf`` (4x4), points (M, 3, metres, keyframe frame), iterations,
    RMS reprojection error (pixels) before and after, and per-point inlier flags."""

    f_from_kf: F64
    points_in_kf: F64
    iterations: int
    initial_rms_px: float
    final_rms_px: float
    inliers: NDArray[np.bool_]


def _huber_w(n: F64, k: float) -> F64:
    return np.where(n <= k, 1.0, k / np.maximum(n, 1e-300))


def _huber_rho(n: F64, k: float) -> F64:
    return np.where(n <= k, 0.5 * n * n, k * (n - 0.5 * k))


def hybrid_keyframe_ba(
    points_in_kf: F64,
    uv_left: F64,
    uv_right: F64,
    uv_final: F64,
    f_from_kf: F64,
    left: CentralCamera,
    right: CentralCamera,
    right_from_left: F64,
    iterations: int = 10,
    huber_px: float = 1.0,
) -> HybridBAResult:
    """Minimise eq. (1) of seed 004 over the points and ``f_from_kf``; all pixels are
    undistorted (rectified) coordinates."""
    X = np.asarray(points_in_kf, dtype=float).copy()
    T = np.asarray(f_from_kf, dtype=float).copy()
    R_rl, t_rl = right_from_left[:3, :3], right_from_left[:3, 3]
    meas = (uv_left, uv_right, uv_final)

    def residuals(Xc: F64, Tc: F64) -> tuple[F64, F64, F64, F64, F64]:
        pr = Xc @ R_rl.T + t_rl
        pf = Xc @ Tc[:3, :3].T + Tc[:3, 3]
        r = np.stack(
            [left.project(Xc) - meas[0], right.project(pr) - meas[1], left.project(pf) - meas[2]]
        )  # (3, M, 2)
        return r, pr, pf, np.linalg.norm(r, axis=2), Xc

    def cost_of(nrm: F64) -> float:
        return float(np.sum(_huber_rho(nrm, huber_px)))

    r, pr, pf, nrm, _ = residuals(X, T)
    init_rms = float(np.sqrt(np.mean(nrm**2)))
    cost = cost_of(nrm)
    lam = 1e-3
    it = 0
    for it in range(1, iterations + 1):
        w = _huber_w(nrm, huber_px)  # (3, M)
        JlX = left.project_jacobian(X)
        JrX = right.project_jacobian(pr) @ R_rl
        Jf = left.project_jacobian(pf)
        JfX = Jf @ T[:3, :3]
        Jfp = np.concatenate([Jf, np.cross(pf[:, None, :], Jf)], axis=2)  # (M, 2, 6)
        Hxx = (
            w[0, :, None, None] * np.einsum("mki,mkj->mij", JlX, JlX)
            + w[1, :, None, None] * np.einsum("mki,mkj->mij", JrX, JrX)
            + w[2, :, None, None] * np.einsum("mki,mkj->mij", JfX, JfX)
        )
        gx = (
            w[0, :, None] * np.einsum("mki,mk->mi", JlX, r[0])
            + w[1, :, None] * np.einsum("mki,mk->mi", JrX, r[1])
            + w[2, :, None] * np.einsum("mki,mk->mi", JfX, r[2])
        )
        Hpx = w[2, :, None, None] * np.einsum("mki,mkj->mij", Jfp, JfX)  # (M, 6, 3)
        Hpp = np.einsum("m,mki,mkj->ij", w[2], Jfp, Jfp)
        gp = np.einsum("m,mki,mk->i", w[2], Jfp, r[2])
        improved = False
        for _ in range(6):
            Hxx_d = Hxx + lam * (Hxx * np.eye(3)) + 1e-12 * np.eye(3)
            Hpp_d = Hpp + lam * np.diag(np.diag(Hpp)) + 1e-12 * np.eye(6)
            Hxx_inv = np.linalg.inv(Hxx_d)
            HpxHi = Hpx @ Hxx_inv  # (M, 6, 3)
            S = Hpp_d - np.einsum("mij,mkj->ik", HpxHi, Hpx)
            b = -gp + np.einsum("mij,mj->i", HpxHi, gx)
            try:
                dp = np.linalg.solve(S, b)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dx = -np.einsum("mij,mj->mi", Hxx_inv, gx + np.einsum("mji,j->mi", Hpx, dp))
            T_new = se3_exp(dp) @ T
            X_new = X + dx
            r_n, pr_n, pf_n, nrm_n, _ = residuals(X_new, T_new)
            valid = np.all(X_new[:, 2] > 0) and np.all(pf_n[:, 2] > 0)
            c_new = cost_of(nrm_n)
            if valid and c_new < cost:
                X, T, r, pr, pf, nrm = X_new, T_new, r_n, pr_n, pf_n, nrm_n
                converged = cost - c_new < 1e-6 * cost
                cost = c_new
                lam = max(lam * 0.3, 1e-9)
                improved = True
                break
            lam *= 10.0
        if not improved or converged:
            break
    inliers = np.all(nrm < 3.0 * huber_px, axis=0)
    return HybridBAResult(T, X, it, init_rms, float(np.sqrt(np.mean(nrm**2))), inliers)
