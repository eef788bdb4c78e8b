"""Benchmark ``sessions`` (issue 20): save a map, localize in it, extend it, merge the meshes.

Two simulated sessions of one object (the scene seeded alike, the paths and noise by different
seeds): session A browses 240 deg from azimuth 0, session B the same from azimuth 90 deg, so they
share 150 deg of the object. ``loopmodel.pipeline.run_pipeline`` runs A normally (its results
folder holds the map ``map/``), then B three times: normally (B's own mesh, the normal mode's
``fps``), with ``--mode localize`` in A's map and with ``--mode extend`` (merged map, one mesh
of both sessions' stripes).

* ``localize_first_frame``: frames from B's start to its first relocalization in A's map;
  ``localize_rot_err_deg_median`` / ``localize_pos_err_mm_median``: B's localized frames
  (``trajectory_in_map.tum``) against the truth, after moving A's map into the truth's world
  once by the SE(3) alignment of A's own final trajectory to its ground truth (the relative rotation
  angle and the position difference of the left-camera poses ``truth_from_map @ world_from_cam``
  and the true ``world_from_cam0``). The floor under them: ``map_a_*``, session A's own final poses
  (and its map's keyframes) after that alignment, with ``map_a_rotation_gain`` (A's summed rotation
  over 6-frame steps, over the truth's). ``localize_rel_*``: each localized pose relative to its
  nearest map keyframe against the true relative pose (the localization without the map's error).
* ``merged_mesh_err_mm``: mean distance of the merged mesh's vertices (moved by the same
  alignment) to the scene; ``merged_mesh_err_gt_mm``: the mesh of both sessions' stripes
  placed with ground-truth poses; ``merged_completeness`` / ``best_single_completeness``: the
  share of the object's surface within 2 mm of the merged mesh / of the better single
  session's mesh (each SE(3)-aligned to the truth by its own trajectory).
* ``map_load_s`` / ``map_size_mib``: A's map with its keyframes replicated to 1,000 keyframes,
  saved and loaded (median of 3 loads, the keyframe database built too).
* ``fps`` / ``fps_normal`` (``fps_ratio``): frames per second of tracking time in localization mode
  and in the normal mode on the same session B, in the same bench run. ``single_<a|b>_*``: each
  session's own mesh (aligned by its own trajectory). ``cpu_ms_per_frame`` / ``_normal``: the main
  thread's CPU time per frame (``time.thread_time`` between frames, from the second frame on) in
  the two modes, which the machine's load does not change as it changes wall time.
* KITTI (real, ``configs/kitti.yaml``): a map of frames 0-30 of the shared clip, then localization of frames 20-50
  in it: ``kitti_relocalized_20_30`` of the 11 frames 20-30 in the map's frame,
  ``kitti_ate_rmse_m`` of the localized frames against the ground truth (no alignment: the
  map's world is the clip's first camera, as the ground truth's), ``_inside_map`` of those up to
  the map's last keyframe, and ``kitti_map_ate_rmse_m`` of the mapping run itself (frames 0-30).

Full: 640x480 images (the simulator's default camera), A 240 frames, B 160. ``--quick``: 320x240
images, A 120 frames, B 80, and the same KITTI part. Scans are generated once into
``~/.cache/loopmodel``. ``LOOPMODEL_BENCH_SESSIONS_REFINE=final`` runs the simulated sessions with
``calibration.refine: final`` (``calibration_refine`` says which). A's map then carries its refined
calibration and its keyframe points placed with it, and B (the same rig) localizes with A's refined
calibration (``localize_session_calibration``: ``map`` or ``own``, ``_max_sigma`` the largest
parameter difference); ``localize_own_calibration_*``: B localized in the same map with its own
recorded calibration (``session.same_rig_sigma: 0``).
"""

from __future__ import annotations

import logging
import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from loopmodel.config import Config, config_from_dict
from loopmodel.geometry.align import umeyama_alignment
from loopmodel.geometry.se3 import invert_pose, make_pose, so3_log
from loopmodel.listener import RunListener
from loopmodel.types import Trajectory

