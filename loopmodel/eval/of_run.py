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


@dataclass
class MeshTruth:
    """The ground truth the mesh errors need, in the run's world: made before the run's mesh is there.

    ``run_from_gt`` (4x4) takes the truth into the world of ``final`` (the trajectory it was aligned
    with); ``scene`` the ground-truth scene mesh there, ``object_truth`` the scanned object's samples
    (:func:`~loopmodel.mapping.accuracy.object_truth_of`; None without ``object.ply``); ``to_scene``
    the distance to ``scene`` (:class:`~loopmodel.mapping.accuracy.SurfaceDistance`, its search
    structure built here; None for a scene without triangles).
    """

    final: Trajectory
    stripes: list[Any]
    run_from_gt: Any
    scene: Any
    object_truth: Any
    in_run: Any
    to_scene: Any = None


def mesh_truth(result: RunResult, sequence: Sequence) -> MeshTruth | None:
    """:class:`MeshTruth` for ``result``'s final trajectory and stripes (None when no mesh error can be made)."""
    gt = sequence.ground_truth
    names = sequence.attachment_names
    if not result.stripes or gt is None or "scene.ply" not in names or len(result.final) < 2:
        return None
    from loopmodel.geometry.se3 import invert_pose
    from loopmodel.io.mesh_io import mesh_from_bytes
    from loopmodel.mapping.accuracy import SurfaceDistance, object_truth_of
    from loopmodel.mapping.final import reference_from_traj

    run_from_gt = invert_pose(reference_from_traj(result.final, gt))

    def in_run(traj: Trajectory) -> Trajectory:
        return Trajectory(traj.timestamps_ns, run_from_gt[None] @ traj.world_from_cam)

    gt_mesh = mesh_from_bytes(sequence.read_attachment("scene.ply"), "ply", sequence.path)
    gt_mesh.transform(run_from_gt)
    obj = None
    if "object.ply" in names:
        obj_mesh = mesh_from_bytes(sequence.read_attachment("object.ply"), "ply", sequence.path)
        obj_mesh.transform(run_from_gt)
        obj = object_truth_of(obj_mesh, result.stripes, in_run(gt), result.config.mapping)
    # fin15 (issue 32): the scene's search structure built here, while the run's mesh is made, not after
    to_scene = SurfaceDistance(gt_mesh, build=True) if len(gt_mesh.triangles) else None
    return MeshTruth(result.final, result.stripes, run_from_gt, gt_mesh, obj, in_run, to_scene)


def mesh_errors(
    result: RunResult, sequence: Sequence, references: bool = False, truth: MeshTruth | None = None
) -> dict[str, Any]:
    """The final mesh against the sequence's ground-truth scene (``scene.ply`` attachment).

    ``mesh_err_after_mm`` (mean, and p95) and the completeness of the scanned object (``object.ply``)
    and of its swept part when the sequence has it. With ``references`` also the stripes meshed with
    the ground-truth poses (``gt``: the floor the stripes allow) and with the online poses
    (``before``: before loop closure), two more Poisson meshes. Every trajectory is SE(3)-aligned to
    the truth by its frame positions (as ATE) and the meshes are made in the run's world, where the
    run made its own: open3d's Poisson octree follows the frame's axes, so meshes made in different
    frames would not compare like with like. Empty without a mesh, stripes, scene or ground truth.
    ``truth``: :func:`mesh_truth` of this result made beforehand (e.g. while the mesh was made).
    """
    gt = sequence.ground_truth
    if result.mesh is None or gt is None:
        return {}
    if truth is None or truth.final is not result.final or truth.stripes is not result.stripes:
        truth = mesh_truth(result, sequence)
    if truth is None:
        return {}
    from loopmodel.mapping.accuracy import mesh_error_metrics
    from loopmodel.mapping.final import aligned_to

    trajs: dict[str, Trajectory] = {"after": result.final}
    if references:
        trajs = {"gt": truth.in_run(gt), "before": truth.in_run(aligned_to(result.online, gt)), **trajs}
    cfg = result.config.mapping
    given = {"after": result.mesh}
    return mesh_error_metrics(
        result.stripes, trajs, truth.scene, cfg, meshes=given, swept_by=truth.in_run(gt),
        object_truth=truth.object_truth, to_gt=truth.to_scene,
    )


