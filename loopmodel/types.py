"""The data every stage shares: calibration, frames, stripe profiles, keyframes, trajectories.

Times are ``int`` nanoseconds; poses are 4x4 ``world_from_cam`` matrices (metres); the
camera frame is x right, y down, z forward.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import CalibrationError, InputError
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose, is_rotation


@dataclass
class StereoCalibration:
    """Intrinsics of the left and right cameras and their relative pose.

    ``K_left``/``K_right`` are 3x3 (pixels), ``dist_*`` OpenCV distortion coefficients,
    ``right_from_left`` a 4x4 rigid transform (metres), ``image_size`` is (width, height)
    in pixels. ``rectified`` means row-aligned images with no distortion, where the
    baseline lies along x.
    """

    K_left: NDArray[np.float64]
    K_right: NDArray[np.float64]
    right_from_left: NDArray[np.float64]
    image_size: tuple[int, int]
    dist_left: NDArray[np.float64] = field(default_factory=lambda: np.zeros(5))
    dist_right: NDArray[np.float64] = field(default_factory=lambda: np.zeros(5))
    rectified: bool = True
    # "pinhole": OpenCV's standard distortion (plumb_bob 5 / rational_polynomial 8 coefficients);
    # "equidistant": OpenCV's fisheye (Kannala-Brandt, k1..k4) model.
    camera_model: str = "pinhole"

    def __post_init__(self) -> None:
        self.K_left = np.asarray(self.K_left, dtype=float).reshape(3, 3)
        self.K_right = np.asarray(self.K_right, dtype=float).reshape(3, 3)
        self.right_from_left = np.asarray(self.right_from_left, dtype=float).reshape(4, 4)
        self.dist_left = np.asarray(self.dist_left, dtype=float).ravel()
        self.dist_right = np.asarray(self.dist_right, dtype=float).ravel()
        self.image_size = (int(self.image_size[0]), int(self.image_size[1]))

    def check(self, source: str | None = None) -> StereoCalibration:
        """Raise :class:`CalibrationError` unless finite, positive focal lengths, baseline > 0."""
        for name, K in (("left", self.K_left), ("right", self.K_right)):
            if not np.all(np.isfinite(K)):
                raise CalibrationError(source, f"{name} camera matrix has non-finite values")
            if K[0, 0] <= 0 or K[1, 1] <= 0:
                raise CalibrationError(source, f"{name} focal length must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        for name, d in (("left", self.dist_left), ("right", self.dist_right)):
            if not np.all(np.isfinite(d)):
                raise CalibrationError(source, f"{name} distortion has non-finite values")
        if not np.all(np.isfinite(self.right_from_left)) or not is_rotation(self.right_from_left[:3, :3], 1e-5):
            raise CalibrationError(source, "right_from_left is not a finite rigid transform")
        if self.camera_model not in ("pinhole", "equidistant"):
            raise CalibrationError(source, f"camera model must be pinhole or equidistant, got '{self.camera_model}'")
        if self.camera_model == "equidistant" and (self.dist_left.size != 4 or self.dist_right.size != 4):
            raise CalibrationError(source, "equidistant distortion needs 4 coefficients (k1..k4) per camera")
        if self.baseline_m <= 0:
            raise CalibrationError(source, f"stereo baseline must be > 0 m, got {self.baseline_m}")
        if self.image_size[0] <= 0 or self.image_size[1] <= 0:
            raise CalibrationError(source, f"image size must be positive, got {self.image_size}")
        self._check_against_image(source)
        return self

    #: a focal length (px) between these multiples of the image's larger side: a 170-degree fisheye
    #: (about 0.1) to a 0.3-degree telephoto (about 200)
    FOCAL_FACTOR_RANGE = (0.02, 500.0)
    #: the largest magnitude of a distortion coefficient (radial-tangential fits stay within a few
    #: units; rational ones reach tens)
    MAX_DISTORTION = 1e3

    def _check_against_image(self, source: str | None) -> None:
        """Bound the intrinsics by the image (issue 34): a physically possible camera."""
        w, h = self.image_size
        lo, hi = (f * max(w, h) for f in self.FOCAL_FACTOR_RANGE)
        for name, K in (("left", self.K_left), ("right", self.K_right)):
            fx, fy, skew, cx, cy = K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]
            if not (lo <= fx <= hi and lo <= fy <= hi):
                raise CalibrationError(
                    source, f"{name} focal length fx={fx:g}, fy={fy:g} px is impossible for a {w}x{h} image"
                )
            if not (0 <= cx <= w and 0 <= cy <= h):
                raise CalibrationError(
                    source, f"{name} principal point ({cx:g}, {cy:g}) px lies outside the {w}x{h} image"
                )
            if abs(skew) > 1e-3 * fx:
                raise CalibrationError(source, f"{name} camera matrix has a skew of {skew:g} px (must be 0)")
            if np.any(K[1, :1] != 0) or np.any(K[2] != (0, 0, 1)):
                raise CalibrationError(source, f"{name} camera matrix rows are not [fx s cx; 0 fy cy; 0 0 1]")
        for name, d in (("left", self.dist_left), ("right", self.dist_right)):
            worst = float(np.max(np.abs(d))) if d.size else 0.0
            if worst > self.MAX_DISTORTION:
                raise CalibrationError(source, f"{name} distortion coefficient {worst:g} above {self.MAX_DISTORTION:g}")

    @property
    def baseline_m(self) -> float:
        """Distance between the two projection centres (metres)."""
        return float(np.linalg.norm(self.right_from_left[:3, 3]))

    @property
    def fx_px(self) -> float:
        """Left focal length along x (pixels)."""
        return float(self.K_left[0, 0])

    def left_camera(self) -> CentralCamera:
        """Pinhole model of the left camera (distortion not included)."""
        return CentralCamera.from_K(self.K_left)

    def right_camera(self) -> CentralCamera:
        """Pinhole model of the right camera (distortion not included)."""
        return CentralCamera.from_K(self.K_right)

    def summary(self) -> dict[str, object]:
        """Plain numbers for display and JSON."""
        K = self.K_left
        return {
            "fx_px": float(K[0, 0]),
            "fy_px": float(K[1, 1]),
            "cx_px": float(K[0, 2]),
            "cy_px": float(K[1, 2]),
            "baseline_m": self.baseline_m,
            "image_size": list(self.image_size),
            "rectified": self.rectified,
        }


@dataclass
class StereoFrame:
    """One stereo pair; images as numpy arrays (uint8 grey HxW or BGR HxWx3)."""

    timestamp_ns: int
    left: NDArray[np.uint8]
    right: NDArray[np.uint8]
    index: int = 0


@dataclass
class StripeProfile:
    """One laser-stripe profile: N x 3 points (metres) in the left-camera frame."""

    timestamp_ns: int
    points_in_cam: NDArray[np.float64]


@dataclass
class MapFileData:
    """The content of a map file: ``meta`` (JSON-able dict) and named numpy ``arrays``."""

    meta: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, NDArray[Any]] = field(default_factory=dict)


@dataclass
class ScanFrame:
    """A stereo frame with the laser data taken up to its time (after the previous frame's).

    ``stripes``: laser-stripe messages (left-camera frame, metres); ``laser_images``: laser-line
    images of the left camera, ``(timestamp_ns, image)``. A sequence gives one kind or none.
    """

    frame: StereoFrame
    stripes: list[StripeProfile] = field(default_factory=list)
    laser_images: list[tuple[int, NDArray[np.uint8]]] = field(default_factory=list)


@dataclass
class StripeAnchors:
    """Stripe profiles anchored to keyframes: their keyframe ids (S,) and ``kf_from_cam`` (S, 4, 4, metres).

    The sensor pose of stripe ``s`` is ``world_from_kf[kf_ids[s]] @ kf_from_cam[s]``.
    """

    stripes: list[StripeProfile]
    kf_ids: NDArray[np.int64]
    kf_from_cam: NDArray[np.float64]


TrackingStatus = Literal["OK", "LOST"]
"""A frame's tracking state: ``OK`` (pose measured) or ``LOST`` (only the motion model)."""


def _empty_image() -> NDArray[np.uint8]:
    return np.zeros((0, 0), np.uint8)


@dataclass
class Keyframe:
    """A stereo keyframe and its feature set.

    The one keyframe type of the front end, the back ends, loop closing, tests and tools.

    Poses are of the (original, unrectified) left camera; pixel measurements are in the
    rectified images, and ``rect_from_cam`` relates the two frames (identity for rectified
    input). ``landmark_ids`` (M,) unique ids; ``points_in_kf`` (M, 3) metres in this
    keyframe's left camera frame (stereo triangulation); ``stereo_px`` (M, 3) = (u_left,
    u_right, v) in the rectified pair; ``mono_obs`` (K, 3) = (landmark_id, u, v): earlier
    keyframes' landmarks as seen in this keyframe's left image (rectified pixels; seed 004:
    the last frame tracking set i is the left image of keyframe i+1); ``image`` the
    rectified left grey image (empty where no stage needs it). ``connected`` is False when
    the pose relative to the previous keyframe was not measured (recovery after tracking
    loss); ``kf_prev_from_kf`` is the measured transform (after the local hybrid BA) when
    connected; ``kf_prev_from_kf_tracked`` the tracker's own pose of this frame in the
    previous keyframe, before the local BA (the end of the tracked frames' chain; the final
    refinement bridges its drift).
    """

    id: int
    timestamp_ns: int
    world_from_kf: NDArray[np.float64]
    landmark_ids: NDArray[np.int64]
    points_in_kf: NDArray[np.float64]
    stereo_px: NDArray[np.float64]
    mono_obs: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    image: NDArray[np.uint8] = field(default_factory=_empty_image)
    frame_index: int = 0
    prev_keyframe_id: int | None = None
    connected: bool = True
    kf_prev_from_kf: NDArray[np.float64] | None = None
    kf_prev_from_kf_tracked: NDArray[np.float64] | None = None
    rect_from_cam: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    segment: int = 0
    ba_info: dict[str, float] = field(default_factory=dict)
    #: (M,) the rectified row of each stereo match in the right image (the order of ``stereo_px``;
    #: empty when not measured): the self-calibration measures it (issue 31)
    right_rows_px: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))

    @property
    def world_from_rect(self) -> NDArray[np.float64]:
        """Pose of the keyframe's rectified left camera (4x4, metres)."""
        return np.asarray(self.world_from_kf, dtype=float) @ invert_pose(self.rect_from_cam)

    def without_image(self) -> Keyframe:
        """A shallow copy without the image (small to hold or send to a worker process)."""
        return replace(self, image=_empty_image())

    def at_disparity_offset(self, offset_px: float) -> Keyframe:
        """A copy whose right columns have the disparity offset ``offset_px`` taken out instead of the front end's.

        With ``frontend.disparity_offset: estimate`` the front end stored each right column as measured
        minus the offset estimated when the keyframe was made (``ba_info["disparity_offset_applied_px"]``);
        the copy holds measured minus ``offset_px`` (its ``stereo_px`` column 1 moved by applied minus
        ``offset_px``, and that key set to ``offset_px``). The keyframe itself when nothing moves.
        """
        applied = self.ba_info.get("disparity_offset_applied_px")
        if applied is None or not np.isfinite(applied) or float(applied) == float(offset_px):
            return self
        st = np.array(self.stereo_px, dtype=float, copy=True).reshape(-1, 3)
        st[:, 1] += float(applied) - float(offset_px)
        info = {**self.ba_info, "disparity_offset_applied_px": float(offset_px)}
        return replace(self, stereo_px=st, ba_info=info)


