"""Laser points of a turntable scan in the table frame, the session's laser plane, the mesh.

Per frame: the laser line's response (:func:`loopmodel.mapping.extraction.line_response`)
and sub-pixel peaks inside the image of the working volume (a cylinder above the table,
table frame) or of the table-top annulus; peaks are triangulated with a light plane in the
camera frame and moved into the table frame with the frame's ``cam_from_table``. Points
outside the working volume (the wall, the table edge and top) drop out.

The laser plane of a session is judged by the table-top points: triangulated with the
plane, they must lie on the table plane the markers give (``table_plane_residual_mm``).
When no candidate does, the plane is self-calibrated: it contains the 3-D line the laser
draws on the table top (the table plane is known from the markers in every frame) and its
one remaining angle about that line is the one for which the surfaces seen from opposite
sides (180° apart) agree best - within 10 %, the angle nearest the plane that contains the
table axis (the agreement is flat near its minimum).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from loopmodel.geometry.se3 import invert_pose, so3_exp
from loopmodel.mapping.extraction import LightPlane, extract_laser_peaks, line_response, triangulate_with_plane
from loopmodel.turntable.reader import TurntableScan, WorkingVolume

F64 = NDArray[np.float64]

#: top-hat response threshold (grey levels) of the laser line: measured on the turntable frames
#: (line 60-250 above, lit texture under 15) and on the chessboard images bcap1..6
LINE_MIN_CONTRAST = 25.0
#: wider than this at half maximum (px) is blooming or a broad reflection
LINE_MAX_WIDTH_PX = 12.0
#: table-top annulus (fraction of the table radius) used for the table-plane residual: outside
#: the object's base, inside the rim (on the real table the rim's edge starts near 0.85 R)
TABLE_ANNULUS = (0.52, 0.84)
#: relative cost margin within which the self-calibrated plane prefers the axis-containing one
SELF_COST_SLACK = 0.1
#: overlap radius for the 180° self-consistency (metres)
SELF_OVERLAP_M = 3e-3


def _cylinder_outline(radius: float, z0: float, z1: float, n: int = 72) -> F64:
    th = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    ring = np.column_stack([radius * np.cos(th), radius * np.sin(th)])
    return np.concatenate([np.column_stack([ring, np.full(n, z)]) for z in (z0, z1)])


def _project(P: F64, cam_from_table: F64, K: F64, dist: F64) -> F64:
    rvec, _ = cv2.Rodrigues(cam_from_table[:3, :3])
    uv, _ = cv2.projectPoints(P, rvec, cam_from_table[:3, 3], K, dist)
    return np.asarray(uv, dtype=np.float64).reshape(-1, 2)


def volume_mask(
    cam_from_table: F64, K: F64, dist: F64, shape: tuple[int, int], vol: WorkingVolume
) -> NDArray[np.bool_]:
    """Image mask of the working volume (convex hull of its projected outline)."""
    uv = _project(_cylinder_outline(vol.radius_m, vol.z_min_m, vol.z_max_m), cam_from_table, K, dist)
    hull = cv2.convexHull(np.round(uv).astype(np.int32))
    m = np.zeros(shape, dtype=np.uint8)
    cv2.fillConvexPoly(m, hull, 1)
    return m.astype(bool)


def annulus_mask(
    cam_from_table: F64, K: F64, dist: F64, shape: tuple[int, int], r0: float, r1: float
) -> NDArray[np.bool_]:
    """Image mask of the table-top annulus ``r0 <= r <= r1`` (metres, z = 0)."""
    m = np.zeros(shape, dtype=np.uint8)
    for r, val in ((r1, 1), (r0, 0)):
        uv = _project(_cylinder_outline(r, 0.0, 0.0)[:72], cam_from_table, K, dist)
        cv2.fillPoly(m, [np.round(uv).astype(np.int32)], val)
    return m.astype(bool)


@dataclass
class FramePeaks:
    """Laser peaks (raw pixels) of one frame: in the working volume's image and on the table top."""

    object_uv: F64
    table_uv: F64


