"""Robust pose solver: synthetic 2-D/3-D correspondences with gross outliers."""

from __future__ import annotations

import numpy as np
import pytest

from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose, make_pose, se3_exp, so3_log
from loopmodel.pose import CameraRig, PointTerm, PoseOptions, estimate_pose, refine_pose


def _pose_errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    d = invert_pose(T_true) @ T_est
    return float(np.linalg.norm(d[:3, 3])), float(np.degrees(np.linalg.norm(so3_log(d[:3, :3]))))


def _scene(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-4, 4, n), rng.uniform(-2, 2, n), rng.uniform(4, 15, n)])


CAM = CentralCamera(700.0, 700.0, 600.0, 180.0)


def test_jacobian_matches_finite_differences(rng: np.random.Generator) -> None:
    rig = CameraRig.stereo(
        CAM,
        CentralCamera(650.0, 660.0, 590.0, 190.0, xi=0.3),
        make_pose(np.eye(3), [-0.5, 0.01, 0.02]),
    )
    P = _scene(rng, 20)
    term = PointTerm(rig, P, rng.normal(300, 50, (20, 2)), rng.integers(0, 2, 20))
    T = se3_exp([0.1, -0.2, 0.3, 0.05, -0.02, 0.03])
    r0, J = term.residuals_and_jacobian(T)
    eps = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        num = (term.residuals(se3_exp(d) @ T) - term.residuals(se3_exp(-d) @ T)) / (2 * eps)
        np.testing.assert_allclose(J[:, :, k], num, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("loss", ["tukey", "huber"])
def test_robust_pose_with_30pct_outliers(rng: np.random.Generator, loss: str) -> None:
    n = 300
    P = _scene(rng, n)
    T_true = se3_exp([0.4, -0.1, 1.2, 0.05, -0.08, 0.03])  # cam_from_ref
    uv = CAM.project(P @ T_true[:3, :3].T + T_true[:3, 3]) + rng.normal(0, 0.3, (n, 2))
    bad = rng.choice(n, int(0.3 * n), replace=False)
    uv[bad] += rng.uniform(-80, 80, (bad.size, 2)) + np.sign(rng.normal(size=(bad.size, 2))) * 10
    term = PointTerm(CameraRig.single(CAM), P, uv)
    # start: ransac (no init) and a perturbed init
    for init in (None, se3_exp([0.05, 0.05, -0.1, 0.01, 0.01, -0.01]) @ T_true):
        res = estimate_pose(term, init, PoseOptions(loss=loss))  # type: ignore[arg-type]
        dt, dr = _pose_errors(res.rig_from_ref, T_true)
        # Tukey rejects the outliers (the 1 mm / 0.05 deg); Huber only bounds them
        tol_m = 1e-3 if loss == "tukey" else 5e-3
        assert dt < tol_m and dr < 0.05, (dt, dr, loss, init is None)
        flagged = ~res.inliers[0]
        assert np.isin(np.flatnonzero(flagged), bad).mean() > 0.95
        assert flagged[bad].mean() > 0.9
    assert np.all(np.isfinite(res.covariance))


def test_rig_of_two_cameras_with_outliers(rng: np.random.Generator) -> None:
    cam1 = CentralCamera(400.0, 400.0, 320.0, 240.0, xi=0.8)
    R1 = np.array([[0, 0, -1], [0, 1, 0], [1, 0, 0]])
    rig = CameraRig((CAM, cam1), (np.eye(4), make_pose(R1, [0, 0, -0.1])))
    T_true = se3_exp([0.2, 0.1, -0.3, 0.02, 0.1, -0.05])  # rig_from_ref
    P0 = _scene(rng, 120)
    # points for camera 1: in front of it (its z axis is rig -x)
    P1_cam = np.column_stack(
        [rng.uniform(-3, 3, 120), rng.uniform(-2, 2, 120), rng.uniform(3, 10, 120)]
    )
    P1_rig = (P1_cam - rig.cam_from_rig[1][:3, 3]) @ rig.cam_from_rig[1][:3, :3]
    P1 = (P1_rig - T_true[:3, 3]) @ T_true[:3, :3]
    P = np.vstack([P0, P1])
    ci = np.repeat([0, 1], 120)
    term = PointTerm(rig, P, np.zeros((240, 2)), ci)
    uv = term.residuals(T_true) + rng.normal(0, 0.3, (240, 2))
    bad = rng.choice(240, 72, replace=False)
    uv[bad] += rng.uniform(20, 60, (72, 2))
    term = PointTerm(rig, P, uv, ci)
    res = estimate_pose(term, None)
    dt, dr = _pose_errors(res.rig_from_ref, T_true)
    assert dt < 2e-3 and dr < 0.05, (dt, dr)
    assert res.used_ransac


def test_refine_rejects_too_few_points() -> None:
    from loopmodel.errors import EstimationError

    term = PointTerm(CameraRig.single(CAM), np.ones((2, 3)), np.zeros((2, 2)))
    with pytest.raises(EstimationError):
        refine_pose(term, np.eye(4))


def test_nearest_rigid_repairs_a_drifted_rotation(rng: np.random.Generator) -> None:
    from loopmodel.geometry.se3 import is_rotation, nearest_rigid

    T = se3_exp([0.3, -0.2, 1.0, 0.4, -0.1, 0.2])
    bad = T.copy()
    bad[:3, :3] += rng.normal(0, 1e-3, (3, 3))
    fixed = nearest_rigid(bad)
    assert is_rotation(fixed[:3, :3], 1e-12)
    np.testing.assert_allclose(fixed[:3, 3], T[:3, 3])
    assert np.degrees(np.linalg.norm(so3_log(fixed[:3, :3].T @ T[:3, :3]))) < 0.2
    np.testing.assert_allclose(nearest_rigid(T), T, atol=1e-12)


def test_homogeneous_points_match_euclidean_and_infinity_has_the_right_jacobian(rng: np.random.Generator) -> None:
    rig = CameraRig.stereo(
        CAM,
        CentralCamera(650.0, 660.0, 590.0, 190.0, xi=0.3),
        make_pose(np.eye(3), [-0.5, 0.01, 0.02]),
    )
    P = _scene(rng, 20)
    uv = rng.normal(300, 50, (20, 2))
    ci = rng.integers(0, 2, 20)
    T = se3_exp([0.1, -0.2, 0.3, 0.05, -0.02, 0.03])
    depth = np.linalg.norm(P, axis=1)
    euclid = PointTerm(rig, P, uv, ci)
    homog = PointTerm(rig, P / depth[:, None], uv, ci, inverse_depth_per_m=1.0 / depth)
    r_e, J_e = euclid.residuals_and_jacobian(T)
    r_h, J_h = homog.residuals_and_jacobian(T)
    np.testing.assert_allclose(r_h, r_e, atol=1e-9)
    np.testing.assert_allclose(J_h, J_e, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(homog.depths(T) > 0, euclid.depths(T) > 0)
    # points at infinity: the residual ignores the translation, its Jacobian has no v block
    inf = PointTerm(rig, P / depth[:, None], uv, ci, inverse_depth_per_m=np.zeros(20))
    r0, J = inf.residuals_and_jacobian(T)
    np.testing.assert_array_equal(J[:, :, :3], 0.0)
    eps = 1e-6
    for k in range(3, 6):
        d = np.zeros(6)
        d[k] = eps
        num = (inf.residuals(se3_exp(d) @ T) - inf.residuals(se3_exp(-d) @ T)) / (2 * eps)
        np.testing.assert_allclose(J[:, :, k], num, rtol=1e-5, atol=1e-5)


def test_far_bearings_fix_the_rotation_with_few_near_points(rng: np.random.Generator) -> None:
    """A few noisy near points plus bearings at infinity: the rotation comes from the bearings."""
    rig = CameraRig.single(CAM)
    T_true = se3_exp([0.05, -0.02, 1.2, 0.004, -0.01, 0.003])  # cam_from_ref
    near = _scene(rng, 12)
    uv_near = CAM.project(near @ T_true[:3, :3].T + T_true[:3, 3]) + rng.normal(0, 1.0, (12, 2))
    rays = np.column_stack([rng.uniform(-0.8, 0.8, 200), rng.uniform(-0.25, 0.25, 200), np.ones(200)])
    uv_far = CAM.project(rays @ T_true[:3, :3].T) + rng.normal(0, 0.3, (200, 2))
    opts = PoseOptions(loss="tukey", max_iterations=20)
    near_only = refine_pose(PointTerm(rig, near, uv_near), np.eye(4), opts)
    far = PointTerm(rig, rays, uv_far, inverse_depth_per_m=np.zeros(200))
    both = refine_pose([PointTerm(rig, near, uv_near), far], np.eye(4), opts)
    _, rot_near = _pose_errors(near_only.rig_from_ref, T_true)
    _, rot_both = _pose_errors(both.rig_from_ref, T_true)
    # measured over seeds 0-4: 0.08-0.16 deg from the near points alone, 0.0006-0.006 deg with the bearings
    assert rot_both < 0.01
    assert rot_both < rot_near / 3
