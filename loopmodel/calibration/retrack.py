"""The frames between keyframes solved again with the refined calibration (issue 31, ``calibration.refine: final``).

The front end solved every frame's pose from pixels of images rectified with the *recorded*
calibration, against points triangulated with it. After the final self-calibration
(:mod:`loopmodel.calibration.selfcal`) the keyframes and landmarks are refined, but a frame between
two keyframes still carries the recorded calibration's error in its pose (the bridge of
:func:`loopmodel.mapping.anchored.bridge_interval` moves it with its interval's ends, which cannot
undo an error that is not a scale). :func:`retrack_frames` takes the points each frame's pose kept
(:class:`~loopmodel.frontend.keyframe.FrameObservations`), maps their pixels back to the raw image
through the recorded model (exactly the pixel the tracker measured) and out again through the
refined left camera (:func:`refined_left_px`), and solves the pose once more with the project's
robust pose solver (:func:`loopmodel.pose.refine_pose`) against the refined landmarks; a landmark the
refinement did not hold takes its keyframe's stereo match triangulated with the refined rig
(:func:`refined_stereo_points`: every keyframe's in one batch, shared with the session map's refined
points). The keyframes' own tracked poses are solved again the same way,
and each interval's re-solved frames are bridged onto the refined keyframes (the tracker's KLT
drift over the interval stays in the pixels). A frame with too few points, or whose solve fails or
jumps, keeps its earlier pose.

Frames: camera = the raw (unrectified) left camera, ``world_from_cam``; metres, pixels.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.calibration.refine_rig import distortion5, project_with_jacobians, raw_from_rectified_px
from loopmodel.calibration.selfcal import rays_from_raw_px, rectifying_rotations
from loopmodel.errors import EstimationError
from loopmodel.frontend.keyframe import FrameObservations, FrameResult
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose, so3_log
from loopmodel.mapping.anchored import bridge_interval
from loopmodel.pose import CameraRig, PointTerm, PoseOptions, refine_pose
from loopmodel.types import Keyframe, StereoCalibration, Trajectory

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def refined_left_px(uv_rect_px: F64, recorded: StereoCalibration, refined: StereoCalibration) -> F64:
    """Pixels of the recorded rectified left image as the refined left camera sees them (N x 2).

    Each pixel goes back to its raw (distorted) pixel through the recorded model (rectifying
    rotation, rectified and raw intrinsics, distortion), then out along the refined camera's ray
    (its intrinsics and distortion) and onto the refined ``K_left`` without distortion: a pinhole
    pixel of the raw left camera's frame.
    """
    R1, _R2, K1, _K2 = rectifying_rotations(recorded)
    raw = raw_from_rectified_px(np.asarray(uv_rect_px, float).reshape(-1, 2), K1, R1, recorded.K_left,
                                recorded.dist_left)
    ray = rays_from_raw_px(raw, refined.K_left, refined.dist_left)
    K = refined.K_left
    return np.column_stack([K[0, 0] * ray[:, 0] + K[0, 2], K[1, 1] * ray[:, 1] + K[1, 2]])


class RefinedPixelGrid:
    """:func:`refined_left_px` tabulated every ``step_px`` over the image, read bilinearly.

    The map from the recorded rectified image to the refined pinhole camera is smooth (the two
    calibrations' distortions nearly cancel): bilinear reading on an 8-px grid agrees with the exact
    conversion to 6.5e-4 px (a 4-px grid 1.6e-4 px, 16 px 2.6e-3 px; 5,000 pixels of the selfcal scene's
    640 x 480 rig, tests/test_retrack.py), far below the tracking noise, at 1 ms instead of 46 ms for
    5,000 pixels (the exact one's iterative undistortion: 12 ms of a KITTI frame's 60 ms re-solve at
    load 20).
    """

    def __init__(self, recorded: StereoCalibration, refined: StereoCalibration, step_px: float = 8.0) -> None:
        w, h = recorded.image_size
        self.step_px = float(step_px)
        self.u0, self.v0 = -2.0 * step_px, -2.0 * step_px  # a margin: points just outside the image
        self.nu = int(np.ceil((w + 4.0 * step_px) / step_px)) + 1
        self.nv = int(np.ceil((h + 4.0 * step_px) / step_px)) + 1
        u = self.u0 + step_px * np.arange(self.nu)
        v = self.v0 + step_px * np.arange(self.nv)
        uu, vv = np.meshgrid(u, v)
        grid = refined_left_px(np.column_stack([uu.ravel(), vv.ravel()]), recorded, refined)
        self.table = grid.reshape(self.nv, self.nu, 2)

    def __call__(self, uv_rect_px: F64) -> F64:
        """The refined pixels of recorded rectified pixels ``uv_rect_px`` (N x 2)."""
        uv = np.asarray(uv_rect_px, float).reshape(-1, 2)
        x = (uv[:, 0] - self.u0) / self.step_px
        y = (uv[:, 1] - self.v0) / self.step_px
        i = np.clip(np.floor(x).astype(np.int64), 0, self.nu - 2)
        j = np.clip(np.floor(y).astype(np.int64), 0, self.nv - 2)
        fx, fy = (x - i)[:, None], (y - j)[:, None]
        t = self.table
        top = t[j, i] * (1 - fx) + t[j, i + 1] * fx
        bottom = t[j + 1, i] * (1 - fx) + t[j + 1, i + 1] * fx
        return np.asarray(top * (1 - fy) + bottom * fy, dtype=np.float64)


def refined_keyframe_points(
    keyframe: Keyframe, rows: I64, recorded: StereoCalibration, refined: StereoCalibration, iterations: int = 4
) -> F64:
    """Keyframe stereo points ``rows`` (indices into its ``stereo_px``) triangulated with the refined rig (N x 3).

    In the keyframe's raw left camera (metres); :func:`refined_stereo_px_points` of those rows.
    """
    st = np.asarray(keyframe.stereo_px, float).reshape(-1, 3)[np.asarray(rows, np.int64)]
    return refined_stereo_px_points(st, recorded, refined, iterations)


def refined_stereo_px_points(
    stereo_px: F64, recorded: StereoCalibration, refined: StereoCalibration, iterations: int = 4
) -> F64:
    """Stereo matches triangulated with the refined rig (N x 3, the raw left camera's frame, metres).

    ``stereo_px`` (N x 3): u_left, u_right, v of the recorded rectified pair. The left pixel goes
    back to its raw pixel through the recorded model and out along the refined left camera's ray;
    the depth along it is where the point's refined right-camera projection,
    rectified with the recorded model, has the measured right column (the front end measures the
    right match's column only, as the refinement models it:
    :class:`~loopmodel.calibration.refine_rig.RigObservations`): secant steps from the linear
    two-ray triangulation (OpenCV) at the left row. NaN rows where it does not converge.
    """
    R1, R2, K1, K2 = rectifying_rotations(recorded)
    st = np.asarray(stereo_px, float).reshape(-1, 3)
    if st.shape[0] == 0:
        return np.zeros((0, 3))
    raw_l = raw_from_rectified_px(st[:, [0, 2]], K1, R1, recorded.K_left, recorded.dist_left)
    raw_r = raw_from_rectified_px(st[:, [1, 2]], K2, R2, recorded.K_right, recorded.dist_right)
    ray_l = rays_from_raw_px(raw_l, refined.K_left, refined.dist_left)
    ray_r = rays_from_raw_px(raw_r, refined.K_right, refined.dist_right)
    T = np.asarray(refined.right_from_left, float)
    X = cv2.triangulatePoints(np.hstack([np.eye(3), np.zeros((3, 1))]), T[:3, :], ray_l[:, :2].T.copy(),
                              ray_r[:, :2].T.copy())
    z0 = np.asarray(X[2] / X[3], float)
    intr = np.array([refined.K_right[0, 0], refined.K_right[1, 1], refined.K_right[0, 2], refined.K_right[1, 2]])
    dist = distortion5(refined.dist_right)

    def u_error(z: F64) -> F64:  # rectified (recorded) column of the right projection minus the measured one
        p_r = (z[:, None] * ray_l) @ T[:3, :3].T + T[:3, 3]
        raw, _, _ = project_with_jacobians(p_r, intr, dist)
        q = rays_from_raw_px(raw, recorded.K_right, recorded.dist_right) @ R2.T
        return K2[0, 0] * q[:, 0] / q[:, 2] + K2[0, 2] - st[:, 1]

    z1 = z0 * (1.0 + 1e-3)
    e0, e1 = u_error(z0), u_error(z1)
    for _ in range(iterations):
        slope = (e1 - e0) / np.where(z1 != z0, z1 - z0, 1.0)
        z2 = z1 - e1 / np.where(np.abs(slope) > 1e-12, slope, np.nan)
        z0, e0, z1 = z1, e1, z2
        e1 = u_error(z1)
    z1 = np.where(np.abs(e1) < 1e-6, z1, np.nan)
    return np.asarray(z1[:, None] * ray_l, dtype=np.float64)


def refined_stereo_points(
    keyframes: Iterable[Keyframe], held_ids: I64, recorded: StereoCalibration, refined: StereoCalibration
) -> dict[int, F64]:
    """Every keyframe's stereo points triangulated with the refined rig in one batch: keyframe id -> (M x 3).

    The rows of each keyframe's ``stereo_px``, in its raw left camera (metres). NaN rows: the
    landmarks in ``held_ids`` (the calibrating bundle adjustment holds them; their refined world point
    is the one) and the matches whose triangulation does not converge. One triangulation for the
    re-solve of the frames (:func:`retrack_frames`) and the session map's refined points
    (:func:`loopmodel.sessions.refined_map_points`; issue 32: they triangulated the same keyframe
    points twice).
    """
    held = np.unique(np.asarray(held_ids, np.int64).ravel())
    kfs = list(keyframes)
    need = [~np.isin(np.asarray(k.landmark_ids, np.int64).ravel(), held) for k in kfs]
    rows = [np.asarray(k.stereo_px, float).reshape(-1, 3)[n] for k, n in zip(kfs, need, strict=True)]
    p = refined_stereo_px_points(np.concatenate(rows) if rows else np.zeros((0, 3)), recorded, refined)
    out: dict[int, F64] = {}
    at = 0
    for k, n in zip(kfs, need, strict=True):
        pts = np.full((n.size, 3), np.nan)
        pts[n] = p[at : at + int(n.sum())]
        at += int(n.sum())
        pts[~(pts[:, 2] > 0)] = np.nan
        out[int(k.id)] = pts
    return out


@dataclass
class RetrackedFrames:
    """The re-solved frames: their ``timestamps_ns`` and ``world_from_cam`` (N x 4 x 4, metres), and counts.

    ``stats``: ``frames`` considered, ``resolved``, ``few_points`` / ``failed`` / ``jumped`` (kept
    their earlier pose), ``unbridged`` (kept their earlier pose: no end of their interval was
    re-solved; with ``bridge`` such a frame is not solved), ``tail`` (re-solved alone after their
    segment's last keyframe), ``points_median`` per re-solved frame, ``move_mm_median`` /
    ``move_mm_max`` from the earlier pose, ``rms_px_median`` of the re-solved poses' inliers.
    """

    timestamps_ns: I64
    world_from_cam: F64
    stats: dict[str, float] = field(default_factory=dict)

    def over(self, trajectory: Trajectory) -> Trajectory:
        """``trajectory`` with the re-solved frames' poses in place of its own (matched by timestamp)."""
        out = trajectory.world_from_cam.copy()
        index = {int(t): i for i, t in enumerate(trajectory.timestamps_ns.tolist())}
        for t, T in zip(self.timestamps_ns.tolist(), self.world_from_cam, strict=True):
            i = index.get(int(t))
            if i is not None:
                out[i] = T
        return Trajectory(trajectory.timestamps_ns.copy(), out)


class _Landmarks:
    """World points (metres) by landmark id: refined, else their keyframe's stereo point with the refined rig.

    Held as arrays over the sorted ids (a frame's few hundred points are looked up at once); a
    landmark the refinement did not hold takes its point from the last keyframe that measured it
    (``keyframe_points``: :func:`refined_stereo_points`) placed with that keyframe's refined pose.
    """

    def __init__(
        self,
        keyframes: Mapping[int, Keyframe],
        world_from_kf: Mapping[int, F64],
        landmark_ids: I64,
        landmarks_in_world: F64,
        keyframe_points: Mapping[int, F64],
        recorded: StereoCalibration,
        refined: StereoCalibration,
    ) -> None:
        ref_ids = np.asarray(landmark_ids, np.int64).ravel()
        kids = [int(k) for k in keyframes if int(k) in world_from_kf]
        own = [np.asarray(keyframes[k].landmark_ids, np.int64).ravel() for k in kids]
        self.ids = np.unique(np.concatenate([ref_ids, *own]))
        n = self.ids.size
        self.points = np.full((n, 3), np.nan)
        refined_at = np.searchsorted(self.ids, ref_ids)
        self.refined_count = int(np.unique(ref_ids).size)
        self.owner = np.full(n, -1, np.int64)  # index into ``kids`` of the keyframe that measured it (the last)
        self.row = np.zeros(n, np.int64)
        for j, li in enumerate(own):
            at = np.searchsorted(self.ids, li)
            self.owner[at] = j
            self.row[at] = np.arange(li.size)
        for j, kid in enumerate(kids):  # the owned points, placed with their keyframe's refined pose
            sel = np.flatnonzero(self.owner == j)
            p = keyframe_points.get(kid)
            if sel.size == 0 or p is None or p.shape[0] != own[j].size:
                continue
            T = np.asarray(world_from_kf[kid], float)
            self.points[sel] = p[self.row[sel]] @ T[:3, :3].T + T[:3, 3]
        self.points[refined_at] = np.asarray(landmarks_in_world, float).reshape(-1, 3)
        is_refined = np.zeros(n, bool)
        is_refined[refined_at] = True
        self.triangulated = int((np.all(np.isfinite(self.points), axis=1) & ~is_refined).sum())
        self.fb_px_m = float(refined.K_left[0, 0]) * float(refined.baseline_m)
        # each keyframe's camera centre and optical axis (world); a last row of NaN for "no keyframe"
        self._axes = np.array(
            [np.concatenate([np.asarray(world_from_kf[k], float)[:3, 3], np.asarray(world_from_kf[k], float)[:3, 2]])
             for k in kids] + [np.full(6, np.nan)]
        ).reshape(-1, 6)
        self.pixels = RefinedPixelGrid(recorded, refined)  # a frame's pixels as the refined camera sees them

    def _index(self, ids: I64) -> tuple[I64, NDArray[np.bool_]]:
        at = np.minimum(np.searchsorted(self.ids, ids), max(self.ids.size - 1, 0))
        return at, (self.ids.size > 0) & (self.ids[at] == ids)

    def depth_rays(self, ids: I64, p_w: F64) -> tuple[F64, F64]:
        """Each point's depth in its stereo keyframe (m), and the ray per metre of that depth (world, N x 3).

        NaN where that keyframe is not known.
        """
        at, found = self._index(np.asarray(ids, np.int64))
        axes = self._axes[np.where(found, self.owner[at], -1)]
        d = p_w - axes[:, :3]
        z = np.einsum("ni,ni->n", d, axes[:, 3:])
        with np.errstate(invalid="ignore", divide="ignore"):
            ray = np.where((z > 0)[:, None], d / z[:, None], np.nan)
        return z, ray

    def get(self, ids: I64) -> tuple[F64, NDArray[np.bool_]]:
        """World points of ``ids`` (N x 3) and which are known (refined or triangulated)."""
        at, found = self._index(np.asarray(ids, np.int64))
        out = np.where(found[:, None], self.points[at], np.nan)
        return out, np.all(np.isfinite(out), axis=1)


def _depth_weights(
    lms: _Landmarks, ids: I64, p_w: F64, world_from_cam: F64, camera: CentralCamera, pixel_sigma_px: float,
    disparity_sigma_px: float,
) -> F64:
    """Pixel variance over pixel-plus-depth variance of each point's projection (first order; 1 where unknown)."""
    z, ray = lms.depth_rays(ids, p_w)
    R, t = world_from_cam[:3, :3], world_from_cam[:3, 3]
    p_cam = (p_w - t) @ R
    g = np.einsum("nij,nj->ni", camera.project_jacobian(p_cam), ray @ R)  # px per metre of depth
    sigma_z = z**2 / lms.fb_px_m * disparity_sigma_px
    var = pixel_sigma_px**2
    w = var / (var + np.einsum("ni,ni->n", g, g) * sigma_z**2)
    return np.where(np.isfinite(w), w, 1.0)


def _solve_frame(
    obs: FrameObservations, world_from_cam0: F64, lms: _Landmarks, rig: CameraRig, recorded: StereoCalibration,
    refined: StereoCalibration, options: PoseOptions, disparity_sigma_px: float | None, min_points: int,
    max_move_over_depth: float, max_turn_deg: float,
) -> tuple[str, F64, float, float, int, float]:
    """One frame re-solved from ``world_from_cam0``: (outcome, pose, move m, turn deg, inliers, rms px).

    Outcome ``ok``, ``few_points``, ``failed`` or ``jumped`` (then the pose is ``world_from_cam0``).
    """
    ids = np.asarray(obs.landmark_ids, np.int64)
    p_w, known = lms.get(ids)
    if int(known.sum()) < min_points:
        return "few_points", world_from_cam0, 0.0, 0.0, 0, 0.0
    uv = lms.pixels(np.asarray(obs.uv_px, float)[known])
    weight = None
    if disparity_sigma_px is not None:
        weight = _depth_weights(lms, ids[known], p_w[known], world_from_cam0, rig.cameras[0], options.min_scale,
                                disparity_sigma_px)
    try:
        res = refine_pose(PointTerm(rig, p_w[known], uv, prior_weight=weight), invert_pose(world_from_cam0), options)
    except (EstimationError, np.linalg.LinAlgError):
        return "failed", world_from_cam0, 0.0, 0.0, 0, 0.0
    inl = res.inliers[0]
    world_from_cam = invert_pose(res.rig_from_ref)
    step = invert_pose(world_from_cam0) @ world_from_cam
    move_m = float(np.linalg.norm(step[:3, 3]))
    turn_deg = float(np.degrees(np.linalg.norm(so3_log(step[:3, :3]))))
    depth_m = float(np.median((p_w[known] - world_from_cam0[:3, 3]) @ world_from_cam0[:3, 2]))
    if int(inl.sum()) < min_points:
        return "few_points", world_from_cam0, 0.0, 0.0, 0, 0.0
    if move_m > max_move_over_depth * depth_m or turn_deg > max_turn_deg:
        return "jumped", world_from_cam0, move_m, turn_deg, 0, 0.0
    rms = float(np.sqrt(np.mean(res.residual_norms[0][inl] ** 2)))
    return "ok", world_from_cam, move_m, turn_deg, int(inl.sum()), rms


_Solved = tuple[str, F64, float, float, int, float]


def solve_frames(starts: list[tuple[FrameObservations, F64]], args: tuple[Any, ...]) -> list[_Solved]:
    """:func:`_solve_frame` of each (observations, start pose) with the shared ``args``."""
    return [_solve_frame(obs, T0, *args) for obs, T0 in starts]


def helper_solve_frames(
    starts: list[tuple[FrameObservations, F64]], args: tuple[Any, ...]
) -> tuple[list[_Solved], float]:
    """:func:`solve_frames` in a helper process, with that process's CPU seconds in it."""
    c0 = time.process_time()
    out = solve_frames(starts, args)
    return out, time.process_time() - c0


def warm_up() -> None:
    """This module and the pose solve's compiled kernels loaded (a helper process, before its share is sent).

    One pose solve of 20 synthetic points (numba loads each kernel at its first call).
    """
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    rig = CameraRig.single(CentralCamera.from_K(K))
    g = np.linspace(-0.2, 0.2, 5)
    p = np.column_stack([np.repeat(g, 4), np.tile(g[:4], 5), np.full(20, 1.0)])
    uv = p[:, :2] / p[:, 2:] * 500.0 + np.array([320.0, 240.0])
    refine_pose(PointTerm(rig, p, uv), np.eye(4), PoseOptions())


def _solve_shared(
    starts: list[tuple[FrameObservations, F64]], args: tuple[Any, ...], helper: Any, helper_share: float,
    chunk: int = 16,
) -> tuple[list[_Solved], int, float]:
    """:func:`solve_frames` of ``starts``, the last ``helper_share`` of them offered to ``helper`` (a process pool).

    Issue 32: the frames' solves are independent and hold the interpreter; a helper process (the
    run's idle stripe-extraction worker) takes its share in chunks of ``chunk`` frames while this
    process solves the rest; the chunks the pool has not begun (nor queued for its process: at most
    two are) when this process is done are taken back, so a helper slowed by the machine's load costs
    little wait. The same function on the same values: the poses are those of one process. A chunk
    whose helper fails is solved here. Returns the solves in the order of ``starts``, how many the
    helper made and its CPU seconds in them.
    """
    n_here = len(starts) - (int(round(helper_share * len(starts))) if helper is not None else 0)
    bounds = [(a, min(a + chunk, len(starts))) for a in range(n_here, len(starts), chunk)]
    futures: list[Any] = []
    for a, b in bounds:
        try:
            futures.append(helper.submit(helper_solve_frames, starts[a:b], args))
        except RuntimeError:  # a broken or shut-down pool
            futures.append(None)
    out = solve_frames(starts[:n_here], args)
    helped, helper_cpu_s = 0, 0.0
    parts: list[list[_Solved] | None] = [None] * len(bounds)
    for k in reversed(range(len(bounds))):  # not begun: solved here
        if futures[k] is None or futures[k].cancel():
            parts[k] = solve_frames(starts[bounds[k][0] : bounds[k][1]], args)
    for k, (a, b) in enumerate(bounds):
        part = parts[k]
        if part is None:
            try:
                part, cpu_s = futures[k].result()
                helped += b - a
                helper_cpu_s += cpu_s
            except Exception as exc:  # noqa: BLE001 - the helper process died: its chunk solved here
                logger.warning("re-tracking helper failed (%s): its frames solved here", exc or type(exc).__name__)
                part = solve_frames(starts[a:b], args)
        out += part
    return out, helped, helper_cpu_s


def retrack_frames(
    frames: Sequence[FrameResult],
    start: Trajectory,
    keyframes: Mapping[int, Keyframe],
    world_from_kf: Mapping[int, F64],
    landmark_ids: I64,
    landmarks_in_world: F64,
    recorded: StereoCalibration,
    refined: StereoCalibration,
    options: PoseOptions,
    min_points: int = 20,
    max_move_over_depth: float = 0.02,
    max_turn_deg: float = 0.5,
    disparity_sigma_px: float | None = 0.3,
    bridge: bool = True,
    tail: bool = True,
    keyframe_points: Mapping[int, F64] | None = None,
    helper: Any = None,
    helper_share: float = 0.5,
) -> RetrackedFrames:
    """Each tracked frame with kept points (``FrameResult.observed``) solved again; see the module docstring.

    ``start``: every frame's pose before (``world_from_cam``, e.g. the bridged final trajectory):
    the solve's start, and what a frame keeps when it has fewer than ``min_points`` known points,
    the solve fails, or the solved pose moves more than ``max_move_over_depth`` times the points'
    median depth or ``max_turn_deg`` from it (a tracking failure, not a calibration: a calibration's
    depth error is a few tenths of a percent; measured moves: the selfcal orbits' frames at most
    1.4 mm at 0.67 m (0.2 %) and 0.36 deg; the KITTI clip's 11 mm at about 10 m).
    ``keyframes`` as the front end measured them, ``world_from_kf`` and the landmarks refined,
    ``recorded`` / ``refined`` the raw calibrations before and after. With ``disparity_sigma_px``
    each point is weighted as the front end weighs it (``frontend.depth_weighting``): pixel variance
    (``options.min_scale`` squared) over pixel-plus-depth variance, its depth uncertain by stereo
    (``z^2 / (f b)`` times the disparity sigma) along its ray from the keyframe that measured it.

    ``bridge``: the re-solved frames still carry the tracker's drift (KLT slides over an interval;
    the local BA's keyframe does not): a keyframe B whose tracked pose's points were kept is solved
    again the same way in its previous keyframe A, and :func:`~loopmodel.mapping.anchored.bridge_interval`
    moves the re-solved frames between A and B as that end's disagreement with the refined A -> B;
    a frame whose end's solve failed keeps its earlier pose: re-solved alone it carries the drift
    unbridged (the KITTI clip's last frame: ATE 0.0549 -> 0.0553 m re-solved alone, 0.0549 m kept; a
    rendered perfect rig's frames 0.27 -> 0.42 mm alone). ``tail``: the frames after a segment's last
    keyframe (no interval end exists) are re-solved alone: kept, they carry the recorded calibration's
    depth error in their whole motion from that keyframe (a rendered rig with the right camera's cx
    0.6 px off, tests/test_retrack.py: the four frames after the last keyframe 1.4-3.9 mm and up to
    0.04 deg off kept, 0.26-0.59 mm and 0.005 deg re-solved alone; their motion's translation rescaled
    by the keyframe's refined-over-recorded depth ratio instead: 0.97-3.6 mm, the rotation error
    stays). On a well-calibrated rig: the KITTI clip (``configs/kitti.yaml``, ``refine: final``, the
    keyframes at one disparity offset, drift8) ATE 0.02428 -> 0.02466 m with its last two frames
    re-solved alone (the front end's monocular points, which the re-solve does not use, and the KLT
    drift unbridged), drift after the ground truth's constant-rate segment 0.560 -> 0.558 %.
    ``keyframe_points``: :func:`refined_stereo_points` of ``keyframes`` when the caller has them
    (computed here otherwise). ``helper``: a one-process pool (:func:`warm_up` submitted to it
    beforehand) that solves ``helper_share`` of the frames between keyframes meanwhile; the same poses.
    """
    rig = CameraRig.single(CentralCamera.from_K(refined.K_left))
    index = {int(t): i for i, t in enumerate(start.timestamps_ns.tolist())}
    if keyframe_points is None:
        keyframe_points = refined_stereo_points(
            [kf for k, kf in keyframes.items() if int(k) in world_from_kf], landmark_ids, recorded, refined
        )
    lms = _Landmarks(keyframes, world_from_kf, landmark_ids, landmarks_in_world, keyframe_points, recorded, refined)
    solved: dict[int, tuple[int, F64]] = {}  # frame time -> (its keyframe, world_from_cam re-solved)
    ends: dict[int, F64] = {}  # keyframe B -> world_from_B re-solved from its tracked pose's points
    counts = {"frames": 0, "ok": 0, "few_points": 0, "failed": 0, "jumped": 0}
    points, moves, turns, rms = [], [], [], []
    args = (lms, rig, recorded, refined, options, disparity_sigma_px, min_points, max_move_over_depth, max_turn_deg)
    tracked = [fr for fr in frames if fr.observed is not None and fr.ok]
    # the interval ends first: with ``bridge`` a frame whose interval has no end keeps its pose, so
    # it is not solved at all (the KITTI clip: 38 frames solved and then dropped, 0.4 s at load 18)
    for fr in tracked if bridge else []:
        kid = int(fr.keyframe_id)
        kf = keyframes.get(kid)
        if (not fr.is_keyframe or kf is None or kf.prev_keyframe_id is None or not kf.connected
                or int(kf.prev_keyframe_id) not in world_from_kf or kid not in world_from_kf):
            continue
        outcome, T, *_ = _solve_frame(fr.observed, np.asarray(world_from_kf[kid], float), *args)  # type: ignore[arg-type]
        if outcome == "ok":
            ends[kid] = T
    starts = {int(keyframes[b].prev_keyframe_id) for b in ends}  # type: ignore[arg-type]
    # a keyframe no later keyframe follows (its segment's last): its frames have no interval end at all
    followed = {int(k.prev_keyframe_id) for k in keyframes.values() if k.prev_keyframe_id is not None and k.connected}
    tails = {int(k) for k in world_from_kf if int(k) not in followed} if tail else set()
    skipped = 0
    todo: list[FrameResult] = []
    from_pose: list[tuple[FrameObservations, F64]] = []
    for fr in tracked:
        kid = int(fr.keyframe_id)
        i = index.get(int(fr.timestamp_ns))
        if fr.is_keyframe or i is None or kid not in world_from_kf:
            continue
        counts["frames"] += 1
        if bridge and kid not in starts and kid not in tails:
            skipped += 1
            continue
        todo.append(fr)
        from_pose.append((fr.observed, start.world_from_cam[i]))  # type: ignore[arg-type]
    solves, helped, helper_cpu_s = _solve_shared(from_pose, args, helper, helper_share)
    for fr, (outcome, T, move_m, turn_deg, n_inl, r) in zip(todo, solves, strict=True):
        kid = int(fr.keyframe_id)
        counts[outcome] += 1
        if outcome != "ok":
            continue
        solved[int(fr.timestamp_ns)] = (kid, T)
        points.append(n_inl)
        moves.append(move_m)
        turns.append(turn_deg)
        rms.append(r)
    bridged = 0
    done: set[int] = set()
    for b, world_from_b in ends.items():
        kb = keyframes[b]
        a = int(kb.prev_keyframe_id)  # type: ignore[arg-type]
        t_a, t_b = int(keyframes[a].timestamp_ns), int(kb.timestamp_ns)
        sel = sorted(t for t, (k, _T) in solved.items() if k == a and t_a < t < t_b)
        if not sel:
            continue
        a_from_world = invert_pose(np.asarray(world_from_kf[a], float))
        rel = np.array([a_from_world @ solved[t][1] for t in sel])
        frac = (np.array(sel, float) - t_a) / (t_b - t_a)
        out = bridge_interval(rel, frac, a_from_world @ world_from_b, a_from_world @ world_from_kf[b])
        for t, T in zip(sel, out, strict=True):
            solved[t] = (a, np.asarray(world_from_kf[a], float) @ T)
        done.update(sel)
        bridged += 1
    if bridge:  # a frame whose interval end was not re-solved keeps its pose; after the last keyframe, alone
        alone = {t for t, (k, _T) in solved.items() if t not in done and k in tails}
        counts["unbridged"] = len(solved) - len(done) - len(alone) + skipped
        counts["tail"] = len(alone)
        solved = {t: v for t, v in solved.items() if t in done or t in alone}
    times = sorted(solved)
    stats = {k: float(v) for k, v in counts.items() if k != "ok"}
    stats["resolved"] = float(len(times))
    stats["bridged_intervals"] = float(bridged)
    stats["points_median"] = float(np.median(points)) if points else 0.0
    stats["move_mm_median"] = 1e3 * float(np.median(moves)) if moves else 0.0
    stats["move_mm_max"] = 1e3 * float(np.max(moves)) if moves else 0.0
    stats["turn_deg_max"] = float(np.max(turns)) if turns else 0.0
    stats["rms_px_median"] = float(np.median(rms)) if rms else 0.0
    stats["landmarks_refined"] = float(lms.refined_count)
    stats["landmarks_triangulated"] = float(lms.triangulated)
    stats["helper_frames"] = float(helped)  # re-solved in the helper process
    stats["helper_cpu_s"] = helper_cpu_s  # its CPU in them (not in the run's finish_cpu_s)
    logger.info(
        "re-tracking: %d of %d frames re-solved (%d few points, %d failed, %d jumped), %d intervals bridged, "
        "median move %.2f mm", len(times), counts["frames"], counts["few_points"], counts["failed"],
        counts["jumped"], bridged, stats["move_mm_median"],
    )
    return RetrackedFrames(
        np.array(times, np.int64), np.array([solved[t][1] for t in times]).reshape(-1, 4, 4), stats
    )
