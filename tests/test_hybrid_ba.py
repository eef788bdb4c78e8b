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


def test_wider_window_matches_an_independent_least_squares(rng: np.random.Generator) -> None:
    """Points of an earlier (fixed) keyframe in the BA (issue 36): the same optimum as scipy's solver.

    Small noise and a wide Huber threshold make the cost plain least squares, which
    ``scipy.optimize.least_squares`` minimises independently over the same unknowns.
    """
    from scipy.optimize import least_squares

    cam = CentralCamera(700.0, 700.0, 600.0, 180.0)
    right_from_left = np.eye(4)
    right_from_left[0, 3] = -0.5
    M0, M1 = 80, 60
    X = np.column_stack([rng.uniform(-5, 5, M0 + M1), rng.uniform(-2, 2, M0 + M1), rng.uniform(5, 25, M0 + M1)])
    F_true = se3_exp([0.05, -0.02, -1.0, 0.01, 0.03, -0.005])  # f_from_kf
    own_true = se3_exp([0.02, 0.0, 1.2, 0.0, -0.01, 0.0])  # earlier keyframe from keyframe i (fixed)
    owner = np.r_[np.zeros(M0, np.int64), np.ones(M1, np.int64)]
    frames = np.stack([np.eye(4), own_true])
    sig = 0.2

    def obs(T: np.ndarray, P: np.ndarray) -> np.ndarray:
        return cam.project(P @ T[:3, :3].T + T[:3, 3])

    uvl = np.vstack([obs(frames[k], X[owner == k]) for k in (0, 1)]) + rng.normal(0, sig, (M0 + M1, 2))
    uvr = np.vstack([obs(right_from_left @ frames[k], X[owner == k]) for k in (0, 1)])
    uvr += rng.normal(0, sig, uvr.shape)
    uvf = obs(F_true, X) + rng.normal(0, sig, (M0 + M1, 2))
    uvf[M0::4] = np.nan  # some earlier points not seen at the end
    X0 = X * rng.uniform(0.95, 1.05, (M0 + M1, 1))
    F0 = se3_exp([0.03, 0.02, 0.05, 0.004, -0.004, 0.003]) @ F_true
    res = hybrid_keyframe_ba(
        X0, uvl, uvr, uvf, F0, cam, cam, right_from_left, iterations=50, huber_px=50.0,
        owner=owner, own_from_kf=frames,
    )
    seen = np.all(np.isfinite(uvf), axis=1)

    def residuals(z: np.ndarray) -> np.ndarray:
        T = se3_exp(z[:6]) @ F0
        P = z[6:].reshape(-1, 3)
        r = [obs(frames[k], P[owner == k]) - uvl[owner == k] for k in (0, 1)]
        r += [obs(right_from_left @ frames[k], P[owner == k]) - uvr[owner == k] for k in (0, 1)]
        r.append(obs(T, P[seen]) - uvf[seen])
        return np.concatenate([a.ravel() for a in r])

    # which unknowns each residual depends on (the finite differences then take few evaluations)
    from scipy.sparse import lil_matrix

    n = M0 + M1
    rows = [np.flatnonzero(owner == k) for k in (0, 1)] * 2 + [np.flatnonzero(seen)]
    pattern = lil_matrix((2 * sum(r.size for r in rows), 6 + 3 * n), dtype=int)
    i = 0
    for blk, pts in enumerate(rows):
        for j in pts:
            for _ in range(2):
                pattern[i, 6 + 3 * j : 9 + 3 * j] = 1
                if blk == 4:
                    pattern[i, :6] = 1
                i += 1
    ref = least_squares(
        residuals, np.r_[np.zeros(6), X0.ravel()], jac_sparsity=pattern, x_scale="jac", xtol=1e-12, ftol=1e-12
    )
    F_ref = se3_exp(ref.x[:6]) @ F0
    d = invert_pose(F_ref) @ res.f_from_kf
    assert np.linalg.norm(d[:3, 3]) < 2e-4
    assert np.degrees(np.linalg.norm(so3_log(d[:3, :3]))) < 2e-3
    np.testing.assert_allclose(res.points_in_kf, ref.x[6:].reshape(-1, 3), atol=2e-3)
    # and near the truth
    dt = invert_pose(F_true) @ res.f_from_kf
    assert np.linalg.norm(dt[:3, 3]) < 0.01


