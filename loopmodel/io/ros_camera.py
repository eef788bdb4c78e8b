"""ROS camera messages read from any bag (ROS 1 or ROS 2, decoded by ``rosbags`` or ``mcap_ros2``).

Image encodings beyond the plain ones, and CameraInfo distortion models.

Images come back as uint8 (grey HxW or BGR HxWx3) as the front end uses them: ``mono16``
is scaled to 8 bits like ``cv_bridge`` does (divided by 256), ``bayer_*`` is debayered to
BGR, ``bgra8``/``rgba8`` lose alpha. CameraInfo ``plumb_bob`` (5 coefficients) and
``rational_polynomial`` (8) are OpenCV's standard model; ``equidistant`` (4, Kannala-Brandt)
is OpenCV's fisheye model.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import CalibrationError, FormatError
from loopmodel.io.images import MAX_IMAGE_PIXELS, check_declared_size, check_image_bytes, decode_quietly
from loopmodel.io.mcap_io import calibration_from_camera_info
from loopmodel.types import StereoCalibration

# ROS bayer names -> OpenCV conversion codes (OpenCV names the pattern by the second row,
# the same mapping cv_bridge uses).
_BAYER = {
    "bayer_rggb8": cv2.COLOR_BayerBG2BGR,
    "bayer_bggr8": cv2.COLOR_BayerRG2BGR,
    "bayer_gbrg8": cv2.COLOR_BayerGR2BGR,
    "bayer_grbg8": cv2.COLOR_BayerGB2BGR,
}
# encoding -> (channels, bytes per channel)
_RAW = {
    "mono8": (1, 1),
    "8uc1": (1, 1),
    "mono16": (1, 2),
    "16uc1": (1, 2),
    "bgr8": (3, 1),
    "rgb8": (3, 1),
    "8uc3": (3, 1),
    "bgra8": (4, 1),
    "rgba8": (4, 1),
    "8uc4": (4, 1),
    **{k: (1, 1) for k in _BAYER},
}
IMAGE_ENCODINGS = tuple(_RAW)
DISTORTION_MODELS = {
    "plumb_bob": "pinhole",
    "rational_polynomial": "pinhole",
    "equidistant": "equidistant",
    "": "pinhole",
}


def _field(msg: Any, name: str) -> Any:
    """A CameraInfo field under its ROS 2 (lower case) or ROS 1 (upper case) name."""
    if hasattr(msg, name):
        return getattr(msg, name)
    return getattr(msg, name.upper())


def raw_image_array(msg: Any, topic: str, max_pixels: int = MAX_IMAGE_PIXELS) -> NDArray[Any]:
    """The pixels of a ``sensor_msgs/Image`` as stored (HxW, HxWxC; uint8 or uint16).

    No copy where the rows are packed.
    """
    enc = str(msg.encoding).lower()
    if enc not in _RAW:
        raise FormatError(topic, f"unsupported image encoding '{msg.encoding}' (expected one of {', '.join(_RAW)})")
    c, nbytes = _RAW[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    check_declared_size(w, h, max_pixels, topic)
    data = np.frombuffer(msg.data, np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data.view(np.uint8)
    row = w * c * nbytes
    if h <= 0 or w <= 0 or step < row or data.size < h * step:
        raise FormatError(topic, f"image data of {data.size} bytes is too short for {w}x{h} {enc} (step {step})")
    rows = data[: h * step].reshape(h, step)
    if step != row:
        rows = rows[:, :row]
    rows = np.ascontiguousarray(rows)
    img: NDArray[Any]
    if nbytes == 2:
        img = rows.view(">u2" if bool(msg.is_bigendian) else "<u2").astype(np.uint16)
    else:
        img = rows
    return img.reshape(h, w, c) if c > 1 else img.reshape(h, w)


def decode_ros_image(msg: Any, msgtype: str, topic: str, max_pixels: int = MAX_IMAGE_PIXELS) -> NDArray[np.uint8]:
    """uint8 grey or BGR image of an Image or CompressedImage message (any encoding above).

    The size it declares must be at most ``max_pixels`` before it is decoded.
    """
    if msgtype.endswith("CompressedImage"):
        data = msg.data if isinstance(msg.data, np.ndarray) else np.frombuffer(bytes(msg.data), np.uint8)
        check_image_bytes(data, max_pixels, topic)
        img = decode_quietly(data)
        if img is None:
            raise FormatError(topic, f"cannot decode compressed image (format '{msg.format}')")
        return to_uint8(np.asarray(img), "bgra8" if img.ndim == 3 and img.shape[2] == 4 else "")
    return to_uint8(raw_image_array(msg, topic, max_pixels), str(msg.encoding).lower())


def to_uint8(img: NDArray[Any], encoding: str) -> NDArray[np.uint8]:
    """8-bit grey or BGR from a decoded image of the given ROS encoding."""
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if encoding in _BAYER:
        return np.asarray(cv2.cvtColor(img, _BAYER[encoding]))
    if encoding == "rgb8":
        return np.ascontiguousarray(img[:, :, ::-1])
    if img.ndim == 3 and img.shape[2] == 4:
        code = cv2.COLOR_RGBA2BGR if encoding == "rgba8" else cv2.COLOR_BGRA2BGR
        return np.asarray(cv2.cvtColor(img, code))
    return np.asarray(img, dtype=np.uint8)


def camera_model(msg: Any, topic: str) -> str:
    """``pinhole`` or ``equidistant`` for a CameraInfo's distortion model.

    An error naming the topic for anything else.
    """
    name = str(msg.distortion_model).strip().lower()
    if name not in DISTORTION_MODELS:
        raise CalibrationError(
            topic, f"unsupported distortion model '{msg.distortion_model}' ({', '.join(list(DISTORTION_MODELS)[:3])})"
        )
    n = len(_field(msg, "d"))
    expected = {"plumb_bob": (0, 5), "rational_polynomial": (0, 8), "equidistant": (0, 4), "": (0, 5, 8)}[name]
    if n not in expected:
        raise CalibrationError(
            topic, f"{name or 'no'} distortion model with {n} coefficients (expected {expected[-1]})"
        )
    return DISTORTION_MODELS[name]


class _Info:
    """A CameraInfo with ROS 2 field names (ROS 1 names D, K, R, P mapped)."""

    def __init__(self, msg: Any) -> None:
        self.width, self.height = int(msg.width), int(msg.height)
        self.d = [float(x) for x in _field(msg, "d")]
        self.k, self.r, self.p = (np.asarray(_field(msg, n), dtype=float) for n in ("k", "r", "p"))


def calibration_from_infos(
    left: Any, right: Any, left_topic: str, right_topic: str, max_pixels: int = MAX_IMAGE_PIXELS
) -> StereoCalibration:
    """Stereo calibration of two CameraInfo messages (any of the three distortion models).

    A declared image size above ``max_pixels`` is refused (before any undistortion map).
    """
    models = {camera_model(left, left_topic), camera_model(right, right_topic)}
    if len(models) != 1:
        raise CalibrationError(f"{left_topic}/{right_topic}", "left and right distortion models differ")
    if (int(left.width), int(left.height)) != (int(right.width), int(right.height)):
        raise CalibrationError(
            right_topic,
            f"image size {right.width}x{right.height} differs from {left_topic}'s {left.width}x{left.height}",
        )
    li, ri = _Info(left), _Info(right)
    cal = calibration_from_camera_info(li, ri, f"{left_topic}/{right_topic}", max_pixels)
    model = models.pop()
    if model == "equidistant":
        if len(li.d) == 0:
            cal.dist_left = np.zeros(4)
        if len(ri.d) == 0:
            cal.dist_right = np.zeros(4)
        cal.rectified = False if (np.any(cal.dist_left) or np.any(cal.dist_right)) else cal.rectified
        if not cal.rectified:
            cal.camera_model = "equidistant"
    return cal


def camera_info_values(cal: StereoCalibration) -> tuple[dict[str, Any], dict[str, Any]]:
    """CameraInfo field dicts (left, right) of a calibration.

    ``plumb_bob`` (or ``rational_polynomial`` for 8 coefficients) through :func:`camera_info_dicts`,
    ``equidistant`` with the rectification of ``cv2.fisheye.stereoRectify`` in R and P.
    """
    from loopmodel.io.mcap_io import camera_info_dicts

    left, right = camera_info_dicts(cal) if cal.camera_model == "pinhole" else _fisheye_infos(cal)
    if cal.camera_model == "pinhole":
        for info in (left, right):
            info["distortion_model"] = "rational_polynomial" if len(info["d"]) == 8 else "plumb_bob"
    return left, right


def _fisheye_infos(cal: StereoCalibration) -> tuple[dict[str, Any], dict[str, Any]]:
    from loopmodel.imaging.rectify import rectification
    from loopmodel.io.mcap_io import camera_info_dicts

    R0, R1, P0, P1 = rectification(cal)
    pin = StereoCalibration(cal.K_left, cal.K_right, cal.right_from_left, cal.image_size, rectified=True)
    left, right = camera_info_dicts(pin)
    for info, d, R, P in ((left, cal.dist_left, R0, P0), (right, cal.dist_right, R1, P1)):
        info["distortion_model"] = "equidistant"
        info["d"] = [float(x) for x in d]
        info["r"] = [float(x) for x in np.asarray(R).ravel()]
        info["p"] = [float(x) for x in np.asarray(P).ravel()]
    return left, right
