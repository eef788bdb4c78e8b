"""KITTI odometry folders.

``image_0``/``image_1`` (or ``image_l``/``image_r``), ``calib.txt`` (P0/P1, or the unnamed two-line
form), optional ``times.txt`` and ``poses.txt``.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from loopmodel.errors import CalibrationError, FormatError, InputError
from loopmodel.io.base import FolderSequence
from loopmodel.io.images import MAX_IMAGE_PIXELS, image_size
from loopmodel.io.text import read_text_file
from loopmodel.io.trajectory_io import read_trajectory, seconds_text_to_ns
from loopmodel.types import StereoCalibration, Trajectory

logger = logging.getLogger(__name__)

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
    for lineno, line in enumerate(read_text_file(path).splitlines(), 1):
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
    for name, P in (("P0", P0), ("P1", P1)):
        if not np.array_equal(P[2], [0.0, 0.0, 1.0, 0.0]):
            raise CalibrationError(source, f"{name}: the third row of a rectified projection must be 0 0 1 0")
    right_from_left = np.eye(4)
    right_from_left[0, 3] = (P1[0, 3] - P0[0, 3]) / K1[0, 0]
    right_from_left[1, 3] = (P1[1, 3] - P0[1, 3]) / K1[1, 1]
    cal = StereoCalibration(K0, K1, right_from_left, size, rectified=True)
    return cal.check(source)


class KittiSequence(FolderSequence):
    """A KITTI odometry sequence folder."""

    format_name = "kitti"

    def __init__(self, path: Path, rate_hz: float = 10.0, max_image_pixels: int = MAX_IMAGE_PIXELS) -> None:
        super().__init__(path)
        self.max_image_pixels = max_image_pixels
        left_dir = right_dir = None
        for a, b in IMAGE_DIRS:
            if (path / a).is_dir() and (path / b).is_dir():
                left_dir, right_dir = path / a, path / b
                break
        if left_dir is None or right_dir is None:
            raise FormatError(path, "no KITTI image folders (image_0/image_1 or image_l/image_r)")
        left_all = sorted(p for p in left_dir.iterdir() if p.suffix.lower() in IMAGE_EXTS)
        right_all = sorted(p for p in right_dir.iterdir() if p.suffix.lower() in IMAGE_EXTS)
        if not left_all:
            raise FormatError(left_dir, "no images found")
        # left and right images pair by file name (stem), never by sorted position
        right_by_stem = {p.stem: p for p in right_all}
        left_stems = {p.stem for p in left_all}
        self._left_index = [i for i, p in enumerate(left_all) if p.stem in right_by_stem]
        self._left = [left_all[i] for i in self._left_index]
        self._right = [right_by_stem[p.stem] for p in self._left]
        self._n_left_files = len(left_all)
        only_left = [p.name for p in left_all if p.stem not in right_by_stem]
        only_right = [p.name for p in right_all if p.stem not in left_stems]
        if not self._left:
            raise InputError(
                path, f"no left image in {left_dir.name} has a right image of the same name in {right_dir.name}"
            )
        if only_left or only_right:
            logger.warning(
                "%s: %d unpaired images skipped (left only: %s; right only: %s)",
                path,
                len(only_left) + len(only_right),
                ", ".join(only_left[:5]) or "none",
                ", ".join(only_right[:5]) or "none",
            )
        self.unpaired = only_left + only_right
        size_l = image_size(self._left[0], max_image_pixels)
        size_r = image_size(self._right[0], max_image_pixels)
        if size_l != size_r:
            raise InputError(path, f"left and right image sizes differ: {size_l} vs {size_r}")
        P0, P1 = parse_kitti_calib(path / "calib.txt")
        self._calibration = calibration_from_projections(P0, P1, size_l, str(path / "calib.txt"))
        self._times = self._read_times(path, rate_hz)
        self._pairs = list(zip(self._times, self._left, self._right, strict=True))
        self._check_image_files()
        self._gt = self._read_poses(path)

    def _read_times(self, path: Path, rate_hz: float) -> list[int]:
        """Timestamps of the paired frames (``times.txt`` has one line per left image)."""
        times_file = path / "times.txt"
        n = self._n_left_files
        if not os.path.lexists(times_file):  # a FIFO, folder or link loop is read (and refused)
            return [round(i * 1e9 / rate_hz) for i in self._left_index]
        lines = [s.strip() for s in read_text_file(times_file).splitlines() if s.strip()]
        if len(lines) != n:
            raise FormatError(times_file, f"{len(lines)} times for {n} images")
        try:
            times = [seconds_text_to_ns(s) for s in lines]
        except Exception:
            raise FormatError(times_file, "times must be decimal seconds, one per line") from None
        for i in range(1, n):
            if times[i] <= times[i - 1]:
                raise FormatError(times_file, f"timestamps go backwards at line {i + 1}")
        return [times[i] for i in self._left_index]

    def _read_poses(self, path: Path) -> Trajectory | None:
        """Ground truth.

        One pose row per left image (row i = image i in sorted order); fewer than 90 % of the rows
        it needs is an error, a shortfall below that a warning.
        """
        for name in ("poses.txt", "groundtruth.txt"):
            p = path / name
            if os.path.lexists(p):  # a FIFO, folder or link loop is read (and refused), not skipped
                traj = read_trajectory(p, "kitti", check=False)
                n_img = self._n_left_files
                if len(traj) < 0.9 * n_img or len(traj) > n_img:
                    raise FormatError(p, f"{len(traj)} pose rows for {n_img} images (expected one row per image)")
                if len(traj) < n_img:
                    logger.warning(
                        "%s: %d pose rows for %d images; the last frames have no ground truth", p, len(traj), n_img
                    )
                rows = [k for k, i in enumerate(self._left_index) if i < len(traj)]
                idx = [self._left_index[k] for k in rows]
                times = np.asarray([self._times[k] for k in rows])
                return Trajectory(times, traj.world_from_cam[idx]).check(str(p))
        return None
