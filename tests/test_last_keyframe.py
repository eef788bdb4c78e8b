"""The run's last frame becomes a keyframe (issue 36, tail14: ``frontend.last_frame_keyframe``).

Without it the frames after the keyframe policy's last keyframe have no keyframe after them: they are
not bridged and the last pose is not in the final bundle adjustment.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from frontend_scene import default_scene, stereo_frames, stereo_rig, trajectory, write_kitti_folder

from loopmodel.config import Config, FrontendConfig
from loopmodel.frontend import FrontEnd
from loopmodel.geometry.se3 import invert_pose


def test_the_front_end_makes_the_last_frame_a_keyframe() -> None:
    """``prepare(frame, last=True)``: that frame, tracked, is a keyframe; the frames before it are unchanged."""
    cal = stereo_rig()
    poses = trajectory(9)
    frames = stereo_frames(default_scene(np.random.default_rng(5)), cal, invert_pose(poses[0]) @ poses)
    runs = {}
    for last in (False, True):
        fe = FrontEnd(cal, FrontendConfig(max_disparity_px=64, max_features=400, local_ba_beside=False))
        res = []
        for i, f in enumerate(frames):
            fe.prepare(f, last=last and i == len(frames) - 1)
            res.append(fe.process(f))
        runs[last] = res
    assert all(r.ok for r in runs[True])
    assert not runs[False][-1].is_keyframe  # the policy alone makes no keyframe there
    assert runs[True][-1].is_keyframe and runs[True][-1].keyframe is not None
    assert runs[True][-1].keyframe.connected
    for a, b in zip(runs[False][:-1], runs[True][:-1], strict=True):  # the frames before: the same
        assert a.is_keyframe == b.is_keyframe
        assert np.array_equal(a.world_from_cam, b.world_from_cam)
    # the keyframe's pose (its local BA's) near its frame's tracked pose (measured 0.6 mm apart, 0.06 m steps)
    assert np.linalg.norm(runs[True][-1].world_from_cam[:3, 3] - runs[False][-1].world_from_cam[:3, 3]) < 3e-3


def test_the_last_frame_is_a_keyframe_and_nearer_the_truth(tmp_path: Path) -> None:
    """A full run with the calibrating finish: the last frame a keyframe of the result, its final pose nearer the truth.

    The rendered rig of tests/test_retrack.py (right cx 0.6 px off the recorded calibration); with the
    option off, the frames after the last keyframe are re-solved alone (``calibration_retrack_tail``).
    """
    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import process

    truth = write_kitti_folder(tmp_path / "seq", 20, np.random.default_rng(7), cx_right_error_px=0.6)
    pos_mm, rot_deg, out = {}, {}, {}
    for on in (False, True):
        cfg = Config()
        cfg.frontend.max_disparity_px = 64
        cfg.frontend.max_features = 400
        cfg.frontend.min_tracked_fraction = 0.95
        cfg.frontend.last_frame_keyframe = on
        cfg.calibration.refine = "final"  # type: ignore[assignment]
        cfg.output.write_map = False
        cfg.mapping.write_mesh = False
        res = out[on] = process(open_sequence(tmp_path / "seq"), cfg)
        assert len(res.final.timestamps_ns) == len(truth)
        last = res.final.world_from_cam[-1]
        pos_mm[on] = 1e3 * float(np.linalg.norm(last[:3, 3] - truth[-1][:3, 3]))
        c = (np.trace(last[:3, :3].T @ truth[-1][:3, :3]) - 1) / 2
        rot_deg[on] = float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
    kf_off = out[False].keyframes.timestamps_ns.tolist()
    kf_on = out[True].keyframes.timestamps_ns.tolist()
    stamps = out[True].final.timestamps_ns.tolist()
    assert stamps[-1] not in kf_off and out[False].metrics["calibration_retrack_tail"] >= 2
    assert kf_on == [*kf_off, stamps[-1]]  # one keyframe more: the last frame
    assert out[True].metrics["calibration_retrack_tail"] == 0
    # measured (seed 7): last frame 0.284 -> 0.149 mm, 0.0068 -> 0.0042 deg (seeds 3, 11: 0.68 -> 0.41,
    # 0.75 -> 0.34 mm)
    assert pos_mm[True] < 0.75 * pos_mm[False]
    assert rot_deg[True] < 0.9 * rot_deg[False]
