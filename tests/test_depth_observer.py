"""Seed 003 depth observer.

Kinematics vs finite differences, convergence, excitation, two-view decomposition, Euclidean
reconstruction, real KITTI tracks vs stereo.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from loopmodel.geometry.se3 import invert_pose, se3_exp, so3_exp, so3_log
from loopmodel.observers import DepthObserver, ObserverConfig, ViewMeasurement, feature_jacobian, l_omega
from loopmodel.observers.homography import decompose_homography, signals_from_essential
from loopmodel.observers.kinematics import error_signals
from loopmodel.observers.simulation import pure_rotation, simulate

A_PX = np.array([[700.0, 0, 320], [0, 690.0, 240], [0, 0, 1]])


def test_l_omega_is_the_log_derivative(rng: np.random.Generator) -> None:
    for _ in range(5):
        ew = rng.normal(size=3)
        ew *= rng.uniform(0.1, 2.5) / np.linalg.norm(ew)
        w = rng.normal(size=3)
        h = 1e-6
        R = so3_exp(ew)
        fd = (so3_log(so3_exp(h * w) @ R) - so3_log(so3_exp(-h * w) @ R)) / (2 * h)
        assert np.allclose(l_omega(ew) @ w, fd, atol=1e-6)


def test_feature_jacobian_matches_kinematics(rng: np.random.Generator) -> None:
    """de/dt of a static point under a scene velocity (v_s, w_s) equals J (v_s/z*, w_s)."""
    p_ref_m = np.array([0.4, -0.3, 3.0])
    cur_from_ref = se3_exp([0.1, -0.05, 0.2, 0.1, -0.2, 0.05])
    v_s, w_s = rng.normal(size=3), rng.normal(size=3) * 0.3

    def signals(T: np.ndarray) -> np.ndarray:
        P = T[:3, :3] @ p_ref_m + T[:3, 3]
        p = A_PX @ (P / P[2])
        pr = A_PX @ (p_ref_m / p_ref_m[2])
        return error_signals(p[None, :2], pr[None, :2], [p_ref_m[2] / P[2]], T[:3, :3])[0]

    h = 1e-6
    # scene points move by d m/dt = v_s + w_s x m  <=>  cur_from_ref evolves by the left twist (v_s, w_s)
    fd = (
        signals(se3_exp(np.r_[v_s, w_s] * h) @ cur_from_ref) - signals(se3_exp(-np.r_[v_s, w_s] * h) @ cur_from_ref)
    ) / (2 * h)
    P = cur_from_ref[:3, :3] @ p_ref_m + cur_from_ref[:3, 3]
    p = A_PX @ (P / P[2])
    J = feature_jacobian(A_PX, p[:2], p_ref_m[2] / P[2], so3_log(cur_from_ref[:3, :3]))
    assert np.allclose(J @ np.r_[v_s / p_ref_m[2], w_s], fd, rtol=1e-5, atol=1e-4)


def test_true_rates_converge_to_true_ratios(rng: np.random.Generator) -> None:
    """Fed the exact signal rates, the adaptive law recovers lambda = z*_1 / z*_i."""
    pts = np.column_stack([rng.uniform(-1, 1, 8), rng.uniform(-1, 1, 8), rng.uniform(2, 5, 8)])
    p_ref = (pts @ A_PX.T)[:, :2] / pts[:, 2:3]
    obs = DepthObserver(A_PX, p_ref, ObserverConfig(l_inv0=1e-2))
    ref_from_cam = np.eye(4)
    dt = 1e-3
    for k in range(3000):
        t = k * dt
        v_cam, w_cam = np.array([np.cos(t), -np.sin(t), 0.1 * np.sin(t)]), np.array([0.05, 0.1 * np.cos(t), 0.02])
        cam_from_ref = invert_pose(ref_from_cam)
        P = pts @ cam_from_ref[:3, :3].T + cam_from_ref[:3, 3]
        p = (P @ A_PX.T)[:, :2] / P[:, 2:3]
        alpha = pts[:, 2] / P[:, 2]
        ew = so3_log(cam_from_ref[:3, :3])
        v_s, w_s = -v_cam, -w_cam
        e_dot = np.array([feature_jacobian(A_PX, p[i], alpha[i], ew) @ np.r_[v_s / pts[i, 2], w_s] for i in range(8)])
        obs.adapt(e_dot, p, alpha, ew, dt)
        ref_from_cam = ref_from_cam @ se3_exp(np.r_[v_cam, w_cam] * dt)
    assert np.allclose(obs.lambda_hat, pts[0, 2] / pts[:, 2], rtol=1e-3)


def test_paper_simulation_converges() -> None:
    res = simulate(duration_s=4.0, rate_hz=100.0, config=ObserverConfig(l_inv0=1e-3))
    assert res.converge_time_s(0.05) < 3.0
    # 1 %: the explicit-Euler sign term chattered (rms rate error ~9e-3) and left 1.3 % here
    assert res.rel_err[-1].max() < 0.01
    assert res.observer.excited


def test_pure_rotation_reports_missing_excitation() -> None:
    res = simulate(duration_s=3.0, rate_hz=100.0, motion=pure_rotation)
    assert np.all(np.isfinite(res.lambda_hat))
    assert np.abs(res.lambda_hat - 1.0).max() < 0.5  # stays near the initial guess, no divergence
    assert not res.observer.excited


def test_euclidean_reconstruction_from_one_distance() -> None:
    res = simulate(duration_s=4.0, rate_hz=100.0, config=ObserverConfig(l_inv0=1e-3))
    P = res.points_ref_m
    est = res.observer.points_from_distance(2, 5, float(np.linalg.norm(P[2] - P[5])))
    assert np.abs(est - P).max() / P[:, 2].max() < 0.03


def test_homography_decomposition_recovers_motion_and_plane(rng: np.random.Generator) -> None:
    plane_from_ref = se3_exp([0.2, -0.1, 4.0, 0.25, -0.15, 0.0])
    q = np.column_stack([rng.uniform(-1.5, 1.5, 30), rng.uniform(-1, 1, 30), np.zeros(30)])
    P = q @ plane_from_ref[:3, :3].T + plane_from_ref[:3, 3]
    cur_from_ref = se3_exp([0.3, 0.1, -0.4, 0.05, 0.1, -0.03])
    Pc = P @ cur_from_ref[:3, :3].T + cur_from_ref[:3, 3]
    pr, pc = (P @ A_PX.T)[:, :2] / P[:, 2:3], (Pc @ A_PX.T)[:, :2] / Pc[:, 2:3]
    G, _ = cv2.findHomography(pr, pc)
    sig = decompose_homography(G, A_PX, pr, pc)
    n = plane_from_ref[:3, 2] * np.sign(plane_from_ref[:3, 2] @ P[0])
    d = float(n @ P[0])
    assert np.allclose(sig.cur_from_ref_rot, cur_from_ref[:3, :3], atol=1e-5)
    assert np.allclose(sig.n_ref, n, atol=1e-5)
    assert np.allclose(sig.x_h, cur_from_ref[:3, 3] / d, atol=1e-5)
    assert np.allclose(sig.alpha, P[:, 2] / Pc[:, 2], atol=1e-6)
    # non-coplanar features: essential matrix and virtual plane through features 0, 1, 2
    X = np.column_stack([rng.uniform(-2, 2, 40), rng.uniform(-1, 1, 40), rng.uniform(4, 12, 40)])
    Xc = X @ cur_from_ref[:3, :3].T + cur_from_ref[:3, 3]
    s2 = signals_from_essential(A_PX, (X @ A_PX.T)[:, :2] / X[:, 2:3], (Xc @ A_PX.T)[:, :2] / Xc[:, 2:3])
    assert np.allclose(s2.cur_from_ref_rot, cur_from_ref[:3, :3], atol=1e-8)
    assert np.allclose(s2.alpha, X[:, 2] / Xc[:, 2], atol=1e-8)
    nv = np.cross(X[1] - X[0], X[2] - X[0])
    nv *= np.sign(nv @ X[0]) / np.linalg.norm(nv)
    assert np.allclose(s2.x_h, cur_from_ref[:3, 3] / (nv @ X[0]), atol=1e-8)


def test_kitti_tracks_against_stereo(shared_data: Path) -> None:
    from loopmodel.io import open_sequence
    from loopmodel.observers.real_tracks import observe_sequence

    seq = open_sequence(shared_data / "kitti_clip")
    frames = (f for f in seq.frames() if f.index < 26)
    results, _skipped = observe_sequence(frames, seq.calibration, window=6, stride=10)
    assert len(results) >= 2
    errs = np.concatenate([r.rel_err for r in results])
    assert errs.size > 50
    assert np.median(errs) < 0.25  # goal 10 %; measured by `bench.py depth` on the whole clip


def test_velocity_estimator_tracks_the_true_rates_without_chattering() -> None:
    """Eq. 20 discretised at 1 kHz.

    Once the start-up transient is over (1.2 s), the estimated signal rates match the analytic rates
    J (v_s/z*, w_s) (the implicit treatment of the sign term removes the numerical limit cycle of
    explicit Euler, rms ~1e-2 at these gains).
    """
    pts = np.array([[0.5, -0.2, 4.0], [-0.8, 0.4, 3.0], [0.1, 0.6, 5.5]])
    A = np.eye(3)
    errs = {}
    for implicit in (True, False):
        obs = DepthObserver(A, pts[:, :2] / pts[:, 2:3], ObserverConfig(implicit_sign=implicit))
        ref_from_cam, dt, err = np.eye(4), 1e-3, []
        for k in range(2001):
            t = k * dt
            if k > 0:
                v, w = np.array([np.cos(t - dt / 2), -np.sin(t - dt / 2), 0.1]), np.array([0.1, 0.05, 0.0])
                ref_from_cam = ref_from_cam @ se3_exp(np.r_[v, w] * dt)
            cam_from_ref = invert_pose(ref_from_cam)
            P = pts @ cam_from_ref[:3, :3].T + cam_from_ref[:3, 3]
            p, alpha, ew = P[:, :2] / P[:, 2:3], pts[:, 2] / P[:, 2], so3_log(cam_from_ref[:3, :3])
            obs.feed(ViewMeasurement(t, p, alpha, cam_from_ref[:3, :3]))
            if t > 1.2 and k % 5 == 0:
                v_s, w_s = -np.array([np.cos(t), -np.sin(t), 0.1]), -np.array([0.1, 0.05, 0.0])
                true = [feature_jacobian(A, p[i], alpha[i], ew) @ np.r_[v_s / pts[i, 2], w_s] for i in range(3)]
                err.append(obs.e_dot_hat - np.array(true))
        errs[implicit] = float(np.sqrt(np.mean(np.square(err))))
    assert errs[True] < 1e-3  # ~1e-4: the one-step lag of the discretisation
    assert errs[False] > 3 * errs[True]
