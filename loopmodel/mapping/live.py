"""The pipeline's live mapping stage.

Laser stripes fed to the run's :class:`StripeMap` as frames arrive, and the chunked live mesh
re-meshed in a worker (a process by default) on a thread of lowered scheduling priority.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np

from loopmodel.config import MappingConfig
from loopmodel.errors import LoopmodelError
from loopmodel.mapping.stripe_map import StripeMap
from loopmodel.priority import low_priority_pool
from loopmodel.types import StripeProfile

logger = logging.getLogger(__name__)


BlockKey = tuple[int, int, int]
#: a block's mesh as arrays: vertices (V, 3) m, triangles (T, 3) int, vertex normals (V, 3)
MeshArrays = tuple[np.ndarray, np.ndarray, np.ndarray]


def _worker_start() -> None:
    """The meshing process: Ctrl-C is the run's (it stops between frames); open3d loaded up front."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from loopmodel.open3d_import import without_plotly_viewer

    without_plotly_viewer()  # the process only meshes: open3d's import 0.7 s CPU less
    import loopmodel.mapping.meshing  # noqa: F401 - open3d's import, before the first update


# the meshing process's low-priority thread (its main thread keeps the process's priority for other
# work, e.g. the final mesh: mapping.final_mesh_in_live_worker)
_LOW_PRIORITY: Any = None


def remesh_blocks_low(
    nice: int, points_w: np.ndarray, sensors_w: np.ndarray, blocks: set[BlockKey], config: MappingConfig
) -> tuple[dict[BlockKey, MeshArrays | None], float, int]:
    """:func:`remesh_blocks` on a thread of this process whose priority is lowered by ``nice``.

    Issue 32/33: a live update (0.3-1 s of a core on the 300-frame realistic orbit) then yields the
    cores to the tracking thread and its keyframe work (tail11).
    """
    global _LOW_PRIORITY
    if _LOW_PRIORITY is None:
        _LOW_PRIORITY = low_priority_pool("live-mesh-low", nice)
    return _LOW_PRIORITY.submit(remesh_blocks, points_w, sensors_w, blocks, config).result()  # type: ignore[no-any-return]


def preload_low(nice: int) -> None:
    """The sdf kernels loaded on this process's low-priority thread (the final mesh may be made here)."""
    global _LOW_PRIORITY
    if _LOW_PRIORITY is None:
        _LOW_PRIORITY = low_priority_pool("live-mesh-low", nice)
    from loopmodel.mapping.meshing import preload_kernels

    _LOW_PRIORITY.submit(preload_kernels).result()


def _load_sdf_kernels() -> None:
    """The sdf kernels loaded from numba's cache into this process (a thread worker; open3d not imported)."""
    from loopmodel.mapping._sdf_kernels import warm_up

    warm_up()


def remesh_blocks(
    points_w: np.ndarray, sensors_w: np.ndarray, blocks: set[BlockKey], config: MappingConfig
) -> tuple[dict[BlockKey, MeshArrays | None], float, int]:
    """:func:`~loopmodel.mapping.meshing.mesh_blocks` at the live settings, as arrays (for a worker process).

    Returns the blocks' meshes, the meshing time (ms) and the number of points given.
    """
    from loopmodel.mapping.meshing import live_mesh_config, mesh_blocks

    t0 = time.perf_counter()
    meshes = mesh_blocks(points_w, sensors_w, blocks, live_mesh_config(config))
    out: dict[BlockKey, MeshArrays | None] = {
        k: None if m is None else (np.asarray(m.vertices), np.asarray(m.triangles), np.asarray(m.vertex_normals))
        for k, m in meshes.items()
    }
    return out, (time.perf_counter() - t0) * 1e3, len(points_w)


def mesh_of_arrays(arrays: MeshArrays | None) -> Any:
    """An open3d mesh of (vertices, triangles, vertex normals) arrays (None for None)."""
    if arrays is None:
        return None
    import open3d as o3d

    v, t, n = arrays
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t.astype(np.int32)))
    mesh.vertex_normals = o3d.utility.Vector3dVector(n)
    return mesh


