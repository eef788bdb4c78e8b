"""A turntable scan as MCAP.

``/laser/image`` frames, the camera's ``camera_info`` and the per-frame pose ``table_from_cam`` (the
table is the world: the camera circles the object).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from loopmodel.config import TopicsConfig
from loopmodel.geometry.se3 import invert_pose
from loopmodel.io.mcap_io import McapSequenceWriter
from loopmodel.io.ros2_msgs import header
from loopmodel.turntable.reader import TurntableScan

F64 = np.ndarray


def mono_camera_info(scan: TurntableScan) -> dict:
    """CameraInfo dict of the scan's (unrectified) camera."""
    K = scan.K
    P = np.hstack([K, np.zeros((3, 1))])
    w, h = scan.image_size
    return {
        "header": header(0, "cam0"),
        "height": h,
        "width": w,
        "distortion_model": "plumb_bob",
        "d": [float(x) for x in scan.dist],
        "k": [float(x) for x in K.ravel()],
        "r": [float(x) for x in np.eye(3).ravel()],
        "p": [float(x) for x in P.ravel()],
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


def write_turntable_mcap(
    scan: TurntableScan, cam_from_table: list[F64] | None, out: Path, image_format: str = "jpeg"
) -> Path:
    """Write the scan's frames, camera info and (when given) per-frame poses as MCAP."""
    topics = TopicsConfig()
    times = scan.timestamps_ns()
    with McapSequenceWriter(out, None, topics, image_format) as w:
        w.write_camera_info(topics.left_info, times[0], mono_camera_info(scan))
        w.add_metadata(
            "turntable", {"step_deg": str(scan.step_deg), "source": str(scan.folder), "pose": "table_from_cam0"}
        )
        for k, img in scan.frames():
            w.write_image(topics.laser_image, times[k], img)
            if cam_from_table is not None:
                w.write_pose(times[k], invert_pose(cam_from_table[k]))
    return out