def frame_peaks(image: NDArray[np.uint8], cam_from_table: F64, scan: TurntableScan) -> FramePeaks:
    """The laser line's sub-pixel peaks of one frame (one per image row)."""
    resp = line_response(image, scan.laser_colour, axis="rows")
    shape = image.shape[:2]
    vm = volume_mask(cam_from_table, scan.K, scan.dist, shape, scan.volume)
    r = scan.table_radius_m
    am = annulus_mask(cam_from_table, scan.K, scan.dist, shape, TABLE_ANNULUS[0] * r, TABLE_ANNULUS[1] * r)
    # the strongest line response of each row, then kept by region: a weaker response beside
    # the line (a lit marker cell, texture) never stands in for it
    uv = extract_laser_peaks(resp, "rows", LINE_MIN_CONTRAST, 3, "cog", max_width_px=LINE_MAX_WIDTH_PX)
    iu = np.clip(np.round(uv[:, 0]).astype(int), 0, shape[1] - 1)
    iv = np.clip(np.round(uv[:, 1]).astype(int), 0, shape[0] - 1)
    # table top: the near half only (below the table centre in the image); behind the object
    # the far half is mostly hidden and what shows there is the rim and the wall
    v_centre = float(_project(np.zeros((1, 3)), cam_from_table, scan.K, scan.dist)[0, 1])
    near = uv[:, 1] > v_centre
    return FramePeaks(uv[vm[iv, iu]], uv[am[iv, iu] & near])


def to_table(points_in_cam: F64, cam_from_table: F64) -> F64:
    """N x 3 camera-frame points into the table frame."""
    T = invert_pose(cam_from_table)
    return np.asarray(points_in_cam @ T[:3, :3].T + T[:3, 3], dtype=np.float64)


def in_volume(P: F64, vol: WorkingVolume) -> NDArray[np.bool_]:
    """Which table-frame points lie in the working volume."""
    r = np.hypot(P[:, 0], P[:, 1])
    return np.asarray((r <= vol.radius_m) & (P[:, 2] >= vol.z_min_m) & (P[:, 2] <= vol.z_max_m))


def table_residual(
    peaks: list[FramePeaks], poses: list[F64], plane: LightPlane, K: F64, dist: F64
) -> tuple[float, float, int]:
    """Table-top laser points triangulated with ``plane`` against the markers' table plane z = 0.

    (RMS mm after 3-sigma (MAD) rejection about the median, median mm, count).
    """
    z = np.concatenate(
        [
            to_table(triangulate_with_plane(p.table_uv, K, plane, dist), T)[:, 2]
            for p, T in zip(peaks, poses, strict=True)
        ]
    )
    if z.size == 0:
        return float("inf"), float("nan"), 0
    med = float(np.median(z))
    mad = 1.4826 * float(np.median(np.abs(z - med)))
    inl = np.abs(z - med) <= 3.0 * max(mad, 1e-5)
    return float(1e3 * np.sqrt(np.mean(z[inl] ** 2))), 1e3 * med, int(z.size)


def table_line_in_cam(peaks: list[FramePeaks], poses: list[F64], K: F64, dist: F64) -> tuple[F64, F64, float]:
    """The 3-D line the laser draws on the table top (camera frame).

    Point, unit direction and the RMS distance (m) of the table-top points from it. Each frame's
    table-top rays meet its table plane (from the markers).
    """
    pts = []
    for p, T in zip(peaks, poses, strict=True):
        n = T[:3, 2]
        table_plane = LightPlane(n, -float(n @ T[:3, 3]))
        pts.append(triangulate_with_plane(p.table_uv, K, table_plane, dist))
    P = np.concatenate(pts)
    if P.shape[0] < 10:
        raise ValueError("too few laser points on the table top")
    # RANSAC on point pairs (band 1.5 mm), then total least squares on the inliers
    rng = np.random.default_rng(0)
    keep = np.ones(len(P), dtype=bool)
    best = -1
    for _ in range(300):
        a, b = P[rng.choice(len(P), 2, replace=False)]
        d = b - a
        nd = float(np.linalg.norm(d))
        if nd < 1e-4:
            continue
        d /= nd
        off = P - a
        inl = np.linalg.norm(off - np.outer(off @ d, d), axis=1) < 1.5e-3
        if inl.sum() > best:
            best, keep = int(inl.sum()), inl
    for _ in range(3):
        c = P[keep].mean(axis=0)
        _, _, vt = np.linalg.svd(P[keep] - c, full_matrices=False)
        d = vt[0]
        off = P - c
        dist_line = np.linalg.norm(off - np.outer(off @ d, d), axis=1)
        s = 1.4826 * np.median(dist_line[keep])
        keep = dist_line <= 3.0 * max(s, 1e-5)
    return c, d, float(np.sqrt(np.mean(dist_line[keep] ** 2)))


def plane_through_line(point: F64, direction: F64, reference_normal: F64, angle_rad: float) -> LightPlane:
    """Plane containing the line, its normal turned by ``angle_rad`` about the line.

    The normal starts as the reference normal, made perpendicular to the line.
    """
    d = direction / np.linalg.norm(direction)
    n0 = reference_normal - (reference_normal @ d) * d
    n0 /= np.linalg.norm(n0)
    n = so3_exp(d * angle_rad) @ n0
    return LightPlane.from_point_normal(point, n)