def at_latest_disparity_offset(keyframes: list[Keyframe]) -> list[Keyframe]:
    """``keyframes`` with every right column at one disparity offset: the latest estimate (issue 36, drift8).

    The front end's offset (``frontend.disparity_offset: estimate``) converges over the run, so early
    keyframes had a different one taken out of their right columns than later ones; the back end's
    batch refinement re-expresses them at the latest estimate (``Isam2Backend.batch_refine``), and a
    stage that reads ``stereo_px`` itself (the calibrating bundle adjustment) does the same through
    this. The latest: that of the last keyframe (in the given order) whose ``ba_info`` holds both
    ``disparity_offset_applied_px`` and ``disparity_offset_estimate_px``, as the back end takes it.
    The list as it is without an estimate (``disparity_offset: none``, the code default).
    """
    latest = None
    for kf in keyframes:
        a, e = kf.ba_info.get("disparity_offset_applied_px"), kf.ba_info.get("disparity_offset_estimate_px")
        if a is not None and e is not None and np.isfinite(a) and np.isfinite(e):
            latest = float(e)
    if latest is None:
        return list(keyframes)
    return [kf.at_disparity_offset(latest) for kf in keyframes]


@dataclass
class Trajectory:
    """Timed poses: ``timestamps_ns`` (N, int64) and ``world_from_cam`` (N x 4 x 4, metres)."""

    timestamps_ns: NDArray[np.int64]
    world_from_cam: NDArray[np.float64]

    def __post_init__(self) -> None:
        self.timestamps_ns = np.asarray(self.timestamps_ns, dtype=np.int64).ravel()
        self.world_from_cam = np.asarray(self.world_from_cam, dtype=float).reshape(-1, 4, 4)

    def __len__(self) -> int:
        return int(self.timestamps_ns.shape[0])

    @property
    def positions_m(self) -> NDArray[np.float64]:
        """N x 3 camera positions in the world frame (metres)."""
        return self.world_from_cam[:, :3, 3]

    @property
    def timestamps_s(self) -> NDArray[np.float64]:
        """Times in seconds (float; lossy beyond microseconds for epoch times)."""
        return self.timestamps_ns.astype(np.float64) * 1e-9

    def check(self, source: str | None = None, strict: bool = True) -> Trajectory:
        """Raise :class:`InputError` unless shapes agree, rotations are proper and times increase.

        Strictly, or allowing repeats when ``strict`` is False.
        """
        n = len(self)
        if self.world_from_cam.shape != (n, 4, 4):
            raise InputError(source, f"{n} timestamps but {self.world_from_cam.shape[0]} poses")
        if not np.all(np.isfinite(self.world_from_cam)):
            raise InputError(source, "trajectory has non-finite pose values")
        R = self.world_from_cam[:, :3, :3]
        ortho = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(R)
        bad = np.flatnonzero((ortho > 1e-4) | (np.abs(det - 1) > 1e-4))
        if bad.size:
            raise InputError(source, f"pose {int(bad[0])} is not a proper rotation")
        steps = np.diff(self.timestamps_ns)
        back = np.flatnonzero(steps <= 0 if strict else steps < 0)
        if back.size:
            i = int(back[0])
            raise InputError(
                source,
                f"timestamps must {'strictly ' if strict else ''}increase: entry {i + 1} "
                f"({self.timestamps_ns[i + 1]} ns) follows {self.timestamps_ns[i]} ns",
            )
        return self

    def slice(self, mask: NDArray[np.bool_] | slice) -> Trajectory:
        """Subset of the poses (a boolean mask or a slice)."""
        return Trajectory(self.timestamps_ns[mask], self.world_from_cam[mask])
