"""The run's worker processes start beside its set-up and before its first frame; the live mesh yields (tail11).

Issues 32/33: the extraction, back-end and live-mesh workers' imports (0.5-1.5 s of a core each) shared
the 2-core machine with the first frames, and a live update took the tracking thread's core.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from frontend_scene import write_kitti_folder

import loopmodel.pipeline as pl
from loopmodel.backend import Backend, create_backend
from loopmodel.backend.base import BackendEstimate, BackendUpdate
from loopmodel.backend.worker import BackgroundBackend
from loopmodel.config import BackendConfig, Config, MappingConfig
from loopmodel.io.base import Sequence
from loopmodel.io.sequence import open_sequence
from loopmodel.mapping import live
from loopmodel.priority import lower_thread_priority
from loopmodel.types import Keyframe, StereoCalibration, StereoFrame, Trajectory

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread priorities are Linux's")


def _priority() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


@linux_only
def test_lower_thread_priority_lowers_only_the_calling_thread() -> None:
    base = _priority()
    seen: dict[str, int] = {}

    def lowered(nice: int, key: str) -> None:
        lower_thread_priority(nice)
        seen[key] = _priority()

    for nice, key in ((0, "zero"), (4, "four"), (40, "capped")):
        t = threading.Thread(target=lowered, args=(nice, key))
        t.start()
        t.join()
    assert seen == {"zero": base, "four": min(base + 4, 19), "capped": 19}
    assert _priority() == base  # this (the calling test's) thread is untouched


@linux_only
def test_live_update_runs_on_a_lowered_thread() -> None:
    """:func:`remesh_blocks_low` runs :func:`remesh_blocks` on a thread 7 below the caller's priority.

    (The same block meshes through a worker process: ``tests/test_live_workers.py``.)
    """
    points = np.zeros((0, 3))
    got = live.remesh_blocks_low(7, points, points, set(), MappingConfig())
    assert got[0] == {} and got[2] == 0
    assert live._LOW_PRIORITY.submit(_priority).result() == min(_priority() + 7, 19)
    assert live._LOW_PRIORITY.submit(threading.get_native_id).result() != threading.get_native_id()


def _slow_backend(config: BackendConfig, calibration: StereoCalibration, givens: Any = None) -> Backend:
    import time

    time.sleep(1.0)
    return create_backend(config, calibration, givens)


def _failing_backend(config: BackendConfig, calibration: StereoCalibration, givens: Any = None) -> Backend:
    raise RuntimeError("no back end here")


def test_back_end_worker_start_is_waited_for_and_a_failed_start_is_not_raised() -> None:
    """(A thread worker: the process's queues are read by the same code.)"""
    import functools

    kind = "thread"
    cal = _calibration()
    slow = BackgroundBackend(functools.partial(_slow_backend, BackendConfig(), cal), kind)  # type: ignore[arg-type]
    assert not slow._started
    slow.wait_started(60.0)
    assert slow._started and not slow.errors
    slow.close()
    failed = BackgroundBackend(functools.partial(_failing_backend, BackendConfig(), cal), kind)  # type: ignore[arg-type]
    failed.wait_started(60.0)  # logged, not raised: the run's later calls report it as before
    assert failed._started and failed.errors and "no back end here" in failed.errors[0]
    failed.close()


def _calibration() -> StereoCalibration:
    K = np.array([[250.0, 0, 160], [0, 250.0, 120], [0, 0, 1]])
    right_from_left = np.eye(4)
    right_from_left[0, 3] = -0.06
    return StereoCalibration(K, K, right_from_left, (320, 240))


class _WithLaserImages(Sequence):
    """A frames-only sequence with a laser-line image at each frame's time (the extraction worker's input)."""

    format_name = "test"

    def __init__(self, inner: Sequence) -> None:
        super().__init__(inner.path)
        self.inner = inner

    @property
    def calibration(self) -> StereoCalibration:
        return self.inner.calibration

    @property
    def ground_truth(self) -> Trajectory | None:
        return self.inner.ground_truth

    def __len__(self) -> int:
        return len(self.inner)

    def frames(self) -> Iterator[StereoFrame]:
        return self.inner.frames()

    def laser_image_count(self) -> int:
        return len(self.inner)

    def laser_images(self) -> Iterator[tuple[int, np.ndarray]]:
        from test_live_workers import _laser_image

        for i, frame in enumerate(self.inner.frames()):
            yield frame.timestamp_ns, _laser_image(3.0 * i)


def test_a_run_waits_for_its_workers_before_the_first_frame(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The extraction, back-end and live-mesh workers started while the run is set up, done before frame 0."""
    folder = tmp_path / "seq"
    write_kitti_folder(folder, 4, np.random.default_rng(7))
    seq = _WithLaserImages(open_sequence(folder))
    cfg = Config()
    cfg.frontend.max_disparity_px = 64
    cfg.loop.enabled = False
    cfg.mapping.write_mesh = False
    cfg.mapping.live_mesh_every_kf = 1
    cfg.output.write_map = False
    at_first: dict[str, bool] = {}
    step = pl._Run.step

    def first_step(self: pl._Run, frame: StereoFrame) -> Any:
        if not at_first:
            worker = self.laser._worker
            at_first["extraction"] = worker is not None and worker._started.done()
            at_first["backend"] = isinstance(self.backend, BackgroundBackend) and self.backend._started
            at_first["live"] = self.live._started is not None and self.live._started.done()
        return step(self, frame)

    monkeypatch.setattr(pl._Run, "step", first_step)
    result = pl.process(seq, cfg)
    assert at_first == {"extraction": True, "backend": True, "live": True}
    assert len(result.frames) == 4


class _PriorityBackend:
    """A back end that notes the scheduling priority of the thread each call runs on."""

    def __init__(self) -> None:
        self.seen: dict[str, int] = {}

    def add_keyframe(self, keyframe: Keyframe) -> BackendUpdate:
        self.seen["add_keyframe"] = _priority()
        return BackendUpdate(int(keyframe.id))

    def estimate(self, landmarks: bool = True) -> BackendEstimate:
        self.seen["estimate_landmarks" if landmarks else "estimate"] = _priority()
        return BackendEstimate({}, np.zeros(0, np.int64), np.zeros((0, 3)))

    def final_estimate(self, refine: Any) -> BackendEstimate:
        self.seen["final_estimate"] = _priority()
        return self.estimate(landmarks=True)

    def metrics(self) -> dict[str, Any]:
        return {f"priority_{k}": v for k, v in self.seen.items()}


@linux_only
def test_backend_updates_run_lowered_and_what_the_run_waits_for_does_not() -> None:
    """The back end's keyframe updates (and their estimate) run ``worker_nice`` below the worker's start.

    The end-of-run call the tracker waits for keeps the run's priority (kf12).
    """
    base = _priority()
    backend = BackgroundBackend(_PriorityBackend, "thread", nice=6)
    backend.wait_started(10.0)
    backend.add_keyframe(Keyframe(0, 0, np.eye(4), np.arange(1), np.ones((1, 3)), np.ones((1, 3))))
    deadline = time.perf_counter() + 10.0
    while not backend.batch_ms and time.perf_counter() < deadline:  # its batch (update, estimate) done alone
        backend.estimate(landmarks=False)
        time.sleep(0.01)
    backend.final_estimate(None)
    seen = {k.removeprefix("priority_"): v for k, v in backend.metrics().items() if k.startswith("priority_")}
    low = min(base + 6, 19)
    assert seen == {"add_keyframe": low, "estimate": low, "final_estimate": base, "estimate_landmarks": base}
    assert _priority() == base
