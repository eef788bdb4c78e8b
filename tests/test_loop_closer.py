"""LoopCloser on rendered keyframes.

A revisit is found with the right relative pose, the global hybrid BA with its loop observations
removes the drift, a lost view relocalizes.
"""

from __future__ import annotations

import cv2
import numpy as np

from loopmodel.config import LoopConfig
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose, make_pose, se3_exp, so3_exp, so3_log
from loopmodel.io.vocabulary_file import loop_vocabulary, shipped_vocabulary
from loopmodel.loop.closer import LoopCloser
from loopmodel.loop.stage import LoopClosingStage, MapState
from loopmodel.types import Keyframe, StereoCalibration

CAM = CentralCamera(400.0, 400.0, 319.5, 239.5)
BASELINE = 0.12
PLANE_Z = 3.0
S = 200.0  # texture pixels per metre



def _texture(rng: np.random.Generator) -> np.ndarray:
    h, w = int(6 * S), int(10 * S)
    img = np.zeros((h, w), np.float32)
    for scale in (4, 16, 64):
        img += cv2.resize(rng.random((h // scale + 1, w // scale + 1)).astype(np.float32), (w, h))
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _render(tex: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
    """The plane Z = PLANE_Z (world), texture over X in [-5, 5], Y in [-3, 3] metres."""
    cfw = invert_pose(world_from_cam)
    R, t = cfw[:3, :3], cfw[:3, 3]
    A = np.array([[1 / S, 0, -5.0], [0, 1 / S, -3.0], [0, 0, 1.0]])
    H = CAM.K @ np.column_stack([R[:, 0], R[:, 1], PLANE_Z * R[:, 2] + t]) @ A
    return cv2.warpPerspective(tex, H, (640, 480), flags=cv2.INTER_LINEAR)


def _keyframe(kf_id: int, tex, true_T, est_T, next_lid: int, rng) -> Keyframe:
    img = _render(tex, true_T)
    c = cv2.goodFeaturesToTrack(img, 150, 0.01, 20).reshape(-1, 2)
    rays = CAM.lift(c)
    # depth along the ray to the plane (true geometry), in the camera frame
    wR, wt = true_T[:3, :3], true_T[:3, 3]
    d_w = rays @ wR.T
    s = (PLANE_Z - wt[2]) / d_w[:, 2]
    p = rays * s[:, None]
    uR = CAM.px * (p[:, 0] - BASELINE) / p[:, 2] + CAM.u0 + rng.normal(0, 0.2, len(p))
    return Keyframe(
        kf_id,
        kf_id,
        est_T,
        np.arange(next_lid, next_lid + len(p)),
        p,
        np.column_stack([c[:, 0], uR, c[:, 1]]),
        np.zeros((0, 3)),
        img,
    )


def _sequence(rng):
    """Out along x and back: keyframes 0..8 go right, 9..17 come back over the start."""
    xs = np.concatenate([np.linspace(-1.0, 1.0, 9), np.linspace(0.9, -1.0, 9)])
    true = [make_pose(so3_exp([0.0, 0.05 * np.sin(i), 0.0]), [x, 0.1 * np.sin(0.7 * i), 0.0]) for i, x in enumerate(xs)]
    est = [true[0]]
    for i in range(1, len(true)):
        rel = invert_pose(true[i - 1]) @ true[i]
        est.append(est[-1] @ rel @ se3_exp(np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.002, 3)]))
    return true, est


def _add_mono(kfs: list[Keyframe], true: list[np.ndarray], rng) -> None:
    """Each keyframe's monocular observations of the previous keyframe's landmarks."""
    for i in range(1, len(kfs)):
        prev = kfs[i - 1]
        p_w = prev.points_in_kf @ true[i - 1][:3, :3].T + true[i - 1][:3, 3]
        cfw = invert_pose(true[i])
        q = p_w @ cfw[:3, :3].T + cfw[:3, 3]
        uv = CAM.project(q) + rng.normal(0, 0.3, (len(q), 2))
        ok = np.all((uv > 0) & (uv < [640, 480]), axis=1)
        kfs[i].mono_obs = np.column_stack([prev.landmark_ids[ok].astype(float), uv[ok]])


def test_relocalize_lost_view() -> None:
    rng = np.random.default_rng(8)
    tex = _texture(rng)
    true, _ = _sequence(rng)
    calib = StereoCalibration(CAM.K, CAM.K, make_pose(np.eye(3), [-BASELINE, 0, 0]), (640, 480))
    closer = LoopCloser(calib, LoopConfig(min_gap_keyframes=8, n_features=800), shipped_vocabulary("orb"))
    lid = 0
    for i in range(9):
        kf = _keyframe(i, tex, true[i], true[i], lid, rng)
        lid += len(kf.landmark_ids)
        closer.process_keyframe(kf)
    lost_T = make_pose(so3_exp([0.02, -0.04, 0.01]), [0.35, -0.05, 0.15])
    kf_id, res = closer.relocalize(_render(tex, lost_T))
    assert kf_id is not None and res.cam_from_map is not None, res.reason
    world_from_cam = true[kf_id] @ invert_pose(res.cam_from_map)
    assert np.linalg.norm(world_from_cam[:3, 3] - lost_T[:3, 3]) < 0.03
    assert np.degrees(np.linalg.norm(so3_log(world_from_cam[:3, :3].T @ lost_T[:3, :3]))) < 0.5


class _FakeTracker:
    """Stands in for the front end: keyframe poses and the corrections it receives."""

    def __init__(self) -> None:
        self.poses: dict[int, np.ndarray] = {}
        self.corrections: list[dict[int, np.ndarray]] = []

    @property
    def world_from_kf(self) -> dict[int, np.ndarray]:
        return dict(self.poses)

    def apply_correction(self, world_from_kf: dict[int, np.ndarray]) -> None:
        self.corrections.append(world_from_kf)
        self.poses.update(world_from_kf)


def test_stage_feeds_corrections_back_and_records_events() -> None:
    rng = np.random.default_rng(7)
    tex = _texture(rng)
    true, est = _sequence(rng)
    calib = StereoCalibration(CAM.K, CAM.K, make_pose(np.eye(3), [-BASELINE, 0, 0]), (640, 480))
    kfs, lid = [], 0
    for i, (Tt, Te) in enumerate(zip(true, est, strict=True)):
        kfs.append(_keyframe(i, tex, Tt, Te, lid, rng))
        lid += len(kfs[-1].landmark_ids)
    _add_mono(kfs, true, rng)
    tracker = _FakeTracker()
    stage = LoopClosingStage(
        calib, LoopConfig(min_gap_keyframes=8, n_features=800), vocabulary=shipped_vocabulary("orb"), via_backend=False
    )
    for kf in kfs:
        tracker.poses[kf.id] = kf.world_from_kf.copy()
        out = stage.on_keyframe(kf, MapState(tracker.world_from_kf))
        assert not out.constraints  # the stage corrects loops itself: poses, no constraints
        if out.corrections:
            tracker.apply_correction(out.corrections)
    final = stage.close(MapState(tracker.world_from_kf))  # the BA runs in a worker process; wait for it
    if final:
        tracker.apply_correction(final)
    m = stage.metrics()
    assert m["loop_closure_count"] >= 1
    assert tracker.corrections
    last = max(e["keyframe"] for e in m["loop_events"])
    err_before = np.linalg.norm(est[last][:3, 3] - true[last][:3, 3])
    err_after = np.linalg.norm(tracker.poses[last][:3, 3] - true[last][:3, 3])
    assert err_after < 0.3 * err_before
    for c in stage.closer.closures:  # relative pose of every closure against the truth
        true_rel = invert_pose(true[c.query_kf]) @ true[c.match_kf]
        err = invert_pose(true_rel) @ c.query_from_match
        assert np.degrees(np.linalg.norm(so3_log(err[:3, :3]))) < 0.3
        assert np.linalg.norm(err[:3, 3]) < 0.02
        assert np.all(np.isin(c.observations.landmark_ids, kfs[c.match_kf].landmark_ids))
    ev = m["loop_events"][-1]
    assert ev["type"] == "loop" and ev["correction_m"] > 0 and ev["optimise_ms"] > 0
    assert ev["inliers"] >= 25


def test_stage_via_backend_returns_constraints_and_changes_no_keyframe() -> None:
    """The pipeline's mode: a verified revisit comes back as a constraint and an extended keyframe.

    A relative-pose constraint (checked against the true relative pose) and a copy of the keyframe
    carrying the old landmarks' observations; the keyframe handed in is left as it was.
    """
    rng = np.random.default_rng(7)
    tex = _texture(rng)
    true, est = _sequence(rng)
    calib = StereoCalibration(CAM.K, CAM.K, make_pose(np.eye(3), [-BASELINE, 0, 0]), (640, 480))
    kfs, lid = [], 0
    for i, (Tt, Te) in enumerate(zip(true, est, strict=True)):
        kfs.append(_keyframe(i, tex, Tt, Te, lid, rng))
        lid += len(kfs[-1].landmark_ids)
    _add_mono(kfs, true, rng)
    # inline detection: each loop comes back with its own keyframe (a worker would hand it
    # to a later one; tests/test_loop_background.py)
    cfg = LoopConfig(min_gap_keyframes=8, n_features=800, detection_worker="none")
    stage = LoopClosingStage.from_config(cfg, calib, loop_vocabulary(cfg))
    poses: dict[int, np.ndarray] = {}
    constraints = []
    for kf in kfs:
        poses[kf.id] = kf.world_from_kf.copy()
        mono_before = kf.mono_obs.copy()
        out = stage.on_keyframe(kf, MapState(dict(poses), last_update_ms=3.0, last_constraint_ids=(7,) * 3))
        assert np.array_equal(kf.mono_obs, mono_before) and not out.corrections
        if out.constraints:
            assert out.keyframe is not kf and len(out.keyframe.mono_obs) > len(kf.mono_obs)
        constraints += out.constraints
    stage.close(MapState(dict(poses), last_update_ms=3.0, last_constraint_ids=(7,) * 3))
    assert constraints and stage.metrics()["loop_closure_count"] == len(constraints)
    for c in constraints:
        true_a_from_b = invert_pose(true[c.kf_a]) @ true[c.kf_b]
        err = invert_pose(true_a_from_b) @ c.a_from_b
        assert np.degrees(np.linalg.norm(so3_log(err[:3, :3]))) < 0.3 and np.linalg.norm(err[:3, 3]) < 0.02
    for e in stage.events:  # completed from the next MapState: the back end's time and ids
        assert e["optimise_ms"] == 3.0 and e["constraint_id"] == 7
