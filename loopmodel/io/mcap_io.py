"""MCAP sequences with ROS 2 messages (topics of DESIGN.md): a streaming reader and a writer.

Images: ``sensor_msgs/Image`` (mono8, bgr8, rgb8, mono16) or ``sensor_msgs/CompressedImage``
(png/jpeg). Left and right images are paired by header stamp within a tolerance. Stripes are
``PointCloud2`` (x, y, z float32, metres, left-camera frame); ground truth is
``PoseStamped`` ``world_from_cam0``. The scene mesh may ride along as an attachment.
"""

from __future__ import annotations

import contextlib
import functools
import logging
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer

from loopmodel.config import TopicsConfig
from loopmodel.errors import CalibrationError, FormatError, InputError
from loopmodel.geometry.se3 import quat_wxyz_from_rotation, rotation_from_quat_wxyz
from loopmodel.io.atomic import atomic_path
from loopmodel.io.base import Sequence
from loopmodel.io.images import (
    MAX_IMAGE_PIXELS,
    DeferredRightFrame,
    check_declared_size,
    check_image_bytes,
    decode_quietly,
    image_to_uint8,
)
from loopmodel.io.ros2_msgs import MSGDEFS, POINTFIELD_FLOAT32, header, stamp_ns
from loopmodel.types import StereoCalibration, StereoFrame, StripeProfile, Trajectory

logger = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
_READ_ERRORS = (McapError, EOFError, ValueError, KeyError, IndexError, OSError, RuntimeError, AssertionError)


def is_mcap(path: Path) -> bool:
    """True when the file starts with the MCAP magic."""
    if not path.is_file():
        return False
    with open(path, "rb") as f:
        return f.read(8) == MCAP_MAGIC


# ----------------------------------------------------------------------------- decoding


