"""What the front end hands to the back end and loop closing: keyframes and per-frame results.

Poses are of the (original, unrectified) left camera; ``world_from_cam =
world_from_kf[keyframe_id] @ kf_from_cam`` always holds. Pixel measurements are in the
rectified images (``FrontEnd.calibration``); ``rect_from_cam`` relates the two frames
(identity for rectified input). The keyframe type itself lives in :mod:`loopmodel.types`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.types import Keyframe, TrackingStatus

F64 = NDArray[np.float64]

__all__ = ["FrameObservations", "FrameResult", "Keyframe", "TrackingStatus"]


@dataclass
class FrameObservations:
    """What a tracked frame's pose was solved from: the stereo points the pose kept.

    ``landmark_ids`` (N,): the points' landmark ids (``Keyframe.landmark_ids`` of the active
    keyframe's set and of the local map's earlier sets); ``uv_px`` (N, 2, float32): where the frame
    saw them, pixels of its rectified left image (rectified with the calibration the front end was
    given). Kept for re-solving the pose after the calibration is refined (issue 31); float32 pixels
    are exact to 1e-4 px at 2,000 px, far below the tracking noise.
    """

    landmark_ids: NDArray[np.int64]
    uv_px: NDArray[np.float32]

    @property
    def nbytes(self) -> int:
        """Memory held (bytes)."""
        return int(self.landmark_ids.nbytes + self.uv_px.nbytes)


@dataclass
class FrameResult:
    """Front-end output for one stereo frame.

    ``status`` is "OK" or "LOST"; a LOST frame's ``world_from_cam`` is only the motion-model
    prediction and must not be used as a measurement. ``keyframe_id`` is the keyframe the
    pose is expressed against (for a frame that became a keyframe: itself, with
    ``kf_from_cam`` = identity). ``tracked`` counts KLT tracks that passed the
    forward-backward check, ``inliers`` those the robust pose kept (stereo points; the
    observer-depth points of ``frontend.mono_depth`` are counted in ``mono_points``).
    """

    timestamp_ns: int
    world_from_cam: F64
    status: TrackingStatus
    is_keyframe: bool
    keyframe_id: int
    kf_from_cam: F64
    tracked: int
    inliers: int
    keyframe: Keyframe | None = None
    frame_index: int = 0
    segment: int = 0
    reason: str = ""
    track_ms: float = 0.0
    keyframe_ms: float = 0.0
    used_ransac: bool = False
    mono_points: int = 0  # points with observer depth (frontend.mono_depth) the pose kept
    # the points the pose kept (FrontEnd(keep_observations=True), a tracked frame; for a connected
    # keyframe those of its tracked pose in the previous keyframe, ``Keyframe.kf_prev_from_kf_tracked``)
    observed: FrameObservations | None = None

    @property
    def ok(self) -> bool:
        """True when the pose was measured."""
        return self.status == "OK"


@dataclass
class TrackedFeatures:
    """What the front end tracked in its last frame, for display.

    The rectified left image (None before the first frame), the features the pose kept and those it
    rejected (N x 2, pixels of the rectified left image), and the keyframe whose set they belong to
    (-1: none).
    """

    left_rect: NDArray[np.uint8] | None
    inlier_px: NDArray[np.float64]
    outlier_px: NDArray[np.float64]
    keyframe_id: int

