"""ROS bags (rosbags).

Round trips of every storage and encoding against the folder reader and an independent reader
(mcap), stereo pairing by stamp, topic guessing, camera models, bad bags, trajectories from bag
topics against evo, and the real bags of ../shared/data.
"""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from loopmodel.cli import main
from loopmodel.config import SequenceConfig, TopicsConfig
from loopmodel.errors import CalibrationError, FormatError, InputError
from loopmodel.geometry.se3 import se3_exp
from loopmodel.imaging.rectify import Rectifier, rectification, undistort_rectify_map
from loopmodel.io.bag_topics import ImageTopic, camera_info_for, guess_stereo_pair
from loopmodel.io.mcap_io import McapSequence
from loopmodel.io.ros_camera import camera_info_values, decode_ros_image
from loopmodel.io.rosbag_io import BagSequence
from loopmodel.io.rosbag_writer import BagSequenceWriter, image_message_values, mosaic_rggb
from loopmodel.io.sequence import open_sequence
from loopmodel.io.stereo_pairing import PairingStats, pair_by_stamp
from loopmodel.types import StereoCalibration, StereoFrame

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "datasets" / "tiny_kitti"
LOSSLESS = ("mono8", "bgr8", "mono16", "rgb8", "bgra8", "png")
KINDS = ("ros2-sqlite3", "ros2-mcap", "ros1")


def _bag(tmp: Path, kind: str, name: str = "b") -> Path:
    return tmp / (f"{name}.bag" if kind == "ros1" else name)


def _write(path: Path, kind: str, encoding: str = "mono8", **kw: object) -> Path:
    src = open_sequence(TINY)
    with BagSequenceWriter(path, src.calibration, kind, encoding=encoding, **kw) as w:  # type: ignore[arg-type]
        w.write_trajectory(src.ground_truth)  # type: ignore[arg-type]
        for f in src.frames():
            w.write_frame(f)
    return path


def _grey(img: np.ndarray) -> np.ndarray:
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_round_trip_every_storage_and_encoding(tmp_path: Path, kind: str) -> None:
    folder = open_sequence(TINY)
    ref = list(folder.frames())
    for enc in (*LOSSLESS, "jpeg"):
        seq = open_sequence(_write(_bag(tmp_path, kind, enc), kind, enc))
        assert isinstance(seq, BagSequence) and seq.format_name.startswith(("ros1", "ros2"))
        got = list(seq.frames())
        assert [f.timestamp_ns for f in got] == [f.timestamp_ns for f in ref]
        for a, b in zip(ref, got, strict=True):
            for x, y in ((a.left, b.left), (a.right, b.right)):
                d = np.abs(_grey(y).astype(int) - x.astype(int)).max()
                if enc == "jpeg":
                    assert d <= 12  # measured 4 grey levels at OpenCV's default quality 95
                else:
                    assert d == 0, enc
        assert np.array_equal(seq.calibration.K_left, folder.calibration.K_left)
        assert seq.calibration.baseline_m == pytest.approx(folder.calibration.baseline_m, abs=1e-12)
        assert seq.ground_truth is not None and folder.ground_truth is not None
        assert np.allclose(seq.ground_truth.world_from_cam, folder.ground_truth.world_from_cam, atol=1e-12)


def test_ros2_mcap_bag_against_independent_reader(tmp_path: Path) -> None:
    """The .mcap storage written by rosbags, read by the mcap library (McapSequence)."""
    bag = _write(tmp_path / "m", "ros2-mcap", "mono8")
    storage = next(bag.glob("*.mcap"))
    ind = list(McapSequence(storage).frames())
    ours = list(open_sequence(bag).frames())
    assert len(ind) == len(ours) == len(open_sequence(TINY))
    for a, b in zip(ind, ours, strict=True):
        assert a.timestamp_ns == b.timestamp_ns and np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    # the sqlite3 storage, counted with plain sqlite3
    db = next(_write(tmp_path / "s", "ros2-sqlite3").glob("*.db3"))
    with sqlite3.connect(db) as con:
        rows = dict(
            con.execute(
                "select t.name, count(*) from messages m join topics t on m.topic_id = t.id group by t.name"
            ).fetchall()
        )
    assert rows["/cam0/image_raw"] == rows["/cam1/image_raw"] == rows["/cam0/camera_info"] == 8  # one per image


def test_single_storage_files_open(tmp_path: Path) -> None:
    for kind, ext in (("ros2-sqlite3", ".db3"), ("ros2-mcap", ".mcap")):
        bag = _write(
            tmp_path / kind,
            kind,
            "mono8",
            topics=TopicsConfig(
                left_image="/l/image_raw",
                right_image="/r/image_raw",
                left_info="/l/camera_info",
                right_info="/r/camera_info",
            ),
        )
        storage = next(bag.glob("*" + ext))
        seq = open_sequence(storage)
        assert isinstance(seq, BagSequence) and len(list(seq.frames())) == 8