ROOT = Path(__file__).resolve().parents[1]
CACHE = Path.home() / ".cache" / "loopmodel"


def _sim_config(seed: int, azimuth_deg: float, frames: int, small: bool) -> Any:
    """Session of the shared object: scene seed 5, path and noise from ``seed``; ``small``: 320x240 images."""
    from loopmodel.sim.generate import resolve_config

    camera = {"width_px": 320, "height_px": 240, "fx_px": 250.0} if small else {}
    base = config_from_dict(
        {
            "simulation": {
                "seed": seed,
                "workers": 1,
                "camera": camera,
                "scene": {"seed": 5},
                "trajectory": {"start_azimuth_deg": azimuth_deg},
            }
        }
    ).simulation
    return resolve_config(base, "browse", {"trajectory": {"frames": frames}}, None, "realistic")


def _ensure(name: str, seed: int, azimuth_deg: float, frames: int, small: bool) -> Path:
    from loopmodel.sim.generate import simulate_scan

    path = CACHE / f"sessions_{name}_{frames}{'_small' if small else ''}.mcap"
    if not path.is_file():
        CACHE.mkdir(parents=True, exist_ok=True)
        print(f"generating {path} ...")
        simulate_scan(_sim_config(seed, azimuth_deg, frames, small), path, Config().sequence.topics, None, "browse")
    return path


class _Window:
    """Frames ``first`` .. ``last`` (inclusive) of a sequence."""

    def __init__(self, seq: Any, first: int, last: int) -> None:
        self._seq, self._first, self._last = seq, first, last

    def __getattr__(self, name: str) -> Any:
        return getattr(self._seq, name)

    def __len__(self) -> int:
        return min(len(self._seq) - 1, self._last) - self._first + 1

    def frames(self) -> Any:
        return (f for i, f in enumerate(self._seq.frames()) if self._first <= i <= self._last)


class _Calibrated:
    """A sequence seen with another calibration."""

    def __init__(self, seq: Any, calibration: Any) -> None:
        self._seq, self.calibration = seq, calibration

    def __getattr__(self, name: str) -> Any:
        return getattr(self._seq, name)

    def __len__(self) -> int:
        return len(self._seq)

    def frames(self) -> Any:
        return self._seq.frames()


class _FrameCpu(RunListener):
    """Main-thread CPU time (ms) of each frame: ``time.thread_time`` between ``on_frame`` calls."""

    def __init__(self) -> None:
        self.ms: list[float] = []
        self._last = time.thread_time()

    def on_frame(self, frame: Any, result: Any, tracks: Any) -> None:
        now = time.thread_time()
        self.ms.append((now - self._last) * 1e3)
        self._last = now


def _run(seq: Any, config: Config, out: Path, name: str, base_map: Any = None, mode: str = "localize") -> Any:
    from loopmodel.io.results import ResultsFolder
    from loopmodel.pipeline import _process_and_write

    cfg = config.model_copy(deep=True)
    cfg.session.mode = mode  # type: ignore[assignment]
    cpu = _FrameCpu()
    res = _process_and_write(ResultsFolder(out, name), seq, cfg, False, base_map=base_map, listeners=[cpu])
    # load-independent: the main thread's CPU per frame (the first frame's includes the start-up)
    res.metrics["bench_cpu_ms_per_frame"] = float(np.mean(cpu.ms[1:])) if len(cpu.ms) > 1 else None
    return res