def test_compiled_loop_gives_the_numpy_loop(rng: np.random.Generator) -> None:
    """The compiled Levenberg-Marquardt loop (fe11) against the numpy one, every option at once.

    An earlier keyframe's points (a wider window), the final right image with unmatched rows, per-point
    disparity sigmas, a disparity offset with a prior, 10 % outliers (Huber active); a pinhole and a
    unified (``xi`` 0.8) camera. Only the order of the sums differs: measured |d pose| <= 1e-14, points
    <= 1e-11 m on the KITTI clip's 12 keyframe BAs, the same iterations and inliers.
    """
    right_from_left = np.eye(4)
    right_from_left[0, 3] = -0.5
    for cam in (CentralCamera(700.0, 700.0, 600.0, 180.0), CentralCamera(500.0, 500.0, 320.0, 240.0, 0.8)):
        M0, M1 = 90, 40
        n = M0 + M1
        X = np.column_stack([rng.uniform(-5, 5, n), rng.uniform(-2, 2, n), rng.uniform(5, 25, n)])
        F_true = se3_exp([0.05, -0.02, -1.0, 0.01, 0.03, -0.005])
        own_true = se3_exp([0.02, 0.0, 1.2, 0.0, -0.01, 0.0])
        owner = np.r_[np.zeros(M0, np.int64), np.ones(M1, np.int64)]
        frames = np.stack([np.eye(4), own_true])

        def obs(T: np.ndarray, P: np.ndarray, cam: CentralCamera = cam) -> np.ndarray:
            return cam.project(P @ T[:3, :3].T + T[:3, 3])

        uvl = np.vstack([obs(frames[k], X[owner == k]) for k in (0, 1)]) + rng.normal(0, 0.2, (n, 2))
        uvr = np.vstack([obs(right_from_left @ frames[k], X[owner == k]) for k in (0, 1)]) + 0.3  # offset 0.3 px
        uvr += rng.normal(0, 0.2, uvr.shape)
        uvf = obs(F_true, X) + rng.normal(0, 0.2, (n, 2))
        uvf[rng.random(n) < 0.1] += rng.normal(0, 15, 2)  # outliers
        uvf[M0::4] = np.nan
        uvfr = np.full((n, 2), np.nan)
        uvfr[:M0] = obs(right_from_left @ F_true, X[:M0]) + 0.3 + rng.normal(0, 0.2, (M0, 2))
        uvfr[:M0:3] = np.nan
        X0 = X * rng.uniform(0.95, 1.05, (n, 1))
        F0 = se3_exp([0.03, 0.02, 0.05, 0.004, -0.004, 0.003]) @ F_true
        kw = {"uv_final_right": uvfr, "right_sigma_px": rng.uniform(0.05, 0.4, n), "estimate_disparity_offset": True,
              "offset_prior": (0.1, 4.0), "owner": owner, "own_from_kf": frames}
        got = hybrid_keyframe_ba(X0, uvl, uvr, uvf, F0, cam, cam, right_from_left, iterations=10, **kw)
        want = hybrid_keyframe_ba(X0, uvl, uvr, uvf, F0, cam, cam, right_from_left, iterations=10, compiled=False,
                                  **kw)
        assert got.iterations == want.iterations >= 3
        np.testing.assert_array_equal(got.inliers, want.inliers)
        assert 0 < (~got.inliers).sum() < 0.3 * n  # the outliers are found
        np.testing.assert_allclose(got.f_from_kf, want.f_from_kf, rtol=0, atol=1e-10)
        np.testing.assert_allclose(got.points_in_kf, want.points_in_kf, rtol=0, atol=1e-8)
        for f in ("initial_rms_px", "final_rms_px", "disparity_offset_px", "disparity_offset_var_px2"):
            assert abs(getattr(got, f) - getattr(want, f)) <= 1e-9 * max(1.0, abs(getattr(want, f))), f