def test_bayer_and_colour_decoding() -> None:
    bgr = np.zeros((8, 10, 3), np.uint8)
    bgr[:] = (10, 100, 200)
    _t, v = image_message_values(bgr, 0, "c", "bayer_rggb8")
    m = type("M", (), {**v, "header": None})()
    out = decode_ros_image(m, "sensor_msgs/msg/Image", "/t")
    assert out.shape == (8, 10, 3) and np.array_equal(
        out[2:-2, 2:-2], np.broadcast_to(bgr[2:-2, 2:-2], out[2:-2, 2:-2].shape)
    )
    assert mosaic_rggb(bgr)[0, 0] == 200 and mosaic_rggb(bgr)[1, 1] == 10
    for enc in ("rgb8", "bgra8", "mono16"):
        _t, v = image_message_values(bgr, 0, "c", enc)
        m = type("M", (), {**v, "header": None})()
        got = decode_ros_image(m, "sensor_msgs/msg/Image", "/t")
        want = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) if enc == "mono16" else bgr
        assert np.array_equal(got, want), enc


def test_pairing_with_jitter_and_drops(rng: np.random.Generator) -> None:
    n = 60
    tl = [100_000_000 * i + int(rng.integers(-300_000, 300_000)) for i in range(n)]
    tr = [100_000_000 * i + 2_000_000 + int(rng.integers(-300_000, 300_000)) for i in range(n)]
    drop_r, drop_l = {5, 6, 30}, {44}
    items = [(True, t, i) for i, t in enumerate(tl) if i not in drop_l]
    items += [(False, t, i) for i, t in enumerate(tr) if i not in drop_r]
    # arrival order by receive time with a little latency
    items.sort(key=lambda x: x[1] + (1_500_000 if x[0] else 0))
    st = PairingStats()
    pairs = list(pair_by_stamp(items, 3_000_000, st))
    assert all(p.left == p.right for p in pairs)  # never paired across a gap
    assert len(pairs) == n - len(drop_r | drop_l) == st.pairs
    assert st.unmatched_left == len(drop_r) and st.unmatched_right == len(drop_l)
    # a tolerance below the offset pairs nothing
    assert list(pair_by_stamp(items, 1_000_000)) == []
    with pytest.raises(InputError, match="right.*backwards"):
        list(pair_by_stamp([(False, 10, 0), (False, 5, 1)], 1))


def test_unsynchronised_bag_offset_and_missing_right(tmp_path: Path) -> None:
    src = open_sequence(TINY)
    frames = list(src.frames())
    bag = tmp_path / "u.bag"
    with BagSequenceWriter(bag, src.calibration, "ros1") as w:
        for f in frames:
            w.write_frame(f, right_offset_ns=2_000_000, right=f.index not in (3, 5))
    seq = open_sequence(bag)
    assert isinstance(seq, BagSequence)
    assert seq.stamp_offset_ns == 2_000_000 and seq.tolerance_ns == 3_000_000
    got = list(seq.frames())
    assert [g.timestamp_ns for g in got] == [f.timestamp_ns for f in frames if f.index not in (3, 5)]
    assert seq.pairing.unmatched_left == 2 and seq.pairing.unmatched_right == 0
    for g in got:
        f = frames[[x.timestamp_ns for x in frames].index(g.timestamp_ns)]
        assert np.array_equal(g.right, f.right)


def _it(topic: str, size: tuple[int, int] = (640, 480), rate: float = 20.0, info: bool = True) -> ImageTopic:
    return ImageTopic(
        topic,
        "sensor_msgs/msg/Image",
        100,
        rate,
        size,
        "mono8",
        topic.rsplit("/", 1)[0] + "/camera_info" if info else None,
    )


