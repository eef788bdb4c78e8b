"""The stereo keyframe front end (seed 004, section 4).

Stereo-triangulated feature sets tracked by KLT, robust pose per frame against the current keyframe,
keyframe policy, local hybrid keyframe BA, and LOST/recovery handling.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.config import FrontendConfig
from loopmodel.errors import EstimationError, InputError
from loopmodel.frontend.beside import Beside
from loopmodel.frontend.hybrid_ba import HybridBAResult, hybrid_keyframe_ba
from loopmodel.frontend.keyframe import FrameObservations, FrameResult, Keyframe, TrackedFeatures
from loopmodel.frontend.klt_halves import track_klt_halves
from loopmodel.frontend.mono_depth import MonoDepthTracks, kf_from_ref_map
from loopmodel.frontend.resume import ResumedSet
from loopmodel.frontend.stereo import KeyframeMatches, StereoSet, keyframe_matches, keyframe_stereo_set, match_stereo
from loopmodel.geometry.se3 import invert_pose, nearest_rigid, se3_exp, se3_log, so3_log
from loopmodel.imaging.klt import Pyramid, build_pyramid, shared_tracks
from loopmodel.imaging.rectify import Rectifier
from loopmodel.pose import CameraRig, PointTerm, PoseOptions, estimate_pose
from loopmodel.pose.robust import robust_scale
from loopmodel.pose.solver import PoseResult
from loopmodel.priority import lower_switch_interval
from loopmodel.stages import ResumeFeatures
from loopmodel.types import StereoCalibration, StereoFrame

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass
class _ActiveSet:
    """The current keyframe's feature set, in the rectified left frame of that keyframe."""

    keyframe: Keyframe
    world_from_kfrect: F64
    points: F64  # (M, 3) rectified keyframe frame
    stereo_px: F64  # (M, 3)
    median_depth_m: float
    # far points (frontend.far_points = "bearing"): rays (x/z, y/z, 1) in the rectified keyframe
    # frame, inverse depths (1/m, 0 at zero disparity), rectified left pixels
    far_rays: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    far_inv_depth: F64 = field(default_factory=lambda: np.zeros(0))
    far_px: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    # issue 36: each point's disparity standard deviation (px) from its stereo match
    disparity_sigma_px: F64 = field(default_factory=lambda: np.zeros(0))
    # issue 36: per point, a running mean of its signed pose residual (px) and how many frames it has
    residual_mean_px: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    residual_frames: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    disparity_offset_px: float = 0.0  # the correction applied to this set's matches (issue 36)
    # depth standard deviation (m) of each point: stereo at first, smaller once the local BA has
    # refined the point over the keyframe interval (local-map tracking weighs the points by it)
    sigma_z_m: F64 = field(default_factory=lambda: np.zeros(0))


@dataclass
class _LocalPrediction:
    """The local map's points for one frame.

    In the active keyframe's frame (L, 3, m), last and predicted pixels (L, 2), in front of the
    predicted camera, depth weights, points per set.
    """

    points_kf: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    prev_uv: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    guess: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    front: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    prior: F64 | None = None
    sizes: list[int] = field(default_factory=list)


@dataclass
class _WideRows:
    """The local map's points for the wider local BA: keyframe-i frame, own stereo pixels, final pixels."""

    points_kf: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    uv_left: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    uv_right: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    uv_final: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    owner: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    own_from_kf: F64 = field(default_factory=lambda: np.zeros((0, 4, 4)))
    sizes: list[int] = field(default_factory=list)


@dataclass
class _LocalSet:
    """An earlier keyframe's set whose points are still tracked and kept in the pose (local map).

    ``idx``: the tracked points (indices into ``kf_set.points``), ``uv``: where they were seen in the
    last good frame (rectified left pixels).
    """

    kf_set: _ActiveSet
    idx: NDArray[np.int64]
    uv: F64


@dataclass
class _ClosedInterval:
    """The outgoing set's keyframe interval closed at a new keyframe, not yet applied to the tracker.

    ``mono_obs``: rows (landmark_id, u, v) of earlier landmarks in the new keyframe; ``kf_from_new``:
    the new keyframe in the outgoing one (rectified; the local BA's when accepted); the outgoing
    set's tracks there (``track_idx``, ``track_uv`` px); the local map's sets after their
    re-measurement; the BA's refined points (set, indices, points in its keyframe, inliers, its
    keyframe from the interval's end) and disparity offset (px, variance px^2); ``ba_info``.
    """

    mono_obs: F64
    kf_from_new: F64
    track_idx: NDArray[np.int64]
    track_uv: F64
    local: list[_LocalSet]
    refined: list[tuple[_ActiveSet, NDArray[np.int64], F64, NDArray[np.bool_], F64]] = field(default_factory=list)
    offset: tuple[float, float] | None = None
    ba_info: dict[str, float] = field(default_factory=dict)
    ba_job: _LocalBAJob | None = None  # frontend.local_ba_beside: the BA still to run


@dataclass
class _FrameTracks:
    """One frame's KLT of the active set, its far bearings and the local map.

    The active set's tracks ``idx`` (points ``pts``, keyframe frame) at ``uv`` (valid ``ok``), its far
    bearings ``fidx`` (homogeneous points ``q_far`` at the predicted pose), the local map's points.
    """

    idx: NDArray[np.int64]
    fidx: NDArray[np.int64]
    pts: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    uv: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    ok: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    q_far: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    uv_far: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    ok_far: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    loc: _LocalPrediction = field(default_factory=_LocalPrediction)
    uv_loc: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    ok_loc: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    # the resumed old set (seed 004 section 5), in the same KLT call (fr16)
    uv_res: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    ok_res: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))


@dataclass
class _PoseTerms:
    """A frame's pose terms and how their rows map back to the tracks.

    ``term``: the active set's tracked points, then the local map's (``loc_sel``: their rows in the
    frame's local prediction), ``n_stereo`` rows in all, then the converged mono-depth points
    (``mono_sel`` of the tracked ``m_ok``, in the frames ``kf_from_ref``); ``extra``: the far bearings
    (``far_sel``: the tracked ones) when three or more.
    """

    term: PointTerm | None = None
    extra: list[PointTerm] = field(default_factory=list)
    loc_sel: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    n_stereo: int = 0
    m_ok: NDArray[np.bool_] | None = None
    mono_sel: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    kf_from_ref: dict[int, F64] = field(default_factory=dict)
    far_sel: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))



@dataclass
class _LocalBAJob:
    """One local BA: its inputs (gathered on the tracking thread) and where its result goes (``closed``).

    :meth:`take` fills ``closed`` from the BA's result: the new keyframe's pose (when within
    ``max_jump_m`` / ``max_jump_deg`` of the tracked ``kf_from_cur``), the refined points, the
    disparity offset and ``ba_info``. ``offset_px``: the offset applied to the matches of the time.
    """

    closed: _ClosedInterval
    prev: _ActiveSet
    wide: _WideRows
    kf_from_cur: F64
    config: FrontendConfig
    offset_px: float
    args: tuple  # type: ignore[type-arg]
    kwargs: dict  # type: ignore[type-arg]
    solve_ms: float = 0.0

    def run(self) -> HybridBAResult:
        """The BA itself (numpy and OpenCV; any thread)."""
        t0 = time.perf_counter()
        ba = hybrid_keyframe_ba(*self.args, **self.kwargs)
        self.solve_ms = (time.perf_counter() - t0) * 1e3
        return ba

    def take(self, ba: HybridBAResult) -> None:
        """Fill ``closed`` from the BA's result."""
        cfg, closed, prev, wide = self.config, self.closed, self.prev, self.wide
        idx = closed.track_idx
        n_own = idx.size
        step = invert_pose(self.kf_from_cur) @ invert_pose(ba.f_from_kf)
        if np.linalg.norm(step[:3, 3]) < cfg.max_jump_m and _rotation_deg(step) < cfg.max_jump_deg:
            closed.kf_from_new = kf_from_new = invert_pose(ba.f_from_kf)
            if cfg.local_map_keyframes > 0:  # the local map keeps the refined points
                closed.refined.append((prev, idx, ba.points_in_kf[:n_own], ba.inliers[:n_own], kf_from_new))
                off = n_own
                for k, (ls, n) in enumerate(zip(closed.local, wide.sizes, strict=False)):
                    own_from_kf = wide.own_from_kf[k]
                    p_own = ba.points_in_kf[off : off + n] @ own_from_kf[:3, :3].T + own_from_kf[:3, 3]
                    kf_from_end = own_from_kf @ kf_from_new
                    closed.refined.append((ls.kf_set, ls.idx, p_own, ba.inliers[off : off + n], kf_from_end))
                    off += n
            if cfg.disparity_offset == "estimate":
                closed.offset = (prev.disparity_offset_px + ba.disparity_offset_px, ba.disparity_offset_var_px2)
        closed.ba_info.update({
            "ba_ms": self.solve_ms,
            "ba_iterations": float(ba.iterations),
            "ba_rms_before_px": ba.initial_rms_px,
            "ba_rms_after_px": ba.final_rms_px,
            "ba_points": float(n_own),
            "ba_window_points": float(sum(wide.sizes)),
        })
        if cfg.disparity_offset == "estimate":
            closed.ba_info["disparity_offset_px"] = ba.disparity_offset_px
            closed.ba_info["disparity_offset_sigma_px"] = float(np.sqrt(ba.disparity_offset_var_px2))
            closed.ba_info["disparity_offset_applied_px"] = self.offset_px  # to the new keyframe's matches



def median_parallax_rad(points_m: F64, centre_m: F64) -> float:
    """Median angle (rad) between the rays to ``points_m`` (N, 3) from the origin and from ``centre_m`` (3,).

    Frames: the keyframe camera (metres); ``centre_m`` is the current camera centre there. Motion
    along the viewing rays (a car driving towards the scene) changes these angles much less than
    the translation over the depth; sideways motion (a hand-held orbit) about as much.
    """
    if points_m.shape[0] == 0:
        return 0.0
    q = points_m - centre_m
    cos = np.einsum("ij,ij->i", points_m, q) / (np.linalg.norm(points_m, axis=1) * np.linalg.norm(q, axis=1))
    return float(np.median(np.arccos(np.clip(cos, -1.0, 1.0))))


#: smallest detection-grid cell (px): a Shi-Tomasi corner needs its 3x3 neighbourhood plus one
MIN_GRID_CELL_PX = 4


