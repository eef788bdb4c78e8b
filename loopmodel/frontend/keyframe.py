"""What the front end hands to the back end and loop closing: keyframes and per-frame results.

Poses are of the (original, unrectified) left camera; ``world_from_cam =
world_from_kf[keyframe_id] @ kf_from_cam`` always holds. Pixel measurements are in the
rectified images (``FrontEnd.calibration``); ``rect_from_cam`` relates the two frames
(identity for rectified input).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass
class Keyframe:
    """A stereo keyframe and its feature set.

    ``landmark_ids`` (M,) unique ids; ``points_in_kf`` (M, 3) metres in this keyframe's left
    camera frame (stereo triangulation); ``stereo_px`` (M, 3) = (u_left, u_right, v) in the
    rectified pair; ``mono_obs`` (K, 3) = (landmark_id, u, v): the previous keyframe's
    landmarks as seen in this keyframe's left image (rectified pixels; seed 004: the last
    frame tracking set i is the left image of keyframe i+1); ``image`` the rectified left
    grey image. ``connected`` is False when the pose relative to the previous keyframe was
    not measured (recovery after tracking loss); ``kf_prev_from_kf`` is the measured
    transform (after the local hybrid BA) when connected; ``kf_prev_from_kf_tracked`` the
    tracker's own pose of this frame in the previous keyframe, before the local BA (the end
    of the tracked frames' chain; the final refinement bridges its drift).
    """

    id: int
    timestamp_ns: int
    world_from_kf: F64
    landmark_ids: NDArray[np.int64]
    points_in_kf: F64
    stereo_px: F64
    mono_obs: F64
    image: NDArray[np.uint8]
    frame_index: int = 0
    prev_keyframe_id: int | None = None
    connected: bool = True
    kf_prev_from_kf: F64 | None = None
    kf_prev_from_kf_tracked: F64 | None = None
    rect_from_cam: F64 = field(default_factory=lambda: np.eye(4))
    segment: int = 0
    ba_info: dict[str, float] = field(default_factory=dict)


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
    status: str
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

    @property
    def ok(self) -> bool:
        """True when the pose was measured."""
        return self.status == "OK"
