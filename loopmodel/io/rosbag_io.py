"""ROS bags read with the pure-Python ``rosbags`` package (no ROS installation).

ROS 2 bag folders (``metadata.yaml`` with sqlite3 or MCAP storage), single ``.db3``/``.mcap`` files
and ROS 1 ``.bag`` files, as a streaming :class:`~loopmodel.io.base.Sequence`.

The stereo topics are the configured ones when the bag has them, ``--left/--right`` when
given, else guessed (:mod:`loopmodel.io.bag_topics`); the camera_info topics are found
beside the image topics. Left and right images pair by header stamp
(:mod:`loopmodel.io.stereo_pairing`). ``/tf_static`` gives ``body_from_cam0`` when it links
the left camera's frame to a root frame.

Why ``mcap`` (``mcap_io``) stays for the project's own MCAP files: they carry attachments
(the scene mesh), metadata records and a summary with per-channel counts, which ``rosbags``'
MCAP storage does not expose; this module reads every other MCAP (ROS 2 bags recorded by
``ros2 bag record`` with other topic names) and all sqlite3 and ROS 1 bags.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from loopmodel.config import TopicsConfig
from loopmodel.errors import CalibrationError, FormatError, InputError
from loopmodel.io.bag_topics import IMAGE_MSGTYPES, INFO_MSGTYPE, ImageTopic, camera_info_for, guess_stereo_pair
from loopmodel.io.base import Sequence
from loopmodel.io.ros_camera import IMAGE_ENCODINGS, calibration_from_infos, decode_ros_image
from loopmodel.io.stereo_pairing import PairingStats, pair_by_stamp, stamp_offset_ns
from loopmodel.types import StereoCalibration, StereoFrame, Trajectory

logger = logging.getLogger(__name__)

ROS1_MAGIC = b"#ROSBAG V2.0"
SQLITE_MAGIC = b"SQLite format 3\x00"
BAG_SUFFIXES = (".bag", ".db3", ".mcap")
_SAMPLE = 30  # messages per image topic read at opening for rate, size and stamp offset


def _head(path: Path, n: int) -> bytes:
    with open(path, "rb") as f:
        return f.read(n)


def is_bag(path: Path) -> bool:
    """True for a ROS 1 bag, a sqlite3 ``.db3``, or a folder that is (or was) a ROS 2 bag."""
    if path.is_file():
        return (
            path.suffix.lower() in (".bag", ".db3")
            or _head(path, 16) in (SQLITE_MAGIC,)
            or (_head(path, 12) == ROS1_MAGIC)
        )
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(
            p.suffix in (".db3", ".mcap") for p in path.iterdir() if p.is_file()
        )
    return False


def pose_from_msg_fields(translation: Any, rotation: Any) -> np.ndarray:
    """4x4 pose of a ROS position/translation and an xyzw quaternion (normalised)."""
    from loopmodel.geometry.se3 import rotation_from_quat_wxyz

    q = np.array([rotation.w, rotation.x, rotation.y, rotation.z], dtype=float)
    n = float(np.linalg.norm(q))
    T = np.eye(4)
    T[:3, :3] = rotation_from_quat_wxyz(q / n if n > 0 else np.array([1.0, 0, 0, 0]))
    T[:3, 3] = [translation.x, translation.y, translation.z]
    return T


def header_stamp_ns(msg: Any) -> int:
    """Header stamp (ns) of a decoded message (ROS 1 and ROS 2 both as sec/nanosec)."""
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


@functools.cache
def default_typestore(ros1: bool) -> Any:
    """The message types of ROS 1 Noetic or ROS 2 Humble, for bags without definitions.

    Such as old sqlite3 bags; built once (building a store costs about 0.2 s).
    """
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


class BagReader:
    """An open bag: connections by topic and decoded messages.

    Errors of ``rosbags`` become :class:`FormatError` naming the bag.
    """

    def __init__(self, path: Path) -> None:
        from rosbags.highlevel import AnyReader

        self.path = path
        if path.is_dir() and not (path / "metadata.yaml").is_file():
            files = ", ".join(sorted(p.name for p in path.iterdir() if p.suffix in (".db3", ".mcap")))
            raise FormatError(
                path / "metadata.yaml",
                f"ROS 2 bag folder without metadata.yaml (storage files: {files}); open the storage file itself",
            )
        if path.is_dir():  # a FIFO or device among the bag's files would block rosbags' open()
            from loopmodel.io.text import require_regular_file

            for p in sorted(path.iterdir()):
                if p.name == "metadata.yaml" or p.suffix.lower() in (".db3", ".mcap", ".zstd"):
                    require_regular_file(p, "bag file")
        self.is_ros1 = path.is_file() and path.suffix.lower() == ".bag"
        if path.is_file() and not self.is_ros1 and _head(path, 12) == ROS1_MAGIC:
            raise FormatError(path, "a ROS 1 bag whose name does not end in .bag; rename it to *.bag")
        try:
            self._reader = AnyReader([path], default_typestore=default_typestore(self.is_ros1))
            self._reader.open()
        except Exception as exc:  # rosbags raises several types for corrupt or foreign files
            raise FormatError(path, f"cannot read as a ROS bag ({type(exc).__name__}: {exc})") from None
        self.connections: dict[str, list[Any]] = {}
        for c in self._reader.connections:
            self.connections.setdefault(c.topic, []).append(c)

    def close(self) -> None:
        """Close the bag."""
        self._reader.close()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def msgtype(self, topic: str) -> str:
        """Message type of a topic ('' when absent)."""
        conns = self.connections.get(topic)
        return str(conns[0].msgtype) if conns else ""

    def count(self, topic: str) -> int:
        """Messages on a topic."""
        return sum(int(c.msgcount) for c in self.connections.get(topic, []))

    def topics_of_type(self, *msgtypes: str) -> list[str]:
        """Topics whose message type is one of ``msgtypes``."""
        return sorted(t for t in self.connections if self.msgtype(t) in msgtypes)

    @property
    def duration_s(self) -> float:
        """Time from the first to the last message (receive time, seconds)."""
        return max(0, self._reader.end_time - self._reader.start_time) * 1e-9

    def messages(self, topics: list[str]) -> Iterator[tuple[str, str, int, Any]]:
        """``(topic, msgtype, log_time_ns, decoded)`` in receive-time order."""
        conns = [c for t in topics for c in self.connections.get(t, [])]
        if not conns:
            return
        try:
            for c, log_ns, raw in self._reader.messages(connections=conns):
                yield c.topic, c.msgtype, int(log_ns), self._reader.deserialize(raw, c.msgtype)
        except (InputError, GeneratorExit):
            raise
        except Exception as exc:
            raise FormatError(self.path, f"corrupt message data ({type(exc).__name__}: {exc})") from None

    def first(self, topic: str) -> Any | None:
        """The first decoded message of a topic, or None."""
        for _t, _m, _l, msg in self.messages([topic]):
            return msg
        return None

    def topic_table(self) -> dict[str, dict[str, object]]:
        """Every topic with its type and message count."""
        return {t: {"type": self.msgtype(t), "messages": self.count(t)} for t in sorted(self.connections)}

    def recording_summary(self) -> dict[str, object]:
        """What ``ros2 bag info`` says: duration, start, message count, and per topic type, count, rate.

        The rate of a topic is its messages over its own span of receive times (one pass over the
        raw messages, nothing decoded); None for a topic with fewer than two messages.
        """
        from datetime import UTC, datetime

        first: dict[str, int] = {}
        last: dict[str, int] = {}
        for conn, t_ns, _raw in self._reader.messages():
            first.setdefault(conn.topic, t_ns)
            last[conn.topic] = t_ns
        topics: dict[str, dict[str, object]] = {}
        for t, row in self.topic_table().items():
            n, span_s = int(row["messages"]), (last.get(t, 0) - first.get(t, 0)) * 1e-9  # type: ignore[call-overload]
            topics[t] = {**row, "rate_hz": (n - 1) / span_s if n > 1 and span_s > 0 else None}
        start = self._reader.start_time if self.connections else None
        return {
            "duration_s": self.duration_s,
            "start": None if start is None else datetime.fromtimestamp(start * 1e-9, UTC).isoformat(),
            "messages": sum(int(r["messages"]) for r in topics.values()),  # type: ignore[call-overload]
            "topics": topics,
        }


class NoImageTopicsError(InputError):
    """A bag without image topics: not a sequence to run, but ``loopmodel info`` still describes it."""


def describe_recording(path: Path) -> dict[str, object]:
    """``loopmodel info`` of any bag or ROS 2 MCAP, images or not (topics, types, counts, rates, duration)."""
    with open_bag(path) as bag:
        return {"path": str(path), "format": BagSequence._format_of(bag), **bag.recording_summary()}


@contextmanager
def open_bag(path: Path) -> Iterator[BagReader]:
    """Context manager of :class:`BagReader`."""
    reader = BagReader(path)
    try:
        yield reader
    finally:
        reader.close()


def _image_size(msg: Any, msgtype: str, topic: str) -> tuple[tuple[int, int], str]:
    if msgtype.endswith("CompressedImage"):
        img = decode_ros_image(msg, msgtype, topic)
        return (int(img.shape[1]), int(img.shape[0])), str(msg.format)
    if str(msg.encoding).lower() not in IMAGE_ENCODINGS:
        raise FormatError(
            topic, f"unsupported image encoding '{msg.encoding}' (expected one of {', '.join(IMAGE_ENCODINGS)})"
        )
    return (int(msg.width), int(msg.height)), str(msg.encoding)


def scan_image_topics(bag: BagReader) -> tuple[list[ImageTopic], dict[str, list[int]]]:
    """Image topics of a bag with rate, size, encoding and camera_info, and header stamps by topic.

    Rate, size, encoding and camera_info come from their first messages; the stamps are those
    messages' header stamps.
    """
    infos = bag.topics_of_type(INFO_MSGTYPE)
    out: list[ImageTopic] = []
    stamps: dict[str, list[int]] = {}
    for topic in bag.topics_of_type(*IMAGE_MSGTYPES):
        it = ImageTopic(topic, bag.msgtype(topic), bag.count(topic), info_topic=camera_info_for(topic, infos))
        ts: list[int] = []
        for _t, msgtype, _l, msg in bag.messages([topic]):
            if not ts:
                it.size, it.encoding = _image_size(msg, msgtype, topic)
                it.frame_id = str(msg.header.frame_id)
            ts.append(header_stamp_ns(msg))
            if len(ts) >= _SAMPLE:
                break
        if len(ts) > 1 and ts[-1] > ts[0]:
            it.rate_hz = (len(ts) - 1) / ((ts[-1] - ts[0]) * 1e-9)
        stamps[topic] = ts
        out.append(it)
    return out, stamps


def static_transforms(bag: BagReader, topic: str = "/tf_static") -> dict[str, tuple[str, np.ndarray]]:
    """``child -> (parent, parent_from_child)`` of every transform on ``/tf_static``."""
    out: dict[str, tuple[str, np.ndarray]] = {}
    if bag.msgtype(topic) != "tf2_msgs/msg/TFMessage":
        return out
    for _t, _m, _l, msg in bag.messages([topic]):
        for tr in msg.transforms:
            T = pose_from_msg_fields(tr.transform.translation, tr.transform.rotation)
            out[str(tr.child_frame_id).lstrip("/")] = (str(tr.header.frame_id).lstrip("/"), T)
    return out


def root_from_frame(frame: str, tree: dict[str, tuple[str, np.ndarray]]) -> tuple[str, np.ndarray] | None:
    """The root frame above ``frame`` in a static tree and ``root_from_frame``.

    None when ``frame`` is not in the tree.
    """
    frame = frame.lstrip("/")
    if frame not in tree:
        return None
    T = np.eye(4)
    seen = set()
    while frame in tree and frame not in seen:
        seen.add(frame)
        parent, parent_from_child = tree[frame]
        T = parent_from_child @ T
        frame = parent
    return frame, T


class BagSequence(Sequence):
    """A stereo sequence in a ROS 1 or ROS 2 bag, read as a stream."""

    format_name = "rosbag"

    def __init__(
        self,
        path: Path,
        topics: TopicsConfig | None = None,
        tolerance_ns: int = 1_000_000,
        left: str | None = None,
        right: str | None = None,
        calibration_file: Path | None = None,
    ) -> None:
        super().__init__(path)
        self.topics = (topics or TopicsConfig()).model_copy()
        self.pairing = PairingStats()
        self.body_from_cam0: np.ndarray | None = None
        self.body_frame: str | None = None
        with open_bag(path) as bag:
            self.format_name = self._format_of(bag)
            self._topic_table = bag.topic_table()
            self._duration_s = bag.duration_s
            images, stamps = scan_image_topics(bag)
            self._images = {t.topic: t for t in images}
            li, ri = self._choose(images, left, right)
            if self._how == "configured":  # configured camera_info topics win over the guess
                for it, info in ((li, self.topics.left_info), (ri, self.topics.right_info)):
                    if bag.msgtype(info) == INFO_MSGTYPE:
                        it.info_topic = info
            self._left, self._right = li, ri
            self.topics.left_image, self.topics.right_image = li.topic, ri.topic
            for side, it in (("left", li), ("right", ri)):
                if it.info_topic is None and calibration_file is None:
                    raise CalibrationError(
                        it.topic,
                        f"no CameraInfo topic for this {side} image topic (expected a "
                        "sensor_msgs/CameraInfo topic camera_info beside it, or give a calibration file)",
                    )
            if calibration_file is not None:  # a calibration file wins over CameraInfo
                from loopmodel.io.calib_files import read_stereo_calibration

                calibration = read_stereo_calibration(calibration_file, li.size)
                for it in (li, ri):
                    if it.size is not None and it.size != calibration.image_size:
                        raise InputError(
                            it.topic,
                            f"image size {it.size[0]}x{it.size[1]}, the calibration says "
                            f"{calibration.image_size[0]}x{calibration.image_size[1]}",
                        )
                self._calibration = calibration
                self._how += ", calibration from file"
            else:
                assert li.info_topic is not None and ri.info_topic is not None
                self.topics.left_info, self.topics.right_info = li.info_topic, ri.info_topic
                self._calibration = self._read_calibration(bag, li, ri)
            self.tolerance_ns, self.stamp_offset_ns = self._tolerance(tolerance_ns, stamps[li.topic], stamps[ri.topic])
            self._gt = self._read_ground_truth(bag)
            tree = static_transforms(bag)
            found = root_from_frame(li.frame_id, tree)
            if found is not None:
                self.body_frame, self.body_from_cam0 = found
        info = f"camera info {li.info_topic}, {ri.info_topic}" if calibration_file is None else str(calibration_file)
        self.choice = f"stereo topics {li.topic} and {ri.topic} ({self._how}); {info}"

    @staticmethod
    def _format_of(bag: BagReader) -> str:
        p = bag.path
        if bag.is_ros1:
            return "ros1-bag"
        if p.is_file():
            return "ros2-" + ("mcap" if p.suffix.lower() == ".mcap" else "sqlite3")
        files = {q.suffix for q in p.iterdir()}
        return "ros2-" + ("mcap" if ".mcap" in files else "sqlite3")

    def _choose(self, images: list[ImageTopic], left: str | None, right: str | None) -> tuple[ImageTopic, ImageTopic]:
        by_name = {t.topic: t for t in images}
        listing = ", ".join(f"{k} ({v['type']})" for k, v in self._topic_table.items()) or "none"
        if left is not None or right is not None:
            if left is None or right is None:
                raise InputError("--left/--right", "give both --left and --right")
            for t in (left, right):
                if t not in by_name:
                    raise InputError(t, f"not an image topic of {self.path}; topics found: {listing}")
            self._how = "given"
            return by_name[left], by_name[right]
        cfg = self.topics
        if cfg.left_image in by_name and cfg.right_image in by_name:
            self._how = "configured"
            return by_name[cfg.left_image], by_name[cfg.right_image]
        if not images:
            raise NoImageTopicsError(
                self.path, f"no image topics (sensor_msgs Image/CompressedImage); topics found: {listing}"
            )
        try:
            pair = guess_stereo_pair(images)
        except LookupError as exc:
            raise InputError(self.path, str(exc)) from None
        self._how = "guessed"
        return pair

    def _read_calibration(self, bag: BagReader, li: ImageTopic, ri: ImageTopic) -> StereoCalibration:
        assert li.info_topic is not None and ri.info_topic is not None
        left, right = bag.first(li.info_topic), bag.first(ri.info_topic)
        if left is None or right is None:
            raise CalibrationError(li.info_topic if left is None else ri.info_topic, "no CameraInfo message")
        cal = calibration_from_infos(left, right, li.info_topic, ri.info_topic)
        for it, info in ((li, left), (ri, right)):
            if it.size is not None and it.size != (int(info.width), int(info.height)):
                raise InputError(
                    it.topic,
                    f"image size {it.size[0]}x{it.size[1]} but {it.info_topic} says {info.width}x{info.height}",
                )
        return cal

    @staticmethod
    def _tolerance(tol_ns: int, left: list[int], right: list[int]) -> tuple[int, int | None]:
        """Pairing tolerance: the configured one, widened by a constant left/right offset.

        Widened for unsynchronised cameras, when the sampled stamps show one below a quarter frame.
        """
        offset = stamp_offset_ns(left, right)
        if offset is None or offset <= tol_ns or len(left) < 2:
            return tol_ns, offset
        period = (left[-1] - left[0]) / (len(left) - 1)
        if offset < period / 4:
            return int(offset + tol_ns), offset
        return tol_ns, offset

    def _read_ground_truth(self, bag: BagReader) -> Trajectory | None:
        topic = self.topics.ground_truth
        if topic not in self._topic_table:
            return None
        from loopmodel.io.bag_trajectory import trajectory_from_messages

        return trajectory_from_messages(bag, topic, f"{self.path}:{topic}")

    # -- public
    @property
    def calibration(self) -> StereoCalibration:
        return self._calibration

    @property
    def ground_truth(self) -> Trajectory | None:
        return self._gt

    def __len__(self) -> int:
        return min(self._left.count, self._right.count)

    def describe(self) -> dict[str, object]:
        out = super().describe()
        out["duration_s"] = self._duration_s
        out["stereo_topics"] = self.choice.removeprefix("stereo topics ")  # the row label says it (issue 35)
        out["camera_model"] = self._calibration.camera_model
        if self.stamp_offset_ns is not None:
            out["left_right_stamp_offset_ms"] = self.stamp_offset_ns * 1e-6
        out["pairing_tolerance_ms"] = self.tolerance_ns * 1e-6
        out["image_topics"] = {k: v.summary() for k, v in sorted(self._images.items())}
        out["camera_info_topics"] = [k for k, v in self._topic_table.items() if v["type"] == INFO_MSGTYPE]
        out["topics"] = self._topic_table
        if self.body_from_cam0 is not None:
            out["body_from_cam0"] = f"{self.body_frame} <- {self._left.frame_id} (/tf_static)"
        return out

    def frames(self) -> Iterator[StereoFrame]:
        lt, rt = self._left.topic, self._right.topic
        size = self._calibration.image_size
        self.pairing = PairingStats()
        with open_bag(self.path) as bag:
            stream = (
                (topic == lt, header_stamp_ns(msg), (msgtype, msg))
                for topic, msgtype, _l, msg in bag.messages([lt, rt])
            )
            for index, pair in enumerate(pair_by_stamp(stream, self.tolerance_ns, self.pairing, (lt, rt))):
                left = decode_ros_image(pair.left[1], pair.left[0], lt)
                right = decode_ros_image(pair.right[1], pair.right[0], rt)
                for img, topic in ((left, lt), (right, rt)):
                    if (img.shape[1], img.shape[0]) != size:
                        raise InputError(
                            topic,
                            f"image of {img.shape[1]}x{img.shape[0]} at {pair.left_ns} ns, camera_info says "
                            f"{size[0]}x{size[1]}",
                        )
                yield StereoFrame(pair.left_ns, left, right, index)
        if self.pairing.unmatched:
            logger.warning(
                "%s: %d left and %d right images without a stereo partner within %.2f ms were skipped",
                self.path,
                self.pairing.unmatched_left,
                self.pairing.unmatched_right,
                self.tolerance_ns * 1e-6,
            )