def test_topic_guessing_with_distractors() -> None:
    cases = [
        (
            [
                "/camera/color/image_raw",
                "/camera/infra1/image_rect_raw",
                "/camera/infra2/image_rect_raw",
                "/camera/depth/image_rect_raw",
            ],
            ("/camera/infra1/image_rect_raw", "/camera/infra2/image_rect_raw"),
        ),
        (
            ["/usb_cam/image_raw", "/stereo/right/image_raw", "/stereo/left/image_raw", "/stereo/left/image_rect"],
            ("/stereo/left/image_raw", "/stereo/right/image_raw"),
        ),
        (["/cam1/image_raw", "/cam0/image_raw", "/cam2/image_raw"], ("/cam0/image_raw", "/cam1/image_raw")),
        (
            [
                "/zed/zed_node/left/image_rect_color",
                "/zed/zed_node/right/image_rect_color",
                "/zed/zed_node/rgb/image_rect_color",
            ],
            ("/zed/zed_node/left/image_rect_color", "/zed/zed_node/right/image_rect_color"),
        ),
        (
            ["/camera_left/image", "/camera_right/image", "/camera_rear/image"],
            ("/camera_left/image", "/camera_right/image"),
        ),
    ]
    for names, want in cases:
        left, right = guess_stereo_pair([_it(n) for n in names])
        assert (left.topic, right.topic) == want
    # sizes or rates that differ are no pair
    with pytest.raises(LookupError, match="--left"):
        guess_stereo_pair([_it("/left/image_raw"), _it("/right/image_raw", size=(320, 240))])
    with pytest.raises(LookupError):
        guess_stereo_pair([_it("/left/image_raw", rate=30), _it("/right/image_raw", rate=15)])
    assert camera_info_for("/a/left/image_raw/compressed", ["/a/left/camera_info", "/a/right/camera_info"]) == (
        "/a/left/camera_info"
    )
    assert camera_info_for("/a/left/image_raw", ["/camera_info"]) is None