def _gt_at(seq: Any, stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gt = seq.ground_truth
    idx = {int(t): i for i, t in enumerate(gt.timestamps_ns.tolist())}
    keep = np.array([int(t) in idx for t in stamps], bool)
    return keep, gt.world_from_cam[[idx[int(t)] for t in stamps[keep]]]


def _align(est: Any, seq: Any) -> np.ndarray:
    """``truth_from_run``: SE(3) alignment of a trajectory's positions to the ground truth."""
    keep, gt = _gt_at(seq, est.timestamps_ns)
    R, t, _ = umeyama_alignment(est.world_from_cam[keep][:, :3, 3], gt[:, :3, 3], with_scale=False)
    return make_pose(np.asarray(R), np.asarray(t))


def _pose_errors(est: Any, seq: Any, truth_from_map: np.ndarray) -> tuple[float | None, float | None]:
    if len(est) == 0:
        return None, None
    keep, gt = _gt_at(seq, est.timestamps_ns)
    rot, pos = [], []
    for T, G in zip(est.world_from_cam[keep], gt, strict=True):
        d = invert_pose(G) @ truth_from_map @ T
        rot.append(float(np.degrees(np.linalg.norm(so3_log(d[:3, :3])))))
        pos.append(float(np.linalg.norm(d[:3, 3]) * 1e3))
    return statistics.median(rot), statistics.median(pos)


def _relative_errors(est: Any, seq: Any, smap: Any, seq_map: Any) -> tuple[float | None, float | None]:
    """Median error of each localized pose relative to its nearest map keyframe (deg, mm).

    Compares ``map_kf_from_cam`` of the estimate (map keyframe pose, localized pose) with the true one
    (the keyframe's and the frame's ground truth): the localization alone, without the map's own
    error against the truth.
    """
    if len(est) == 0 or len(smap) == 0:
        return None, None
    keep, gt = _gt_at(seq, est.timestamps_ns)
    keep_m, gt_m = _gt_at(seq_map, smap.timestamps_ns)
    kf_pos = smap.world_from_kf[keep_m][:, :3, 3]
    kf_T = smap.world_from_kf[keep_m]
    rot, pos = [], []
    for T, G in zip(est.world_from_cam[keep], gt, strict=True):
        k = int(np.argmin(np.linalg.norm(kf_pos - T[:3, 3], axis=1)))
        d = invert_pose(invert_pose(gt_m[k]) @ G) @ (invert_pose(kf_T[k]) @ T)
        rot.append(float(np.degrees(np.linalg.norm(so3_log(d[:3, :3])))))
        pos.append(float(np.linalg.norm(d[:3, 3]) * 1e3))
    return statistics.median(rot), statistics.median(pos)


def _rotation_gain(est: Any, seq: Any, step: int = 6) -> float:
    """Summed rotation angle of the estimate over steps of ``step`` frames, over the truth's."""
    keep, gt = _gt_at(seq, est.timestamps_ns)
    E = est.world_from_cam[keep]
    num = den = 0.0
    for i in range(0, len(E) - step, step):
        num += float(np.linalg.norm(so3_log((invert_pose(E[i + step]) @ E[i])[:3, :3])))
        den += float(np.linalg.norm(so3_log((invert_pose(gt[i + step]) @ gt[i])[:3, :3])))
    return num / den if den > 0 else float("nan")


def _mesh_numbers(mesh: Any, truth_from_run: np.ndarray, seq: Any) -> tuple[float, float]:
    """Mean vertex error (mm) and object completeness of a run's mesh moved into the truth's world."""
    import copy

    from loopmodel.io.mesh_io import mesh_from_bytes
    from loopmodel.mapping.accuracy import mesh_accuracy, sample_surface

    scene = mesh_from_bytes(seq.read_attachment("scene.ply"), "ply", seq.path)
    obj = mesh_from_bytes(seq.read_attachment("object.ply"), "ply", seq.path)
    m = copy.deepcopy(mesh)
    m.transform(truth_from_run)
    acc = mesh_accuracy(m, scene, 0.002, reference_points=sample_surface(obj, 200_000))
    return acc.mean_mm, acc.completeness


def _gt_merged_mesh(seqs: list[Any], config: Config) -> Any:
    from loopmodel.io.laser import sequence_stripes
    from loopmodel.mapping.final import posed_stripes_mesh
    from loopmodel.mapping.stripe_map import StripeMap

    stripes, poses = [], []
    for seq in seqs:
        st = list(sequence_stripes(seq, config.mapping))
        smap = StripeMap.from_trajectory(seq.ground_truth, st, config.mapping)
        ok = smap.placed_mask
        kept = [s for s in st if np.asarray(s.points_in_cam).size]
        stripes += [s for s, k in zip(kept, ok, strict=True) if k]
        poses.append(smap.stripe_poses()[ok])
    return posed_stripes_mesh(stripes, np.concatenate(poses), config.mapping)


def _map_load(smap: Any, tmp: Path) -> dict[str, float]:
    from loopmodel.io.map_file import load_session_map, map_size_bytes, save_session_map
    from loopmodel.loop.database import PlaceParams
    from loopmodel.loop.session_map import replicate, select_rows

    copies = int(np.ceil(1000 / len(smap)))
    big = replicate(smap, copies)
    big = select_rows(big, np.arange(1000))
    path = save_session_map(tmp / "map1000", big)
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        loaded = load_session_map(path)
        loaded.database(PlaceParams())
        times.append(time.perf_counter() - t0)
    return {"map_load_s": statistics.median(times), "map_size_mib": map_size_bytes(path) / 2**20}


def _kitti(config: Config, tmp: Path) -> dict[str, Any]:
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from shared_data import SHARED_DATA

    from loopmodel.io.map_file import load_session_map
    from loopmodel.io.sequence import open_sequence

    clip = SHARED_DATA / "kitti_clip"
    if not clip.is_dir():
        return {"kitti": f"skipped: {clip} not found"}
    from loopmodel.config import load_config

    config = load_config(ROOT / "configs" / "kitti.yaml")
    seq = open_sequence(clip, config.sequence)
    a = _run(_Window(seq, 0, 30), config, tmp, "kitti_map")
    smap = load_session_map(a.folder / "map")
    b = _run(_Window(seq, 20, 50), config, tmp, "kitti_loc", smap, "localize")
    status = b.metrics["localization_status"]
    loc = b.localized
    keep, gt = _gt_at(seq, loc.timestamps_ns)
    err = np.linalg.norm(loc.world_from_cam[keep][:, :3, 3] - gt[:, :3, 3], axis=1)
    in_map = loc.timestamps_ns[keep] <= smap.timestamps_ns.max()
    keep_a, gt_a = _gt_at(seq, a.final.timestamps_ns)
    err_a = np.linalg.norm(a.final.world_from_cam[keep_a][:, :3, 3] - gt_a[:, :3, 3], axis=1)
    return {
        "kitti_map_ate_rmse_m": float(np.sqrt(np.mean(err_a**2))),
        "kitti_ate_rmse_m_inside_map": float(np.sqrt(np.mean(err[in_map] ** 2))) if in_map.any() else None,
        "kitti_map_keyframes": len(smap),
        "kitti_relocalized_20_30": sum(s == "MAP" for s in status[:11]),
        "kitti_localized_frames": int(keep.sum()),
        "kitti_ate_rmse_m": float(np.sqrt(np.mean(err**2))) if err.size else None,
        "kitti_localize_first_frame": b.metrics.get("map_first_localized_frame"),
    }


def run(quick: bool = False) -> dict[str, Any]:
    logging.basicConfig(level=logging.WARNING)
    from loopmodel.io.sequence import open_sequence

    frames_a, frames_b = (120, 80) if quick else (240, 160)
    path_a = _ensure("A", 11, 0.0, frames_a, quick)
    path_b = _ensure("B", 12, 90.0, frames_b, quick)
    config = Config()
    # issue 31: the simulated sessions with the self-calibration (none|final; the KITTI part keeps kitti.yaml)
    refine = os.environ.get("LOOPMODEL_BENCH_SESSIONS_REFINE", config.calibration.refine)
    config.calibration.refine = refine  # type: ignore[assignment]
    seq_a, seq_b = open_sequence(path_a), open_sequence(path_b)
    out: dict[str, Any] = {"dataset": f"realistic simulator browse sessions {path_a.name}, {path_b.name}; KITTI clip"}
    out["calibration_refine"] = refine
    with tempfile.TemporaryDirectory() as tmpd:
        tmp = Path(tmpd)
        ra = _run(seq_a, config, tmp, "A")
        from loopmodel.io.map_file import load_session_map

        map_a = load_session_map(ra.folder / "map")
        truth_from_a = _align(ra.final, seq_a)
        rb = _run(seq_b, config, tmp, "B")
        loc = _run(seq_b, config, tmp, "B_localize", map_a, "localize")
        rot, pos = _pose_errors(loc.localized, seq_b, truth_from_a)
        rel_rot, rel_pos = _relative_errors(loc.localized, seq_b, map_a, seq_a)
        a_rot, a_pos = _pose_errors(ra.final, seq_a, truth_from_a)
        a_kf = Trajectory(map_a.timestamps_ns, map_a.world_from_kf)
        akf_rot, akf_pos = _pose_errors(a_kf, seq_a, truth_from_a)
        first = loc.metrics.get("map_first_localized_frame")
        out.update(
            {
                "localize_first_frame": first,
                "localize_rot_err_deg_median": rot,
                "localize_pos_err_mm_median": pos,
                # the floor: session A's own poses against the truth after the same alignment
                "map_a_rot_err_deg_median": a_rot,
                "map_a_pos_err_mm_median": a_pos,
                "map_a_keyframe_rot_err_deg_median": akf_rot,
                "map_a_keyframe_pos_err_mm_median": akf_pos,
                "map_a_drift_pct": ra.metrics.get("drift_pct"),
                "map_a_rotation_gain": _rotation_gain(ra.final, seq_a),
                "localize_rel_rot_err_deg_median": rel_rot,
                "localize_rel_pos_err_mm_median": rel_pos,
                "localized_frames": loc.metrics.get("localized_frames"),
                "frames_b": len(loc.frames),
                "fps": loc.metrics.get("fps"),
                "fps_normal": rb.metrics.get("fps"),
            }
        )
        if out["fps"] and out["fps_normal"]:
            out["fps_ratio"] = out["fps"] / out["fps_normal"]
        out["cpu_ms_per_frame"] = loc.metrics.get("bench_cpu_ms_per_frame")
        out["localize_session_calibration"] = loc.metrics.get("session_calibration")
        out["localize_session_calibration_max_sigma"] = loc.metrics.get("session_calibration_max_sigma")
        if map_a.refined_calibration is not None:
            # issue 31 item 4: B (the same rig) starts from A's refined calibration; here B with its own
            # recorded one instead (session.same_rig_sigma 0), in the same map
            own = config.model_copy(deep=True)
            own.session.same_rig_sigma = 0.0
            loc_o = _run(seq_b, own, tmp, "B_localize_own", map_a, "localize")
            rot_o, pos_o = _pose_errors(loc_o.localized, seq_b, truth_from_a)
            out["localize_own_calibration_rot_err_deg_median"] = rot_o
            out["localize_own_calibration_pos_err_mm_median"] = pos_o
        out["cpu_ms_per_frame_normal"] = rb.metrics.get("bench_cpu_ms_per_frame")
        ext = _run(seq_b, config, tmp, "B_extend", map_a, "extend")
        gt_mesh = _gt_merged_mesh([seq_a, seq_b], config)
        out["merged_mesh_err_gt_mm"], out["merged_completeness_gt"] = _mesh_numbers(gt_mesh, np.eye(4), seq_a)
        if ext.metrics.get("merged") and ext.mesh is not None:
            out["merged_mesh_err_mm"], out["merged_completeness"] = _mesh_numbers(ext.mesh, truth_from_a, seq_a)
            out["merge_links"] = ext.metrics.get("merge_links")
        else:
            out["merged_mesh_err_mm"], out["merged_completeness"] = None, None
        singles = []
        for name, r, s in (("a", ra, seq_a), ("b", rb, seq_b)):
            if r.mesh is not None:
                err, comp = _mesh_numbers(r.mesh, _align(r.final, s), s)
                out[f"single_{name}_mesh_err_mm"], out[f"single_{name}_completeness"] = err, comp
                singles.append(comp)
        out["best_single_completeness"] = max(singles) if singles else None
        out.update(_map_load(map_a, tmp))
        out.update(_kitti(config, tmp))
    return out
