"""The signed-distance surface (``mapping.method: sdf``, sdf16) against analytic surfaces.

A sphere and a bounded plane sampled with noise: vertex distance to the true surface (mean and
signed mean: no bias to either side), completeness (share of the true surface near the mesh),
orientation and the trim at the data's border. Checked against the closed-form surfaces, never
against the code's own earlier output.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from loopmodel.config import MappingConfig
from loopmodel.mapping.accuracy import distances_to_mesh
from loopmodel.mapping.meshing import mesh_cloud, mesh_from_points


def _cloud(points: np.ndarray, normals: np.ndarray, voxel_m: float) -> o3d.geometry.PointCloud:
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.normals = o3d.utility.Vector3dVector(normals)
    return pc.voxel_down_sample(voxel_m)


def _sphere_samples(radius_m: float, n: int, noise_m: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * radius_m + rng.normal(scale=noise_m, size=d.shape), d


@pytest.mark.parametrize("radius_m", [0.02, 0.05])
def test_sdf_sphere_vertices_lie_on_the_sphere_without_bias(radius_m: float) -> None:
    cfg = MappingConfig(method="sdf")
    pts, nrm = _sphere_samples(radius_m, 60_000, 0.0002, seed=1)
    mesh = mesh_cloud(_cloud(pts, nrm, cfg.voxel_m), cfg)
    v = np.asarray(mesh.vertices)
    err = np.linalg.norm(v, axis=1) - radius_m
    # measured (radius 20 / 50 mm): signed mean +0.013 / +0.0005 mm, mean |err| 0.015 / 0.011 mm (Poisson on the
    # same cloud: +0.008 / +0.013 mm, 0.036 mm); without the Newton step onto the field (sigma 1 cell) the vertices
    # were 0.087 / 0.035 mm inside, with the tangent-plane term alone 0.086 mm outside (radius 50 mm)
    assert abs(err.mean()) < 0.02e-3
    assert np.mean(np.abs(err)) < 0.03e-3
    assert mesh.is_watertight()
    # normals out of the sphere (the samples' normals' side)
    assert np.all(np.einsum("ij,ij->i", np.asarray(mesh.vertex_normals), v) > 0)
    # completeness: the whole true sphere within 0.25 mm of the mesh's surface (measured: at most 0.15 / 0.08 mm,
    # the chords between vertices)
    truth, _ = _sphere_samples(radius_m, 20_000, 0.0, seed=2)
    assert np.max(distances_to_mesh(truth, mesh)) < 0.25e-3


def test_sdf_plane_patch_stays_on_the_plane_and_within_the_samples() -> None:
    cfg = MappingConfig(method="sdf")
    rng = np.random.default_rng(4)
    # a 60 x 40 mm patch of the plane through c with normal n (tilted against the grid's axes)
    n = np.array([0.3, -0.2, 0.93])
    n /= np.linalg.norm(n)
    u = np.cross(n, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    c = np.array([0.011, -0.027, 0.4])
    ab = rng.uniform([-0.03, -0.02], [0.03, 0.02], size=(40_000, 2))
    pts = c + ab[:, :1] * u + ab[:, 1:] * w + rng.normal(scale=0.0002, size=(40_000, 1)) * n
    sensors = c + 0.3 * n + np.zeros_like(pts)  # a sensor on the normal's side
    mesh = mesh_from_points(pts, sensors, cfg)
    v = np.asarray(mesh.vertices)
    off = (v - c) @ n
    # measured over seeds 0-3: signed mean -0.002 ... +0.008 mm, mean |offset| 0.018 ... 0.026 mm
    assert abs(off.mean()) < 0.012e-3 and np.mean(np.abs(off)) < 0.04e-3
    # within the patch, up to the trim distance (2.5 voxels) beyond its border
    a, b = (v - c) @ u, (v - c) @ w
    trim = 2.5 * cfg.voxel_m
    assert np.all(np.abs(a) < 0.03 + trim) and np.all(np.abs(b) < 0.02 + trim)
    # covers the patch: a 2 mm grid of its inner part on the mesh
    g = np.stack(np.meshgrid(np.arange(-0.028, 0.028, 0.002), np.arange(-0.018, 0.018, 0.002)), -1).reshape(-1, 2)
    truth = c + g[:, :1] * u + g[:, 1:] * w
    assert np.max(distances_to_mesh(truth, mesh)) < 0.1e-3  # measured 0.044 ... 0.068 mm
    assert np.all(np.asarray(mesh.vertex_normals) @ n > 0.9)


def test_sdf_falls_back_to_poisson_for_a_grid_too_large(caplog: pytest.LogCaptureFixture) -> None:
    cfg = MappingConfig(method="sdf", voxel_m=1e-5, poisson_depth=6)
    pts, nrm = _sphere_samples(1.0, 2_000, 0.0, seed=0)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.normals = o3d.utility.Vector3dVector(nrm)
    with caplog.at_level("WARNING"):
        mesh = mesh_cloud(pc, cfg.model_copy(update={"trim_distance_m": 0.2}))
    assert "Poisson instead" in caplog.text and len(mesh.triangles) > 0


def test_grid_normals_match_open3d_kd_tree_search() -> None:
    """fin18: the grid search's normals are those of open3d's k-d tree search (the same nearest points).

    Stripes on a sphere (dense along, sparse across: the 12 mm radius matters there), one stripe alone
    (a line: the view made perpendicular to it) and a lone point (fewer than 3 neighbours: open3d's identity).
    """
    from loopmodel.mapping.meshing import _grid_normals, _open3d_normals

    rng = np.random.default_rng(3)
    cfg = MappingConfig()
    rows = []
    for a in np.linspace(0.0, np.pi, 40):  # stripes: great half-circles 4.5 deg apart (4 mm at 50 mm)
        t = np.linspace(0.1, np.pi - 0.1, 120)
        rows.append(np.stack([np.cos(a) * np.sin(t), np.sin(a) * np.sin(t), np.cos(t)], 1) * 0.05)
    line = np.stack([np.linspace(0.2, 0.26, 40), np.zeros(40), np.zeros(40)], 1)
    lone = np.array([[0.0, 0.3, 0.0]])
    pts = np.concatenate(rows + [line, lone]) + rng.normal(scale=1e-4, size=(40 * 120 + 41, 3))
    view = np.concatenate([pts[:-41] / np.linalg.norm(pts[:-41], axis=1, keepdims=True),
                           np.tile([[0.0, 0.6, 0.8]], (41, 1))])
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    expected = _open3d_normals(cloud, view, cfg)
    got = _grid_normals(pts, view, cfg)
    assert got is not None
    assert np.max(np.abs(got - expected)) < 1e-9
    assert abs(got[-10] @ np.array([1.0, 0.0, 0.0])) < 0.01  # the stripe alone (0.1 mm noise): across it


def test_sdf_trim_keeps_the_vertices_within_reach_of_a_sample() -> None:
    """fin18: the sdf's distance trim on the samples' cells keeps a vertex iff a sample lies within the distance."""
    from loopmodel.mapping import _sdf_kernels as k

    rng = np.random.default_rng(5)
    pts = rng.uniform(0.0, 0.05, size=(2000, 3))
    verts = rng.uniform(-0.01, 0.06, size=(3000, 3))
    h, limit = 0.003, 0.00375
    origin = pts.min(axis=0) - 4 * h
    bdims = (np.floor((pts.max(axis=0) - origin) / h).astype(np.int64) + 3 >> k.SHIFT) + 1
    bmap, blocks = k.mark_blocks(pts, origin, h, 3 * h, bdims)
    order, start = k.bucket_points(pts, origin, h, bmap, blocks.shape[0])
    got = k.near_samples(verts, pts, limit, origin, h, bmap, order, start)
    brute = np.min(np.linalg.norm(verts[:, None] - pts[None], axis=2), axis=1) <= limit
    assert np.array_equal(got, brute)