def test_bag_guess_override_and_run_message(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    topics = TopicsConfig(
        left_image="/stereo/left/image_raw",
        right_image="/stereo/right/image_raw",
        left_info="/stereo/left/camera_info",
        right_info="/stereo/right/camera_info",
    )
    bag = _write(tmp_path / "g", "ros2-sqlite3", "bgr8", topics=topics)
    seq = open_sequence(bag)
    assert isinstance(seq, BagSequence)
    assert (seq.topics.left_image, seq.topics.right_image) == (topics.left_image, topics.right_image)
    assert "guessed" in seq.choice
    swapped = open_sequence(bag, left=topics.right_image, right=topics.left_image)
    assert isinstance(swapped, BagSequence) and "given" in swapped.choice
    assert swapped.topics.left_info == topics.right_info
    assert main(["info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "/stereo/left/image_raw" in out and "guessed" in out
    with pytest.raises(InputError, match="/nope"):
        open_sequence(bag, left="/nope", right=topics.right_image)


def _one_line_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str], must: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert must in err and "Traceback" not in err and len(err.splitlines()) <= 2, err


@pytest.mark.slow
def test_bad_bags(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # missing metadata.yaml
    bag = _write(tmp_path / "nometa", "ros2-sqlite3")
    (bag / "metadata.yaml").unlink()
    _one_line_exit_2(["info", str(bag)], capsys, "metadata.yaml")
    src = open_sequence(TINY)
    f = next(iter(src.frames()))
    # unknown encoding
    bad = tmp_path / "enc.bag"
    with BagSequenceWriter(bad, src.calibration, "ros1") as w:
        w.write_image(0, 0, f.left)
        w.write_image(1, 0, f.right)
        _t, v = image_message_values(f.left, 1, "cam0", "mono8")
        v["encoding"] = "yuv422"
        w.write_message("/cam0/image_raw", "sensor_msgs/msg/Image", v, 1)
        w.write_image(1, 1, f.right)
    seq = open_sequence(bad)
    with pytest.raises(FormatError, match="/cam0/image_raw.*yuv422"):
        list(seq.frames())
    first_bad = tmp_path / "enc2.bag"
    with BagSequenceWriter(first_bad, src.calibration, "ros1") as w:
        info = camera_info_values(src.calibration)[0]
        w.write_message("/cam0/camera_info", "sensor_msgs/msg/CameraInfo", info, 0)
        _t, v = image_message_values(f.left, 0, "cam0", "mono8")
        v["encoding"] = "yuv422"
        w.write_message("/cam0/image_raw", "sensor_msgs/msg/Image", v, 0)
        w.write_image(1, 0, f.right)
    _one_line_exit_2(["info", str(first_bad)], capsys, "/cam0/image_raw: unsupported image encoding 'yuv422'")
    # no camera_info
    noinfo = tmp_path / "noinfo"
    with BagSequenceWriter(noinfo, src.calibration, "ros2-mcap") as w:
        for side, img in ((0, f.left), (1, f.right)):
            topic = ("/cam0/image_raw", "/cam1/image_raw")[side]
            w.write_message(topic, *image_message_values(img, 0, "c", "mono8"), 0)
    _one_line_exit_2(["run", str(noinfo)], capsys, "/cam0/image_raw")
    # image size differs from camera_info
    small = tmp_path / "size.bag"
    with BagSequenceWriter(small, src.calibration, "ros1") as w:
        w.write_image(0, 0, f.left)
        w.write_image(1, 0, f.right[:, :-2])
    _one_line_exit_2(["info", str(small)], capsys, "/cam1/image_raw")
    # unknown distortion model
    left, right = camera_info_values(src.calibration)
    left["distortion_model"] = "fov"
    fov = tmp_path / "fov.bag"
    with BagSequenceWriter(fov, src.calibration, "ros1", camera_info=(left, right)) as w:
        w.write_frame(f)
    _one_line_exit_2(["info", str(fov)], capsys, "/cam0/camera_info")


def test_nav2_mcap_still_clear(shared_data: Path, capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    nav2 = str(shared_data / "mcap" / "nav2_turtlebot.mcap")
    _one_line_exit_2(["run", nav2, "-o", str(tmp_path)], capsys, "no image topics")
    assert main(["info", nav2, "--json"]) == 0  # described as a recording (issue 35)
    assert '"messages": 2639' in capsys.readouterr().out


def _fisheye_cal() -> StereoCalibration:
    K = np.array([[190.0, 0, 256.0], [0, 190.5, 255.0], [0, 0, 1]])
    right_from_left = se3_exp([-0.1, 0.001, 0.002, 0.004, -0.006, 0.002])
    d = np.array([0.0034, 0.0007, -0.0015, 0.0002])  # TUM-VI-like Kannala-Brandt coefficients
    return StereoCalibration(K, K, right_from_left, (512, 512), d, d * 1.1, rectified=False, camera_model="equidistant")


def _kb_project(p: np.ndarray, K: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Kannala-Brandt projection written out: theta_d = theta (1 + k1 theta^2 + ... k4 theta^8)."""
    r = np.hypot(p[:, 0], p[:, 1])
    th = np.arctan2(r, p[:, 2])
    thd = th * (1 + d[0] * th**2 + d[1] * th**4 + d[2] * th**6 + d[3] * th**8)
    x, y = thd * p[:, 0] / r, thd * p[:, 1] / r
    return np.column_stack([K[0, 0] * x + K[0, 2], K[1, 1] * y + K[1, 2]])


def test_equidistant_rectification_against_known_projection(rng: np.random.Generator) -> None:
    cal = _fisheye_cal().check()
    R1, R2, P1, P2 = rectification(cal)
    for side, R, P in ((0, R1, P1), (1, R2, P2)):
        mapx, mapy = undistort_rectify_map(cal, side, R, P)
        pts = np.column_stack([rng.uniform(-0.4, 0.4, 200), rng.uniform(-0.4, 0.4, 200), np.ones(200)])
        pts_cam = pts if side == 0 else pts @ cal.right_from_left[:3, :3].T + cal.right_from_left[:3, 3]
        raw = _kb_project(pts_cam, cal.K_right if side else cal.K_left, cal.dist_right if side else cal.dist_left)
        rect = (P[:3, :3] @ (R @ pts_cam.T)).T
        uv = rect[:, :2] / rect[:, 2:]
        inside = (uv[:, 0] > 1) & (uv[:, 1] > 1) & (uv[:, 0] < 510) & (uv[:, 1] < 510)
        u, v = uv[inside].T
        # the maps sampled (bilinear) at the rectified point
        mx = cv2.remap(
            mapx, u.astype(np.float32).reshape(-1, 1), v.astype(np.float32).reshape(-1, 1), cv2.INTER_LINEAR
        ).ravel()
        my = cv2.remap(
            mapy, u.astype(np.float32).reshape(-1, 1), v.astype(np.float32).reshape(-1, 1), cv2.INTER_LINEAR
        ).ravel()
        assert inside.sum() > 50
        err = np.hypot(mx - raw[inside, 0], my - raw[inside, 1])
        assert np.median(err) < 0.02 and err.max() < 0.1  # bilinear interpolation of the map
    rect = Rectifier(cal)
    assert rect.calibration.rectified and rect.calibration.baseline_m == pytest.approx(cal.baseline_m, rel=1e-9)


def test_equidistant_camera_info_and_euroc_yaml(tmp_path: Path) -> None:
    cal = _fisheye_cal()
    frame = StereoFrame(0, np.zeros((512, 512), np.uint8), np.zeros((512, 512), np.uint8), 0)
    bag = tmp_path / "fish.bag"
    with BagSequenceWriter(bag, cal, "ros1") as w:
        w.write_frame(frame)
        w.write_frame(StereoFrame(50_000_000, frame.left, frame.right, 1))
    got = open_sequence(bag).calibration
    assert got.camera_model == "equidistant" and not got.rectified
    assert np.allclose(got.dist_left, cal.dist_left) and np.allclose(got.K_left, cal.K_left)
    assert np.allclose(got.right_from_left, cal.right_from_left, atol=1e-9)
    # EuRoC (TUM-VI style) sensor.yaml with equidistant distortion
    root = tmp_path / "E" / "mav0"
    for cam, T in (("cam0", np.eye(4)), ("cam1", np.linalg.inv(cal.right_from_left))):
        d = root / cam
        (d / "data").mkdir(parents=True)
        cv2.imwrite(str(d / "data" / "1000.png"), frame.left)
        (d / "data.csv").write_text("#t,f\n1000,1000.png\n")
        dist = cal.dist_left if cam == "cam0" else cal.dist_right
        (d / "sensor.yaml").write_text(
            yaml.safe_dump(
                {
                    "T_BS": {"data": [float(x) for x in T.ravel()]},
                    "resolution": [512, 512],
                    "intrinsics": [190.0, 190.5, 256.0, 255.0],
                    "distortion_model": "equidistant",
                    "distortion_coefficients": [float(x) for x in dist],
                }
            )
        )
    e = open_sequence(tmp_path / "E").calibration
    assert e.camera_model == "equidistant" and e.dist_left.size == 4
    assert np.allclose(e.right_from_left, cal.right_from_left, atol=1e-9)


def test_convert_between_formats_keeps_frames(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    topics = TopicsConfig(
        left_image="/stereo/left/image_raw",
        right_image="/stereo/right/image_raw",
        left_info="/stereo/left/camera_info",
        right_info="/stereo/right/camera_info",
    )
    src = _write(tmp_path / "src", "ros2-sqlite3", "mono8", topics=topics)
    assert main(["convert", str(src), str(tmp_path / "kept.bag"), "--keep-topics", "--image-format", "png"]) == 0
    assert main(["convert", str(src), str(tmp_path / "proj.mcap"), "--image-format", "raw"]) == 0
    assert main(["convert", str(tmp_path / "proj.mcap"), str(tmp_path / "back"), "--to", "ros2-mcap"]) == 0
    kept = open_sequence(tmp_path / "kept.bag")
    assert isinstance(kept, BagSequence) and kept.topics.left_image == topics.left_image + "/compressed"
    proj = open_sequence(tmp_path / "proj.mcap")
    assert isinstance(proj, McapSequence)
    back = open_sequence(tmp_path / "back")
    ref = list(open_sequence(TINY).frames())
    for seq in (kept, proj, back):
        for a, b in zip(ref, seq.frames(), strict=True):
            assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    assert back.ground_truth is not None and len(back.ground_truth) == len(ref)
    capsys.readouterr()
    _one_line_exit_2(["convert", str(src), str(tmp_path / "x.bag"), "--image-format", "yuv"], capsys, "--image-format")
    _one_line_exit_2(["convert", str(src), str(tmp_path / "x"), "--to", "ros1"], capsys, ".bag")


def test_run_on_bag_equals_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``loopmodel run`` on a lossless bag gives the folder's trajectory, byte for byte."""
    bag = _write(tmp_path / "r.bag", "ros1", "bgr8")
    assert main(["run", str(TINY), "--out", str(tmp_path / "o"), "--name", "folder", "--frontend-only"]) == 0
    assert main(["run", str(bag), "--out", str(tmp_path / "o"), "--name", "bag", "--frontend-only"]) == 0
    out = capsys.readouterr().out
    assert "configured" in out
    a = (tmp_path / "o" / "folder" / "trajectory_final.tum").read_text()
    b = (tmp_path / "o" / "bag" / "trajectory_final.tum").read_text()
    assert a == b and len(a.splitlines()) == 1 + 8
    # a results folder against a bag topic: the same numbers as against the folder's poses.txt
    import json

    run = tmp_path / "o" / "bag"
    assert main(["eval", str(run), "--gt", f"{bag}:/ground_truth/pose", "--no-plots", "-o", str(tmp_path / "e1")]) == 0
    assert main(["eval", str(run), "--gt", str(TINY), "--no-plots", "-o", str(tmp_path / "e2")]) == 0
    m1, m2 = (json.loads((tmp_path / e / "metrics.json").read_text()) for e in ("e1", "e2"))
    assert m1["trajectories"]["final"]["matched"] == 8
    assert m1["ate_rmse_m"] == m2["ate_rmse_m"]


# ------------------------------------------------------------------ trajectories from real bags


@pytest.mark.slow
def test_ros_example_bag_matches_evo(shared_data: Path) -> None:
    """ATE and RPE of ORB-SLAM and S-PTAM against groundtruth in the real ROS 1 bag equal evo's.

    Through ``BAG:TOPIC`` specs; evo: rosbags reader, associate 10 ms, SE(3) Umeyama.
    """
    import copy

    from evo.core import metrics, sync
    from evo.tools import file_interface
    from rosbags.rosbag1 import Reader

    from loopmodel.config import EvalConfig
    from loopmodel.eval import report as rep

    bag = shared_data / "mcap" / "ROS_example.bag"
    cfg = EvalConfig(align="se3", max_dt_ms=10.0, rpe_delta_frames=1, plots=False)
    gt = rep.load_ground_truth(f"{bag}:groundtruth")
    with Reader(bag) as reader:
        ref = file_interface.read_bag_trajectory(reader, "groundtruth")
        for name in ("ORB-SLAM", "S-PTAM"):
            est = rep.load_trajectory_file(f"{bag}:{name}")
            final = rep.evaluate_run(rep.plain_run(est), gt, cfg).metrics["trajectories"]["final"]
            a, b = sync.associate_trajectories(
                copy.deepcopy(ref), file_interface.read_bag_trajectory(reader, name), max_diff=0.01
            )
            b.align(a, correct_scale=False)
            ape = metrics.APE(metrics.PoseRelation.translation_part)
            ape.process_data((a, b))
            rpe = metrics.RPE(metrics.PoseRelation.translation_part, 1, metrics.Unit.frames, all_pairs=False)
            rpe.process_data((a, b))
            assert final["matched"] == a.num_poses
            assert final["ate_m"]["rmse"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), abs=1e-6)
            assert final["rpe_frames"]["trans_m"]["rmse"] == pytest.approx(
                rpe.get_statistic(metrics.StatisticsType.rmse), abs=1e-6
            )


def test_tf_example_trajectory(shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """/tf odom -> base_footprint (+ static base_link) from the real ROS 2 sqlite3 bag.

    Equals the same chain from the real ROS 1 bag and each /tf message composed by hand.
    """
    from rosbags.highlevel import AnyReader

    from loopmodel.io.bag_trajectory import read_bag_trajectory

    ros2 = read_bag_trajectory(shared_data / "mcap" / "tf_example", "/tf:odom.base_link")
    ros1 = read_bag_trajectory(shared_data / "mcap" / "tf_example.bag", "/tf:odom.base_link")
    assert len(ros2) == len(ros1) == 517
    assert np.array_equal(ros2.timestamps_ns, ros1.timestamps_ns)
    assert np.allclose(ros2.world_from_cam, ros1.world_from_cam, atol=1e-12)
    # by hand: the static transform from the raw messages, quaternions through scipy
    from scipy.spatial.transform import Rotation

    def mat(tr: object) -> np.ndarray:
        T = np.eye(4)
        q = tr.transform.rotation  # type: ignore[attr-defined]
        T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        p = tr.transform.translation  # type: ignore[attr-defined]
        T[:3, 3] = [p.x, p.y, p.z]
        return T

    with AnyReader([shared_data / "mcap" / "tf_example"]) as r:
        static = dyn = None
        for c, _t, raw in r.messages():
            m = r.deserialize(raw, c.msgtype)
            if c.topic == "/tf_static":
                static = mat(m.transforms[0])
            elif dyn is None:
                dyn = mat(m.transforms[0])
    assert static is not None and dyn is not None
    assert np.allclose(ros2.world_from_cam[0], dyn @ static, atol=1e-12)
    # eval of the bag's TF trajectory against itself from the ROS 1 bag: zero error
    ref = f"{shared_data / 'mcap' / 'tf_example'}:/tf:odom.base_link"
    est = f"{shared_data / 'mcap' / 'tf_example.bag'}:/tf:odom.base_link"
    assert main(["eval", "--ref", ref, "--est", est, "--no-plots", "-o", str(tmp_path / "ev")]) == 0
    capsys.readouterr()
    _one_line_exit_2(
        [
            "eval",
            "--ref",
            ref,
            "--est",
            f"{shared_data / 'mcap' / 'tf_example'}:/tf:odom.nowhere",
            "--no-plots",
            "-o",
            str(tmp_path / "ev2"),
        ],
        capsys,
        "no TF chain",
    )


def test_bag_pose_types(tmp_path: Path) -> None:
    """PoseWithCovarianceStamped, Odometry and TransformStamped topics read like PoseStamped."""
    from loopmodel.io.bag_trajectory import read_bag_trajectory

    src = open_sequence(TINY)
    gt = src.ground_truth
    assert gt is not None
    bag = tmp_path / "poses"
    with BagSequenceWriter(bag, src.calibration, "ros2-sqlite3") as w:
        for t, T in zip(gt.timestamps_ns, gt.world_from_cam, strict=True):
            from loopmodel.geometry.se3 import quat_wxyz_from_rotation

            q = quat_wxyz_from_rotation(T[:3, :3])
            pose = {
                "position": dict(zip("xyz", map(float, T[:3, 3]), strict=True)),
                "orientation": {"x": q[1], "y": q[2], "z": q[3], "w": q[0]},
            }
            hdr = {"stamp": {"sec": int(t) // 10**9, "nanosec": int(t) % 10**9}, "frame_id": "world"}
            w.write_message(
                "/pwc", "geometry_msgs/msg/PoseWithCovarianceStamped", {"header": hdr, "pose": {"pose": pose}}, int(t)
            )
            w.write_message("/odom", "nav_msgs/msg/Odometry", {"header": hdr, "pose": {"pose": pose}}, int(t))
            w.write_message(
                "/ts",
                "geometry_msgs/msg/TransformStamped",
                {"header": hdr, "transform": {"translation": pose["position"], "rotation": pose["orientation"]}},
                int(t),
            )
    for topic in ("/pwc", "/odom", "/ts"):
        tr = read_bag_trajectory(bag, topic)
        assert np.array_equal(tr.timestamps_ns, gt.timestamps_ns)
        assert np.allclose(tr.world_from_cam, gt.world_from_cam, atol=1e-12)
    with pytest.raises(InputError, match="no such topic"):
        read_bag_trajectory(bag, "/missing")


def test_sequence_config_tolerance_respected(tmp_path: Path) -> None:
    bag = _write(tmp_path / "t.bag", "ros1")
    seq = open_sequence(bag, SequenceConfig(stereo_pair_tolerance_ns=5))
    assert isinstance(seq, BagSequence) and seq.tolerance_ns == 5 and len(list(seq.frames())) == 8


def test_bag_folder_copy_without_storage(tmp_path: Path) -> None:
    bag = _write(tmp_path / "c", "ros2-sqlite3")
    for p in bag.glob("*.db3"):
        p.unlink()
    with pytest.raises((FormatError, CalibrationError)):
        open_sequence(bag)
    shutil.rmtree(bag)


@pytest.mark.parametrize("kind", KINDS)
def test_euroc_folder_into_bags(tmp_path: Path, rng: np.random.Generator, kind: str) -> None:
    """An unrectified EuRoC rig (radial-tangential) through CameraInfo K, D, R, P.

    The same images and, after the front end's rectification, the same rectified rig.
    """
    from test_sequences import _write_euroc

    _write_euroc(tmp_path / "E", rng, n=5)
    folder = open_sequence(tmp_path / "E")
    bag = _bag(tmp_path, kind, "eb")
    assert main(["convert", str(tmp_path / "E"), str(bag), "--to", kind, "--image-format", "raw"]) == 0
    seq = open_sequence(bag)
    a, b = folder.calibration, seq.calibration
    assert not b.rectified and np.allclose(a.K_left, b.K_left) and np.allclose(a.dist_left, b.dist_left)
    # extrinsics rebuilt from the rectifying R and P: measured 2.3e-11
    assert np.allclose(a.right_from_left, b.right_from_left, atol=1e-10)
    ra, rb = Rectifier(a).calibration, Rectifier(b).calibration
    assert np.allclose(ra.K_left, rb.K_left, atol=1e-9) and ra.baseline_m == pytest.approx(rb.baseline_m, abs=1e-12)
    for x, y in zip(folder.frames(), seq.frames(), strict=True):
        assert x.timestamp_ns == y.timestamp_ns and np.array_equal(x.left, y.left) and np.array_equal(x.right, y.right)
    assert seq.ground_truth is not None and folder.ground_truth is not None
    assert np.allclose(seq.ground_truth.world_from_cam, folder.ground_truth.world_from_cam, atol=1e-12)


def test_simulator_fisheye_rays_against_opencv() -> None:
    """The simulator's fisheye pixel rays project back onto their pixels.

    With OpenCV's equidistant model, and its calibration says equidistant.
    """
    from loopmodel.config import SimulationConfig
    from loopmodel.sim.generate import calibration_of, fisheye_pixel_rays

    cfg = SimulationConfig.model_validate(
        {
            "camera": {"width_px": 96, "height_px": 64, "fx_px": 40.0, "fisheye_k": [0.01, -0.002, 0.0005, 0.0]},
            "laser": {"image": False},
        }
    )
    cal = calibration_of(cfg)
    assert cal.camera_model == "equidistant" and not cal.rectified
    rays = fisheye_pixel_rays(cal.K_left, cal.dist_left, (64, 96))
    assert rays.valid.all()
    uv, _ = cv2.fisheye.projectPoints(
        rays.dirs.T.astype(float).reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cal.K_left, cal.dist_left
    )
    u, v = np.meshgrid(np.arange(96.0), np.arange(64.0))
    assert np.abs(uv.reshape(-1, 2) - np.column_stack([u.ravel(), v.ravel()])).max() < 1e-3  # float32 rays


def test_simulator_fisheye_needs_the_clean_world() -> None:
    """The realistic rig renders through its own lens: a fisheye there is refused, not ignored."""
    from loopmodel.config import SimulationConfig
    from loopmodel.errors import ConfigError
    from loopmodel.sim.generate import calibration_of

    cfg = SimulationConfig.model_validate(
        {
            "camera": {"fisheye_k": [0.01, -0.002, 0.0005, 0.0]},
            "laser": {"image": False},
            "realism": {"level": "realistic"},
        }
    )
    with pytest.raises(ConfigError, match="fisheye_k"):
        calibration_of(cfg)


def test_tf_static_camera_to_body(tmp_path: Path) -> None:
    """``body_from_cam0`` composed along /tf_static from the left image's frame to the root."""
    src = open_sequence(TINY)
    base_from_rig = se3_exp([0.1, 0.0, 0.3, 0.0, 0.2, 0.0])
    rig_from_cam0 = se3_exp([0.0, 0.05, 0.0, -1.5, 0.0, -1.5])
    bag = tmp_path / "tf"
    with BagSequenceWriter(bag, src.calibration, "ros2-sqlite3", frame_ids=("cam0_optical", "cam1_optical")) as w:
        w.write_tf_static([("base_link", "rig", base_from_rig), ("rig", "cam0_optical", rig_from_cam0)])
        for f in src.frames():
            w.write_frame(f)
    seq = open_sequence(bag)
    assert isinstance(seq, BagSequence) and seq.body_frame == "base_link"
    assert seq.body_from_cam0 is not None
    assert np.allclose(seq.body_from_cam0, base_from_rig @ rig_from_cam0, atol=1e-12)
    assert "base_link" in str(seq.describe()["body_from_cam0"])


def test_project_mcap_reader_takes_bag_encodings(tmp_path: Path) -> None:
    """An MCAP with the project's topic names but bgra8/bayer images is decoded like bags.

    Such a file is a ROS 2 recording; it is decoded through the same decoder as bags.
    """
    src = open_sequence(TINY)
    for enc in ("bgra8", "bayer_rggb8"):
        bag = _write(tmp_path / enc, "ros2-mcap", enc)
        seq = McapSequence(next(bag.glob("*.mcap")))
        for a, b in zip(src.frames(), seq.frames(), strict=True):
            d = np.abs(_grey(b.left).astype(int) - a.left.astype(int))
            assert d.max() == 0 if enc == "bgra8" else np.median(d) <= 2


def test_bag_without_camera_info_with_calibration_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """EuRoC/TUM-VI style ROS 1 bags have images only: ``--calib`` gives the calibration.

    A EuRoC sensor.yaml folder or a KITTI calib.txt.
    """
    src = open_sequence(TINY)
    bag = tmp_path / "noinfo.bag"
    with BagSequenceWriter(bag, src.calibration, "ros1") as w:
        for f in src.frames():
            for side, img in ((0, f.left), (1, f.right)):
                topic = ("/cam0/image_raw", "/cam1/image_raw")[side]
                w.write_message(topic, *image_message_values(img, f.timestamp_ns, "c", "mono8"), f.timestamp_ns)
    _one_line_exit_2(["info", str(bag)], capsys, "/cam0/image_raw: no CameraInfo")
    seq = open_sequence(bag, calibration_file=TINY / "calib.txt")
    assert np.allclose(seq.calibration.K_left, src.calibration.K_left)
    assert seq.calibration.baseline_m == pytest.approx(src.calibration.baseline_m)
    assert main(["info", str(bag), "--calib", str(TINY / "calib.txt")]) == 0
    _one_line_exit_2(["info", str(TINY), "--calib", str(TINY / "calib.txt")], capsys, "apply to bags")


def test_kalibr_camchain(tmp_path: Path) -> None:
    from loopmodel.io.calib_files import read_stereo_calibration

    cal = _fisheye_cal()
    cams = {}
    for name, d in (("cam0", cal.dist_left), ("cam1", cal.dist_right)):
        cams[name] = {
            "camera_model": "pinhole",
            "intrinsics": [190.0, 190.5, 256.0, 255.0],
            "distortion_model": "equidistant",
            "distortion_coeffs": [float(x) for x in d],
            "resolution": [512, 512],
        }
    cams["cam1"]["T_cn_cnm1"] = [[float(x) for x in row] for row in cal.right_from_left]
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(cams))
    got = read_stereo_calibration(tmp_path / "camchain.yaml", (512, 512))
    assert got.camera_model == "equidistant" and np.allclose(got.right_from_left, cal.right_from_left)
    assert np.allclose(got.dist_right, cal.dist_right) and np.allclose(got.K_left, cal.K_left)
    with pytest.raises(CalibrationError, match="resolution"):
        read_stereo_calibration(tmp_path / "camchain.yaml", (640, 480))