def check_sizes_against_image(config: FrontendConfig, width_px: int, height_px: int) -> None:
    """Size-like front-end knobs must fit the (rectified) image; :class:`InputError` naming the key.

    The detection grid needs cells of at least ``MIN_GRID_CELL_PX`` inside the border, the border
    must leave an area to detect in, and the matching, KLT and re-measured windows must fit the image.
    """
    inner_w, inner_h = width_px - 2 * config.border_px, height_px - 2 * config.border_px
    checks = (
        ("border_px", inner_w > 0 and inner_h > 0, f"twice it must be below the image size {width_px}x{height_px}"),
        ("grid_cols", inner_w >= MIN_GRID_CELL_PX * config.grid_cols,
         f"at most {max(inner_w // MIN_GRID_CELL_PX, 0)} for {width_px} px wide images ({MIN_GRID_CELL_PX} px cells)"),
        ("grid_rows", inner_h >= MIN_GRID_CELL_PX * config.grid_rows,
         f"at most {max(inner_h // MIN_GRID_CELL_PX, 0)} for {height_px} px high images ({MIN_GRID_CELL_PX} px cells)"),
        ("patch_px", config.patch_px <= min(width_px, height_px), f"at most the image size {width_px}x{height_px}"),
        ("klt_window_px", config.klt_window_px <= min(width_px, height_px),
         f"at most the image size {width_px}x{height_px}"),
        ("remeasure_half_window_px", 2 * config.remeasure_half_window_px + 1 <= min(width_px, height_px),
         f"the window (2 x it + 1) must fit the image size {width_px}x{height_px}"),
    )
    for key, ok, expected in checks:
        if not ok:
            raise InputError(f"frontend.{key}", f"{getattr(config, key)} does not fit the images: {expected}")


#: prior standard deviation of the disparity offset (px): a good stereo calibration (frontend.disparity_offset)
OFFSET_PRIOR_SIGMA_PX = 0.3


def _rotation_deg(T: F64) -> float:
    return float(np.degrees(np.linalg.norm(so3_log(T[:3, :3]))))


