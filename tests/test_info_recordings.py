"""``loopmodel info`` describes any bag, images or not (issue 35 item 5)."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pytest
import yaml

from loopmodel.cli import main


def test_bag_without_images_is_described_as_ros2_bag_info(
    shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = shared_data / "mcap" / "tf_example"
    assert main(["info", str(bag), "--json"]) == 0
    desc = json.loads(capsys.readouterr().out)
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    # the recorder's own metadata.yaml: counts, types, duration
    want = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    assert {k: (v["type"], v["messages"]) for k, v in desc["topics"].items()} == {
        k: (t["topic_metadata"]["type"], t["message_count"]) for k, t in want.items()
    }
    assert desc["messages"] == meta["message_count"]
    assert desc["duration_s"] == pytest.approx(meta["duration"]["nanoseconds"] * 1e-9, abs=1e-6)
    # the /tf rate from the storage's receive times, read with plain sqlite3
    with sqlite3.connect(bag / "tf_example.db3") as con:
        ((lo, hi, n),) = con.execute(
            "select min(timestamp), max(timestamp), count(*) from messages m join topics t on m.topic_id = t.id "
            "where t.name = '/tf'"
        ).fetchall()
    assert desc["topics"]["/tf"]["rate_hz"] == pytest.approx((n - 1) / ((hi - lo) * 1e-9), rel=1e-9)
    assert desc["topics"]["/tf_static"]["rate_hz"] is None
    # the table: no error, rates in Hz
    assert main(["info", str(shared_data / "mcap" / "ROS_example.bag")]) == 0
    out = capsys.readouterr().out
    assert "groundtruth (PoseStamped: 12765," in out and "Hz" in out and "duration [s]" in out
