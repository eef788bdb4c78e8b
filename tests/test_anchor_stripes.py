"""Stripes anchored to keyframes for the session map (:func:`loopmodel.mapping.final.anchor_stripes`)."""

from __future__ import annotations

import numpy as np

from loopmodel.config import MappingConfig
from loopmodel.geometry.se3 import interpolate_poses, invert_pose, make_pose, so3_exp
from loopmodel.mapping.final import anchor_stripes
from loopmodel.types import StripeProfile, Trajectory


def test_each_stripe_is_anchored_at_its_interpolated_pose() -> None:
    rng = np.random.default_rng(3)
    t = np.arange(6, dtype=np.int64) * 100
    poses = np.stack([make_pose(so3_exp(rng.normal(0, 0.2, 3)), rng.normal(0, 0.3, 3)) for _ in t])
    final = Trajectory(t, poses)
    kf_of_frame = np.array([0, 0, 0, 3, 3, 3], np.int64)
    world_from_kf = {0: poses[0], 3: poses[3]}
    stripes = [
        StripeProfile(200, rng.normal(0, 0.1, (40, 3))),  # at frame 2
        StripeProfile(0, np.zeros((0, 3))),  # no points: left out
        StripeProfile(425, rng.normal(0, 0.1, (7, 3))),  # between frames 4 and 5 (nearest 4)
        StripeProfile(900, rng.normal(0, 0.1, (5, 3))),  # after the last frame: not placed
    ]
    anchors = anchor_stripes(stripes, final, t, kf_of_frame, world_from_kf, MappingConfig())
    assert [s.timestamp_ns for s in anchors.stripes] == [200, 425]
    assert anchors.kf_ids.tolist() == [0, 3]
    np.testing.assert_array_equal(anchors.stripes[0].points_in_cam, stripes[0].points_in_cam)  # all its points kept
    np.testing.assert_allclose(anchors.kf_from_cam[0], invert_pose(poses[0]) @ poses[2], atol=1e-12)
    between = interpolate_poses(poses[4][None], poses[5][None], np.array([0.25]))[0]
    np.testing.assert_allclose(anchors.kf_from_cam[1], invert_pose(poses[3]) @ between, atol=1e-12)
