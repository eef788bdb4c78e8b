"""Wiring of the stages: a sequence goes through the front end and the back end (later also
loop closing and meshing); outputs go to the results folder. Owns nothing else."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from loopmodel.backend import BackendEstimate, create_backend
from loopmodel.config import Config, MappingConfig
from loopmodel.errors import LoopmodelError
from loopmodel.frontend import FrameResult, FrontEnd, Keyframe
from loopmodel.io.base import Sequence
from loopmodel.io.results import LogCapture, ResultsFolder
from loopmodel.mapping.extraction import sequence_stripe_count, sequence_stripes
from loopmodel.mapping.live import LiveMapping
from loopmodel.mapping.stripe_map import StripeMap
from loopmodel.types import StripeProfile, Trajectory

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
    return Trajectory(np.array([f.timestamp_ns for f in ok]), np.stack([f.world_from_cam for f in ok]))


def _keyframe_trajectory(keyframes: list[tuple[int, int]], world_from_kf: dict[int, np.ndarray]) -> Trajectory:
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
            gt.timestamps_ns,
            gt.world_from_cam,
            est.timestamps_ns,
            est.world_from_cam,
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
    """The front end alone over ``sequence``: :func:`run_pipeline` with ``backend.kind: none``
    (keyframes keep the tracked poses), no loop closing and no mesh. Writes the same results
    folder (``trajectory_final.tum`` equals the online trajectory). An interrupted run still
    writes what it has, then re-raises."""
    fe_config = config.model_copy(deep=True)
    fe_config.backend.kind = "none"
    fe_config.loop.enabled = False
    fe_config.mapping.write_mesh = False
    fe_config.mapping.live_mesh_every_kf = 0
    return run_pipeline(
        sequence,
        fe_config,
        out_dir,
        name,
        None if progress is None else (lambda i, n, fps, _kf: progress(i, n, fps)),
        max_frames,
        keyframe_hooks,
    )


# --------------------------------------------------------------------------- full pipeline
# progress(frames_done, frames_total, frames_per_second, keyframes)
PipelineProgressFn = Callable[[int, int, float, int], None]


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """While a run is going, SIGTERM behaves like Ctrl-C (main thread only), so a killed run
    still writes what it has."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum: int, frame: object) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _quantiles(values: list[float], prefix: str) -> dict[str, float | None]:
    a = np.asarray(values, dtype=float)
    return {
        f"{prefix}_median": float(np.median(a)) if a.size else None,
        f"{prefix}_p95": float(np.percentile(a, 95)) if a.size else None,
    }


def _map_arrays(
    keyframes: list[tuple[int, int]],
    world_from_kf: dict[int, np.ndarray],
    estimate: BackendEstimate | None,
) -> dict[str, np.ndarray]:
    """``map.npz`` content: keyframe ids, times and poses; landmark ids and world points."""
    return {
        "keyframe_ids": np.array([k for k, _ in keyframes], dtype=np.int64),
        "keyframe_timestamps_ns": np.array([t for _, t in keyframes], dtype=np.int64),
        "world_from_kf": np.stack([world_from_kf[k] for k, _ in keyframes]) if keyframes else np.zeros((0, 4, 4)),
        "landmark_ids": estimate.landmark_ids if estimate is not None else np.zeros(0, np.int64),
        "landmarks_in_world": estimate.landmarks_in_world if estimate is not None else np.zeros((0, 3)),
    }


def _write_stripes(
    folder: ResultsFolder, sequence: Sequence, frames: list[FrameResult], config: MappingConfig
) -> list[StripeProfile]:
    """``stripes.npz``: the sequence's laser profiles up to the last processed frame (sensor
    frame; ``loopmodel mesh`` places them with the run's trajectory). Skipped without any."""
    if not frames or sequence_stripe_count(sequence) == 0:
        return []
    from loopmodel.io.stripes_io import STRIPES_FILE, save_stripes

    last_ns = frames[-1].timestamp_ns
    try:
        stripes = [s for s in sequence_stripes(sequence, config) if s.timestamp_ns <= last_ns]
    except LoopmodelError as exc:  # the trajectories matter more than the stripes
        logger.error("laser stripes not written: %s", exc)
        return []
    if stripes:
        save_stripes(folder.file(STRIPES_FILE), stripes)
    return stripes