class LiveMapping:
    """The run's laser stripes handed to the pipeline's :class:`StripeMap`, and the chunked live mesh.

    The stripes of each frame are handed over (:meth:`feed`) as frames arrive.
    Every ``live_mesh_every_kf`` keyframes the blocks that new stripes entered or that pose
    corrections moved are re-meshed in a worker (``worker``): a process by default — open3d's
    surface reconstruction holds the interpreter lock (issue 33: a 7.7 s stall of the tracking thread
    while a thread meshed 60,000 points) — which gets the points as values and returns the block
    meshes as arrays; or a thread. Tracking never waits for it.
    """

    def __init__(
        self, world: StripeMap, every_kf: int, worker: Literal["process", "thread"] = "process", nice: int = 0
    ) -> None:
        self._world = world
        self._every = every_kf
        self._feeding = every_kf > 0
        self._keyframes = 0
        self._pool: Any = None
        self._job: Any = None
        self._started: Any = None  # the worker's start (its imports)
        self._worker_kind = worker
        self._nice = nice  # the updates' priority lowered by this (mapping.live_mesh_nice)
        if every_kf > 0:
            # placing stripes interpolates poses with scipy's rotations: its import (~0.3 s) here,
            # before the frames, not in the frame that places the first stripe (issue 33)
            import scipy.spatial.transform  # noqa: F401
        self._unfed: list[StripeProfile] = []  # stripes taken, not yet in the map (:meth:`flush`)
        self._arrays: dict[BlockKey, MeshArrays | None] = {}  # updated blocks not yet installed
        self.update_ms: list[float] = []
        self.blocks_remeshed = 0
        self.points_meshed = 0
        self.updates_abandoned = 0  # updates dropped unfinished (:meth:`close` without waiting)
        self.updates_skipped = 0  # updates not started: they would not end before the run's last frame
        self._submitted_s = self._done_s = 0.0  # when the running update was handed over and done (perf_counter, s)
        self._last_wall_s: float | None = None  # the last finished update's time from hand-over to result

    @property
    def enabled(self) -> bool:
        """Whether the live mesh is updated (``every_kf`` > 0)."""
        return self._every > 0

    def feed(self, stripes: Sequence[StripeProfile]) -> None:
        """Take a frame's stripes (time order; those without points are skipped).

        They join the map in one batch at the next update's turn (:meth:`flush`; live19: one call a
        frame into the map cost 0.07-0.13 ms of the tracking thread's frame on the 600-frame sample).
        """
        if self._feeding and stripes:
            self._unfed.extend(stripes)
            if self._pool is None:  # the worker's imports overlap the frames before the first update
                self.start()

    def flush(self) -> None:
        """The stripes taken since the last call join the map.

        A bad stripe stops the live feed (logged); the run and its final mesh go on.
        """
        batch, self._unfed = self._unfed, []
        if not self._feeding:
            return
        try:
            self._world.add_many(s for s in batch if np.asarray(s.points_in_cam).size)
        except LoopmodelError as exc:
            logger.error("live mesh: laser stripes no longer fed: %s", exc)
            self._feeding = False

    @property
    def point_count(self) -> int:
        """The stripe points the live mesh has been given."""
        self.flush()
        return self._world.point_count

    def on_keyframe(self, seconds_left: float | None = None) -> None:
        """Count a keyframe.

        Every ``every_kf``-th one installs the worker's finished blocks and, when the worker is
        free, hands it the blocks that changed since. ``seconds_left``: the run's frames still to
        come, in seconds (known when the sequence's length is and a final mesh supersedes the live
        one): in a worker process no update is started that the last one's time says would not end
        before them (mesh14: it would be abandoned, and the final mesh would wait for the process; a
        thread's update is not ended at the finish, and the written live mesh has it when it ends in time).
        """
        self._keyframes += 1
        if self._every <= 0 or self._keyframes % self._every or self.point_count == 0:
            return
        if self._job is not None:
            if not self._job.done():
                return  # still busy: the dirty blocks wait for the next turn
            self._collect()
        late = seconds_left is not None and self._last_wall_s is not None and self._last_wall_s > seconds_left
        if late and self._worker_kind == "process":
            self.updates_skipped += 1  # the dirty blocks stay for the final mesh (or a later turn)
            return
        snap = self._world.take_dirty_blocks()
        if snap is None:
            return
        pool = self._workers()  # (a daemonic process gets a thread)
        self._submitted_s = time.perf_counter()
        if self._worker_kind == "process":
            self._job = pool.submit(remesh_blocks_low, self._nice, *snap, self._world.config)
        else:  # the pool's thread has the lowered priority (it still shares the interpreter lock)
            self._job = pool.submit(remesh_blocks, *snap, self._world.config)
        self._job.add_done_callback(self._note_done)

    def _note_done(self, _job: Any) -> None:
        """The running update's end time (on the pool's thread that sees it end)."""
        self._done_s = time.perf_counter()

    def start(self) -> None:
        """Start the worker now (when the live mesh is on): its imports before the frames, not among them."""
        if self.enabled and self._pool is None:
            pool = self._workers()  # (a daemonic process gets a thread)
            self._started = pool.submit(int, 0)
            cfg = self._world.config
            process = self._worker_kind == "process"
            if cfg.live_method == "sdf" or (process and cfg.method == "sdf" and cfg.final_mesh_in_live_worker):
                # sdf16: the kernels of the updates and the final mesh (0.5-1.4 s CPU), below the run's priority;
                # live19: waited for with the start (wait_started), no longer loaded beside the first frames
                self._started = pool.submit(preload_low, self._nice) if process else pool.submit(_load_sdf_kernels)

    def wait_started(self, timeout_s: float | None = None) -> None:
        """Wait until the worker started by :meth:`start` has done its imports and kernels (a failure is logged)."""
        if self._started is None:
            return
        try:
            self._started.result(timeout_s)
        except Exception as exc:  # noqa: BLE001 - the updates report it again; the run goes on
            logger.warning("live mesh worker not started: %s", exc)

    def _workers(self) -> Any:
        if self._pool is None:
            import multiprocessing as mp

            if self._worker_kind == "process" and mp.current_process().daemon:
                # a daemonic process (a Dask or pool worker running this run) may not start children
                logger.info("live mesh in a thread: this process is a daemon and cannot start a worker process")
                self._worker_kind = "thread"
            if self._worker_kind == "process":
                from concurrent.futures import ProcessPoolExecutor

                ctx = mp.get_context("spawn")
                self._pool = ProcessPoolExecutor(1, mp_context=ctx, initializer=_worker_start)
            else:
                self._pool = low_priority_pool("live-mesh", self._nice)
        return self._pool

    def _collect(self) -> None:
        job, self._job = self._job, None
        # (the end noted by the pool's thread, perhaps just after ``done()`` said so: then now)
        done_s = self._done_s if self._done_s >= self._submitted_s else time.perf_counter()
        self._last_wall_s = done_s - self._submitted_s
        try:
            meshes, ms, n_points = job.result()
        except Exception as exc:  # the live view is a convenience: log, keep tracking
            logger.error("live mesh update failed: %s", exc)
            return
        # installed as open3d meshes only when the mesh is asked for: open3d's first import alone
        # stalled the tracking thread 2.4 s at load 16 (issue 33)
        self._arrays.update(meshes)
        self.blocks_remeshed += len(meshes)
        self.update_ms.append(ms)
        self.points_meshed += n_points
        logger.info("live mesh: %d block(s) re-meshed in %.0f ms", len(meshes), ms)

    def mesh_seconds_estimate(self) -> float | None:
        """Seconds to mesh every stripe point of the map at the rate the live updates measured.

        None before the first update (or when the live mesh is off). A finished update is taken in first.
        """
        if self._job is not None and self._job.done():
            self._collect()
        if not self.points_meshed:
            return None
        return self.point_count * sum(self.update_ms) / 1e3 / self.points_meshed

    @property
    def busy(self) -> bool:
        """Whether an update is running in the worker."""
        return self._job is not None and not self._job.done()

    def take_idle_worker(self, busy: bool = False) -> Any:
        """The worker process's pool when it is idle (its last update installed), for the final mesh; else None.

        The live mesh's updates end (as after :meth:`close`); the caller shuts the pool down.
        A thread pool is not handed over, nor a busy worker unless ``busy``: then its unfinished
        update is abandoned unseen (counted in ``updates_abandoned``) and what the caller submits
        runs after it (finish11: the final mesh started a refinement later, when the update is done).
        """
        if self._pool is None or self._worker_kind != "process":
            return None
        if self._job is not None:
            if not self._job.done():
                if not busy:
                    return None
                self._job = None
                self.updates_abandoned += 1
            else:
                self._collect()
        pool, self._pool = self._pool, None
        return pool

    def close(self, wait: bool) -> None:
        """Install the last worker result (``wait``) or abandon it; stop the worker.

        Abandoned, a worker process is ended at once (issue 32: its last update, 143 blocks of the
        150-frame orbit, took a core beside the final refinement and the final mesh); a thread
        finishes its update unseen.
        """
        if self._job is not None and (wait or self._job.done()):
            self._collect()
        dropped = self._job is not None
        self.updates_abandoned += int(dropped)
        self._job = None
        if self._pool is None:
            return
        pool, self._pool = self._pool, None
        # the executor's own worker processes (a thread pool has none), ended with the dropped
        # update; an idle one exits by itself
        ending = list((getattr(pool, "_processes", None) or {}).values()) if dropped else []
        pool.shutdown(wait=wait, cancel_futures=True)
        for proc in ending:
            if proc.is_alive():
                proc.terminate()

    def mesh(self) -> Any:
        """The live mesh as the run left it (an open3d mesh).

        None when it was off or never updated.
        """
        if self._every <= 0 or not self.update_ms:
            return None
        if self._arrays:
            self._world.install_blocks({k: mesh_of_arrays(m) for k, m in self._arrays.items()})
            self._arrays = {}
        mesh = self._world.live_mesh()
        return mesh if len(mesh.triangles) else None

    def metrics(self) -> dict[str, Any]:
        """Live-mesh update counts and times (ms) for ``metrics.json``; empty when off."""
        if not self.enabled:
            return {}
        a = np.asarray(self.update_ms, dtype=float)
        return {
            "live_mesh_updates": len(self.update_ms),
            "live_mesh_updates_abandoned": self.updates_abandoned,
            "live_mesh_updates_skipped": self.updates_skipped,
            "live_mesh_blocks_remeshed": self.blocks_remeshed,
            "live_mesh_update_ms_median": float(np.median(a)) if a.size else None,
            "live_mesh_update_ms_p95": float(np.percentile(a, 95)) if a.size else None,
        }
