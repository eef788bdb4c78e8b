"""A run's result graded against its sequence's ground truth, after the run.

:func:`evaluate` is the one step the command line (``loopmodel run``, unless ``--no-eval``) and the
API (:func:`loopmodel.evaluate`, and :func:`loopmodel.run` by default) call after
:func:`loopmodel.pipeline.process`, which grades nothing itself. It gives the keys of
``metrics.json`` that compare the estimate with the truth: trajectory errors of the online, final
(and localized) poses, and the final mesh's error against the sequence's ``scene.ply``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from loopmodel.errors import LoopmodelError
from loopmodel.types import Trajectory

if TYPE_CHECKING:
    from loopmodel.io.base import Sequence
    from loopmodel.result import RunResult

logger = logging.getLogger(__name__)


@dataclass
class Evaluation:
    """The numbers of one evaluation (``metrics.json`` keys) and the time it took (seconds)."""

    metrics: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def graded(self) -> bool:
        """Whether anything was compared with ground truth."""
        return bool(self.metrics)


def trajectory_errors(est: Trajectory, gt: Trajectory | None) -> dict[str, float]:
    """ATE RMSE after SE(3) alignment, end-point error and drift of ``est`` against ``gt`` (metres, percent).

    Drift: end-point error with the first poses aligned, percent of the ground-truth path. Empty
    without ground truth, with fewer than 3 poses or when no pose matches (logged).
    """
    if gt is None or len(est) < 3:
        return {}
    from loopmodel.eval.trajectory_metrics import EvalInputError, evaluate_pair

    try:
        ev = evaluate_pair(
            gt.timestamps_ns, gt.world_from_cam, est.timestamps_ns, est.world_from_cam, max_dt_ns=1_000_000
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


def mesh_errors(result: RunResult, sequence: Sequence, references: bool = False) -> dict[str, Any]:
    """The final mesh against the sequence's ground-truth scene (``scene.ply`` attachment).

    ``mesh_err_after_mm`` (mean, and p95) and the completeness of the scanned object (``object.ply``)
    and of its swept part when the sequence has it. With ``references`` also the stripes meshed with
    the ground-truth poses (``gt``: the floor the stripes allow) and with the online poses
    (``before``: before loop closure), two more Poisson meshes. Every trajectory is SE(3)-aligned to
    the truth by its frame positions (as ATE) and the meshes are made in the run's world, where the
    run made its own: open3d's Poisson octree follows the frame's axes, so meshes made in different
    frames would not compare like with like. Empty without a mesh, stripes, scene or ground truth.
    """
    gt = sequence.ground_truth
    names = sequence.attachment_names
    if result.mesh is None or not result.stripes or gt is None or "scene.ply" not in names or len(result.final) < 2:
        return {}
    from loopmodel.geometry.se3 import invert_pose
    from loopmodel.io.mesh_io import mesh_from_bytes
    from loopmodel.mapping.accuracy import mesh_error_metrics
    from loopmodel.mapping.final import aligned_to, reference_from_traj

    run_from_gt = invert_pose(reference_from_traj(result.final, gt))

    def in_run(traj: Trajectory) -> Trajectory:
        return Trajectory(traj.timestamps_ns, run_from_gt[None] @ traj.world_from_cam)

    trajs: dict[str, Trajectory] = {"after": result.final}
    if references:
        trajs = {"gt": in_run(gt), "before": in_run(aligned_to(result.online, gt)), **trajs}
    gt_mesh = mesh_from_bytes(sequence.read_attachment("scene.ply"), "ply", sequence.path)
    gt_mesh.transform(run_from_gt)
    obj = None
    if "object.ply" in names:
        obj = mesh_from_bytes(sequence.read_attachment("object.ply"), "ply", sequence.path)
        obj.transform(run_from_gt)
    cfg = result.config.mapping
    given = {"after": result.mesh}
    return mesh_error_metrics(result.stripes, trajs, gt_mesh, cfg, object_mesh=obj, meshes=given, swept_by=in_run(gt))


def evaluate(result: RunResult, sequence: Sequence, *, mesh_references: bool | None = None) -> Evaluation:
    """Grade ``result`` (of :func:`~loopmodel.pipeline.process` over ``sequence``) against its ground truth.

    Trajectory errors of the final poses (``ate_rmse_m``, ``drift_pct``, ...), of the online ones
    (suffix ``_online``) and of the frames localized in a map (``_localized``); the mesh errors of
    :func:`mesh_errors` (``mesh_references`` defaults to ``eval.mesh_references`` of the run's
    configuration). Nothing without ground truth; a mesh that cannot be measured is logged and left
    out. Changes nothing: the caller merges :attr:`Evaluation.metrics` where it wants them.
    """
    t0 = time.perf_counter()
    gt = sequence.ground_truth
    m: dict[str, Any] = {}
    if gt is not None:
        trajs: list[tuple[str, Trajectory]] = [("_online", result.online), ("", result.final)]
        if result.localized is not None:
            trajs.append(("_localized", result.localized))
        for suffix, traj in trajs:
            m.update({k + suffix: v for k, v in trajectory_errors(traj, gt).items()})
        refs = result.config.eval.mesh_references if mesh_references is None else mesh_references
        try:
            m.update(mesh_errors(result, sequence, refs))
        except LoopmodelError as exc:
            logger.error("no mesh accuracy: %s", exc)
    return Evaluation(m, time.perf_counter() - t0)
