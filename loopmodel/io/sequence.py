"""``open_sequence``: pick the reader for a path.

An MCAP file, ROS 1/ROS 2 bag, EuRoC folder or KITTI folder.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from loopmodel.config import SequenceConfig
from loopmodel.errors import FormatError, InputError
from loopmodel.io.base import Sequence
from loopmodel.io.euroc import EurocSequence, euroc_root
from loopmodel.io.kitti import KittiSequence, is_kitti_folder
from loopmodel.io.mcap_io import McapSequence, McapSequenceWriter, is_mcap
from loopmodel.io.rosbag_io import BagSequence, is_bag

__all__ = ["Sequence", "open_sequence", "convert_to_mcap"]


def _has_project_topics(path: Path, cfg: SequenceConfig) -> bool:
    """True when an MCAP file has the configured stereo topics.

    Also when it has no readable summary, so that :class:`McapSequence` reports it.
    """
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:
        return True
    if summary is None:
        return True
    names = {ch.topic for ch in summary.channels.values()}
    return cfg.topics.left_image in names and cfg.topics.right_image in names


def open_sequence(
    path: str | Path,
    config: SequenceConfig | None = None,
    left: str | None = None,
    right: str | None = None,
    calibration_file: str | Path | None = None,
) -> Sequence:
    """Open a recorded sequence.

    Raises :class:`InputError` naming the path when it is missing or of an unknown layout.
    ``left``/``right`` name the stereo image topics of a bag (default: the configured ones when
    present, else guessed); ``calibration_file`` (EuRoC sensor.yaml folder or KITTI calib.txt)
    replaces a bag's CameraInfo.
    """
    cfg = config or SequenceConfig()
    p = Path(path)
    if not p.exists():
        raise InputError(p, "path does not exist")
    if not p.is_file() and not p.is_dir():  # /dev/null, a FIFO, a socket
        raise InputError(p, "expected an .mcap file or a EuRoC/KITTI folder, found a device or pipe")
    calib = None if calibration_file is None else Path(calibration_file)
    bag_args = (cfg.topics, cfg.stereo_pair_tolerance_ns, left, right, calib)
    if p.is_file():
        if p.suffix.lower() == ".mcap" or is_mcap(p):
            # the project's own MCAP (attachments, stripes, metadata) through mcap; any other
            # ROS 2 MCAP (other topic names) through rosbags
            if left is None and right is None and calib is None and _has_project_topics(p, cfg):
                return McapSequence(p, cfg.topics, cfg.stereo_pair_tolerance_ns, cfg.max_image_pixels)
            return BagSequence(p, *bag_args)
        if is_bag(p):
            return BagSequence(p, *bag_args)
        raise FormatError(p, "unknown file type (expected an .mcap, .bag or .db3 file or a EuRoC/KITTI folder)")
    folder = euroc_root(p) is not None or is_kitti_folder(p)
    if folder and (left is not None or right is not None or calib is not None):
        raise InputError("--left/--right/--calib", f"apply to bags; {p} is a EuRoC/KITTI folder")
    if euroc_root(p) is not None:
        return EurocSequence(p, cfg.stereo_pair_tolerance_ns, cfg.max_image_pixels)
    if is_kitti_folder(p):
        return KittiSequence(p, cfg.kitti_rate_hz, cfg.max_image_pixels)
    if is_bag(p):
        return BagSequence(p, *bag_args)
    found = ", ".join(sorted(x.name for x in p.iterdir())[:8]) or "empty folder"
    raise FormatError(
        p,
        "unknown folder layout (expected EuRoC mav0/cam0+cam1, KITTI image_0+image_1 with calib.txt, "
        "or a ROS 2 bag with metadata.yaml); "
        f"found: {found}",
    )


def convert_to_mcap(
    seq: Sequence,
    dst: str | Path,
    config: SequenceConfig | None = None,
    image_format: str = "png",
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Write a sequence (frames, stripes, ground truth) to an MCAP file, atomically.

    ``progress`` is called with the number of frames written so far.
    """
    cfg = config or SequenceConfig()
    with McapSequenceWriter(dst, seq.calibration, cfg.topics, image_format) as writer:
        if seq.ground_truth is not None:
            writer.write_trajectory(seq.ground_truth)
        for stripe in seq.stripes():
            writer.write_stripe(stripe)
        for i, frame in enumerate(seq.frames(), 1):
            writer.write_frame(frame)
            if progress is not None:
                progress(i)
        writer.add_metadata("source", {"path": str(seq.path), "format": seq.format_name})
    return Path(dst)
