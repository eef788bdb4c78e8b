"""Stereo and laser-plane calibration.

Rendered chessboards with a known rig and plane, the real OpenCV stereo sample and the real
laser-calibration images, and bad input.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from loopmodel.calibration.chessboard import parse_board
from loopmodel.calibration.laser import calibrate_laser_plane, read_laser_planes_json
from loopmodel.calibration.stereo import calibrate_stereo, pair_images, write_stereo_outputs
from loopmodel.cli import main
from loopmodel.errors import InputError
from loopmodel.geometry.se3 import make_pose, so3_exp, so3_log
from loopmodel.io.calib_files import read_stereo_calibration
from loopmodel.io.camera_yaml import read_camera_info_pair, read_intrinsics
from loopmodel.io.kitti import calibration_from_projections, parse_kitti_calib
from tests.calib_scene import board_pose, render_board

SIZE = (640, 480)
K_L = np.array([[520.0, 0, 322.0], [0, 518.0, 243.0], [0, 0, 1]])
K_R = np.array([[515.0, 0, 317.0], [0, 516.0, 238.0], [0, 0, 1]])
D_L = np.array([-0.22, 0.06, 0.0, 0.0, 0.0])
D_R = np.array([-0.18, 0.04, 0.0, 0.0, 0.0])
RIGHT_FROM_LEFT = make_pose(so3_exp([0.01, -0.02, 0.005]), [-0.1, 0.002, 0.001])
BOARD, SQUARE = (9, 6), 0.025


@pytest.fixture(scope="module")
def stereo_pairs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """12 rendered chessboard pairs of the known rig (seeded)."""
    out = tmp_path_factory.mktemp("stereo")
    rng = np.random.default_rng(7)
    k = 0
    while k < 12:
        T = board_pose(rng, ((BOARD[0] - 1) * SQUARE, (BOARD[1] - 1) * SQUARE), 0.45)
        left = render_board(K_L, D_L, SIZE, T, BOARD, SQUARE, rng)
        right = render_board(K_R, D_R, SIZE, RIGHT_FROM_LEFT @ T, BOARD, SQUARE, rng)
        ok_l = cv2.findChessboardCorners(cv2.cvtColor(left, cv2.COLOR_BGR2GRAY), BOARD)[0]
        ok_r = cv2.findChessboardCorners(cv2.cvtColor(right, cv2.COLOR_BGR2GRAY), BOARD)[0]
        if not (ok_l and ok_r):
            continue  # the random pose put the board out of one view
        cv2.imwrite(str(out / f"left{k:02d}.png"), left)
        cv2.imwrite(str(out / f"right{k:02d}.png"), right)
        k += 1
    return out


@pytest.mark.slow
def test_stereo_recovers_rendered_rig(stereo_pairs: Path, tmp_path: Path) -> None:
    pairs = pair_images(sorted(stereo_pairs.glob("left*.png")), sorted(stereo_pairs.glob("right*.png")))
    res = calibrate_stereo(pairs, BOARD, SQUARE)
    cal = res.calibration
    assert not res.rejected
    # measured (seed 7): focal 0.1-0.3 %, principal point 0.5-1 px, k1 0.003, baseline 0.01 %
    for K, Kt in ((cal.K_left, K_L), (cal.K_right, K_R)):
        assert abs(K[0, 0] / Kt[0, 0] - 1) < 0.005 and abs(K[1, 1] / Kt[1, 1] - 1) < 0.005
        assert np.hypot(K[0, 2] - Kt[0, 2], K[1, 2] - Kt[1, 2]) < 2.0
    assert abs(cal.dist_left[0] - D_L[0]) < 0.02 and abs(cal.dist_right[0] - D_R[0]) < 0.02
    assert abs(cal.baseline_m / 0.1 - 1) < 0.005
    rot_err = np.degrees(np.linalg.norm(so3_log(cal.right_from_left[:3, :3] @ RIGHT_FROM_LEFT[:3, :3].T)))
    assert rot_err < 0.2  # measured 0.13 deg (coupled with the principal points' 0.5-1 px)
    assert res.rms_stereo_px < 0.3 and res.epipolar_err_px_rms < 0.3
    # same-run plain OpenCV on the same corners
    assert abs(res.rms_stereo_px - res.reference_rms_stereo_px) < 0.05
    # every reader of the project accepts what is written
    out = tmp_path / "calib.yaml"
    paths = write_stereo_outputs(res, out)
    assert all(p.is_file() for p in paths)
    back = read_camera_info_pair(tmp_path / "calib_left.yaml", tmp_path / "calib_right.yaml")
    assert np.allclose(back.right_from_left, cal.right_from_left, atol=1e-9)
    assert np.allclose(back.K_left, cal.K_left) and np.allclose(back.dist_right, cal.dist_right)
    # the summary YAML is accepted where bag readers take a calibration file (--calib)
    summary = read_stereo_calibration(out, SIZE)
    assert np.allclose(summary.right_from_left, back.right_from_left) and np.allclose(summary.K_right, back.K_right)
    P0, P1 = parse_kitti_calib(tmp_path / "calib_kitti_calib.txt")
    rect = calibration_from_projections(P0, P1, SIZE, "kitti")
    assert abs(rect.baseline_m - cal.baseline_m) < 1e-9
    K, d, size = read_intrinsics(out)
    assert np.allclose(K, cal.K_left) and size == SIZE


@pytest.mark.slow
def test_stereo_bad_input_one_line_exit_2(
    stereo_pairs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    left, right = str(stereo_pairs / "left0[0-2].png"), str(stereo_pairs / "right0[0-2].png")
    # wrong board size: no corners anywhere
    assert main(["calibrate", "stereo", left, right, "--board", "7x4", "--out", str(tmp_path / "c.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "left00.png" in err[0] and "7x4" in err[0]
    assert not (tmp_path / "c.yaml").exists()
    # an image of another size
    odd = tmp_path / "odd"
    odd.mkdir()
    for p in sorted(stereo_pairs.glob("*0[0-4].png")):
        (odd / p.name).write_bytes(p.read_bytes())
    cv2.imwrite(str(odd / "right03.png"), np.zeros((240, 320, 3), np.uint8))
    assert (
        main(
            ["calibrate", "stereo", str(odd / "left*.png"), str(odd / "right*.png"), "--out", str(tmp_path / "d.yaml")]
        )
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "right03.png" in err[0] and "320x240" in err[0]
    with pytest.raises(InputError):
        parse_board("9by6")


LASER_N = np.array([0.93, 0.05, -0.36]) / np.linalg.norm([0.93, 0.05, -0.36])
LASER_D = 0.16  # the line crosses z = 0.5 m at x = 2 cm


@pytest.fixture(scope="module")
def laser_images(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four rendered boards (8x6, 30 mm) crossed by a known laser plane, and the intrinsics."""
    out = tmp_path_factory.mktemp("laser")
    rng = np.random.default_rng(11)
    board, square = (8, 6), 0.03
    k = 0
    while k < 4:
        T = board_pose(rng, (7 * square, 5 * square), 0.5)
        img = render_board(K_L, D_L, SIZE, T, board, square, rng, laser=(LASER_N, LASER_D), margin_squares=1.5)
        if not cv2.findChessboardCorners(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), board)[0]:
            continue
        cv2.imwrite(str(out / f"bcap{k}.png"), img)
        k += 1
    (out / "cam.yaml").write_text(f"camera_matrix: {K_L.tolist()}\ndist_coeff: [{D_L.tolist()}]\n")
    return out


