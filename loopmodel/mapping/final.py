"""The mapping steps at the end of a run.

The mesh of the run's laser stripes placed with the final trajectory, the stripes anchored to
keyframes for the session map, the mesh of stripes at their own poses (a merged map), and the
alignment of a trajectory to a reference (used by the evaluation).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import MappingConfig
from loopmodel.errors import LoopmodelError
from loopmodel.mapping.live import MeshArrays, mesh_of_arrays
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

    Made here (:func:`start_final_mesh` without a worker). (None, {}) when meshing is off, there is
    nothing to mesh, or it fails (logged: a run without a mesh still has its trajectories).
    """
    return start_final_mesh(stripes, final, config).result()


def load_mesh_modules() -> None:
    """open3d, the meshing module and the sdf kernels loaded in this process (the final mesh's pool process).

    Without open3d's plotly viewer (:func:`~loopmodel.open3d_import.without_plotly_viewer`: 0.8 of its
    1.85 s CPU in the laser-extraction process that makes the final mesh; fin19) when open3d is not loaded yet.
    """
    from loopmodel.open3d_import import without_plotly_viewer

    without_plotly_viewer()
    from loopmodel.mapping.meshing import preload_kernels  # open3d's import, before the mesh is asked for

    preload_kernels()


def _mesh_worker_start() -> None:
    """The final mesh's process: Ctrl-C is the run's (it ends the finish); open3d loaded up front."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    load_mesh_modules()


def mesh_arrays(
    points_w: NDArray[np.float64], sensors_w: NDArray[np.float64], config: MappingConfig
) -> tuple[MeshArrays | None, str, float, float]:
    """:func:`~loopmodel.mapping.meshing.mesh_from_points` as arrays (for a worker process).

    Returns the mesh (None when no surface comes out), the reason when there is none, and the
    meshing time and its process's CPU time in it (s). World frame, metres.
    """
    from loopmodel.mapping.meshing import mesh_from_points

    t0, c0 = time.perf_counter(), time.process_time()
    try:
        m = mesh_from_points(points_w, sensors_w, config)
    except LoopmodelError as exc:
        return None, str(exc), time.perf_counter() - t0, time.process_time() - c0
    arrays = (np.asarray(m.vertices), np.asarray(m.triangles), np.asarray(m.vertex_normals))
    return arrays, "", time.perf_counter() - t0, time.process_time() - c0


class FinalMeshWorker:
    """A process that makes the final mesh, started before the mesh is asked for.

    Issue 32: open3d's Poisson reconstruction holds the interpreter for 1.6-2.2 s on the 150-frame
    orbit; in this process it runs while the run's own process makes the session map. The pipeline
    gives it the live mesh's worker process when that is idle at the last frame (open3d already
    loaded there); without one it starts its own (spawned: 1.5 s CPU before it can mesh).
    """

    def __init__(self, pool: Any = None) -> None:
        """``pool``: an idle one-process pool whose process has open3d loaded (the live mesh's), else a new one."""
        from concurrent.futures import ProcessPoolExecutor

        if pool is None:
            ctx = mp.get_context("spawn")
            pool = ProcessPoolExecutor(1, mp_context=ctx, initializer=_mesh_worker_start)
            pool.submit(int, 0)  # the process starts now
        self._pool: Any = pool

    def submit(self, points_w: NDArray[np.float64], sensors_w: NDArray[np.float64], config: MappingConfig) -> Any:
        """The future of :func:`mesh_arrays` of these points (None when the process is gone)."""
        if self._pool is None:
            return None
        try:
            return self._pool.submit(mesh_arrays, points_w, sensors_w, config)
        except RuntimeError:  # a broken or shut-down pool: the caller meshes itself
            return None

    def close(self) -> None:
        """End the process (at once: an unfinished mesh is dropped)."""
        pool, self._pool = self._pool, None
        end_pool(pool)


def end_pool(pool: Any) -> None:
    """Shut a process pool down at once: queued work dropped, its processes ended (a running job too)."""
    if pool is None:
        return
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.terminate()


class FinalMeshJob:
    """The final mesh being made (in a :class:`FinalMeshWorker`, or here when there is none).

    :meth:`result` gives the mesh (open3d, world frame) and its metrics; a worker that died is
    replaced by meshing here (logged).
    """

    def __init__(
        self,
        points_w: NDArray[np.float64] | None,
        sensors_w: NDArray[np.float64] | None,
        config: MappingConfig,
        worker: FinalMeshWorker | None,
    ) -> None:
        self._points, self._sensors, self._config = points_w, sensors_w, config
        self._future = None
        if points_w is not None and sensors_w is not None and worker is not None:
            self._future = worker.submit(points_w, sensors_w, config)

    @property
    def points_w(self) -> NDArray[np.float64] | None:
        """The stripe points being meshed (world, metres; None without)."""
        return self._points

    def cancel(self) -> None:
        """Not wanted any more: dropped if its process has not begun it."""
        if self._future is not None:
            self._future.cancel()

    def result(self) -> tuple[Any, dict[str, Any]]:
        """(mesh, metrics), or (None, {}) without stripes or when no surface comes out (logged).

        Metrics: ``mesh_vertices``, ``final_mesh_s`` (its time where it was made), ``final_mesh_cpu_s``
        (that process's CPU time in it: not in the run's ``finish_cpu_s`` when a worker made it) and
        ``final_mesh_in_worker`` (whether the worker made it).
        """
        if self._points is None or self._sensors is None:
            return None, {}
        out: tuple[MeshArrays | None, str, float, float] | None = None
        in_worker = False
        if self._future is not None:
            try:
                out = self._future.result()
                in_worker = True
            except Exception as exc:  # noqa: BLE001 - the process died (a Poisson crash): mesh here
                logger.warning("final mesh worker failed (%s): meshing here", exc or type(exc).__name__)
        if out is None:
            out = mesh_arrays(self._points, self._sensors, self._config)
        arrays, reason, seconds, cpu_s = out
        if arrays is None:
            logger.error("mesh not written: %s", reason)
            return None, {}
        metrics = {
            "mesh_vertices": int(arrays[0].shape[0]), "final_mesh_s": seconds, "final_mesh_cpu_s": cpu_s,
            "final_mesh_in_worker": in_worker,
        }
        return mesh_of_arrays(arrays), metrics


def start_final_mesh(
    stripes: list[StripeProfile], final: Trajectory, config: MappingConfig, worker: FinalMeshWorker | None = None
) -> FinalMeshJob:
    """The mesh of ``stripes`` placed with ``final`` started (in ``worker`` when given; :func:`final_mesh`'s result).

    The stripes are placed here, and the points handed over as values.
    """
    if not stripes or not config.write_mesh or len(final) < 2:
        return FinalMeshJob(None, None, config, None)
    from loopmodel.mapping.stripe_map import StripeMap

    try:
        smap = StripeMap.from_trajectory(final, stripes, config)
        smap.check_nonempty()
    except LoopmodelError as exc:
        logger.error("mesh not written: %s", exc)
        return FinalMeshJob(None, None, config, None)
    return FinalMeshJob(smap.world_points(), smap.sensor_positions(), config, worker)


class VertexMover:
    """Moves mesh vertices as nearby stripe points moved (world, metres).

    A vertex moves by the inverse-distance weighted mean move of its ``k`` nearest points of
    ``points_from_w`` (the points' positions when the mesh was made; ``points_to_w`` the same
    points, row for row, placed again). For moves small beside the stripes' spacing and smooth
    along the surface (the frames between keyframes re-solved after the mesh was started: the
    600-frame sample 0.36 mm median, 2.7 mm at most, finish11) the moved mesh stands for the mesh
    of the moved points (the mesh error against the scene within its run-to-run spread). The
    search tree is built here, before a mesh is there to move.
    """

    def __init__(self, points_from_w: NDArray[np.float64], points_to_w: NDArray[np.float64], k: int = 8) -> None:
        from scipy.spatial import cKDTree

        src = np.asarray(points_from_w, np.float64).reshape(-1, 3)
        self.move_w = np.asarray(points_to_w, np.float64).reshape(-1, 3) - src
        self.k = int(min(k, src.shape[0]))
        self.tree = cKDTree(src) if src.shape[0] else None

    def moved(self, vertices_w: NDArray[np.float64]) -> NDArray[np.float64]:
        """``vertices_w`` (V x 3) moved."""
        v = np.asarray(vertices_w, np.float64).reshape(-1, 3)
        if v.shape[0] == 0 or self.tree is None:
            return v.copy()
        dist, idx = self.tree.query(v, k=self.k, workers=-1)
        dist, idx = dist.reshape(v.shape[0], self.k), idx.reshape(v.shape[0], self.k)
        w = 1.0 / np.maximum(dist, 1e-6)
        return np.asarray(v + np.einsum("nk,nkj->nj", w, self.move_w[idx]) / w.sum(axis=1, keepdims=True), np.float64)


class MovedMeshJob:
    """A final mesh started before the last change of the frame poses, moved to the final poses when taken.

    Issue 32 (finish11): the mesh of the stripes placed with the keyframes refined but the frames
    between them not yet re-solved starts in the mesh's process while this one re-solves them;
    :meth:`result` moves its vertices as the stripe points moved (:class:`VertexMover`). When
    the two placements do not hold the same points (stripes the new trajectory no longer reaches),
    the mesh of the final placement is made instead (here, or in ``worker``).
    """

    def __init__(
        self,
        stripes: list[StripeProfile],
        first: Trajectory,
        config: MappingConfig,
        worker: FinalMeshWorker | None = None,
    ) -> None:
        """The mesh of ``stripes`` placed with ``first`` started in ``worker``'s process (:func:`start_final_mesh`)."""
        from loopmodel.mapping.stripe_map import StripeMap

        self._stripes, self._config, self._worker = stripes, config, worker
        self._to: Trajectory | None = None
        self._placed: NDArray[np.bool_] | None = None
        job = FinalMeshJob(None, None, config, None)
        if stripes and config.write_mesh and len(first) >= 2:
            try:
                smap = StripeMap.from_trajectory(first, stripes, config)
                smap.check_nonempty()
                self._placed = smap.placed_mask
                job = FinalMeshJob(smap.world_points(), smap.sensor_positions(), config, worker)
            except LoopmodelError as exc:
                logger.error("mesh not written: %s", exc)
        self._job = job

    @property
    def stripes(self) -> list[StripeProfile]:
        """The stripes being meshed (the mesh follows these, as later placed)."""
        return self._stripes

    def moved_to(self, final: Trajectory) -> MovedMeshJob:
        """This job with the trajectory the mesh is to follow (the final one)."""
        self._to = final
        return self

    def result(self) -> tuple[Any, dict[str, Any]]:
        """(mesh, metrics) as :meth:`FinalMeshJob.result`, the mesh moved to the final trajectory.

        Metrics add ``final_mesh_moved``, ``final_mesh_move_mm_max`` and ``final_mesh_move_s``.
        """
        if self._to is None or self._job.points_w is None:
            return self._job.result()
        from loopmodel.mapping.stripe_map import StripeMap

        t0 = time.perf_counter()
        try:
            smap = StripeMap.from_trajectory(self._to, self._stripes, self._config)
            smap.check_nonempty()
        except LoopmodelError as exc:
            logger.error("mesh not written: %s", exc)
            return None, {}
        to_w = smap.world_points()
        if self._placed is None or not np.array_equal(smap.placed_mask, self._placed):
            logger.info("final mesh made again: the re-solved frames place other stripe points")
            self._job.cancel()
            return FinalMeshJob(to_w, smap.sensor_positions(), self._config, self._worker).result()
        mover = VertexMover(self._job.points_w, to_w)  # while the mesh is made
        t_wait = time.perf_counter()
        mesh, metrics = self._job.result()
        if mesh is None:
            return mesh, metrics
        t1 = time.perf_counter()
        v = np.array(mesh.vertices)  # a copy: open3d's buffer is replaced below
        moved = mover.moved(v)
        import open3d as o3d

        mesh.vertices = o3d.utility.Vector3dVector(moved)
        mesh.compute_vertex_normals()
        metrics["final_mesh_moved"] = True
        metrics["final_mesh_move_mm_max"] = 1e3 * float(np.max(np.linalg.norm(moved - v, axis=1))) if v.size else 0.0
        metrics["final_mesh_move_s"] = (t_wait - t0) + (time.perf_counter() - t1)
        return mesh, metrics


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
    kept = [s for s in stripes if np.asarray(s.points_in_cam).size]  # as from_trajectory keeps them
    # a stripe's pose depends on its time only: one point each is placed, not every point (finish9)
    ones = [StripeProfile(s.timestamp_ns, np.asarray(s.points_in_cam)[:1]) for s in kept]
    smap = StripeMap.from_trajectory(final, ones, config)
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
