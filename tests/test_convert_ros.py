"""``loopmodel convert`` writes bags as ROS tools expect them (issue 35 item 4), read back with rosbags."""

from __future__ import annotations

from pathlib import Path

import pytest

from loopmodel.cli import main
from loopmodel.io.sequence import open_sequence

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "datasets" / "tiny_kitti"
EPOCH_NS = 1_317_646_500 * 10**9  # 2011-10-03T12:55:00Z


def _messages(bag: Path) -> dict[str, list[tuple[str, int, int]]]:
    """Per topic: (message type, header stamp ns, log time ns) of every message, by rosbags' reader."""
    from rosbags.highlevel import AnyReader

    out: dict[str, list[tuple[str, int, int]]] = {}
    with AnyReader([bag]) as reader:
        for conn, log_ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec if hasattr(msg, "header") else -1
            out.setdefault(conn.topic, []).append((conn.msgtype, stamp, log_ns))
    return out


@pytest.mark.parametrize("name", ["kitti_ros2", "kitti.bag"])
def test_bag_has_raw_images_camera_info_per_image_and_stated_stamps(
    tmp_path: Path, name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = tmp_path / name
    assert main(["convert", str(TINY), str(bag), "--epoch", "2011-10-03T12:55:00Z"]) == 0
    msgs = _messages(bag)
    n = len(open_sequence(TINY))
    times = open_sequence(TINY).frame_times_ns()
    assert times is not None
    for cam in ("cam0", "cam1"):
        images, infos = msgs[f"/{cam}/image_raw"], msgs[f"/{cam}/camera_info"]
        assert {t for t, _, _ in images} == {"sensor_msgs/msg/Image"}  # what image_transport subscribes to
        assert len(images) == len(infos) == n  # one CameraInfo per image ...
        assert [s for _, s, _ in infos] == [s for _, s, _ in images]  # ... with its stamp
        assert [s for _, s, _ in images] == [EPOCH_NS + int(t) for t in times]  # the stated epoch, not 1970
    assert all(s >= EPOCH_NS for _, s, _ in msgs["/ground_truth/pose"])
    # compressed images go to .../compressed, and our reader still finds the pair
    comp = tmp_path / "png_bag"
    assert main(["convert", str(TINY), str(comp), "--image-format", "png"]) == 0
    assert "relative" in capsys.readouterr().err  # no epoch: the note says what ROS tools will see
    cm = _messages(comp)
    assert {t for t, _, _ in cm["/cam0/image_raw/compressed"]} == {"sensor_msgs/msg/CompressedImage"}
    assert "/cam0/image_raw" not in cm
    assert len(list(open_sequence(comp).frames())) == n
    capsys.readouterr()
    assert main(["info", str(comp)]) == 0
    assert capsys.readouterr().out.count("stereo topics") == 1  # the row's label, not repeated in its value


def test_bad_epoch_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["convert", str(TINY), str(tmp_path / "b.bag"), "--epoch", "yesterday"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "--epoch" in err and "\n" not in err
    assert not (tmp_path / "b.bag").exists()
