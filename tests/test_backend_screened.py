"""``backend.kind.

Both`` and ``givens``: the Givens screen rejects injected blunder tracks before iSAM2 sees them, and
the result is closer to the truth than iSAM2 alone.
"""

from __future__ import annotations

import numpy as np
from test_backend_isam2 import SIGMA_PX, calibration, keyframes, scene

from loopmodel.backend import Backend, create_backend
from loopmodel.config import BackendConfig, GivensConfig


def _blunder_keyframes(rng: np.random.Generator, n_kf: int = 8) -> tuple[list, list, set]:
    poses, pts = scene(rng, n_kf=n_kf, n_pts=80)
    kfs = keyframes(rng, poses, pts, mono_from=1)
    bad: set[tuple[int, int]] = set()
    for kf in kfs[2:]:  # 2 % .. 10 % of the monocular observations of each keyframe: 12 px off
        rows = rng.choice(len(kf.mono_obs), size=3, replace=False)
        kf.mono_obs[rows, 1] += rng.choice([-12.0, 12.0], size=3)
        bad |= {(kf.id, int(kf.mono_obs[r, 0])) for r in rows}
    return poses, kfs, bad


def _pose_errors(backend: Backend, poses: list) -> float:
    est = backend.estimate(landmarks=False)
    return float(np.sqrt(np.mean([np.sum((est.world_from_kf[i][:3, 3] - T[:3, 3]) ** 2) for i, T in enumerate(poses)])))


def test_both_rejects_blunders_and_beats_isam2_alone() -> None:
    gcfg = GivensConfig(sigma_px=SIGMA_PX)
    errors = {}
    for kind in ("isam2", "both"):
        rng = np.random.default_rng(7)
        poses, kfs, bad = _blunder_keyframes(rng)
        backend = create_backend(
            BackendConfig(kind=kind, pixel_sigma_px=SIGMA_PX, blunder_sigma=0.0), calibration(), gcfg
        )
        for kf in kfs:
            backend.add_keyframe(kf)
        errors[kind] = _pose_errors(backend, poses)
        if kind == "both":
            stats = backend.screen_stats()  # type: ignore[attr-defined]
            assert stats["tested"] > 500
            assert stats["rejected"] >= 0.9 * len(bad)
            # collateral rejections (other observations of a blundered landmark) stay rare
            assert stats["rejected"] <= len(bad) + 0.02 * stats["tested"]
    assert errors["both"] < errors["isam2"]


def test_givens_backend_estimates_keyframes() -> None:
    rng = np.random.default_rng(3)
    poses, kfs, _bad = _blunder_keyframes(rng, n_kf=5)
    backend = create_backend(BackendConfig(kind="givens"), calibration(), GivensConfig(sigma_px=SIGMA_PX))
    for kf in kfs:
        backend.add_keyframe(kf)
    assert isinstance(backend, Backend)
    assert _pose_errors(backend, poses) < 0.02


def test_right_image_rows_match_finite_differences() -> None:
    from loopmodel.backend.givens_bundle import SequentialBundle
    from loopmodel.geometry.se3 import make_pose, so3_exp

    cal = calibration()
    bundle = SequentialBundle(cal.left_camera())
    bundle.right_from_left = cal.right_from_left
    T = make_pose(so3_exp([0.05, -0.1, 0.02]), [0.2, -0.1, 0.3])
    X = np.array([0.4, -0.2, 4.0])
    bundle.add_frame("f", T)
    bundle.add_point("p", X)
    oid = bundle.add_image_point("f", "p", [300.0, 200.0], right=True)
    A = bundle.image_obs[oid].a_lin

    def uv(x: np.ndarray) -> np.ndarray:
        R = T[:3, :3] @ so3_exp(x[:3])
        p = R.T @ (X + x[6:] - T[:3, 3] - x[3:6])
        p = cal.right_from_left[:3, :3] @ p + cal.right_from_left[:3, 3]
        return cal.right_camera().project(p)[0]

    h = 1e-6
    fd = np.column_stack([(uv(h * e) - uv(-h * e)) / (2 * h) for e in np.eye(9)])
    assert np.allclose(A, fd, rtol=1e-5, atol=1e-4)


def test_every_back_end_offers_the_end_of_run_protocol() -> None:
    """``final_estimate`` and ``metrics`` on every kind, declared on :class:`Backend` (no forwarding).

    The screened back end reports its screen's counts and refines through iSAM2.
    """
    from loopmodel.config import RefineConfig

    for kind in ("isam2", "givens", "both", "none"):
        rng = np.random.default_rng(5)
        poses, kfs, _bad = _blunder_keyframes(rng, n_kf=5)
        backend = create_backend(
            BackendConfig(kind=kind, pixel_sigma_px=SIGMA_PX), calibration(), GivensConfig(sigma_px=SIGMA_PX)
        )
        assert isinstance(backend, Backend)
        for kf in kfs:
            backend.add_keyframe(kf)
        plain = backend.final_estimate(None)
        refined = backend.final_estimate(RefineConfig(pixel_sigma_px=SIGMA_PX))
        assert set(refined.world_from_kf) == set(plain.world_from_kf) == {kf.id for kf in kfs}
        m = backend.metrics()
        if kind in ("givens", "both"):
            assert m["givens_tested_observations"] > 600 and m["givens_rejected_observations"] >= 9  # 9 injected
        if kind != "none":  # estimated: near the truth after refinement
            err = max(np.linalg.norm(refined.world_from_kf[i][:3, 3] - T[:3, 3]) for i, T in enumerate(poses))
            assert err < 0.01 and refined.landmark_ids.size > 0  # measured 3.8 / 5.5 / 4.0 mm
