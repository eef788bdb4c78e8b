"""Sequence readers and the MCAP writer: round trips, the KITTI clip, EuRoC, bad input."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from loopmodel.cli import main
from loopmodel.errors import CalibrationError, FormatError, InputError
from loopmodel.geometry.se3 import se3_exp
from loopmodel.io.mcap_io import McapSequenceWriter
from loopmodel.io.sequence import open_sequence
from loopmodel.types import StereoCalibration, StereoFrame, StripeProfile, Trajectory

ROOT = Path(__file__).resolve().parents[1]


def _calibration(rectified: bool = True) -> StereoCalibration:
    K = np.array([[50.0, 0, 32.5], [0, 50.1, 24.25], [0, 0, 1]])  # of the 64x48 images (issue 34)
    right_from_left = np.eye(4)
    right_from_left[0, 3] = -0.06
    if not rectified:
        right_from_left = right_from_left @ se3_exp([0, 0, 0, 0.01, -0.02, 0.005])
        d = np.array([-0.28, 0.07, 1e-4, -2e-4, 0.0])
        return StereoCalibration(K, K * [[1.01], [1.0], [1]], right_from_left, (64, 48), d, d * 0.9, rectified=False)
    return StereoCalibration(K, K, right_from_left, (64, 48))


def _write_mcap(
    path: Path, rng: np.random.Generator, n: int = 5, fmt: str = "png", cal: StereoCalibration | None = None
) -> tuple[list[StereoFrame], list[StripeProfile], Trajectory]:
    cal = cal or _calibration()
    frames = [
        StereoFrame(
            1_000_000_000 + 40_000_000 * i + i,
            rng.integers(0, 256, (48, 64), dtype=np.uint8),
            rng.integers(0, 256, (48, 64), dtype=np.uint8),
            i,
        )
        for i in range(n)
    ]
    stripes = [
        StripeProfile(1_000_000_000 + 20_000_000 * i, rng.normal(size=(17, 3)).astype(np.float32).astype(float))
        for i in range(2 * n)
    ]
    gt = Trajectory([f.timestamp_ns for f in frames], [se3_exp(rng.normal(size=6)) for _ in frames])
    with McapSequenceWriter(path, cal, image_format=fmt) as w:
        w.write_trajectory(gt)
        for s in stripes:
            w.write_stripe(s)
        for f in frames:
            w.write_frame(f)
        w.add_attachment("scene.ply", b"ply\nfake\n")
        w.add_metadata("generator", {"seed": "7"})
    return frames, stripes, gt


@pytest.mark.parametrize("fmt", ["raw", "png"])
def test_mcap_round_trip(tmp_path: Path, rng: np.random.Generator, fmt: str) -> None:
    path = tmp_path / "seq.mcap"
    frames, stripes, gt = _write_mcap(path, rng, fmt=fmt)
    seq = open_sequence(path)
    assert len(seq) == len(frames)
    got = list(seq.frames())
    assert [f.timestamp_ns for f in got] == [f.timestamp_ns for f in frames]
    for a, b in zip(got, frames, strict=True):
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    cal, ref = seq.calibration, _calibration()
    assert np.array_equal(cal.K_left, ref.K_left) and np.array_equal(cal.K_right, ref.K_right)
    assert np.allclose(cal.right_from_left, ref.right_from_left, atol=1e-15) and cal.rectified
    got_stripes = list(seq.stripes())
    assert [s.timestamp_ns for s in got_stripes] == [s.timestamp_ns for s in stripes]
    for a, b in zip(got_stripes, stripes, strict=True):
        assert np.array_equal(a.points_in_cam, b.points_in_cam)
    assert seq.ground_truth is not None
    assert np.array_equal(seq.ground_truth.timestamps_ns, gt.timestamps_ns)
    assert np.abs(seq.ground_truth.world_from_cam - gt.world_from_cam).max() < 1e-12
    assert seq.read_attachment("scene.ply") == b"ply\nfake\n"  # type: ignore[attr-defined]
    assert seq.metadata["generator"] == {"seed": "7"}  # type: ignore[attr-defined]


def test_mcap_unrectified_calibration_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    cal = _calibration(rectified=False)
    _write_mcap(tmp_path / "u.mcap", rng, n=2, cal=cal)
    back = open_sequence(tmp_path / "u.mcap").calibration
    assert not back.rectified
    assert np.allclose(back.right_from_left, cal.right_from_left, atol=1e-9)
    assert np.allclose(back.dist_left, cal.dist_left) and np.allclose(back.K_right, cal.K_right)


def test_kitti_clip(shared_data: Path) -> None:
    seq = open_sequence(shared_data / "kitti_clip")
    assert len(seq) == 51
    assert seq.calibration.fx_px == pytest.approx(707.0912)
    assert seq.calibration.baseline_m == pytest.approx(0.537, abs=1e-3)
    assert seq.ground_truth is not None and len(seq.ground_truth) == 51
    n = 0
    for frame in seq.frames():
        assert frame.left.shape == (370, 1226) and frame.right.shape == (370, 1226)
        n += 1
    assert n == 51


def test_convert_then_info(shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    dst = tmp_path / "kitti.mcap"
    assert main(["convert", str(shared_data / "kitti_clip"), str(dst)]) == 0
    capsys.readouterr()
    assert main(["info", str(dst), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert main(["info", str(shared_data / "kitti_clip"), "--json"]) == 0
    ref = json.loads(capsys.readouterr().out)
    assert info["frames"] == ref["frames"] == 51
    for key in ("fx_px", "fy_px", "cx_px", "cy_px", "baseline_m"):
        assert info["calibration"][key] == pytest.approx(ref["calibration"][key], abs=1e-12)
    assert info["ground_truth"] and info["image_size"] == [1226, 370]
    a, b = open_sequence(dst), open_sequence(shared_data / "kitti_clip")
    fa, fb = next(iter(a.frames())), next(iter(b.frames()))
    assert np.array_equal(fa.left, fb.left) and fa.timestamp_ns == fb.timestamp_ns


def _write_euroc(
    root: Path, rng: np.random.Generator, n: int = 4, right_n: int | None = None, right_size: tuple[int, int] = (64, 48)
) -> None:
    body_from_cam0 = se3_exp([0.01, 0.02, 0.0, 0.0, 0.0, 0.1])
    body_from_cam1 = body_from_cam0 @ se3_exp([0.11, 0, 0, 0.002, 0.003, 0.0])
    for cam, T, size, count in (
        ("cam0", body_from_cam0, (64, 48), n),
        ("cam1", body_from_cam1, right_size, right_n or n),
    ):
        d = root / "mav0" / cam
        (d / "data").mkdir(parents=True)
        rows = ["#timestamp [ns],filename"]
        for i in range(count):
            t = 1403715523912143104 + 50_000_000 * i
            cv2.imwrite(str(d / "data" / f"{t}.png"), rng.integers(0, 256, (size[1], size[0]), dtype=np.uint8))
            rows.append(f"{t},{t}.png")
        (d / "data.csv").write_text("\n".join(rows) + "\n")
        (d / "sensor.yaml").write_text(
            yaml.safe_dump(
                {
                    "sensor_type": "camera",
                    "rate_hz": 20,
                    "T_BS": {"cols": 4, "rows": 4, "data": [float(x) for x in T.ravel()]},
                    "resolution": list(size),
                    "camera_model": "pinhole",
                    "intrinsics": [45.8654, 45.7296, 36.7215, 24.8375],  # MH_01's, of 64x48 images
                    "distortion_model": "radial-tangential",
                    "distortion_coefficients": [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05],
                }
            )
        )
    gt = root / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir(parents=True)
    lines = ["#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z,v_x,v_y,v_z,bw_x,bw_y,bw_z,ba_x,ba_y,ba_z"]
    for i in range(n):
        lines.append(f"{1403715523912143104 + 50_000_000 * i},{i * 0.1},0,1,1,0,0,0,0,0,0,0,0,0,0,0,0")
    (gt / "data.csv").write_text("\n".join(lines) + "\n")


def test_euroc_folder(tmp_path: Path, rng: np.random.Generator) -> None:
    _write_euroc(tmp_path / "MH", rng)
    seq = open_sequence(tmp_path / "MH")
    assert seq.format_name == "euroc" and len(seq) == 4
    assert not seq.calibration.rectified
    expected = np.linalg.norm(np.linalg.inv(se3_exp([0.11, 0, 0, 0.002, 0.003, 0.0]))[:3, 3])
    assert seq.calibration.baseline_m == pytest.approx(expected, abs=1e-12)
    assert seq.ground_truth is not None and len(seq.ground_truth) == 4
    assert len(list(seq.frames())) == 4


def test_bad_inputs_give_one_line_errors(
    tmp_path: Path, rng: np.random.Generator, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(InputError, match="does not exist"):
        open_sequence(tmp_path / "missing")
    (tmp_path / "odd").mkdir()
    (tmp_path / "odd" / "x.txt").write_text("x")
    with pytest.raises(FormatError, match="unknown folder layout"):
        open_sequence(tmp_path / "odd")
    # truncated MCAP
    _write_mcap(tmp_path / "ok.mcap", rng, n=3, fmt="raw")
    data = (tmp_path / "ok.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError, match="truncated or corrupt"):
        open_sequence(tmp_path / "cut.mcap")
    # CLI: one line, exit 2, no traceback
    assert main(["info", str(tmp_path / "cut.mcap")]) == 2
    err = capsys.readouterr().err
    assert "cut.mcap" in err and "Traceback" not in err and len(err.strip().splitlines()) <= 2
    # EuRoC left/right mismatch in count and size
    _write_euroc(tmp_path / "E1", rng, n=4, right_size=(32, 48))
    with pytest.raises(InputError, match="sizes differ"):
        open_sequence(tmp_path / "E1")


def test_nav2_mcap_lists_topics(shared_data: Path) -> None:
    with pytest.raises(InputError, match="topics found: .*/odom"):
        open_sequence(shared_data / "mcap" / "nav2_turtlebot.mcap")


def test_kitti_bad_layouts(tmp_path: Path, rng: np.random.Generator, caplog: pytest.LogCaptureFixture) -> None:
    def make(name: str, nl: int, nr: int, calib: str, times: str | None = None) -> Path:
        root = tmp_path / name
        for d, n in (("image_0", nl), ("image_1", nr)):
            (root / d).mkdir(parents=True)
            for i in range(n):
                cv2.imwrite(str(root / d / f"{i:06d}.png"), rng.integers(0, 256, (10, 12), dtype=np.uint8))
        (root / "calib.txt").write_text(calib)
        if times is not None:
            (root / "times.txt").write_text(times)
        return root

    good = "P0: 7 0 6 0 0 7 5 0 0 0 1 0\nP1: 7 0 6 -3.8 0 7 5 0 0 0 1 0\n"  # of 12x10 images
    # images pair by file name: the left image without a right one is skipped and reported
    with caplog.at_level(logging.WARNING, logger="loopmodel"):
        assert len(open_sequence(make("counts", 3, 2, good))) == 2
    assert "1 unpaired images skipped (left only: 000002.png" in caplog.text
    with pytest.raises(CalibrationError, match="focal length"):
        open_sequence(make("neg", 2, 2, good.replace("P0: 7 ", "P0: -7 ").replace("P1: 7 ", "P1: -7 ")))
    with pytest.raises(CalibrationError, match="non-finite|non-numeric"):
        open_sequence(make("nan", 2, 2, good.replace("P0: 7 ", "P0: nan ")))
    with pytest.raises(FormatError, match="backwards"):
        open_sequence(make("back", 3, 3, good, "0.0\n0.2\n0.1\n"))
    seq = open_sequence(make("ok", 3, 3, good))
    assert seq.calibration.baseline_m == pytest.approx(3.8 / 7)


def test_mcap_backwards_timestamps(tmp_path: Path, rng: np.random.Generator) -> None:
    path = tmp_path / "back.mcap"
    with McapSequenceWriter(path, _calibration(), image_format="raw") as w:
        for k, t in enumerate((3_000, 2_000)):  # sensor clock jumps back; receive times increase
            img = rng.integers(0, 256, (48, 64), dtype=np.uint8)
            w.write_frame(StereoFrame(t * 1_000_000, img, img), log_time_ns=(k + 1) * 1_000_000_000)
    seq = open_sequence(path)
    with pytest.raises(InputError, match="backwards"):
        list(seq.frames())


def test_writer_leaves_no_partial_file(tmp_path: Path, rng: np.random.Generator) -> None:
    path = tmp_path / "partial.mcap"
    with pytest.raises(RuntimeError), McapSequenceWriter(path, _calibration()) as w:
        img = rng.integers(0, 256, (48, 64), dtype=np.uint8)
        w.write_frame(StereoFrame(1, img, img))
        raise RuntimeError("interrupted")
    assert not path.exists() and not list(tmp_path.iterdir())


@pytest.mark.slow
def test_streaming_memory_1000_frames(tmp_path: Path) -> None:
    """Iterating a 1,000-frame raw 640x480 MCAP (about 600 MB) stays under 500 MiB peak RSS."""
    path = tmp_path / "big.mcap"
    img = np.random.default_rng(1).integers(0, 256, (480, 640), dtype=np.uint8)
    cal = StereoCalibration(
        np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]),
        np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]),
        np.array([[1, 0, 0, -0.06], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]),
        (640, 480),
    )
    with McapSequenceWriter(path, cal, image_format="raw") as w:
        for i in range(1000):
            w.write_frame(StereoFrame(i * 40_000_000 + 1, img, img))
    # VmHWM: the peak of this process's own memory map (ru_maxrss would also count the
    # forking pytest process, whose high-water mark the child inherits across exec)
    code = (
        "from loopmodel.io.sequence import open_sequence\n"
        f"n = sum(1 for _ in open_sequence({str(path)!r}).frames())\n"
        "hwm = [l for l in open('/proc/self/status') if l.startswith('VmHWM')][0].split()[1]\n"
        "print(n, int(hwm) / 1024)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    n, rss = out.stdout.split()
    assert int(n) == 1000
    assert float(rss) < 500.0, f"peak RSS {rss} MiB"
