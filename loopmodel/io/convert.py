"""``loopmodel convert``.

Any readable sequence to the project's MCAP or to a ROS bag (ROS 2 sqlite3, ROS 2 MCAP, ROS 1), with
the project's topic names or the source's.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from loopmodel.config import SequenceConfig, TopicsConfig
from loopmodel.io.base import Sequence
from loopmodel.io.rosbag_writer import BAG_KINDS, BagSequenceWriter

OUTPUT_KINDS = ("mcap", *BAG_KINDS)


def output_kind(dst: Path, kind: str | None) -> str:
    """The output kind given or implied by the name.

    ``.mcap`` the project's MCAP, ``.bag`` ROS 1, anything else a ROS 2 sqlite3 bag folder.
    """
    if kind is not None:
        return kind
    suffix = dst.suffix.lower()
    return "mcap" if suffix == ".mcap" else "ros1" if suffix == ".bag" else "ros2-sqlite3"


def source_topics(seq: Sequence, config: SequenceConfig, keep: bool) -> TopicsConfig:
    """The configured topic names, or with ``keep`` the source's own (bags and MCAP files)."""
    own = getattr(seq, "topics", None)
    return own.model_copy() if keep and isinstance(own, TopicsConfig) else config.topics.model_copy()


def convert_sequence(
    seq: Sequence,
    dst: str | Path,
    kind: str,
    config: SequenceConfig | None = None,
    image_format: str | None = None,
    keep_topics: bool = False,
    progress: Callable[[int], None] | None = None,
    epoch_ns: int | None = None,
) -> Path:
    """Write ``seq`` as ``kind`` (see :data:`OUTPUT_KINDS`) to ``dst``, atomically.

    Frames and ground truth go into bags; stripes, laser images and attachments only into the MCAP.
    ``image_format`` None: ``raw`` (``sensor_msgs/Image``) in bags, ``png`` in the MCAP.
    ``epoch_ns``: added to every stamp of a bag (a source with relative times, such as KITTI's
    ``times.txt``, placed at a stated date instead of 1970).
    """
    from loopmodel.io.sequence import convert_to_mcap

    cfg = (config or SequenceConfig()).model_copy()
    cfg.topics = source_topics(seq, cfg, keep_topics)
    if kind == "mcap":
        return convert_to_mcap(seq, dst, cfg, image_format or "png", progress)
    offset = int(epoch_ns or 0)
    with BagSequenceWriter(
        dst, seq.calibration, kind, cfg.topics, image_format or "raw", time_offset_ns=offset
    ) as writer:
        if seq.ground_truth is not None:
            writer.write_trajectory(seq.ground_truth)
        for i, frame in enumerate(seq.frames(), 1):
            writer.write_frame(frame)
            if progress is not None:
                progress(i)
    return Path(dst)


def relative_times(seq: Sequence) -> bool:
    """True when the sequence's stamps start within a day of 0 (relative times: 1970 to ROS tools)."""
    times = seq.frame_times_ns()
    return times is not None and len(times) > 0 and int(times[0]) < 86_400 * 10**9


def parse_epoch_ns(text: str) -> int:
    """An epoch given as ISO 8601 (``2011-10-03T12:55:00Z``, UTC when no zone is given) or seconds, in ns."""
    from datetime import UTC, datetime

    try:
        return int(round(float(text) * 1e9))
    except ValueError:
        pass
    when = datetime.fromisoformat(text.replace("Z", "+00:00"))
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return int(round(when.timestamp() * 1e9))
