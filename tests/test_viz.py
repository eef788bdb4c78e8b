"""Seeing a run: rerun recordings read back by rerun's own tools, and mesh pictures."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from loopmodel.cli import main

REPO = Path(__file__).resolve().parents[1]
TINY = REPO / "datasets" / "tiny_kitti"

rr = pytest.importorskip("rerun")


def _rerun_bin() -> str:
    exe = Path(sys.executable).with_name("rerun")
    if not exe.is_file():
        pytest.skip("rerun command line not installed beside python")
    return str(exe)


def rrd_rows(path: Path) -> dict[str, int]:
    """Entity path -> number of logged rows, from ``rerun rrd print`` (rerun's own reader)."""
    out = subprocess.run([_rerun_bin(), "rrd", "print", str(path)], capture_output=True, text=True, check=True)
    rows: dict[str, int] = {}
    for line in out.stdout.splitlines():
        if not line.startswith("Chunk(") or " - /" not in line:
            continue
        n = int(line.split(" with ", 1)[1].split(" rows", 1)[0])
        entity = line.split(" - /", 1)[1].split(" - ", 1)[0]
        rows[entity] = rows.get(entity, 0) + n
    return rows


def test_mesh_picture_silhouette_matches_the_projected_vertices() -> None:
    import cv2
    import open3d as o3d

    from loopmodel.viz.mesh_render import fixed_views, render_mesh

    m = o3d.geometry.TriangleMesh.create_sphere(0.2, resolution=60)
    m.translate([0.1, 0.0, 0.3])
    v, t = np.asarray(m.vertices), np.asarray(m.triangles)
    for view in fixed_views(v, 3):
        img, mask = render_mesh(v, t, view)
        p = v @ view.cam_from_world[:3, :3].T + view.cam_from_world[:3, 3]
        uv = (p @ view.K.T)[:, :2] / p[:, 2:]
        ref = np.zeros(mask.shape, np.uint8)
        hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2)
        cv2.fillConvexPoly(ref, np.round(hull * 16).astype(np.int32), 1, shift=4)
        iou = (mask & ref.astype(bool)).sum() / (mask | ref.astype(bool)).sum()
        assert iou > 0.995  # measured 0.9991 (the sphere's outline is a 60-segment polygon)
        # shaded grey inside; white background away from the (anti-aliased) outline
        far = ~cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        assert img[mask].mean() < 250 and img[far].min() == 255


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("viz")
    seq = root / "seq"
    shutil.copytree(TINY, seq)
    assert main(["run", str(seq), "--out", str(root), "--name", "r", "--rerun", str(root / "live.rrd")]) == 0
    return root


def test_run_with_rerun_records_one_frame_per_processed_frame(tiny_run: Path) -> None:
    rows = rrd_rows(tiny_run / "live.rrd")
    frames = len((TINY / "times.txt").read_text().split())
    assert rows.get("world/camera/image") == frames
    assert rows.get("world/camera/image/features") == frames
    for entity in ("world/camera", "world/keyframes", "world/path/online", "world/path/final"):
        assert entity in rows, entity
    assert any(e.startswith("metrics/") for e in rows)


