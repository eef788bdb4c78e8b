"""A whole turntable scan, with the accuracy figures of the issue (degrees, millimetres).

Markers -> table poses -> loop-closed pose graph -> laser points in the table frame -> mesh.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from loopmodel.config import MappingConfig
from loopmodel.errors import InputError
from loopmodel.geometry.se3 import invert_pose, so3_log
from loopmodel.mapping.meshing import mesh_from_points
from loopmodel.turntable.markers import (
    LayoutCalibration,
    TablePoses,
    calibrate_layout,
    detect_markers,
    make_detector,
    table_poses,
)
from loopmodel.turntable.posegraph import optimise_turntable, step_angles_deg
from loopmodel.turntable.reader import TurntableScan
from loopmodel.turntable.scan import (
    FramePeaks,
    PlaneChoice,
    choose_plane,
    frame_peaks,
    object_points,
    self_consistency_mm,
)

F64 = NDArray[np.float64]
Progress = Callable[[str, int, int], None]


@dataclass
class TurntableResult:
    """Everything a scan gives: poses before/after the graph, the plane, points, mesh, figures."""

    layout: LayoutCalibration
    marker_poses: TablePoses
    cam_from_table: list[F64]
    plane: PlaneChoice
    points_in_table_m: F64
    point_frame: NDArray[np.int64]
    mesh: o3d.geometry.TriangleMesh
    figures: dict[str, Any] = field(default_factory=dict)
    steps_before_deg: F64 = field(default_factory=lambda: np.zeros(0))
    steps_after_deg: F64 = field(default_factory=lambda: np.zeros(0))


def azimuth_coverage(points_in_table_m: F64, bins: int = 72) -> float:
    """Fraction of 5-degree sectors about the table axis that hold object points.

    1 = closed around the whole circumference.
    """
    a = np.arctan2(points_in_table_m[:, 1], points_in_table_m[:, 0])
    h, _ = np.histogram(a, bins=bins, range=(-np.pi, np.pi))
    return float(np.mean(h > 0))


def _nothing(stage: str, done: int, total: int) -> None:
    return None


def scan_turntable(
    scan: TurntableScan,
    config: MappingConfig | None = None,
    progress: Progress = _nothing,
    plane_gate_mm: float = 1.0,
) -> TurntableResult:
    """Run the turntable pipeline on an opened scan.

    A candidate laser plane is taken when its table-plane residual is within ``plane_gate_mm`` (else
    the plane is self-calibrated).
    """
    # octree cells of one voxel, as before issue 32 (the coarser default was measured on hand-held scans only);
    # Poisson, not the sdf (sdf16: on this scan the sdf's mesh lies farther from the points, mean 0.228 -> 0.279 mm,
    # with a few small holes; no surface truth here)
    cfg = config or MappingConfig(poisson_cell_voxels=1.0, method="poisson")
    detector = make_detector(scan.markers.dictionary)
    n = len(scan)
    dets = []
    for k, img in scan.frames():
        dets.append(detect_markers(img, detector, scan.markers.ids))
        progress("markers", k + 1, n)
    layout, _single = calibrate_layout(dets, scan.markers, scan.K, scan.dist)
    tp = table_poses(dets, layout, scan.markers, scan.K, scan.dist)
    if sum(T is not None for T in tp.cam_from_table) < max(3, n // 2):
        raise InputError(scan.folder, "the table pose is known in fewer than half of the frames (markers not seen)")
    graph = optimise_turntable(tp.cam_from_table, tp.covariance, scan.step_deg)
    poses = graph.cam_from_table
    peaks: list[FramePeaks] = []
    for k, img in scan.frames():
        peaks.append(frame_peaks(img, poses[k], scan))
        progress("laser", k + 1, n)
    choice = choose_plane(peaks, poses, scan, plane_gate_mm)
    progress("plane", 1, 1)
    P, frame = object_points(peaks, poses, choice.plane, scan)
    if len(P) < 100:
        raise InputError(scan.folder, f"only {len(P)} laser points in the working volume")
    sensors = np.array([invert_pose(T)[:3, 3] for T in poses])[frame]
    mesh = mesh_from_points(P, sensors, cfg)
    progress("mesh", 1, 1)
    before = step_angles_deg(tp.cam_from_table)
    after = step_angles_deg(poses)
    # marker scatter: each frame's marker-only table angle about the graph's pose (deg, z)
    scatter = np.array(
        [
            np.degrees(so3_log((invert_pose(T) @ G)[:3, :3]))
            for T, G in zip(tp.cam_from_table, poses, strict=True)
            if T is not None
        ]
    )
    pos_scatter = np.array(
        [1e3 * (invert_pose(G) @ T)[:3, 3] for T, G in zip(tp.cam_from_table, poses, strict=True) if T is not None]
    )
    from loopmodel.turntable.accuracy import marker_scatter

    ms = marker_scatter(dets, poses, layout.table_from_marker, scan.markers.side_m, scan.K, scan.dist)
    figures = {
        "marker_pose_scatter": ms.as_dict(),
        "frames": n,
        "step_deg": scan.step_deg,
        "step_angle_err_deg_rms_before": float(np.sqrt(np.nanmean((before - scan.step_deg) ** 2))),
        "step_angle_err_deg_rms_after": float(np.sqrt(np.mean((after - scan.step_deg) ** 2))),
        "loop_closure_err_deg": float(np.nansum(before) - 360.0),
        "table_plane_residual_mm": choice.table_residual_mm,
        "laser_plane": choice.name,
        "mesh_points": int(len(P)),
        "mesh_vertices": int(len(mesh.vertices)),
        "mesh_triangles": int(len(mesh.triangles)),
        "mesh_err_self_mm": self_consistency_mm(P, frame, n),
        "azimuth_coverage": azimuth_coverage(P),
        "marker_angle_scatter_deg_rms": float(np.sqrt(np.mean(scatter[:, 2] ** 2))),
        "marker_tilt_scatter_deg_rms": float(np.sqrt(np.mean(scatter[:, 0] ** 2 + scatter[:, 1] ** 2))),
        "marker_position_scatter_mm_rms": [float(x) for x in np.sqrt(np.mean(pos_scatter**2, axis=0))],
        "marker_corner_residual_px_median": float(np.nanmedian(tp.residual_px)),
        "layout_circle_rms_mm": 1e3 * layout.circle_rms_m,
        "layout_vs_nominal_mm": {str(k): 1e3 * v for k, v in layout.nominal_centre_err_m.items()},
        "frames_without_markers": int(sum(T is None for T in tp.cam_from_table)),
        "graph_error_initial": graph.initial_error,
        "graph_error_final": graph.final_error,
        "plane_candidates": choice.candidates,
        "plane_normal_in_cam": [float(x) for x in choice.plane.normal_in_cam],
        "plane_d_m": float(choice.plane.d_m),
        "table_line_rms_mm": choice.line_rms_mm,
        "plane_tilt_about_table_line_deg": choice.self_angle_deg,
    }
    return TurntableResult(layout, tp, poses, choice, P, frame, mesh, figures, before, after)
