"""Stereo calibrations from files, for bags without CameraInfo (EuRoC and TUM-VI ROS 1 bags
carry none): a EuRoC-style folder (``cam0/sensor.yaml`` and ``cam1/sensor.yaml``, or under
``mav0/``) or a KITTI ``calib.txt``."""

from __future__ import annotations

from pathlib import Path

from loopmodel.errors import CalibrationError
from loopmodel.io.euroc import stereo_calibration_of
from loopmodel.io.kitti import calibration_from_projections, parse_kitti_calib
from loopmodel.types import StereoCalibration


def read_stereo_calibration(path: str | Path, image_size: tuple[int, int] | None = None) -> StereoCalibration:
    """The calibration in ``path``; ``image_size`` (width, height) is needed for a KITTI
    calib.txt, which holds none, and checked against a sensor.yaml's resolution."""
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
    calib_txt = p / "calib.txt" if p.is_dir() else p
    if calib_txt.is_file():
        if image_size is None:
            raise CalibrationError(calib_txt, "a KITTI calib.txt needs the image size of the sequence")
        P0, P1 = parse_kitti_calib(calib_txt)
        return calibration_from_projections(P0, P1, image_size, str(calib_txt))
    raise CalibrationError(p, "expected a folder with cam0/sensor.yaml and cam1/sensor.yaml, or a KITTI calib.txt")
