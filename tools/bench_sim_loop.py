"""Benchmark ``sim-loop``: loop closing on the simulator's orbit scan (and its browse scan).

``loopmodel.pipeline.run_pipeline`` runs the sequence: front end, loop-closing stage
(relocalization, place recognition, verification; a verified loop's observations of old
landmarks and its relative pose go into the iSAM2 back end), back end, corrections fed back
to the tracker. ``before`` is dead reckoning: the keyframes chained by their
measured relative transforms (what the run gives without loop closing); ``after`` is the
final trajectory (corrected keyframe poses, each frame through its keyframe). ATE is after
SE(3) alignment to ground truth; the end-point error is the last frame's position error
with both trajectories expressed relative to their first frame (drift over the loop). A
loop (or relocalization) is false when the final relative pose of its two frames disagrees
with ground truth by more than 5 cm or 2 degrees. Mesh errors: the laser stripes meshed
with each trajectory against the scene mesh: SE(3)-aligned to the truth by the frame
positions (``mesh_err_*_mm``, as ATE and the pipeline's metrics.json) and anchored at the
first ground-truth pose (``mesh_err_*_anchored_mm``: the first frame's own error becomes a
rigid offset of the whole mesh); completeness of the scanned object (``object.ply``) and of its swept part.
Full runs add the ``browse`` scan (no revisit: must close no loop) and the orbit with a
1 s blackout (frames 290-314: LOST during it, relocalized after it).

Sequences: ``datasets/sample/scan.mcap`` (``make demo``), ``browse.mcap`` and
``blackout.mcap`` beside it; each is generated with ``loopmodel simulate scan`` when
missing (slow: minutes). ``--quick``: the orbit only, every 2nd frame.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from loopmodel.config import Config
from loopmodel.geometry.align import umeyama_alignment
from loopmodel.geometry.se3 import invert_pose, so3_log

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "datasets" / "sample"


BLACKOUT = (290, 314)  # frames of the 1 s blackout (25 Hz) in the blackout variant


def _ensure(path: Path, preset: str, faults: list[str] | None = None) -> Path:
    if path.is_file():
        return path
    from loopmodel.sim.generate import resolve_config, simulate_scan

    cfg = Config()
    sim = resolve_config(cfg.simulation, preset, {}, faults)
    print(f"generating {path} ({preset}) ...")
    simulate_scan(sim, path, cfg.sequence.topics, None, preset)
    return path


class _Strided:
    """A sequence seen through every ``stride``-th frame (for ``--quick``)."""

    def __init__(self, seq: Any, stride: int) -> None:
        self._seq, self._stride = seq, stride

    def __getattr__(self, name: str) -> Any:
        return getattr(self._seq, name)

    def __len__(self) -> int:
        return (len(self._seq) + self._stride - 1) // self._stride

    def frames(self) -> Any:
        return (f for i, f in enumerate(self._seq.frames()) if i % self._stride == 0)


def run_sequence(path: Path, config: Config, max_frames: int | None = None, stride: int = 1) -> dict[str, Any]:
    """The pipeline (front end, loop stage, iSAM2 back end) over one sequence (every
    ``stride``-th frame); dead-reckoning and final trajectories, loop events."""
    import tempfile

    from loopmodel.io.sequence import open_sequence
    from loopmodel.io.trajectory_io import read_trajectory
    from loopmodel.listener import RunListener
    from loopmodel.pipeline import run_pipeline

    seq = open_sequence(path, config.sequence)
    view: Any = _Strided(seq, stride) if stride > 1 else seq
    chain: dict[int, tuple[int | None, np.ndarray | None, bool, np.ndarray]] = {}

    class _Chain(RunListener):
        def on_keyframe(self, keyframe: Any, result: Any) -> None:
            kf = keyframe
            chain[kf.id] = (kf.prev_keyframe_id, kf.kf_prev_from_kf, kf.connected, kf.world_from_kf.copy())

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        out = run_pipeline(view, config, tmp, "sim_loop", max_frames=max_frames, listeners=[_Chain()])
        final = read_trajectory(out.folder / "trajectory_final.tum")
    wall = time.perf_counter() - t0
    dr: dict[int, np.ndarray] = {}
    for k in sorted(chain):
        prev, rel, connected, live = chain[k]
        dr[k] = dr[prev] @ rel if connected and prev in dr and rel is not None else live
    by_time = dict(zip(final.timestamps_ns.tolist(), final.world_from_cam, strict=True))
    gt = seq.ground_truth
    gt_index = {t: i for i, t in enumerate(gt.timestamps_ns.tolist())} if gt is not None else {}
    ok = [f for f in out.frames if f.ok and f.timestamp_ns in by_time]
    kept = [gt_index.get(f.timestamp_ns, -1) for f in ok]
    return {
        "before": np.array([dr[f.keyframe_id] @ f.kf_from_cam for f in ok]),
        "after": np.array([by_time[f.timestamp_ns] for f in ok]),
        "gt": gt.world_from_cam[np.array(kept)] if gt is not None else None,
        "events": out.metrics.get("loop_events", []),
        "rejected": out.metrics.get("loop_candidates_rejected", 0),
        "frames": len(out.frames),
        "stamps_ns": np.array([f.timestamp_ns for f in ok], dtype=np.int64),
        "kept": kept,
        "sequence": seq,
        "wall_s": wall,
        "fps": out.metrics.get("fps"),
        "lost": sum(not f.ok for f in out.frames),
        "status": [f.status for f in out.frames],
        "frame_index": {f.frame_index: j for j, f in enumerate(out.frames)},
    }


def _ate(est: np.ndarray, gt: np.ndarray) -> float:
    R, t, _ = umeyama_alignment(est[:, :3, 3], gt[:, :3, 3], with_scale=False)
    p = est[:, :3, 3] @ np.asarray(R).T + t
    return float(np.sqrt(np.mean(np.sum((p - gt[:, :3, 3]) ** 2, axis=1))))


def _endpoint(est: np.ndarray, gt: np.ndarray) -> float:
    e = invert_pose(est[0]) @ est[-1]
    g = invert_pose(gt[0]) @ gt[-1]
    return float(np.linalg.norm(e[:3, 3] - g[:3, 3]))


def _false_loops(out: dict[str, Any]) -> int:
    gt = out["gt"]
    bad = 0
    final = out["after"]
    pos = {f: j for j, f in enumerate(out["kept"])}
    for ev in out["events"]:
        if ev["frame"] not in pos or ev["match_frame"] not in pos:
            continue
        f_q, f_m = pos[ev["frame"]], pos[ev["match_frame"]]
        est_rel = invert_pose(final[f_m]) @ final[f_q]
        gt_rel = invert_pose(gt[f_m]) @ gt[f_q]
        d = invert_pose(gt_rel) @ est_rel
        if np.linalg.norm(d[:3, 3]) > 0.05 or np.degrees(np.linalg.norm(so3_log(d[:3, :3]))) > 2.0:
            bad += 1
    return bad


def _mesh_errors(out: dict[str, Any], scene_ply: Path, config: Config) -> dict[str, float | None]:
    """Mesh the laser stripes with the ground-truth, before and after trajectories and
    measure them against the scene mesh (mm). ``mesh_err_<name>_mm``: SE(3)-aligned to the
    truth by the frame positions, as ATE and the pipeline's ``metrics.json``;
    ``mesh_err_<name>_anchored_mm``: anchored at the first ground-truth pose (the run's
    gauge: its first keyframe is fixed). Completeness: share of the scanned object's surface
    (``object.ply`` attachment) within 2 mm of the mesh, and of the part the laser swept."""
    if not scene_ply.is_file():
        return {"mesh_err_before_mm": None, "mesh_err_after_mm": None}
    import open3d as o3d

    from loopmodel.mapping.accuracy import mesh_error_metrics
    from loopmodel.types import Trajectory

    gt = out["gt"]
    trajs = {"gt": Trajectory(out["stamps_ns"], gt)}
    for name in ("before", "after"):
        est = out[name]
        anchored = np.einsum("ij,njk->nik", gt[0] @ invert_pose(est[0]), est)
        trajs[name + "_anchored"] = Trajectory(out["stamps_ns"], anchored)
        R, t, _ = umeyama_alignment(est[:, :3, 3], gt[:, :3, 3], with_scale=False)
        A = np.eye(4)
        A[:3, :3], A[:3, 3] = R, t
        trajs[name] = Trajectory(out["stamps_ns"], np.einsum("ij,njk->nik", A, est))
    seq = out["sequence"]
    stripes = list(seq.stripes())
    mesh = o3d.io.read_triangle_mesh(scene_ply)
    obj = None
    if "object.ply" in seq.attachment_names:
        from loopmodel.io.mesh_io import mesh_from_bytes

        obj = mesh_from_bytes(seq.read_attachment("object.ply"), "ply", seq.path)
    m = mesh_error_metrics(stripes, trajs, mesh, config.mapping, object_mesh=obj)
    res: dict[str, float | None] = {}
    for k, v in m.items():  # completeness once per trajectory (the SE(3)-aligned one)
        if not (k.startswith("mesh_completeness") and k.endswith("_anchored")):
            res[k] = round(float(v), 4 if "completeness" in k else 3)
    return res


def run(quick: bool = False) -> dict[str, Any]:
    logging.basicConfig(level=logging.WARNING)
    config = Config()
    orbit = _ensure(SAMPLE / "scan.mcap", "orbit")
    stride = 2 if quick else 1
    out = run_sequence(orbit, config, stride=stride)
    gt = out["gt"]
    loops = [e for e in out["events"] if e["type"] == "loop"]
    result: dict[str, Any] = {
        "dataset": f"simulator orbit sample ({orbit.name})" + (", every 2nd frame" if quick else ""),
        "frames": out["frames"],
        "fps": round(out["fps"], 2) if out["fps"] else None,
        "lost_frames": out["lost"],
        "ate_rmse_before_m": round(_ate(out["before"], gt), 5),
        "ate_rmse_after_m": round(_ate(out["after"], gt), 5),
        "endpoint_err_before_m": round(_endpoint(out["before"], gt), 5),
        "endpoint_err_after_m": round(_endpoint(out["after"], gt), 5),
        "loops_closed": len(loops),
        "false_loops": _false_loops(out),
        "relocalizations": len(out["events"]) - len(loops),
        "loop_candidates_rejected": out["rejected"],
        "loop_optimise_ms_median": round(float(np.median([e["optimise_ms"] for e in loops])), 1) if loops else None,
    }
    result.update(_mesh_errors(out, orbit.with_suffix(".scene.ply"), config))
    if not quick:
        browse = _ensure(SAMPLE / "browse.mcap", "browse")
        b = run_sequence(browse, config)
        result["browse_frames"] = b["frames"]
        result["browse_loops_closed"] = sum(e["type"] == "loop" for e in b["events"])
        result["browse_false_loops"] = _false_loops(b)
        path = _ensure(SAMPLE / "blackout.mcap", "orbit", [f"blackout:{BLACKOUT[0]}-{BLACKOUT[1]}"])
        k = run_sequence(path, config)
        lost = [i for i, s in enumerate(k["status"]) if s != "OK"]
        relocs = [e["frame"] for e in k["events"] if e["type"] == "relocalization"]
        after = [f - BLACKOUT[1] for f in relocs if f > BLACKOUT[1]]
        result["blackout_frames"] = f"{BLACKOUT[0]}-{BLACKOUT[1]}"
        result["blackout_lost_frames"] = len(lost)
        result["blackout_lost_during"] = sum(BLACKOUT[0] <= i <= BLACKOUT[1] for i in lost)
        result["blackout_relocalized_frames_after"] = min(after) if after else None
        result["blackout_loops_closed"] = sum(e["type"] == "loop" for e in k["events"])
        result["blackout_false_loops"] = _false_loops(k)
        result["blackout_endpoint_err_after_m"] = round(_endpoint(k["after"], k["gt"]), 5)
    return result
