"""Pose of a known planar target (chessboard, ArUco markers) from its corners.

By the project's robust pose solver (:func:`loopmodel.pose.estimate_pose`) on undistorted pixels.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from loopmodel.geometry.camera import CentralCamera
from loopmodel.pose import CameraRig, PointTerm, PoseResult, estimate_pose

F64 = NDArray[np.float64]


def undistort_px(uv_px: ArrayLike, K: ArrayLike, dist: ArrayLike | None) -> F64:
    """N x 2 ideal (distortion-free) pixels of N x 2 measured pixels (OpenCV distortion model)."""
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    Km = np.asarray(K, dtype=np.float64).reshape(3, 3)
    if dist is None or not np.any(np.asarray(dist) != 0) or uv.shape[0] == 0:
        return uv.copy()
    d = np.asarray(dist, dtype=np.float64).ravel()
    return np.asarray(cv2.undistortPoints(uv.reshape(-1, 1, 2), Km, d, P=Km), dtype=np.float64).reshape(-1, 2)


def target_pose(
    points_in_target_m: ArrayLike,
    uv_px: ArrayLike,
    K: ArrayLike,
    dist: ArrayLike | None = None,
    cam_from_target_init: F64 | None = None,
    ransac_threshold_px: float = 3.0,
) -> PoseResult:
    """``cam_from_target`` (as ``rig_from_ref`` of the result, 4x4, metres) of a target.

    The target's points (N x 3, target frame, metres) are seen at ``uv_px`` (N x 2, raw pixels).
    """
    rig = CameraRig.single(CentralCamera.from_K(np.asarray(K, dtype=np.float64)))
    term = PointTerm(rig, np.asarray(points_in_target_m, dtype=np.float64), undistort_px(uv_px, K, dist))
    return estimate_pose(term, cam_from_target_init, ransac_threshold_px=ransac_threshold_px)
