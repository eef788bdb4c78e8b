"""Turntable scan outputs: meshes (PLY/OBJ/STL/GLB), a software-rendered picture of the mesh,
the step-angle plot and a Markdown report."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d

from loopmodel.io.atomic import save_figure_atomic, write_text_atomic
from loopmodel.io.mesh_io import write_mesh
from loopmodel.turntable.posegraph import MOTOR_SIGMA_DEG
from loopmodel.turntable.run import TurntableResult

MESH_EXPORTS = ("ply", "obj", "stl", "glb")


def render_mesh(
    mesh: o3d.geometry.TriangleMesh, path: Path, views: tuple[float, ...] = (0.0, 90.0, 180.0, 270.0)
) -> Path:
    """Lambert-shaded software render (matplotlib) of the mesh from several azimuths (deg)
    about the table axis, 20 deg above the table; table frame, millimetres on the axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    m = o3d.geometry.TriangleMesh(mesh)
    if len(m.triangles) > 30000:
        m = m.simplify_quadric_decimation(30000)
    m.compute_triangle_normals()
    V = np.asarray(m.vertices) * 1e3
    F = np.asarray(m.triangles)
    N = np.asarray(m.triangle_normals)
    fig = plt.figure(figsize=(4.0 * len(views), 4.4))
    lo, hi = V.min(axis=0), V.max(axis=0)
    c, r = (lo + hi) / 2, float((hi - lo).max()) / 2
    for i, az in enumerate(views):
        ax = fig.add_subplot(1, len(views), i + 1, projection="3d")
        el = np.radians(20.0)
        a = np.radians(az)
        to_eye = np.array([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)])
        light = to_eye + np.array([0.0, 0.0, 0.5])
        light /= np.linalg.norm(light)
        shade = np.clip(np.abs(N @ light), 0.0, 1.0) * 0.8 + 0.15
        colours = np.column_stack([shade * 0.95, shade * 0.75, shade * 0.45, np.ones_like(shade)])
        ax.add_collection3d(Poly3DCollection(V[F], facecolors=colours, edgecolors="none"))
        ax.set_xlim(c[0] - r, c[0] + r)
        ax.set_ylim(c[1] - r, c[1] + r)
        ax.set_zlim(c[2] - r, c[2] + r)
        ax.view_init(elev=20.0, azim=az)
        ax.set_title(f"azimuth {az:.0f} deg")
        ax.set_axis_off()
    fig.tight_layout()
    return save_figure_atomic(path, fig)


def plot_steps(result: TurntableResult, step_deg: float, path: Path) -> Path:
    """Marker-based step angles before and after the loop-closed pose graph (deg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 3.5))
    ax.plot(result.steps_before_deg, ".", ms=3, label="markers only")
    ax.plot(result.steps_after_deg, "-", lw=1, label="loop-closed pose graph")
    ax.axhline(step_deg, color="k", lw=0.8, ls="--", label=f"motor step {step_deg:g} deg")
    ax.set_xlabel("step")
    ax.set_ylabel("step angle (deg)")
    ax.legend()
    fig.tight_layout()
    return save_figure_atomic(path, fig)


def write_outputs(result: TurntableResult, step_deg: float, out: Path, source: str) -> list[Path]:
    """Meshes, points, the render, the plot, ``metrics.json`` and ``report.md`` in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    paths = [write_mesh(out / f"mesh.{fmt}", result.mesh, fmt) for fmt in MESH_EXPORTS]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(result.points_in_table_m))
    tmp = out / ".points.ply.tmp.ply"
    o3d.io.write_point_cloud(tmp, cloud)
    tmp.replace(out / "points.ply")
    paths.append(out / "points.ply")
    paths.append(render_mesh(result.mesh, out / "mesh.png"))
    paths.append(plot_steps(result, step_deg, out / "steps.png"))
    f = result.figures
    paths.append(write_text_atomic(out / "metrics.json", json.dumps(f, indent=2) + "\n"))
    cands = "\n".join(
        f"| {k} | {v['table_residual_mm']:.2f} | {v['table_median_mm']:.2f} | {int(v['points'])} |"
        for k, v in f["plane_candidates"].items()
    )
    md = f"""# Turntable scan of `{source}`

![mesh](mesh.png)

| figure | value |
|---|---|
| frames | {f["frames"]} (motor step {f["step_deg"]:g} deg) |
| step angle error RMS, markers only | {f["step_angle_err_deg_rms_before"]:.3f} deg |
| step angle error RMS, loop-closed pose graph | {f["step_angle_err_deg_rms_after"]:.3f} deg |
| accumulated angle - 360 deg, before the closure | {f["loop_closure_err_deg"]:+.3f} deg |
| laser plane | {f["laser_plane"]} |
| table-plane residual of the table-top laser points | {f["table_plane_residual_mm"]:.3f} mm |
| points in the working volume | {f["mesh_points"]} |
| mesh | {f["mesh_vertices"]} vertices, {f["mesh_triangles"]} triangles |
| surfaces seen 180 deg apart: RMS distance | {f["mesh_err_self_mm"]:.3f} mm |
| sectors of 5 deg around the axis with points | {100 * f["azimuth_coverage"]:.1f} % |
| marker-only table angle about the graph's, RMS | {f["marker_angle_scatter_deg_rms"]:.3f} deg |
| marker corner residual, median | {f["marker_corner_residual_px_median"]:.3f} px |
| marker layout: reference marker's circle, RMS | {f["layout_circle_rms_mm"]:.2f} mm |

Laser-plane candidates (table-top laser points triangulated with each plane, against the table
plane from the markers; `inf` = no table-top ray meets that plane in front of the camera):

| plane | RMS (mm) | median (mm) | points |
|---|---|---|---|
{cands}

![steps](steps.png)

The step angles after the graph lean on the motor factors (sigma {MOTOR_SIGMA_DEG:g} deg per step, an
assumption): the marker-only figures are the independent measurement.
"""
    paths.append(write_text_atomic(out / "report.md", md))
    return paths
