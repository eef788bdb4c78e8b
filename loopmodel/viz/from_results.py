"""A rerun recording of a finished run, built from its results folder (``loopmodel view``).

Reads what the run wrote — ``trajectory_online.tum``, ``trajectory_final.tum``, ``map.npz``,
``stripes.npz``, ``mesh.ply``, ``metrics.json`` (loop events) — and, when the sequence the run
processed is still where ``metrics.json`` says, its left images. Every file is optional except
the online trajectory; what is missing is reported, not fatal.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from loopmodel.errors import InputError
from loopmodel.viz.recorder import RerunRecorder, RerunSink


@dataclass
class ViewSummary:
    """What went into the recording."""

    path: Path
    frames: int = 0
    images: int = 0
    keyframes: int = 0
    landmarks: int = 0
    stripe_points: int = 0
    mesh_triangles: int = 0
    events: int = 0
    notes: list[str] = field(default_factory=list)


def _read_json(p: Path) -> dict[str, Any]:
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(p, f"not a readable JSON file ({exc})") from None
    if not isinstance(data, dict):
        raise InputError(p, "expected a JSON object")
    return data


def record_results(results_dir: Path, out: Path, with_images: bool = True, image_every: int = 1) -> ViewSummary:
    """Write ``out`` (a ``.rrd`` file) from the results folder ``results_dir``."""
    from loopmodel.io.trajectory_io import read_trajectory

    folder = Path(results_dir)
    online_path = folder / "trajectory_online.tum"
    if not folder.is_dir() or not online_path.is_file():
        raise InputError(folder, "not a results folder (expected trajectory_online.tum written by 'loopmodel run')")
    online = read_trajectory(online_path, "tum")
    final = (
        read_trajectory(folder / "trajectory_final.tum", "tum") if (folder / "trajectory_final.tum").is_file() else None
    )
    metrics = _read_json(folder / "metrics.json") if (folder / "metrics.json").is_file() else {}
    summary = ViewSummary(out)
    rec = RerunRecorder(RerunSink(path=out), image_every=image_every)
    try:
        frames_by_time: dict[int, Any] = {}
        seq = _open_sequence(folder, metrics, summary) if with_images else None
        times = online.timestamps_ns
        if seq is not None:
            cal = seq.calibration
            rec.camera_model(cal.K_left, cal.image_size[0], cal.image_size[1])
            if seq.ground_truth is not None and len(seq.ground_truth) and len(times):
                from loopmodel.viz.recorder import ground_truth_in_run_world

                rec.ground_truth(ground_truth_in_run_world(seq.ground_truth, int(times[0])))
        idx = {int(t): i for i, t in enumerate(times)}
        if seq is not None:
            for fr in seq.frames():
                i = idx.get(int(fr.timestamp_ns))
                if i is None:
                    continue
                left = fr.left if fr.left.ndim == 2 else fr.left[..., ::-1]
                rec.frame(i, int(fr.timestamp_ns), online.world_from_cam[i], image=left)
                frames_by_time[i] = True
                summary.images += i % rec.image_every == 0
        for i, (t, T) in enumerate(zip(times, online.world_from_cam, strict=True)):
            if i not in frames_by_time:
                rec.frame(i, int(t), T)
        summary.frames = len(online)
        last = len(online) - 1
        rec.set_frame(last, int(times[-1]) if len(times) else 0)
        if final is not None:
            rec.final_path(final.world_from_cam)
        kf_pose = _map(folder, rec, summary)
        _stripes(folder, rec, summary)
        _mesh(folder, rec, summary)
        for ev in metrics.get("loop_events", []) or []:
            a, b = kf_pose.get(int(ev.get("keyframe", -1))), kf_pose.get(int(ev.get("match_keyframe", -1)))
            frame = int(ev.get("frame", last))
            if 0 <= frame < len(times):
                rec.set_frame(frame, int(times[frame]))
            text = (
                f"{ev.get('type', 'event')}: keyframe {ev.get('keyframe')} ↔ {ev.get('match_keyframe')}, "
                f"{ev.get('inliers', '?')} inliers, correction {1e3 * float(ev.get('correction_m', 0.0)):.2f} mm"
            )
            rec.event(text, None if a is None else a[:3, 3], None if b is None else b[:3, 3])
            summary.events += 1
    finally:
        rec.close()
    return summary


def _open_sequence(folder: Path, metrics: dict[str, Any], summary: ViewSummary) -> Any:
    from loopmodel.config import load_config
    from loopmodel.io.sequence import open_sequence

    src = metrics.get("sequence")
    if not src or not Path(src).exists():
        summary.notes.append(f"sequence {src or '(not recorded)'} not found: no images in the recording")
        return None
    cfg_path = folder / "config.yaml"
    try:
        cfg = load_config(cfg_path if cfg_path.is_file() else None)
        return open_sequence(Path(src), cfg.sequence)
    except InputError as exc:
        summary.notes.append(f"sequence {src} cannot be opened ({exc}): no images in the recording")
        return None


def _map(folder: Path, rec: RerunRecorder, summary: ViewSummary) -> dict[int, np.ndarray]:
    p = folder / "map.npz"
    if not p.is_file():
        summary.notes.append("no map.npz: no keyframes or landmarks")
        return {}
    try:
        with np.load(p, allow_pickle=False) as z:
            ids = z["keyframe_ids"].astype(np.int64)
            T = z["world_from_kf"].astype(float).reshape(-1, 4, 4)
            lm = z["landmarks_in_world"].astype(float).reshape(-1, 3) if "landmarks_in_world" in z.files else None
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(p, f"not a map written by 'loopmodel run' ({exc})") from None
    rec.keyframes(T)
    summary.keyframes = len(ids)
    if lm is not None and len(lm):
        rec.landmarks(lm)
        summary.landmarks = len(lm)
    return {int(k): T[i] for i, k in enumerate(ids)}


def _stripes(folder: Path, rec: RerunRecorder, summary: ViewSummary) -> None:
    if not (folder / "stripes.npz").is_file():
        summary.notes.append("no stripes.npz: no laser points")
        return
    from loopmodel.io.laser import load_stripes_and_poses
    from loopmodel.mapping.stripe_map import StripeMap

    stripes, traj, _ = load_stripes_and_poses(folder, "final")
    pts = StripeMap.from_trajectory(traj, stripes).world_points()
    rec.stripes(pts)
    summary.stripe_points = len(pts)


def _mesh(folder: Path, rec: RerunRecorder, summary: ViewSummary) -> None:
    p = folder / "mesh.ply"
    if not p.is_file():
        summary.notes.append("no mesh.ply: no mesh")
        return
    from loopmodel.io.mesh_io import read_mesh

    m = read_mesh(p)
    if not m.has_vertex_normals():
        m.compute_vertex_normals()
    rec.mesh(np.asarray(m.vertices), np.asarray(m.triangles), np.asarray(m.vertex_normals))
    summary.mesh_triangles = len(m.triangles)
