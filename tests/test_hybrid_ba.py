"""Local hybrid keyframe BA (seed 004 eq. 1) against ground truth."""

from __future__ import annotations

import numpy as np

from loopmodel.frontend.hybrid_ba import hybrid_keyframe_ba
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose, se3_exp, so3_log


def test_hybrid_ba_recovers_pose_and_points(rng: np.random.Generator) -> None:
    cam = CentralCamera(700.0, 700.0, 600.0, 180.0)
    right_from_left = np.eye(4)
    right_from_left[0, 3] = -0.5
    M = 200
    X_true = np.column_stack([rng.uniform(-5, 5, M), rng.uniform(-2, 2, M), rng.uniform(5, 25, M)])
    F_true = se3_exp([0.05, -0.02, -1.0, 0.01, 0.03, -0.005])  # f_from_kf
    sig = 0.2
    uvl = cam.project(X_true) + rng.normal(0, sig, (M, 2))
    uvr = cam.project(X_true @ right_from_left[:3, :3].T + right_from_left[:3, 3])
    uvr += rng.normal(0, sig, (M, 2))
    pf = X_true @ F_true[:3, :3].T + F_true[:3, 3]
    uvf = cam.project(pf) + rng.normal(0, sig, (M, 2))
    # initial: points perturbed in depth, pose perturbed
    X0 = X_true * rng.uniform(0.9, 1.1, (M, 1))
    F0 = se3_exp([0.03, 0.02, 0.05, 0.004, -0.004, 0.003]) @ F_true
    res = hybrid_keyframe_ba(X0, uvl, uvr, uvf, F0, cam, cam, right_from_left, iterations=20)
    d = invert_pose(F_true) @ res.f_from_kf
    assert np.linalg.norm(d[:3, 3]) < 0.01
    assert np.degrees(np.linalg.norm(so3_log(d[:3, :3]))) < 0.02
    assert res.final_rms_px < 1.5 * sig and res.final_rms_px < res.initial_rms_px
    err0 = np.median(np.linalg.norm(X0 - X_true, axis=1))
    err1 = np.median(np.linalg.norm(res.points_in_kf - X_true, axis=1))
    assert err1 < 0.3 * err0


def test_hybrid_ba_with_final_stereo_and_missing_matches(rng: np.random.Generator) -> None:
    cam = CentralCamera(700.0, 700.0, 600.0, 180.0)
    right_from_left = np.eye(4)
    right_from_left[0, 3] = -0.5
    M = 150
    X_true = np.column_stack([rng.uniform(-5, 5, M), rng.uniform(-2, 2, M), rng.uniform(5, 25, M)])
    F_true = se3_exp([0.05, -0.02, -1.0, 0.01, 0.03, -0.005])
    pf = X_true @ F_true[:3, :3].T + F_true[:3, 3]
    sig = 0.2

    def noisy(uv: np.ndarray) -> np.ndarray:
        return uv + rng.normal(0, sig, uv.shape)

    uvl = noisy(cam.project(X_true))
    uvr = noisy(cam.project(X_true + right_from_left[:3, 3]))
    uvf = noisy(cam.project(pf))
    uvfr = noisy(cam.project(pf + right_from_left[:3, 3]))
    uvfr[::3] = np.nan  # unmatched in the final right image
    X0 = X_true * rng.uniform(0.9, 1.1, (M, 1))
    F0 = se3_exp([0.03, 0.02, 0.05, 0.004, -0.004, 0.003]) @ F_true
    res = hybrid_keyframe_ba(X0, uvl, uvr, uvf, F0, cam, cam, right_from_left, iterations=20,
                             uv_final_right=uvfr)
    d = invert_pose(F_true) @ res.f_from_kf
    assert np.linalg.norm(d[:3, 3]) < 0.01
    assert np.degrees(np.linalg.norm(so3_log(d[:3, :3]))) < 0.02
    assert np.isfinite(res.final_rms_px) and res.final_rms_px < 1.5 * sig
