"""Laser-stripe integration, extraction, meshing, export and mesh accuracy (issue 8).

Ground truth comes from ray casting open3d primitives (loopmodel.mapping.synthetic) and from
closed-form motions; nothing is compared with the code's own earlier output.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from loopmodel.config import MappingConfig
from loopmodel.errors import InputError, LoopmodelError
from loopmodel.geometry.se3 import interpolate_pose, invert_pose, make_pose, se3_exp, so3_exp
from loopmodel.io.mesh_io import MESH_FORMATS, UNITS_NOTE, read_mesh, write_mesh
from loopmodel.io.stripes_io import load_stripes, save_stripes
from loopmodel.io.trajectory_io import write_trajectory
from loopmodel.mapping import LightPlane, StripeMap, extract_laser_peaks, stripe_from_image, triangulate_with_plane
from loopmodel.mapping.accuracy import distances_to_mesh, mesh_accuracy
from loopmodel.mapping.synthetic import cast_stripe, default_light_plane, orbit_pose, orbit_scan
from loopmodel.types import StripeProfile, Trajectory

SPHERE_R = 0.06


@pytest.fixture(scope="module")
def sphere() -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh.create_sphere(SPHERE_R, 120)


@pytest.fixture(scope="module")
def sphere_scan(sphere: o3d.geometry.TriangleMesh) -> tuple[Trajectory, list[StripeProfile]]:
    return orbit_scan(sphere, frames=150, stripes_per_frame=2, rays=300)


def _gt_motion(t_s: np.ndarray) -> np.ndarray:
    """Rotation at a constant rate about a fixed body axis, translation linear in time.

    The geodesic/linear interpolation between any two samples is exact.
    """
    R0 = so3_exp([0.3, -0.2, 0.1])
    w = np.array([0.4, 1.1, -0.7])
    a, b = np.array([0.1, -0.2, 0.5]), np.array([0.05, 0.02, -0.03])
    return np.stack([make_pose(R0 @ so3_exp(w * t), a + b * t) for t in np.atleast_1d(t_s)])


def _unit_stripe(t_ns: int, n: int = 5) -> StripeProfile:
    y = np.linspace(-0.02, 0.02, n)
    return StripeProfile(t_ns, np.column_stack([np.full(n, 0.01), y, np.full(n, 0.3)]))


# --------------------------------------------------------------------------- poses
def test_interpolated_poses_equal_ground_truth_and_stay_on_se3(rng: np.random.Generator) -> None:
    frame_t_ns = np.cumsum(rng.integers(20_000_000, 45_000_000, size=30)).astype(np.int64)
    gt_frames = _gt_motion(frame_t_ns * 1e-9)
    m = StripeMap()
    # keyframe-relative bookkeeping: a keyframe every 4 frames, frames given relative to it
    for i, (t, T) in enumerate(zip(frame_t_ns, gt_frames, strict=True)):
        kf = i // 4
        if i % 4 == 0:
            m.poses.set_keyframe(kf, T)
        m.poses.add_frame(int(t), kf_id=kf, kf_from_cam=invert_pose(_gt_motion(frame_t_ns[4 * kf] * 1e-9)[0]) @ T)
    # stripes at every frame time and at random times in between
    between = rng.integers(frame_t_ns[0], frame_t_ns[-1], size=200)
    stripe_t = np.concatenate([frame_t_ns, between])
    for t in stripe_t:
        m.add(_unit_stripe(int(t)))
    assert m.placed_mask.all()
    poses = m.stripe_poses()
    gt = _gt_motion(stripe_t * 1e-9)
    np.testing.assert_allclose(poses[: len(frame_t_ns)], gt_frames, atol=1e-12)
    np.testing.assert_allclose(poses, gt, atol=1e-9)
    R = poses[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_array_equal(poses[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (len(poses), 4)))
    # agrees with the scalar interpolation of geometry.se3
    k = len(frame_t_ns) + 7
    i1 = int(np.searchsorted(frame_t_ns, stripe_t[k]))
    alpha = (stripe_t[k] - frame_t_ns[i1 - 1]) / (frame_t_ns[i1] - frame_t_ns[i1 - 1])
    np.testing.assert_allclose(poses[k], interpolate_pose(gt_frames[i1 - 1], gt_frames[i1], alpha), atol=1e-12)
    # world points are the stripe points moved by the stripe pose
    s = m.stripes()[k].points_in_cam
    np.testing.assert_allclose(m.world_points(k), s @ gt[k][:3, :3].T + gt[k][:3, 3], atol=1e-9)


def test_stripes_wait_for_a_bracketing_frame_and_gaps_are_not_bridged() -> None:
    m = StripeMap(MappingConfig(max_stripe_gap_ns=100_000_000))
    m.poses.add_frame(0, np.eye(4))
    m.add(_unit_stripe(30_000_000))  # after the last frame: waits
    assert not m.placed_mask[0]
    m.poses.add_frame(50_000_000, make_pose(np.eye(3), [0.01, 0, 0]))
    assert m.placed_mask[0]
    np.testing.assert_allclose(m.stripe_poses()[0][:3, 3], [0.006, 0, 0], atol=1e-15)
    m.poses.add_frame(500_000_000, np.eye(4))
    m.add(_unit_stripe(300_000_000))  # inside a 450 ms gap: not placed
    m.add(_unit_stripe(-5))  # before the first frame: not placed
    assert m.placed_mask.tolist() == [True, False, False]


# ----------------------------------------------------------------- corrections
def test_moving_one_keyframe_moves_exactly_the_stripes_it_governs(rng: np.random.Generator) -> None:
    frame_t_ns = np.arange(40, dtype=np.int64) * 33_000_000
    gt = _gt_motion(frame_t_ns * 1e-9)
    m = StripeMap()
    kf_of = np.arange(40) // 5
    for i, t in enumerate(frame_t_ns):
        if i % 5 == 0:
            m.poses.set_keyframe(int(kf_of[i]), gt[i])
        m.poses.add_frame(int(t), kf_id=int(kf_of[i]), kf_from_cam=invert_pose(gt[5 * kf_of[i]]) @ gt[i])
    stripe_t = np.concatenate([frame_t_ns, rng.integers(0, frame_t_ns[-1], size=300)])
    for t in stripe_t:
        m.add(_unit_stripe(int(t)))
    before = [m.world_points(s) for s in range(m.stripe_count)]
    kf = 3  # frames 15..19
    correction = se3_exp([0.004, -0.002, 0.003, 0.01, 0.0, -0.02])
    new_world_from_kf = correction @ gt[15]
    moved = m.stripes_of_frames(m.poses.update_keyframes({kf: new_world_from_kf}))
    # independent: a stripe depends on keyframe 3 iff a neighbouring frame is one of 15..19,
    # i.e. its time lies strictly between frame 14 and frame 20
    expected = np.flatnonzero((stripe_t > frame_t_ns[14]) & (stripe_t < frame_t_ns[20]))
    np.testing.assert_array_equal(np.sort(moved), expected)
    corrected = gt.copy()
    corrected[15:20] = correction @ gt[15:20]
    for s in range(m.stripe_count):
        after = m.world_points(s)
        if s in set(expected.tolist()):
            t = stripe_t[s]
            i1 = int(np.searchsorted(frame_t_ns, t))
            if frame_t_ns[i1] == t:
                T = corrected[i1]
            else:
                a = (t - frame_t_ns[i1 - 1]) / (frame_t_ns[i1] - frame_t_ns[i1 - 1])
                T = interpolate_pose(corrected[i1 - 1], corrected[i1], a)
            p = m.stripes()[s].points_in_cam
            np.testing.assert_allclose(after, p @ T[:3, :3].T + T[:3, 3], atol=1e-12)
            assert np.abs(after - before[s]).max() > 1e-4
        else:
            np.testing.assert_array_equal(after, before[s])
    assert set(m.stripes_governed_by([kf]).tolist()) == set(expected.tolist())


def test_update_poses_retransforms_only_changed_frames(sphere_scan: tuple[Trajectory, list[StripeProfile]]) -> None:
    traj, stripes = sphere_scan
    m = StripeMap.from_trajectory(traj, stripes)
    before = m.world_points().copy()
    changed = traj.world_from_cam.copy()
    changed[40:43] = se3_exp([0.002, 0, 0, 0, 0.01, 0]) @ changed[40:43]
    moved = m.stripes_of_frames(m.poses.update_poses(Trajectory(traj.timestamps_ns, changed)))
    st = np.array([s.timestamp_ns for s in stripes])
    expected = np.flatnonzero((st > traj.timestamps_ns[39]) & (st < traj.timestamps_ns[43]))
    np.testing.assert_array_equal(np.sort(moved), expected)
    after = m.world_points()
    counts = np.array([s.points_in_cam.shape[0] for s in stripes])
    owner = np.repeat(np.arange(len(stripes)), counts)
    untouched = ~np.isin(owner, expected)
    np.testing.assert_array_equal(after[untouched], before[untouched])
    assert np.all(np.abs(after[~untouched] - before[~untouched]).max(axis=1) > 0)


# ------------------------------------------------------------------------ meshing
def test_mesh_with_ground_truth_poses_lies_within_half_a_millimetre(
    sphere: o3d.geometry.TriangleMesh, sphere_scan: tuple[Trajectory, list[StripeProfile]]
) -> None:
    traj, stripes = sphere_scan
    m = StripeMap.from_trajectory(traj, stripes, MappingConfig(voxel_m=0.001))
    # the placed stripe points themselves are on the surface (interpolation on an orbit)
    assert distances_to_mesh(m.world_points(), sphere).max() < 1e-4
    mesh = m.mesh()
    acc = mesh_accuracy(mesh, sphere)
    assert acc.vertices > 1000
    assert acc.mean_mm < 0.15 and acc.p95_mm < 0.5, acc
    # the scanned band of the sphere is covered
    band = mesh_accuracy(mesh, sphere, region_min=np.array([-1, -0.02, -1]), region_max=np.array([1, 0.02, 1]))
    assert band.completeness > 0.95, band
    # normals face the sensor side: outwards on a sphere seen from outside
    v = np.asarray(mesh.vertices)
    n = np.asarray(mesh.vertex_normals)
    assert np.mean(np.einsum("ij,ij->i", n, v) > 0) > 0.99


def test_ball_pivoting_option(
    sphere: o3d.geometry.TriangleMesh, sphere_scan: tuple[Trajectory, list[StripeProfile]]
) -> None:
    traj, stripes = sphere_scan
    m = StripeMap.from_trajectory(traj, stripes[::2], MappingConfig(voxel_m=0.0015, method="ball_pivoting"))
    acc = mesh_accuracy(m.mesh(), sphere)
    assert acc.vertices > 500 and acc.p95_mm < 0.5, acc


def test_live_mesh_updates_only_affected_blocks(
    sphere: o3d.geometry.TriangleMesh, sphere_scan: tuple[Trajectory, list[StripeProfile]]
) -> None:
    traj, stripes = sphere_scan
    cfg = MappingConfig(voxel_m=0.003, chunk_m=0.08, normal_radius_m=0.01)
    stripes = stripes[::2]
    m = StripeMap(cfg)
    kf_of = np.arange(len(traj)) // 10
    for i, (t, T) in enumerate(zip(traj.timestamps_ns, traj.world_from_cam, strict=True)):
        if i % 10 == 0:
            m.poses.set_keyframe(int(kf_of[i]), T)
        m.poses.add_frame(int(t), kf_id=int(kf_of[i]), kf_from_cam=invert_pose(traj.world_from_cam[10 * kf_of[i]]) @ T)
    half = len(stripes) // 2
    m.add_many(stripes[:half])
    first = m.update_live_mesh()
    assert len(first.triangles) > 0 and not m.dirty_blocks
    m.add_many(stripes[half:])
    full = m.update_live_mesh()
    assert len(full.triangles) > len(first.triangles)
    acc = mesh_accuracy(full, sphere)
    assert acc.p95_mm < 0.5, acc
    # a correction of keyframe 2 dirties exactly the blocks its stripes left and entered
    gov = m.stripes_governed_by([2])
    old = np.concatenate([m.world_points(s) for s in gov])
    m.poses.update_keyframes({2: se3_exp([0.003, 0, 0, 0, 0, 0]) @ traj.world_from_cam[20]})
    new = np.concatenate([m.world_points(s) for s in gov])
    keys = {tuple(k) for k in np.floor(np.vstack([old, new]) / cfg.chunk_m).astype(int).tolist()}
    assert m.dirty_blocks == keys
    all_keys = {tuple(k) for k in np.floor(m.world_points() / cfg.chunk_m).astype(int).tolist()}
    assert len(keys) < len(all_keys)
    assert len(m.update_live_mesh().triangles) > 0 and not m.dirty_blocks


def test_block_rows_by_codes_equal_numpys_row_functions(rng: np.random.Generator) -> None:
    """live20: the live update's unique blocks and block membership by one int64 a row, as numpy's row-wise forms."""
    from loopmodel.mapping.meshing import _rows_in, _unique_rows

    for n, span in ((1, 3), (500, 4), (20_000, 40)):
        rows = rng.integers(-span, span, size=(n, 3)) + rng.integers(-(1 << 20), 1 << 20, size=3)
        uniq, inverse = _unique_rows(rows)
        want, want_inv = np.unique(rows, axis=0, return_inverse=True)
        np.testing.assert_array_equal(uniq, want)
        np.testing.assert_array_equal(inverse, want_inv.reshape(-1))
        table = rows[rng.integers(0, n, size=max(n // 3, 1))] + rng.integers(0, 2, size=(max(n // 3, 1), 3))
        in_table = set(map(tuple, table.tolist()))
        np.testing.assert_array_equal(_rows_in(rows, table), [tuple(r) in in_table for r in rows.tolist()])


# --------------------------------------------------------------------- extraction
def _render_laser_image(
    u_of_row: np.ndarray,
    rows: np.ndarray,
    rng: np.random.Generator,
    size: tuple[int, int] = (640, 480),
    sigma_px: float = 1.3,
) -> np.ndarray:
    w, h = size
    img = np.full((h, w), 15.0)
    uu = np.arange(w)[None, :]
    img[rows] += 200.0 * np.exp(-0.5 * ((uu - u_of_row[:, None]) / sigma_px) ** 2)
    img += rng.normal(0, 0.5, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("method", ["cog", "gauss"])
def test_stripe_extraction_recovers_profiles_to_a_tenth_of_a_pixel(
    sphere: o3d.geometry.TriangleMesh, rng: np.random.Generator, method: str
) -> None:
    from loopmodel.mapping.synthetic import raycasting_scene

    K = np.array([[500.0, 0, 320.0], [0, 500.0, 240.0], [0, 0, 1]])
    T = orbit_pose(0.0, 0.3, 1.0, -0.05)
    dense = cast_stripe(raycasting_scene(sphere), T, 0, rays=6000).points_in_cam
    uvw = dense @ K.T
    u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
    order = np.argsort(v)
    u, v = u[order], v[order]
    rows = np.arange(int(np.ceil(v[0])) + 1, int(np.floor(v[-1])))
    u_true = np.interp(rows, v, u)
    img = _render_laser_image(u_true, rows, rng)
    uv = extract_laser_peaks(img, axis="rows", min_contrast=30, window_px=3, method=method)
    np.testing.assert_array_equal(uv[:, 1], rows)  # one peak per lit row, none elsewhere
    err = np.abs(uv[:, 0] - u_true)
    assert err.max() < 0.1, err.max()
    if method == "cog":
        # refined across the line: nearly as close on this image, whose rows are drawn one by one
        # (the ideal of per-row centres) and whose arc turns to 40 deg of the rows at its ends
        # (measured max 0.126 px there)
        across = extract_laser_peaks(img, axis="rows", min_contrast=30, window_px=3, method=method, across_line=True)
        np.testing.assert_array_equal(across[:, 1], rows)
        assert np.abs(across[:, 0] - u_true).max() < 0.15
    plane = default_light_plane()
    assert np.abs(plane.signed_distance_m(dense)).max() < 1e-6
    pts = triangulate_with_plane(uv, K, plane)
    assert pts.shape == (rows.size, 3)
    assert np.abs(plane.signed_distance_m(pts)).max() < 1e-9
    world = pts @ T[:3, :3].T + T[:3, 3]
    assert distances_to_mesh(world, sphere).mean() < 1e-4  # 0.1 mm
    n, p0 = plane.normal_in_cam, -plane.d_m * plane.normal_in_cam
    cfg = MappingConfig(
        peak_axis="rows",
        peak_min_contrast=30,
        peak_method=method,
        peak_window_px=3,
        peak_smooth_along_px=0.0,
        peak_local_background=False,
        peak_across_line=False,  # the settings of the extract_laser_peaks call above
        laser_plane_point_in_cam_m=p0.tolist(),
        laser_plane_normal_in_cam=n.tolist(),
    )
    profile = stripe_from_image(img, 7, K, config=cfg)
    assert profile.timestamp_ns == 7
    np.testing.assert_allclose(profile.points_in_cam, pts, atol=1e-12)
    # a dark image gives no peaks; a 3-channel image works like grey
    assert extract_laser_peaks(np.full((50, 60), 40, np.uint8), min_contrast=10).shape == (0, 2)
    bgr = np.dstack([img // 4, img // 4, img])
    np.testing.assert_allclose(extract_laser_peaks(bgr, axis="rows", min_contrast=30, method=method), uv)


def test_light_plane_triangulation_matches_ray_plane_geometry() -> None:
    plane = LightPlane.from_point_normal([0.05, 0, 0.4], [1.0, 0.2, 0.5])
    K = np.array([[450.0, 0, 300.0], [0, 460.0, 200.0], [0, 0, 1]])
    p_true = np.array([[0.05, 0.0, 0.4], [0.0, 0.05, 0.5 - 0.02]])
    p_true[1, 2] = -(plane.d_m + plane.normal_in_cam[:2] @ p_true[1, :2]) / plane.normal_in_cam[2]
    uv = (p_true @ K.T)[:, :2] / p_true[:, 2:]
    np.testing.assert_allclose(triangulate_with_plane(uv, K, plane), p_true, atol=1e-12)


# ------------------------------------------------------------------------ export
def test_every_export_format_reads_back_with_the_same_vertex_count(tmp_path: Path) -> None:
    mesh = o3d.geometry.TriangleMesh.create_torus(0.1, 0.03, 40, 20)
    mesh.compute_vertex_normals()
    for fmt in MESH_FORMATS:
        out = write_mesh(tmp_path / f"m.{fmt}", mesh, fmt)
        back = o3d.io.read_triangle_mesh(str(out))
        if fmt == "stl":  # STL stores three corners per triangle
            back.remove_duplicated_vertices()
        assert len(back.vertices) == len(mesh.vertices), fmt
        assert len(back.triangles) == len(mesh.triangles), fmt
        np.testing.assert_allclose(
            np.sort(np.asarray(back.vertices), axis=0), np.sort(np.asarray(mesh.vertices), axis=0), atol=1e-6
        )
    head = (tmp_path / "m.ply").read_bytes()[:400]
    assert b"binary_little_endian" in head and f"comment {UNITS_NOTE}".encode() in head
    assert not list(tmp_path.glob(".*tmp*"))


def test_stripes_file_round_trip(tmp_path: Path, sphere_scan: tuple[Trajectory, list[StripeProfile]]) -> None:
    _, stripes = sphere_scan
    save_stripes(tmp_path / "stripes.npz", stripes[:20])
    back = load_stripes(tmp_path)
    assert [s.timestamp_ns for s in back] == [s.timestamp_ns for s in stripes[:20]]
    for a, b in zip(back, stripes[:20], strict=True):
        np.testing.assert_allclose(a.points_in_cam, b.points_in_cam, atol=1e-7)


# ------------------------------------------------------------------ accuracy / CLI
def test_mesh_accuracy_of_a_shifted_plane() -> None:
    plane = o3d.geometry.TriangleMesh.create_box(0.2, 0.2, 1e-9)  # two faces at z=0 (and 1e-9)
    shifted = o3d.geometry.TriangleMesh(plane).translate([0, 0, 0.001])
    acc = mesh_accuracy(shifted, plane, gt_samples=5000)
    assert acc.mean_mm == pytest.approx(1.0, abs=1e-3) and acc.p95_mm == pytest.approx(1.0, abs=1e-3)
    assert acc.completeness == 1.0
    far = o3d.geometry.TriangleMesh(plane).translate([0, 0, 0.003])
    assert mesh_accuracy(far, plane, gt_samples=5000).completeness == 0.0


def _results_dir(tmp: Path, traj: Trajectory, stripes: list[StripeProfile]) -> Path:
    d = tmp / "run"
    d.mkdir()
    write_trajectory(d / "trajectory_final.tum", traj, "tum")
    save_stripes(d / "stripes.npz", stripes)
    return d


def test_cli_mesh_writes_each_format(tmp_path: Path, sphere_scan: tuple[Trajectory, list[StripeProfile]]) -> None:
    from loopmodel.cli import main

    traj, stripes = sphere_scan
    d = _results_dir(tmp_path, traj, stripes[::3])
    assert main(["mesh", str(d)]) == 0
    ply = read_mesh(d / "mesh.ply")
    assert len(ply.triangles) > 100
    assert main(["mesh", str(d), "--format", "obj", "--out", str(tmp_path / "x.obj")]) == 0
    assert len(read_mesh(tmp_path / "x.obj").vertices) == len(ply.vertices)


def test_export_mesh_api_meshes_the_stripes_with_the_runs_poses(
    tmp_path: Path, sphere: o3d.geometry.TriangleMesh, sphere_scan: tuple[Trajectory, list[StripeProfile]]
) -> None:
    """``loopmodel.export_mesh`` (what ``loopmodel mesh`` calls): the stripes placed with the run's trajectory.

    The written surface lies on the true sphere (mean vertex distance 0.05 mm); a second export
    converts the run's own mesh.ply, not re-meshing it.
    """
    import loopmodel

    traj, stripes = sphere_scan
    d = _results_dir(tmp_path, traj, stripes[::3])
    made = loopmodel.export_mesh(d, d / "mesh.ply")
    assert made.converted_from is None and made.poses == "trajectory_final.tum" and made.placed.endswith("stripes")
    assert len(read_mesh(d / "mesh.ply").vertices) == len(made.surface.vertices) > 100
    err_m = distances_to_mesh(np.asarray(made.surface.vertices), sphere)
    assert err_m.mean() < 2e-4  # measured 0.050 mm
    again = loopmodel.export_mesh(d, tmp_path / "x.stl", "stl")
    assert again.converted_from == d / "mesh.ply" and len(again.surface.vertices) == len(made.surface.vertices)
    with pytest.raises(InputError, match="--format"):
        loopmodel.export_mesh(d, tmp_path / "x.xyz", "xyz")


def test_bad_input_gives_clear_errors_and_no_mesh_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from loopmodel.cli import main

    m = StripeMap()
    m.poses.add_frame(0, np.eye(4))
    with pytest.raises(InputError, match="no points"):
        m.add(StripeProfile(1, np.zeros((0, 3))))
    bad = np.ones((4, 3))
    bad[2, 1] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        m.add(StripeProfile(2, bad))
    with pytest.raises(LoopmodelError, match="no placed laser stripes"):
        m.mesh()
    with pytest.raises(InputError, match="empty mesh"):
        write_mesh(tmp_path / "e.ply", o3d.geometry.TriangleMesh())
    assert not (tmp_path / "e.ply").exists()
    traj = Trajectory(np.array([0, 10**8]), np.stack([np.eye(4), np.eye(4)]))
    # results folder without stripes
    d = tmp_path / "nostripes"
    d.mkdir()
    write_trajectory(d / "trajectory_final.tum", traj, "tum")
    assert main(["mesh", str(d)]) == 2
    assert "stripes" in capsys.readouterr().err
    assert not (d / "mesh.ply").exists()
    # empty stripe stream
    save_stripes(d / "stripes.npz", [])
    assert main(["mesh", str(d)]) == 2
    assert "no laser stripes" in capsys.readouterr().err
    assert not (d / "mesh.ply").exists()
    # stripes with NaN in the file
    save_stripes(d / "stripes.npz", [StripeProfile(5, bad)])
    assert main(["mesh", str(d)]) == 2
    assert "non-finite" in capsys.readouterr().err
    assert not list(d.glob("mesh*")) and not list(d.glob(".mesh*"))


def test_stripe_extraction_on_the_simulators_laser_images(rng: np.random.Generator) -> None:
    """Laser-line images drawn by the simulator (``loopmodel.sim.laser.draw_laser_image``).

    For the simulator's default light plane; extraction must recover the drawn profile.
    """
    laser = pytest.importorskip("loopmodel.sim.laser")
    import cv2

    from loopmodel.config import SimLaserConfig
    from loopmodel.geometry.camera import CentralCamera
    from loopmodel.mapping.synthetic import raycasting_scene

    lc = SimLaserConfig()
    plane_sim = laser.LaserPlane.create(lc.origin_in_cam_m, lc.normal_in_cam, lc.fan_deg, 5000)
    plane = LightPlane.from_point_normal(lc.origin_in_cam_m, lc.normal_in_cam)
    # the mapping configuration's default light plane is the simulator's
    cfg_plane = LightPlane.from_config(MappingConfig())
    np.testing.assert_allclose(cfg_plane.normal_in_cam, plane.normal_in_cam, atol=1e-12)
    assert cfg_plane.d_m == pytest.approx(plane.d_m, abs=1e-12)
    K = np.array([[500.0, 0, 320.0], [0, 500.0, 240.0], [0, 0, 1]])
    cam = CentralCamera.from_K(K)
    # a sphere where the light plane crosses the optical axis, camera at the origin
    z0 = -plane.d_m / plane.normal_in_cam[2] if abs(plane.normal_in_cam[2]) > 1e-6 else 0.4
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.06, 160).translate([0.0, 0.0, z0])
    scene = raycasting_scene(sphere)
    o = np.asarray(lc.origin_in_cam_m, float)
    d = plane_sim.directions_in_cam()
    rays = np.hstack([np.repeat(o[None], d.shape[0], 0), d]).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(float)
    p = o + d[np.isfinite(t)] * t[np.isfinite(t), None]
    dist = np.linalg.norm(p, axis=1)
    sight = np.hstack([np.zeros_like(p), p / dist[:, None]]).astype(np.float32)
    p = p[scene.cast_rays(o3d.core.Tensor(sight))["t_hit"].numpy() > dist - 1e-4]
    assert p.shape[0] > 500
    texture = cv2.GaussianBlur(rng.random((480, 640)).astype(np.float32), (0, 0), 4.0)
    texture = (255 * (texture - texture.min()) / np.ptp(texture)).astype(np.uint8)
    img = laser.draw_laser_image(texture, p, cam)
    uv = cam.project(p)
    # one peak per row for a (near-)vertical line, per column otherwise; `a` runs along the
    # line (the integer coordinate), `b` across it (the sub-pixel one)
    vertical = np.ptp(uv[:, 1]) > np.ptp(uv[:, 0])
    axis, ia, ib = ("rows", 1, 0) if vertical else ("columns", 0, 1)
    assert axis == MappingConfig().peak_axis  # the configured axis suits the simulator's plane
    order = np.argsort(uv[:, ia])
    a_t, b_t = uv[order, ia], uv[order, ib]
    peaks = extract_laser_peaks(img, axis=axis, min_contrast=60, window_px=3, method="cog")
    inner = (peaks[:, ia] > a_t[0] + 3) & (peaks[:, ia] < a_t[-1] - 3)
    assert inner.sum() > 50
    err = np.abs(peaks[inner, ib] - np.interp(peaks[inner, ia], a_t, b_t))
    # the simulator's line has a Gaussian cross-section centred on the projected profile:
    # the extracted sub-pixel positions recover the profile to 0.1 px (textured background,
    # 8-bit quantisation)
    assert np.median(err) < 0.05 and np.quantile(err, 0.95) < 0.1 and err.max() < 0.15, (
        np.median(err),
        np.quantile(err, 0.95),
        err.max(),
    )
    # depth sensitivity: a few mm per pixel at this range and laser offset
    pts = triangulate_with_plane(peaks[inner], K, plane)
    assert distances_to_mesh(pts, sphere).mean() < 1e-3


def test_mesh_error_metrics_and_ground_truth_from_an_mcap_attachment(
    tmp_path: Path, sphere: o3d.geometry.TriangleMesh, sphere_scan: tuple[Trajectory, list[StripeProfile]]
) -> None:
    from loopmodel.io.mcap_io import McapSequenceWriter
    from loopmodel.mapping.accuracy import mesh_error_metrics
    from loopmodel.types import StereoCalibration

    traj, stripes = sphere_scan
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    cal = StereoCalibration(K, K, make_pose(np.eye(3), [-0.06, 0, 0]), (640, 480))
    ply = tmp_path / "scene.ply"
    o3d.io.write_triangle_mesh(str(ply), sphere)
    with McapSequenceWriter(tmp_path / "s.mcap", cal) as w:
        w.add_attachment("scene.ply", ply.read_bytes(), "application/x-ply")
    gt_mesh = read_mesh(tmp_path / "s.mcap")
    assert len(gt_mesh.vertices) == len(sphere.vertices)
    with pytest.raises(InputError, match="object.ply"):
        read_mesh(tmp_path / "s.mcap", attachment="object.ply")
    # "before": every pose shifted by 1.5 mm along +x
    shifted = traj.world_from_cam.copy()
    shifted[:, 0, 3] += 0.0015
    cfg = MappingConfig(voxel_m=0.003, normal_radius_m=0.01)
    m = mesh_error_metrics(stripes[::4], {"gt": traj, "before": Trajectory(traj.timestamps_ns, shifted)}, gt_mesh, cfg)
    assert m["mesh_err_gt_mm"] < 0.2 < m["mesh_err_before_mm"]
    assert 0.3 < m["mesh_err_before_mm"] < 1.5 and m["mesh_err_before_mm_p95"] < 1.6
    keys = {f"mesh_err_{n}_mm" for n in ("gt", "before")} | {f"mesh_err_{n}_mm_p95" for n in ("gt", "before")}
    assert set(m) == keys | {"mesh_completeness_gt", "mesh_completeness_before"}


def test_batch_interpolation_matches_the_scalar_one(rng: np.random.Generator) -> None:
    from loopmodel.geometry.se3 import interpolate_poses

    n = 200
    T0 = np.stack([se3_exp(rng.normal(size=6)) for _ in range(n)])
    # relative rotations up to nearly pi (the geodesic is unique below pi)
    angles = np.concatenate([rng.uniform(0, 3.1, n - 3), [0.0, 1e-9, 3.14]])
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    T1 = np.stack([T0[i] @ make_pose(so3_exp(axes[i] * angles[i]), rng.normal(size=3)) for i in range(n)])
    alpha = rng.uniform(0, 1, n)
    batch = interpolate_poses(T0, T1, alpha)
    for i in range(n):
        np.testing.assert_allclose(batch[i], interpolate_pose(T0[i], T1[i], alpha[i]), atol=1e-9)
    np.testing.assert_allclose(interpolate_poses(T0, T1, np.zeros(n)), T0, atol=1e-12)
    np.testing.assert_allclose(interpolate_poses(T0, T1, np.ones(n)), T1, atol=1e-9)


def test_cli_mesh_of_a_sequence_with_ground_truth(
    tmp_path: Path, sphere: o3d.geometry.TriangleMesh, sphere_scan: tuple[Trajectory, list[StripeProfile]]
) -> None:
    from loopmodel.cli import main
    from loopmodel.io.mcap_io import McapSequenceWriter
    from loopmodel.types import StereoCalibration, StereoFrame

    traj, stripes = sphere_scan
    K = np.array([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]])
    cal = StereoCalibration(K, K, make_pose(np.eye(3), [-0.06, 0, 0]), (16, 16))
    seq = tmp_path / "scan.mcap"
    ply = tmp_path / "scene.ply"
    o3d.io.write_triangle_mesh(str(ply), sphere)
    img = np.zeros((16, 16), np.uint8)
    with McapSequenceWriter(seq, cal, image_format="raw") as w:
        for i, t in enumerate(traj.timestamps_ns[::2]):
            w.write_frame(StereoFrame(int(t), img, img, i))
        w.write_trajectory(traj)
        for s in stripes[::3]:
            w.write_stripe(s)
        w.add_attachment("scene.ply", ply.read_bytes(), "application/x-ply")
    assert main(["mesh", str(seq), "--gt-mesh", str(seq)]) == 0
    mesh = read_mesh(tmp_path / "scan_mesh.ply")
    assert mesh_accuracy(mesh, sphere).p95_mm < 0.5


@pytest.mark.parametrize(("method", "p95_mm"), [("poisson", 0.5), ("sdf", 0.8)])
def test_isolated_stripes_get_normals_from_the_view_direction(
    sphere: o3d.geometry.TriangleMesh, sphere_scan: tuple[Trajectory, list[StripeProfile]], method: str, p95_mm: float
) -> None:
    """Every 10th stripe.

    About 13 mm apart, beyond the 12 mm normal radius, so each neighbourhood is a line whose plain
    PCA normal is arbitrary about the stripe. Measured (sdf16): Poisson mean 0.081 mm, p95 0.291 mm
    (0.345 with 6 mm normals); the sdf mean 0.127 mm, p95 0.640 mm (it bridges more of the gaps between
    the stripes: completeness 0.76 against 0.65); without the view direction p95 3.35 / 2.83 mm.
    """
    traj, stripes = sphere_scan
    sparse = stripes[::10]
    good = mesh_accuracy(StripeMap.from_trajectory(traj, sparse, MappingConfig(method=method)).mesh(), sphere)
    assert good.mean_mm < 0.2 and good.p95_mm < p95_mm, good
    plain_cfg = MappingConfig(method=method, line_ratio=0.0)
    plain = mesh_accuracy(StripeMap.from_trajectory(traj, sparse, plain_cfg).mesh(), sphere)
    assert plain.p95_mm > 2 * good.p95_mm, (plain, good)


def test_stripes_extracted_from_a_sequences_laser_images(tmp_path: Path) -> None:
    """A recording with laser-line images but no stripe messages.

    Its profiles are extracted from the images with the configured light plane and lie on the
    simulated surface.
    """
    from loopmodel.config import config_from_dict
    from loopmodel.io.laser import sequence_stripe_count, sequence_stripes
    from loopmodel.io.mesh_io import mesh_from_bytes
    from loopmodel.io.sequence import open_sequence
    from loopmodel.sim import generate as gen

    cfg = config_from_dict(
        {
            "simulation": {
                "seed": 3,
                "camera": {"width_px": 320, "height_px": 240, "fx_px": 250.0},
                "trajectory": {"frames": 6},
                "laser": {"image": True, "range_noise_m": 0.0},
            },
            "sequence": {"topics": {"stripe": "/not/recorded"}},
        }
    )
    path = tmp_path / "laser.mcap"
    gen.simulate_scan(cfg.simulation, path)
    seq = open_sequence(path, cfg.sequence)
    assert seq.stripe_count() == 0 and seq.laser_image_count() == 6 == sequence_stripe_count(seq)
    profiles = list(sequence_stripes(seq, cfg.mapping))
    assert len(profiles) >= 5
    truth = {s.timestamp_ns: s for s in open_sequence(path).stripes()}
    gt = seq.ground_truth
    assert gt is not None
    scene = mesh_from_bytes(seq.read_attachment("scene.ply"), "ply", path)
    for prof in profiles:
        # about one point per image row the line crosses, like the ray-cast profile
        n_true = truth[prof.timestamp_ns].points_in_cam.shape[0]
        assert prof.points_in_cam.shape[0] > 0.5 * min(n_true, 240)
        T = gt.world_from_cam[int(np.searchsorted(gt.timestamps_ns, prof.timestamp_ns))]
        world = prof.points_in_cam @ T[:3, :3].T + T[:3, 3]
        d_mm = 1e3 * distances_to_mesh(world, scene)
        assert np.median(d_mm) < 0.3 and np.quantile(d_mm, 0.9) < 1.0, np.quantile(d_mm, [0.5, 0.9])


def test_uint8_row_medians_equal_numpy(rng: np.random.Generator) -> None:
    from loopmodel.mapping.extraction import _row_medians_u8

    for shape in [(7, 8), (5, 9), (1, 1), (48, 64)]:
        a = rng.integers(0, 256, shape).astype(np.uint8)
        np.testing.assert_array_equal(_row_medians_u8(a), np.median(a, axis=1))


def test_cli_mesh_exports_convert_the_runs_mesh(
    tmp_path: Path, sphere_scan: tuple[Trajectory, list[StripeProfile]], capfd: pytest.CaptureFixture[str]
) -> None:
    """GLB then OBJ of a run: its mesh.ply converted (same triangles), the picture kept, no open3d warning."""
    from loopmodel.cli import main

    traj, stripes = sphere_scan
    d = _results_dir(tmp_path, traj, stripes[::3])
    assert main(["mesh", str(d)]) == 0  # the run's mesh.ply
    ply = read_mesh(d / "mesh.ply")
    capfd.readouterr()
    assert main(["mesh", str(d), "--format", "glb"]) == 0
    assert main(["mesh", str(d), "--format", "obj"]) == 0  # failed: mesh.png of the GLB export existed
    out = capfd.readouterr().out
    assert "converted from" in out and "kept" in out and "can not include triangle normals" not in out
    for fmt in ("glb", "obj"):
        m = read_mesh(d / f"mesh.{fmt}")
        assert len(m.triangles) == len(ply.triangles)
        got, want = np.sort(np.asarray(m.vertices), axis=0), np.sort(np.asarray(ply.vertices), axis=0)
        assert np.allclose(got, want, atol=1e-6)


def test_poisson_cells_are_about_the_configured_number_of_voxels() -> None:
    """The derived octree depth makes the finest cell closest to ``poisson_cell_voxels`` x ``voxel_m``.

    Checked against the cell edge computed here (box edge x scale / 2^depth, within a factor of
    sqrt 2 in log scale); the live mesh keeps cells of one live voxel (issue 32).
    """
    from loopmodel.mapping.meshing import live_mesh_config, poisson_depth

    pts = np.random.default_rng(2).uniform(0.0, 0.55, (2000, 3))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    ext = float(np.max(pts.max(axis=0) - pts.min(axis=0)))
    for factor in (1.0, 2.0, 4.0):
        cfg = MappingConfig(poisson_cell_voxels=factor)
        depth = poisson_depth(cloud, cfg)
        cell_m = ext * cfg.poisson_scale / 2**depth
        assert abs(np.log2(cell_m / (factor * cfg.voxel_m))) <= 0.5
    assert poisson_depth(cloud, MappingConfig(poisson_cell_voxels=1.0)) == 9  # 0.55 m box, 1.5 mm voxels
    assert poisson_depth(cloud, MappingConfig()) == 8  # the default: cells of about 3 mm
    assert live_mesh_config(MappingConfig()).poisson_cell_voxels == 1.0
