"""Stereo sequences written as ROS bags with the ``rosbags`` writers.

ROS 2 folders (``metadata.yaml`` + sqlite3 ``.db3`` or ``.mcap`` storage) and ROS 1 ``.bag`` files.

ROS conventions (image_transport, ``stereo_image_proc``, RViz): images are ``sensor_msgs/Image`` on
the image topic (``raw``: mono8 or bgr8 as the image is; ``mono8``, ``mono16``, ``bgr8``, ``rgb8``,
``bgra8``, ``bayer_rggb8``), or ``sensor_msgs/CompressedImage`` (``png``, ``jpeg``) on
``<image topic>/compressed``; every image has its ``CameraInfo`` with the same stamp; stamps are
the sequence's (shifted by ``time_offset_ns`` when the source's times are relative and an epoch is
given); ground truth is ``PoseStamped``; ``/tf_static`` may carry camera-to-body transforms.
The bag appears under its final name only when :meth:`BagSequenceWriter.close` succeeds.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from loopmodel.config import TopicsConfig
from loopmodel.geometry.se3 import quat_wxyz_from_rotation
from loopmodel.io.ros_camera import camera_info_values
from loopmodel.types import StereoCalibration, StereoFrame, Trajectory

BAG_KINDS = ("ros2-sqlite3", "ros2-mcap", "ros1")
ENCODINGS = ("raw", "mono8", "mono16", "bgr8", "rgb8", "bgra8", "bayer_rggb8", "png", "jpeg")


def _build(typestore: Any, msgtype: str, values: dict[str, Any]) -> Any:
    """A message object of ``msgtype`` from a dict.

    Nested dicts for nested messages; missing fields zero/empty; ROS 1 upper-case CameraInfo names
    filled from lower case.
    """
    from rosbags.typesys.base import Nodetype

    _consts, fields = typestore.fielddefs[msgtype]
    kwargs: dict[str, Any] = {}
    for name, (kind, sub) in fields:
        v = values.get(name, values.get(name.lower()))
        if kind == Nodetype.NAME:
            kwargs[name] = _build(typestore, sub, v or {})
        elif kind == Nodetype.BASE:
            base = sub[0]
            default: Any = "" if base == "string" else (False if base == "bool" else 0)
            kwargs[name] = default if v is None else v
        else:  # arrays and sequences
            elem_kind, elem = sub[0]
            if elem_kind == Nodetype.BASE:
                dtype = {"float64": np.float64, "float32": np.float32, "uint8": np.uint8}.get(elem[0], np.float64)
                n = sub[1] if kind == Nodetype.ARRAY else 0
                arr = np.zeros(n, dtype) if v is None else np.asarray(v, dtype)
                kwargs[name] = arr
            else:
                kwargs[name] = [_build(typestore, elem, x) for x in (v or [])]
    return typestore.types[msgtype](**kwargs)


def _header(t_ns: int, frame_id: str) -> dict[str, Any]:
    return {"stamp": {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}, "frame_id": frame_id}


def mosaic_rggb(bgr: np.ndarray) -> np.ndarray:
    """RGGB Bayer mosaic (HxW uint8) of a BGR image: R at even rows/cols, B at odd/odd."""
    h, w = bgr.shape[:2]
    out = np.empty((h, w), np.uint8)
    out[0::2, 0::2] = bgr[0::2, 0::2, 2]
    out[0::2, 1::2] = bgr[0::2, 1::2, 1]
    out[1::2, 0::2] = bgr[1::2, 0::2, 1]
    out[1::2, 1::2] = bgr[1::2, 1::2, 0]
    return out


def image_message_values(img: np.ndarray, t_ns: int, frame_id: str, encoding: str) -> tuple[str, dict[str, Any]]:
    """``(msgtype, values)`` of an image (uint8 grey or BGR) in the given encoding."""
    if encoding == "raw":
        encoding = "mono8" if img.ndim == 2 else "bgr8"
    grey = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    bgr = img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if encoding in ("png", "jpeg"):
        ok, buf = cv2.imencode(".png" if encoding == "png" else ".jpg", img)
        if not ok:
            raise ValueError(f"cannot encode an image of shape {img.shape} as {encoding}")
        return "sensor_msgs/msg/CompressedImage", {"header": _header(t_ns, frame_id), "format": encoding, "data": buf}
    if encoding == "mono8":
        pix = grey
    elif encoding == "mono16":
        pix = (grey.astype(np.uint16) << 8).view(np.uint8)  # little endian, cv_bridge's 8 <-> 16 bit scaling
    elif encoding == "bgr8":
        pix = bgr
    elif encoding == "rgb8":
        pix = bgr[:, :, ::-1]
    elif encoding == "bgra8":
        pix = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA)
    elif encoding == "bayer_rggb8":
        pix = mosaic_rggb(bgr)
    else:
        raise ValueError(f"image encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
    h, w = img.shape[:2]
    data = np.ascontiguousarray(pix).reshape(-1).view(np.uint8)
    return "sensor_msgs/msg/Image", {
        "header": _header(t_ns, frame_id),
        "height": h,
        "width": w,
        "encoding": encoding,
        "is_bigendian": 0,
        "step": data.size // h,
        "data": data,
    }


class BagSequenceWriter:
    """Writes a stereo sequence as a ROS bag of kind ``ros2-sqlite3``, ``ros2-mcap`` or ``ros1``.

    Topics from ``topics`` (DESIGN.md names by default).
    """

    def __init__(
        self,
        path: str | Path,
        calibration: StereoCalibration,
        kind: str = "ros2-sqlite3",
        topics: TopicsConfig | None = None,
        encoding: str = "mono8",
        frame_ids: tuple[str, str] = ("cam0", "cam1"),
        camera_info: tuple[dict[str, Any], dict[str, Any]] | None = None,
        time_offset_ns: int = 0,
    ) -> None:
        from rosbags.typesys import Stores, get_typestore

        if kind not in BAG_KINDS:
            raise ValueError(f"bag kind must be one of {', '.join(BAG_KINDS)}, got {kind!r}")
        if encoding not in ENCODINGS:
            raise ValueError(f"image encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
        self.path = Path(path)
        self.kind, self.encoding, self.frame_ids = kind, encoding, frame_ids
        self.topics = topics or TopicsConfig()
        self.calibration = calibration
        self.time_offset_ns = int(time_offset_ns)
        self._infos = camera_info or camera_info_values(calibration)
        self._ros1 = kind == "ros1"
        self._ts = get_typestore(Stores.ROS1_NOETIC if self._ros1 else Stores.ROS2_HUMBLE)
        self._tmpdir = self.path.parent / f".{self.path.name}.tmp-{os.getpid()}"
        self._tmpdir.mkdir(parents=True, exist_ok=False)
        self._tmp = self._tmpdir / self.path.name
        if self._ros1:
            from rosbags.rosbag1 import Writer as Writer1

            self._writer: Any = Writer1(self._tmp)
        else:
            from rosbags.rosbag2 import StoragePlugin
            from rosbags.rosbag2 import Writer as Writer2

            plugin = StoragePlugin.MCAP if kind == "ros2-mcap" else StoragePlugin.SQLITE3
            self._writer = Writer2(self._tmp, version=9, storage_plugin=plugin)
        self._writer.open()
        self._conns: dict[tuple[str, str], Any] = {}
        self._closed = False

    def __enter__(self) -> BagSequenceWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def write_message(self, topic: str, msgtype: str, values: dict[str, Any], log_ns: int) -> None:
        """Write one message given as a dict of its fields."""
        key = (topic, msgtype)
        if key not in self._conns:
            self._conns[key] = self._writer.add_connection(topic, msgtype, typestore=self._ts)
        msg = _build(self._ts, msgtype, values)
        raw = self._ts.serialize_ros1(msg, msgtype) if self._ros1 else self._ts.serialize_cdr(msg, msgtype)
        self._writer.write(self._conns[key], int(log_ns), raw)

    def image_topic(self, side: int) -> str:
        """The topic of the left (0) or right (1) images: ``.../compressed`` for PNG and JPEG."""
        topic = (self.topics.left_image, self.topics.right_image)[side].rstrip("/").removesuffix("/compressed")
        return f"{topic}/compressed" if self.encoding in ("png", "jpeg") else topic

    def write_image(self, side: int, t_ns: int, img: np.ndarray, log_ns: int | None = None) -> None:
        """Write an image of the left (0) or right (1) camera after its CameraInfo of the same stamp."""
        info_topic = (self.topics.left_info, self.topics.right_info)[side]
        fid = self.frame_ids[side]
        t_ns = int(t_ns) + self.time_offset_ns
        log = t_ns if log_ns is None else int(log_ns) + self.time_offset_ns
        info = dict(self._infos[side])
        info["header"] = _header(t_ns, fid)
        self.write_message(info_topic, "sensor_msgs/msg/CameraInfo", info, log)
        msgtype, values = image_message_values(img, t_ns, fid, self.encoding)
        self.write_message(self.image_topic(side), msgtype, values, log)

    def write_frame(self, frame: StereoFrame, right_offset_ns: int = 0, right: bool = True) -> None:
        """Write a stereo pair.

        The right stamp may be offset (unsynchronised cameras) or the right image left out (a
        dropped frame).
        """
        self.write_image(0, frame.timestamp_ns, frame.left)
        if right:
            self.write_image(1, frame.timestamp_ns + right_offset_ns, frame.right)

    def write_pose(self, t_ns: int, world_from_cam: np.ndarray, frame_id: str = "world") -> None:
        """Write a ground-truth ``PoseStamped`` (``world_from_cam0``)."""
        t_ns = int(t_ns) + self.time_offset_ns
        q = quat_wxyz_from_rotation(world_from_cam[:3, :3])
        p = world_from_cam[:3, 3]
        values = {
            "header": _header(t_ns, frame_id),
            "pose": {
                "position": {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])},
                "orientation": {"x": float(q[1]), "y": float(q[2]), "z": float(q[3]), "w": float(q[0])},
            },
        }
        self.write_message(self.topics.ground_truth, "geometry_msgs/msg/PoseStamped", values, t_ns)

    def write_trajectory(self, traj: Trajectory) -> None:
        """Write every pose of a ground-truth trajectory."""
        for t, T in zip(traj.timestamps_ns, traj.world_from_cam, strict=True):
            self.write_pose(int(t), T)

    def write_tf_static(self, transforms: list[tuple[str, str, np.ndarray]], t_ns: int = 0) -> None:
        """Write ``(parent, child, parent_from_child)`` transforms on ``/tf_static``."""
        items = []
        for parent, child, T in transforms:
            q = quat_wxyz_from_rotation(T[:3, :3])
            items.append(
                {
                    "header": _header(t_ns, parent),
                    "child_frame_id": child,
                    "transform": {
                        "translation": {"x": float(T[0, 3]), "y": float(T[1, 3]), "z": float(T[2, 3])},
                        "rotation": {"x": float(q[1]), "y": float(q[2]), "z": float(q[3]), "w": float(q[0])},
                    },
                }
            )
        self.write_message("/tf_static", "tf2_msgs/msg/TFMessage", {"transforms": items}, t_ns)

    def close(self) -> Path:
        """Finish the bag and move it to its final name."""
        if not self._closed:
            self._writer.close()
            if self.path.exists():
                shutil.rmtree(self.path) if self.path.is_dir() else self.path.unlink()
            os.replace(self._tmp, self.path)
            self._tmpdir.rmdir()
            self._closed = True
        return self.path

    def abort(self) -> None:
        """Drop the partial bag."""
        if not self._closed:
            with contextlib.suppress(Exception):
                self._writer.close()
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._closed = True