def object_points(
    peaks: list[FramePeaks], poses: list[F64], plane: LightPlane, scan: TurntableScan
) -> tuple[F64, NDArray[np.int64]]:
    """Table-frame points inside the working volume and the frame index of each."""
    P, idx = [], []
    for k, (p, T) in enumerate(zip(peaks, poses, strict=True)):
        Q = to_table(triangulate_with_plane(p.object_uv, scan.K, plane, scan.dist), T)
        Q = Q[in_volume(Q, scan.volume)]
        P.append(Q)
        idx.append(np.full(len(Q), k, dtype=np.int64))
    if not P:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    return np.concatenate(P), np.concatenate(idx)


def self_consistency_mm(P: F64, frame: NDArray[np.int64], n_frames: int, overlap_m: float = SELF_OVERLAP_M) -> float:
    """RMS point-to-surface distance (mm) between the points seen from views 180° apart.

    The first half-turn's points against a local plane through the second half-turn's neighbours
    within ``overlap_m`` (where the two overlap).
    """
    half = n_frames // 2
    A, B = P[frame < half], P[frame >= half]
    if len(A) < 10 or len(B) < 10:
        return float("inf")
    tree = cKDTree(B)
    nbrs = tree.query_ball_point(A, overlap_m)
    d = []
    for a, nb in zip(A, nbrs, strict=True):
        if len(nb) < 6:
            continue
        Q = B[nb]
        c = Q.mean(axis=0)
        _, _, vt = np.linalg.svd(Q - c, full_matrices=False)
        d.append(float((a - c) @ vt[2]))
    if len(d) < 10:
        return float("inf")
    return float(1e3 * np.sqrt(np.mean(np.square(d))))


@dataclass
class PlaneChoice:
    """The session's laser plane and how it was chosen (candidates' table residuals, mm)."""

    name: str
    plane: LightPlane
    table_residual_mm: float
    table_median_mm: float
    candidates: dict[str, dict[str, float]] = field(default_factory=dict)
    line_rms_mm: float = float("nan")
    self_angle_deg: float = float("nan")


def choose_plane(
    peaks: list[FramePeaks], poses: list[F64], scan: TurntableScan, max_residual_mm: float = 1.0
) -> PlaneChoice:
    """The candidate laser plane that fits the table, else the self-calibrated plane.

    A candidate fits when its table-top points lie on the markers' table plane within
    ``max_residual_mm``; among those, the one with the smallest |median|.
    """
    cands: dict[str, dict[str, float]] = {}
    for name, pl in scan.planes.items():
        rms, med, n = table_residual(peaks, poses, pl, scan.K, scan.dist)
        cands[name] = {"table_residual_mm": rms, "table_median_mm": med, "points": float(n)}
    good = [
        k
        for k, v in cands.items()
        if v["table_residual_mm"] <= max_residual_mm and abs(v["table_median_mm"]) <= max_residual_mm
    ]
    if good:
        best = min(good, key=lambda k: abs(cands[k]["table_median_mm"]))
        return PlaneChoice(
            best, scan.planes[best], cands[best]["table_residual_mm"], cands[best]["table_median_mm"], cands
        )
    c, d, line_rms = table_line_in_cam(peaks, poses, scan.K, scan.dist)
    # reference: the plane through the line that contains the turntable axis direction
    axis = np.median([T[:3, 2] for T in poses], axis=0)
    ref_normal = np.cross(d, axis)

    def cost(a: float) -> float:
        pl = plane_through_line(c, d, ref_normal, a)
        P, f = object_points(peaks, poses, pl, scan)
        return self_consistency_mm(P, f, len(poses))

    # the 180° agreement is flat near its minimum (on the real scan within 10 % over +-8 deg):
    # take the angle nearest the axis-containing plane whose cost is within SELF_COST_SLACK of
    # the best, not the noisy minimum itself
    grid = np.radians(np.arange(-10.0, 10.1, 1.0))
    costs = np.array([cost(a) for a in grid])
    ok = costs <= (1.0 + SELF_COST_SLACK) * float(np.min(costs))
    a_best = float(grid[ok][int(np.argmin(np.abs(grid[ok])))])
    plane = plane_through_line(c, d, ref_normal, a_best)
    rms, med, _ = table_residual(peaks, poses, plane, scan.K, scan.dist)
    return PlaneChoice("self-calibrated", plane, rms, med, cands, 1e3 * line_rms, float(np.degrees(a_best)))
