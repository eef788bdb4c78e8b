"""Synthetic scan simulator (issue 3).

Stereo geometry, ground-truth consistency, laser stripes, faults, determinism, parameter errors.
Small images and few frames keep it fast.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scipy.ndimage import map_coordinates, spline_filter

from loopmodel.cli import main
from loopmodel.config import SimulationConfig, config_from_dict
from loopmodel.errors import ConfigError
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose, so3_log
from loopmodel.io.sequence import open_sequence
from loopmodel.sim import generate as gen
from loopmodel.sim.render import Raycaster, pixel_rays
from loopmodel.sim.trajectory import HandheldPath

TEX = 256  # small textures: fast scene building


def small_cfg(seed: int = 3, **sections: dict) -> SimulationConfig:
    """A small, fast configuration; ``sections`` override parts of it."""
    base = {
        "seed": seed, "workers": 1, "write_scene_ply": False,
        "scene": {"texture_size_px": TEX},
        "camera": {"width_px": 96, "height_px": 72, "fx_px": 75.0},
        "trajectory": {"frames": 8},
    }
    for k, v in sections.items():
        base.setdefault(k, {})
        base[k] = {**base[k], **v} if isinstance(v, dict) else v
    return config_from_dict({"simulation": base}).simulation


@pytest.fixture(scope="module")
def wide() -> tuple[SimulationConfig, Raycaster]:
    """320 x 240 window of the default fx = 500 camera, noiseless, with its raycaster."""
    cfg = small_cfg(camera={"width_px": 320, "height_px": 240, "fx_px": 500.0},
                    render={"noise_sigma": 0.0, "motion_blur": False})
    return cfg, Raycaster(gen.scene_of(cfg))


def _sub_lk_disparity(
    L: np.ndarray, R: tuple[np.ndarray, np.ndarray], u: float, v: float, d0: float, half: int = 4
) -> float:
    """Disparity of left pixel (u, v) in the right image by 1-D Lucas-Kanade on float images.

    Cubic interpolation; ``R``, ``gxR`` are spline-prefiltered right image and x-gradient; with a
    disparity affine over the window, started from d0.
    """
    R, gxR = R
    ys, xs = np.mgrid[v - half: v + half + 1, u - half: u + half + 1].astype(float)
    tmpl = L[ys.astype(int), xs.astype(int)]
    # disparity affine in the window (exact for a plane): d + a (x - u) + c (y - v)
    dx, dy = xs - u, ys - v
    p = np.array([d0, 0.0, 0.0])
    for _ in range(30):
        disp = p[0] + p[1] * dx + p[2] * dy
        coords = np.array([ys.ravel(), (xs - disp).ravel()])
        r = (map_coordinates(R, coords, order=3, prefilter=False).reshape(xs.shape) - tmpl).ravel()
        g = map_coordinates(gxR, coords, order=3, prefilter=False)
        J = -g[:, None] * np.column_stack([np.ones(g.size), dx.ravel(), dy.ravel()])
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        p += step
        if abs(step[0]) < 1e-5:
            break
    return float(p[0])


def test_stereo_disparity_matches_depth(wide: tuple[SimulationConfig, Raycaster]) -> None:
    cfg, caster = wide
    st = gen._make_state(cfg, caster.scene)
    path = gen.path_of(cfg)
    fx, b = cfg.camera.fx_px, cfg.camera.baseline_m
    errs_geom, errs_img = [], []
    for t_s in (0.0, 0.13):
        T = path.pose(t_s)
        light = gen.light_position(cfg, t_s, T)
        left = st.caster.render(st.rays, T, light, cfg.render.ambient)
        right = st.caster.render(st.rays, T @ st.cam0_from_cam1, light, cfg.render.ambient)
        z = left.depth_m
        Rr = right.radiance.astype(float)
        R_spl = (spline_filter(Rr, order=3), spline_filter(np.gradient(Rr, axis=1), order=3))
        for v in range(20, 220, 12):
            for u in range(40, 300, 12):
                win = z[v - 5: v + 6, u - 5: u + 6]
                if not np.all(np.isfinite(win)) or np.ptp(win) > 0.05 * z[v, u]:
                    continue  # depth edge: skip
                if np.abs(np.diff(win, 2, axis=1)).max() > 0.002 * z[v, u]:
                    continue  # crease or strong curvature: skip
                d_true = fx * b / float(z[v, u])
                ur = u - d_true
                if ur < 8:
                    continue
                if abs(right.depth_m[v, int(round(ur))] - z[v, u]) > 0.02 * z[v, u]:
                    continue  # occluded in the right view
                # geometry: the right camera's ray at (u - d, v) hits the same 3-D point
                X = left.points_world[v, u].astype(float)
                c = [[v] * 3, [ur] * 3]
                Xr = np.array([map_coordinates(right.points_world[..., k], c, order=1)[0] for k in range(3)])
                errs_geom.append(np.linalg.norm(Xr - X) * fx / float(z[v, u]))
                # image: the rendered pair shows that disparity
                if np.std(left.radiance[v - 4: v + 5, u - 4: u + 5]) < 0.02:
                    continue  # too little texture to measure
                d_img = _sub_lk_disparity(left.radiance, R_spl, u, v, d_true + 0.4)
                errs_img.append(abs(d_img - d_true))
    errs_geom_a, errs_img_a = np.array(errs_geom), np.array(errs_img)
    assert errs_geom_a.size > 100 and errs_img_a.size > 60
    assert np.percentile(errs_geom_a, 95) < 0.1
    assert np.median(errs_img_a) < 0.05 and np.percentile(errs_img_a, 90) < 0.1


@pytest.mark.parametrize("xi", [0.0, 0.8])
def test_marked_point_lands_at_its_projection(wide: tuple[SimulationConfig, Raycaster], xi: float) -> None:
    cfg, caster = wide
    cam = CentralCamera(500.0 * (1 + xi), 500.0 * (1 + xi), 159.5, 119.5, xi)
    rays = pixel_rays(cam, 320, 240)
    T = gen.path_of(cfg).pose(0.0)
    # marked points where the surface faces the camera (a slanted surface shifts the centroid
    # of the imaged spot by perspective, a camera-independent effect we do not test here)
    grid = np.array([(u + 0.37, v + 0.61) for v in range(40, 200, 9) for u in range(60, 260, 11)])
    rays_g = cam.lift(grid) @ T[:3, :3].T
    hits = caster.cast_points(T[:3, 3], rays_g)
    facing = -np.einsum("ij,ji->i", rays_g, hits.normal)
    picks = grid[np.argsort(-facing)[:3]]
    assert facing.max() > 0.85
    for uv0 in picks:
        ray = cam.lift(np.array([uv0]))[0]
        hit = caster.cast_points(T[:3, 3], (T[:3, :3] @ ray)[None, :])
        X = T[:3, 3] + T[:3, :3] @ ray * float(hit.range_m[0])
        sigma = 1.6 * float(hit.range_m[0]) / cam.px * (1 + xi)
        light = np.array([0.0, 0.0, 3.0])
        caster.markers = []
        base = caster.render(rays, T, light, 1.0).radiance
        caster.markers = [(X, sigma, 0.6)]
        marked = caster.render(rays, T, light, 1.0).radiance
        caster.markers = []
        diff = (marked - base).astype(float)
        u0, v0 = int(round(uv0[0])), int(round(uv0[1]))
        win = diff[v0 - 12: v0 + 13, u0 - 12: u0 + 13]
        vs, us = np.mgrid[v0 - 12: v0 + 13, u0 - 12: u0 + 13]
        centroid = np.array([np.sum(win * us), np.sum(win * vs)]) / np.sum(win)
        cam_from_world = invert_pose(T)
        expected = cam.project((cam_from_world[:3, :3] @ X + cam_from_world[:3, 3])[None, :])[0]
        assert np.linalg.norm(centroid - expected) < 0.05, (uv0, centroid, expected)


def _read(path: Path) -> dict:
    seq = open_sequence(path)
    frames = {f.timestamp_ns: (f.left, f.right) for f in seq.frames()}
    stripes = {s.timestamp_ns: s.points_in_cam for s in seq.stripes()}
    gt = seq.ground_truth
    assert gt is not None
    return {"seq": seq, "frames": frames, "stripes": stripes, "gt": gt, "meta": seq.metadata}


def test_patches_painted_as_by_testing_every_point(wide: tuple[SimulationConfig, Raycaster]) -> None:
    """The albedo's patches (tested only on points near them, gen20) as testing every point of a view.

    Overlapping flat and tiled patches around points the view sees, on the table and on the object;
    the painting by their definition on all points, in their order, gives the same float32 albedo.
    """
    cfg, caster = wide
    T = gen.path_of(cfg).pose(0.0)
    rays = pixel_rays(gen.camera_of(cfg), cfg.camera.width_px, cfg.camera.height_px)
    d = np.ascontiguousarray(T[:3, :3].astype(np.float32) @ rays.dirs)
    o = T[:3, 3].astype(np.float32)
    hits = caster.cast(o, d)
    p = o[:, None] + d * np.where(np.isfinite(hits.range_m), hits.range_m, np.float32(0.0))
    seen = np.flatnonzero(hits.primitive >= 0)
    picks = seen[np.linspace(0, seen.size - 1, 7).astype(int)[1:-1]]
    patches = [(p[:, i].astype(float), rad, kind) for i, rad, kind in
               zip(picks, (0.05, 0.03, 0.08, 0.04, 0.06), ("flat", "tiles", "tiles", "flat", "tiles"), strict=True)]
    patches.append((p[:, picks[0]].astype(float) + 0.01, 0.03, "tiles"))  # over the first one
    try:
        caster.patches = []
        plain = caster.albedo(p, hits.normal, hits.primitive)
        caster.patches = patches
        got = caster.albedo(p, hits.normal, hits.primitive)
    finally:
        caster.patches = []
    want = plain.copy()
    w = hits.normal * hits.normal
    w *= w
    w /= np.maximum(w[0] + w[1] + w[2], 1e-12)
    for centre, radius, kind in patches:
        c = np.asarray(centre, np.float32)
        r2 = (p[0] - c[0]) ** 2 + (p[1] - c[1]) ** 2
        r2 += (p[2] - c[2]) ** 2
        inside = (r2 < np.float32(radius * radius)) & (hits.primitive >= 0)
        assert inside.sum() > 20  # every patch is seen
        if kind == "flat":
            want[inside] = 0.55
        else:
            ax = np.argmax(w[:, inside], axis=0)
            q = p[:, inside]
            a = np.choose(ax, [q[1], q[0], q[0]])
            b = np.choose(ax, [q[2], q[2], q[1]])
            want[inside] = (0.3 + 0.4 * ((np.floor(a / 0.012) + np.floor(b / 0.012)) % 2)).astype(np.float32)
    assert not np.array_equal(want, plain)
    assert np.array_equal(got, want)


def test_stripes_on_surface_and_in_plane(tmp_path: Path) -> None:
    cfg = small_cfg(laser={"range_noise_m": 0.0}, trajectory={"frames": 5})
    out = tmp_path / "s.mcap"
    gen.simulate_scan(cfg, out)
    data = _read(out)
    scene_rs = o3d.t.geometry.RaycastingScene()
    scene = gen.scene_of(cfg)
    scene_rs.add_triangles(o3d.core.Tensor(scene.vertices.astype(np.float32)),
                           o3d.core.Tensor(scene.triangles.astype(np.uint32)))
    o = np.array(cfg.laser.origin_in_cam_m)
    n = np.array(cfg.laser.normal_in_cam) / np.linalg.norm(cfg.laser.normal_in_cam)
    poses = dict(zip(data["gt"].timestamps_ns.tolist(), data["gt"].world_from_cam, strict=True))
    assert len(data["stripes"]) == 5
    total = 0
    for t, pts in data["stripes"].items():
        assert pts.shape[0] > 20
        T = poses[t]
        pw = pts @ T[:3, :3].T + T[:3, 3]
        dist = scene_rs.compute_distance(o3d.core.Tensor(pw.astype(np.float32))).numpy()
        assert dist.max() < 1e-6
        assert np.abs((pts - o) @ n).max() < 1e-6  # float32 storage in PointCloud2
        total += pts.shape[0]
    assert total > 100
    # with range noise the points leave the surface by about sigma, along the laser rays
    cfg2 = small_cfg(laser={"range_noise_m": 0.001}, trajectory={"frames": 2})
    out2 = tmp_path / "n.mcap"
    gen.simulate_scan(cfg2, out2)
    d2 = _read(out2)
    t0, pts = next(iter(d2["stripes"].items()))
    T = dict(zip(d2["gt"].timestamps_ns.tolist(), d2["gt"].world_from_cam, strict=True))[t0]
    pw = pts @ T[:3, :3].T + T[:3, 3]
    dist = scene_rs.compute_distance(o3d.core.Tensor(pw.astype(np.float32))).numpy()
    assert 0.0003 < np.sqrt(np.mean(dist**2)) < 0.002
    assert np.abs((pts - o) @ n).max() < 1e-6


def test_faults_exactly_where_metadata_says(tmp_path: Path) -> None:
    frames = 12
    clean_cfg = small_cfg(trajectory={"frames": frames})
    faults = ["dropped:2", "blackout:4-5", "occluder:6-8", "duplicate_timestamp:9", "blur:10-11"]
    fault_cfg = gen.resolve_config(clean_cfg, faults=faults)
    gen.simulate_scan(clean_cfg, tmp_path / "clean.mcap")
    res = gen.simulate_scan(fault_cfg, tmp_path / "fault.mcap")
    clean, bad = _read(tmp_path / "clean.mcap"), _read(tmp_path / "fault.mcap")
    records = json.loads(bad["meta"]["faults"]["json"])
    assert records == res.faults and len(records) == 5
    kinds = {}
    for r in records:
        for i in range(r["first_frame"], r["last_frame"] + 1):
            kinds.setdefault(i, set()).add(r["kind"])
    assert kinds == {2: {"dropped"}, 4: {"blackout"}, 5: {"blackout"}, 6: {"occluder"}, 7: {"occluder"},
                     8: {"occluder"}, 9: {"duplicate_timestamp"}, 10: {"blur"}, 11: {"blur"}}
    times = [gen.frame_time_ns(fault_cfg, i) for i in range(frames)]
    for r in records:
        assert r["first_time_ns"] == times[r["first_frame"]] and r["last_time_ns"] == times[r["last_frame"]]
    # the reader sees every frame except the dropped one and the duplicate (skipped)
    assert sorted(bad["frames"]) == [t for i, t in enumerate(times) if i not in (2, 9)]
    assert len(clean["frames"]) == frames
    assert len(bad["gt"]) == frames - 1  # no second pose for the duplicated stamp
    for i, t in enumerate(times):
        if i in (2, 9):
            continue
        (l0, r0), (l1, r1) = clean["frames"][t], bad["frames"][t]
        same = np.array_equal(l0, l1) and np.array_equal(r0, r1)
        assert same == (i not in kinds), f"frame {i}"
        if i in (4, 5):
            assert l1.mean() < 5 and l0.mean() > 30
        if i in (6, 7, 8):  # the occluder covers a part of the view
            assert 0.02 < np.mean(np.abs(l1.astype(int) - l0.astype(int)) > 20) < 0.9
    # stripes: none for dropped, blacked-out and duplicated frames
    assert sorted(bad["stripes"]) == [t for i, t in enumerate(times) if i not in (2, 4, 5, 9)]


@pytest.mark.slow
def test_same_seed_same_content_and_workers_do_not_matter(tmp_path: Path) -> None:
    cfg = small_cfg(trajectory={"frames": 4}, laser={"image": True})
    gen.simulate_scan(cfg, tmp_path / "a.mcap")
    gen.simulate_scan(cfg.model_copy(update={"workers": 2}), tmp_path / "b.mcap")
    gen.simulate_scan(small_cfg(seed=4, trajectory={"frames": 4}), tmp_path / "c.mcap")
    a, b, c = (_read(tmp_path / f"{k}.mcap") for k in "abc")
    assert a["frames"].keys() == b["frames"].keys()
    for t in a["frames"]:
        assert all(np.array_equal(x, y) for x, y in zip(a["frames"][t], b["frames"][t], strict=True))
        assert np.array_equal(a["stripes"][t], b["stripes"][t])
    assert np.array_equal(a["gt"].world_from_cam, b["gt"].world_from_cam)
    assert a["seq"].read_attachment("scene.ply") == b["seq"].read_attachment("scene.ply")
    t0 = next(iter(a["frames"]))
    assert not np.array_equal(a["frames"][t0][0], c["frames"][t0][0])
    assert "/laser/image" in a["seq"].describe()["topics"]


def test_scene_ply_attachment_is_the_scene(tmp_path: Path) -> None:
    cfg = small_cfg(trajectory={"frames": 1}, write_scene_ply=True)
    out = tmp_path / "x.mcap"
    res = gen.simulate_scan(cfg, out)
    seq = open_sequence(out)
    assert res.scene_ply is not None and res.scene_ply.read_bytes() == seq.read_attachment("scene.ply")
    mesh = o3d.io.read_triangle_mesh(str(res.scene_ply))
    scene = gen.scene_of(cfg)
    assert len(mesh.triangles) == scene.triangles.shape[0]
    assert np.allclose(np.asarray(mesh.vertices), scene.vertices[np.unique(scene.triangles)])
    lo, hi = scene.object_bounds_m
    assert 0.45 < hi[2] - lo[2] < 0.55 and lo[2] > -1e-9  # 0.5 m object on the table top
    meta = seq.metadata["simulation"]
    assert SimulationConfig.model_validate_json(meta["config_json"]) == cfg


@pytest.mark.parametrize("kind", ["orbit", "sweeps", "browse"])
def test_paths_close_range_loops_and_no_revisit(kind: str) -> None:
    cfg = small_cfg(trajectory={"kind": kind, "frames": 400})
    path = gen.path_of(cfg)
    times = np.arange(400) / cfg.trajectory.rate_hz
    poses = np.array([path.pose(t) for t in times])
    scene = gen.scene_of(cfg)
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(scene.legacy_mesh(object_only=True)))
    dist = rs.compute_distance(o3d.core.Tensor(poses[:, :3, 3].astype(np.float32))).numpy()
    assert 0.3 <= dist.min() and dist.max() <= 1.0
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert step.max() < 0.03  # smooth: under 3 cm per frame at 25 Hz
    az = np.unwrap(np.arctan2(poses[:, 1, 3], poses[:, 0, 3]))
    end_pos = np.linalg.norm(poses[-1, :3, 3] - poses[0, :3, 3])
    end_rot = np.degrees(np.linalg.norm(so3_log(poses[0, :3, :3].T @ poses[-1, :3, :3])))
    if kind == "orbit":
        assert abs(abs(az[-1] - az[0]) - 2 * np.pi) < 0.05 and end_pos < 0.02 and end_rot < 3
    elif kind == "sweeps":
        assert np.ptp(az) > np.radians(85) and end_pos < 0.02 and end_rot < 3
    else:
        assert np.all(np.diff(az) * np.sign(az[-1] - az[0]) > 0)  # monotone: no revisit
        assert abs(az[-1] - az[0]) > np.radians(200)


def test_rounds_keep_finding_new_views() -> None:
    """Issue 33: every round turns once around the object at its own height and distance, then revisits its start."""
    n, frames = 4, 1200
    cfg = small_cfg(trajectory={"kind": "rounds", "frames": frames, "sweeps": n})
    path = gen.path_of(cfg)
    poses = np.array([path.pose(t) for t in np.arange(frames) / cfg.trajectory.rate_hz])
    scene = gen.scene_of(cfg)
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(scene.legacy_mesh(object_only=True)))
    dist = rs.compute_distance(o3d.core.Tensor(poses[:, :3, 3].astype(np.float32))).numpy()
    assert 0.3 <= dist.min() and dist.max() <= 1.0
    az = np.unwrap(np.arctan2(poses[:, 1, 3], poses[:, 0, 3]))
    assert abs(abs(az[-1] - az[0]) - n * np.radians(400)) < 0.2  # a turn and 40 deg more per round
    per = frames // n  # the middle of each round's turn: its own height and distance
    mid = poses[per // 3 :: per][:n, :3, 3]
    heights, radii = mid[:, 2], np.linalg.norm(mid[:, :2], axis=1)
    assert np.min(np.abs(np.diff(heights))) > 0.04 and np.min(np.abs(np.diff(radii))) > 0.03
    # each round's end passes its own start again (the revisit) from about the same place
    for i in range(n):
        start = poses[i * per + 5, :3, 3]
        seen = poses[i * per + int(0.85 * per) : (i + 1) * per, :3, 3]
        assert np.min(np.linalg.norm(seen - start, axis=1)) < 0.05


def test_impossible_parameters_raise_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="baseline_m"):
        small_cfg(camera={"baseline_m": -0.06})
    with pytest.raises(ConfigError, match="frames"):
        small_cfg(trajectory={"frames": 0})
    with pytest.raises(ConfigError, match="light plane never hits"):
        gen.simulate_scan(small_cfg(laser={"normal_in_cam": [0.0, 0.0, 1.0]}), tmp_path / "x.mcap")
    with pytest.raises(ConfigError, match="outside 0-7"):
        gen.resolve_config(small_cfg(), faults=["blackout:5-9"])
    with pytest.raises(ConfigError, match="KIND:FIRST"):
        gen.resolve_config(small_cfg(), faults=["smoke:5"])
    with pytest.raises(ConfigError, match="scene surface"):
        gen.simulate_scan(small_cfg(trajectory={"radius_m": 0.1}), tmp_path / "y.mcap")
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "y.mcap").exists()
    assert main(["simulate", "scan", "--out", str(tmp_path / "z.mcap"), "--frames", "0"]) == 2
    assert main(["simulate", "scan", "--out", str(tmp_path / "z.mcap"), "--baseline", "-1"]) == 2


def test_shake_is_small_and_smooth() -> None:
    p = HandheldPath("orbit", 20.0, 1, shake_translation_m=0.002, shake_rotation_deg=0.3)
    d = [np.linalg.norm(p.pose(t)[:3, 3] - p.nominal_pose(t)[:3, 3]) for t in np.linspace(0, 20, 200)]
    assert 0.0005 < np.sqrt(np.mean(np.square(d))) < 0.01


def test_preset_files_match_the_presets() -> None:
    root = Path(__file__).resolve().parents[1]
    for name in gen.PRESETS:
        from loopmodel.config import load_config

        from_file = load_config(root / "datasets" / "presets" / f"{name}.yaml").simulation
        assert from_file == gen.resolve_config(SimulationConfig(), preset=name)
    sample = load_config(root / "configs" / "sim.yaml").simulation
    assert sample == gen.resolve_config(SimulationConfig(), preset="orbit")


def _viewer_modules_after(start: str) -> list[str]:
    """Which of open3d, dash and plotly a fresh interpreter holds after running ``start`` (its last line out)."""
    code = start + "import sys\nprint(' '.join(m for m in ('open3d', 'dash', 'plotly') if m in sys.modules))\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    return out.stdout.splitlines()[-1].split()


def test_render_workers_load_open3d_without_its_plotly_viewer() -> None:
    """A render worker's start (``start_without_plotly_viewer``) loads open3d but not dash or plotly (gen20)."""
    start = (
        "from loopmodel.open3d_import import start_without_plotly_viewer\n"
        "start_without_plotly_viewer('loopmodel.sim.render:to_tensor', __import__('numpy').zeros(3, 'float32'))\n"
    )
    assert _viewer_modules_after(start) == ["open3d"]