class FrontEnd:
    """Stereo keyframe visual odometry. Feed frames in time order to :meth:`process`.

    Internally everything runs on rectified images in the rectified left camera frame;
    results are converted to the original left camera (``world_from_cam``). The world frame
    is the first keyframe's left camera.
    """

    def __init__(
        self,
        calibration: StereoCalibration,
        config: FrontendConfig | None = None,
        keep_observations: bool = False,
        warm: bool = True,
    ) -> None:
        """``keep_observations``: each tracked frame's result carries the points its pose kept (``observed``).

        ``warm``: :meth:`warm_up` now; else the caller calls it before the first frame (the pipeline, after
        starting its worker processes: their start-up then runs beside the warm-ups, cpu17).
        """
        self.config = config or FrontendConfig()
        self.keep_observations = keep_observations
        if self.config.patch_px % 2 == 0:
            raise InputError("frontend.patch_px", f"must be odd, got {self.config.patch_px}")
        self.input_calibration = calibration.check("calibration")
        self.rectifier = Rectifier(calibration)
        self.calibration = self.rectifier.calibration  # rectified
        check_sizes_against_image(self.config, *self.calibration.image_size)
        self.rect_from_cam = self.rectifier.rect_from_cam
        self.cam_from_rect = invert_pose(self.rect_from_cam)
        self.left_camera = self.calibration.left_camera()
        self.right_camera = self.calibration.right_camera()
        self.rig = CameraRig.single(self.left_camera)
        self.pose_options = PoseOptions(
            loss=self.config.pose_loss,  # type: ignore[arg-type]
            min_scale=self.config.pose_min_scale_px,
            step_tolerance=self.config.pose_step_tolerance,
            max_iterations=self.config.pose_max_iterations,
            huber_warmup=self.config.pose_huber_warmup,
            reweight_iterations=self.config.pose_reweight_iterations,
        )
        self._world_from_kf: dict[int, F64] = {}
        self._active: _ActiveSet | None = None
        self._older: list[_ActiveSet] = []  # keyframes before the active one (re-measured)
        self._local: list[_LocalSet] = []  # earlier keyframes' sets still tracked (local map)
        self._local_inliers: list[int] = []  # local-map points each frame's pose kept, since the keyframe
        # (image, d/du, d/dv): the last image's gradients for the affine re-measurements in it
        self._gradients: tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.float32]] | None = None
        self._next_kf_id = 0
        self._next_landmark_id = 0
        self._segment = 0
        # tracking state (rectified frames)
        self._track_idx = np.zeros(0, dtype=np.int64)
        self._track_uv = np.zeros((0, 2))
        self._far_idx = np.zeros(0, dtype=np.int64)  # tracked far bearings of the active set
        self._far_uv = np.zeros((0, 2))
        self._outlier_uv = np.zeros((0, 2))  # tracked in the last frame, rejected by the pose
        self._moving_uv = np.zeros((0, 2))  # last positions of tracks dropped as moving (issue 36)
        # frontend.disparity_offset (issue 36): the local BAs' offsets fused by their information
        self._offset_mean_px = 0.0  # posterior mean of the offset (px)
        self._offset_info = 1.0 / OFFSET_PRIOR_SIGMA_PX**2  # its information (1/px^2)
        self._offset_count = 0
        self._offset_px = 0.0  # applied to new matches (measured right column - offset)
        self._left_rect: NDArray[np.uint8] | None = None  # the last rectified left image
        self._prev_pyr: Pyramid | None = None
        self._kf_pyr: Pyramid | None = None
        self._kf_from_prev: F64 = np.eye(4)
        self._velocity: F64 = np.eye(4)  # prev_from_cur of the last measured step
        self._velocity_known = False  # a measured step exists (the jump test needs one)
        self._frames_since_ok = 0
        self._last_stamp: int | None = None
        # frontend.mono_depth: observer depths of corners without a stereo match
        self._mono = (
            MonoDepthTracks(self.config, self.left_camera, self.calibration.image_size)
            if self.config.mono_depth == "observer"
            else None
        )
        self._mono_used = 0
        self._good_stamp = 0
        # robust per-coordinate scale (px) of each frame's pose residuals since the keyframe
        self._pose_sigma_px: list[float] = []
        # an old keyframe's features tracked again after a closure (resume_features)
        self._resumed: ResumedSet | None = None
        # frontend.local_ba_beside: the last keyframe's BA on its thread, and the keyframes not handed yet
        # (each with the next frame's result, at its BA's pose)
        self._pending_ba: tuple[Beside[HybridBAResult], _LocalBAJob, int] | None = None
        self._late: list[Keyframe] = []
        # the keyframe policy run one frame ahead (prepare): the last tracked frame's inliers and whether
        # the next frame is expected to make a keyframe
        self._inliers_prev: int | None = None
        self._expect_keyframe = False
        # issue 36 (tail14): the frame being processed is the run's last (prepare): it becomes a keyframe
        # when tracked, so the frames after the last policy keyframe are bridged and refined like the others
        self._last_frame = False
        # frontend.keyframe_match_ahead: the expected keyframe's corners and matches, made beside its
        # frame's tracking (its rectified left image, the thread)
        self._ahead: tuple[NDArray[np.uint8], Beside[KeyframeMatches]] | None = None
        if 0 < self.config.opencv_threads < cv2.getNumThreads():  # process-wide: only ever lowered
            cv2.setNumThreads(self.config.opencv_threads)
        lower_switch_interval(self.config.gil_switch_interval_ms)
        if warm:
            self.warm_up()

    def warm_up(self) -> None:
        """Load (or compile) the front end's compiled kernels now, not in a frame (issue 33).

        The stereo scan, the affine re-measurement, the pose's point term, the local BA's loop (and the
        shared tracks' kernel when on): 0.11-0.13 s of CPU from numba's cache in a KITTI clip run (cpu17).
        """
        from loopmodel.frontend._ba_kernels import warm_up as warm_up_ba
        from loopmodel.frontend._stereo_kernels import warm_up as warm_up_stereo
        from loopmodel.frontend.affine_klt import warm_up
        from loopmodel.pose._point_kernels import warm_up as warm_up_pose

        warm_up_stereo()
        warm_up()
        warm_up_pose()
        if self.config.local_ba:
            warm_up_ba()
        if self.config.klt_share_px > 0:
            from loopmodel.imaging._klt_kernels import warm_up as warm_up_share

            warm_up_share()

    # ------------------------------------------------------------------ public
    @property
    def world_from_kf(self) -> dict[int, F64]:
        """Current estimate of every keyframe pose (original left camera, metres)."""
        return dict(self._world_from_kf)

    def mono_depth_estimates(self) -> dict[str, NDArray] | None:
        """Observer depths of the current tracks without stereo depth (``frontend.mono_depth``; None when off).

        ``ref_kf`` reference keyframe ids, ``uv_ref`` (N, 2) rectified pixels in the reference
        keyframe, ``depth_m`` depths there, ``rel_sigma`` predicted relative standard deviations,
        ``converged`` whether the pose uses them.
        """
        if self._mono is None:
            return None
        mono = self._mono
        return {
            "ref_kf": mono.ref_kf.copy(),
            "uv_ref": mono.uv_ref.copy(),
            "depth_m": mono.obs.depth_m(),
            "rel_sigma": mono.obs.rel_sigma(mono.sigma_norm),
            "converged": mono.converged(),
        }

    def tracked_features(self) -> TrackedFeatures:
        """The last frame's rectified left image and its tracked features (pixels)."""
        kf = self._active.keyframe.id if self._active is not None else -1
        return TrackedFeatures(self._left_rect, self._track_uv.copy(), self._outlier_uv.copy(), kf)

    def apply_correction(self, world_from_kf: dict[int, F64]) -> None:
        """Replace keyframe poses by corrected ones (e.g. from the back end).

        Tracking continues from the corrected pose of the current keyframe. A keyframe not handed yet
        (``local_ba_beside``) moves with its previous keyframe, as if made after the correction.
        """
        moved: dict[int, F64] = {}  # corrected keyframe -> new_from_old (world)
        for kf_id, T in world_from_kf.items():
            if kf_id in self._world_from_kf:
                new = np.asarray(T, dtype=float).reshape(4, 4).copy()
                moved[int(kf_id)] = new @ invert_pose(self._world_from_kf[kf_id])
                self._world_from_kf[kf_id] = new
        for i, late in enumerate(self._late):
            prev_id = late.prev_keyframe_id
            if late.id not in moved and prev_id is not None and prev_id in moved:
                moved[late.id] = moved[prev_id]
                self._world_from_kf[late.id] = nearest_rigid(moved[prev_id] @ self._world_from_kf[late.id])
                self._late[i] = replace(late, world_from_kf=self._world_from_kf[late.id].copy())
        if self._active is not None:
            kf = self._active.keyframe
            kf.world_from_kf = self._world_from_kf[kf.id]
            self._active.world_from_kfrect = kf.world_from_kf @ self.cam_from_rect

    def resume_features(self, request: ResumeFeatures) -> int:
        """Go on tracking an old keyframe's features found again in the current keyframe (seed 004, section 5).

        ``request`` comes from the loop stage (:class:`~loopmodel.stages.LoopOutcome.resume`) for the
        keyframe just made; its features are tracked on beside the current set, and each later
        keyframe observes them (monocular observations with the old landmark ids, for the back end).
        Returns how many are taken (0 when the request is not for the active keyframe).
        """
        if self._active is None or int(request.keyframe) != self._active.keyframe.id or not len(request):
            return 0
        self._resumed = ResumedSet.from_request(request)
        if self._prev_pyr is not self._kf_pyr and self._kf_pyr is not None:
            # the keyframe was handed a frame late (local_ba_beside): tracked on into the frame since, as
            # that frame would have tracked it
            self._track_resumed(self._prev_pyr, self._kf_from_prev, self._kf_pyr)
        return len(self._resumed) if self._resumed is not None else 0

    def resumed_features(self) -> ResumedSet | None:
        """The old feature set being tracked again, if any (read-only use)."""
        return self._resumed

    def process(self, frame: StereoFrame) -> FrameResult:
        """Track one stereo frame; may create a keyframe.

        ``res.keyframe`` is final when handed: with ``local_ba_beside`` a keyframe whose local BA runs
        beside the next frame comes with that frame's result, at the BA's pose (its own frame's result
        has ``is_keyframe`` and no ``keyframe``); after the last frame :meth:`finish_keyframes` hands it.
        """
        res = self._process(frame)
        if self._late and self._late[0].timestamp_ns < frame.timestamp_ns:
            # the last frame's keyframe: its BA taken in this frame after the KLT (here when the frame
            # did not get that far); a keyframe made in this frame waits behind it
            if self._pending_ba is not None and self._pending_ba[2] == self._late[0].id:
                self._finish_local_ba()
            assert res.keyframe is None
            res.keyframe = self._late.pop(0)
        return res

    def finish_keyframes(self) -> list[Keyframe]:
        """The keyframes not handed yet (``local_ba_beside``: the last one), their BA taken.

        Between frames (the pipeline, before each frame: the BA then precedes that frame's KLT, the
        inline order) or after the last one.
        """
        self._finish_local_ba()
        out, self._late = self._late, []
        return out

    def _process(self, frame: StereoFrame) -> FrameResult:
        """:meth:`process` but for the hand-off of the last frame's keyframe."""
        t0 = time.perf_counter()
        if self._last_stamp is not None and frame.timestamp_ns <= self._last_stamp:
            raise InputError(
                f"frame {frame.index}",
                f"timestamps must increase ({frame.timestamp_ns} ns after {self._last_stamp} ns)",
            )
        self._last_stamp = frame.timestamp_ns
        cfg = self.config
        # the rectified image and its check: from the thread that made them between frames (left_ahead)
        left, (quality_ok, why) = self.rectifier.left_and(frame.left, self._image_ok)
        self._left_rect = left
        self._outlier_uv = np.zeros((0, 2))
        if self._active is None:
            if not quality_ok:
                return self._lost(frame, np.eye(4), why, t0)
            res = self._start_keyframe(
                frame, left, None, np.eye(4) @ self.cam_from_rect, t0, connected=False
            )
            return (
                res
                if res is not None
                else self._lost(frame, np.eye(4), "too few stereo points", t0)
            )

        active = self._active
        gap = self._frames_since_ok
        vel = self._velocity
        for _ in range(gap):
            vel = vel @ self._velocity
        kf_from_pred = self._kf_from_prev @ vel
        if not quality_ok:
            self._frames_since_ok += 1
            return self._lost(frame, active.world_from_kfrect @ kf_from_pred, why, t0)

        self._match_ahead(frame, left)
        cur_pyr = build_pyramid(left, cfg.klt_window_px, cfg.klt_levels)
        status, reason, tracked, inliers, kf_from_cur, used_ransac = self._track(
            cur_pyr, kf_from_pred
        )
        t_track = time.perf_counter()
        if status != "OK":
            self._frames_since_ok += 1
            if (
                self._frames_since_ok > cfg.max_retrack_frames
                or len(self._track_idx) < cfg.min_inliers
            ):
                # recovery: a new, unconnected keyframe at the motion-model pose
                self._segment += 1
                res = self._start_keyframe(
                    frame,
                    left,
                    cur_pyr,
                    active.world_from_kfrect @ kf_from_pred,
                    t0,
                    connected=False,
                )
                if res is not None:
                    res.status = "LOST"
                    res.reason = f"{reason}; new keyframe (segment {self._segment})"
                    return res
                self._segment -= 1
            return self._lost(
                frame, active.world_from_kfrect @ kf_from_pred, reason, t0, tracked, inliers
            )

        # measured: update the motion model and the tracking state
        step = invert_pose(self._kf_from_prev) @ kf_from_cur
        if gap > 0:
            step = se3_exp(se3_log(step) / (gap + 1))
        # re-projected onto SE(3): these products feed back every frame, so rounding in
        # the rotation blocks would otherwise grow geometrically
        self._velocity = nearest_rigid(step)
        self._velocity_known = True
        self._kf_from_prev = nearest_rigid(kf_from_cur)  # (the resumed old set tracked with the frame: _klt_frame)
        self._prev_pyr = cur_pyr
        self._frames_since_ok = 0

        need = self._need_keyframe(kf_from_cur, inliers)
        self._expect_keyframe = not need and self._keyframe_ahead(kf_from_cur, inliers)
        self._inliers_prev = inliers
        if need:
            observed = self._observed() if self.keep_observations else None  # before the new set replaces them
            res = self._start_keyframe(
                frame,
                left,
                cur_pyr,
                active.world_from_kfrect @ kf_from_cur,
                t0,
                connected=True,
                kf_from_cur=kf_from_cur,
            )
            if res is not None:
                res.tracked, res.inliers, res.used_ransac = tracked, inliers, used_ransac
                res.mono_points = self._mono_used
                res.track_ms = (t_track - t0) * 1e3
                # the new keyframe: handed now, or (local_ba_beside) waiting behind its BA, last in line
                made = res.keyframe if res.keyframe is not None else (self._late[-1] if self._late else None)
                res.observed = observed if made is not None and made.connected else None
                return res
        kf = active.keyframe
        world_from_cam = active.world_from_kfrect @ kf_from_cur @ self.rect_from_cam
        return FrameResult(
            frame.timestamp_ns,
            world_from_cam,
            "OK",
            False,
            kf.id,
            self.cam_from_rect @ kf_from_cur @ self.rect_from_cam,
            tracked,
            inliers,
            frame_index=frame.index,
            segment=self._segment,
            track_ms=(time.perf_counter() - t0) * 1e3,
            used_ransac=used_ransac,
            mono_points=self._mono_used,
            observed=self._observed() if self.keep_observations else None,
        )

    def _observed(self) -> FrameObservations:
        """The stereo points the last pose kept (active set, then the local map's sets) and their pixels."""
        assert self._active is not None
        ids = [self._active.keyframe.landmark_ids[self._track_idx]]
        uv = [self._track_uv]
        for ls in self._local:
            ids.append(ls.kf_set.keyframe.landmark_ids[ls.idx])
            uv.append(ls.uv)
        return FrameObservations(np.concatenate(ids).astype(np.int64), np.vstack(uv).astype(np.float32))

    # ------------------------------------------------------------------ tracking
    def _image_ok(self, left: NDArray[np.uint8]) -> tuple[bool, str]:
        """Whether a rectified left image can be tracked (not flat or black, not blurred), and why not.

        Run on the rectify-ahead thread between frames (:meth:`left_ahead`); OpenCV's standard
        deviations (double sums), which release the interpreter lock, not numpy's.
        """
        small = cv2.resize(left, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
        std = float(cv2.meanStdDev(small)[1][0, 0])
        if std < self.config.min_image_std:
            return False, f"image flat or black (std {std:.1f})"
        if self.config.min_sharpness > 0:
            sharp = float(cv2.meanStdDev(cv2.Laplacian(small, cv2.CV_32F))[1][0, 0]) ** 2
            if sharp < self.config.min_sharpness:
                return False, f"image blurred (Laplacian variance {sharp:.1f})"
        return True, ""

    def _track(self, cur_pyr: Pyramid, kf_from_pred: F64) -> tuple[str, str, int, int, F64, bool]:
        """KLT from the last good frame, robust pose against the keyframe."""
        cfg = self.config
        assert self._active is not None and self._prev_pyr is not None
        idx = self._track_idx
        if idx.size < cfg.min_inliers:
            return "LOST", f"only {idx.size} tracks left", int(idx.size), 0, kf_from_pred, False
        pred_from_kf = invert_pose(kf_from_pred)
        ft = self._klt_frame(cur_pyr, pred_from_kf)
        tracked = int(ft.ok.sum())
        if tracked < cfg.min_inliers:
            return "LOST", f"only {tracked} KLT tracks", tracked, 0, kf_from_pred, False
        terms = self._pose_terms(ft, cur_pyr, pred_from_kf)
        assert terms.term is not None
        try:
            res = estimate_pose(
                terms.term,
                pred_from_kf,
                self.pose_options,
                cfg.ransac_threshold_px,
                cfg.prediction_gate_px,
                extra_terms=terms.extra,
            )
        except EstimationError as exc:
            return "LOST", f"pose failed ({exc})", tracked, 0, kf_from_pred, False
        inl_all = res.inliers[0]
        n_inl = int(inl_all[:tracked].sum())  # stereo points; local-map and mono-depth points follow
        kf_from_cur = invert_pose(res.rig_from_ref)
        why = self._pose_rejected(int(inl_all.sum()), n_inl, kf_from_pred, kf_from_cur)
        if why:
            return "LOST", why, tracked, n_inl, kf_from_pred, res.used_ransac
        self._commit_tracks(ft, terms, res)
        return "OK", "", tracked, n_inl, kf_from_cur, res.used_ransac

    def _klt_frame(self, cur_pyr: Pyramid, pred_from_kf: F64) -> _FrameTracks:
        """This frame's KLT of the active set's points, its far bearings and the local map's points.

        Each starts at its motion-model prediction (``pred_from_kf``: predicted camera from the
        active keyframe, rectified); a point behind the predicted camera is not tracked. The last
        keyframe's local BA run beside (``local_ba_beside``) is taken after the KLT, before the pose.
        """
        cfg = self.config
        assert self._active is not None and self._prev_pyr is not None
        active = self._active
        ft = _FrameTracks(idx=self._track_idx, fidx=self._far_idx)
        ft.pts = active.points[ft.idx]
        p_pred = ft.pts @ pred_from_kf[:3, :3].T + pred_from_kf[:3, 3]
        front = p_pred[:, 2] > 1e-3
        guess = self._track_uv.copy()
        guess[front] = self.left_camera.project(p_pred[front])
        start = self._track_uv
        if ft.fidx.size:
            # far bearings: homogeneous points R ray + rho t at the predicted pose
            ft.q_far = active.far_rays[ft.fidx] @ pred_from_kf[:3, :3].T
            ft.q_far += active.far_inv_depth[ft.fidx, None] * pred_from_kf[:3, 3]
            f_front = ft.q_far[:, 2] > 1e-6
            f_guess = self._far_uv.copy()
            f_guess[f_front] = self.left_camera.project(ft.q_far[f_front])
            start, guess = np.vstack([start, self._far_uv]), np.vstack([guess, f_guess])
            front = np.concatenate([front, f_front])
        ft.loc = self._local_prediction(pred_from_kf)
        if ft.loc.sizes:
            start, guess = np.vstack([start, ft.loc.prev_uv]), np.vstack([guess, ft.loc.guess])
            front = np.concatenate([front, ft.loc.front])
        rs = self._resumed
        n_res = len(rs) if rs is not None else 0
        if rs is not None and n_res:  # fr16: its own KLT call cost 0.6 ms of fixed CPU (pyramids, derivatives)
            r_guess, r_front = rs.predict(self.left_camera, pred_from_kf)
            start, guess = np.vstack([start, rs.uv]), np.vstack([guess, r_guess])
            front = np.concatenate([front, r_front])
        share = shared_tracks(start, guess, cfg.klt_share_px, cfg.klt_share_motion_px) if cfg.klt_share_px > 0 else None
        uv, ok = track_klt_halves(self._prev_pyr, cur_pyr, start, guess, cfg, self.calibration.image_size, share)
        ok &= front
        if self._pending_ba is not None:  # the last keyframe's BA: its points and pose before this pose solve
            self._finish_local_ba()
            ft.loc = self._local_prediction(pred_from_kf)
        n_near, n_far, n_all = ft.idx.size, ft.fidx.size, uv.shape[0] - n_res
        ft.uv_far, ft.ok_far = uv[n_near : n_near + n_far], ok[n_near : n_near + n_far]
        ft.uv_loc, ft.ok_loc = uv[n_near + n_far : n_all], ok[n_near + n_far : n_all]
        ft.uv_res, ft.ok_res = uv[n_all:], ok[n_all:]
        ft.uv, ft.ok = uv[:n_near], ok[:n_near]
        return ft

    def _pose_terms(self, ft: _FrameTracks, cur_pyr: Pyramid, pred_from_kf: F64) -> _PoseTerms:
        """The pose's terms: tracked stereo points (active set, local map), mono-depth points, far bearings."""
        cfg = self.config
        assert self._active is not None and self._prev_pyr is not None
        active = self._active
        ok, idx, loc = ft.ok, ft.idx, ft.loc
        out = _PoseTerms()
        prior = None
        if cfg.depth_weighting:
            sigma_z = None
            if cfg.disparity_sigma_source == "match" and active.disparity_sigma_px.size:
                fb = self.calibration.fx_px * self.calibration.baseline_m
                sigma_z = ft.pts[ok, 2] ** 2 / fb * active.disparity_sigma_px[idx[ok]]
            prior = self._depth_weights(ft.pts[ok], pred_from_kf, sigma_z)
        p_all, uv_all = ft.pts[ok], ft.uv[ok]
        out.loc_sel = np.flatnonzero(ft.ok_loc)
        if out.loc_sel.size:  # the local map's points (earlier keyframes), in the active keyframe's frame
            p_all = np.vstack([p_all, loc.points_kf[out.loc_sel]])
            uv_all = np.vstack([uv_all, ft.uv_loc[out.loc_sel]])
            if prior is not None and loc.prior is not None:
                prior = np.concatenate([prior, loc.prior[out.loc_sel]])
        out.n_stereo = p_all.shape[0]
        if self._mono is not None and len(self._mono):
            out.kf_from_ref = self._mono_frames()
            m_uv, out.m_ok = self._mono.track(self._prev_pyr, cur_pyr, pred_from_kf, out.kf_from_ref)
            out.mono_sel = np.flatnonzero(out.m_ok & self._mono.converged())
            if out.mono_sel.size:
                p_m = self._mono.points_in(out.kf_from_ref)[out.mono_sel]
                w_m = self._depth_weights(p_m, pred_from_kf, self._mono.sigma_z_m()[out.mono_sel])
                prior = np.concatenate([np.ones(len(p_all)) if prior is None else prior, w_m])
                p_all, uv_all = np.vstack([p_all, p_m]), np.vstack([uv_all, m_uv[out.mono_sel]])
        out.term = PointTerm(self.rig, p_all, uv_all, prior_weight=prior)
        out.far_sel = np.flatnonzero(ft.ok_far)
        if out.far_sel.size >= 3:
            s = out.far_sel
            out.extra.append(self._far_term(ft.fidx[s], ft.uv_far[s], ft.q_far[s], pred_from_kf))
        return out

    def _pose_rejected(self, n_all: int, n_inl: int, kf_from_pred: F64, kf_from_cur: F64) -> str:
        """Why a solved pose is not taken ("" when it is): too few inliers, or a jump from the motion model."""
        cfg = self.config
        if n_all < cfg.min_inliers:
            return f"only {n_inl} pose inliers"
        jump = invert_pose(kf_from_pred) @ kf_from_cur
        jump_m = float(np.linalg.norm(jump[:3, 3]))
        jump_deg = _rotation_deg(jump)
        if self._velocity_known and (jump_m > cfg.max_jump_m or jump_deg > cfg.max_jump_deg):
            return f"pose jump {jump_m:.3f} m / {jump_deg:.2f} deg from the motion model"
        return ""

    def _commit_tracks(self, ft: _FrameTracks, terms: _PoseTerms, res: PoseResult) -> None:
        """Keep what the pose ``res`` kept: the active set's, far, local-map and mono-depth tracks."""
        tracked = int(ft.ok.sum())
        n_sl = terms.n_stereo
        inl_all = res.inliers[0]
        inl = inl_all[:tracked]
        keep = np.flatnonzero(ft.ok)[inl]
        if self.config.moving_gate > 0:
            keep = self._drop_moving(ft.idx, keep, ft.uv, res.rig_from_ref)
        self._outlier_uv = ft.uv[np.flatnonzero(ft.ok)[~inl]]
        if int(inl.sum()) >= 6:  # the run's own KLT/stereo noise (for the back end's final refinement)
            self._pose_sigma_px.append(robust_scale(res.residual_norms[0][:tracked][inl], 2, 0.0))
        self._track_idx = ft.idx[keep]
        self._mono_used = 0
        if self._mono is not None and terms.m_ok is not None:
            m_keep = terms.m_ok.copy()
            m_keep[terms.mono_sel[~inl_all[n_sl:]]] = False  # converged points the pose rejected
            self._mono_used = int(inl_all[n_sl:].sum())
            dt_s = max((self._last_stamp or 0) - self._good_stamp, 1) * 1e-9
            self._mono.commit(res.rig_from_ref, terms.kf_from_ref, dt_s, m_keep)
            self._good_stamp = self._last_stamp or 0
        self._track_uv = ft.uv[keep]
        if ft.loc.sizes:
            self._keep_local(ft.loc, terms.loc_sel[inl_all[tracked:n_sl]], ft.uv_loc)
        f_keep = terms.far_sel[res.inliers[1]] if terms.extra else terms.far_sel
        self._far_idx, self._far_uv = ft.fidx[f_keep], ft.uv_far[f_keep]
        if self._resumed is not None and ft.ok_res.size == len(self._resumed):
            self._keep_resumed(ft, invert_pose(res.rig_from_ref))

    def _keep_resumed(self, ft: _FrameTracks, kf_from_cur: F64) -> None:
        """The resumed old set's tracks of this frame (:meth:`_klt_frame`) within the gate of the solved pose."""
        rs = self._resumed
        assert rs is not None
        if not rs.keep_tracked(self.left_camera, kf_from_cur, ft.uv_res, ft.ok_res, self.config.prediction_gate_px):
            logger.info("old feature set of keyframe %d: no feature left", rs.match_keyframe)
            self._resumed = None

    def _local_prediction(self, pred_from_kf: F64) -> _LocalPrediction:
        """The local map's tracked points (earlier keyframes' sets) for this frame, at the predicted pose.

        ``pred_from_kf``: predicted current camera from the active keyframe (rectified). Each set's
        points are carried into the active keyframe's frame through the current keyframe poses
        (corrected by the back end); with ``depth_weighting`` each is weighted by its own depth
        uncertainty, in its own keyframe's frame.
        """
        assert self._active is not None
        kf_from_world = invert_pose(self._active.world_from_kfrect)
        out = _LocalPrediction()
        parts: list[tuple[F64, F64, F64, NDArray[np.bool_], F64 | None]] = []
        for ls in self._local:
            kf = ls.kf_set.keyframe
            kf_from_old = kf_from_world @ self._world_from_kf.get(kf.id, kf.world_from_kf) @ self.cam_from_rect
            pred_from_old = pred_from_kf @ kf_from_old
            p_old = ls.kf_set.points[ls.idx]
            q = p_old @ pred_from_old[:3, :3].T + pred_from_old[:3, 3]
            front = q[:, 2] > 1e-3
            guess = ls.uv.copy()
            guess[front] = self.left_camera.project(q[front])
            prior = (
                self._depth_weights(p_old, pred_from_old, ls.kf_set.sigma_z_m[ls.idx])
                if self.config.depth_weighting
                else None
            )
            parts.append((p_old @ kf_from_old[:3, :3].T + kf_from_old[:3, 3], ls.uv, guess, front, prior))
            out.sizes.append(ls.idx.size)
        if parts:
            out.points_kf = np.vstack([p[0] for p in parts])
            out.prev_uv = np.vstack([p[1] for p in parts])
            out.guess = np.vstack([p[2] for p in parts])
            out.front = np.concatenate([p[3] for p in parts])
            priors = [p[4] for p in parts]
            out.prior = None if any(w is None for w in priors) else np.concatenate(priors)  # type: ignore[arg-type]
        return out

    def _keep_local(self, loc: _LocalPrediction, kept: NDArray[np.int64], uv: F64) -> None:
        """Keep the local map's points the pose kept (``kept``: indices into ``loc``) at ``uv`` (px)."""
        offsets = np.concatenate([[0], np.cumsum(loc.sizes)])
        self._local_inliers.append(int(kept.size))
        local = []
        for ls, a, b in zip(self._local, offsets[:-1], offsets[1:], strict=True):
            sel = kept[(kept >= a) & (kept < b)]
            if sel.size >= 3:
                local.append(_LocalSet(ls.kf_set, ls.idx[sel - a], uv[sel]))
        self._local = local

    def _fuse_offset(self, offset_px: float, var_px2: float) -> None:
        """Take a local BA's posterior disparity offset (px, total: the applied correction plus the BA's rest).

        Each BA starts from the previous posterior as its prior (a scalar Kalman filter without
        process noise, starting from 0 +- ``OFFSET_PRIOR_SIGMA_PX``); the posterior mean corrects the
        next keyframe's matches, clipped to 2 px (a larger one is a wrong calibration).
        """
        if not (np.isfinite(offset_px) and np.isfinite(var_px2) and var_px2 > 0):
            return
        self._offset_mean_px = offset_px
        self._offset_info = 1.0 / var_px2
        self._offset_count += 1
        self._offset_px = float(np.clip(offset_px, -2.0, 2.0))

    def _drop_moving(
        self, idx: NDArray[np.int64], keep: NDArray[np.int64], uv: F64, cur_from_kf: F64
    ) -> NDArray[np.int64]:
        """Pose inliers ``keep`` (indices into the tracks ``idx``, seen at ``uv``) minus the points that move.

        Each point's signed residual at the solved pose ``cur_from_kf`` goes into a running mean
        (halved each frame); a point whose mean, after two frames or more, exceeds ``moving_gate``
        times the frame's robust residual scale drifts consistently, as a point on a moving object
        does, even when each frame's residual passes the per-frame gate. Its position is kept in
        ``_moving_uv``: the next keyframe takes no new point near it.
        """
        cfg = self.config
        assert self._active is not None
        a = self._active
        if a.residual_mean_px.shape[0] != a.points.shape[0]:
            a.residual_mean_px = np.zeros((a.points.shape[0], 2))
            a.residual_frames = np.zeros(a.points.shape[0], np.int64)
        pi = idx[keep]
        p = a.points[pi] @ cur_from_kf[:3, :3].T + cur_from_kf[:3, 3]
        r = self.left_camera.project(p) - uv[keep]
        a.residual_mean_px[pi] = 0.5 * a.residual_mean_px[pi] + 0.5 * r
        a.residual_frames[pi] += 1
        scale = max(robust_scale(np.linalg.norm(r, axis=1), 2, 0.0), cfg.pose_min_scale_px)
        mean = a.residual_mean_px[pi]
        if a.sigma_z_m.shape[0] == a.points.shape[0]:
            # a static point whose stereo depth is off drifts too, along its epipolar line: take out
            # what a depth error within moving_gate depth sigmas explains (g: px per metre of depth)
            ray = a.points[pi] / a.points[pi, 2:3]
            g = np.einsum("nij,nj->ni", self.left_camera.project_jacobian(p), ray @ cur_from_kf[:3, :3].T)
            dz = np.einsum("ni,ni->n", mean, g) / np.maximum(np.einsum("ni,ni->n", g, g), 1e-12)
            lim = cfg.moving_gate * a.sigma_z_m[pi]
            mean = mean - g * np.clip(dz, -lim, lim)[:, None]
        drift_px = np.linalg.norm(mean, axis=1)
        moving = (a.residual_frames[pi] >= 2) & (drift_px > cfg.moving_gate * scale)
        self._moving_uv = uv[keep[moving]]
        return keep[~moving]

    def _far_term(self, sel: NDArray[np.int64], uv: F64, q_pred: F64, cur_from_kf: F64) -> PointTerm:
        """Pose term of the tracked far bearings ``sel`` of the active set, seen at ``uv`` (pixels).

        Homogeneous points (ray, inverse depth); with ``depth_weighting`` each is weighted by pixel
        variance over pixel-plus-inverse-depth variance at the predicted pose (``q_pred``: its
        homogeneous point there), the inverse depth's standard deviation being the disparity
        noise over focal length times baseline.
        """
        cfg = self.config
        assert self._active is not None
        active = self._active
        prior = None
        if cfg.depth_weighting:
            fb = self.calibration.fx_px * self.calibration.baseline_m
            sigma_rho = cfg.disparity_sigma_px / fb
            q = np.where(q_pred[:, 2:3] > 1e-6, q_pred, active.far_rays[sel])
            g = np.einsum("nij,j->ni", self.left_camera.project_jacobian(q), cur_from_kf[:3, 3])
            var_px = cfg.pose_min_scale_px**2
            prior = var_px / (var_px + np.einsum("ni,ni->n", g, g) * sigma_rho**2)
        return PointTerm(
            self.rig, active.far_rays[sel], uv, prior_weight=prior, inverse_depth_per_m=active.far_inv_depth[sel]
        )

    def _track_resumed(self, cur_pyr: Pyramid | None, kf_from_cur: F64, prev_pyr: Pyramid | None = None) -> None:
        """Track the resumed old set into this frame (KLT from ``prev_pyr``, else the last good frame)."""
        prev_pyr = self._prev_pyr if prev_pyr is None else prev_pyr
        if self._resumed is None or prev_pyr is None or cur_pyr is None:
            return
        cfg = self.config
        klt = (cfg.klt_window_px, cfg.klt_levels, cfg.fb_threshold_px, cfg.klt_iterations)
        rs = self._resumed
        if not rs.track(
            self.left_camera, prev_pyr, cur_pyr, kf_from_cur, cfg.prediction_gate_px, klt,
            self.calibration.image_size,
        ):
            logger.info("old feature set of keyframe %d: no feature left", rs.match_keyframe)
            self._resumed = None

    def _observe_resumed(self, closed: _ClosedInterval, left: NDArray[np.uint8], kf_from_cur: F64) -> F64:
        """``closed``'s observations plus the resumed old set's features found in the new keyframe ``left``.

        Rows (landmark_id, u, v); the resumed set moves to the new keyframe.
        """
        rs = self._resumed
        if rs is None:
            return closed.mono_obs
        cfg = self.config
        match_kf = rs.match_keyframe
        rows = rs.observe_at_keyframe(
            self.left_camera, left, kf_from_cur, closed.kf_from_new,
            cfg.remeasure_half_window_px, cfg.remeasure_min_ncc, cfg.remeasure_max_shift_px,
        )
        if not len(rs):
            self._resumed = None
        seen = set(closed.mono_obs[:, 0].astype(np.int64).tolist())
        rows = rows[[int(i) not in seen for i in rows[:, 0]]]
        closed.ba_info["resumed_features"] = float(rows.shape[0])
        closed.ba_info["resumed_from_keyframe"] = float(match_kf)
        return np.vstack([closed.mono_obs, rows])

    def _mono_frames(self) -> dict[int, F64]:
        """Reference keyframes of the mono-depth tracks -> the active keyframe (rectified)."""
        assert self._mono is not None and self._active is not None
        refs = np.append(self._mono.ref_kf, self._active.keyframe.id)
        w = {int(k): self._world_from_kf[int(k)] @ self.cam_from_rect for k in np.unique(refs)}
        return kf_from_ref_map(w, self._active.keyframe.id, self._mono.ref_kf)

    def _depth_weights(self, pts: F64, cur_from_kf: F64, sigma_z: F64 | None = None) -> F64:
        """Pixel variance over pixel-plus-depth variance of each point's projection at the predicted pose (first order).

        Far points, whose stereo depth is uncertain, count less for the pose. ``sigma_z`` (m): depth
        standard deviations (default: from stereo).
        """
        cfg = self.config
        fb = self.calibration.fx_px * self.calibration.baseline_m
        if sigma_z is None:
            sigma_z = pts[:, 2] ** 2 / fb * cfg.disparity_sigma_px
        p = pts @ cur_from_kf[:3, :3].T + cur_from_kf[:3, 3]
        ray = pts / pts[:, 2:3]  # d point / d depth (keyframe frame)
        J = self.left_camera.project_jacobian(p)  # (N, 2, 3)
        g = np.einsum("nij,nj->ni", J, ray @ cur_from_kf[:3, :3].T)
        var_px = cfg.pose_min_scale_px**2
        return var_px / (var_px + np.einsum("ni,ni->n", g, g) * sigma_z**2)

    def _keyframe_ahead(self, kf_from_cur: F64, inliers: int) -> bool:
        """Whether the next frame will likely make a keyframe (:meth:`prepare`).

        :meth:`_need_keyframe` of the next frame as extrapolated: the pose one more velocity step on,
        the inliers losing half this frame's loss (the loss slows down over an interval; none in the
        first frame after the keyframe, whose loss counts its outliers). Measured with the defaults'
        keyframes (front end alone): KITTI clip (configs/kitti.yaml) 13 keyframes after the first, 12
        expected, no false expectation in 37 other frames; orbit sample (configs/sim.yaml, 300 frames) 10
        keyframes, 7 expected, 1 false in 289. A missed keyframe decodes its right image within its frame (beside
        the corner detection), a false expectation decodes one never used.
        """
        loss = max(self._inliers_prev - inliers, 0) if self._inliers_prev is not None else 0
        return self._need_keyframe(kf_from_cur @ self._velocity, inliers - loss // 2)

    def left_ahead(self, left: NDArray[np.uint8]) -> None:
        """A coming frame's left image (raw) rectified and checked on the rectify-ahead thread (cpu15).

        Between frames, while the next one is read (the pipeline's frame loop); :meth:`process` of that
        frame takes both (``Rectifier.left_and``): the image check's 0.4-0.5 ms a 640x480 frame leaves
        the tracking thread. A rectifier replaced meanwhile (``calibration.refine: online``) does both then.
        """
        self.rectifier.left_ahead(left, self._image_ok)

    def prepare(self, frame: StereoFrame, last: bool = False) -> None:
        """Before :meth:`process` of ``frame``, outside its time: decode what it will need.

        Its right image when the last frame expected a keyframe now (a reader may decode it only when
        first used, :class:`~loopmodel.io.images.DeferredRightFrame`); it is then not decoded beside the
        keyframe's corner detection, within the frame (fe7: kitti_frame_ms_p95). ``last``: ``frame`` is
        the run's last one; tracked, it becomes a keyframe (``last_frame_keyframe``; issue 36, tail14: the
        frames after the last keyframe otherwise have none after them, are not bridged nor in the final BA).
        """
        self._last_frame = last and self.config.last_frame_keyframe
        self._expect_keyframe = self._expect_keyframe or self._last_frame
        if self._expect_keyframe:
            frame.right  # noqa: B018  # decoded here, kept by the frame

    def _match_ahead(self, frame: StereoFrame, left: NDArray[np.uint8]) -> None:
        """An expected keyframe's corners and stereo matches started beside this frame's KLT and pose.

        ``frontend.keyframe_match_ahead`` with ``keyframe_stereo: thread``. They read no tracker state
        (:func:`~loopmodel.frontend.stereo.keyframe_matches`); :meth:`_stereo_set` takes them when the
        frame makes its keyframe, with the offset and moving gate of that moment: the same set as made
        then. A false expectation drops them (the thread ends on its own).
        """
        self._ahead = None
        cfg = self.config
        if self._expect_keyframe and cfg.keyframe_match_ahead and cfg.keyframe_stereo == "thread":
            rectified = self.rectifier.right
            self._ahead = (left, Beside(True, keyframe_matches, left, lambda: rectified(frame.right), cfg))

    def _need_keyframe(self, kf_from_cur: F64, inliers: int) -> bool:
        cfg = self.config
        assert self._active is not None
        m = self._active.points.shape[0]
        if self._last_frame or inliers < max(cfg.min_tracked, cfg.min_tracked_fraction * m):
            return True
        if cfg.keyframe_parallax == "angle":
            parallax = median_parallax_rad(self._active.points[self._track_idx], kf_from_cur[:3, 3])
            if parallax > np.arctan(cfg.max_parallax_ratio):
                return True
        elif (
            np.linalg.norm(kf_from_cur[:3, 3])
            > cfg.max_parallax_ratio * self._active.median_depth_m
        ):
            return True
        return _rotation_deg(kf_from_cur) > cfg.max_rotation_deg

    def _left_gradients(self, left: NDArray[np.uint8]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Gradients of the rectified left image ``left``, computed once for all re-measurements in it."""
        from loopmodel.frontend.affine_klt import image_gradients

        if self._gradients is None or self._gradients[0] is not left:
            self._gradients = (left, *image_gradients(left))
        return self._gradients[1], self._gradients[2]

    def _remeasure_tracks(
        self, prev: _ActiveSet, left: NDArray[np.uint8], kf_from_cur: F64
    ) -> tuple[NDArray[np.int64], F64]:
        """The tracked features measured again against the keyframe's own patches: (indices, pixels) kept.

        Affine warp predicted by the pose, :mod:`loopmodel.frontend.affine_klt`. Frame-to-frame KLT
        slides over a keyframe interval, and these positions link the keyframes (mono observations,
        local BA). The tracks unchanged when fewer than ``max(6, min_inliers)`` match.
        """
        from loopmodel.frontend.affine_klt import predicted_affine, refine_affine

        cfg = self.config
        idx = self._track_idx
        if idx.size == 0:
            return idx, self._track_uv
        cur_from_kf = invert_pose(kf_from_cur)
        match = refine_affine(
            prev.keyframe.image,
            left,
            prev.stereo_px[idx][:, [0, 2]],
            self._track_uv,
            predicted_affine(self.left_camera, prev.points[idx], cur_from_kf),
            cfg.remeasure_half_window_px,
            min_ncc=cfg.remeasure_min_ncc,
            max_shift_px=cfg.remeasure_max_shift_px,
            cur_gradients=self._left_gradients(left),
        )
        if int(match.ok.sum()) >= max(6, cfg.min_inliers):
            return idx[match.ok], match.uv_px[match.ok]
        return idx, self._track_uv

    def _wide_ba_rows(self, prev: _ActiveSet, local: list[_LocalSet]) -> _WideRows:
        """The local map's points for a wider local BA (``frontend.local_ba_keyframes`` earlier sets of ``local``).

        Each set's tracked points, carried into ``prev``'s keyframe frame through the keyframe poses,
        with their stereo pixels in their own keyframe (held fixed in the BA: ``own_from_kf``, owner
        1, 2, ...) and where they are seen now.
        """
        out = _WideRows()
        k = self.config.local_ba_keyframes
        if k <= 0 or not local:
            return out
        kf_from_world = invert_pose(prev.world_from_kfrect)
        pts, ul, ur, uf, own, frames = [], [], [], [], [], []
        for j, ls in enumerate(local[:k]):
            kf = ls.kf_set.keyframe
            kf_from_own = kf_from_world @ self._world_from_kf.get(kf.id, kf.world_from_kf) @ self.cam_from_rect
            p = ls.kf_set.points[ls.idx]
            sp = ls.kf_set.stereo_px[ls.idx]
            pts.append(p @ kf_from_own[:3, :3].T + kf_from_own[:3, 3])
            ul.append(sp[:, [0, 2]])
            ur.append(sp[:, [1, 2]])
            uf.append(ls.uv)
            own.append(np.full(ls.idx.size, j + 1, np.int64))
            frames.append(invert_pose(kf_from_own))
            out.sizes.append(int(ls.idx.size))
        out.points_kf, out.uv_left, out.uv_right = np.vstack(pts), np.vstack(ul), np.vstack(ur)
        out.uv_final, out.owner, out.own_from_kf = np.vstack(uf), np.concatenate(own), np.stack(frames)
        return out

    def _refine_points(
        self, kf_set: _ActiveSet, sel_all: NDArray[np.int64], points_m: F64, inliers: NDArray[np.bool_],
        kf_from_end: F64,
    ) -> None:
        """Keep the local BA's refined points (``points_m``, keyframe frame) of the set's points ``sel_all``.

        Their depth standard deviation combines stereo with the triangulation over the keyframe
        interval (``kf_from_end``: the final frame's pose in the keyframe): the baseline across each
        ray, the same pixel noise.
        """
        sel = sel_all[inliers]
        p = points_m[inliers]
        if sel.size == 0:
            return
        kf_set.points[sel] = p
        ray = p / np.linalg.norm(p, axis=1, keepdims=True)
        t = kf_from_end[:3, 3]
        across_m = np.linalg.norm(t - (ray @ t)[:, None] * ray, axis=1)
        z2 = p[:, 2] ** 2
        fx, sd = self.calibration.fx_px, self.config.disparity_sigma_px
        inv_var = (fx * self.calibration.baseline_m / (z2 * sd)) ** 2 + (fx * across_m / (z2 * sd)) ** 2
        kf_set.sigma_z_m[sel] = 1.0 / np.sqrt(inv_var)

    def _remeasure_local(
        self, ls: _LocalSet, left: NDArray[np.uint8], world_from_rect: F64,
        gradients: tuple[NDArray[np.float32], NDArray[np.float32]],
    ) -> _LocalSet:
        """A local-map set's points measured again in a new keyframe against their own keyframe's patch.

        Affine, as :meth:`_remeasure_tracks`; those that fail leave the set. ``left``: the new
        keyframe's rectified left image (``gradients``: its :meth:`_left_gradients`),
        ``world_from_rect`` its pose. Reads no state that the tracking thread changes meanwhile.
        """
        from loopmodel.frontend.affine_klt import predicted_affine, refine_affine

        cfg = self.config
        if not ls.idx.size:
            return ls
        kf = ls.kf_set.keyframe
        cur_from_old = invert_pose(world_from_rect) @ self._world_from_kf.get(kf.id, kf.world_from_kf)
        cur_from_old = cur_from_old @ self.cam_from_rect
        match = refine_affine(
            kf.image,
            left,
            ls.kf_set.stereo_px[ls.idx][:, [0, 2]],
            ls.uv,
            predicted_affine(self.left_camera, ls.kf_set.points[ls.idx], cur_from_old),
            cfg.remeasure_half_window_px,
            min_ncc=cfg.remeasure_min_ncc,
            max_shift_px=cfg.remeasure_max_shift_px,
            cur_gradients=gradients,
        )
        return _LocalSet(ls.kf_set, ls.idx[match.ok], match.uv_px[match.ok])

    @staticmethod
    def _observe_local(mono_obs: F64, sets: list[_LocalSet]) -> tuple[F64, list[_LocalSet]]:
        """``mono_obs`` plus the local map's ``sets`` in the new keyframe (landmark_id, u, v rows), and the sets.

        ``sets``: the earlier keyframes' sets as tracked into the new keyframe (re-measured with
        ``local_map_remeasure``, :meth:`_remeasure_local`; the outgoing active set's tracks are in
        ``mono_obs`` already). Points that :meth:`_observe_older` found again (rows already in
        ``mono_obs``) rejoin their set at the measured position; the others are added at their
        tracked position. The returned sets replace the local map's when the keyframe is made.
        """
        rows = [mono_obs]
        local = []
        obs_ids = mono_obs[:, 0].astype(np.int64)
        for ls in sets:
            ids = ls.kf_set.keyframe.landmark_ids
            if ids.size == 0 or ids[-1] - ids[0] != ids.size - 1:  # ids not one run: no re-seeding
                rows.append(np.column_stack([ids[ls.idx].astype(float), ls.uv]))
                local.append(ls)
                continue
            uv = np.full((ids.size, 2), np.nan)
            uv[ls.idx] = ls.uv
            found = (obs_ids >= ids[0]) & (obs_ids < ids[0] + ids.size)
            j = obs_ids[found] - ids[0]
            tracked_only = np.setdiff1d(ls.idx, j)
            rows.append(np.column_stack([ids[tracked_only].astype(float), uv[tracked_only]]))
            uv[j] = mono_obs[found, 1:3]
            idx = np.flatnonzero(np.isfinite(uv[:, 0]))
            local.append(_LocalSet(ls.kf_set, idx, uv[idx]))
        return np.vstack(rows), local

    def _observe_older(
        self, old: _ActiveSet, left: NDArray[np.uint8], world_from_rect: F64,
        gradients: tuple[NDArray[np.float32], NDArray[np.float32]],
    ) -> F64:
        """Rows (landmark_id, u, v) of an older keyframe's points found in the new keyframe image ``left``.

        ``left`` has the rectified pose ``world_from_rect`` (``gradients``: its
        :meth:`_left_gradients`). Points are projected with the current poses, then matched against
        their own keyframe's patch (affine); links keyframes two or more intervals apart.
        """
        from loopmodel.frontend.affine_klt import predicted_affine, refine_affine

        cfg = self.config
        w, h = self.calibration.image_size
        # the old keyframe as the back end has corrected it since
        world_from_old = self._world_from_kf.get(old.keyframe.id, old.keyframe.world_from_kf) @ self.cam_from_rect
        cur_from_old = invert_pose(world_from_rect) @ world_from_old
        p = old.points @ cur_from_old[:3, :3].T + cur_from_old[:3, 3]
        front = p[:, 2] > 1e-3
        uv = np.full((p.shape[0], 2), -1.0)
        uv[front] = self.left_camera.project(p[front])
        margin = cfg.remeasure_half_window_px + cfg.remeasure_max_shift_px + 2
        sel = np.flatnonzero(
            front & (uv[:, 0] > margin) & (uv[:, 0] < w - 1 - margin)
            & (uv[:, 1] > margin) & (uv[:, 1] < h - 1 - margin)
        )
        if sel.size == 0:
            return np.zeros((0, 3))
        match = refine_affine(
            old.keyframe.image,
            left,
            old.stereo_px[sel][:, [0, 2]],
            uv[sel],
            predicted_affine(self.left_camera, old.points[sel], cur_from_old),
            cfg.remeasure_half_window_px,
            min_ncc=cfg.remeasure_min_ncc,
            max_shift_px=cfg.remeasure_max_shift_px,
            cur_gradients=gradients,
        )
        ok = match.ok
        ids = old.keyframe.landmark_ids[sel[ok]].astype(float)
        return np.column_stack([ids, match.uv_px[ok]])

    # ------------------------------------------------------------------ keyframes
    def _start_keyframe(
        self,
        frame: StereoFrame,
        left: NDArray[np.uint8],
        cur_pyr: Pyramid | None,
        world_from_rect: F64,
        t0: float,
        connected: bool,
        kf_from_cur: F64 | None = None,
    ) -> FrameResult | None:
        """Stereo-initialise a feature set at this frame.

        With ``kf_from_cur`` (tracked) the previous set's interval is closed first (its observations
        in the new keyframe, the local hybrid BA), on this thread while the new set's detection and
        stereo matching run beside it (``frontend.keyframe_stereo``). None when too few points.
        """
        cfg = self.config
        t_kf = time.perf_counter()
        self._finish_local_ba()
        prev = self._active if connected and kf_from_cur is not None else None
        # the right image is rectified with the matching unless the local BA needs it here too
        right = self.rectifier.right(frame.right) if prev is not None and cfg.ba_final_stereo else None
        # beside the interval's closing on this thread; without one (the first keyframe, a new
        # segment) the matching itself is split between the two threads
        threaded = cfg.keyframe_stereo == "thread"
        ahead, self._ahead = self._ahead, None
        stereo = Beside(
            threaded and prev is not None, self._stereo_set, left, frame, right,
            self._moving_uv if connected else None, 2 if threaded and prev is None else 1,
            ahead[1] if ahead is not None and ahead[0] is left else None,
        )
        closed = None
        if prev is not None and kf_from_cur is not None:
            closed = self._close_interval(prev, left, right, kf_from_cur)
        new = stereo.result()
        if new is None:
            logger.debug("frame %d: too few stereo points, no keyframe", frame.index)
            return None
        if prev is not None and closed is not None and kf_from_cur is not None:
            self._apply_closed(closed)
            world_from_rect = nearest_rigid(prev.world_from_kfrect @ closed.kf_from_new)
            closed.mono_obs = self._observe_resumed(closed, left, kf_from_cur)
        kf = self._new_keyframe(frame, left, new, world_from_rect, closed, kf_from_cur)
        self._activate(kf, new, world_from_rect, cur_pyr)
        job = closed.ba_job if closed is not None else None
        if job is not None:
            self._pending_ba = (Beside(True, job.run), job, kf.id)
        # handed with the next frame, after its BA (process); behind a keyframe still waiting, in order
        late = job is not None or bool(self._late)
        if late:
            self._late.append(kf)
        return FrameResult(
            frame.timestamp_ns,
            kf.world_from_kf,
            "OK",
            True,
            kf.id,
            np.eye(4),
            0,
            0,
            keyframe=None if late else kf,
            frame_index=frame.index,
            segment=self._segment,
            track_ms=(t_kf - t0) * 1e3,
            keyframe_ms=(time.perf_counter() - t_kf) * 1e3,
        )

    def _stereo_set(
        self, left: NDArray[np.uint8], frame: StereoFrame, right: NDArray[np.uint8] | None, avoid_px: F64 | None,
        threads: int, ahead: Beside[KeyframeMatches] | None = None,
    ) -> StereoSet | None:
        """:func:`~loopmodel.frontend.stereo.keyframe_stereo_set` of the rectified ``left`` and ``right``.

        ``right`` (rectified) is ``frame``'s right image rectified here when None, on a thread of its
        own while the corners are detected (``keyframe_stereo: thread``): a reader may decode it only now
        (:class:`~loopmodel.io.images.DeferredRightFrame`). ``ahead``: the corners and matches being made
        beside the frame's tracking (:meth:`_match_ahead`), taken instead. The disparity offset is the
        current one.
        """
        if ahead is not None:  # made beside this frame's tracking (_match_ahead)
            return keyframe_stereo_set(
                left, lambda: self.rectifier.right(frame.right), self.calibration.K_left, self.calibration.baseline_m,
                self.config, self._offset_px, avoid_px, matched=ahead.result(),
            )
        if right is None:
            # decoded already (FrontEnd.prepare, or a reader that decodes it): rectified when needed, here
            threaded = self.config.keyframe_stereo == "thread" and not getattr(frame, "right_decoded", True)
            rectified = Beside(threaded, lambda: self.rectifier.right(frame.right))
            return keyframe_stereo_set(
                left, rectified.result, self.calibration.K_left, self.calibration.baseline_m, self.config,
                self._offset_px, avoid_px, threads,
            )
        return keyframe_stereo_set(
            left, right, self.calibration.K_left, self.calibration.baseline_m, self.config, self._offset_px,
            avoid_px, threads,
        )

    def _close_interval(
        self, prev: _ActiveSet, left: NDArray[np.uint8], right: NDArray[np.uint8] | None, kf_from_cur: F64
    ) -> _ClosedInterval:
        """The outgoing set ``prev``'s interval closed at a new keyframe (``left``/``right``, at ``kf_from_cur``).

        Rectified images and pose. The set's tracks there (re-measured with ``keyframe_remeasure``),
        older keyframes' and the local map's points found in the new image, then the local hybrid BA.
        Changes nothing in the tracker (it runs beside the new set's matching): :meth:`_apply_closed`
        applies it.
        """
        cfg = self.config
        world_from_rect = prev.world_from_kfrect @ kf_from_cur
        # older keyframes' points and the local map's sets measured in the new image on one thread
        # beside this thread's work (numba nogil kernels): one thread, not one per set (fe7: eight
        # local-map sets on the KITTI clip, each a thread start and an interpreter-lock hand-over,
        # while the stereo thread already fills the second core)
        gradients = self._left_gradients(left)
        olders = self._older if cfg.keyframe_remeasure else []
        sets_in = self._local if cfg.local_map_remeasure else []
        measured = Beside(
            cfg.keyframe_stereo == "thread" and bool(olders or sets_in), self._measure_in_keyframe, olders, sets_in,
            left, world_from_rect, gradients,
        )
        idx, uv = self._track_idx, self._track_uv
        if cfg.keyframe_remeasure:
            idx, uv = self._remeasure_tracks(prev, left, kf_from_cur)
        mono_obs = np.column_stack([prev.keyframe.landmark_ids[idx].astype(float), uv])
        closed = _ClosedInterval(mono_obs, kf_from_cur, idx, uv, self._local)
        ba = cfg.local_ba and idx.size >= 6
        beside = ba and cfg.local_ba_beside
        ba = ba and not beside
        if ba and cfg.local_ba_keyframes == 0:  # the two-keyframe BA does not take the local map
            self._local_ba(closed, prev, left, right, kf_from_cur)
        older, remeasured = measured.result()
        if older:
            closed.mono_obs = np.vstack([mono_obs, *older])
        if self._local:
            sets = remeasured if remeasured else self._local
            closed.mono_obs, closed.local = self._observe_local(closed.mono_obs, sets)
        if ba and cfg.local_ba_keyframes > 0:
            self._local_ba(closed, prev, left, right, kf_from_cur)
        if beside:  # gathered here; run beside the next frame's tracking (_finish_local_ba)
            closed.ba_job = self._local_ba_job(closed, prev, left, right, kf_from_cur)
        if self._local_inliers:
            closed.ba_info["local_map_inliers"] = float(np.median(self._local_inliers))
        if self._pose_sigma_px:
            # robust scale (px per coordinate) of the pose residuals over the interval
            closed.ba_info["pose_residual_sigma_px"] = float(np.median(self._pose_sigma_px))
        return closed

    def _measure_in_keyframe(
        self, olders: list[_ActiveSet], sets: list[_LocalSet], left: NDArray[np.uint8], world_from_rect: F64,
        gradients: tuple[NDArray[np.float32], NDArray[np.float32]],
    ) -> tuple[list[F64], list[_LocalSet]]:
        """:meth:`_observe_older` of each of ``olders`` and :meth:`_remeasure_local` of each of ``sets``, in order."""
        older = [self._observe_older(old, left, world_from_rect, gradients) for old in olders]
        return older, [self._remeasure_local(ls, left, world_from_rect, gradients) for ls in sets]

    def _final_right(self, left: NDArray[np.uint8], right: NDArray[np.uint8], uv: F64, n_window: int) -> F64:
        """The tracked points ``uv`` (N, 2) found in the new keyframe's right image: (N + ``n_window``, 2) pixels.

        Both ends of the set then carry a stereo observation (``frontend.ba_final_stereo``); NaN rows
        where unmatched and for the wider BA's ``n_window`` points.
        """
        fm = match_stereo(left, right, uv, self.config)
        out = np.full((uv.shape[0] + n_window, 2), np.nan)
        frac = uv[fm.index] - fm.uv_left  # sub-pixel part of the corner
        out[fm.index, 0] = fm.u_right - self._offset_px + frac[:, 0]
        out[fm.index, 1] = fm.v_right + frac[:, 1]
        return out

    def _local_ba(
        self, closed: _ClosedInterval, prev: _ActiveSet, left: NDArray[np.uint8], right: NDArray[np.uint8] | None,
        kf_from_cur: F64,
    ) -> None:
        """The local hybrid BA over ``closed``'s interval: its pose, refined points, offset and ``ba_info``.

        The outgoing set's tracked points (stereo in ``prev``, seen in the new keyframe), with
        ``local_ba_keyframes`` the local map's sets too. Accepted only within ``max_jump_m`` /
        ``max_jump_deg`` of the robust pose ``kf_from_cur`` (guards against a bad set).
        """
        job = self._local_ba_job(closed, prev, left, right, kf_from_cur)
        job.take(job.run())

    def _local_ba_job(
        self, closed: _ClosedInterval, prev: _ActiveSet, left: NDArray[np.uint8], right: NDArray[np.uint8] | None,
        kf_from_cur: F64,
    ) -> _LocalBAJob:
        """:meth:`_local_ba`'s inputs, gathered on this thread (the BA itself may run on another)."""
        cfg = self.config
        idx, uv = closed.track_idx, closed.track_uv
        sp = prev.stereo_px[idx]
        wide = self._wide_ba_rows(prev, closed.local)
        final_right = None
        if cfg.ba_final_stereo and right is not None:
            final_right = self._final_right(left, right, uv, int(sum(wide.sizes)))
        right_sigma = None  # per-point disparity standard deviations (px), own set then the window's
        if cfg.disparity_sigma_source == "match" and prev.disparity_sigma_px.size:
            sig = [prev.disparity_sigma_px[idx]]
            for ls, n in zip(closed.local, wide.sizes, strict=False):
                ds = ls.kf_set.disparity_sigma_px
                sig.append(ds[ls.idx] if ds.size else np.full(n, cfg.disparity_sigma_px))
            right_sigma = np.concatenate(sig)
        args = (
            np.vstack([prev.points[idx], wide.points_kf]),
            np.vstack([sp[:, [0, 2]], wide.uv_left]),
            np.vstack([sp[:, [1, 2]], wide.uv_right]),
            np.vstack([uv, wide.uv_final]),
            invert_pose(kf_from_cur),
            self.left_camera,
            self.right_camera,
            self.calibration.right_from_left,
            cfg.ba_iterations,
            cfg.ba_huber_px,
        )
        kwargs = {
            "uv_final_right": final_right,
            "right_sigma_px": right_sigma,
            "estimate_disparity_offset": cfg.disparity_offset == "estimate",
            "offset_prior": (self._offset_mean_px - prev.disparity_offset_px, self._offset_info),
            "owner": np.concatenate([np.zeros(idx.size, np.int64), wide.owner]),
            "own_from_kf": np.concatenate([np.eye(4)[None], wide.own_from_kf]),
        }
        return _LocalBAJob(closed, prev, wide, kf_from_cur, cfg, self._offset_px, args, kwargs)

    def _finish_local_ba(self) -> None:
        """Take the last keyframe's BA run beside the tracking (``frontend.local_ba_beside``), once done.

        Its refined points and disparity offset join the tracker's state as inline; the keyframe's
        pose moves by the BA's correction of the tracked pose, and the keyframe waiting to be handed
        takes that pose, its ``kf_prev_from_kf`` and ``ba_info`` (what the inline BA gives it).
        """
        if self._pending_ba is None:
            return
        thread, job, kf_id = self._pending_ba
        self._pending_ba = None
        job.take(thread.result())
        closed = job.closed
        for kf_set, sel, points_m, inliers, kf_from_end in closed.refined:
            self._refine_points(kf_set, sel, points_m, inliers, kf_from_end)
        if closed.offset is not None:
            self._fuse_offset(*closed.offset)
        if kf_id in self._world_from_kf and closed.kf_from_new is not job.kf_from_cur:
            # tracked keyframe <- BA keyframe, on top of any correction made since
            tracked_from_ba = invert_pose(job.kf_from_cur) @ closed.kf_from_new
            world_from_rect = nearest_rigid(self._world_from_kf[kf_id] @ self.cam_from_rect @ tracked_from_ba)
            self.apply_correction({kf_id: world_from_rect @ self.rect_from_cam})
            if self._resumed is not None and "resumed_from_keyframe" in closed.ba_info:
                # the resumed old set moved to this keyframe at its tracked pose: to the BA's, as inline
                rs = self._resumed
                rs.kf_from_match = invert_pose(closed.kf_from_new) @ job.kf_from_cur @ rs.kf_from_match
        for i, kf in enumerate(self._late):
            if kf.id == kf_id:
                info = {**kf.ba_info, **closed.ba_info}
                if self.config.disparity_offset == "estimate":  # as _new_keyframe: applied, and the latest
                    info["disparity_offset_applied_px"] = kf.ba_info["disparity_offset_applied_px"]
                    info["disparity_offset_estimate_px"] = self._offset_px
                self._late[i] = replace(
                    kf, world_from_kf=self._world_from_kf[kf_id].copy(), ba_info=info,
                    kf_prev_from_kf=self.cam_from_rect @ closed.kf_from_new @ self.rect_from_cam,
                )

    def _apply_closed(self, closed: _ClosedInterval) -> None:
        """Take a closed interval: the outgoing set's final tracks, the local map's sets, the BA's points and offset."""
        self._track_idx, self._track_uv = closed.track_idx, closed.track_uv
        self._local = closed.local
        for kf_set, sel, points_m, inliers, kf_from_end in closed.refined:
            self._refine_points(kf_set, sel, points_m, inliers, kf_from_end)
        if closed.offset is not None:
            self._fuse_offset(*closed.offset)

    def _new_keyframe(
        self, frame: StereoFrame, left: NDArray[np.uint8], new: StereoSet, world_from_rect: F64,
        closed: _ClosedInterval | None, kf_from_cur: F64 | None,
    ) -> Keyframe:
        """The keyframe of the set ``new`` at ``world_from_rect`` (rectified), with fresh ids; registered.

        Connected to the active set when its interval was ``closed`` (tracked pose ``kf_from_cur``).
        """
        prev = self._active
        kf_id = self._next_kf_id
        self._next_kf_id += 1
        n = new.points.shape[0]
        ids = np.arange(self._next_landmark_id, self._next_landmark_id + n, dtype=np.int64)
        self._next_landmark_id += n
        world_from_kf = world_from_rect @ self.rect_from_cam
        self._world_from_kf[kf_id] = world_from_kf
        linked = closed is not None and kf_from_cur is not None
        info = dict(closed.ba_info) if closed is not None else {}
        if self.config.disparity_offset == "estimate":  # the offset in these matches, and the latest estimate
            # (the back end's final refinement re-expresses every keyframe with the latest)
            info = {**info, "disparity_offset_applied_px": new.offset_px,
                    "disparity_offset_estimate_px": self._offset_px}
        return Keyframe(
            id=kf_id,
            timestamp_ns=frame.timestamp_ns,
            world_from_kf=world_from_kf,
            landmark_ids=ids,
            points_in_kf=new.points @ self.cam_from_rect[:3, :3].T,
            stereo_px=new.stereo_px,
            right_rows_px=new.right_rows_px,
            mono_obs=closed.mono_obs if closed is not None else np.zeros((0, 3)),
            image=left,
            frame_index=frame.index,
            prev_keyframe_id=prev.keyframe.id if prev is not None else None,
            connected=linked,
            kf_prev_from_kf=(self.cam_from_rect @ closed.kf_from_new @ self.rect_from_cam) if closed else None,
            kf_prev_from_kf_tracked=(
                self.cam_from_rect @ kf_from_cur @ self.rect_from_cam if closed is not None and kf_from_cur is not None
                else None
            ),
            rect_from_cam=self.rect_from_cam.copy(),
            segment=self._segment,
            ba_info=info,
        )

    def _activate(self, kf: Keyframe, new: StereoSet, world_from_rect: F64, cur_pyr: Pyramid | None) -> None:
        """Make ``new`` (keyframe ``kf`` at ``world_from_rect``) the active set; the outgoing joins the local map."""
        cfg = self.config
        prev = self._active
        self._pose_sigma_px = []
        self._local_inliers = []
        self._inliers_prev, self._expect_keyframe = None, False
        if prev is not None and kf.connected and cfg.local_map_keyframes > 0:
            local = [_LocalSet(prev, self._track_idx.copy(), self._track_uv.copy()), *self._local]
            self._local = [ls for ls in local if ls.idx.size >= 3][: cfg.local_map_keyframes]
        else:
            self._local = []
        if not kf.connected:
            self._resumed = None  # a new segment: the old set's relation to it is unknown
        pts = new.points
        depth = float(np.median(pts[:, 2]))
        if self._mono is not None:
            if not kf.connected:
                self._mono.reset()
            self._mono.spawn(kf.id, new.unmatched_px, depth, new.stereo_px[:, [0, 2]])
            self._good_stamp = kf.timestamp_ns
        if prev is not None and kf.connected and cfg.remeasure_older_keyframes > 0:
            self._older = [prev, *self._older][: cfg.remeasure_older_keyframes]
        else:
            self._older = []
        fb = self.calibration.fx_px * self.calibration.baseline_m
        sigma_z = pts[:, 2] ** 2 / fb * cfg.disparity_sigma_px  # stereo depth standard deviation (m)
        if cfg.disparity_sigma_source == "match" and len(new.disparity_sigma_px) == len(pts):
            sigma_z = pts[:, 2] ** 2 / fb * new.disparity_sigma_px
        self._active = _ActiveSet(
            kf, world_from_rect, pts, new.stereo_px, depth, new.far_rays, new.far_inv_depth, new.far_px,
            new.disparity_sigma_px, disparity_offset_px=new.offset_px, sigma_z_m=sigma_z,
        )
        self._moving_uv = np.zeros((0, 2))
        self._track_idx = np.arange(pts.shape[0], dtype=np.int64)
        self._track_uv = new.stereo_px[:, [0, 2]].copy()
        self._far_idx = np.arange(new.far_px.shape[0], dtype=np.int64)
        self._far_uv = new.far_px.copy()
        self._prev_pyr = (
            cur_pyr if cur_pyr is not None else build_pyramid(kf.image, cfg.klt_window_px, cfg.klt_levels)
        )
        self._kf_pyr = self._prev_pyr  # the keyframe's own (resume_features of a keyframe handed late)
        self._kf_from_prev = np.eye(4)
        self._frames_since_ok = 0

    def _lost(
        self,
        frame: StereoFrame,
        world_from_rect: F64,
        reason: str,
        t0: float,
        tracked: int = 0,
        inliers: int = 0,
    ) -> FrameResult:
        kf_id = self._active.keyframe.id if self._active is not None else -1
        kf_from_cam = np.eye(4)
        if self._active is not None:
            kf_from_cam = (
                self.cam_from_rect
                @ invert_pose(self._active.world_from_kfrect)
                @ world_from_rect
                @ self.rect_from_cam
            )
        return FrameResult(
            frame.timestamp_ns,
            world_from_rect @ self.rect_from_cam,
            "LOST",
            False,
            kf_id,
            kf_from_cam,
            tracked,
            inliers,
            frame_index=frame.index,
            segment=self._segment,
            reason=reason,
            track_ms=(time.perf_counter() - t0) * 1e3,
        )