def test_laser_plane_recovers_rendered_plane(laser_images: Path) -> None:
    K, d, _ = read_intrinsics(laser_images / "cam.yaml")
    res = calibrate_laser_plane(sorted(laser_images.glob("bcap*.png")), K, d, (8, 6), 0.03)
    assert len(res.views) == 4
    n = res.plane.normal_in_cam * np.sign(res.plane.normal_in_cam @ LASER_N)
    angle = np.degrees(np.arccos(min(1.0, float(n @ LASER_N))))
    offset_mm = 1e3 * abs(res.plane.d_m * np.sign(res.plane.normal_in_cam @ LASER_N) - LASER_D)
    # measured: 0.05 deg, 0.1 mm, RMS 0.05 mm
    assert angle < 0.3 and offset_mm < 0.5
    assert res.rms_mm < 0.2


def test_laser_bad_input(laser_images: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    one = str(laser_images / "bcap0.png")
    cam = str(laser_images / "cam.yaml")
    assert (
        main(
            [
                "calibrate",
                "laser",
                one,
                "--intrinsics",
                cam,
                "--board",
                "8x6",
                "--square-m",
                "0.03",
                "--out",
                str(tmp_path / "p.yaml"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "two or more poses" in err[0] and "bcap0.png" in err[0]
    # an image of another size than the intrinsics
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((1080, 1920, 3), np.uint8))
    assert (
        main(
            ["calibrate", "laser", str(tmp_path / "small.png"), "--intrinsics", cam, "--out", str(tmp_path / "p.yaml")]
        )
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "small.png" in err[0] and "1920x1080" in err[0]
    assert not (tmp_path / "p.yaml").exists()


def test_real_stereo_sample(shared_data: Path) -> None:
    d = shared_data / "stereo_calib"
    res = calibrate_stereo(
        pair_images(sorted(d.glob("left[0-9]*.jpg")), sorted(d.glob("right[0-9]*.jpg"))), (9, 6), 1.0
    )
    assert len(res.views) == 13
    # measured 0.197 / 0.303 / 0.267 px against plain OpenCV's 0.197 / 0.302 / 0.269 px
    assert abs(res.rms_left_px - res.reference_rms_left_px) < 0.05
    assert abs(res.rms_right_px - res.reference_rms_right_px) < 0.05
    assert abs(res.rms_stereo_px - res.reference_rms_stereo_px) < 0.05
    assert res.epipolar_err_px_rms <= 0.5  # measured 0.243
    assert 3.2 < res.calibration.baseline_m < 3.45  # squares; measured 3.33


@pytest.mark.slow
def test_real_laser_plane(shared_data: Path) -> None:
    d = shared_data / "turntable_laser"
    K, dist, size = read_intrinsics(d / "calibration3.yaml")
    res = calibrate_laser_plane(sorted((d / "laser_calibration").glob("bcap*.jpg")), K, dist, (8, 6), 0.04, size)
    assert len(res.views) == 6
    assert res.rms_mm < 0.3  # measured 0.145 mm
    assert res.line_to_plane_deg_max < 0.3  # measured 0.08 deg
    best = res.compare(read_laser_planes_json(d / "laser_planes.json"))[0]
    assert best["rms_mm"] > 50  # none of the saved planes is this one (measured 114 mm at best)


def test_stereo_cli_prints_units_and_four_digits(
    stereo_pairs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 35: ``baseline 0.1000 m`` and ``fx 700.1 px``, not ``baseline 3.33062`` or ``fx_px: 469.367``."""
    import re

    from loopmodel.cli import main

    args = ["calibrate", "stereo", str(stereo_pairs / "left*.png"), str(stereo_pairs / "right*.png")]
    board = f"{BOARD[0]}x{BOARD[1]}"
    assert main([*args, "--board", board, "--square-m", str(SQUARE), "-o", str(tmp_path / "c.yaml")]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert re.search(r"baseline 0\.\d{4} m \(square", out), out
    assert re.search(r"fx \d{3}\.\d px", out) and "fx_px" not in out
    for x in re.findall(r"(?<![\w/.-])\d+\.\d+(?![\w/])", out):  # numbers, not parts of paths
        assert len(x.replace(".", "").lstrip("0")) <= 4, x  # 4 significant digits at most