def decode_image(msg: Any, schema_name: str, topic: str, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """numpy image of a decoded Image or CompressedImage message.

    The size it declares (PNG/ JPEG header, or width and height) must be at most ``max_pixels``
    before it is decoded.
    """
    data = bytes(msg.data)
    if schema_name.endswith("CompressedImage"):
        check_image_bytes(data, max_pixels, topic)
        img = decode_quietly(data)
        if img is None:
            raise FormatError(topic, f"cannot decode compressed image (format '{msg.format}')")
        return image_to_uint8(np.asarray(img), topic)
    enc = str(msg.encoding).lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    channels = {"mono8": 1, "8uc1": 1, "bgr8": 3, "rgb8": 3, "8uc3": 3, "mono16": 1, "16uc1": 1}
    check_declared_size(w, h, max_pixels, topic)
    if enc not in channels:  # bgra8, bayer_*, ...: the bag readers' decoder (8-bit output)
        from loopmodel.io.ros_camera import decode_ros_image

        return decode_ros_image(msg, schema_name, topic)
    dtype = np.uint16 if enc in ("mono16", "16uc1") else np.uint8
    itemsize = np.dtype(dtype).itemsize
    c = channels[enc]
    if len(data) < h * step or step < w * c * itemsize:
        raise FormatError(topic, f"image data of {len(data)} bytes is too short for {w}x{h} {enc}")
    rows = np.frombuffer(data, np.uint8, count=h * step).reshape(h, step)[:, : w * c * itemsize]
    img = np.ascontiguousarray(rows).view(dtype)
    if dtype == np.uint16 and bool(msg.is_bigendian):
        img = img.byteswap()
    img = img.reshape(h, w, c) if c == 3 else img.reshape(h, w)
    if enc == "rgb8":
        img = img[:, :, ::-1].copy()
    return image_to_uint8(img, topic)  # mono16: the high byte, as the bag readers


def calibration_from_camera_info(
    left: Any, right: Any, source: str, max_pixels: int = MAX_IMAGE_PIXELS
) -> StereoCalibration:
    """Stereo calibration from two decoded CameraInfo messages.

    ROS conventions: R rectifies, P of the right camera carries ``fx * t_x`` of the rectified
    baseline.
    """
    K0 = np.array(left.k, dtype=float).reshape(3, 3)
    K1 = np.array(right.k, dtype=float).reshape(3, 3)
    R0 = np.array(left.r, dtype=float).reshape(3, 3)
    R1 = np.array(right.r, dtype=float).reshape(3, 3)
    P0 = np.array(left.p, dtype=float).reshape(3, 4)
    P1 = np.array(right.p, dtype=float).reshape(3, 4)
    d0 = np.array(left.d, dtype=float) if len(left.d) else np.zeros(5)
    d1 = np.array(right.d, dtype=float) if len(right.d) else np.zeros(5)
    if not (np.all(np.isfinite(P0)) and np.all(np.isfinite(P1))):
        raise CalibrationError(source, "CameraInfo P has non-finite values")
    if P1[0, 0] <= 0 or P0[0, 0] <= 0 or K0[0, 0] <= 0 or K1[0, 0] <= 0:
        raise CalibrationError(source, "CameraInfo focal length must be positive")
    if not (np.array_equal(P0[2], [0.0, 0.0, 1.0, 0.0]) and np.array_equal(P1[2], [0.0, 0.0, 1.0, 0.0])):
        raise CalibrationError(source, "CameraInfo P: the third row must be 0 0 1 0")
    t_rect = np.array([(P1[0, 3] - P0[0, 3]) / P1[0, 0], (P1[1, 3] - P0[1, 3]) / P1[1, 1], 0.0])
    rectified = bool(np.allclose(R0, np.eye(3)) and np.allclose(R1, np.eye(3)) and not d0.any() and not d1.any())
    right_from_left = np.eye(4)
    right_from_left[:3, :3] = R1.T @ R0
    right_from_left[:3, 3] = R1.T @ t_rect
    size = (int(left.width), int(left.height))
    if (int(right.width), int(right.height)) != size:
        raise CalibrationError(
            source, f"left and right CameraInfo sizes differ: {size} vs {(right.width, right.height)}"
        )
    check_declared_size(size[0], size[1], max_pixels, f"{source} (CameraInfo width x height)")
    return StereoCalibration(K0, K1, right_from_left, size, d0, d1, rectified).check(source)


def camera_info_dicts(cal: StereoCalibration) -> tuple[dict, dict]:
    """CameraInfo message dicts (left, right) for a calibration.

    Unrectified rigs get the rectification of ``cv2.stereoRectify`` in R and P.
    """
    w, h = cal.image_size
    if cal.rectified:
        R0 = R1 = np.eye(3)
        P0 = np.hstack([cal.K_left, np.zeros((3, 1))])
        P1 = np.hstack([cal.K_right, np.zeros((3, 1))])
        P1[:2, 3] = cal.K_right[[0, 1], [0, 1]] * cal.right_from_left[:2, 3]
    else:
        R0, R1, P0, P1, *_ = cv2.stereoRectify(
            cal.K_left,
            cal.dist_left,
            cal.K_right,
            cal.dist_right,
            (w, h),
            cal.right_from_left[:3, :3].copy(),
            cal.right_from_left[:3, 3].reshape(3, 1).copy(),
            alpha=0,
        )
    out = []
    for K, d, R, P, fid in ((cal.K_left, cal.dist_left, R0, P0, "cam0"), (cal.K_right, cal.dist_right, R1, P1, "cam1")):
        out.append(
            {
                "header": header(0, fid),
                "height": h,
                "width": w,
                "distortion_model": "plumb_bob",
                "d": [float(x) for x in d],
                "k": [float(x) for x in np.asarray(K).ravel()],
                "r": [float(x) for x in np.asarray(R).ravel()],
                "p": [float(x) for x in np.asarray(P).ravel()],
                "binning_x": 0,
                "binning_y": 0,
                "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
            }
        )
    return out[0], out[1]


def decode_pointcloud_xyz(msg: Any, topic: str) -> np.ndarray:
    """N x 3 float64 points of a PointCloud2 with float32 x, y, z fields."""
    offsets = {f.name: (int(f.offset), int(f.datatype)) for f in msg.fields}
    for axis in "xyz":
        if axis not in offsets or offsets[axis][1] != POINTFIELD_FLOAT32:
            raise FormatError(topic, "PointCloud2 needs float32 fields x, y, z")
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    buf = np.frombuffer(bytes(msg.data), np.uint8)
    if step < 12 or max(offsets[a][0] for a in "xyz") + 4 > step:
        raise FormatError(topic, f"PointCloud2 point_step {step} cannot hold float32 x, y, z")
    if buf.size < n * step:
        raise FormatError(
            topic,
            f"PointCloud2 declares {n} points ({msg.width}x{msg.height}, {step} bytes each) "
            f"but carries {buf.size} bytes",
        )
    endian = ">" if msg.is_bigendian else "<"
    dt = np.dtype(
        {
            "names": list("xyz"),
            "formats": [endian + "f4"] * 3,
            "offsets": [offsets[a][0] for a in "xyz"],
            "itemsize": step,
        }
    )
    rec = buf[: n * step].view(dt)
    pts = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)
    # ROS: a cloud with is_dense false marks invalid points with NaN; they are skipped (issue 34)
    return pts[np.isfinite(pts).all(axis=1)]


