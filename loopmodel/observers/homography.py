"""Partial Euclidean reconstruction between a reference view and the current view (seed 003 section 2).

The rotation ``R_bar = cur_from_ref``, the scaled translation, the depth ratios ``alpha_i = z*_i /
z_i`` and the Euclidean homography ``H = R_bar + x_h n*^T`` of the (possibly virtual) plane through
three features.

For coplanar features the homography is estimated from pixels and decomposed
(OpenCV's decomposition, solutions filtered by the visibility constraint). For
non-coplanar features we obtain the same quantities as the Virtual Parallax method from
the essential matrix (five-point RANSAC and cheirality), with the virtual plane defined by
three chosen features."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from loopmodel.errors import InputError

F64 = NDArray[np.float64]


@dataclass
class TwoViewSignals:
    """What the observer measures between the reference and the current view."""

    cur_from_ref_rot: F64  # R_bar
    x_h: F64  # x_f / d*: translation scaled by the distance of the (virtual) plane
    n_ref: F64  # unit normal of the plane in the reference frame
    alpha: F64  # N depth ratios z*_i / z_i
    inliers: NDArray[np.bool_]
    H: F64  # Euclidean homography R_bar + x_h n*^T


def _rays(A: F64, p: F64) -> F64:
    return np.column_stack([p, np.ones(len(p))]) @ np.linalg.inv(A).T


def decompose_homography(
    H: ArrayLike,
    A: ArrayLike,
    p_ref_px: ArrayLike,
    p_cur_px: ArrayLike,
    normal_prior: ArrayLike = (0.0, 0.0, 1.0),
) -> TwoViewSignals:
    """Decompose the pixel homography ``G ~ A H A^-1`` of coplanar points (``p_cur ~ G p_ref``)
    into ``R_bar``, ``x_h = x_f/d*`` and ``n*``. Of the four solutions, those that put every
    point in front of both cameras remain (usually two, which explain the images equally);
    the one whose normal is closest to ``normal_prior`` (reference frame; default: a plane
    facing the camera) is returned."""
    G = np.asarray(H, dtype=float)
    A = np.asarray(A, dtype=float)
    pr = np.asarray(p_ref_px, dtype=float).reshape(-1, 2)
    pc = np.asarray(p_cur_px, dtype=float).reshape(-1, 2)
    _n, Rs, ts, ns = cv2.decomposeHomographyMat(G, A)
    mr, mc = _rays(A, pr), _rays(A, pc)
    best: tuple[float, int] | None = None
    for k in range(len(Rs)):
        n = ns[k].ravel()
        # reference depths ∝ 1 / (n . m*) must be positive; current ones too: (H m*)_z > 0
        Hk = Rs[k] + ts[k].reshape(3, 1) @ n.reshape(1, 3)
        if np.any(mr @ n <= 0) or np.any((mr @ Hk.T)[:, 2] <= 0):
            continue
        residual = float(
            np.linalg.norm(
                np.cross(
                    mc / np.linalg.norm(mc, axis=1, keepdims=True),
                    mr @ Hk.T / np.linalg.norm(mr @ Hk.T, axis=1, keepdims=True),
                ),
                axis=1,
            ).mean()
        )
        score = round(residual, 6) - float(n @ np.asarray(normal_prior, dtype=float))
        if best is None or score < best[0]:
            best = (score, k)
    if best is None:
        raise InputError("homography", "no decomposition puts the points in front of both cameras")
    k = best[1]
    n = ns[k].ravel()
    Hk = Rs[k] + ts[k].reshape(3, 1) @ n.reshape(1, 3)
    alpha = 1.0 / (mr @ Hk.T)[:, 2]
    return TwoViewSignals(Rs[k], ts[k].ravel(), n, alpha, np.ones(len(pr), bool), Hk)


def signals_from_essential(
    A: ArrayLike,
    p_ref_px: ArrayLike,
    p_cur_px: ArrayLike,
    plane_features: tuple[int, int, int] = (0, 1, 2),
    threshold_px: float = 1.0,
) -> TwoViewSignals:
    """Two-view signals of non-coplanar features.

    ``R_bar`` and the translation direction from the essential matrix, ``alpha_i`` by least squares
    from ``(1/alpha_i) m_i - b_i t = R_bar m*_i``, and the virtual plane through three features
    (scale: ``x_h = x_f / d*``).
    """
    A = np.asarray(A, dtype=float)
    pr = np.asarray(p_ref_px, dtype=float).reshape(-1, 2)
    pc = np.asarray(p_cur_px, dtype=float).reshape(-1, 2)
    if len(pr) < 8:
        raise InputError("two-view signals", f"need at least 8 features, got {len(pr)}")
    E, mask = cv2.findEssentialMat(pr, pc, A, method=cv2.RANSAC, prob=0.999, threshold=threshold_px)
    if E is None or E.shape != (3, 3):
        raise InputError("two-view signals", "essential matrix estimation failed (too little motion?)")
    _n, R, t, mask_pose = cv2.recoverPose(E, pr, pc, A, mask=mask.copy())
    t = t.ravel() / np.linalg.norm(t)
    inliers = mask_pose.ravel() > 0
    mr, mc = _rays(A, pr), _rays(A, pc)
    rm = mr @ R.T
    # solve [m_i, -t] [a_i, b_i]^T = R m*_i per feature (2 unknowns, 3 equations)
    M = np.stack([mc, np.repeat(-t[None], len(mc), axis=0)], axis=2)  # N x 3 x 2
    MtM = np.einsum("nki,nkj->nij", M, M)
    Mtb = np.einsum("nki,nk->ni", M, rm)
    ab = np.linalg.solve(MtM + 1e-15 * np.eye(2), Mtb[..., None])[..., 0]
    alpha = 1.0 / ab[:, 0]
    depth_ref = 1.0 / ab[:, 1]  # b_i = s / z*_i, s = |x_f|: reference depths in units of s
    i, j, k = plane_features
    P = mr[[i, j, k]] * depth_ref[[i, j, k], None]
    n = np.cross(P[1] - P[0], P[2] - P[0])
    n /= np.linalg.norm(n)
    d = float(n @ P[0])
    if d < 0:
        n, d = -n, -d
    x_h = t / d  # x_f / d* with |x_f| = 1 in these units
    H = R + np.outer(x_h, n)
    return TwoViewSignals(R, x_h, n, alpha, inliers & (alpha > 0), H)
