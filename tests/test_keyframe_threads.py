"""Keyframe work beside the tracking thread (issue 33): the same results as inline, on two threads."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
from frontend_scene import default_scene, render, stereo_rig, trajectory, write_kitti_folder

import loopmodel.frontend.stereo as stereo_mod
import loopmodel.frontend.tracker as tracker_mod
from loopmodel.config import FrontendConfig
from loopmodel.frontend import FrontEnd
from loopmodel.frontend.stereo import detect_corners, match_stereo, match_stereo_split
from loopmodel.geometry.se3 import invert_pose
from loopmodel.types import StereoFrame

# a keyframe every other frame or so (max_parallax_ratio): 8 keyframes in 16 frames
CFG = FrontendConfig(
    max_disparity_px=64, max_features=400, grid_cols=6, grid_rows=3, min_tracked=60, max_parallax_ratio=0.01
)


def _frames(rng: np.random.Generator, n: int) -> tuple[list[StereoFrame], np.ndarray, object]:
    planes = default_scene(rng)
    cal = stereo_rig()
    poses = trajectory(n)
    poses = invert_pose(poses[0]) @ poses
    frames = []
    for i, world_from_cam in enumerate(poses):
        cam_from_world = invert_pose(world_from_cam)
        left = render(planes, cal.K_left, cam_from_world, cal.image_size)
        right = render(planes, cal.K_right, cal.right_from_left @ cam_from_world, cal.image_size)
        frames.append(StereoFrame(i * 100_000_000, left, right, i))
    return frames, poses, cal


def test_split_matching_finds_the_same_matches_at_their_corners(rng: np.random.Generator) -> None:
    frames, _, _ = _frames(rng, 1)
    left, right = frames[0].left, frames[0].right
    corners = detect_corners(left, 400, (6, 3), 0.005, 10.0, 12)
    whole = match_stereo(left, right, corners, CFG)
    split = match_stereo_split(left, right, corners, CFG, threads=3)
    assert whole.index.size > 100  # measured 300+ matches of ~400 corners
    for name in ("uv_left", "u_right", "v_right", "disparity", "score", "index", "sigma_px"):
        np.testing.assert_array_equal(getattr(split, name), getattr(whole, name), err_msg=name)
    # each match's index points at its own corner (the parts' indices offset into the whole list)
    np.testing.assert_array_equal(split.uv_left, np.rint(corners[split.index]))


def test_keyframe_stereo_runs_beside_the_tracker_with_the_same_poses(
    rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    frames, poses, cal = _frames(rng, 16)
    threads: list[tuple[int, int]] = []  # (thread of the stereo set, threads its matching used)
    match_threads: set[int] = set()
    inner_set, inner_match = stereo_mod.keyframe_stereo_set, stereo_mod.match_stereo

    def recording_set(*args, **kwargs):  # type: ignore[no-untyped-def]
        match_threads.clear()
        out = inner_set(*args, **kwargs)
        threads.append((threading.get_ident(), len(match_threads)))
        return out

    def recording_match(*args, **kwargs):  # type: ignore[no-untyped-def]
        match_threads.add(threading.get_ident())
        return inner_match(*args, **kwargs)

    monkeypatch.setattr(tracker_mod, "keyframe_stereo_set", recording_set)
    monkeypatch.setattr(stereo_mod, "match_stereo", recording_match)
    runs = {}
    for mode in ("inline", "thread"):
        threads.clear()
        fe = FrontEnd(cal, CFG.model_copy(update={"keyframe_stereo": mode}))
        runs[mode] = [fe.process(f) for f in frames]
        kf_threads = list(threads)
        if mode == "thread":
            main = threading.get_ident()
            assert kf_threads[0] == (main, 2)  # the first keyframe: its matching split over two threads
            assert len(kf_threads) >= 3 and all(t != main and n == 1 for t, n in kf_threads[1:])
        else:
            assert all(t == threading.get_ident() for t, _ in kf_threads)
    inline, threaded = runs["inline"], runs["thread"]
    assert [r.keyframe_id for r in threaded] == [r.keyframe_id for r in inline]
    for a, b in zip(inline, threaded, strict=True):
        np.testing.assert_array_equal(a.world_from_cam, b.world_from_cam)
        if a.keyframe is not None:
            assert b.keyframe is not None
            np.testing.assert_array_equal(a.keyframe.mono_obs, b.keyframe.mono_obs)
            assert a.keyframe.ba_info.keys() == b.keyframe.ba_info.keys()
    for r in threaded:  # and right: against the rendered ground truth (measured 1.8 mm at most)
        assert r.status == "OK"
        assert np.linalg.norm(r.world_from_cam[:3, 3] - poses[r.frame_index][:3, 3]) < 0.005


def test_an_error_in_the_stereo_thread_reaches_the_tracker(
    rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    frames, _, cal = _frames(rng, 16)
    calls = []

    def failing(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(threading.get_ident())
        if len(calls) > 1:
            raise ValueError("stereo failed")
        return stereo_mod.keyframe_stereo_set(*args, **kwargs)

    monkeypatch.setattr(tracker_mod, "keyframe_stereo_set", failing)
    fe = FrontEnd(cal, CFG)
    with pytest.raises(ValueError, match="stereo failed"):
        for f in frames:
            fe.process(f)
    assert calls[-1] != threading.get_ident()  # raised on the stereo thread, re-raised here


def test_local_ba_beside_the_next_frame_gives_the_inline_poses(
    rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    """frontend.local_ba_beside: each keyframe's BA runs on another thread while the tracker returns.

    It is taken in the next frame before its pose: every later frame's pose is the inline run's; a
    keyframe's own frame carries its tracked pose, and the BA's correction reaches take_corrections.
    """
    frames, poses, cal = _frames(rng, 16)
    ba_threads: list[int] = []
    inner = tracker_mod.hybrid_keyframe_ba

    def recording(*args, **kwargs):  # type: ignore[no-untyped-def]
        ba_threads.append(threading.get_ident())
        return inner(*args, **kwargs)

    monkeypatch.setattr(tracker_mod, "hybrid_keyframe_ba", recording)
    cfg = CFG.model_copy(update={"local_ba_beside": True})
    fe_inline, fe_beside = FrontEnd(cal, CFG), FrontEnd(cal, cfg)
    inline = [fe_inline.process(f) for f in frames]
    n_inline = len(ba_threads)
    assert n_inline >= 4 and set(ba_threads) == {threading.get_ident()}
    beside, corrected = [], {}
    for f in frames:
        beside.append(fe_beside.process(f))
        corrected.update(fe_beside.take_corrections())
    assert len(ba_threads) - n_inline >= n_inline - 1  # the last keyframe's BA may still be pending
    assert threading.get_ident() not in ba_threads[n_inline:]
    assert [r.keyframe_id for r in beside] == [r.keyframe_id for r in inline]
    # every connected keyframe but the last had its BA taken and its pose moved (a few mm here)
    kf_ids = [r.keyframe_id for r in inline if r.is_keyframe][1:-1]
    assert set(kf_ids) <= set(corrected)
    # the same up to rounding and the KLT's tolerance: the local map's KLT starts at the points before
    # their BA (measured 3e-8 at most)
    for k in kf_ids:
        np.testing.assert_allclose(fe_beside.world_from_kf[k], fe_inline.world_from_kf[k], atol=1e-6)
    for a, b in zip(inline, beside, strict=True):
        if a.is_keyframe:  # the keyframe's own frame: the tracked pose (measured within 1 mm of the BA's)
            assert np.linalg.norm(a.world_from_cam[:3, 3] - b.world_from_cam[:3, 3]) < 0.003
        else:
            np.testing.assert_allclose(b.world_from_cam, a.world_from_cam, atol=1e-6)
        assert np.linalg.norm(b.world_from_cam[:3, 3] - poses[b.frame_index][:3, 3]) < 0.005


def test_the_pipeline_takes_the_beside_ba_corrections(tmp_path: Path) -> None:
    """With ``local_ba_beside`` the pipeline applies each keyframe's BA correction in the next frame.

    Through the one correction path: the anchored keyframe poses then hold the front end's; the run
    stays on the rendered ground truth.
    """
    import loopmodel.pipeline as pl
    from loopmodel.config import Config
    from loopmodel.eval.of_run import evaluate
    from loopmodel.io.sequence import open_sequence

    write_kitti_folder(tmp_path / "seq", 12, np.random.default_rng(7))
    cfg = Config()
    cfg.frontend.max_disparity_px = 64
    cfg.frontend.max_features = 400
    cfg.frontend.min_tracked_fraction = 0.95  # several keyframes in a short sequence
    cfg.frontend.local_ba_beside = True
    cfg.backend.worker = "inline"  # type: ignore[assignment]
    cfg.loop.enabled = False
    cfg.mapping.write_mesh = False
    cfg.output.write_map = False
    seq = open_sequence(tmp_path / "seq")
    run = pl._Run(seq.calibration, cfg, [])
    events: list[tuple[str, dict]] = []  # type: ignore[type-arg]
    inner_correct, inner_take = run._correct, run.frontend.take_corrections

    def correct(world_from_kf):  # type: ignore[no-untyped-def]
        events.append(("correct", dict(world_from_kf)))
        inner_correct(world_from_kf)

    def take():  # type: ignore[no-untyped-def]
        out = inner_take()
        events.append(("take", dict(out)))
        return out

    run._correct = correct  # type: ignore[method-assign]
    run.frontend.take_corrections = take  # type: ignore[method-assign]
    for frame in seq.frames():
        run.step(frame)
    taken: set[int] = set()
    for (kind, poses), (next_kind, applied) in zip(events, events[1:], strict=False):
        if kind == "take" and poses:  # the next correction is exactly the BA's: same keyframes, same poses
            assert next_kind == "correct" and applied.keys() == poses.keys()
            for k in poses:
                np.testing.assert_array_equal(applied[k], poses[k])
            taken |= set(poses)
    kf_ids = sorted(run.keyframes)
    assert len(kf_ids) >= 3
    assert set(kf_ids[1:-1]) <= taken  # each connected keyframe's BA but the last one's
    result = run.finish(False)
    assert evaluate(result, seq).metrics["ate_rmse_m"] < 0.005
