"""Stopping a run.

A signal only sets the stop flag, the frame loop stops between frames, and an interruption inside a
keyframe's step still leaves a complete, consistent results folder.
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest
from frontend_scene import write_kitti_folder

from loopmodel.backend.isam2 import Isam2Backend
from loopmodel.config import Config
from loopmodel.io.sequence import open_sequence
from loopmodel.io.trajectory_io import read_trajectory
from loopmodel.pipeline import StopFlag, process, run_pipeline

N_FRAMES = 10


@pytest.fixture(scope="module")
def sequence_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("stop") / "seq"
    write_kitti_folder(folder, N_FRAMES, np.random.default_rng(11))
    return folder


def _config() -> Config:
    cfg = Config()
    cfg.frontend.max_disparity_px = 64
    cfg.frontend.max_features = 300
    cfg.frontend.min_tracked_fraction = 0.95  # several keyframes in a short sequence
    return cfg


def _check_folder(out: Path) -> dict[str, object]:
    """Every result file is there and parses; the trajectories agree with the metrics."""
    m = json.loads((out / "metrics.json").read_text())
    online = read_trajectory(out / "trajectory_online.tum")
    final = read_trajectory(out / "trajectory_final.tum")
    kfs = read_trajectory(out / "keyframes.tum")
    z = np.load(out / "map.npz")
    assert len(online) == m["ok_frames"] and len(final) == len(online)
    assert z["keyframe_ids"].size == len(kfs) and np.array_equal(z["keyframe_timestamps_ns"], kfs.timestamps_ns)
    assert "interrupted after" in (out / "run.log").read_text()
    return m


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_the_run_between_frames(sequence_dir: Path, tmp_path: Path, signum: int) -> None:
    def progress(i: int, n: int, fps: float, kf: int) -> None:
        if i == 4:
            os.kill(os.getpid(), signum)  # the handler only sets the flag: frame 4 is the last

    before = signal.getsignal(signum)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(open_sequence(sequence_dir), _config(), tmp_path, "cut", progress=progress)
    m = _check_folder(tmp_path / "cut")
    assert m["interrupted"] is True and m["frames"] == 4
    assert signal.getsignal(signum) == before


def test_an_interrupt_inside_a_keyframe_step_leaves_a_consistent_folder(
    sequence_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A ``KeyboardInterrupt`` in the back end's update of the third keyframe (no signal handler installed).

    The keyframe is in the back end but not recorded; every file is written.
    """
    calls = {"n": 0}
    add = Isam2Backend.add_keyframe

    def interrupted_add(self: Isam2Backend, keyframe: object) -> object:
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return add(self, keyframe)  # type: ignore[arg-type]

    monkeypatch.setattr(Isam2Backend, "add_keyframe", interrupted_add)
    cfg = _config()
    cfg.backend.worker = "inline"  # the back end's update on the tracking thread (issue 33: else a worker's)
    # keyframes at frames 0, 4, 8 (with refine final's right columns read at their rows: 0, 5, 9, the
    # third then reaches the back end only after the last frame, in the finish)
    cfg.calibration.refine = "none"
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(open_sequence(sequence_dir), cfg, tmp_path, "half", handle_signals=False)
    m = _check_folder(tmp_path / "half")
    # the third keyframe reaches the back end at the start of the next frame's step, after its local BA
    # (frontend.local_ba_beside): its own frame is recorded, the next frame and the keyframe are not
    assert m["interrupted"] is True and m["keyframes"] == 3 and m["frames"] < N_FRAMES
    assert len(read_trajectory(tmp_path / "half" / "keyframes.tum")) == 2


def test_a_set_stop_flag_ends_the_run_before_the_next_frame(sequence_dir: Path) -> None:
    stop = StopFlag()

    def progress(i: int, n: int, fps: float, kf: int) -> None:
        if i == 3:
            stop.set("enough")

    result = process(open_sequence(sequence_dir), _config(), progress=progress, stop=stop)
    assert result.interrupted and len(result.frames) == 3 and stop.reason == "enough"
    assert len(result.final) == 3 and result.folder is None


def test_a_second_signal_during_the_final_writes_says_what_is_written(
    sequence_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    import logging

    from loopmodel import pipeline

    real_finish = pipeline._Run.finish

    def finish(self: pipeline._Run, interrupted: bool) -> object:
        os.kill(os.getpid(), signal.SIGINT)  # after the last frame: the run is complete
        os.kill(os.getpid(), signal.SIGINT)
        return real_finish(self, interrupted)

    monkeypatch.setattr(pipeline._Run, "finish", finish)
    with caplog.at_level(logging.WARNING, logger="loopmodel.pipeline"):
        out = run_pipeline(open_sequence(sequence_dir), _config(), tmp_path, "twice")
    said = [r.getMessage() for r in caplog.records if "already stopping" in r.getMessage()]
    # no stripes here (the mesh case with its time estimate: test_pipeline_mesh)
    assert said == ["signal 2: already stopping, please wait: the results are being written (a few seconds)"]
    assert out.metrics["frames"] == N_FRAMES and not out.interrupted


def test_the_objects_before_the_first_frame_are_frozen_during_the_frames_only(sequence_dir: Path) -> None:
    """fr16 (issue 33): the garbage collector's full passes skip the set-up's objects during the frames.

    ``gc.freeze`` before the first frame, ``gc.unfreeze`` after the last (also when stopped): a process
    running many runs keeps none of them out of the collector.
    """
    import gc

    frozen: list[int] = []

    def progress(i: int, n: int, fps: float, kf: int) -> None:
        frozen.append(gc.get_freeze_count())

    process(open_sequence(sequence_dir), _config(), progress=progress)
    assert len(frozen) == N_FRAMES and min(frozen) > 10_000  # the imports' objects (about 110,000)
    assert gc.get_freeze_count() == 0
    stop = StopFlag()
    process(open_sequence(sequence_dir), _config(), progress=lambda i, *_: stop.set() if i == 2 else None, stop=stop)
    assert gc.get_freeze_count() == 0
