"""The results files written while the final mesh is made (pre16, issue 32): the same folder as one write."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from loopmodel.config import Config
from loopmodel.io.results import ResultsFolder, write_results, write_results_early
from loopmodel.result import RunResult
from loopmodel.types import Trajectory


def _trajectory(n: int, shift_m: float = 0.0) -> Trajectory:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n) * 0.1 + shift_m
    return Trajectory(np.arange(n, dtype=np.int64) * 40_000_000, poses)


def _result(localized: bool = True, shift_m: float = 0.0) -> RunResult:
    traj = _trajectory(5, shift_m)
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])),
        o3d.utility.Vector3iVector(np.array([[0, 1, 2]])),
    )
    return RunResult(
        Config(),
        online=_trajectory(5, 0.01),
        final=traj,
        keyframes=Trajectory(traj.timestamps_ns[::2], traj.world_from_cam[::2]),
        keyframe_ids=np.array([0, 2, 4], np.int64),
        landmark_ids=np.arange(4, dtype=np.int64),
        landmarks_in_world=np.arange(12, dtype=float).reshape(4, 3),
        mesh=mesh,
        live_mesh=mesh,
        metrics={"frames": 5},
        log="a line\n",
        localized=_trajectory(3) if localized else None,
    )


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_early_then_rest_writes_the_same_folder_as_one_write(tmp_path: Path) -> None:
    one = write_results(ResultsFolder(tmp_path / "a", "run"), _result())
    folder = ResultsFolder(tmp_path / "b", "run")
    run = _result()
    early = write_results_early(folder, run)
    assert early is not None and early.holds_for(run)
    assert "trajectory_final.tum" in early.names and "metrics.json" not in early.names
    assert not (folder.path / "metrics.json").exists() and not (folder.path / "mesh.ply").exists()
    assert (folder.path / "mesh_live.ply").exists()  # settled before the final mesh
    run.metrics["later"] = 1.0  # the metrics may change after the early files
    two = write_results(folder, run, early=early)
    a, b = _files(one), _files(two)
    assert sorted(a) == sorted(b)
    assert all(a[k] == b[k] for k in a if k != "metrics.json")
    assert b"later" in b["metrics.json"]


def test_a_result_replaced_after_the_early_files_is_written_whole(tmp_path: Path) -> None:
    """E.g. a Ctrl-C during the mesh: the partial result has no localized frames and other poses."""
    folder = ResultsFolder(tmp_path / "b", "run")
    early = write_results_early(folder, _result(localized=True))
    assert early is not None
    other = _result(localized=False, shift_m=0.5)
    assert not early.holds_for(other)
    got = _files(write_results(folder, other, early=early))
    want = _files(write_results(ResultsFolder(tmp_path / "a", "run"), _result(localized=False, shift_m=0.5)))
    assert got == want
    assert "trajectory_in_map.tum" not in got


def test_a_failed_early_write_leaves_nothing_and_the_write_does_it_all(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = ResultsFolder(tmp_path / "b", "run")

    def full_disk(name: str, arrays: dict[str, object]) -> Path:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(folder, "write_npz", full_disk)
    assert write_results_early(folder, _result()) is None
    assert [p.name for p in folder.path.iterdir()] == []  # config.yaml and the trajectories taken out
    monkeypatch.undo()
    got = _files(write_results(folder, _result(), early=None))
    assert got == _files(write_results(ResultsFolder(tmp_path / "a", "run"), _result()))


def test_a_ctrl_c_in_the_early_write_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A partial result written after it has no calibration, stripes or map: no early file may stay."""
    folder = ResultsFolder(tmp_path / "b", "run")

    def ctrl_c(name: str, arrays: dict[str, object]) -> Path:
        raise KeyboardInterrupt

    monkeypatch.setattr(folder, "write_npz", ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        write_results_early(folder, _result())
    assert [p.name for p in folder.path.iterdir()] == []
