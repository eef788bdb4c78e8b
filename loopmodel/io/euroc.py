"""EuRoC ASL folders.

``mav0/cam0``, ``mav0/cam1`` (``data.csv``, ``data/``, ``sensor.yaml``) and optional
``mav0/state_groundtruth_estimate0/data.csv``. Images are not rectified; the calibration says so and
the front end rectifies.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import yaml

from loopmodel.errors import CalibrationError, FormatError, InputError
from loopmodel.geometry.se3 import invert_pose
from loopmodel.io.base import FolderSequence
from loopmodel.io.text import read_text_file
from loopmodel.io.trajectory_io import read_trajectory
from loopmodel.types import StereoCalibration, Trajectory

logger = logging.getLogger(__name__)


def euroc_root(path: Path) -> Path | None:
    """The folder holding ``cam0``/``cam1`` (the path itself or its ``mav0``), or None."""
    for root in (path / "mav0", path):
        if (root / "cam0" / "data.csv").is_file() and (root / "cam1" / "data.csv").is_file():
            return root
    return None


def _read_sensor_yaml(path: Path) -> dict:
    if not path.is_file():
        raise CalibrationError(path, "camera sensor.yaml is missing")
    text = "\n".join(s for s in read_text_file(path, "sensor.yaml").splitlines() if not s.startswith("%"))
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError:
        raise CalibrationError(path, "sensor.yaml is not valid YAML") from None
    if not isinstance(data, dict):
        raise CalibrationError(path, "sensor.yaml is empty or not a mapping of keys")
    for key in ("T_BS", "intrinsics", "resolution"):
        if key not in data:
            raise CalibrationError(path, f"sensor.yaml lacks key '{key}'")
    return data


def _camera_from_yaml(data: dict, path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    try:
        body_from_cam = np.array(data["T_BS"]["data"], dtype=float).reshape(4, 4)
        fu, fv, cu, cv = (float(v) for v in data["intrinsics"])
        dist = np.array(data.get("distortion_coefficients", [0, 0, 0, 0]), dtype=float)
        w, h = (int(v) for v in data["resolution"])
    except (KeyError, TypeError, ValueError):
        raise CalibrationError(path, "sensor.yaml: T_BS, intrinsics or resolution malformed") from None
    K = np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]])
    if dist.size == 4 and camera_model_of(data, path) == "pinhole":
        dist = np.append(dist, 0.0)
    return K, dist, body_from_cam, (w, h)


def camera_model_of(data: dict, source: Path | None = None) -> str:
    """Camera model of a sensor.yaml: ``equidistant`` or ``pinhole``.

    ``equidistant`` for a sensor.yaml ``distortion_model: equidistant`` (Kannala-Brandt, k1..k4),
    else ``pinhole`` (radial-tangential).
    """
    model = str(data.get("distortion_model", "")).lower()
    if model in ("equidistant", "fisheye"):
        return "equidistant"
    if model in ("", "none", "radial-tangential", "radtan", "plumb_bob", "pinhole"):
        return "pinhole"
    raise CalibrationError(
        source, f"distortion_model '{model}' is not one this reader knows (radial-tangential, equidistant)"
    )


def stereo_calibration_of(root: Path, source: Path | None = None) -> tuple[StereoCalibration, np.ndarray]:
    """Unrectified stereo calibration and ``body_from_cam0`` of two sensor.yaml files.

    Of ``root/cam0/sensor.yaml`` and ``root/cam1/sensor.yaml`` (``source`` names the sequence in
    size errors).
    """
    yaml0 = _read_sensor_yaml(root / "cam0" / "sensor.yaml")
    yaml1 = _read_sensor_yaml(root / "cam1" / "sensor.yaml")
    K0, d0, body_from_cam0, size0 = _camera_from_yaml(yaml0, root / "cam0" / "sensor.yaml")
    K1, d1, body_from_cam1, size1 = _camera_from_yaml(yaml1, root / "cam1" / "sensor.yaml")
    if camera_model_of(yaml0) != camera_model_of(yaml1):
        raise CalibrationError(root / "cam1" / "sensor.yaml", "distortion_model differs from cam0's")
    if size0 != size1:
        raise InputError(source or root, f"left and right image sizes differ: {size0} vs {size1}")
    right_from_left = invert_pose(body_from_cam1) @ body_from_cam0
    model = camera_model_of(yaml0)
    cal = StereoCalibration(K0, K1, right_from_left, size0, d0, d1, rectified=False, camera_model=model)
    return cal.check(str(root / "cam0" / "sensor.yaml")), body_from_cam0


def _existing(cam: Path, times: list[int], names: list[str]) -> tuple[list[int], list[str]]:
    """The rows of ``cam/data.csv`` whose image is in ``cam/data``; the others skipped with a warning."""
    missing = [n for n in names if not os.path.lexists(cam / "data" / n)]
    if not missing:
        return times, names
    logger.warning(
        "%s: %d of %d rows name a missing image, skipped (%s)",
        cam / "data.csv",
        len(missing),
        len(names),
        ", ".join(missing[:5]),
    )
    gone = set(missing)
    kept = [(t, n) for t, n in zip(times, names, strict=True) if n not in gone]
    return [t for t, _ in kept], [n for _, n in kept]


def _read_index(csv: Path) -> tuple[list[int], list[str]]:
    times: list[int] = []
    names: list[str] = []
    for lineno, line in enumerate(read_text_file(csv, "image index").splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [p.strip() for p in s.split(",")]
        if len(parts) != 2:
            raise FormatError(csv, f"line {lineno}: expected 2 columns (timestamp, filename)")
        try:
            t = int(parts[0])
        except ValueError:
            raise FormatError(csv, f"line {lineno}: timestamp is not an integer") from None
        if t < 0:
            raise FormatError(csv, f"line {lineno}: negative timestamp {t}")
        name = parts[1]
        # confined to the camera's data/ folder: a plain file name, no absolute path, no '..'
        if not name or name in (".", "..") or "/" in name or "\\" in name or "\0" in name:
            raise FormatError(csv, f"line {lineno}: image '{name}' must be a file name inside data/")
        if times and t <= times[-1]:
            raise FormatError(csv, f"line {lineno}: timestamps go backwards ({t} after {times[-1]})")
        times.append(t)
        names.append(name)
    return times, names


class EurocSequence(FolderSequence):
    """A EuRoC MAV sequence (stereo pairs matched by timestamp)."""

    format_name = "euroc"

    def __init__(self, path: Path, tolerance_ns: int = 1_000_000, max_image_pixels: int = 100_000_000) -> None:
        super().__init__(path)
        self.max_image_pixels = max_image_pixels
        root = euroc_root(path)
        if root is None:
            raise FormatError(path, "not a EuRoC folder (mav0/cam0/data.csv and mav0/cam1/data.csv)")
        self._root = root
        tl, nl = _existing(root / "cam0", *_read_index(root / "cam0" / "data.csv"))
        tr, nr = _existing(root / "cam1", *_read_index(root / "cam1" / "data.csv"))
        self._pairs: list[tuple[int, Path, Path]] = []
        j = 0
        for t, name in zip(tl, nl, strict=True):
            while j < len(tr) and tr[j] < t - tolerance_ns:
                j += 1
            if j < len(tr) and abs(tr[j] - t) <= tolerance_ns:
                self._pairs.append((t, root / "cam0" / "data" / name, root / "cam1" / "data" / nr[j]))
                j += 1
        if not self._pairs:
            raise InputError(path, "no left/right image pairs with matching timestamps")
        self._check_image_files()
        self._calibration, self._body_from_cam0 = stereo_calibration_of(root, path)
        self._gt = self._read_ground_truth(root)

    def _read_ground_truth(self, root: Path) -> Trajectory | None:
        gt = root / "state_groundtruth_estimate0" / "data.csv"
        if not gt.is_file():
            return None
        world_from_body = read_trajectory(gt, "euroc")
        return Trajectory(world_from_body.timestamps_ns, world_from_body.world_from_cam @ self._body_from_cam0)
