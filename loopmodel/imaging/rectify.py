"""Stereo rectification.

Unrectified input (distortion, rotated cameras) becomes a row-aligned pair with one pinhole camera
matrix and the baseline along x.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import make_pose
from loopmodel.types import StereoCalibration

F64 = NDArray[np.float64]

_AHEAD: list[ThreadPoolExecutor] = []  # the thread that rectifies coming frames (one per process, made when first used)
_AHEAD_LOCK = threading.Lock()


def _ahead_pool() -> ThreadPoolExecutor:
    with _AHEAD_LOCK:
        if not _AHEAD:
            _AHEAD.append(ThreadPoolExecutor(1, thread_name_prefix="rectify-ahead"))
        return _AHEAD[0]


Then = Callable[[NDArray[np.uint8]], Any]
"""A function of a rectified left image run after its rectification (:meth:`Rectifier.left_ahead`)."""


_Ahead = tuple[NDArray[np.uint8], Then | None, Future[tuple[NDArray[np.uint8], Any]]]
"""A started :meth:`Rectifier.left_ahead`: the raw image, its ``then`` and the job (rectified image, value)."""


def _applied(then: Then | None, rect: NDArray[np.uint8]) -> Any:
    return None if then is None else then(rect)


def to_grey(img: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Grey uint8 image of a grey or BGR image."""
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return img


def rectification(cal: StereoCalibration) -> tuple[F64, F64, F64, F64]:
    """``R1, R2`` (rectified_from_cam rotations) and ``P1, P2`` (3x4 rectified projections) of an unrectified rig.

    ``cv2.stereoRectify`` for the pinhole model (plumb_bob, rational polynomial),
    ``cv2.fisheye.stereoRectify`` for equidistant (Kannala-Brandt) cameras.
    """
    R = cal.right_from_left[:3, :3].copy()
    t = cal.right_from_left[:3, 3].reshape(3, 1).copy()
    if cal.camera_model == "equidistant":
        R1, R2, P1, P2, _Q = cv2.fisheye.stereoRectify(
            cal.K_left,
            cal.dist_left.reshape(4, 1),
            cal.K_right,
            cal.dist_right.reshape(4, 1),
            cal.image_size,
            R,
            t,
            flags=cv2.CALIB_ZERO_DISPARITY,
            balance=0.0,
        )
    else:
        R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(
            cal.K_left,
            cal.dist_left,
            cal.K_right,
            cal.dist_right,
            cal.image_size,
            R,
            t,
            flags=cv2.CALIB_ZERO_DISPARITY,
            alpha=0.0,
        )
    return np.asarray(R1), np.asarray(R2), np.asarray(P1), np.asarray(P2)


def undistort_rectify_map(
    cal: StereoCalibration, side: int, R: F64, P: F64, m1type: int = cv2.CV_32FC1
) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps from the rectified image of camera ``side`` to its raw pixels.

    ``side``: 0 left, 1 right; for the calibration's camera model.
    """
    K = cal.K_left if side == 0 else cal.K_right
    D = cal.dist_left if side == 0 else cal.dist_right
    if cal.camera_model == "equidistant":
        return cv2.fisheye.initUndistortRectifyMap(K, D.reshape(4, 1), R, P, cal.image_size, m1type)
    return cv2.initUndistortRectifyMap(K, D, R, P, cal.image_size, m1type)


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
        self._ahead: list[_Ahead] = []  # see left_ahead
        if calibration.rectified:
            self.calibration = calibration
            return
        size = calibration.image_size
        R1, R2, P1, P2 = rectification(calibration)
        m1 = undistort_rectify_map(calibration, 0, R1, P1, cv2.CV_16SC2)
        m2 = undistort_rectify_map(calibration, 1, R2, P2, cv2.CV_16SC2)
        self._maps = (m1, m2)
        self.rect_from_cam = make_pose(R1, np.zeros(3))
        K = P1[:3, :3].copy()
        right_from_left = np.eye(4)
        right_from_left[0, 3] = P2[0, 3] / P2[0, 0]
        self.calibration = StereoCalibration(
            K, P2[:3, :3].copy(), right_from_left, size, rectified=True
        )

    @classmethod
    def following(
        cls, rectifier: Rectifier, raw: StereoCalibration, rot_rect_from_left: F64, rot_rect_from_right: F64
    ) -> Rectifier:
        """A rectifier to the same rectified pair as ``rectifier`` from another raw calibration.

        ``raw``'s lenses (K, distortion) with the rectifying rotations given (3x3, rectified from
        each camera); the rectified calibration and ``rect_from_cam`` stay ``rectifier``'s, so
        rectified pixels keep their meaning (issue 31, ``calibration.refine: online``).
        """
        out = cls.__new__(cls)
        out._ahead = []
        out.input_calibration = raw
        out.rect_from_cam = rectifier.rect_from_cam.copy()
        out.calibration = rectifier.calibration
        K1, K2 = rectifier.calibration.K_left, rectifier.calibration.K_right
        out._maps = (
            undistort_rectify_map(raw, 0, rot_rect_from_left, K1, cv2.CV_16SC2),
            undistort_rectify_map(raw, 1, rot_rect_from_right, K2, cv2.CV_16SC2),
        )
        return out

    @property
    def is_identity(self) -> bool:
        """True when images pass through unchanged."""
        return self._maps is None

    def __getstate__(self) -> dict[str, object]:
        return {**self.__dict__, "_ahead": []}  # a started rectification stays with this process

    def left_ahead(self, img: NDArray[np.uint8], then: Then | None = None) -> None:
        """Start rectifying a coming frame's left image in a background thread.

        ``cv2.remap`` releases the interpreter, so it runs beside the frame being tracked (issue 33:
        2 ms of the realistic orbit's 640x480 frames on the tracking thread); :meth:`left` of the
        same array takes the result. The last two images started are kept. ``then``: a function of the
        rectified image run after it on the same thread (the front end's image check, cpu15; started
        also when the images pass through unrectified), whose value :meth:`left_and` hands with the image.
        """
        if self._maps is not None or then is not None:
            job = _ahead_pool().submit(self._left_then, img, then)
            self._ahead = [*self._ahead[-1:], (img, then, job)]

    def left(self, img: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """Rectified grey left image (the one :meth:`left_ahead` started for this array, when it did)."""
        return self.left_and(img)[0]

    def left_and(self, img: NDArray[np.uint8], then: Then | None = None) -> tuple[NDArray[np.uint8], Any]:
        """:meth:`left` of ``img`` and ``then`` of it (None without ``then``).

        Both from :meth:`left_ahead`'s thread when it was started for this array with the same ``then``;
        what it did not start is done here.
        """
        for i, (src, fn, job) in enumerate(self._ahead):
            if src is img:
                del self._ahead[: i + 1]
                rect, value = job.result()
                return rect, value if fn == then else _applied(then, rect)
        rect = self._left_now(img)
        return rect, _applied(then, rect)

    def _left_then(self, img: NDArray[np.uint8], then: Then | None) -> tuple[NDArray[np.uint8], Any]:
        rect = self._left_now(img)
        return rect, _applied(then, rect)

    def _left_now(self, img: NDArray[np.uint8]) -> NDArray[np.uint8]:
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
