"""Descriptors on stereo keyframes and relocalization with 50 % wrong matches."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from loopmodel.errors import ConfigError
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose, make_pose, so3_exp, so3_log
from loopmodel.loop.features import (
    FeatureSet,
    describe_at,
    detect_and_describe,
    make_extractor,
    stereo_keyframe_features,
)
from loopmodel.loop.reloc import RelocParams, localize
from loopmodel.loop.surf import Surf
from loopmodel.types import StereoCalibration

CAM = CentralCamera(500.0, 500.0, 319.5, 239.5)


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    img = rng.integers(0, 256, (h // 8, w // 8)).astype(np.uint8)
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC)
    return cv2.GaussianBlur(img, (3, 3), 0.8)


def _flip_bits(desc: np.ndarray, rng: np.random.Generator, n_bits: int) -> np.ndarray:
    out = desc.copy()
    for row in out:
        bits = rng.choice(256, n_bits, replace=False)
        row[bits // 8] ^= (1 << (bits % 8)).astype(np.uint8)
    return out


def test_surf_extractor_and_unknown_kind() -> None:
    """SURF is always available (written here); an unknown kind is a configuration error."""
    assert isinstance(make_extractor("surf", 300), Surf)
    with pytest.raises(ConfigError, match="unknown descriptor"):
        make_extractor("akaze-ish")


def test_stereo_keyframe_features_depth(rng: np.random.Generator) -> None:
    """Fronto-parallel textured plane at 3 m: the right image is the left shifted by the
    disparity f*B/Z = 20 px, so every triangulated feature must lie at Z = 3 m."""
    left = _texture(rng, 480, 680)
    right = np.roll(left, -20, axis=1)
    left, right = left[:, :640].copy(), right[:, :640].copy()
    right_from_left = make_pose(np.eye(3), [-0.12, 0.0, 0.0])
    calib = StereoCalibration(CAM.K, CAM.K, right_from_left, (640, 480))
    fs = stereo_keyframe_features(left, right, calib, "orb", 1500)
    has = fs.has_3d
    assert has.sum() > 200
    assert np.median(np.abs(fs.points_in_kf[has, 2] - 3.0)) < 0.02
    assert np.percentile(np.abs(fs.points_in_kf[has, 2] - 3.0), 95) < 0.2
    # X, Y consistent with the left pixel rays
    uv = CAM.project(fs.points_in_kf[has])
    assert np.median(np.linalg.norm(uv - fs.keypoints_px[has], axis=1)) < 0.5


def test_relocalization_with_half_wrong_matches(rng: np.random.Generator) -> None:
    """Synthetic map of 600 landmarks with binary descriptors; the query view sees them from
    a new pose with 0.5 px noise, and half of its descriptors belong to other landmarks."""
    m = 600
    p_map = np.column_stack([rng.uniform(-3, 3, m), rng.uniform(-2, 2, m), rng.uniform(4, 9, m)])
    desc = rng.integers(0, 256, (m, 32), dtype=np.uint8)
    landmarks = FeatureSet(CAM.project(p_map), desc, "orb", p_map)
    cam_from_map = make_pose(so3_exp([0.05, 0.25, -0.03]), [0.6, -0.1, 0.3])
    p_cam = p_map @ cam_from_map[:3, :3].T + cam_from_map[:3, 3]
    uv = CAM.project(p_cam) + rng.normal(0, 0.5, (m, 2))
    q_desc = _flip_bits(desc, rng, 12)
    wrong = rng.random(m) < 0.5
    q_desc[wrong] = q_desc[rng.permutation(np.flatnonzero(wrong))]  # wrong landmark's descriptor
    wrong_true = wrong & np.any(q_desc != _flip_bits(desc, np.random.default_rng(0), 0), axis=1)
    query = FeatureSet(uv, q_desc, "orb")
    res = localize(query, landmarks, CAM, RelocParams(threshold_px=2.0))
    assert res.success, res.reason
    assert res.cam_from_map is not None
    T = res.cam_from_map
    rot_deg = np.degrees(np.linalg.norm(so3_log(T[:3, :3] @ cam_from_map[:3, :3].T)))
    pos_m = np.linalg.norm(invert_pose(T)[:3, 3] - invert_pose(cam_from_map)[:3, 3])
    assert rot_deg < 0.1
    assert pos_m < 0.01
    assert res.matches is not None and res.inliers is not None
    right = res.matches[:, 0] == res.matches[:, 1]
    assert np.mean(~right) > 0.4  # about half of the matches are wrong
    assert np.all(right[res.inliers])  # and none of them is an inlier
    assert wrong_true.sum() > 0.4 * m


def test_relocalization_refuses_unrelated_view(rng: np.random.Generator) -> None:
    """Matches between unrelated features (random geometry) must not give a pose."""
    m = 300
    p_map = np.column_stack([rng.uniform(-3, 3, m), rng.uniform(-2, 2, m), rng.uniform(4, 9, m)])
    desc = rng.integers(0, 256, (m, 32), dtype=np.uint8)
    landmarks = FeatureSet(CAM.project(p_map), desc, "orb", p_map)
    query = FeatureSet(rng.uniform([0, 0], [640, 480], (m, 2)), _flip_bits(desc, rng, 12), "orb")
    res = localize(query, landmarks, CAM, RelocParams(threshold_px=2.0))
    assert not res.success


def test_detect_and_describe_kinds(rng: np.random.Generator) -> None:
    img = _texture(rng, 240, 320)
    for kind, dtype, dim in (("orb", np.uint8, 32), ("sift", np.float32, 128), ("surf", np.float32, 64)):
        fs = detect_and_describe(img, kind, 300)
        assert len(fs) > 50 and fs.descriptors.dtype == dtype and fs.descriptors.shape[1] == dim
        assert np.all(np.isnan(fs.points_in_kf))
        assert np.all(fs.laplacian != 0) == (kind == "surf")


def test_stereo_keyframe_features_surf(rng: np.random.Generator) -> None:
    """SURF on a stereo keyframe: the fronto-parallel plane at 3 m is triangulated at 3 m
    (same set-up as the ORB test above), and descriptors at given pixels keep every point
    inside the image."""
    left = _texture(rng, 480, 680)
    right = np.roll(left, -20, axis=1)
    left, right = left[:, :640].copy(), right[:, :640].copy()
    calib = StereoCalibration(CAM.K, CAM.K, make_pose(np.eye(3), [-0.12, 0.0, 0.0]), (640, 480))
    fs = stereo_keyframe_features(left, right, calib, "surf", 1500)
    has = fs.has_3d
    assert has.sum() > 150
    assert np.median(np.abs(fs.points_in_kf[has, 2] - 3.0)) < 0.02
    uv = np.array([[10.0, 10.0], [320.0, 240.0], [639.0, 479.0], [700.0, 10.0]])
    at, kept = describe_at(left, uv, "surf")
    assert kept.tolist() == [0, 1, 2] and at.descriptors.shape == (3, 64) and np.all(at.laplacian != 0)
