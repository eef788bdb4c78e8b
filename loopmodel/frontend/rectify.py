"""Stereo rectification: unrectified input (distortion, rotated cameras) becomes a
row-aligned pair with one pinhole camera matrix and the baseline along x."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import make_pose
from loopmodel.types import StereoCalibration

F64 = NDArray[np.float64]


def to_grey(img: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Grey uint8 image of a grey or BGR image."""
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return img


class Rectifier:
    """Maps raw stereo images to a rectified pair.

    ``calibration`` is the rectified calibration (left K, right K equal, distortion zero,
    ``right_from_left`` a pure x translation). ``rect_from_cam`` (4x4 rotation) maps points
    of the original left camera into the rectified left camera; for input that is already
    rectified it is the identity and images pass through unchanged.
    """

    def __init__(self, calibration: StereoCalibration) -> None:
        self.input_calibration = calibration
        self.rect_from_cam: F64 = np.eye(4)
        self._maps: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = (
            None
        )
        if calibration.rectified:
            self.calibration = calibration
            return
        size = calibration.image_size
        R = calibration.right_from_left[:3, :3]
        t = calibration.right_from_left[:3, 3].reshape(3, 1).copy()
        R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(
            calibration.K_left,
            calibration.dist_left,
            calibration.K_right,
            calibration.dist_right,
            size,
            R,
            t,
            flags=cv2.CALIB_ZERO_DISPARITY,
            alpha=0.0,
        )
        m1 = cv2.initUndistortRectifyMap(
            calibration.K_left, calibration.dist_left, R1, P1, size, cv2.CV_16SC2
        )
        m2 = cv2.initUndistortRectifyMap(
            calibration.K_right, calibration.dist_right, R2, P2, size, cv2.CV_16SC2
        )
        self._maps = (m1, m2)
        self.rect_from_cam = make_pose(R1, np.zeros(3))
        K = P1[:3, :3].copy()
        right_from_left = np.eye(4)
        right_from_left[0, 3] = P2[0, 3] / P2[0, 0]
        self.calibration = StereoCalibration(
            K, P2[:3, :3].copy(), right_from_left, size, rectified=True
        )

    @property
    def is_identity(self) -> bool:
        """True when images pass through unchanged."""
        return self._maps is None

    def left(self, img: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """Rectified grey left image."""
        g = to_grey(img)
        if self._maps is None:
            return g
        return cv2.remap(g, self._maps[0][0], self._maps[0][1], cv2.INTER_LINEAR)

    def right(self, img: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """Rectified grey right image."""
        g = to_grey(img)
        if self._maps is None:
            return g
        return cv2.remap(g, self._maps[1][0], self._maps[1][1], cv2.INTER_LINEAR)