def _aligned_to(traj: Trajectory, reference: Trajectory) -> Trajectory:
    """``traj`` moved by the SE(3) transform that best aligns its positions to ``reference``
    at common timestamps (exact match)."""
    from loopmodel.geometry.align import umeyama_alignment
    from loopmodel.geometry.se3 import make_pose

    _, ia, ib = np.intersect1d(traj.timestamps_ns, reference.timestamps_ns, return_indices=True)
    if ia.size < 3:
        return traj
    R, t, _s = umeyama_alignment(traj.positions_m[ia], reference.positions_m[ib])
    return Trajectory(traj.timestamps_ns, make_pose(R, t)[None] @ traj.world_from_cam)


def _write_mesh(
    folder: ResultsFolder,
    sequence: Sequence,
    stripes: list[StripeProfile],
    online: Trajectory,
    final: Trajectory,
    config: Config,
) -> dict[str, Any]:
    """``mesh.ply`` of the stripes placed with the final trajectory; with a ground-truth scene
    (``scene.ply`` attachment) and poses, the mesh error with ground-truth, online (before loop
    closure) and final (after) poses, both SE(3)-aligned to the truth by their frame
    positions; completeness of the scanned object (``object.ply``) and of its swept part when
    the sequence has it. Returns the metrics to record."""
    if not stripes or not config.mapping.write_mesh or len(final) < 2:
        return {}
    from loopmodel.io.mesh_io import mesh_from_bytes, write_mesh
    from loopmodel.mapping.accuracy import mesh_error_metrics
    from loopmodel.mapping.stripe_map import StripeMap

    out: dict[str, Any] = {}
    try:
        smap = StripeMap.from_trajectory(final, stripes, config.mapping)
        smap.check_nonempty()
        surface = smap.mesh()
        write_mesh(folder.file("mesh.ply"), surface, "ply")
        out["mesh_vertices"] = len(surface.vertices)
        names = getattr(sequence, "attachment_names", [])
        gt = sequence.ground_truth
        if "scene.ply" in names and gt is not None:
            scene = sequence.read_attachment("scene.ply")  # type: ignore[attr-defined]
            gt_mesh = mesh_from_bytes(scene, "ply", sequence.path)
            # the run's world is its first keyframe: express both trajectories in the truth's
            # world by the SE(3) alignment of the frame positions before meshing
            trajs = {"gt": gt, "before": _aligned_to(online, gt), "after": _aligned_to(final, gt)}
            # completeness of the scanned object (``object.ply``) when the sequence has it
            obj = (
                mesh_from_bytes(sequence.read_attachment("object.ply"), "ply", sequence.path)  # type: ignore[attr-defined]
                if "object.ply" in names
                else None
            )
            out.update(mesh_error_metrics(stripes, trajs, gt_mesh, config.mapping, object_mesh=obj))
    except LoopmodelError as exc:  # a run without a mesh still has its trajectories
        logger.error("mesh not written: %s", exc)
    return out


