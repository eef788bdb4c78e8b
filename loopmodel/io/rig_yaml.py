"""Files of ``loopmodel vvs track``.

The rig of central cameras sharing one image, its mask, and the polyhedral model.

``rig.yaml``::

    cameras:                       # one per mirror (or lens), all in the same image
      - {xi: 1.0, px: 164.6, py: 164.6, u0: 256.0, v0: 256.0,
         cam_from_rig: [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}   # 4x4, metres
    mask: mask.png                 # optional, beside rig.yaml: pixel value j+1 = usable by camera j

``model.yaml``::

    box: {size_m: [0.30, 0.25, 0.20]}   # a box centred on the model frame, edges along its axes

Poses are ``rig_from_model`` (4x4, metres); on the command line as ``tx ty tz qx qy qz qw``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from loopmodel.errors import InputError
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import is_rotation, make_pose, quat_wxyz_from_rotation, rotation_from_quat_wxyz
from loopmodel.io.atomic import write_text_atomic
from loopmodel.pose.rig import CameraRig
from loopmodel.pose.tracking import PolyhedronModel

F64 = NDArray[np.float64]


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise InputError(path, f"not a readable YAML file ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise InputError(path, "expected a YAML mapping")
    return data


def _matrix(path: Path, key: str, value: Any) -> F64:
    try:
        T = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(path, f"{key}: expected a 4x4 matrix of numbers") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not is_rotation(T[:3, :3], 1e-5):
        raise InputError(path, f"{key}: expected a 4x4 rigid transform (rotation and translation in metres)")
    return T


def read_rig(path: str | Path) -> tuple[CameraRig, NDArray[np.uint8] | None]:
    """The rig and its label mask (None when the file names none)."""
    import cv2

    p = Path(path)
    data = _read_yaml(p)
    cams_in = data.get("cameras")
    if not isinstance(cams_in, list) or not cams_in:
        raise InputError(p, "cameras: expected a list of cameras (xi, px, py, u0, v0, cam_from_rig)")
    cams, poses = [], []
    for j, c in enumerate(cams_in):
        key = f"cameras[{j}]"
        if not isinstance(c, dict):
            raise InputError(p, f"{key}: expected a mapping")
        try:
            vals = {k: float(c[k]) for k in ("xi", "px", "py", "u0", "v0")}
        except (KeyError, TypeError, ValueError):
            raise InputError(p, f"{key}: needs numbers xi, px, py, u0, v0") from None
        if not (vals["px"] > 0 and vals["py"] > 0 and 0 <= vals["xi"] <= 1.5):
            raise InputError(p, f"{key}: px, py must be > 0 and xi in [0, 1.5]")
        cams.append(CentralCamera(vals["px"], vals["py"], vals["u0"], vals["v0"], vals["xi"]))
        poses.append(_matrix(p, f"{key}.cam_from_rig", c.get("cam_from_rig", np.eye(4).tolist())))
    mask = None
    if data.get("mask"):
        from loopmodel.io.images import MAX_IMAGE_PIXELS, check_image_bytes, decode_quietly, read_image_bytes

        mp = (p.parent / str(data["mask"])).resolve()
        if not mp.is_relative_to(p.parent.resolve()):  # issue 34: paths a data file names stay in its folder
            raise InputError(p, f"mask: {data['mask']!r} must be a path inside {p.parent}")
        # a regular file, its declared size checked before decoding (cv2.imread waited on a FIFO)
        raw = read_image_bytes(mp)
        check_image_bytes(raw, MAX_IMAGE_PIXELS, mp)
        mask = decode_quietly(raw, cv2.IMREAD_UNCHANGED) if raw else None
        if mask is None or mask.ndim != 2:
            raise InputError(mp, "mask: expected a one-channel label image (value j+1 = camera j)")
    return CameraRig(tuple(cams), tuple(poses)), mask


def write_rig(path: str | Path, rig: CameraRig, mask: NDArray[np.uint8] | None = None) -> Path:
    """Write ``rig.yaml`` (and ``mask.png`` beside it when given)."""
    import cv2

    p = Path(path)
    data: dict[str, Any] = {
        "cameras": [
            {"xi": c.xi, "px": c.px, "py": c.py, "u0": c.u0, "v0": c.v0, "cam_from_rig": T.tolist()}
            for c, T in zip(rig.cameras, rig.cam_from_rig, strict=True)
        ]
    }
    if mask is not None:
        cv2.imwrite(str(p.with_name("mask.png")), mask)
        data["mask"] = "mask.png"
    return write_text_atomic(p, yaml.safe_dump(data, sort_keys=False))


def read_model(path: str | Path) -> PolyhedronModel:
    """The polyhedral model of ``model.yaml`` (a box)."""
    p = Path(path)
    data = _read_yaml(p)
    box = data.get("box")
    if not isinstance(box, dict):
        raise InputError(p, "expected 'box: {size_m: [x, y, z]}' (boxes are the models supported)")
    try:
        size = tuple(float(v) for v in box["size_m"])
    except (KeyError, TypeError, ValueError):
        raise InputError(p, "box.size_m: expected three lengths in metres") from None
    if len(size) != 3 or not all(s > 0 for s in size):
        raise InputError(p, "box.size_m: expected three positive lengths in metres")
    return PolyhedronModel.box((size[0], size[1], size[2]))


def write_model(path: str | Path, size_m: tuple[float, float, float]) -> Path:
    """Write ``model.yaml`` for a box."""
    return write_text_atomic(Path(path), yaml.safe_dump({"box": {"size_m": [float(s) for s in size_m]}}))


def parse_pose(text: str) -> F64:
    """``tx ty tz qx qy qz qw`` (metres, unit quaternion) or the path of a file holding it."""
    src = Path(text)
    if src.is_file():
        try:
            text = src.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(src, f"cannot be read ({exc})") from None
    try:
        v = np.array([float(x) for x in text.replace(",", " ").split()])
    except ValueError:
        raise InputError("--init", f"expected 'tx ty tz qx qy qz qw', got '{text.strip()}'") from None
    if v.shape != (7,) or not np.all(np.isfinite(v)) or abs(np.linalg.norm(v[3:]) - 1) > 1e-3:
        raise InputError("--init", "expected 7 numbers 'tx ty tz qx qy qz qw' with a unit quaternion")
    q = v[[6, 3, 4, 5]]
    return make_pose(rotation_from_quat_wxyz(q / np.linalg.norm(q)), v[:3])


def format_pose(T: F64) -> str:
    """``tx ty tz qx qy qz qw`` of a pose."""
    q = quat_wxyz_from_rotation(T[:3, :3])
    return " ".join(f"{x:.9g}" for x in (*T[:3, 3], q[1], q[2], q[3], q[0]))
