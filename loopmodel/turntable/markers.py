"""Table pose per frame from the ArUco markers on the turntable.

OpenCV's aruco module only detects the markers (corners refined to sub-pixel); every pose
comes from the project's robust pose solver (:func:`loopmodel.calibration.pose.target_pose`).

Frames: camera (x right, y down, z forward); marker m (x right, y up on the print, z out
of the table); table frame: origin on the rotation axis in the table-top plane, z along the
axis (out of the table), x/y turning with the table. The marker layout ``table_from_marker``
is self-calibrated from the scan: the markers' poses relative to a reference marker
(averaged over frames that see both), then the rotation axis as the centre of the circle the
reference marker describes. ``cam_from_table[k]`` then comes from all visible markers'
corners at once.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.calibration.pose import target_pose
from loopmodel.errors import EstimationError, InputError, LoopmodelError
from loopmodel.geometry.se3 import invert_pose, make_pose
from loopmodel.pose import refine_pose
from loopmodel.turntable.reader import MarkerLayout

F64 = NDArray[np.float64]


def marker_corners_in_marker(side_m: float) -> F64:
    """4 x 3 corners (top-left, top-right, bottom-right, bottom-left; ArUco order) in the marker frame."""
    s = side_m / 2.0
    return np.array([[-s, s, 0.0], [s, s, 0.0], [s, -s, 0.0], [-s, -s, 0.0]])


def make_detector(dictionary: str) -> cv2.aruco.ArucoDetector:
    """ArUco detector for a predefined dictionary name (e.g. ``DICT_4X4_50``), refined corners."""
    if not hasattr(cv2.aruco, dictionary):
        raise InputError("markers.dictionary", f"unknown ArUco dictionary '{dictionary}'")
    params = cv2.aruco.DetectorParameters()
    # AprilTag-style edge refinement: on rendered 40 px markers its corners sit 0.015 px inside
    # the true square on average, the subpix (saddle) refinement's 0.29 px inside - a 1.7 %
    # scale, i.e. 7 mm of table depth at 0.42 m
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params)


def detect_markers(image: NDArray[np.uint8], detector: cv2.aruco.ArucoDetector, ids: list[int]) -> dict[int, F64]:
    """Marker id -> 4 x 2 corner pixels (raw image) of the wanted markers seen in the image."""
    corners, found, _ = detector.detectMarkers(image)
    out: dict[int, F64] = {}
    if found is None:
        return out
    for c, i in zip(corners, np.asarray(found).ravel(), strict=True):
        if int(i) in ids and int(i) not in out:
            out[int(i)] = np.asarray(c, dtype=np.float64).reshape(4, 2)
    return out


def single_marker_pose(corners_px: F64, side_m: float, K: F64, dist: F64, init: F64 | None = None) -> F64:
    """``cam_from_marker`` of one marker from its four corners (robust solver)."""
    return target_pose(marker_corners_in_marker(side_m), corners_px, K, dist, init).rig_from_ref


def _planar_median(poses: list[F64]) -> F64:
    """A marker's pose relative to another on the same flat table top.

    The median in-plane offset and turn of many noisy relative poses (robust to single-marker pose
    flips).
    """
    t = np.median([T[:3, 3] for T in poses], axis=0)
    yaw = float(np.median([np.arctan2(T[1, 0], T[0, 0]) for T in poses]))
    c, s = np.cos(yaw), np.sin(yaw)
    return make_pose(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), [t[0], t[1], 0.0])


@dataclass
class LayoutCalibration:
    """``table_from_marker`` per marker id (4x4, metres), and how it was found."""

    table_from_marker: dict[int, F64]
    reference_id: int
    axis_in_cam: F64  # unit rotation axis (camera frame)
    centre_in_cam: F64  # a point of the axis in the table-top plane (camera frame, m)
    circle_rms_m: float  # RMS distance of the reference marker's positions from the fitted circle
    nominal_centre_err_m: dict[int, float]  # |fitted - nominal| table centre position per marker


def fit_circle_3d(points: F64) -> tuple[F64, F64, float, float]:
    """Centre (3,), unit normal (3,), radius and RMS residual (m) of a circle through N x 3 points."""
    c0 = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c0, full_matrices=False)
    n = vt[2]
    e1, e2 = vt[0], vt[1]
    xy = np.column_stack([(points - c0) @ e1, (points - c0) @ e2])
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    sol, *_ = np.linalg.lstsq(A, (xy**2).sum(axis=1), rcond=None)
    cx, cy = sol[:2]
    r = float(np.sqrt(sol[2] + cx * cx + cy * cy))
    centre = c0 + cx * e1 + cy * e2
    d_plane = (points - c0) @ n
    d_radial = np.linalg.norm(xy - [cx, cy], axis=1) - r
    return centre, n, r, float(np.sqrt(np.mean(d_plane**2 + d_radial**2)))


def calibrate_layout(
    detections: list[dict[int, F64]], layout: MarkerLayout, K: F64, dist: F64
) -> tuple[LayoutCalibration, list[dict[int, F64]]]:
    """Self-calibrate the marker layout from all frames' detections.

    Returns it and the per-frame single-marker poses ``cam_from_marker`` used for it.
    """
    single: list[dict[int, F64]] = []
    for det in detections:
        poses = {}
        for i, c in det.items():
            try:
                poses[i] = single_marker_pose(c, layout.side_m, K, dist)
            except LoopmodelError:
                continue
        single.append(poses)
    counts: dict[int, int] = defaultdict(int)
    for s in single:
        for i in s:
            counts[i] += 1
    if not counts:
        raise InputError("frames", "no ArUco marker of the layout found in any frame")
    ref = max(counts, key=lambda i: counts[i])
    # relative poses ref_from_m, by breadth-first chaining over co-visible pairs
    known: dict[int, F64] = {ref: np.eye(4)}
    for _ in range(len(layout.ids)):
        rel: dict[int, list[F64]] = defaultdict(list)
        for s in single:
            base = [i for i in s if i in known]
            if not base:
                continue
            b = base[0]
            for i in s:
                if i not in known:
                    rel[i].append(known[b] @ invert_pose(s[b]) @ s[i])
        if not rel:
            break
        for i, lst in rel.items():
            known[i] = _planar_median(lst)
    # the reference marker's pose in every frame, from all visible markers at once
    ref_poses: list[F64 | None] = [
        frame_pose(det, {i: invert_pose(T) for i, T in known.items()}, layout, K, dist) for det in detections
    ]
    origins = np.array([T[:3, 3] for T in ref_poses if T is not None])
    if len(origins) < 3:
        raise InputError("frames", "markers seen in fewer than 3 frames: no rotation axis")
    centre, normal, _r, rms = fit_circle_3d(origins)
    # normal along the markers' z (out of the table)
    z_ref = np.mean([T[:3, 2] for T in ref_poses if T is not None], axis=0)
    if normal @ z_ref < 0:
        normal = -normal
    # table_from_ref: fixed; from each frame, the axis point in the reference marker frame
    offsets = []
    for T in ref_poses:
        if T is None:
            continue
        c_in_ref = invert_pose(T) @ np.append(centre, 1.0)
        offsets.append(c_in_ref[:3])
    c_ref = np.median(np.array(offsets), axis=0)
    c_ref[2] = 0.0  # the axis point in the table-top plane
    table_from_ref = make_pose(np.eye(3), -c_ref)
    table_from_marker = {i: table_from_ref @ ref_from_m for i, ref_from_m in known.items()}
    nominal = {}
    for i, T in table_from_marker.items():
        if i in layout.centre_in_marker_m:
            cx, cy = layout.centre_in_marker_m[i]
            fitted = invert_pose(T) @ np.array([0.0, 0.0, 0.0, 1.0])
            nominal[i] = float(np.linalg.norm(fitted[:2] - [cx, cy]))
    return LayoutCalibration(table_from_marker, ref, normal, centre, rms, nominal), single


def frame_pose(
    det: dict[int, F64],
    marker_from_table: dict[int, F64],
    layout: MarkerLayout,
    K: F64,
    dist: F64,
    init: F64 | None = None,
) -> F64 | None:
    """``cam_from_table`` of one frame from the corners of all its visible known markers.

    ``marker_from_table`` per id; None with no known marker.
    """
    P, uv = [], []
    local = marker_corners_in_marker(layout.side_m)
    for i, c in det.items():
        if i not in marker_from_table:
            continue
        table_from_m = invert_pose(marker_from_table[i])
        P.append(local @ table_from_m[:3, :3].T + table_from_m[:3, 3])
        uv.append(c)
    if not P:
        return None
    try:
        return target_pose(np.concatenate(P), np.concatenate(uv), K, dist, init).rig_from_ref
    except LoopmodelError:
        return None


@dataclass
class TablePoses:
    """Per-frame ``cam_from_table`` (None where no marker was seen), covariance and residual RMS.

    With the solver's 6x6 covariance (left twist v, w) and the corner residual RMS (px).
    """

    cam_from_table: list[F64 | None]
    covariance: list[F64 | None]
    residual_px: list[float]
    markers_seen: list[list[int]]


def table_poses(
    detections: list[dict[int, F64]], calib: LayoutCalibration, layout: MarkerLayout, K: F64, dist: F64
) -> TablePoses:
    """``cam_from_table`` per frame from all visible markers' corners (robust solver)."""
    from loopmodel.calibration.pose import undistort_px
    from loopmodel.geometry.camera import CentralCamera
    from loopmodel.pose import CameraRig, PointTerm

    rig = CameraRig.single(CentralCamera.from_K(K))
    local = marker_corners_in_marker(layout.side_m)
    poses: list[F64 | None] = []
    covs: list[F64 | None] = []
    res: list[float] = []
    seen: list[list[int]] = []
    prev: F64 | None = None
    for det in detections:
        ids = [i for i in det if i in calib.table_from_marker]
        seen.append(ids)
        if not ids:
            poses.append(None)
            covs.append(None)
            res.append(float("nan"))
            continue
        P = np.concatenate(
            [local @ calib.table_from_marker[i][:3, :3].T + calib.table_from_marker[i][:3, 3] for i in ids]
        )
        uv = undistort_px(np.concatenate([det[i] for i in ids]), K, dist)
        term = PointTerm(rig, P, uv)
        try:
            from loopmodel.pose import estimate_pose

            r = estimate_pose(term, prev, ransac_threshold_px=3.0)
            r = refine_pose(term, r.rig_from_ref)
        except (LoopmodelError, EstimationError):
            poses.append(None)
            covs.append(None)
            res.append(float("nan"))
            continue
        poses.append(r.rig_from_ref)
        covs.append(r.covariance)
        res.append(float(np.sqrt(np.mean(r.residual_norms[0] ** 2))))
        prev = r.rig_from_ref
    return TablePoses(poses, covs, res, seen)
