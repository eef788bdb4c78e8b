"""KITTI odometry folders: ``image_0``/``image_1`` (or ``image_l``/``image_r``), ``calib.txt``
(P0/P1, or the unnamed two-line form), optional ``times.txt`` and ``poses.txt``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from loopmodel.errors import CalibrationError, FormatError, InputError
from loopmodel.io.base import FolderSequence
from loopmodel.io.images import image_size
from loopmodel.io.trajectory_io import read_trajectory, seconds_text_to_ns
from loopmodel.types import StereoCalibration, Trajectory

IMAGE_DIRS = (("image_0", "image_1"), ("image_l", "image_r"))
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".pgm", ".bmp")


def is_kitti_folder(path: Path) -> bool:
    """True when the folder has a KITTI image pair layout and a calib.txt."""
    return (
        path.is_dir()
        and (path / "calib.txt").is_file()
        and any((path / a).is_dir() and (path / b).is_dir() for a, b in IMAGE_DIRS)
    )


def parse_kitti_calib(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """P0 and P1 (3x4) from a KITTI calib.txt (named ``P0:`` lines or two unnamed lines)."""
    named: dict[str, np.ndarray] = {}
    unnamed: list[np.ndarray] = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        label, _, rest = s.partition(":") if ":" in s else ("", "", s)
        try:
            vals = np.array([float(v) for v in rest.split()])
        except ValueError:
            raise CalibrationError(path, f"line {lineno}: non-numeric value") from None
        if label:
            if label.strip() in ("P0", "P1") and vals.size != 12:
                raise CalibrationError(path, f"line {lineno}: {label} needs 12 numbers, found {vals.size}")
            named[label.strip()] = vals
        else:
            if vals.size != 12:
                raise CalibrationError(path, f"line {lineno}: expected 12 numbers, found {vals.size}")
            unnamed.append(vals)
    if "P0" in named and "P1" in named:
        return named["P0"].reshape(3, 4), named["P1"].reshape(3, 4)
    if len(unnamed) >= 2:
        return unnamed[0].reshape(3, 4), unnamed[1].reshape(3, 4)
    raise CalibrationError(path, "expected P0 and P1 projection matrices (12 numbers each)")


def calibration_from_projections(
    P0: np.ndarray, P1: np.ndarray, size: tuple[int, int], source: str
) -> StereoCalibration:
    """Rectified stereo calibration from two 3x4 projection matrices (P1 carries -fx*B)."""
    K0, K1 = P0[:3, :3].copy(), P1[:3, :3].copy()
    if not np.all(np.isfinite(P0)) or not np.all(np.isfinite(P1)):
        raise CalibrationError(source, "projection matrix has non-finite values")
    if K0[0, 0] <= 0 or K1[0, 0] <= 0:
        raise CalibrationError(source, f"focal length must be positive, got {K0[0, 0]}, {K1[0, 0]}")
    right_from_left = np.eye(4)
    right_from_left[0, 3] = (P1[0, 3] - P0[0, 3]) / K1[0, 0]
    right_from_left[1, 3] = (P1[1, 3] - P0[1, 3]) / K1[1, 1]
    cal = StereoCalibration(K0, K1, right_from_left, size, rectified=True)
    return cal.check(source)


class KittiSequence(FolderSequence):
    """A KITTI odometry sequence folder."""

    format_name = "kitti"

    def __init__(self, path: Path, rate_hz: float = 10.0) -> None:
        super().__init__(path)
        left_dir = right_dir = None
        for a, b in IMAGE_DIRS:
            if (path / a).is_dir() and (path / b).is_dir():
                left_dir, right_dir = path / a, path / b
                break
        if left_dir is None or right_dir is None:
            raise FormatError(path, "no KITTI image folders (image_0/image_1 or image_l/image_r)")
        self._left = sorted(p for p in left_dir.iterdir() if p.suffix.lower() in IMAGE_EXTS)
        self._right = sorted(p for p in right_dir.iterdir() if p.suffix.lower() in IMAGE_EXTS)
        if not self._left:
            raise FormatError(left_dir, "no images found")
        if len(self._left) != len(self._right):
            raise InputError(
                path,
                f"left and right image counts differ: {len(self._left)} in {left_dir.name}, "
                f"{len(self._right)} in {right_dir.name}",
            )
        size_l, size_r = image_size(self._left[0]), image_size(self._right[0])
        if size_l != size_r:
            raise InputError(path, f"left and right image sizes differ: {size_l} vs {size_r}")
        P0, P1 = parse_kitti_calib(path / "calib.txt")
        self._calibration = calibration_from_projections(P0, P1, size_l, str(path / "calib.txt"))
        self._times = self._read_times(path, rate_hz)
        self._pairs = list(zip(self._times, self._left, self._right, strict=True))
        self._gt = self._read_poses(path)

    def _read_times(self, path: Path, rate_hz: float) -> list[int]:
        times_file = path / "times.txt"
        n = len(self._left)
        if not times_file.is_file():
            return [round(i * 1e9 / rate_hz) for i in range(n)]
        lines = [s.strip() for s in times_file.read_text().splitlines() if s.strip()]
        if len(lines) != n:
            raise FormatError(times_file, f"{len(lines)} times for {n} images")
        try:
            times = [seconds_text_to_ns(s) for s in lines]
        except Exception:
            raise FormatError(times_file, "times must be decimal seconds, one per line") from None
        for i in range(1, n):
            if times[i] <= times[i - 1]:
                raise FormatError(times_file, f"timestamps go backwards at line {i + 1}")
        return times

    def _read_poses(self, path: Path) -> Trajectory | None:
        for name in ("poses.txt", "groundtruth.txt"):
            p = path / name
            if p.is_file():
                traj = read_trajectory(p, "kitti", check=False)
                n = min(len(traj), len(self._times))
                return Trajectory(np.asarray(self._times[:n]), traj.world_from_cam[:n]).check(str(p))
        return None