def run_pipeline(
    sequence: Sequence,
    config: Config,
    out_dir: str | Path | None = None,
    name: str = "run",
    progress: PipelineProgressFn | None = None,
    max_frames: int | None = None,
    keyframe_hooks: list[KeyframeHook] | None = None,
) -> RunOutput:
    """Reader -> front end -> back end -> results folder ``<out_dir>/<name>/``.

    Every keyframe first goes to loop closing (``config.loop``: relocalization of a new
    segment, verified revisits whose observations of old landmarks join the keyframe's
    monocular observations, plus a relative-pose loop constraint), then to the back end
    (``config.backend.kind``); keyframes it moves are handed back to the front end and to
    the anchored trajectory, in which every frame is stored relative to its keyframe.
    ``metrics.json`` lists each closure under ``loop_events``. Writes ``config.yaml``, ``trajectory_online.tum`` (poses
    as estimated live), ``trajectory_final.tum`` (frames recomposed with the final keyframe
    poses), ``keyframes.tum``, ``map.npz``, ``metrics.json``, ``run.log`` (KITTI variants
    of the trajectories when ``output.write_kitti``) and ``stripes.npz`` when the sequence
    has laser profiles. Ctrl-C or SIGTERM stops the run after
    the current frame; everything up to it is written, then ``KeyboardInterrupt`` is raised.
    """
    folder = ResultsFolder(out_dir if out_dir is not None else config.output.out_dir, name)
    folder.write_config(config)
    frontend = FrontEnd(sequence.calibration, config.frontend)
    backend = create_backend(config.backend, frontend.calibration, config.givens)
    # frame poses anchored to their keyframes (corrections reach every frame), and the stripes
    anchored = StripeMap(config.mapping)
    live = LiveMapping(anchored, sequence, config.mapping.live_mesh_every_kf)
    loop_stage = None
    if config.loop.enabled and config.backend.kind != "none":
        from loopmodel.loop.stage import LoopClosingStage

        loop_stage = LoopClosingStage(frontend, frontend.calibration, config.loop, backend=backend)
    total = len(sequence) if max_frames is None else min(len(sequence), max_frames)
    frames: list[FrameResult] = []
    keyframes: list[tuple[int, int]] = []
    # keyframe -> (previous keyframe, the tracker's pose of it there): drift per interval
    tracked_links: dict[int, tuple[int, np.ndarray]] = {}
    backend_ms: list[float] = []
    frame_ms: list[float] = []
    hooks = keyframe_hooks or []
    interrupted = False
    estimate: BackendEstimate | None = None
    t_start = time.perf_counter()
    with LogCapture() as log, _sigterm_as_interrupt():
        logger.info("pipeline on %s (%d frames, back end %s)", sequence.path, total, config.backend.kind)
        try:
            for i, frame in enumerate(sequence.frames()):
                if i >= total:
                    break
                t0 = time.perf_counter()
                res = frontend.process(frame)
                if res.status != "OK":
                    logger.info("frame %d LOST: %s", frame.index, res.reason)
                kf = res.keyframe
                if kf is not None:
                    keyframes.append((kf.id, kf.timestamp_ns))
                    tracked = getattr(kf, "kf_prev_from_kf_tracked", None)
                    if kf.connected and kf.prev_keyframe_id is not None and tracked is not None:
                        tracked_links[kf.id] = (kf.prev_keyframe_id, tracked)
                    if loop_stage is not None:  # revisits and relocalization, before the back end
                        loop_stage.on_keyframe(kf)
                    anchored.set_keyframe(kf.id, kf.world_from_kf)
                    tb = time.perf_counter()
                    backend.add_keyframe(kf)
                    if loop_stage is not None:
                        loop_stage.update_backend()
                    estimate = backend.estimate(landmarks=False)
                    backend_ms.append((time.perf_counter() - tb) * 1e3)
                    if loop_stage is not None:
                        loop_stage.note_estimate(estimate.world_from_kf, backend_ms[-1])
                    moved = {
                        k: estimate.world_from_kf[k] for k in estimate.changed_keyframes if k in estimate.world_from_kf
                    }
                    if moved:
                        frontend.apply_correction(moved)
                        anchored.update_keyframes(moved)
                    for hook in hooks:
                        hook(kf, res)
                    # do not hold every keyframe (and its image) for the whole run
                    res = dataclasses.replace(res, keyframe=None)
                frames.append(res)
                if res.ok:
                    anchored.add_frame(res.timestamp_ns, kf_id=res.keyframe_id, kf_from_cam=res.kf_from_cam)
                    live.feed(res.timestamp_ns)
                if kf is not None:
                    live.on_keyframe()
                frame_ms.append((time.perf_counter() - t0) * 1e3)
                if progress is not None:
                    el = time.perf_counter() - t_start
                    progress(i + 1, total, (i + 1) / el if el > 0 else 0.0, len(keyframes))
        except KeyboardInterrupt:
            interrupted = True
            logger.warning("interrupted after %d frames", len(frames))
        finally:
            wall = time.perf_counter() - t_start
            live.close(wait=not interrupted)
            live.write(folder)
            online = _online_trajectory(frames)
            folder.write_trajectory("trajectory_online.tum", online)
            t_final = time.perf_counter()
            try:
                if keyframes and not interrupted:
                    refine = getattr(backend, "refine", None)
                    if callable(refine):
                        refine()
                if keyframes:
                    estimate = backend.estimate()
                    batch = getattr(backend, "batch_refine", None)
                    if config.refine.batch_ba and not interrupted and callable(batch):
                        rc = config.refine
                        estimate = batch(rc.pixel_sigma_px, rc.huber_k, rc.max_iterations)
                    anchored.update_keyframes(estimate.world_from_kf)
            except Exception as exc:  # keep the front end's keyframes; still write everything
                logger.error("back end failed at the end of the run: %s", exc)
            if config.refine.bridge_frames:
                final = anchored.bridged_trajectory(dict(keyframes), tracked_links)
            else:
                final = anchored.trajectory()
            final_refine_s = time.perf_counter() - t_final
            kf_poses = anchored.keyframe_poses
            folder.write_trajectory("trajectory_final.tum", final)
            folder.write_trajectory("keyframes.tum", _keyframe_trajectory(keyframes, kf_poses))
            if config.output.write_kitti:
                folder.write_trajectory("trajectory_online.kitti", online, "kitti")
                folder.write_trajectory("trajectory_final.kitti", final, "kitti")
            folder.write_npz("map.npz", _map_arrays(keyframes, kf_poses, estimate))
            stripes = _write_stripes(folder, sequence, frames, config.mapping)
            metrics: dict[str, Any] = {"sequence": str(sequence.path), "interrupted": interrupted}
            metrics.update(_write_mesh(folder, sequence, stripes, online, final, config))
            metrics.update(frontend_metrics(frames, wall))
            metrics["fps"] = len(frames) / (sum(frame_ms) / 1e3) if sum(frame_ms) > 0 else None
            metrics["backend"] = config.backend.kind
            metrics["final_refine_s"] = final_refine_s
            if loop_stage is not None:
                metrics.update(loop_stage.metrics())
            if live.enabled:
                metrics["live_mesh_updates"] = len(live.update_ms)
                metrics["live_mesh_blocks_remeshed"] = live.blocks_remeshed
                metrics.update(_quantiles(live.update_ms, "live_mesh_update_ms"))
            screen_stats = getattr(backend, "screen_stats", None)
            if callable(screen_stats):
                stats = screen_stats()
                metrics["givens_tested_observations"] = stats["tested"]
                metrics["givens_rejected_observations"] = stats["rejected"]
            metrics["landmarks"] = 0 if estimate is None else int(estimate.landmark_ids.size)
            metrics.update(_quantiles(frame_ms, "frame_total_ms"))
            metrics.update(_quantiles(backend_ms, "backend_ms"))
            gt = sequence.ground_truth
            for suffix, traj in (("_online", online), ("", final)):
                metrics.update({k + suffix: v for k, v in _ground_truth_errors(traj, gt).items()})
            folder.write_json("metrics.json", metrics)
            logger.info(
                "done: %d frames, %d keyframes, %s fps",
                len(frames),
                len(keyframes),
                f"{metrics['fps']:.1f}" if metrics["fps"] else "-",
            )
            folder.write_text("run.log", log.text())
            folder.commit()  # the staged folder replaces an older run's only now
    if interrupted:
        raise KeyboardInterrupt
    return RunOutput(folder.path, frames, keyframes, metrics, interrupted)
