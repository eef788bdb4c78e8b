"""Front end on rendered piecewise-planar scenes with ground truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from frontend_scene import default_scene, depth_at, random_texture, stereo_frames, stereo_rig, trajectory

from loopmodel.config import FrontendConfig
from loopmodel.frontend import FrontEnd
from loopmodel.frontend.stereo import detect_corners, match_stereo, triangulate_rectified
from loopmodel.geometry.se3 import invert_pose, make_pose, so3_exp, so3_log
from loopmodel.imaging.klt import track_klt
from loopmodel.types import StereoCalibration, StereoFrame

CFG = FrontendConfig(
    max_disparity_px=64,
    max_features=400,
    grid_cols=6,
    grid_rows=3,
    min_tracked=60,
    min_stereo_points=30,
)


def _pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    d = invert_pose(T_true) @ T_est
    return float(np.linalg.norm(d[:3, 3])), float(np.degrees(np.linalg.norm(so3_log(d[:3, :3]))))


def test_triangulation_matches_ground_truth_depth(rng: np.random.Generator) -> None:
    planes = default_scene(rng)
    cal = stereo_rig()
    (frame,) = stereo_frames(planes, cal, np.eye(4)[None])
    corners = detect_corners(frame.left, 400, (6, 3), 0.005, 8, 12)
    m = match_stereo(frame.left, frame.right, corners, CFG)
    assert len(m.disparity) > 150
    pts = triangulate_rectified(m.uv_left, m.disparity, cal.K_left, cal.baseline_m)
    z_true = depth_at(planes, cal.K_left, np.eye(4), m.uv_left)
    rel = np.abs(pts[:, 2] - z_true) / z_true
    assert np.nanmedian(rel) < 0.01
    assert np.nanpercentile(rel, 95) < 0.03
    # both depth layers are present
    assert np.any(z_true < 5.5) and np.any(z_true > 8.0)


def test_klt_forward_backward_rejects_wrong_track(rng: np.random.Generator) -> None:
    prev = random_texture(rng, 240, 320)
    shift = np.array([2.6, -1.4])
    cur = cv2.warpAffine(
        prev,
        np.array([[1, 0, shift[0]], [0, 1, shift[1]]]),
        (320, 240),
        flags=cv2.INTER_CUBIC,
        borderMode=cv2.BORDER_REFLECT,
    )
    bad = np.array([160.0, 120.0])
    # the content around the bad point changes completely (e.g. an occluder moved in)
    cur[100:141, 140:181] = random_texture(rng, 41, 41)
    good = np.array([[u, v] for u in (50.0, 90.0, 250.0, 280.0) for v in (40.0, 200.0)])
    pts = np.vstack([good, bad])
    guess = pts + shift  # a perfect motion prediction for every point
    uv, ok, fb = track_klt(prev, cur, pts, guess, 21, 2, 0.5, 30, (320, 240))
    assert ok[:-1].all()
    np.testing.assert_allclose(uv[:-1], good + shift, atol=0.1)
    assert not ok[-1], f"wrong track accepted (fb error {fb[-1]:.3f} px)"


def _check_ok_poses(results, poses: np.ndarray, tol_m: float, tol_deg: float) -> None:
    for r in results:
        if r.status == "OK":
            dt, dr = _pose_error(r.world_from_cam, poses[r.frame_index])
            assert dt < tol_m and dr < tol_deg, (r.frame_index, dt, dr)


def test_short_sequence_ok_poses_match_ground_truth(rng: np.random.Generator) -> None:
    planes = default_scene(rng)
    cal = stereo_rig()
    poses = trajectory(16)
    poses = invert_pose(poses[0]) @ poses  # world = first camera
    fe = FrontEnd(cal, CFG)
    results = [fe.process(f) for f in stereo_frames(planes, cal, poses)]
    assert all(r.status == "OK" for r in results)
    assert results[0].is_keyframe and results[0].keyframe is not None
    _check_ok_poses(results, poses, 0.02, 0.2)
    # the world_from_kf / kf_from_cam contract
    for r in results:
        np.testing.assert_allclose(
            r.world_from_cam, fe.world_from_kf[r.keyframe_id] @ r.kf_from_cam, atol=1e-9
        )
    # keyframes after the first carry the previous set's observations in their left image
    later = [r.keyframe for r in results[1:] if r.keyframe is not None]
    for kf in later:
        assert kf.mono_obs.shape[1] == 3 and len(kf.mono_obs) >= CFG.min_inliers


def test_blackout_burst_is_lost_then_tracking_resumes(rng: np.random.Generator) -> None:
    planes = default_scene(rng)
    cal = stereo_rig()
    poses = trajectory(22, step_m=0.04)
    poses = invert_pose(poses[0]) @ poses
    frames = stereo_frames(planes, cal, poses)
    burst = range(8, 11)
    for i in burst:
        frames[i] = StereoFrame(
            frames[i].timestamp_ns, np.zeros_like(frames[i].left), np.zeros_like(frames[i].right), i
        )
    fe = FrontEnd(cal, CFG)
    results = [fe.process(f) for f in frames]
    assert [results[i].status for i in burst] == ["LOST"] * len(burst)
    assert all(r.status == "OK" for r in results[:8])
    assert all(r.status == "OK" for r in results[12:]), [r.status for r in results]
    _check_ok_poses(results, poses, 0.03, 0.3)


def test_unrectified_input_gets_rectified(rng: np.random.Generator) -> None:
    planes = default_scene(rng)
    rect = stereo_rig()
    # real right camera: rotated by a known rotation and with another focal length
    R_rot = so3_exp(np.radians([0.8, -1.5, 0.6]))
    K_right = rect.K_right.copy()
    K_right[0, 0] = K_right[1, 1] = 470.0
    right_from_left = make_pose(R_rot, R_rot @ np.array([-0.3, 0.0, 0.0]))
    cal = StereoCalibration(rect.K_left, K_right, right_from_left, rect.image_size, rectified=False)
    poses = trajectory(6)
    poses = invert_pose(poses[0]) @ poses
    frames = stereo_frames(planes, cal, poses)
    fe = FrontEnd(cal, CFG)
    assert not fe.rectifier.is_identity
    assert fe.calibration.rectified and abs(fe.calibration.baseline_m - 0.3) < 1e-6
    results = [fe.process(f) for f in frames]
    kf = results[0].keyframe
    assert kf is not None and len(kf.points_in_kf) > 100
    # triangulated points (original left camera frame) agree with ground-truth depth
    uv = kf.points_in_kf[:, :2] / kf.points_in_kf[:, 2:] @ cal.K_left[:2, :2].T + cal.K_left[:2, 2]
    z_true = depth_at(planes, cal.K_left, np.eye(4), uv)
    rel = np.abs(kf.points_in_kf[:, 2] - z_true) / z_true
    assert np.nanmedian(rel) < 0.015
    assert all(r.status == "OK" for r in results)
    _check_ok_poses(results, poses, 0.02, 0.2)
    # unrectified matching along rows would fail: the raw right image is rotated
    raw = match_stereo(
        frames[0].left,
        frames[0].right,
        detect_corners(frames[0].left, 400, (6, 3), 0.005, 8, 12),
        CFG,
    )
    assert len(raw.disparity) < 0.5 * len(kf.points_in_kf)


def test_bad_patch_size_is_a_config_error() -> None:
    from loopmodel.errors import InputError

    with pytest.raises(InputError, match="patch_px"):
        FrontEnd(stereo_rig(), FrontendConfig(patch_px=10))


def test_apply_correction_moves_later_poses(rng: np.random.Generator) -> None:
    planes = default_scene(rng)
    cal = stereo_rig()
    poses = trajectory(12)
    frames = stereo_frames(planes, cal, invert_pose(poses[0]) @ poses)
    fe1, fe2 = FrontEnd(cal, CFG), FrontEnd(cal, CFG)
    for f in frames[:6]:
        fe1.process(f)
        last = fe2.process(f)
    kid = last.keyframe_id
    delta = make_pose(so3_exp([0.01, -0.02, 0.03]), [0.1, -0.05, 0.2])
    fe2.apply_correction({kid: delta @ fe2.world_from_kf[kid], 999: np.eye(4)})
    for f in frames[6:]:
        r1, r2 = fe1.process(f), fe2.process(f)
        assert r1.status == r2.status == "OK"
        np.testing.assert_allclose(r2.world_from_cam, delta @ r1.world_from_cam, atol=1e-9)
    assert 999 not in fe2.world_from_kf


def test_long_track_on_one_keyframe_stays_rigid(rng: np.random.Generator) -> None:
    """Many frames against one keyframe.

    The motion-model products must stay in SE(3) (rounding in the rotation blocks once grew
    geometrically here).
    """
    planes = default_scene(rng)
    cal = stereo_rig()
    poses = trajectory(40, step_m=0.004)
    poses = invert_pose(poses[0]) @ poses
    fe = FrontEnd(cal, CFG)
    results = [fe.process(f) for f in stereo_frames(planes, cal, poses)]
    assert sum(r.is_keyframe for r in results) <= 3
    for r in results:
        R = r.world_from_cam[:3, :3]
        assert np.abs(R.T @ R - np.eye(3)).max() < 1e-9
    _check_ok_poses(results, poses, 0.01, 0.1)


def test_blurred_frame_and_pose_jump_are_lost_not_wrong(rng: np.random.Generator) -> None:
    planes = default_scene(rng)
    cal = stereo_rig()
    poses = trajectory(16, step_m=0.04)
    poses = invert_pose(poses[0]) @ poses
    frames = stereo_frames(planes, cal, poses)
    # frame 6: heavy defocus blur; frame 10: the view of a camera 1 m to the side and turned
    frames[6] = StereoFrame(frames[6].timestamp_ns, cv2.GaussianBlur(frames[6].left, (0, 0), 12),
                            cv2.GaussianBlur(frames[6].right, (0, 0), 12), 6)
    jumped = poses[10] @ make_pose(so3_exp([0.0, 0.25, 0.0]), [1.0, 0.0, 0.0])
    (far,) = stereo_frames(planes, cal, jumped[None])
    frames[10] = StereoFrame(frames[10].timestamp_ns, far.left, far.right, 10)
    fe = FrontEnd(cal, CFG)
    results = [fe.process(f) for f in frames]
    assert results[6].status == "LOST" and results[10].status == "LOST"
    assert all(r.status == "OK" for i, r in enumerate(results) if i not in (6, 10)), [
        (r.frame_index, r.status, r.reason) for r in results
    ]
    _check_ok_poses(results, poses, 0.02, 0.2)


def test_pose_jump_beyond_motion_model_is_lost(rng: np.random.Generator) -> None:
    planes = default_scene(rng)
    cal = stereo_rig()
    poses = trajectory(14, step_m=0.04)
    poses = invert_pose(poses[0]) @ poses
    poses[8] = poses[8] @ make_pose(np.eye(3), [0.25, 0.0, 0.0])  # one frame 25 cm off
    cfg = CFG.model_copy(update={"max_jump_m": 0.1})
    fe = FrontEnd(cal, cfg)
    results = [fe.process(f) for f in stereo_frames(planes, cal, poses)]
    assert results[8].status == "LOST" and "jump" in results[8].reason
    assert all(r.status == "OK" for i, r in enumerate(results) if i != 8)
    _check_ok_poses(results, poses, 0.02, 0.2)


def test_spread_subset_takes_the_best_of_every_cell(rng: np.random.Generator) -> None:
    from loopmodel.frontend.stereo import spread_subset

    uv = np.column_stack([rng.uniform(0, 400, 500), rng.uniform(0, 200, 500)])
    uv[:400, 0] *= 0.25  # crowd most points into the left quarter
    score = rng.uniform(0, 1, 500)
    cand = np.ones(500, bool)
    cand[::7] = False
    pick = spread_subset(uv, score, cand, 40, (4, 2), (400, 200))
    assert pick.sum() == 40 and not np.any(pick & ~cand)
    cells = np.clip((uv[:, 0] // 100).astype(int), 0, 3) + 4 * np.clip((uv[:, 1] // 100).astype(int), 0, 1)
    for c in range(8):
        members = np.flatnonzero(cand & (cells == c))
        if members.size:  # every occupied cell gives at least its best point
            assert pick[members[np.argmax(score[members])]]


def test_parallax_angle_is_small_for_motion_along_the_rays(rng: np.random.Generator) -> None:
    from loopmodel.frontend.tracker import median_parallax_rad

    pts = np.column_stack([rng.uniform(-3, 3, 200), rng.uniform(-1, 1, 200), rng.uniform(8, 20, 200)])
    forward = median_parallax_rad(pts, np.array([0.0, 0.0, 2.0]))
    sideways = median_parallax_rad(pts, np.array([2.0, 0.0, 0.0]))
    # independent: the angle for sideways motion of points straight ahead is atan(2 / depth)
    ahead = np.column_stack([np.zeros(5), np.zeros(5), np.array([8.0, 10, 12, 14, 16])])
    np.testing.assert_allclose(median_parallax_rad(ahead, np.array([2.0, 0.0, 0.0])), np.arctan(2 / 12), rtol=1e-12)
    assert median_parallax_rad(ahead, np.array([0.0, 0.0, 2.0])) == 0.0
    assert forward < 0.3 * sideways


def test_local_map_points_stay_in_the_pose_and_are_observed_later(rng: np.random.Generator) -> None:
    """Local-map tracking (issue 36): earlier keyframes' points stay in the pose and reach later keyframes.

    Checked against the rendering's ground truth: the poses, and every observation a keyframe
    carries of a landmark two or more keyframes old lies where that landmark's point (its own
    keyframe's stereo/BA estimate) projects with the true poses.
    """
    planes = default_scene(rng)
    cal = stereo_rig()
    poses = trajectory(24)
    poses = invert_pose(poses[0]) @ poses
    fe = FrontEnd(cal, CFG.model_copy(update={"local_map_keyframes": 3, "max_parallax_ratio": 0.05}))
    results = [fe.process(f) for f in stereo_frames(planes, cal, poses)]
    assert all(r.status == "OK" for r in results)
    _check_ok_poses(results, poses, 0.02, 0.2)
    kfs = [r.keyframe for r in results if r.keyframe is not None]
    assert len(kfs) >= 4
    assert max(kf.ba_info.get("local_map_inliers", 0.0) for kf in kfs) >= 20
    true_of = {kf.id: poses[kf.frame_index] for kf in kfs}
    first_id = {int(kf.landmark_ids[0]): kf for kf in kfs}
    starts = np.array(sorted(first_id))
    errs = []
    for kf, prev in zip(kfs[2:], kfs[1:], strict=False):
        old = kf.mono_obs[kf.mono_obs[:, 0] < prev.landmark_ids[0]]
        for lid, u, v in old:
            owner = first_id[int(starts[np.searchsorted(starts, lid, side="right") - 1])]
            p = owner.points_in_kf[int(lid) - int(owner.landmark_ids[0])]
            cur_from_owner = invert_pose(true_of[kf.id]) @ true_of[owner.id]
            q = cur_from_owner[:3, :3] @ p + cur_from_owner[:3, 3]
            uv = cal.K_left[:2, :2] @ (q[:2] / q[2]) + cal.K_left[:2, 2]
            errs.append(np.hypot(uv[0] - u, uv[1] - v))
    assert len(errs) >= 20  # older keyframes' landmarks observed again
    assert np.median(errs) < 1.0


def test_wider_keyframe_ba_takes_the_local_map_and_keeps_the_poses(rng: np.random.Generator) -> None:
    """``local_ba_keyframes`` (issue 36): the keyframe BA takes earlier sets' points; poses stay on the truth."""
    planes = default_scene(rng)
    cal = stereo_rig()
    poses = trajectory(24)
    poses = invert_pose(poses[0]) @ poses
    cfg = CFG.model_copy(update={"local_map_keyframes": 3, "local_ba_keyframes": 2, "max_parallax_ratio": 0.05})
    fe = FrontEnd(cal, cfg)
    results = [fe.process(f) for f in stereo_frames(planes, cal, poses)]
    assert all(r.status == "OK" for r in results)
    _check_ok_poses(results, poses, 0.02, 0.2)
    kfs = [r.keyframe for r in results if r.keyframe is not None]
    assert max(kf.ba_info.get("ba_window_points", 0.0) for kf in kfs) >= 20
