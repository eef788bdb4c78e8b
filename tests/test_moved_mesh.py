"""The final mesh started before the frames' re-solve and moved to the re-solved frames (issue 32, finish11)."""

from __future__ import annotations

import numpy as np

from loopmodel.config import MappingConfig
from loopmodel.geometry.se3 import make_pose, so3_exp
from loopmodel.mapping.final import MovedMeshJob, VertexMover, final_mesh
from loopmodel.types import StripeProfile, Trajectory


def _sphere_scan(n: int = 24) -> tuple[list[StripeProfile], Trajectory]:
    """Stripes of a 0.2 m sphere 0.8 m in front of a camera that turns about it (seeded), and its frames."""
    rng = np.random.default_rng(5)
    stamps = np.arange(n, dtype=np.int64) * 1_000_000
    poses = []
    for i in range(n):  # the camera on a 0.8 m circle about the sphere's centre (0, 0, 0.8), looking at it
        a = 0.6 * i / n
        R = so3_exp(np.array([0.0, -a, 0.0]))
        centre = np.array([0.0, 0.0, 0.8])
        poses.append(make_pose(R, centre - R @ np.array([0.0, 0.0, 0.8])))
    stripes = []
    for i in range(n):
        d = rng.normal(size=(600, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d = d[d[:, 2] < 0]  # the half facing the camera, in the camera's frame
        stripes.append(StripeProfile(int(stamps[i]), np.array([0.0, 0.0, 0.8]) + 0.2 * d))
    return stripes, Trajectory(stamps, np.stack(poses))


def test_vertex_mover_follows_a_translation_exactly_and_a_small_turn_closely() -> None:
    rng = np.random.default_rng(2)
    pts = rng.uniform(-0.1, 0.1, (5000, 3))
    verts = rng.uniform(-0.09, 0.09, (300, 3))
    shift = np.array([0.0012, -0.0005, 0.0008])
    moved = VertexMover(pts, pts + shift).moved(verts)
    np.testing.assert_allclose(moved, verts + shift, atol=1e-12)
    # a turn of 0.002 rad about the origin: each vertex moves as the points next to it (about 6 mm
    # apart here), so off by at most the turn times their distance (measured 0.022 mm; the moves up to 0.25 mm)
    R = so3_exp(np.array([0.0, 0.0, 0.002]))
    moved = VertexMover(pts, pts @ R.T).moved(verts)
    err = np.linalg.norm(moved - verts @ R.T, axis=1)
    assert err.max() < 0.002 * 0.015


def test_moved_mesh_job_moves_the_first_mesh_with_the_frames() -> None:
    """Every frame moved by one translation: the moved mesh is the first placement's mesh translated."""
    cfg = MappingConfig(voxel_m=0.004, normal_radius_m=0.016)
    stripes, traj = _sphere_scan()
    first, _ = final_mesh(stripes, traj, cfg)  # made here, independently of the job
    assert first is not None and len(first.vertices) > 500
    shift = np.array([0.002, 0.001, -0.0015])
    later = Trajectory(traj.timestamps_ns, traj.world_from_cam.copy())
    later.world_from_cam[:, :3, 3] += shift
    mesh, metrics = MovedMeshJob(stripes, traj, cfg).moved_to(later).result()
    assert metrics["final_mesh_moved"] is True
    np.testing.assert_allclose(np.asarray(mesh.vertices), np.asarray(first.vertices) + shift, atol=1e-9)
    np.testing.assert_array_equal(np.asarray(mesh.triangles), np.asarray(first.triangles))
    assert abs(metrics["final_mesh_move_mm_max"] - 1e3 * np.linalg.norm(shift)) < 1e-6


def test_moved_mesh_job_meshes_again_when_the_stripes_placed_differ() -> None:
    """A later trajectory that no longer reaches the last stripe: the mesh of the later placement itself."""
    cfg = MappingConfig(voxel_m=0.004, normal_radius_m=0.016)
    stripes, traj = _sphere_scan()
    shorter = Trajectory(traj.timestamps_ns[:-1], traj.world_from_cam[:-1])
    mesh, metrics = MovedMeshJob(stripes, traj, cfg).moved_to(shorter).result()
    expected, _ = final_mesh(stripes, shorter, cfg)
    assert "final_mesh_moved" not in metrics
    np.testing.assert_allclose(np.asarray(mesh.vertices), np.asarray(expected.vertices), atol=1e-12)
