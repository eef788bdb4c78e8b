"""The mesh of a finished run or of a saved map, as the API exports it (``loopmodel mesh`` calls it).

:func:`export_mesh` reads a results folder (its laser stripes and a trajectory), a saved (merged)
session map, or a sequence with ground truth, meshes the stripes (or converts the run's own
``mesh.ply``), writes the file and returns what it made; it prints nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from loopmodel.config import Config
from loopmodel.errors import InputError

__all__ = ["MeshExport", "export_mesh"]


@dataclass
class MeshExport:
    """A written mesh: the ``surface`` (open3d, metres), its ``path``, where it came from.

    ``placed``: what was meshed (``"S/T stripes"``; empty when converted), ``poses``: which poses
    placed them (``"final"``, ``"ground truth"``, ``"map keyframes of N sessions"``, ...),
    ``converted_from``: the run's own mesh file when it was converted, not re-meshed;
    ``camera_world``: whether the world is a first camera's (y down) rather than z up;
    ``path_poses``: the ``world_from_cam`` (N, 4, 4) that placed the stripes (None when converted).
    """

    surface: Any
    path: Path
    placed: str = ""
    poses: str = ""
    converted_from: Path | None = None
    camera_world: bool = True
    path_poses: np.ndarray | None = None


def export_mesh(
    source: str | Path,
    target: str | Path,
    fmt: str = "ply",
    trajectory: Literal["final", "online"] = "final",
    config: Config | None = None,
    remesh: bool = False,
) -> MeshExport:
    """Mesh the laser stripes of ``source`` and write ``target`` in ``fmt`` (ply, obj, stl, glb).

    ``source``: a results folder (stripes placed with its ``trajectory``; with ``final`` its own
    ``mesh.ply`` is converted unless ``remesh``), a saved session map folder (its stripes at their
    keyframe anchors, every session), or a sequence with ground truth (stripes placed with it).
    Raises :class:`InputError` when there is nothing to mesh.
    """
    from loopmodel.io.laser import load_stripes_and_poses
    from loopmodel.io.mesh_io import MESH_FORMATS, read_mesh, write_mesh
    from loopmodel.mapping.stripe_map import StripeMap

    if fmt not in MESH_FORMATS:
        raise InputError(None, f"--format must be one of {', '.join(MESH_FORMATS)}, got '{fmt}'")
    cfg = config if config is not None else Config()
    src, out = Path(source), Path(target)
    run_mesh = src / "mesh.ply"
    if trajectory == "final" and not remesh and run_mesh.is_file() and run_mesh.resolve() != out.resolve():
        # the run's own product (its final trajectory): converted, not re-meshed
        surface = read_mesh(run_mesh)
        write_mesh(out, surface, fmt)
        return MeshExport(surface, out, converted_from=run_mesh)
    if (src / "map.json").is_file():  # a saved (merged) session map: its stripes at their anchors
        from loopmodel.io.map_file import load_session_map
        from loopmodel.mapping.final import posed_stripes_mesh

        session_map = load_session_map(src)
        map_stripes, map_poses = session_map.stripes_with_poses()
        surface = posed_stripes_mesh(map_stripes, map_poses, cfg.mapping)
        if surface is None:
            raise InputError(src, "the map holds no laser stripes to mesh")
        sessions = len(set(session_map.session.tolist()))
        write_mesh(out, surface, fmt)
        placed = f"{len(map_stripes)} stripes"
        return MeshExport(surface, out, placed, f"map keyframes of {sessions} sessions", path_poses=map_poses)
    stripes, traj, poses = load_stripes_and_poses(src, trajectory, cfg.sequence, cfg.mapping)
    smap = StripeMap.from_trajectory(traj, stripes, cfg.mapping)
    smap.check_nonempty()
    surface = smap.mesh()
    write_mesh(out, surface, fmt)
    camera_world = poses != "ground truth" or bool(np.allclose(traj.world_from_cam[0], np.eye(4), atol=1e-6))
    return MeshExport(
        surface,
        out,
        f"{int(smap.placed_mask.sum())}/{smap.stripe_count} stripes",
        poses,
        None,
        camera_world,
        traj.world_from_cam,
    )