def test_view_without_the_original_sequence_says_so(tiny_run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tiny_run / "r"
    moved = tiny_run / "seq_moved"
    shutil.move(tiny_run / "seq", moved)
    try:
        assert main(["view", str(run), "--out", str(tiny_run / "after.rrd")]) == 0
    finally:
        shutil.move(moved, tiny_run / "seq")
    out = " ".join(capsys.readouterr().out.split())  # the console wraps at its width (a long tmp path)
    assert "not found: no images" in out
    rows = rrd_rows(tiny_run / "after.rrd")
    assert "world/camera/image" not in rows
    assert rows["world/camera"] == len((TINY / "times.txt").read_text().split())
    assert "world/landmarks" in rows and "world/keyframes" in rows


def test_view_of_a_folder_that_is_not_a_run_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "not a results folder" in err and "Traceback" not in err


def test_recording_has_ground_truth_loop_events_and_a_blueprint(tiny_run: Path, tmp_path: Path) -> None:
    """Issue 35 item 8: the ground-truth path, loops found at the end, and the viewer's layout."""
    from loopmodel.result import RunResult
    from loopmodel.types import Trajectory
    from loopmodel.viz.recorder import RerunListener, RerunRecorder, RerunSink

    rows = rrd_rows(tiny_run / "live.rrd")
    assert "world/ground_truth" in rows  # tiny_kitti has poses.txt
    out = subprocess.run([_rerun_bin(), "rrd", "print", str(tiny_run / "live.rrd")], capture_output=True, text=True)
    assert "ViewBlueprint:space_origin" in out.stdout  # the layout travels with the recording
    # a loop reported only in metrics.json (found after the last keyframe) still draws its line
    rrd = tmp_path / "late.rrd"
    listener = RerunListener(RerunRecorder(RerunSink(path=rrd)), np.eye(3) * 100, (64, 48))
    T = np.repeat(np.eye(4)[None], 3, axis=0)
    T[:, 0, 3] = [0.0, 0.1, 0.2]
    traj = Trajectory(np.arange(3, dtype=np.int64) * 10**8, T)
    from loopmodel.config import Config

    result = RunResult(Config(), final=traj, keyframes=traj, keyframe_ids=np.arange(3, dtype=np.int64))
    result.metrics = {"loop_events": [{"type": "loop", "keyframe": 2, "match_keyframe": 0, "inliers": 40}]}
    listener.on_finish(result)
    assert rrd_rows(rrd).get("world/events") == 1


@pytest.mark.slow  # 17 s at load 14 (the viewer renders on the CPU)
def test_headless_screenshot_of_a_recording_is_not_blank(tiny_run: Path, tmp_path: Path) -> None:
    """``tools/screenshot_rerun.sh`` (xvfb + rerun --screenshot-to) draws the 3-D view and the plots."""
    import cv2

    if shutil.which("xvfb-run") is None or not list(Path("/usr/share/vulkan/icd.d").glob("lvp_icd*.json")):
        pytest.skip("headless viewer needs Debian's xvfb and mesa-vulkan-drivers (make viewer-libs)")
    png = tmp_path / "view.png"
    env = {**__import__("os").environ, "RERUN": _rerun_bin(), "SIZE": "1000x640"}
    subprocess.run(
        ["bash", str(REPO / "tools" / "screenshot_rerun.sh"), str(tiny_run / "live.rrd"), str(png)],
        check=True,
        env=env,
        capture_output=True,
        timeout=240,
    )
    img = cv2.imread(str(png))
    assert img is not None and img.shape[1] >= 1000
    h, w = img.shape[:2]
    view3d, side = img[h // 10 : 9 * h // 10, : int(0.7 * w)], img[h // 10 : 9 * h // 10, int(0.78 * w) :]
    # the 3-D view shows the scene (keyframes, paths: many colours), the side panel the camera image
    assert len(np.unique((view3d.reshape(-1, 3) // 32).astype(np.int32) @ np.array([64, 8, 1]))) > 20
    assert float(side.std()) > 20


@pytest.mark.parametrize("up", [(0.0, 0.0, 1.0), (0.0, -1.0, 0.0)])
def test_mesh_views_stand_upright_about_the_given_up(up: tuple[float, float, float]) -> None:
    """A run's mesh (world: first camera, y down) is drawn with -y up, not on its side (issue 35)."""
    from loopmodel.viz.mesh_render import fixed_views

    rng = np.random.default_rng(3)
    verts = rng.normal(size=(200, 3)) * [0.1, 0.2, 0.15]
    u = np.asarray(up)
    for view in fixed_views(verts, 3, up=up):
        R, t = view.cam_from_world[:3, :3], view.cam_from_world[:3, 3]
        assert (R @ u)[1] < -0.8  # world up points up in the image (image y is down)
        eye = -R.T @ t
        assert float((eye - verts.mean(axis=0)) @ u) > 0  # seen from above


def test_picture_of_a_scanned_cone_stands_upright_in_the_runs_world() -> None:
    """A known mesh in a run's world is pictured upright (issue 35 item 7).

    A cone (apex up) scanned by an orbit looking 30 degrees down; the run's world is the first
    camera's. The picture's up comes from the orbit's principal axes: the cone's axis points up in
    every view and its pixels lie mostly in the lower half of its outline.
    """
    import open3d as o3d

    from loopmodel.geometry.se3 import invert_pose, look_at, up_from_poses
    from loopmodel.viz.mesh_render import View, fixed_views, render_mesh

    el = np.radians(30.0)
    az = np.radians(np.arange(0, 360, 15))
    eyes = 0.5 * np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(len(az), np.sin(el))])
    orbit = np.array([look_at(eye, [0.0, 0.0, 0.08], [0.0, 0.0, 1.0]) for eye in eyes])
    run_from_world = invert_pose(orbit[0])  # the run's world is its first camera
    cone = o3d.geometry.TriangleMesh.create_cone(radius=0.08, height=0.16, resolution=48)  # base z=0, apex z=0.16
    v = np.asarray(cone.vertices) @ run_from_world[:3, :3].T + run_from_world[:3, 3]
    t = np.asarray(cone.triangles)
    apex, base = v[np.argmax(np.asarray(cone.vertices)[:, 2])], run_from_world[:3, 3]

    def axis_tilt_deg(view: View) -> float:  # the cone's axis (base to apex) in the picture, from the image's up
        uv = [view.K @ (view.cam_from_world[:3, :3] @ p + view.cam_from_world[:3, 3]) for p in (apex, base)]
        d = uv[0][:2] / uv[0][2] - uv[1][:2] / uv[1][2]
        return float(np.degrees(np.arctan2(abs(d[0]), -d[1])))

    up = up_from_poses(run_from_world[None] @ orbit)
    # the first camera's -y, the former up: the cone leans by 11-26 degrees (measured)
    assert max(axis_tilt_deg(old) for old in fixed_views(v, 3, up=(0.0, -1.0, 0.0))) > 20
    for view in fixed_views(v, 3, up=up):
        # measured 2.1 in each view: perspective (the axis is off the view's centre), 0.0 at its centre
        assert axis_tilt_deg(view) < 3.0
        _, mask = render_mesh(v, t, view)
        ys, xs = np.nonzero(mask)
        top, bottom = ys.min(), ys.max()
        # a cone seen from above its base: most of its pixels in the lower half of its outline
        assert (ys < (top + bottom) / 2).mean() < 0.35  # measured 0.28-0.29
        # the apex is the topmost pixel, above the silhouette's centre (measured 0.7-1.5 % of the width)
        assert abs(xs[ys == top].mean() - xs.mean()) < 0.025 * mask.shape[1]


def test_ground_truth_in_the_runs_world_follows_the_run(tiny_run: Path, tmp_path: Path) -> None:
    """The logged ground truth starts at the run's origin and lies along its final path (and in ``view``)."""
    from loopmodel.io.sequence import open_sequence
    from loopmodel.io.trajectory_io import read_trajectory
    from loopmodel.viz.recorder import ground_truth_in_run_world

    final = read_trajectory(tiny_run / "r" / "trajectory_final.tum")
    gt = open_sequence(TINY).ground_truth
    assert gt is not None
    p = ground_truth_in_run_world(gt, int(final.timestamps_ns[0]))
    np.testing.assert_allclose(p[0], 0.0, atol=1e-9)
    # the run's own estimate, independent of the transform: within 2 cm over the 0.31 m path (ATE 2.7 mm)
    assert np.abs(p - final.positions_m).max() < 0.02
    assert main(["view", str(tiny_run / "r"), "--out", str(tmp_path / "v.rrd")]) == 0
    assert "world/ground_truth" in rrd_rows(tmp_path / "v.rrd")
