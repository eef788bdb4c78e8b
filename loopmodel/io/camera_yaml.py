"""Camera calibration files.

ROS ``camera_info`` YAML (camera_calibration_parsers layout), the KITTI ``calib.txt`` of a rectified
pair, and intrinsics from OpenCV-style YAML.

ROS YAML: ``image_width``, ``image_height``, ``camera_name``, ``camera_matrix``,
``distortion_model``, ``distortion_coefficients``, ``rectification_matrix`` and
``projection_matrix`` (each ``{rows, cols, data}``). Reading a left/right pair goes through
the project's CameraInfo conversion (:func:`loopmodel.io.mcap_io.calibration_from_camera_info`),
so a YAML pair and an MCAP ``camera_info`` topic give the same calibration.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from loopmodel.errors import CalibrationError, FormatError
from loopmodel.io.atomic import write_text_atomic
from loopmodel.io.mcap_io import calibration_from_camera_info
from loopmodel.types import StereoCalibration

F64 = NDArray[np.float64]


def _matrix(rows: int, cols: int, values: Any) -> dict[str, Any]:
    return {"rows": rows, "cols": cols, "data": [float(x) for x in np.asarray(values, dtype=float).ravel()]}


def camera_info_yaml(info: dict[str, Any], name: str) -> dict[str, Any]:
    """The ROS YAML dict of a CameraInfo message dict (as :func:`camera_info_dicts` gives)."""
    d = list(info["d"])
    return {
        "image_width": int(info["width"]),
        "image_height": int(info["height"]),
        "camera_name": name,
        "camera_matrix": _matrix(3, 3, info["k"]),
        "distortion_model": info.get("distortion_model", "plumb_bob"),
        "distortion_coefficients": _matrix(1, len(d), d),
        "rectification_matrix": _matrix(3, 3, info["r"]),
        "projection_matrix": _matrix(3, 4, info["p"]),
    }


def dump_yaml(data: dict[str, Any]) -> str:
    """YAML text with matrices in flow style (one line of numbers each)."""

    class _Dumper(yaml.SafeDumper):
        pass

    def _list(dumper: yaml.SafeDumper, value: list[Any]) -> yaml.Node:
        flow = all(isinstance(v, int | float) for v in value)
        return dumper.represent_sequence("tag:yaml.org,2002:seq", value, flow_style=flow)

    _Dumper.add_representer(list, _list)
    return yaml.dump(data, Dumper=_Dumper, sort_keys=False, width=200)


def write_camera_info_yaml(path: str | Path, info: dict[str, Any], name: str) -> Path:
    """Write one camera's ROS ``camera_info`` YAML (atomically)."""
    return write_text_atomic(path, dump_yaml(camera_info_yaml(info, name)))


def _load(path: Path) -> dict[str, Any]:
    from loopmodel.io.text import one_line, read_text_file

    try:
        data = yaml.safe_load(read_text_file(path, "camera YAML"))
    except (OSError, yaml.YAMLError, RecursionError) as exc:
        raise FormatError(path, f"cannot read YAML ({one_line(exc)})") from None
    if not isinstance(data, dict):
        raise FormatError(path, "expected a YAML mapping")
    return data


def _mat(data: dict[str, Any], key: str, n: int, path: Path) -> F64:
    v = data.get(key)
    if isinstance(v, dict):
        v = v.get("data")
    if v is None:
        raise CalibrationError(path, f"missing '{key}'")
    try:
        a = np.asarray(v, dtype=float).ravel()
    except (TypeError, ValueError):
        raise CalibrationError(path, f"'{key}' is not numeric") from None
    if n and a.size != n:
        raise CalibrationError(path, f"'{key}' needs {n} numbers, found {a.size}")
    return a


def camera_info_from_yaml(path: Path, data: dict[str, Any] | None = None) -> SimpleNamespace:
    """A CameraInfo-like record (``k``, ``d``, ``r``, ``p``, ``width``, ``height``) from ROS YAML."""
    data = _load(path) if data is None else data
    for key in ("image_width", "image_height"):
        if not isinstance(data.get(key), int) or data[key] <= 0:
            raise CalibrationError(path, f"'{key}' must be a positive integer")
    return SimpleNamespace(
        k=_mat(data, "camera_matrix", 9, path),
        d=_mat(data, "distortion_coefficients", 0, path),
        r=_mat(data, "rectification_matrix", 9, path),
        p=_mat(data, "projection_matrix", 12, path),
        width=int(data["image_width"]),
        height=int(data["image_height"]),
    )


def read_camera_info_pair(left: str | Path, right: str | Path) -> StereoCalibration:
    """Stereo calibration from a left and a right ROS ``camera_info`` YAML file."""
    lp, rp = Path(left), Path(right)
    return calibration_from_camera_info(camera_info_from_yaml(lp), camera_info_from_yaml(rp), f"{lp}/{rp.name}")


def write_kitti_calib(path: str | Path, P_left: F64, P_right: F64) -> Path:
    """KITTI ``calib.txt`` (``P0:``/``P1:`` rows) of a rectified pair."""
    rows = [f"P{i}: " + " ".join(f"{x:.12e}" for x in np.asarray(P).ravel()) for i, P in enumerate((P_left, P_right))]
    return write_text_atomic(path, "\n".join(rows) + "\n")


def read_intrinsics(path: str | Path) -> tuple[F64, F64, tuple[int, int] | None]:
    """Camera matrix K (3x3, pixels), distortion (OpenCV order) and image size (or None) of one camera from YAML.

    ROS ``camera_info`` (``camera_matrix``/``distortion_coefficients``), OpenCV-style
    (``camera_matrix`` as rows, ``dist_coeff``), or a stereo calibration summary of ``loopmodel
    calibrate stereo`` (its ``left`` camera).
    """
    p = Path(path)
    data = _load(p)
    if "camera_matrix" not in data and isinstance(data.get("left"), dict):
        data = data["left"]
    K = _mat(data, "camera_matrix", 9, p).reshape(3, 3)
    dkey = next((k for k in ("distortion_coefficients", "dist_coeff", "dist_coeffs", "distortion") if k in data), None)
    d = _mat(data, dkey, 0, p) if dkey else np.zeros(5)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(p, "camera_matrix needs finite, positive focal lengths")
    if not np.all(np.isfinite(d)):
        raise CalibrationError(p, "distortion has non-finite values")
    w, h = data.get("image_width"), data.get("image_height")
    size = (int(w), int(h)) if isinstance(w, int) and isinstance(h, int) else None
    return K, d, size
