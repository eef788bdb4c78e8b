"""The mapping steps that read the sequence.

Its laser stripes for the live mapping and at the end of the run, and the mesh of them placed with
the final trajectory, with its accuracy when the sequence carries a ground-truth scene.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import MappingConfig
from loopmodel.errors import LoopmodelError
from loopmodel.io.base import Sequence
from loopmodel.mapping.extraction import sequence_stripe_count, sequence_stripes
from loopmodel.types import StereoCalibration, StripeAnchors, StripeProfile, Trajectory

logger = logging.getLogger(__name__)


def live_stripes(sequence: Sequence, config: MappingConfig) -> Iterator[StripeProfile]:
    """The sequence's laser profiles in time order, for the live mapping (none without)."""
    return sequence_stripes(sequence, config) if sequence_stripe_count(sequence) else iter(())


def run_stripes(
    sequence: Sequence, last_ns: int | None, config: MappingConfig, calibration: StereoCalibration | None = None
) -> list[StripeProfile]:
    """The sequence's laser profiles up to ``last_ns`` (the last processed frame; sensor frame, metres).

    Laser images are triangulated with ``calibration``'s left camera when given (a refined one,
    issue 31), else the sequence's.

    None without a processed frame or without profiles. A reader error is logged and gives none (the
    trajectories matter more than the stripes).
    """
    if last_ns is None or sequence_stripe_count(sequence) == 0:
        return []
    try:
        return [s for s in sequence_stripes(sequence, config, calibration) if s.timestamp_ns <= last_ns]
    except LoopmodelError as exc:
        logger.error("laser stripes not written: %s", exc)
        return []


def reference_from_traj(traj: Trajectory, reference: Trajectory) -> NDArray[np.float64]:
    """The 4x4 SE(3) transform that best aligns ``traj``'s positions to ``reference`` (identity when it cannot).

    At common timestamps (exact match); metres.
    """
    from loopmodel.geometry.align import umeyama_alignment
    from loopmodel.geometry.se3 import make_pose

    _, ia, ib = np.intersect1d(traj.timestamps_ns, reference.timestamps_ns, return_indices=True)
    if ia.size < 3:
        return np.eye(4)
    R, t, _s = umeyama_alignment(traj.positions_m[ia], reference.positions_m[ib])
    return make_pose(R, t)


def aligned_to(traj: Trajectory, reference: Trajectory) -> Trajectory:
    """``traj`` moved by the SE(3) transform that best aligns its positions to ``reference``.

    At common timestamps (exact match).
    """
    T = reference_from_traj(traj, reference)
    return Trajectory(traj.timestamps_ns, T[None] @ traj.world_from_cam)


def _mesh_errors(
    sequence: Sequence,
    stripes: list[StripeProfile],
    online: Trajectory,
    final: Trajectory,
    config: MappingConfig,
    final_surface: Any = None,
) -> dict[str, Any]:
    """With a ground-truth scene (``scene.ply`` attachment) and poses.

    The mesh error with ground-truth, online (before loop closure) and final (after) poses, both
    SE(3)-aligned to the truth by their frame positions, and the completeness of the scanned object
    (``object.ply``) and of its swept part when the sequence has it. ``final_surface``: the run's
    mesh of ``stripes`` placed with ``final`` (run world frame); "after" measures that mesh instead
    of meshing the stripes a second time.
    """
    from loopmodel.io.mesh_io import mesh_from_bytes
    from loopmodel.mapping.accuracy import mesh_error_metrics

    names = sequence.attachment_names
    gt = sequence.ground_truth
    if "scene.ply" not in names or gt is None:
        return {}
    from loopmodel.geometry.se3 import invert_pose

    gt_mesh = mesh_from_bytes(sequence.read_attachment("scene.ply"), "ply", sequence.path)
    # the run's world is its first keyframe. The online trajectory is SE(3)-aligned to the truth
    # by the frame positions (as ATE), and so is the final one: every mesh is then made in the
    # run's world, where the run made its own mesh ("after"), with the truth moved there. open3d's
    # Poisson octree follows the frame's axes (its depth comes from the bounding box), so meshes
    # made in different frames would differ in resolution (the demo orbit: 1.85 mm cells in the
    # run's world, 1.08 mm in the truth's) and not compare like with like.
    run_from_gt = invert_pose(reference_from_traj(final, gt))

    def in_run(traj: Trajectory) -> Trajectory:
        return Trajectory(traj.timestamps_ns, run_from_gt[None] @ traj.world_from_cam)

    trajs = {"gt": in_run(gt), "before": in_run(aligned_to(online, gt)), "after": final}
    gt_mesh.transform(run_from_gt)
    given: dict[str, Any] = {"after": final_surface} if final_surface is not None else {}
    obj = None
    if "object.ply" in names:
        obj = mesh_from_bytes(sequence.read_attachment("object.ply"), "ply", sequence.path)
        obj.transform(run_from_gt)
    return mesh_error_metrics(stripes, trajs, gt_mesh, config, object_mesh=obj, meshes=given)