def test_the_command_and_the_live_mesh_worker_load_open3d_without_its_plotly_viewer() -> None:
    """``loopmodel`` run as the program, and the live mesh's process start, load open3d without dash or plotly."""
    command = "import sys\nfrom loopmodel.cli import main\nsys.argv = ['loopmodel', '--version']\nmain()\n"
    command += "import open3d\n"
    assert _viewer_modules_after(command) == ["open3d"]
    live = "from loopmodel.mapping.live import _worker_start\n_worker_start()\n"
    assert _viewer_modules_after(live) == ["open3d"]


def test_open3d_loaded_without_its_plotly_viewer_loads_it_when_drawn_with() -> None:
    """``load_open3d`` leaves out dash and plotly; the viewer's functions then load them when called (fin21).

    The run's process loads open3d that way in the finish (a library caller's process: nothing is lost).
    """
    start = (
        "import sys\nfrom loopmodel.open3d_import import load_open3d\no3d = load_open3d()\n"
        "assert 'plotly' not in sys.modules and 'dash' not in sys.modules\n"
        "viewer = sys.modules['open3d.visualization.draw_plotly']\n"
        "assert not hasattr(viewer, '__file__') and 'plotly' not in sys.modules\n"
        "assert viewer.go.__name__ == 'plotly.graph_objects'\n"
        "fig = o3d.visualization.get_plotly_fig([o3d.geometry.TriangleMesh.create_box()])\n"
        "assert fig.data[0].type == 'mesh3d' and len(fig.data[0].x) == 8, fig.data\n"
        "assert o3d.visualization.draw_plotly.__module__ == 'open3d.visualization.draw_plotly'\n"
    )
    assert _viewer_modules_after(start) == ["open3d", "dash", "plotly"]
