"""Final refinement of a run.

Batch BA of the iSAM2 graph with re-weighted observations (against an independent gtsam batch
solution and the truth) and frames bridged between keyframes (against ground-truth motion with an
exactly known drift).
"""

from __future__ import annotations

import numpy as np
from gtsam.symbol_shorthand import L, X
from test_backend_isam2 import SIGMA_PX, batch_solution, calibration, exact_config, keyframes, scene

from loopmodel.backend import BackendEstimate
from loopmodel.backend.isam2 import Isam2Backend
from loopmodel.geometry.se3 import invert_pose, make_pose, se3_exp, so3_exp
from loopmodel.mapping.anchored import AnchoredTrajectory


def _backend(kfs: list, **kw: float) -> Isam2Backend:
    backend = Isam2Backend(calibration(), exact_config(**kw))
    for kf in kfs:
        backend.add_keyframe(kf)
    backend.refine()
    return backend


def test_batch_refine_equals_an_independent_batch_solution(rng: np.random.Generator) -> None:
    poses, pts = scene(rng)
    kfs = keyframes(rng, poses, pts)
    # the incremental back end runs with other weights and a Huber loss ...
    backend = _backend(kfs, pixel_sigma_px=2.0, huber_k=1.0)
    # ... the batch refinement re-weights every observation to the given sigma (Gaussian)
    est = backend.batch_refine(SIGMA_PX, huber_k=0.0, max_iterations=50)
    batch = batch_solution(kfs)
    assert set(est.world_from_kf) == {kf.id for kf in kfs}
    for k, T in est.world_from_kf.items():
        assert np.linalg.norm(T[:3, 3] - batch.atPose3(X(k)).translation()) < 1e-5
    for lm, p in zip(est.landmark_ids, est.landmarks_in_world, strict=True):
        assert np.allclose(p, batch.atPoint3(L(int(lm))), atol=1e-4)
    assert len(est.landmark_ids) == len(pts)


def test_batch_refine_with_huber_resists_blunders(rng: np.random.Generator) -> None:
    poses, pts = scene(rng, n_kf=6, n_pts=80)
    kfs = keyframes(rng, poses, pts)
    for kf in kfs[2:]:  # 8 px errors in the right image of a tenth of the stereo points
        kf.stereo_px[::10, 1] += 8.0
    backend = _backend(kfs)

    def error(est: BackendEstimate) -> float:
        return max(float(np.linalg.norm(T[:3, 3] - poses[k][:3, 3])) for k, T in est.world_from_kf.items())

    gaussian = error(backend.batch_refine(SIGMA_PX, huber_k=0.0))
    robust = error(backend.batch_refine(SIGMA_PX, huber_k=1.345))
    assert robust < 0.5 * gaussian, (robust, gaussian)


def _twist(rng: np.random.Generator, rot: float, trans: float) -> np.ndarray:
    return np.concatenate([rng.normal(0, trans, 3), rng.normal(0, rot, 3)])


def test_bridged_trajectory_removes_drift_that_grows_along_the_interval(rng: np.random.Generator) -> None:
    # ground truth: 3 keyframes, 10 frames per interval, hand-held-like wobble
    n = 31
    t_ns = np.arange(n, dtype=np.int64) * 40_000_000
    truth = np.stack(
        [make_pose(so3_exp([0.01 * np.sin(i), 0.02 * i, 0.0]), [0.004 * i, 0.001 * np.cos(i), 0.0]) for i in range(n)]
    )
    kf_frames = [0, 10, 20]
    drift = {0: _twist(rng, 2e-4, 3e-4), 10: _twist(rng, 2e-4, 3e-4), 20: _twist(rng, 2e-4, 3e-4)}
    anchored = AnchoredTrajectory()
    links: dict[int, tuple[int, np.ndarray]] = {}
    for i in range(n):
        a = max(k for k in kf_frames if k <= i)
        if i == a:
            anchored.set_keyframe(a, truth[a])  # keyframe poses as estimated: exact here
            if a > 0:  # the tracker's pose of this keyframe in the previous one: drifted
                prev = a - 10
                links[a] = (prev, invert_pose(truth[prev]) @ truth[a] @ se3_exp(-drift[prev]))
        alpha = (i - a) / 10
        # tracked frame pose in its keyframe: the drift grows linearly along the interval
        anchored.add_frame(
            int(t_ns[i]), kf_id=a, kf_from_cam=invert_pose(truth[a]) @ truth[i] @ se3_exp(-alpha * drift[a])
        )
    times = {k: int(t_ns[k]) for k in kf_frames}
    bridged = anchored.bridged_trajectory(times, links).world_from_cam
    plain = anchored.trajectory().world_from_cam
    # frames of the linked intervals come back to the truth, keyframes stay where they are
    np.testing.assert_allclose(bridged[:20], truth[:20], atol=1e-9)
    assert np.abs(plain[1:10] - truth[1:10]).max() > 1e-5
    # the last interval has no successor: unchanged
    np.testing.assert_allclose(bridged[20:], plain[20:], atol=1e-15)
    # without links it is the plain recomposition
    np.testing.assert_allclose(anchored.bridged_trajectory(times, {}).world_from_cam, plain, atol=1e-15)


def test_batch_refine_gives_every_keyframe_the_latest_disparity_offset(rng: np.random.Generator) -> None:
    """Keyframes matched before the front end's disparity offset estimate settled keep another offset.

    The raw right columns are 1 px off; the front end took nothing out of the first three keyframes'
    matches and 1 px out of the last three's (``ba_info``), then estimated 1 px. Re-expressed with
    that estimate, the batch refinement equals an independent batch solution of the consistent
    measurements (measured 2e-8 m); as measured it is 5.1 mm away at the worst keyframe.
    """
    poses, pts = scene(rng)
    kfs = keyframes(rng, poses, pts)
    batch = batch_solution(kfs)  # the right columns with the offset taken out of every keyframe
    for kf in kfs:
        applied = 0.0 if kf.id < 3 else 1.0
        kf.stereo_px[:, 1] += 1.0 - applied
        kf.ba_info = {"disparity_offset_applied_px": applied, "disparity_offset_estimate_px": 1.0}

    def error(est: BackendEstimate) -> float:
        worst = [np.linalg.norm(T[:3, 3] - batch.atPose3(X(k)).translation()) for k, T in est.world_from_kf.items()]
        return float(max(worst))

    shared = error(_backend(kfs).batch_refine(SIGMA_PX, huber_k=0.0, max_iterations=50))
    for kf in kfs:
        kf.ba_info = {}
    as_measured = error(_backend(kfs).batch_refine(SIGMA_PX, huber_k=0.0, max_iterations=50))
    assert shared < 1e-5 and as_measured > 1e-3, (shared, as_measured)
