"""Minimal-solver RANSAC start for the pose solver (P3P/AP3P).

One pinhole camera: OpenCV's ``solvePnPRansac`` with AP3P. A rig of central cameras:
samples of 3 correspondences seen by one camera, P3P on normalised coordinates of the
lifted rays (rays in front of the camera), scored by reprojection in all cameras.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import invert_pose, make_pose
from loopmodel.pose.rig import F64, PointTerm


def _pose_from_rvec(rvec: NDArray[np.float64], tvec: NDArray[np.float64]) -> F64:
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=float))
    return make_pose(R, np.asarray(tvec, dtype=float).ravel())


def ransac_pose(
    term: PointTerm,
    threshold_px: float = 2.0,
    iterations: int = 200,
    confidence: float = 0.999,
    seed: int = 0,
) -> tuple[F64, NDArray[np.bool_]] | None:
    """``(rig_from_ref, inlier mask)`` of the best P3P hypothesis, or None."""
    n = len(term)
    if n < 4:
        return None
    if term.inverse_depth_per_m is not None:
        raise ValueError("RANSAC needs Euclidean points (a term without inverse_depth_per_m)")
    rig = term.rig
    if rig.is_single_pinhole:
        cam = rig.cameras[0]
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            term.p_in_ref.astype(np.float64),
            term.uv_px.astype(np.float64),
            cam.K,
            None,
            iterationsCount=iterations,
            reprojectionError=threshold_px,
            confidence=confidence,
            flags=cv2.SOLVEPNP_AP3P,
        )
        if not ok or inl is None or len(inl) < 4:
            return None
        T = _pose_from_rvec(rvec, tvec)
        mask = np.linalg.norm(term.residuals(T), axis=1) < threshold_px
        mask &= term.depths(T) > 0
        return T, mask
    return _ransac_rig(term, threshold_px, iterations, confidence, seed)


def _ransac_rig(
    term: PointTerm, threshold_px: float, iterations: int, confidence: float, seed: int
) -> tuple[F64, NDArray[np.bool_]] | None:
    rig = term.rig
    rng = np.random.default_rng(seed)
    groups = [np.flatnonzero(term.cam_index == j) for j in range(len(rig))]
    # normalised coordinates (x/z) of each measurement's lifted ray in its camera
    norm_xy = np.full((len(term), 2), np.nan)
    for j, idx in enumerate(groups):
        if idx.size:
            rays = rig.cameras[j].lift(term.uv_px[idx])
            front = rays[:, 2] > 1e-3
            norm_xy[idx[front]] = rays[front, :2] / rays[front, 2:3]
    usable = [idx[np.isfinite(norm_xy[idx, 0])] for idx in groups]
    cams = [j for j, idx in enumerate(usable) if idx.size >= 3]
    if not cams:
        return None
    probs = np.array([usable[j].size for j in cams], dtype=float)
    probs /= probs.sum()
    best_T, best_mask, best_count = None, None, -1
    needed = iterations
    it = 0
    while it < min(iterations, needed):
        it += 1
        j = cams[int(rng.choice(len(cams), p=probs))]
        sample = rng.choice(usable[j], size=3, replace=False)
        n_sol, rvecs, tvecs = cv2.solveP3P(
            term.p_in_ref[sample].astype(np.float64),
            norm_xy[sample].astype(np.float64),
            np.eye(3),
            None,
            flags=cv2.SOLVEPNP_AP3P,
        )
        for k in range(int(n_sol or 0)):
            cam_from_ref = _pose_from_rvec(rvecs[k], tvecs[k])
            T = invert_pose(rig.cam_from_rig[j]) @ cam_from_ref
            with np.errstate(all="ignore"):
                res = np.linalg.norm(term.residuals(T), axis=1)
            mask = (res < threshold_px) & (term.depths(T) > 0)
            count = int(mask.sum())
            if count > best_count:
                best_T, best_mask, best_count = T, mask, count
                frac = count / len(term)
                if frac > 0:
                    denom = np.log(max(1.0 - frac**3, 1e-12))
                    needed = int(np.ceil(np.log(1.0 - confidence) / denom)) if denom < 0 else 1
    if best_T is None or best_count < 4:
        return None
    assert best_mask is not None
    return best_T, best_mask