# ----------------------------------------------------------------------------- reader


class McapSequence(Sequence):
    """A stereo sequence in an MCAP file, read as a stream."""

    format_name = "mcap"

    def __init__(
        self,
        path: Path,
        topics: TopicsConfig | None = None,
        tolerance_ns: int = 1_000_000,
        max_image_pixels: int = MAX_IMAGE_PIXELS,
    ) -> None:
        super().__init__(path)
        self.topics = topics or TopicsConfig()
        self.tolerance_ns = tolerance_ns
        self.max_image_pixels = max_image_pixels
        self._channels: dict[str, str] = {}  # topic -> schema name
        self._counts: dict[str, int] = {}
        self._attachments: list[str] = []
        self._metadata: dict[str, dict[str, str]] = {}
        self._scan()
        self._check_topics()
        self._calibration = self._read_calibration()
        self._gt = self._read_ground_truth()

    # -- indexing
    def _scan(self) -> None:
        try:
            with open(self.path, "rb") as f:
                if f.read(8) != MCAP_MAGIC:
                    raise FormatError(self.path, "not an MCAP file (bad magic)")
                f.seek(0)
                reader = make_reader(f)
                summary = reader.get_summary()
                if summary is None:
                    raise FormatError(self.path, "truncated or corrupt MCAP (no summary section)")
                for ch in summary.channels.values():
                    schema = summary.schemas.get(ch.schema_id)
                    self._channels[ch.topic] = schema.name if schema else ""
                if summary.statistics is not None:
                    for ch in summary.channels.values():  # a channel without messages counts 0
                        self._counts.setdefault(ch.topic, 0)
                    for cid, n in summary.statistics.channel_message_counts.items():
                        topic = summary.channels[cid].topic
                        self._counts[topic] = self._counts.get(topic, 0) + n
                self._attachments = [a.name for a in summary.attachment_indexes]
                self._metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except FormatError:
            raise
        except _READ_ERRORS as exc:
            raise FormatError(self.path, f"truncated or corrupt MCAP ({type(exc).__name__}: {exc})") from None

    def _check_topics(self) -> None:
        t = self.topics
        missing = [x for x in (t.left_image, t.right_image) if self._channels.get(x) not in IMAGE_TYPES]
        if missing:
            found = ", ".join(f"{k} ({v})" for k, v in sorted(self._channels.items())) or "none"
            raise InputError(
                self.path,
                f"no stereo image topics {t.left_image} and {t.right_image} "
                f"(sensor_msgs Image/CompressedImage); topics found: {found}",
            )
        nl, nr = self._counts.get(t.left_image), self._counts.get(t.right_image)
        empty = [x for x, n in ((t.left_image, nl), (t.right_image, nr)) if n == 0]
        if empty:
            raise InputError(self.path, f"image topic {' and '.join(empty)} has no messages")
        if nl is not None and nr is not None and nl != nr:
            raise InputError(
                self.path, f"left and right image counts differ: {nl} on {t.left_image}, {nr} on {t.right_image}"
            )

    def _messages(self, topics: list[str]) -> Iterator[tuple[str, str, Any]]:
        try:
            with open(self.path, "rb") as f:
                reader = make_reader(f, decoder_factories=[DecoderFactory()])
                for schema, channel, _message, decoded in reader.iter_decoded_messages(
                    topics=topics, log_time_order=True
                ):
                    yield channel.topic, schema.name if schema else "", decoded
        except _READ_ERRORS as exc:
            raise FormatError(self.path, f"truncated or corrupt MCAP ({type(exc).__name__}: {exc})") from None

    def _first(self, topic: str) -> Any | None:
        if topic not in self._channels:
            return None
        for _t, _s, msg in self._messages([topic]):
            return msg
        return None

    def _read_calibration(self) -> StereoCalibration:
        t = self.topics
        left, right = self._first(t.left_info), self._first(t.right_info)
        if left is None or right is None:
            raise CalibrationError(self.path, f"no CameraInfo on {t.left_info} and {t.right_info}")
        from loopmodel.io.ros_camera import calibration_from_infos  # distortion models

        return calibration_from_infos(
            left, right, f"{self.path} {t.left_info}", f"{self.path} {t.right_info}", self.max_image_pixels
        )

    def _read_ground_truth(self) -> Trajectory | None:
        topic = self.topics.ground_truth
        if topic not in self._channels:
            return None
        times, poses = [], []
        for _t, _s, msg in self._messages([topic]):
            p, q = msg.pose.position, msg.pose.orientation
            T = np.eye(4)
            T[:3, :3] = rotation_from_quat_wxyz([q.w, q.x, q.y, q.z])
            T[:3, 3] = [p.x, p.y, p.z]
            times.append(stamp_ns(msg))
            poses.append(T)
        if not times:
            return None
        return Trajectory(np.array(times), np.array(poses)).check(f"{self.path} {topic}")

    # -- public
    @property
    def calibration(self) -> StereoCalibration:
        return self._calibration

    @property
    def ground_truth(self) -> Trajectory | None:
        return self._gt

    @property
    def metadata(self) -> dict[str, dict[str, str]]:
        """MCAP metadata records by name."""
        return self._metadata

    @property
    def attachment_names(self) -> list[str]:
        """Names of the attachments (e.g. ``scene.ply``)."""
        return list(self._attachments)

    def read_attachment(self, name: str) -> bytes:
        """Bytes of the attachment called ``name``."""
        try:
            with open(self.path, "rb") as f:
                for att in make_reader(f).iter_attachments():
                    if att.name == name:
                        return bytes(att.data)
        except _READ_ERRORS as exc:
            raise FormatError(self.path, f"corrupt attachment section ({exc})") from None
        raise InputError(self.path, f"no attachment named '{name}'")

    def __len__(self) -> int:
        t = self.topics
        return min(self._counts.get(t.left_image, 0), self._counts.get(t.right_image, 0))

    def stripe_count(self) -> int:
        return self._counts.get(self.topics.stripe, 0)

    def frame_times_ns(self) -> list[int] | None:
        return None

    def describe(self) -> dict[str, object]:
        out = super().describe()
        span = self._image_time_span()
        out["duration_s"] = span
        out["topics"] = {k: {"type": v, "messages": self._counts.get(k, 0)} for k, v in sorted(self._channels.items())}
        out["attachments"] = self.attachment_names
        out["metadata"] = sorted(self._metadata)
        return out

    def _image_time_span(self) -> float | None:
        with open(self.path, "rb") as f:
            summary = make_reader(f).get_summary()
        if summary is None or summary.statistics is None or len(self) < 2:
            return None
        st = summary.statistics
        return (st.message_end_time - st.message_start_time) * 1e-9

    def frames(self) -> Iterator[StereoFrame]:
        t = self.topics
        lq: deque[tuple[int, Any, str]] = deque()
        rq: deque[tuple[int, Any, str]] = deque()
        last = {t.left_image: -1, t.right_image: -1}
        index = 0
        dropped = 0
        for topic, schema, msg in self._messages([t.left_image, t.right_image]):
            ts = stamp_ns(msg)
            if ts < last[topic]:
                raise InputError(self.path, f"timestamps go backwards on {topic}: {ts} ns after {last[topic]} ns")
            if ts == last[topic]:
                logger.warning("%s: duplicated timestamp %d ns on %s, message skipped", self.path, ts, topic)
                continue
            last[topic] = ts
            (lq if topic == t.left_image else rq).append((ts, msg, schema))
            while lq and rq:
                tl, ml, sl = lq[0]
                tr, mr, sr = rq[0]
                if abs(tl - tr) <= self.tolerance_ns:
                    lq.popleft()
                    rq.popleft()
                    # the image errors name the frame too (issue 34)
                    left = self._image(ml, sl, t.left_image, index, tl)
                    yield self._frame(tl, left, mr, sr, index)
                    index += 1
                elif tl < tr:
                    lq.popleft()
                    dropped += 1
                else:
                    rq.popleft()
                    dropped += 1
        if dropped:
            logger.warning("%s: %d images without a stereo partner were skipped", self.path, dropped)

    def _image(self, msg: Any, schema: str, topic: str, index: int, stamp: int) -> np.ndarray:
        """Frame ``index``'s image on ``topic`` decoded, of the CameraInfo's size (else :class:`InputError`)."""
        img = decode_image(msg, schema, f"{topic} frame {index} ({stamp} ns)", self.max_image_pixels)
        w, h = self._calibration.image_size
        if img.shape[:2] != (h, w):
            raise InputError(
                f"{self.path} {topic}",
                f"frame {index} ({stamp} ns) is {img.shape[1]}x{img.shape[0]} pixels, the CameraInfo says {w}x{h}",
            )
        return img

    def _frame(self, stamp: int, left: np.ndarray, msg: Any, schema: str, index: int) -> StereoFrame:
        """The frame, its right image decoded when first used when compressed (orb13).

        The front end uses a right image only at a keyframe (:class:`DeferredRightFrame`): a PNG decode
        saved on the others; its declared size is checked now, its decoded size at the first use.
        """
        topic = self.topics.right_image
        if not schema.endswith("CompressedImage"):
            return StereoFrame(stamp, left, self._image(msg, schema, topic, index, stamp), index)
        check_image_bytes(bytes(msg.data), self.max_image_pixels, f"{topic} frame {index} ({stamp} ns)")
        decode = functools.partial(self._image, msg, schema, topic, index, stamp)
        return DeferredRightFrame(stamp, left, None, index, right_decode=decode)

    def stripes(self) -> Iterator[StripeProfile]:
        topic = self.topics.stripe
        if topic not in self._channels:
            return
        for _t, _s, msg in self._messages([topic]):
            yield StripeProfile(stamp_ns(msg), decode_pointcloud_xyz(msg, f"{self.path} {topic}"))

    def laser_images(self) -> Iterator[tuple[int, np.ndarray]]:
        topic = self.topics.laser_image
        if topic not in self._channels:
            return
        for _t, schema, msg in self._messages([topic]):
            yield stamp_ns(msg), decode_image(msg, schema, topic, self.max_image_pixels)

    def laser_image_count(self) -> int:
        return self._counts.get(self.topics.laser_image, 0)