def final_mesh(
    sequence: Sequence, stripes: list[StripeProfile], online: Trajectory, final: Trajectory, config: MappingConfig
) -> tuple[Any, dict[str, Any]]:
    """The mesh of ``stripes`` placed with ``final`` (open3d, world frame) and its metrics.

    Metrics: vertex count, accuracy against the sequence's ground truth. (None, {}) when meshing is
    off, there is nothing to mesh, or it fails (logged: a run without a mesh still has its
    trajectories).
    """
    if not stripes or not config.write_mesh or len(final) < 2:
        return None, {}
    from loopmodel.mapping.stripe_map import StripeMap

    try:
        smap = StripeMap.from_trajectory(final, stripes, config)
        smap.check_nonempty()
        surface = smap.mesh()
    except LoopmodelError as exc:
        logger.error("mesh not written: %s", exc)
        return None, {}
    out: dict[str, Any] = {"mesh_vertices": len(surface.vertices)}
    try:
        out.update(_mesh_errors(sequence, stripes, online, final, config, final_surface=surface))
    except LoopmodelError as exc:
        logger.error("no mesh accuracy: %s", exc)
    return surface, out


def anchor_stripes(
    stripes: list[StripeProfile],
    final: Trajectory,
    frame_times_ns: NDArray[np.int64],
    frame_keyframes: NDArray[np.int64],
    world_from_kf: Mapping[int, NDArray[np.float64]],
    config: MappingConfig,
) -> StripeAnchors:
    """Each stripe placed with ``final``, anchored to the keyframe of its nearest tracked frame.

    ``frame_times_ns`` / ``frame_keyframes``: the tracked frames and their keyframe ids;
    ``kf_from_cam`` of a stripe is its sensor pose in that keyframe's frame (metres). Stripes the
    trajectory does not reach are left out.
    """
    from loopmodel.geometry.se3 import invert_pose
    from loopmodel.mapping.stripe_map import StripeMap

    none = StripeAnchors([], np.zeros(0, np.int64), np.zeros((0, 4, 4)))
    if not stripes or len(final) < 2 or frame_times_ns.size == 0:
        return none
    smap = StripeMap.from_trajectory(final, stripes, config)
    kept = [s for s in stripes if np.asarray(s.points_in_cam).size]  # as from_trajectory keeps them
    placed = smap.placed_mask
    poses = smap.stripe_poses()
    order = np.argsort(frame_times_ns)
    times, kfs = frame_times_ns[order], frame_keyframes[order]
    out_s: list[StripeProfile] = []
    out_k: list[int] = []
    out_T: list[NDArray[np.float64]] = []
    for s, ok, T in zip(kept, placed, poses, strict=True):
        if not ok:
            continue
        j = int(np.clip(np.searchsorted(times, s.timestamp_ns), 1, times.size - 1)) if times.size > 1 else 0
        if times.size > 1 and abs(times[j - 1] - s.timestamp_ns) < abs(times[j] - s.timestamp_ns):
            j -= 1
        k = int(kfs[j])
        if k not in world_from_kf:
            continue
        out_s.append(s)
        out_k.append(k)
        out_T.append(invert_pose(np.asarray(world_from_kf[k])) @ T)
    if not out_s:
        return none
    return StripeAnchors(out_s, np.array(out_k, np.int64), np.stack(out_T))


def posed_stripes_mesh(stripes: list[StripeProfile], world_from_cam: NDArray[np.float64], config: MappingConfig) -> Any:
    """The mesh (open3d, world frame) of stripes placed at their own sensor poses (S, 4, 4); None without.

    Stripes of several sessions may share times: each gets its own pose.
    """
    from loopmodel.mapping.stripe_map import StripeMap

    keep = [i for i, s in enumerate(stripes) if np.asarray(s.points_in_cam).size]
    if len(keep) < 2:
        return None
    stamps = np.arange(len(keep), dtype=np.int64) * 1000
    traj = Trajectory(stamps, world_from_cam[keep])
    retimed = [StripeProfile(int(t), stripes[i].points_in_cam) for t, i in zip(stamps, keep, strict=True)]
    try:
        smap = StripeMap.from_trajectory(traj, retimed, config)
        smap.check_nonempty()
        return smap.mesh()
    except LoopmodelError as exc:
        logger.error("no mesh of the map: %s", exc)
        return None
