"""``loopmodel run --frontend-only`` on a small rendered KITTI-layout folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from frontend_scene import write_kitti_folder

from loopmodel.cli import main
from loopmodel.config import Config
from loopmodel.io.sequence import open_sequence
from loopmodel.io.trajectory_io import read_trajectory
from loopmodel.pipeline import run_frontend


def test_run_frontend_only_writes_results_folder(tmp_path: Path, rng: np.random.Generator) -> None:
    seq_dir = tmp_path / "seq"
    poses = write_kitti_folder(seq_dir, 8, rng)
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
    write_kitti_folder(seq_dir, 5, rng)
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
