"""Local hybrid keyframe bundle adjustment (seed 004, eq. 1).

For one feature set i: its M 3-D points (keyframe i's rectified left camera frame) and the
transform ``f_from_kf`` to the final monocular frame (the left image of keyframe i+1)
are refined together from the left and right projections at keyframe i and the final
left projections. Optionally (an extension of eq. 1) the final right projections too, when
the final frame is a stereo keyframe: this anchors the scale at both ends of the set.
Minimal rotation parameters (a left twist on ``f_from_kf``), Huber loss, analytic
Jacobians, the points eliminated by the Schur complement (a 6x6 reduced system).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import se3_exp
from loopmodel.pose.rig import point_cross_rows

F64 = NDArray[np.float64]


@dataclass
class HybridBAResult:
    """Refined ``f_from_kf`` (4x4), points, iterations, RMS errors and inlier flags.

    Points (M, 3, metres, keyframe frame), RMS reprojection error (pixels) before and after, and
    per-point inlier flags.
    """

    f_from_kf: F64
    points_in_kf: F64
    iterations: int
    initial_rms_px: float
    final_rms_px: float
    inliers: NDArray[np.bool_]
    # with estimate_disparity_offset: the right images' column offset (px; measured = projected + offset)
    # and its variance (px^2, the normal equations' inverse times the residual variance per coordinate)
    disparity_offset_px: float = 0.0
    disparity_offset_var_px2: float = float("inf")


def _huber_w(n: F64, k: float) -> F64:
    return np.where(n <= k, 1.0, k / np.maximum(n, 1e-300))


def _huber_rho(n: F64, k: float) -> F64:
    return np.where(n <= k, 0.5 * n * n, k * (n - 0.5 * k))


def _relative_weights(sigma_px: F64 | None) -> F64 | None:
    """(median / sigma)^2 clipped to [1/4, 4]; None stays None."""
    if sigma_px is None or len(sigma_px) == 0:
        return None
    s = np.asarray(sigma_px, dtype=float)
    return np.clip((np.median(s) / np.maximum(s, 1e-9)) ** 2, 0.25, 4.0)


@dataclass
class _Block:
    camera: CentralCamera
    fixed: F64  # camera_from_(kf or final left) transform, 4x4
    moving: bool  # True: the block's camera sees the points through f_from_kf
    is_right: bool  # a right image: its column carries the disparity offset
    uv: F64  # (M, 2) measurements
    valid: F64  # (M,) 1.0 where measured
    weight: F64 | None = None  # (M,) relative weights (inverse variances); None: 1


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
    uv_final_right: F64 | None = None,
    right_sigma_px: F64 | None = None,
    estimate_disparity_offset: bool = False,
    offset_prior: tuple[float, float] = (0.0, 0.0),
    owner: NDArray[np.int64] | None = None,
    own_from_kf: F64 | None = None,
) -> HybridBAResult:
    """Minimise eq. (1) of seed 004 over the points and ``f_from_kf``.

    All pixels are undistorted (rectified) coordinates. ``uv_final_right`` (M, 2; NaN rows where
    unmatched) adds the final right projections. ``right_sigma_px`` (M,): each point's disparity
    standard deviation (px, from its stereo match): its keyframe right projection is weighted by
    (median / own)^2, clipped to [1/4, 4], so a doubtful match counts less (issue 36).
    ``estimate_disparity_offset`` adds one unknown: a column offset of every right projection (a
    disparity offset, e.g. from an error in the right camera's principal point), observable from
    the motion parallax of points at different depths (issue 36); ``offset_prior`` = (mean px,
    information 1/px^2) is a Gaussian prior on it, and the result's variance is the posterior's.
    A wider window (issue 36, item 4): ``owner`` (M,) names the keyframe whose stereo pair
    measured each point's ``uv_left``/``uv_right``, and ``own_from_kf`` (K, 4, 4) those keyframes'
    left cameras from keyframe i's (held fixed; owner 0 is keyframe i itself, identity);
    ``uv_final`` may then have NaN rows (not seen at the end).
    """
    X = np.asarray(points_in_kf, dtype=float).copy()
    T = np.asarray(f_from_kf, dtype=float).copy()
    M = X.shape[0]
    rfl = np.asarray(right_from_left, dtype=float)
    own = np.zeros(M, np.int64) if owner is None else np.asarray(owner, np.int64)
    frames = np.eye(4)[None] if own_from_kf is None else np.asarray(own_from_kf, float).reshape(-1, 4, 4)
    uv_f = np.asarray(uv_final, float)
    right_w = _relative_weights(right_sigma_px)
    blocks = []
    for k, own_from in enumerate(frames):
        valid = (own == k).astype(float)
        if valid.any():
            blocks.append(_Block(left, own_from, False, False, np.asarray(uv_left, float), valid))
            blocks.append(_Block(right, rfl @ own_from, False, True, np.asarray(uv_right, float), valid, right_w))
    f_valid = np.all(np.isfinite(uv_f), axis=1).astype(float)
    blocks.append(_Block(left, np.eye(4), True, False, np.where(np.isfinite(uv_f), uv_f, 0.0), f_valid))
    if uv_final_right is not None:
        fr = np.asarray(uv_final_right, dtype=float)
        valid = np.all(np.isfinite(fr), axis=1).astype(float)
        blocks.append(_Block(right, rfl, True, True, np.where(np.isfinite(fr), fr, 0.0), valid))

    Eval = list[tuple[F64, F64, F64 | None, F64 | None]]
    n_par = 7 if estimate_disparity_offset else 6
    delta = 0.0

    def evaluate(Xc: F64, Tc: F64, jac: bool, dc: float) -> Eval:
        pf = Xc @ Tc[:3, :3].T + Tc[:3, 3]
        out: Eval = []
        for b in blocks:
            base = pf if b.moving else Xc
            p = base @ b.fixed[:3, :3].T + b.fixed[:3, 3]
            # rows a block does not measure are projected from a harmless point (no inf, no NaN)
            p = np.where(b.valid[:, None] > 0, p, np.array([0.0, 0.0, 1.0]))
            pr = b.camera.project(p)
            if b.is_right and dc != 0.0:
                pr[:, 0] += dc
            r = (pr - b.uv) * b.valid[:, None]
            if not jac:
                out.append((r, p, None, None))
                continue
            Jc = b.camera.project_jacobian(p) @ b.fixed[:3, :3]  # d uv / d base point
            JX = Jc @ Tc[:3, :3] if b.moving else Jc
            Jp: F64 | None = None
            if b.moving or (b.is_right and n_par == 7):
                Jp = np.zeros((M, 2, n_par))
                if b.moving:
                    Jp[:, :, :6] = np.concatenate([Jc, point_cross_rows(pf, Jc)], axis=2)
                if b.is_right and n_par == 7:
                    Jp[:, 0, 6] = b.valid
            out.append((r, p, JX, Jp))
        return out

    def norms(ev: Eval) -> F64:
        return np.stack([np.linalg.norm(e[0], axis=1) for e in ev])

    def cost_of(nrm: F64) -> float:
        return float(np.sum(_huber_rho(nrm, huber_px)))

    ev = evaluate(X, T, True, delta)
    nrm = norms(ev)
    valid_all = np.stack([b.valid for b in blocks]) > 0
    init_rms = float(np.sqrt(np.mean(nrm[valid_all] ** 2)))
    # the prior in the cost's units (pixels^2): scaled by the residual variance per coordinate, from
    # the starting residuals (conservative: they carry the tracked pose's error too); the posterior
    # variance uses the same scale
    prior_mean, prior_info = offset_prior
    dof = max(int(valid_all.sum()) * 2 - 3 * M - n_par, 1)
    sigma2 = max(float(np.sum(nrm**2)) / dof, 0.01)
    prior_w = prior_info * sigma2 if n_par == 7 else 0.0

    def prior_cost(dc: float) -> float:
        return 0.5 * prior_w * (dc - prior_mean) ** 2

    cost = cost_of(nrm) + prior_cost(delta)
    lam = 1e-3
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 (it is reported)
        w = _huber_w(nrm, huber_px) * np.stack([b.valid if b.weight is None else b.valid * b.weight for b in blocks])
        Hxx = np.zeros((M, 3, 3))
        gx = np.zeros((M, 3))
        Hpx = np.zeros((M, n_par, 3))
        Hpp = np.zeros((n_par, n_par))
        gp = np.zeros(n_par)
        for k, (r, _p, JX, Jp) in enumerate(ev):
            assert JX is not None
            wk = w[k]
            JXw = JX * wk[:, None, None]
            Hxx += np.matmul(JXw.transpose(0, 2, 1), JX)
            gx += np.einsum("mki,mk->mi", JXw, r)
            if Jp is not None:
                Jpw = Jp * wk[:, None, None]
                Hpx += np.matmul(Jpw.transpose(0, 2, 1), JX)
                Hpp += np.einsum("mki,mkj->ij", Jpw, Jp)
                gp += np.einsum("mki,mk->i", Jpw, r)
        if prior_w > 0:
            Hpp[6, 6] += prior_w
            gp[6] += prior_w * (delta - prior_mean)
        improved = False
        converged = False
        for _ in range(6):
            Hxx_d = Hxx + lam * (Hxx * np.eye(3)) + 1e-9 * np.eye(3)
            Hpp_d = Hpp + lam * np.diag(np.diag(Hpp)) + 1e-12 * np.eye(n_par)
            Hxx_inv = np.linalg.inv(Hxx_d)
            HpxHi = np.matmul(Hpx, Hxx_inv)  # (M, 6, 3)
            S = Hpp_d - np.einsum("mij,mkj->ik", HpxHi, Hpx)
            b = -gp + np.einsum("mij,mj->i", HpxHi, gx)
            try:
                dp = np.linalg.solve(S, b)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dx = -np.einsum("mij,mj->mi", Hxx_inv, gx + np.einsum("mji,j->mi", Hpx, dp))
            T_new = se3_exp(dp[:6]) @ T
            X_new = X + dx
            d_new = delta + (float(dp[6]) if n_par == 7 else 0.0)
            ev_new = evaluate(X_new, T_new, False, d_new)
            nrm_new = norms(ev_new)
            in_front = all(np.all(e[1][:, 2] > 0) for e in ev_new)
            c_new = cost_of(nrm_new) + prior_cost(d_new)
            if in_front and c_new < cost:
                X, T, nrm, delta = X_new, T_new, nrm_new, d_new
                converged = cost - c_new < 1e-4 * cost
                cost = c_new
                lam = max(lam * 0.3, 1e-9)
                improved = True
                break
            lam *= 10.0
        if not improved or converged:
            break
        ev = evaluate(X, T, True, delta)
    inliers = np.all((nrm < 3.0 * huber_px) | ~valid_all, axis=0)
    final_rms = float(np.sqrt(np.mean(nrm[valid_all] ** 2)))
    var = float("inf")
    if n_par == 7:
        # the offset's variance: the reduced system at the solution (Huber weights), scaled by the
        # residual variance per coordinate
        w = _huber_w(nrm, huber_px) * np.stack([b.valid if b.weight is None else b.valid * b.weight for b in blocks])
        ev = evaluate(X, T, True, delta)
        Hxx = np.zeros((M, 3, 3))
        Hpx = np.zeros((M, n_par, 3))
        Hpp = np.zeros((n_par, n_par))
        for k, (_r, _p, JX, Jp) in enumerate(ev):
            assert JX is not None
            JXw = JX * w[k][:, None, None]
            Hxx += np.matmul(JXw.transpose(0, 2, 1), JX)
            if Jp is not None:
                Jpw = Jp * w[k][:, None, None]
                Hpx += np.matmul(Jpw.transpose(0, 2, 1), JX)
                Hpp += np.einsum("mki,mkj->ij", Jpw, Jp)
        Hpp[6, 6] += prior_w
        HpxHi = np.matmul(Hpx, np.linalg.inv(Hxx + 1e-9 * np.eye(3)))
        S = Hpp - np.einsum("mij,mkj->ik", HpxHi, Hpx)
        try:
            var = float(np.linalg.inv(S)[6, 6]) * sigma2
        except np.linalg.LinAlgError:
            var = float("inf")
    return HybridBAResult(T, X, it, init_rms, final_rms, inliers, delta, var)
