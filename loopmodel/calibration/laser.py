"""Laser light-plane calibration from chessboard images with the laser line on the board.

Per image: the board's corners (a partly visible board gives its largest visible sub-grid),
its pose by the project's robust pose solver, hence its plane in the camera frame; the laser
line's sub-pixel peaks (:func:`loopmodel.mapping.extraction.line_response` and
:func:`extract_laser_peaks`) inside the board's image region; their viewing rays meet the
board plane (:func:`triangulate_with_plane`). All images' points give the light plane by a
robust fit (:func:`fit_plane`). Camera frame of the intrinsics, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.calibration.chessboard import detect_corners
from loopmodel.calibration.pose import target_pose
from loopmodel.errors import InputError, LoopmodelError
from loopmodel.io.images import read_image
from loopmodel.mapping.extraction import (
    LightPlane,
    extract_laser_peaks,
    fit_plane,
    line_response,
    triangulate_with_plane,
)

F64 = NDArray[np.float64]

#: inlier band of the robust plane fit (metres)
PLANE_INLIER_M = 2e-3
#: the board's plane is trusted this many squares beyond its outer detected corners
BOARD_MARGIN_SQUARES = 3.0
#: peak acceptance on the top-hat response (grey levels); measured on bcap1..6 (1920x1080)
#: and on the turntable frames (640x480): the line stands 60-200 above, texture below 15
LINE_MIN_CONTRAST = 25.0


@dataclass
class LaserView:
    """One calibration image: the board pose, the laser peaks on it and their 3-D points."""

    path: str
    corners: int
    partial: bool
    cam_from_board: F64
    board_plane: LightPlane
    peaks_uv_px: F64
    points_in_cam_m: F64
    line_direction: F64  # unit direction of the 3-D line through the image's points
    board_rms_px: float


@dataclass
class LaserPlaneResult:
    """The fitted light plane and its quality figures (millimetres, degrees)."""

    plane: LightPlane
    rms_mm: float
    inlier_fraction: float
    line_angle_spread_deg: float
    line_to_plane_deg_max: float
    views: list[LaserView]
    rejected: list[tuple[str, str]]
    points_in_cam_m: F64 = field(repr=False, default_factory=lambda: np.zeros((0, 3)))
    inliers: NDArray[np.bool_] = field(repr=False, default_factory=lambda: np.zeros(0, dtype=bool))

    def compare(self, planes: dict[str, LightPlane]) -> list[dict[str, float | str]]:
        """Each candidate plane's RMS distance (mm) to this fit's inlier points and angle (deg) between normals.

        Sorted best first.
        """
        P = self.points_in_cam_m[self.inliers]
        rows: list[dict[str, float | str]] = []
        for name, pl in planes.items():
            dist = pl.signed_distance_m(P)
            cosang = abs(float(pl.normal_in_cam @ self.plane.normal_in_cam))
            rows.append(
                {
                    "name": name,
                    "rms_mm": float(1e3 * np.sqrt(np.mean(dist**2))),
                    "normal_angle_deg": float(np.degrees(np.arccos(min(cosang, 1.0)))),
                    "offset_diff_mm": float(1e3 * abs(abs(pl.d_m) - abs(self.plane.d_m))),
                }
            )
        return sorted(rows, key=lambda r: float(r["rms_mm"]))


def board_region_mask(
    cam_from_board: F64, board_m: F64, square_m: float, K: F64, dist: F64, shape: tuple[int, int], margin: float
) -> NDArray[np.bool_]:
    """Image mask of the board plane's rectangle spanning the detected corners.

    Plus ``margin`` squares on every side.
    """
    lo = board_m[:, :2].min(axis=0) - margin * square_m
    hi = board_m[:, :2].max(axis=0) + margin * square_m
    quad = np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0], [lo[0], hi[1], 0]], dtype=np.float64)
    # sample the edges densely so the distorted outline is followed
    t = np.linspace(0.0, 1.0, 20, endpoint=False)[:, None]
    outline = np.concatenate([quad[i] + t * (quad[(i + 1) % 4] - quad[i]) for i in range(4)])
    rvec, _ = cv2.Rodrigues(cam_from_board[:3, :3])
    uv, _ = cv2.projectPoints(outline, rvec, cam_from_board[:3, 3], K, dist)
    mask = np.zeros(shape, dtype=np.uint8)
    cv2.fillPoly(mask, [np.round(uv.reshape(-1, 2)).astype(np.int32)], 1)
    return mask.astype(bool)


def _line_direction(P: F64) -> F64:
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    return np.asarray(vt[0], dtype=np.float64)


def check_intrinsics_fit(path: str | Path, size: tuple[int, int], K: F64, calib_size: tuple[int, int] | None) -> None:
    """Raise :class:`InputError` when an image cannot belong to these intrinsics (another size)."""
    w, h = size
    if calib_size is not None and calib_size != size:
        raise InputError(path, f"image is {w}x{h} but the intrinsics are for {calib_size[0]}x{calib_size[1]}")
    if not (0.25 * w < K[0, 2] < 0.75 * w and 0.25 * h < K[1, 2] < 0.75 * h):
        raise InputError(
            path,
            f"image is {w}x{h} but the intrinsics' principal point ({K[0, 2]:.0f}, {K[1, 2]:.0f}) lies far from "
            "its centre (intrinsics of another image size?)",
        )


def laser_view(
    path: Path,
    K: F64,
    dist: F64,
    board: tuple[int, int],
    square_m: float,
    calib_size: tuple[int, int] | None = None,
    channel: str = "green",
) -> LaserView:
    """Board pose and laser points of one calibration image.

    Raises InputError naming the file when it has no board or no laser line on the board.
    """
    img = read_image(path)
    if img.ndim != 3:
        raise InputError(path, "laser calibration needs a colour image (the laser's colour picks the line)")
    size = (int(img.shape[1]), int(img.shape[0]))
    check_intrinsics_fit(path, size, K, calib_size)
    corners = detect_corners(img, board, square_m, str(path), allow_partial=True)
    if corners is None:
        raise InputError(path, f"no {board[0]}x{board[1]} chessboard corners (nor a 4x4 part of it) found")
    try:
        pose = target_pose(corners.board_m, corners.uv_px, K, dist)
    except LoopmodelError as exc:
        raise InputError(path, f"no board pose ({exc})") from None
    T = pose.rig_from_ref
    rms = float(np.sqrt(np.mean(np.concatenate(pose.residual_norms) ** 2)))
    normal = T[:3, 2]
    plane = LightPlane.from_point_normal(T[:3, 3], normal)
    mask = board_region_mask(T, corners.board_m, square_m, K, dist, img.shape[:2], BOARD_MARGIN_SQUARES)
    resp = line_response(img, channel, axis="rows")
    uv = extract_laser_peaks(resp, "rows", LINE_MIN_CONTRAST, 3, "cog", mask=mask, max_width_px=15)
    if uv.shape[0] < 10:
        raise InputError(path, f"laser line not found on the board ({uv.shape[0]} peaks)")
    P = triangulate_with_plane(uv, K, plane, dist)
    return LaserView(str(path), len(corners.uv_px), corners.partial, T, plane, uv, P, _line_direction(P), rms)


def calibrate_laser_plane(
    paths: list[Path],
    K: F64,
    dist: F64,
    board: tuple[int, int],
    square_m: float,
    calib_size: tuple[int, int] | None = None,
    channel: str = "green",
) -> LaserPlaneResult:
    """The light plane (camera frame, metres) from chessboard images with the laser line."""
    if not (np.isfinite(square_m) and square_m > 0):
        raise InputError("--square-m", f"square size must be a positive number of metres, got {square_m}")
    views: list[LaserView] = []
    rejected: list[tuple[str, str]] = []
    for p in paths:
        try:
            views.append(laser_view(p, K, dist, board, square_m, calib_size, channel))
        except InputError as exc:
            if "intrinsics" in exc.problem:
                raise
            rejected.append((str(p), exc.problem))
    if len(views) < 2:
        first = rejected[0] if rejected else (str(paths[0]) if paths else "IMAGES", "")
        raise InputError(
            first[0],
            f"a laser plane needs boards at two or more poses, {len(views)} usable of {len(paths)} image(s)"
            + (f" ({first[1]})" if first[1] else ""),
        )
    P = np.concatenate([v.points_in_cam_m for v in views])
    plane, inl = fit_plane(P, PLANE_INLIER_M)
    res = plane.signed_distance_m(P[inl])
    dirs = np.array([v.line_direction for v in views])
    cos = np.clip(np.abs(dirs @ dirs.T), 0.0, 1.0)
    spread = float(np.degrees(np.arccos(cos.min())))
    to_plane = float(np.degrees(np.arcsin(np.clip(np.abs(dirs @ plane.normal_in_cam), 0, 1))).max())
    return LaserPlaneResult(
        plane,
        float(1e3 * np.sqrt(np.mean(res**2))),
        float(inl.mean()),
        spread,
        to_plane,
        views,
        rejected,
        P,
        inl,
    )


def read_laser_planes_json(path: str | Path) -> dict[str, LightPlane]:
    """Planes ``[a, b, c, d]`` (``a x + b y + c z + d = 0``, metres) of a ``laser_planes.json``.

    The file holds ``{"planes": {name: [a, b, c, d]}}``.
    """
    import json

    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(p, f"cannot read laser planes JSON ({exc})") from None
    planes = data.get("planes", data) if isinstance(data, dict) else None
    if not isinstance(planes, dict) or not planes:
        raise InputError(p, "expected {'planes': {name: [a, b, c, d]}}")
    out = {}
    for name, v in planes.items():
        if not isinstance(v, list) or len(v) != 4:
            raise InputError(p, f"plane '{name}' needs 4 numbers [a, b, c, d]")
        out[str(name)] = LightPlane(np.asarray(v[:3], dtype=float), float(v[3]))
    return out


def plane_summary(result: LaserPlaneResult, comparison: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The plane YAML written by ``loopmodel calibrate laser``."""
    n = result.plane.normal_in_cam
    return {
        "plane_abcd": [float(n[0]), float(n[1]), float(n[2]), float(result.plane.d_m)],
        "frame": "camera (x right, y down, z forward), metres: a x + b y + c z + d = 0",
        "laser_plane_normal_in_cam": [float(x) for x in n],
        "laser_plane_point_in_cam_m": [float(x) for x in -result.plane.d_m * n],
        "rms_mm": result.rms_mm,
        "inlier_fraction": result.inlier_fraction,
        "line_angle_spread_deg": result.line_angle_spread_deg,
        "line_to_plane_deg_max": result.line_to_plane_deg_max,
        "views": [
            {
                "path": v.path,
                "corners": v.corners,
                "partial_board": v.partial,
                "board_rms_px": v.board_rms_px,
                "laser_points": int(v.points_in_cam_m.shape[0]),
                "board_distance_m": float(np.linalg.norm(v.cam_from_board[:3, 3])),
            }
            for v in result.views
        ],
        "rejected": [{"path": p, "reason": r} for p, r in result.rejected],
        **({"comparison": comparison} if comparison else {}),
    }
