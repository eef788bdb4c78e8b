"""Stereo calibrations from files, for bags without CameraInfo.

EuRoC and TUM-VI ROS 1 bags carry none. Formats: a EuRoC-style folder (``cam0/sensor.yaml`` and
``cam1/sensor.yaml``, or under ``mav0/``), a Kalibr ``camchain.yaml`` (``cam0``/``cam1`` with
``intrinsics``, ``distortion_model`` radtan or equidistant, ``distortion_coeffs``, ``resolution``,
and ``cam1.T_cn_cnm1`` = ``cam1_from_cam0``), the summary YAML of ``loopmodel calibrate stereo``
(``left``/``right`` ROS ``camera_info``) or a KITTI ``calib.txt``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from loopmodel.errors import CalibrationError
from loopmodel.io.euroc import stereo_calibration_of
from loopmodel.io.kitti import calibration_from_projections, parse_kitti_calib
from loopmodel.types import StereoCalibration


def read_stereo_calibration(path: str | Path, image_size: tuple[int, int] | None = None) -> StereoCalibration:
    """The calibration in ``path``.

    ``image_size`` (width, height) is needed for a KITTI calib.txt, which holds none, and checked
    against a sensor.yaml's resolution.
    """
    p = Path(path)
    if p.is_file() and p.name == "sensor.yaml":
        p = p.parent.parent
    for root in (p / "mav0", p):
        if (root / "cam0" / "sensor.yaml").is_file() and (root / "cam1" / "sensor.yaml").is_file():
            cal, _body_from_cam0 = stereo_calibration_of(root)
            if image_size is not None and cal.image_size != tuple(image_size):
                raise CalibrationError(
                    root / "cam0" / "sensor.yaml",
                    f"resolution {cal.image_size[0]}x{cal.image_size[1]}, images are {image_size[0]}x{image_size[1]}",
                )
            return cal
    if p.is_file() and p.suffix.lower() in (".yaml", ".yml"):
        cal = calibrate_stereo_summary(p) or kalibr_calibration(p)
        if image_size is not None and cal.image_size != tuple(image_size):
            raise CalibrationError(p, f"resolution {cal.image_size}, images are {tuple(image_size)}")
        return cal
    calib_txt = p / "calib.txt" if p.is_dir() else p
    if calib_txt.is_file():
        if image_size is None:
            raise CalibrationError(calib_txt, "a KITTI calib.txt needs the image size of the sequence")
        P0, P1 = parse_kitti_calib(calib_txt)
        return calibration_from_projections(P0, P1, image_size, str(calib_txt))
    raise CalibrationError(
        p,
        "expected a folder with cam0/sensor.yaml and cam1/sensor.yaml, a Kalibr camchain.yaml, "
        "a 'loopmodel calibrate stereo' YAML or a KITTI calib.txt",
    )


def calibrate_stereo_summary(path: Path) -> StereoCalibration | None:
    """The calibration of a ``loopmodel calibrate stereo`` summary YAML, or None for another YAML.

    The summary holds the ROS ``camera_info`` of each camera under ``left`` and ``right``; they are
    read as the ``calib_left.yaml`` / ``calib_right.yaml`` pair written beside it.
    """
    try:
        data: Any = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return None
    if not (isinstance(data, dict) and isinstance(data.get("left"), dict) and isinstance(data.get("right"), dict)):
        return None
    from loopmodel.io.camera_yaml import camera_info_from_yaml
    from loopmodel.io.mcap_io import calibration_from_camera_info

    left, right = (camera_info_from_yaml(path, data[side]) for side in ("left", "right"))
    return calibration_from_camera_info(left, right, str(path))


def kalibr_calibration(path: Path) -> StereoCalibration:
    """Stereo calibration of a Kalibr camchain.yaml (pinhole cameras, radtan or equidistant)."""
    try:
        data: Any = yaml.safe_load(path.read_text())
        cams = [data["cam0"], data["cam1"]]
        K: list[np.ndarray] = []
        D: list[np.ndarray] = []
        sizes: list[tuple[int, int]] = []
        models: list[str] = []
        for c in cams:
            fu, fv, cu, cv = (float(v) for v in c["intrinsics"])
            K.append(np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]]))
            model = str(c.get("distortion_model", "radtan")).lower()
            d = np.array(c.get("distortion_coeffs", [0, 0, 0, 0]), dtype=float)
            models.append("equidistant" if model in ("equidistant", "equi", "fisheye") else "pinhole")
            D.append(d if models[-1] == "equidistant" or d.size != 4 else np.append(d, 0.0))
            w, h = (int(v) for v in c["resolution"])
            sizes.append((w, h))
        right_from_left = np.array(cams[1]["T_cn_cnm1"], dtype=float).reshape(4, 4)
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(
            path, f"not a Kalibr camchain with cam0 and cam1 ({type(exc).__name__}: {' '.join(str(exc).split())})"
        ) from None
    if models[0] != models[1] or sizes[0] != sizes[1]:
        raise CalibrationError(path, "cam0 and cam1 differ in distortion model or resolution")
    cal = StereoCalibration(K[0], K[1], right_from_left, sizes[0], D[0], D[1], False, models[0])
    return cal.check(str(path))


CAMERA_PARAMS = ("fx", "fy", "cx", "cy", "k1", "k2")


def refined_calibration_yaml(cal: StereoCalibration, report: dict[str, Any]) -> str:
    """``calibration_refined.yaml`` (issue 31): a Kalibr camchain that ``--calib`` reads, with sigmas.

    ``cam0``/``cam1`` as Kalibr writes them (``intrinsics`` fu fv cu cv, ``distortion_coeffs`` k1 k2
    p1 p2 k3, ``cam1.T_cn_cnm1`` = ``right_from_left``), each camera's posterior standard deviations
    under ``sigma``; ``loopmodel_selfcal`` holds every parameter's recorded and refined value, prior
    and posterior sigma, move in sigmas and observability, and the refined light plane.
    """
    import json

    report = json.loads(json.dumps(report, default=float))  # plain floats for YAML
    params: dict[str, Any] = dict(report.get("parameters", {}))
    cams: dict[str, Any] = {}
    for i, (side, K, d) in enumerate((("left", cal.K_left, cal.dist_left), ("right", cal.K_right, cal.dist_right))):
        sig = {
            f"{p}{'_px' if p[0] in 'fc' else ''}": params.get(f"{p}_{side}{'_px' if p[0] in 'fc' else ''}", {}).get(
                "sigma"
            )
            for p in CAMERA_PARAMS
        }
        cam: dict[str, Any] = {
            "camera_model": "pinhole",
            "intrinsics": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
            "distortion_model": "radtan",
            "distortion_coeffs": [float(v) for v in np.asarray(d, float).ravel()],
            "resolution": [int(cal.image_size[0]), int(cal.image_size[1])],
            "sigma": {k: (None if v is None else float(v)) for k, v in sig.items()},
        }
        if i == 1:
            cam["T_cn_cnm1"] = [[float(v) for v in row] for row in cal.right_from_left]
            cam["sigma"].update(
                {
                    k: (None if params.get(k) is None else float(params[k]["sigma"]))
                    for k in ("rot_x_deg", "rot_y_deg", "rot_z_deg", "baseline_m")
                }
            )
        cams[f"cam{i}"] = cam
    cams["loopmodel_selfcal"] = {
        "parameters": params,
        "light_plane": report.get("light_plane"),
        "note": "posterior sigma per parameter; rot_*_deg: correction of the recorded stereo rotation",
    }
    return yaml.safe_dump(cams, sort_keys=False)
