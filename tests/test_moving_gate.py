"""The moving-track gate (issue 36) against points with a known depth error and a known motion.

Forward motion of 1 m per frame in front of points 10-30 m away. A static point whose stereo depth
is 2.5 depth sigmas off drifts consistently along its epipolar line (6 px after 4 m): it is kept;
without taking the depth error out the gate dropped it. A point moving sideways at 0.1 m per frame
drifts across its epipolar line: it is dropped.
"""

from __future__ import annotations

import numpy as np

from loopmodel.config import FrontendConfig
from loopmodel.frontend import FrontEnd
from loopmodel.frontend.tracker import _ActiveSet
from loopmodel.geometry.se3 import make_pose
from loopmodel.types import Keyframe, StereoCalibration

FX, B = 700.0, 0.54


def test_gate_keeps_a_static_point_with_a_depth_error_and_drops_a_moving_one() -> None:
    K = np.array([[FX, 0, 600.0], [0, FX, 180.0], [0, 0, 1.0]])
    cal = StereoCalibration(K, K, make_pose(np.eye(3), [-B, 0, 0]), (1200, 360))
    fe = FrontEnd(cal, FrontendConfig())
    rng = np.random.default_rng(3)
    n = 60
    truth = np.column_stack([rng.uniform(-8, 8, n), rng.uniform(-2, 2, n), rng.uniform(10, 30, n)])
    truth[0] = [6.0, 1.0, 12.0]  # static, 350 px right of the centre
    truth[1] = [0.0, -1.5, 15.0]  # moves sideways
    sigma_z = truth[:, 2] ** 2 / (FX * B) * 0.3  # 0.3 px of disparity
    est = truth.copy()
    est[0] *= 1.0 + 2.5 * sigma_z[0] / truth[0, 2]  # point 0: 2.5 sigma too far (6 px off after 4 m)
    kf = Keyframe(0, 0, np.eye(4), np.arange(n), est, np.zeros((n, 3)))
    fe._active = _ActiveSet(kf, np.eye(4), est, np.zeros((n, 3)), 20.0, sigma_z_m=sigma_z)
    idx = np.arange(n)
    keep = idx.copy()
    for k in range(1, 5):
        cur_from_kf = make_pose(np.eye(3), [0.0, 0.0, -1.0 * k])  # the pose solved (exact here)
        world = truth.copy()
        world[1, 0] += 0.1 * k  # point 1 moves sideways
        p = world @ cur_from_kf[:3, :3].T + cur_from_kf[:3, 3]
        uv = fe.left_camera.project(p) + rng.normal(0, 0.1, (n, 2))
        keep = fe._drop_moving(idx, keep, uv, cur_from_kf)
    assert 0 in keep and 1 not in keep
    assert len(keep) >= n - 3  # the other static points stay
