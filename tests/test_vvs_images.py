"""VVS tracking from rendered omnidirectional images (seed 002): renderer geometry against the
unified model, the moving-edge search against a known edge, tracking from a perturbed start."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from loopmodel.geometry.se3 import make_pose
from loopmodel.pose.moving_edges import ImageMovingEdges, MovingEdgeOptions
from loopmodel.sim.omni_images import OmniRenderer, OmniScenario, omni_scenario, track_scenario


def test_a_rendered_point_lands_where_the_unified_model_projects_it() -> None:
    base = omni_scenario(0, 1, clutter=False)
    sensor = base.sensor
    m = 1
    cam = sensor.cameras[m]
    # a small bright cube 0.9 m from mirror 2's focus, seen from the side (the mirrors' field
    # of view is around the horizon), in front of the dark room
    X = sensor.foci_m[m] + 0.9 * np.array([np.cos(0.6), np.sin(0.6), 0.15]) / np.linalg.norm([1, 0, 0.15])
    cube = o3d.geometry.TriangleMesh.create_box(0.012, 0.012, 0.012)
    cube.translate(X - 0.006)
    room_mesh, _ = base.static_meshes[0]
    scen = OmniScenario(
        0,
        sensor,
        [(room_mesh, np.full(len(room_mesh.triangles), 0.05)), (cube, np.full(12, 1.0))],
        (0.01, 0.01, 0.01),
        np.zeros(6),
        [make_pose(np.eye(3), [0.0, 0.0, 50.0])],  # the box far away: out of sight
    )
    img = OmniRenderer(scen).render(0).astype(float)
    expect = cam.project((X - sensor.foci_m[m])[None])[0]
    u0, v0 = np.round(expect).astype(int)
    win = img[v0 - 8 : v0 + 9, u0 - 8 : u0 + 9]
    w = np.clip(win - np.median(win) - 20, 0, None)
    assert w.sum() > 0
    vv, uu = np.mgrid[v0 - 8 : v0 + 9, u0 - 8 : u0 + 9]
    centroid = np.array([(uu * w).sum(), (vv * w).sum()]) / w.sum()
    # the cube spans ~3 px; its bright-pixel centroid is within 0.3 px of the projected centre
    assert np.linalg.norm(centroid - expect) < 0.3, (centroid, expect)


def test_moving_edge_search_finds_a_step_at_a_known_offset() -> None:
    rng = np.random.default_rng(0)
    x = np.arange(200)[None, :]
    edge_x = 103.3
    # the step as an area-sampled edge (pixel i covers [i - 0.5, i + 0.5]), then noise
    frac = np.clip(x + 0.5 - edge_x, 0, 1)
    img = 60.0 + 110.0 * frac * np.ones((120, 1)) + rng.normal(0, 2.0, (120, 200))
    me = ImageMovingEdges(MovingEdgeOptions(range_px=10))
    me.set_image(np.clip(img, 0, 255).astype(np.uint8))
    uv = np.column_stack([np.full(20, 98.0), np.linspace(30, 90, 20)])
    normals = np.tile([1.0, 0.0], (20, 1))
    found, out = me.measure(0, uv, normals, np.zeros(20, np.int64))
    assert found.all()
    err = out[:, 0] - edge_x
    assert np.abs(np.median(err)) < 0.15 and np.abs(err).max() < 0.35, err  # sub-pixel
    # a site remembers the polarity: the opposite edge (dark after bright) is not accepted
    me.remember(0)
    me.set_image(np.clip(230 - img, 0, 255).astype(np.uint8))
    found2, _ = me.measure(0, uv, normals, np.zeros(20, np.int64))
    assert not found2.any()


@pytest.mark.slow
def test_tracking_from_a_perturbed_start_converges_on_rendered_images() -> None:
    sc = omni_scenario(1, 12)
    (r4, r2), init_rot_deg, init_pos_m = track_scenario(sc, init_rot_deg=6.0, init_pos_m=0.025)
    assert init_rot_deg >= 5.0 and init_pos_m >= 0.02
    for r in (r4, r2):
        assert not r.lost.any()
        # measured: 4 mirrors 0.02-0.2 deg, 0.1-1.3 mm; 2 mirrors 0.05-0.3 deg, 0.1-1.8 mm
        assert np.median(r.rot_err_deg) < 0.4 and np.median(r.pos_err_mm) < 2.0


@pytest.mark.slow
def test_without_clutter_two_mirrors_lose_no_frame() -> None:
    sc = omni_scenario(5, 15, clutter=False)
    (r2,), _, _ = track_scenario(sc, mirror_sets=((0, 3),))
    assert not r2.lost.any()


def test_cli_renders_a_folder_and_tracks_it_from_its_images(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    from loopmodel.cli import main

    out = tmp_path / "scan"
    assert main(["vvs", "render", "--seed", "4", "--frames", "4", "--out", str(out)]) == 0
    assert len(list((out / "images").glob("*.png"))) == 4
    args = ["vvs", "track", str(out / "images"), "--rig", str(out / "rig.yaml"), "--model", str(out / "model.yaml")]
    args += ["--init", str(out / "init.txt"), "--truth", str(out / "truth.tum"), "--out", str(tmp_path / "t")]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "4 tracked" in text
    rows = (tmp_path / "t" / "track.csv").read_text().splitlines()
    assert len(rows) == 5 and all(r.split(",")[1] == "1" for r in rows[1:])
    # a bad start pose is one line naming the option, exit 2
    bad = args[:]
    bad[bad.index("--init") + 1] = "0 0 0 1 2 3"
    assert main(bad) == 2
    err = capsys.readouterr().err
    assert "--init" in err and "Traceback" not in err


def test_calibration_from_the_nominal_design_recovers_the_sensor_as_built() -> None:
    from loopmodel.geometry.se3 import se3_log
    from loopmodel.pose import PointTerm, estimate_pose
    from loopmodel.pose.calibration import CalibrationView, calibrate_rig
    from loopmodel.sim.omni import calibration_views, manufactured_rig, omni_sensor

    sensor = omni_sensor()
    truth = manufactured_rig(sensor, seed=0)
    design = sensor.rig()
    obs, _ = calibration_views(sensor, 8, 0.3, 0, rig=truth)
    starts = [estimate_pose(PointTerm(design, P, uv, ci), ransac_threshold_px=8.0).rig_from_ref for P, uv, ci in obs]
    cal = calibrate_rig([CalibrationView(*o) for o in obs], design, starts)
    # the design is really off: xi up to 0.05, a few % of focal length, ~0.5 deg and ~2 mm
    assert max(abs(c.xi - 1.0) for c in truth.cameras) > 0.01
    for c, t in zip(cal.rig.cameras, truth.cameras, strict=True):
        # measured: xi within 4e-4, focal and principal point within 0.15 px
        assert abs(c.xi - t.xi) < 2e-3
        assert max(abs(c.px - t.px), abs(c.py - t.py), abs(c.u0 - t.u0), abs(c.v0 - t.v0)) < 0.5
    for E, T in zip(cal.rig.cam_from_rig, truth.cam_from_rig, strict=True):
        e = se3_log(E @ np.linalg.inv(T))
        # measured: 0.55 mm and 0.04 deg at most
        assert np.linalg.norm(e[:3]) < 1.5e-3 and np.degrees(np.linalg.norm(e[3:])) < 0.1
