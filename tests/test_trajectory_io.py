"""Trajectory files: round trips in TUM/KITTI/EuRoC, agreement with evo's readers, strictness."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from loopmodel.cli import main
from loopmodel.errors import FormatError, InputError
from loopmodel.geometry.se3 import se3_exp
from loopmodel.io.trajectory_io import (
    ns_to_seconds_text,
    read_trajectory,
    seconds_text_to_ns,
    write_trajectory,
)
from loopmodel.types import Trajectory


def _random_trajectory(rng: np.random.Generator, n: int = 50) -> Trajectory:
    t0 = 1_403_715_529_112_143_517
    times = t0 + np.cumsum(rng.integers(1, 100_000_000, n))
    poses = np.array([se3_exp(rng.normal(size=6) * [5, 5, 5, 2, 2, 2]) for _ in range(n)])
    return Trajectory(times, poses)


@pytest.mark.parametrize("fmt, ext", [("tum", ".tum"), ("kitti", ".kitti"), ("euroc", ".csv")])
def test_round_trip_full_precision(tmp_path: Path, rng: np.random.Generator, fmt: str, ext: str) -> None:
    traj = _random_trajectory(rng)
    path = write_trajectory(tmp_path / f"t{ext}", traj)
    back = read_trajectory(path, fmt, timestamps_ns=traj.timestamps_ns if fmt == "kitti" else None)  # type: ignore[arg-type]
    assert np.array_equal(back.timestamps_ns, traj.timestamps_ns)
    # KITTI stores the matrix itself: bit-exact; quaternion formats: within float rounding
    tol = 0.0 if fmt == "kitti" else 1e-14
    assert np.abs(back.world_from_cam - traj.world_from_cam).max() <= tol


def test_seconds_text_exact() -> None:
    for ns in (0, 1, 999_999_999, 1_403_715_529_112_143_517):
        assert seconds_text_to_ns(ns_to_seconds_text(ns)) == ns
    assert seconds_text_to_ns("1.403715529112143517e+09") == 1_403_715_529_112_143_517


def test_wrong_column_count_is_an_error(tmp_path: Path) -> None:
    p = tmp_path / "bad.txt"
    p.write_text("0.0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 1\n")
    with pytest.raises(FormatError, match="line 2: expected 8 columns, found 7"):
        read_trajectory(p, "tum")
    assert main(["no-such-command"]) == 2  # unknown command is a usage error, exit 2


def test_backwards_time_is_an_error(tmp_path: Path) -> None:
    p = tmp_path / "back.tum"
    p.write_text("1.0 0 0 0 0 0 0 1\n0.5 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="must increase"):
        read_trajectory(p)


EVO_CASES = [
    ("KITTI_00_gt.txt", "kitti"),
    ("KITTI_00_ORB.txt", "kitti"),
    ("V102_groundtruth.csv", "euroc"),
    ("V102.txt", "tum"),
    ("fr2_desk_groundtruth.txt", "tum"),
    ("fr2_desk_ORB.txt", "tum"),
]


@pytest.mark.parametrize("name, fmt", EVO_CASES)
def test_reads_like_evo(shared_data: Path, name: str, fmt: str) -> None:
    from evo.tools import file_interface

    path = shared_data / "trajectories" / name
    ours = read_trajectory(path, fmt)  # type: ignore[arg-type]
    if fmt == "kitti":
        theirs = file_interface.read_kitti_poses_file(str(path))
    elif fmt == "euroc":
        theirs = file_interface.read_euroc_csv_trajectory(str(path))
    else:
        theirs = file_interface.read_tum_trajectory_file(str(path))
    ref = np.array(theirs.poses_se3)
    assert ref.shape == ours.world_from_cam.shape
    # evo re-orthonormalises nothing: compare translations and rotations directly
    assert np.abs(ours.world_from_cam[:, :3, 3] - ref[:, :3, 3]).max() <= 1e-9
    # quaternion files: same rotation (evo normalises the same way)
    assert np.abs(ours.world_from_cam[:, :3, :3] - ref[:, :3, :3]).max() <= 1e-9
    if fmt != "kitti":
        assert np.allclose(ours.timestamps_s, theirs.timestamps, rtol=0, atol=1e-6)
