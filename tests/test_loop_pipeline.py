"""Loop closing inside the pipeline (front end -> loop stage -> back end).

A revisit is closed, recorded in metrics.json, and the final trajectory agrees with ground truth.
(No-revisit runs: tests/test_loop_closure.py and the ``browse`` run of the sim-loop bench.)
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

if not hasattr(pytest.importorskip("loopmodel.pipeline"), "run_pipeline"):
    pytest.skip("the pipeline has no back end yet (run_pipeline)", allow_module_level=True)

from frontend_scene import default_scene, render, stereo_rig  # noqa: E402

from loopmodel.config import Config  # noqa: E402
from loopmodel.geometry.se3 import invert_pose, make_pose, so3_exp  # noqa: E402
from loopmodel.io.sequence import open_sequence  # noqa: E402
from loopmodel.io.trajectory_io import read_trajectory  # noqa: E402
from loopmodel.pipeline import run_pipeline  # noqa: E402


def _poses(revisit: bool) -> list[np.ndarray]:
    xs = np.linspace(0.0, 1.8, 30)
    if revisit:  # and back to the start view
        xs = np.concatenate([xs, np.linspace(1.8, 0.0, 30)[1:]])
    return [
        make_pose(so3_exp([0.0, 0.03 * np.sin(i / 7), 0.0]), [x, 0.01 * np.sin(i / 3), 0.0]) for i, x in enumerate(xs)
    ]


def _write_kitti(folder: Path, poses: list[np.ndarray], rng: np.random.Generator) -> None:
    planes = default_scene(rng)
    cal = stereo_rig()
    (folder / "image_0").mkdir(parents=True)
    (folder / "image_1").mkdir()
    for i, world_from_cam in enumerate(poses):
        cam_from_world = invert_pose(world_from_cam)
        for sub, T in (("image_0", cam_from_world), ("image_1", cal.right_from_left @ cam_from_world)):
            cv2.imwrite(str(folder / sub / f"{i:06d}.png"), render(planes, cal.K_left, T, cal.image_size))
    P0 = np.hstack([cal.K_left, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -cal.K_left[0, 0] * cal.baseline_m
    rows = [" ".join(repr(float(x)) for x in P.ravel()) for P in (P0, P1)]
    (folder / "calib.txt").write_text(f"P0: {rows[0]}\nP1: {rows[1]}\n")
    (folder / "poses.txt").write_text("".join(" ".join(repr(float(x)) for x in T[:3, :].ravel()) + "\n" for T in poses))


def _config() -> Config:
    cfg = Config()
    cfg.frontend.max_parallax_ratio = 0.04  # a keyframe every few frames
    cfg.loop.min_gap_keyframes = 3
    cfg.loop.consistency = 1
    cfg.loop.vocabulary_train_after = 4
    cfg.loop.n_features = 800
    return cfg


@pytest.mark.slow
def test_pipeline_closes_the_loop_and_records_it(tmp_path: Path) -> None:
    poses = _poses(revisit=True)
    _write_kitti(tmp_path / "seq", poses, np.random.default_rng(4))
    out = run_pipeline(open_sequence(tmp_path / "seq"), _config(), tmp_path, "loop")
    metrics = json.loads((out.folder / "metrics.json").read_text())
    assert metrics["loop_closure_count"] >= 1
    events = [e for e in metrics["loop_events"] if e["type"] == "loop"]
    assert events and all(e["frame"] > e["match_frame"] >= 0 for e in events)
    assert all(e["inliers"] >= 25 and "correction_m" in e and "optimise_ms" in e for e in events)
    # the loop's keyframes sit where ground truth has them (relative pose, final trajectory)
    final = read_trajectory(out.folder / "trajectory_final.tum")
    by_time = dict(zip(final.timestamps_ns.tolist(), final.world_from_cam, strict=True))
    stamps = open_sequence(tmp_path / "seq").ground_truth.timestamps_ns
    for e in events:
        a, b = by_time[int(stamps[e["frame"]])], by_time[int(stamps[e["match_frame"]])]
        est = invert_pose(b) @ a
        gt = invert_pose(poses[e["match_frame"]]) @ poses[e["frame"]]
        assert np.linalg.norm(est[:3, 3] - gt[:3, 3]) < 0.03


@pytest.mark.slow
def test_front_end_tracks_the_old_feature_set_after_a_revisit(tmp_path: Path) -> None:
    """Seed 004 section 5: after the closure the tracker resumes the old keyframe's features.

    Keyframes after the closure keyframe observe landmarks of the loop's old keyframe (their
    ids reach the back end's factors), at the pixels where ground truth projects those landmarks.
    """
    from loopmodel.pipeline import _Run

    poses = _poses(revisit=True)
    _write_kitti(tmp_path / "seq", poses, np.random.default_rng(4))
    seq = open_sequence(tmp_path / "seq")
    cfg = _config()
    cfg.loop.detection_worker = "none"  # loops found at their own keyframe, whatever the load
    cfg.backend.worker = "inline"  # the back end's factors are read below
    run = _Run(seq.calibration, cfg, [])
    kept: dict[int, object] = {}
    for frame in seq.frames():
        run.step(frame)
        for k in run.keyframes:  # each keyframe once the loop stage has it (local_ba_beside: with the next frame)
            kept.setdefault(k, run.loop.keyframes[k])  # type: ignore[attr-defined]
    run.finish(False)  # the last keyframe (local_ba_beside) reaches the loop stage and back end here
    for k in run.keyframes:
        kept.setdefault(k, run.loop.keyframes[k])  # type: ignore[attr-defined]
    loops = [e for e in run.loop.metrics()["loop_events"] if e.get("old_features_resumed", 0) > 0]
    assert loops, "no closure handed old features to the front end"
    assert any(e.get("old_features_tracked_on") for e in loops), "no later keyframe observed them"
    cal = seq.calibration
    n_later = in_backend = 0
    errors: list[float] = []
    for e in loops:
        old = kept[e["match_keyframe"]]
        old_ids = set(np.asarray(old.landmark_ids).tolist())  # type: ignore[attr-defined]
        by_id = dict(zip(old.landmark_ids.tolist(), old.points_in_kf, strict=True))  # type: ignore[attr-defined]
        world_from_old = poses[old.frame_index]  # type: ignore[attr-defined]
        for k in sorted(kept):
            kf = kept[k]
            if k <= e["keyframe"] or kf.ba_info.get("resumed_from_keyframe") != e["match_keyframe"]:  # type: ignore[attr-defined]
                continue
            rows = [r for r in np.asarray(kf.mono_obs) if int(r[0]) in old_ids]  # type: ignore[attr-defined]
            for r in rows:
                in_backend += run.backend.observation_factor_index((k, int(r[0]))) is not None  # type: ignore[attr-defined]
                # ground truth: the old landmark's stereo point, placed by the true poses
                p_world = world_from_old[:3, :3] @ by_id[int(r[0])] + world_from_old[:3, 3]
                cam_from_world = invert_pose(poses[kf.frame_index])  # type: ignore[attr-defined]
                p = cam_from_world[:3, :3] @ p_world + cam_from_world[:3, 3]
                uv = (cal.K_left @ (p / p[2]))[:2]
                errors.append(float(np.linalg.norm(uv - r[1:])))
            n_later += len(rows)
    # measured (seed 4): 788 later observations, 779 of them factors; error median 0.04 px, p90 0.14 px
    assert n_later >= 400
    assert in_backend >= 0.95 * n_later
    assert float(np.median(errors)) < 0.1 and float(np.percentile(errors, 90)) < 0.3
