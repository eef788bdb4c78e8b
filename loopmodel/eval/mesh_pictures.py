"""Pictures of a run's laser mesh for the evaluation report: before and after loop closure.

The run's stripes (``stripes.npz``) are placed twice — with the online poses (before any
correction) and with the final poses — each SE(3)-aligned to the ground truth by the same
alignment the trajectory evaluation used, so both meshes are in the truth's world frame and
the pictures share viewpoints. When the ground truth is a recording with a ``scene.ply``
attachment (the simulator's), the meshes are coloured by their distance to the true surface.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from loopmodel.errors import LoopmodelError
from loopmodel.eval.trajectory_metrics import Alignment
from loopmodel.types import Trajectory
from loopmodel.viz.mesh_render import Panel

logger = logging.getLogger(__name__)

#: File name of the picture in the report.
PLOT_MESH = "mesh_before_after.png"


def _aligned(traj: Trajectory, alignment: Alignment) -> Trajectory:
    return Trajectory(traj.timestamps_ns, alignment.apply(traj.world_from_cam))


def mesh_before_after_png(
    run_path: Path,
    online: Trajectory | None,
    online_alignment: Alignment | None,
    final: Trajectory,
    final_alignment: Alignment,
    gt_source: str | None,
    up: ArrayLike = (0.0, 0.0, 1.0),
) -> bytes | None:
    """The before/after mesh picture of the run at ``run_path``, seen from around ``up`` (truth's world).

    ``up``: :func:`~loopmodel.geometry.se3.world_up` of the truth (z for a simulator's, the principal
    axes of a camera-frame truth such as KITTI's). None when the run has no stripes (or they do
    not mesh).
    """

    from loopmodel.config import load_config
    from loopmodel.io.stripes_io import load_stripes
    from loopmodel.mapping.accuracy import SurfaceDistance
    from loopmodel.mapping.stripe_map import StripeMap
    from loopmodel.viz.mesh_render import before_after_png, distance_colors

    if not (run_path / "stripes.npz").is_file():
        return None
    try:
        cfg_file = run_path / "config.yaml"
        mapping = load_config(cfg_file if cfg_file.is_file() else None).mapping
        stripes = load_stripes(run_path)
        gt_mesh = _gt_mesh(gt_source)
        tracks = [("after loop closure (final poses)", final, final_alignment)]
        if online is not None and online_alignment is not None:
            tracks.insert(0, ("before loop closure (online poses)", online, online_alignment))
        meshes = []
        run_mesh = _run_mesh(run_path, final_alignment)
        for title, traj, al in tracks:
            if run_mesh is not None and traj is final:  # the run's own final mesh, moved by the alignment
                meshes.append((title, *run_mesh))
                continue
            if run_mesh is None:
                m = StripeMap.from_trajectory(_aligned(traj, al), stripes, mapping).mesh()
                meshes.append((title, np.asarray(m.vertices), np.asarray(m.triangles)))
                continue
            # made in the run's world like mesh.ply (the Poisson octree follows the frame's axes, and
            # so does the mesh's resolution), then moved by the final alignment
            R, t = final_alignment.rotation, final_alignment.translation_m
            run_from_aligned = np.eye(4)
            run_from_aligned[:3, :3], run_from_aligned[:3, 3] = R.T, -R.T @ t
            in_run = Trajectory(traj.timestamps_ns, run_from_aligned[None] @ _aligned(traj, al).world_from_cam)
            m = StripeMap.from_trajectory(in_run, stripes, mapping).mesh()
            meshes.append((title, np.asarray(m.vertices) @ R.T + t, np.asarray(m.triangles)))
        panels: list[Panel] = []
        scale_mm = None
        if gt_mesh is not None:
            to_gt = SurfaceDistance(gt_mesh)
            dists = [to_gt(v) for _, v, _ in meshes]
            scale_mm = max(1.0, float(np.percentile(np.concatenate(dists), 95)) * 1e3)
            for (title, v, t), d in zip(meshes, dists, strict=True):
                panels.append((f"{title}: mean {1e3 * d.mean():.2f} mm", v, t, distance_colors(d, scale_mm * 1e-3)))
        else:
            panels = [(title, v, t, None) for title, v, t in meshes]  # shaded grey
        return before_after_png(panels, colorbar_mm=scale_mm, up=up)
    except LoopmodelError as exc:
        logger.warning("no mesh pictures: %s", exc)
        return None


def _run_mesh(run_path: Path, alignment: Alignment) -> tuple[Any, Any] | None:
    """Vertices (V x 3, aligned world, metres) and triangles of the run's ``mesh.ply``.

    Only when it is the run's final mesh (its vertex count is the one ``metrics.json`` recorded)
    and the alignment is rigid (a scaled alignment scales the poses, not the stripes: that mesh
    is made again from the stripes). None otherwise.
    """
    import json

    path, metrics = run_path / "mesh.ply", run_path / "metrics.json"
    if abs(alignment.scale - 1.0) > 1e-12 or not path.is_file() or not metrics.is_file():
        return None
    try:
        recorded = json.loads(metrics.read_text()).get("mesh_vertices")
        from loopmodel.io.mesh_io import read_mesh

        mesh = read_mesh(path)
    except (LoopmodelError, ValueError, OSError):
        return None
    v = np.asarray(mesh.vertices)
    if recorded is None or int(recorded) != len(v):
        return None
    return v @ alignment.rotation.T + alignment.translation_m, np.asarray(mesh.triangles)


def _gt_mesh(gt_source: str | None) -> Any:
    """The true surface when the ground truth is a recording with a ``scene.ply`` attachment."""
    if not gt_source or not gt_source.lower().endswith(".mcap") or not Path(gt_source).is_file():
        return None
    from loopmodel.io.mesh_io import read_mesh

    try:
        return read_mesh(gt_source, "scene.ply")
    except LoopmodelError:
        return None
