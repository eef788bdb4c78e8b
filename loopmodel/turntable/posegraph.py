"""The turntable's pose graph over all frames with the 360° closure (gtsam).

Variables ``X_k = cam_from_table`` (the camera is fixed, the table turns). Factors:

* a marker factor per frame: the robust solver's pose with its covariance (converted from
  the solver's left twist (v, w) to gtsam's right tangent (w, v)), Huber-robustified;
* motor odometry between consecutive frames: ``table_k_from_table_k+1 = Rz(step)`` about
  the table axis, with ``motor_sigma_deg`` about z and ``wobble_*`` for the other axes;
* the closure: the same step from the last frame back to the first (N steps = 360°).

Angles in degrees where named so, lengths in metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import hat, invert_pose, make_pose, so3_exp, so3_log

F64 = NDArray[np.float64]

#: non-cumulative step error of the stepper (deg, 1 sigma): an assumption (typical hybrid
#: stepper datasheets give +-5 % of a full step), not measured here
MOTOR_SIGMA_DEG = 0.05
#: tilt / translation freedom of the table between steps (bearing play). On the real scan a
#: once-per-turn fit of the marker poses gives a tilt of 0.1-0.3 deg and 0.5 mm amplitude,
#: i.e. 0.006 deg and 0.01 mm per 1.125 deg step; these sigmas allow twice that per step
WOBBLE_SIGMA_DEG = 0.01
WOBBLE_SIGMA_M = 2e-5


def right_covariance_wv(cam_from_table: F64, cov_left_vw: F64) -> F64:
    """The gtsam (w, v) right-tangent covariance of a pose from its left-twist covariance.

    The given covariance is that of the left twist (v, w) of ``T <- exp(delta) T``.
    """
    R, t = cam_from_table[:3, :3], cam_from_table[:3, 3]
    ad_inv = np.zeros((6, 6))
    ad_inv[:3, :3] = R.T
    ad_inv[:3, 3:] = -R.T @ hat(t)
    ad_inv[3:, 3:] = R.T
    c = ad_inv @ cov_left_vw @ ad_inv.T
    order = [3, 4, 5, 0, 1, 2]
    return c[np.ix_(order, order)]


def step_angles_deg(cam_from_table: Sequence[F64 | None], closed: bool = True) -> F64:
    """Signed rotation (deg) about the table's z axis from each frame to the next.

    And from the last to the first when ``closed``; NaN where a pose is missing.
    """
    n = len(cam_from_table)
    out = []
    for k in range(n if closed else n - 1):
        a, b = cam_from_table[k], cam_from_table[(k + 1) % n]
        if a is None or b is None:
            out.append(np.nan)
            continue
        out.append(float(np.degrees(so3_log((invert_pose(a) @ b)[:3, :3])[2])))
    return np.array(out)


@dataclass
class PoseGraphResult:
    """Optimised ``cam_from_table`` per frame and the graph's figures."""

    cam_from_table: list[F64]
    initial_error: float
    final_error: float
    iterations: int


def optimise_turntable(
    cam_from_table: list[F64 | None],
    covariance: list[F64 | None],
    step_deg: float,
    motor_sigma_deg: float = MOTOR_SIGMA_DEG,
    huber_k: float = 1.345,
) -> PoseGraphResult:
    """Loop-closed pose graph of the table poses (missing frames are bridged by the motor)."""
    n = len(cam_from_table)
    first = next((k for k, T in enumerate(cam_from_table) if T is not None), None)
    if first is None:
        raise ValueError("no frame has a table pose")
    sign = np.sign(np.nanmedian(step_angles_deg(cam_from_table))) or 1.0
    step = make_pose(so3_exp([0.0, 0.0, sign * np.radians(step_deg)]), np.zeros(3))
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    huber = gtsam.noiseModel.mEstimator.Huber.Create(huber_k)
    # initial values: measured poses, gaps filled by the motor steps
    last = cam_from_table[first]
    assert last is not None
    init: list[F64] = [np.eye(4)] * n
    for j in range(n):
        k = (first + j) % n
        T = cam_from_table[k]
        last = T if T is not None else last @ step
        init[k] = last
    for k in range(n):
        values.insert(k, gtsam.Pose3(init[k]))
        T, C = cam_from_table[k], covariance[k]
        if T is None or C is None or not np.all(np.isfinite(C)):
            continue
        Cr = right_covariance_wv(T, C)
        Cr = 0.5 * (Cr + Cr.T) + 1e-12 * np.eye(6)
        noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Gaussian.Covariance(Cr))
        graph.add(gtsam.PriorFactorPose3(k, gtsam.Pose3(T), noise))
    sig = np.array(
        [np.radians(WOBBLE_SIGMA_DEG), np.radians(WOBBLE_SIGMA_DEG), np.radians(motor_sigma_deg)] + [WOBBLE_SIGMA_M] * 3
    )
    odo = gtsam.noiseModel.Diagonal.Sigmas(sig)
    for k in range(n):  # k = n - 1 is the 360° closure back to frame 0
        graph.add(gtsam.BetweenFactorPose3(k, (k + 1) % n, gtsam.Pose3(step), odo))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(50)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    e0 = graph.error(values)
    res = opt.optimize()
    poses = [np.asarray(res.atPose3(k).matrix(), dtype=np.float64) for k in range(n)]
    return PoseGraphResult(poses, float(e0), float(graph.error(res)), int(opt.iterations()))