# ----------------------------------------------------------------------------- writer


class McapSequenceWriter:
    """Writes a stereo sequence as MCAP with ROS 2 messages.

    The file appears under its final name only when :meth:`close` succeeds; on error the partial
    file is removed.
    """

    def __init__(
        self,
        path: str | Path,
        calibration: StereoCalibration | None,
        topics: TopicsConfig | None = None,
        image_format: str = "png",
    ) -> None:
        """``calibration`` None: a monocular recording that writes its own camera info."""
        if image_format not in ("raw", "png", "jpeg"):
            raise ValueError(f"image_format must be raw, png or jpeg, got {image_format!r}")
        self.path = Path(path)
        self.topics = topics or TopicsConfig()
        self.image_format = image_format
        self.calibration = calibration
        self._ctx = atomic_path(self.path)
        self._tmp = self._ctx.__enter__()
        self._file = open(self._tmp, "wb")
        self._writer = Ros2Writer(self._file)
        self._schemas = {name: self._writer.register_msgdef(name, text) for name, text in MSGDEFS.items()}
        self._info_written = False
        self._closed = False

    def __enter__(self) -> McapSequenceWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort(exc_type, exc, tb)

    def _write(self, topic: str, type_name: str, msg: dict, t_ns: int, log_time_ns: int | None = None) -> None:
        log = int(t_ns if log_time_ns is None else log_time_ns)
        self._writer.write_message(topic, self._schemas[type_name], msg, log_time=log, publish_time=log)

    def _write_info(self, t_ns: int) -> None:
        from loopmodel.io.ros_camera import camera_info_values  # equidistant too

        if self.calibration is None:
            raise ValueError("a stereo frame needs the writer's stereo calibration")
        left, right = camera_info_values(self.calibration)
        left["header"] = header(t_ns, "cam0")
        right["header"] = header(t_ns, "cam1")
        self._write(self.topics.left_info, "sensor_msgs/msg/CameraInfo", left, t_ns)
        self._write(self.topics.right_info, "sensor_msgs/msg/CameraInfo", right, t_ns)
        self._info_written = True

    def _image_msg(self, img: np.ndarray, t_ns: int, frame_id: str) -> tuple[str, dict]:
        if self.image_format == "raw":
            if img.ndim == 2 and img.dtype == np.uint8:
                enc, step = "mono8", img.shape[1]
            elif img.ndim == 2 and img.dtype == np.uint16:
                enc, step = "mono16", img.shape[1] * 2
            elif img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8:
                enc, step = "bgr8", img.shape[1] * 3
            else:
                raise ValueError(f"cannot write image of shape {img.shape} and dtype {img.dtype}")
            return "sensor_msgs/msg/Image", {
                "header": header(t_ns, frame_id),
                "height": img.shape[0],
                "width": img.shape[1],
                "encoding": enc,
                "is_bigendian": 0,
                "step": step,
                "data": np.ascontiguousarray(img).tobytes(),
            }
        ext = ".png" if self.image_format == "png" else ".jpg"
        ok, buf = cv2.imencode(ext, img)
        if not ok:
            raise ValueError(f"cannot encode image of shape {img.shape} as {self.image_format}")
        return "sensor_msgs/msg/CompressedImage", {
            "header": header(t_ns, frame_id),
            "format": self.image_format,
            "data": buf.tobytes(),
        }

    def write_frame(self, frame: StereoFrame, log_time_ns: int | None = None) -> None:
        """Write one stereo pair (and the camera info before the first).

        The header stamp is the frame's time; ``log_time_ns`` (receive time) defaults to it.
        """
        if not self._info_written:
            self._write_info(frame.timestamp_ns if log_time_ns is None else log_time_ns)
        for img, topic, fid in (
            (frame.left, self.topics.left_image, "cam0"),
            (frame.right, self.topics.right_image, "cam1"),
        ):
            type_name, msg = self._image_msg(img, frame.timestamp_ns, fid)
            self._write(topic, type_name, msg, frame.timestamp_ns, log_time_ns)

    def write_image(self, topic: str, t_ns: int, img: np.ndarray, frame_id: str = "cam0") -> None:
        """Write a single image on any topic (e.g. ``/laser/image``)."""
        type_name, msg = self._image_msg(img, t_ns, frame_id)
        self._write(topic, type_name, msg, t_ns)

    def write_stripe(self, stripe: StripeProfile, topic: str | None = None) -> None:
        """Write one laser-stripe profile as PointCloud2 on the stripe topic (or ``topic``).

        Fields: float32 x, y, z in the left-camera frame.
        """
        pts = np.ascontiguousarray(np.asarray(stripe.points_in_cam, dtype=np.float32).reshape(-1, 3))
        fields = [{"name": a, "offset": 4 * i, "datatype": POINTFIELD_FLOAT32, "count": 1} for i, a in enumerate("xyz")]
        msg = {
            "header": header(stripe.timestamp_ns, "cam0"),
            "height": 1,
            "width": pts.shape[0],
            "fields": fields,
            "is_bigendian": False,
            "point_step": 12,
            "row_step": 12 * pts.shape[0],
            "data": pts.tobytes(),
            "is_dense": bool(np.all(np.isfinite(pts))),
        }
        self._write(topic or self.topics.stripe, "sensor_msgs/msg/PointCloud2", msg, stripe.timestamp_ns)

    def write_camera_info(self, topic: str, t_ns: int, info: dict, frame_id: str = "cam0") -> None:
        """Write one CameraInfo message dict (as :func:`camera_info_dicts` makes) on any topic."""
        msg = dict(info)
        msg["header"] = header(t_ns, frame_id)
        self._write(topic, "sensor_msgs/msg/CameraInfo", msg, t_ns)

    def write_pose(self, t_ns: int, world_from_cam: np.ndarray, topic: str | None = None) -> None:
        """Write one pose ``world_from_cam0`` (ground truth topic unless ``topic`` is given)."""
        q = quat_wxyz_from_rotation(world_from_cam[:3, :3])
        p = world_from_cam[:3, 3]
        msg = {
            "header": header(t_ns, "world"),
            "pose": {
                "position": {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])},
                "orientation": {"x": float(q[1]), "y": float(q[2]), "z": float(q[3]), "w": float(q[0])},
            },
        }
        self._write(topic or self.topics.ground_truth, "geometry_msgs/msg/PoseStamped", msg, t_ns)

    def write_trajectory(self, traj: Trajectory) -> None:
        """Write every pose of a ground-truth trajectory."""
        for t, T in zip(traj.timestamps_ns, traj.world_from_cam, strict=True):
            self.write_pose(int(t), T)

    def add_attachment(self, name: str, data: bytes, media_type: str = "application/octet-stream") -> None:
        """Attach a file (e.g. ``scene.ply``)."""
        self._writer.add_attachment(0, 0, name, media_type, data)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Add a metadata record of string key/value pairs."""
        self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def close(self) -> Path:
        """Finish the file and move it to its final name."""
        if not self._closed:
            self._writer.finish()
            self._file.close()
            self._ctx.__exit__(None, None, None)
            self._closed = True
        return self.path

    def abort(self, exc_type: Any = KeyboardInterrupt, exc: Any = None, tb: Any = None) -> None:
        """Drop the partial file."""
        if not self._closed:
            self._file.close()
            with contextlib.suppress(BaseException):
                self._ctx.__exit__(exc_type or KeyboardInterrupt, exc or KeyboardInterrupt(), tb)
            self._closed = True
