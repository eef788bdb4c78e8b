"""``loopmodel run --frontend-only`` on a small rendered KITTI-layout folder."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from frontend_scene import default_scene, render, stereo_rig, trajectory

from loopmodel.cli import main
from loopmodel.config import Config
from loopmodel.geometry.se3 import invert_pose
from loopmodel.io.sequence import open_sequence
from loopmodel.io.trajectory_io import read_trajectory
from loopmodel.pipeline import run_frontend


def _write_kitti(folder: Path, n: int, rng: np.random.Generator) -> np.ndarray:
    planes = default_scene(rng)
    cal = stereo_rig()
    poses = trajectory(n)
    poses = invert_pose(poses[0]) @ poses
    (folder / "image_0").mkdir(parents=True)
    (folder / "image_1").mkdir()
    for i, world_from_cam in enumerate(poses):
        cam_from_world = invert_pose(world_from_cam)
        cv2.imwrite(str(folder / "image_0" / f"{i:06d}.png"),
                    render(planes, cal.K_left, cam_from_world, cal.image_size))
        cv2.imwrite(str(folder / "image_1" / f"{i:06d}.png"),
                    render(planes, cal.K_right, cal.right_from_left @ cam_from_world, cal.image_size))
    P0 = np.hstack([cal.K_left, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -cal.K_left[0, 0] * cal.baseline_m
    row = [" ".join(repr(float(x)) for x in P.ravel()) for P in (P0, P1)]
    (folder / "calib.txt").write_text(f"P0: {row[0]}\nP1: {row[1]}\n")
    (folder / "poses.txt").write_text(
        "".join(" ".join(repr(float(x)) for x in T[:3, :].ravel()) + "\n" for T in poses)
    )
    return poses


def test_run_frontend_only_writes_results_folder(tmp_path: Path, rng: np.random.Generator) -> None:
    seq_dir = tmp_path / "seq"
    poses = _write_kitti(seq_dir, 8, rng)
    cfg_file = tmp_path / "fe.yaml"
    cfg_file.write_text("frontend:\n  max_disparity_px: 64\n  max_features: 400\n  min_tracked: 60\n")
    code = main(["run", str(seq_dir), "--frontend-only", "-c", str(cfg_file), "--out", str(tmp_path / "out"),
                 "--name", "t1"])
    assert code == 0
    out = tmp_path / "out" / "t1"
    for name in ("trajectory_online.tum", "keyframes.tum", "metrics.json", "config.yaml", "run.log"):
        assert (out / name).is_file(), name
    assert not list(out.glob(".*tmp*"))
    online = read_trajectory(out / "trajectory_online.tum")
    assert len(online) == 8
    err = np.linalg.norm(online.positions_m - poses[:, :3, 3], axis=1)
    assert err.max() < 0.02
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == 8 and m["lost_frames"] == 0 and m["ate_rmse_m"] < 0.02
    assert "max_disparity_px: 64" in (out / "config.yaml").read_text()
    assert len(read_trajectory(out / "keyframes.tum")) == m["keyframes"] >= 1


def test_run_without_frontend_only_is_a_clear_error(tmp_path: Path) -> None:
    assert main(["run", str(tmp_path), "--frontend-only"]) == 2  # not a sequence folder
    assert main(["run", str(tmp_path)]) == 2


def test_interrupted_run_still_writes_outputs(tmp_path: Path, rng: np.random.Generator) -> None:
    seq_dir = tmp_path / "seq"
    _write_kitti(seq_dir, 5, rng)
    cfg = Config()
    cfg.frontend.max_disparity_px = 64

    def stop(i: int, n: int, fps: float) -> None:
        if i == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_frontend(open_sequence(seq_dir), cfg, tmp_path / "out", "cut", progress=stop)
    out = tmp_path / "out" / "cut"
    assert len(read_trajectory(out / "trajectory_online.tum")) == 3
    m = json.loads((out / "metrics.json").read_text())
    assert m["interrupted"] is True and m["frames"] == 3
