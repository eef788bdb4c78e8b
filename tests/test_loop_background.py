"""Loop detection off the tracking path (issue 26).

With the verifier blocked, the pipeline still processes every frame and keyframe; the detections are
applied afterwards, in order.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest

from loopmodel.config import Config
from loopmodel.io.sequence import open_sequence
from loopmodel.io.vocabulary_file import loop_vocabulary
from loopmodel.loop.closer import LoopCloser
from loopmodel.pipeline import run_pipeline

TINY = Path(__file__).resolve().parents[1] / "datasets" / "tiny_kitti"


def test_keyframes_do_not_wait_for_a_blocked_verifier(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    release = threading.Event()
    started: list[int] = []
    finished: list[int] = []
    original = LoopCloser.process_keyframe

    def slow(self: LoopCloser, kf: Any, *args: Any, **kwargs: Any) -> Any:
        started.append(int(kf.id))
        assert threading.current_thread() is not threading.main_thread()
        assert release.wait(timeout=60.0)  # blocked until the last frame was processed
        out = original(self, kf, *args, **kwargs)
        finished.append(int(kf.id))
        return out

    monkeypatch.setattr(LoopCloser, "process_keyframe", slow)
    seq = open_sequence(TINY)
    cfg = Config()
    cfg.frontend.max_parallax_ratio = 0.005  # a keyframe every frame or two on this short clip
    cfg.loop.detection_worker = "thread"  # (the default) the patched verifier runs in this process
    cfg.loop.max_queued_keyframes = 100
    frames_while_blocked: list[int] = []
    keyframes_while_blocked: list[int] = []

    def progress(done: int, total: int, fps: float, keyframes: int) -> None:
        if not release.is_set():
            frames_while_blocked.append(done)
            keyframes_while_blocked.append(keyframes)
        if done == total:
            release.set()

    out = run_pipeline(seq, cfg, tmp_path, "bg", progress=progress)
    n_kf = len(out.keyframe_ids)
    assert n_kf >= 3
    # every frame and keyframe went through while the first detection was still blocked
    assert frames_while_blocked == list(range(1, len(seq) + 1))
    # (frontend.local_ba_beside: a keyframe made at the last frame reaches the loop stage after it)
    assert keyframes_while_blocked[-1] == n_kf - int(out.frames[-1].is_keyframe)
    assert finished == out.keyframe_ids.tolist()  # each keyframe detected once, in order
    assert started == finished
    assert out.metrics["loop_keyframes_not_queried"] == 0


def test_backlog_stores_keyframes_without_querying(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    release = threading.Event()
    queried: list[bool] = []
    original = LoopCloser.process_keyframe

    def slow(self: LoopCloser, kf: Any, neighbours: Any = None, query: bool = True, **kwargs: Any) -> Any:
        assert release.wait(timeout=60.0)
        queried.append(query)
        return original(self, kf, neighbours, query, **kwargs)

    monkeypatch.setattr(LoopCloser, "process_keyframe", slow)
    cfg = Config()
    cfg.frontend.max_parallax_ratio = 0.005
    cfg.loop.detection_worker = "thread"
    cfg.loop.max_queued_keyframes = 2

    def progress(done: int, total: int, fps: float, keyframes: int) -> None:
        if done == total:
            release.set()

    out = run_pipeline(open_sequence(TINY), cfg, tmp_path, "bg", progress=progress)
    n_kf = len(out.keyframe_ids)
    assert len(queried) == n_kf
    # the first two were queried; while the backlog held 2, the rest were only stored
    assert queried[:2] == [True, True] and not any(queried[2:])
    assert out.metrics["loop_keyframes_not_queried"] == n_kf - 2


@pytest.mark.slow
def test_process_worker_finds_the_loops_the_inline_detection_finds() -> None:
    """The database in a worker process (``detection_worker: process``).

    The same loops as inline detection on test_loop_closer's synthetic revisit, applied by its
    global BA.
    """
    import numpy as np
    from test_loop_closer import BASELINE, CAM, _add_mono, _keyframe, _sequence, _texture

    from loopmodel.config import LoopConfig
    from loopmodel.geometry.se3 import make_pose
    from loopmodel.loop.stage import LoopClosingStage, MapState
    from loopmodel.types import StereoCalibration

    counts = {}
    for mode in ("none", "process"):
        rng = np.random.default_rng(7)
        tex = _texture(rng)
        true, est = _sequence(rng)
        calib = StereoCalibration(CAM.K, CAM.K, make_pose(np.eye(3), [-BASELINE, 0, 0]), (640, 480))
        kfs, lid = [], 0
        for i, (Tt, Te) in enumerate(zip(true, est, strict=True)):
            kfs.append(_keyframe(i, tex, Tt, Te, lid, rng))
            lid += len(kfs[-1].landmark_ids)
        _add_mono(kfs, true, rng)
        # keyframes arrive at once here: no backlog limit, so every keyframe is queried
        cfg = LoopConfig(min_gap_keyframes=8, n_features=800, detection_worker=mode, max_queued_keyframes=100)
        stage = LoopClosingStage(calib, cfg, vocabulary=loop_vocabulary(cfg), via_backend=False)
        poses = {}
        for kf in kfs:
            poses[kf.id] = kf.world_from_kf.copy()
            stage.on_keyframe(kf, MapState(dict(poses)))
        stage.close(MapState(dict(poses)))
        m = stage.metrics()
        verified = [c for c in stage.closer.closures if "verified_at_keyframe" not in c.info]
        counts[mode] = (m["loop_closure_count"], sorted((c.query_kf, c.match_kf) for c in verified))
        assert m["loop_detection_worker"] == mode
    assert counts["process"][0] >= 1
    assert counts["process"][1] == counts["none"][1]  # the same loops were verified
