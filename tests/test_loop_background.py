"""Loop detection off the tracking path (issue 26): with the verifier blocked, the pipeline
still processes every frame and keyframe; the detections are applied afterwards, in order."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest

from loopmodel.config import Config
from loopmodel.io.sequence import open_sequence
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
    assert keyframes_while_blocked[-1] == n_kf
    assert finished == out.keyframe_ids.tolist()  # each keyframe detected once, in order
    assert started == finished
    assert out.metrics["loop_keyframes_not_queried"] == 0


def test_backlog_stores_keyframes_without_querying(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    release = threading.Event()
    queried: list[bool] = []
    original = LoopCloser.process_keyframe

    def slow(self: LoopCloser, kf: Any, neighbours: Any = None, query: bool = True) -> Any:
        assert release.wait(timeout=60.0)
        queried.append(query)
        return original(self, kf, neighbours, query)

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
