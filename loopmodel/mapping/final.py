"""The mapping steps at the end of a run.

The mesh of the run's laser stripes placed with the final trajectory, the stripes anchored to
keyframes for the session map, the mesh of stripes at their own poses (a merged map), and the
alignment of a trajectory to a reference (used by the evaluation).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import MappingConfig
from loopmodel.errors import LoopmodelError
from loopmodel.types import StripeAnchors, StripeProfile, Trajectory

logger = logging.getLogger(__name__)


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


def final_mesh(stripes: list[StripeProfile], final: Trajectory, config: MappingConfig) -> tuple[Any, dict[str, Any]]:
    """The mesh of ``stripes`` placed with ``final`` (open3d, world frame) and its metrics (vertex count).

    (None, {}) when meshing is off, there is nothing to mesh, or it fails (logged: a run without a
    mesh still has its trajectories).
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
    return surface, {"mesh_vertices": len(surface.vertices)}


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
