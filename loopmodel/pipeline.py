"""Wiring of the stages: a sequence goes through the front end (and, later, the back end,
loop closing and meshing); outputs go to the results folder. Owns nothing else."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from loopmodel.config import Config
from loopmodel.frontend import FrameResult, FrontEnd, Keyframe
from loopmodel.io.base import Sequence
from loopmodel.io.results import LogCapture, ResultsFolder
from loopmodel.types import Trajectory

logger = logging.getLogger(__name__)

# progress(frames_done, frames_total, frames_per_second)
ProgressFn = Callable[[int, int, float], None]
KeyframeHook = Callable[[Keyframe, FrameResult], None]


@dataclass
class RunOutput:
    """What a run produced: the results folder, per-frame results (without their keyframe
    payload, so a long run does not hold every keyframe image), the keyframe ids and times,
    and the metrics. Keyframes themselves go to the keyframe hooks as they are made."""

    folder: Path
    frames: list[FrameResult]
    keyframes: list[tuple[int, int]]  # (keyframe id, timestamp_ns)
    metrics: dict[str, Any]
    interrupted: bool = False
    extra: dict[str, Any] = field(default_factory=dict)


def _online_trajectory(frames: list[FrameResult]) -> Trajectory:
    ok = [f for f in frames if f.ok]
    if not ok:
        return Trajectory(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))
    return Trajectory(
        np.array([f.timestamp_ns for f in ok]), np.stack([f.world_from_cam for f in ok])
    )


def _keyframe_trajectory(
    keyframes: list[tuple[int, int]], world_from_kf: dict[int, np.ndarray]
) -> Trajectory:
    if not keyframes:
        return Trajectory(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))
    return Trajectory(
        np.array([t for _, t in keyframes]),
        np.stack([world_from_kf[k] for k, _ in keyframes]),
    )


def _ground_truth_errors(est: Trajectory, gt: Trajectory | None) -> dict[str, float]:
    """ATE RMSE after SE(3) alignment and drift (end-point error with the first poses
    aligned, percent of the ground-truth path), computed by :mod:`loopmodel.eval`."""
    if gt is None or len(est) < 3:
        return {}
    from loopmodel.eval.trajectory_metrics import EvalInputError, evaluate_pair

    try:
        ev = evaluate_pair(
            gt.timestamps_ns, gt.world_from_cam, est.timestamps_ns, est.world_from_cam,
            max_dt_ns=1_000_000,
        )
    except EvalInputError as exc:
        logger.warning("no ground-truth evaluation: %s", exc)
        return {}
    m = ev.metrics
    end = m["end_point"]
    ate = m["ate_m"]
    assert isinstance(end, dict) and isinstance(ate, dict)
    return {
        "ate_rmse_m": float(ate["rmse"]),
        "final_error_m": float(end["error_origin_aligned_m"]),
        "path_length_m": float(m["path_length_m"]),  # type: ignore[arg-type]
        "drift_pct": float(end["error_origin_aligned_pct"]),
        "gt_frames": int(m["matched"]),  # type: ignore[call-overload]
    }


def frontend_metrics(frames: list[FrameResult], wall_s: float) -> dict[str, Any]:
    """Counts and timings of a front-end run (milliseconds, medians and 95th percentiles)."""
    track = np.array([f.track_ms for f in frames]) if frames else np.zeros(0)
    kf_ms = np.array([f.keyframe_ms for f in frames if f.is_keyframe])
    total = np.array([f.track_ms + f.keyframe_ms for f in frames]) if frames else np.zeros(0)

    def q(a: np.ndarray, p: float) -> float | None:
        return float(np.percentile(a, p)) if a.size else None

    return {
        "frames": len(frames),
        "ok_frames": sum(f.ok for f in frames),
        "lost_frames": sum(not f.ok for f in frames),
        "keyframes": sum(f.is_keyframe for f in frames),
        "segments": (max(f.segment for f in frames) + 1) if frames else 0,
        "track_ms_median": q(track, 50),
        "track_ms_p95": q(track, 95),
        "keyframe_ms_median": q(kf_ms, 50),
        "frame_ms_median": q(total, 50),
        "fps": len(frames) / float(total.sum() / 1e3) if total.size and total.sum() > 0 else None,
        "fps_with_io": len(frames) / wall_s if wall_s > 0 else None,
    }


def run_frontend(
    sequence: Sequence,
    config: Config,
    out_dir: str | Path | None = None,
    name: str = "run",
    progress: ProgressFn | None = None,
    max_frames: int | None = None,
    keyframe_hooks: list[KeyframeHook] | None = None,
) -> RunOutput:
    """Run the front end over ``sequence`` and write ``trajectory_online.tum``,
    ``keyframes.tum``, ``metrics.json``, ``config.yaml`` and ``run.log`` into
    ``<out_dir>/<name>/`` (``out_dir`` defaults to ``config.output.out_dir``). An interrupted
    run (Ctrl-C included) still writes what it has, then re-raises."""
    folder = ResultsFolder(out_dir if out_dir is not None else config.output.out_dir, name)
    folder.write_config(config)
    frontend = FrontEnd(sequence.calibration, config.frontend)
    total = len(sequence) if max_frames is None else min(len(sequence), max_frames)
    frames: list[FrameResult] = []
    keyframes: list[tuple[int, int]] = []
    hooks = keyframe_hooks or []
    interrupted = False
    t_start = time.perf_counter()
    with LogCapture() as log:
        logger.info("front end on %s (%d frames)", sequence.path, total)
        try:
            for i, frame in enumerate(sequence.frames()):
                if i >= total:
                    break
                res = frontend.process(frame)
                if res.status != "OK":
                    logger.info("frame %d LOST: %s", frame.index, res.reason)
                if res.keyframe is not None:
                    keyframes.append((res.keyframe.id, res.keyframe.timestamp_ns))
                    for hook in hooks:
                        hook(res.keyframe, res)
                    res = dataclasses.replace(res, keyframe=None)
                frames.append(res)
                if progress is not None:
                    el = time.perf_counter() - t_start
                    progress(i + 1, total, (i + 1) / el if el > 0 else 0.0)
        except KeyboardInterrupt:
            interrupted = True
            logger.warning("interrupted after %d frames", len(frames))
        finally:
            wall = time.perf_counter() - t_start
            online = _online_trajectory(frames)
            folder.write_trajectory("trajectory_online.tum", online)
            folder.write_trajectory(
                "keyframes.tum", _keyframe_trajectory(keyframes, frontend.world_from_kf)
            )
            metrics: dict[str, Any] = {"sequence": str(sequence.path), "interrupted": interrupted}
            metrics.update(frontend_metrics(frames, wall))
            metrics.update(_ground_truth_errors(online, sequence.ground_truth))
            folder.write_json("metrics.json", metrics)
            logger.info("done: %s", {k: metrics[k] for k in ("frames", "ok_frames", "keyframes")})
            folder.write_text("run.log", log.text())
    if interrupted:
        raise KeyboardInterrupt
    return RunOutput(folder.path, frames, keyframes, metrics, interrupted)