@dataclass
class Prepared:
    """What :func:`evaluate` can make of a result before its mesh is there (:func:`prepare`)."""

    trajectory_metrics: dict[str, Any]
    truth: MeshTruth | None
    seconds: float = 0.0
    #: the result's trajectories it was made of (``online``, ``final``, ``localized``)
    of: tuple[Any, ...] = ()

    def holds_for(self, result: RunResult) -> bool:
        """Whether ``result`` still has the trajectories this was made of."""
        now = (result.online, result.final, result.localized)
        return len(self.of) == 3 and all(a is b for a, b in zip(self.of, now, strict=True))


def trajectory_metrics(result: RunResult, sequence: Sequence) -> dict[str, Any]:
    """The trajectory errors of :func:`evaluate` (final, ``_online``, ``_localized``)."""
    gt = sequence.ground_truth
    m: dict[str, Any] = {}
    if gt is None:
        return m
    trajs: list[tuple[str, Trajectory]] = [("_online", result.online), ("", result.final)]
    if result.localized is not None:
        trajs.append(("_localized", result.localized))
    for suffix, traj in trajs:
        m.update({k + suffix: v for k, v in trajectory_errors(traj, gt).items()})
    return m


def prepare(result: RunResult, sequence: Sequence) -> Prepared:
    """The evaluation's part that needs no mesh: trajectory errors and the mesh's ground truth (finish11).

    For a caller with time while the run's mesh is made (:func:`loopmodel.pipeline.process`'s
    ``beside_mesh``); :func:`evaluate` with it gives what it gives without.
    """
    t0 = time.perf_counter()
    truth = None
    try:
        truth = mesh_truth(result, sequence) if result.config.mapping.write_mesh else None
    except LoopmodelError as exc:
        logger.error("no mesh accuracy: %s", exc)
    of = (result.online, result.final, result.localized)
    return Prepared(trajectory_metrics(result, sequence), truth, time.perf_counter() - t0, of)


def evaluate(
    result: RunResult, sequence: Sequence, *, mesh_references: bool | None = None, prepared: Prepared | None = None
) -> Evaluation:
    """Grade ``result`` (of :func:`~loopmodel.pipeline.process` over ``sequence``) against its ground truth.

    Trajectory errors of the final poses (``ate_rmse_m``, ``drift_pct``, ...), of the online ones
    (suffix ``_online``) and of the frames localized in a map (``_localized``); the mesh errors of
    :func:`mesh_errors` (``mesh_references`` defaults to ``eval.mesh_references`` of the run's
    configuration). Nothing without ground truth; a mesh that cannot be measured is logged and left
    out. Changes nothing: the caller merges :attr:`Evaluation.metrics` where it wants them.
    ``prepared``: :func:`prepare` of this result (its trajectories as they are now), made earlier;
    :attr:`Evaluation.seconds` then counts only what is left.
    """
    t0 = time.perf_counter()
    gt = sequence.ground_truth
    m: dict[str, Any] = {}
    if prepared is not None and not prepared.holds_for(result):
        prepared = None
    if gt is not None:
        m.update(prepared.trajectory_metrics if prepared is not None else trajectory_metrics(result, sequence))
        refs = result.config.eval.mesh_references if mesh_references is None else mesh_references
        try:
            m.update(mesh_errors(result, sequence, refs, prepared.truth if prepared is not None else None))
        except LoopmodelError as exc:
            logger.error("no mesh accuracy: %s", exc)
    return Evaluation(m, time.perf_counter() - t0)
