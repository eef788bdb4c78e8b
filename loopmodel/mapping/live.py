"""The pipeline's live mapping stage.

Laser stripes fed to the run's :class:`StripeMap` as frames arrive, and the chunked live mesh
re-meshed in a worker thread.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from loopmodel.errors import LoopmodelError
from loopmodel.mapping.stripe_map import StripeMap
from loopmodel.types import StripeProfile

logger = logging.getLogger(__name__)


class LiveMapping:
    """The run's laser stripes handed to the pipeline's :class:`StripeMap`, and the chunked live mesh.

    The stripes of each frame are handed over (:meth:`feed`) as frames arrive. Every
    ``live_mesh_every_kf`` keyframes the blocks that new stripes entered or that pose corrections
    moved are re-meshed in a worker thread (open3d releases the GIL), so tracking does not wait
    for it.
    """

    def __init__(self, world: StripeMap, every_kf: int) -> None:
        self._world = world
        self._every = every_kf
        self._feeding = every_kf > 0
        self._keyframes = 0
        self._pool: Any = None
        self._job: Any = None
        self.update_ms: list[float] = []
        self.blocks_remeshed = 0
        self.points_meshed = 0

    @property
    def enabled(self) -> bool:
        """Whether the live mesh is updated (``every_kf`` > 0)."""
        return self._every > 0

    def feed(self, stripes: Sequence[StripeProfile]) -> None:
        """Add a frame's stripes (time order; those without points are skipped).

        A bad stripe stops the live feed (logged); the run and its final mesh go on.
        """
        if not self._feeding:
            return
        batch = [s for s in stripes if np.asarray(s.points_in_cam).size]
        try:
            if batch:
                self._world.add_many(batch)
        except LoopmodelError as exc:
            logger.error("live mesh: laser stripes no longer fed: %s", exc)
            self._feeding = False

    def on_keyframe(self) -> None:
        """Count a keyframe.

        Every ``every_kf``-th one installs the worker's finished blocks and, when the worker is
        free, hands it the blocks that changed since.
        """
        self._keyframes += 1
        if self._every <= 0 or self._keyframes % self._every or self._world.point_count == 0:
            return
        if self._job is not None:
            if not self._job.done():
                return  # still busy: the dirty blocks wait for the next turn
            self._collect()
        snap = self._world.take_dirty_blocks()
        if snap is None:
            return
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="live-mesh")
        self._job = self._pool.submit(self._remesh, *snap)

    def _remesh(self, points_w: np.ndarray, sensors_w: np.ndarray, blocks: set[tuple[int, int, int]]) -> Any:
        from loopmodel.mapping.meshing import live_mesh_config, mesh_blocks

        t0 = time.perf_counter()
        meshes = mesh_blocks(points_w, sensors_w, blocks, live_mesh_config(self._world.config))
        return meshes, (time.perf_counter() - t0) * 1e3, len(points_w)

    def _collect(self) -> None:
        job, self._job = self._job, None
        try:
            meshes, ms, n_points = job.result()
        except Exception as exc:  # the live view is a convenience: log, keep tracking
            logger.error("live mesh update failed: %s", exc)
            return
        self._world.install_blocks(meshes)
        self.blocks_remeshed += len(meshes)
        self.update_ms.append(ms)
        self.points_meshed += n_points
        logger.info("live mesh: %d block(s) re-meshed in %.0f ms", len(meshes), ms)

    def mesh_seconds_estimate(self) -> float | None:
        """Seconds to mesh every stripe point of the map at the rate the live updates measured.

        None before the first update (or when the live mesh is off).
        """
        if not self.points_meshed:
            return None
        return self._world.point_count * sum(self.update_ms) / 1e3 / self.points_meshed

    def close(self, wait: bool) -> None:
        """Install the last worker result (``wait``) or abandon it; stop the worker."""
        if self._job is not None and wait:
            self._collect()
        if self._pool is not None:
            self._pool.shutdown(wait=wait, cancel_futures=True)

    def mesh(self) -> Any:
        """The live mesh as the run left it (an open3d mesh).

        None when it was off or never updated.
        """
        if self._every <= 0 or not self.update_ms:
            return None
        mesh = self._world.live_mesh()
        return mesh if len(mesh.triangles) else None

    def metrics(self) -> dict[str, Any]:
        """Live-mesh update counts and times (ms) for ``metrics.json``; empty when off."""
        if not self.enabled:
            return {}
        a = np.asarray(self.update_ms, dtype=float)
        return {
            "live_mesh_updates": len(self.update_ms),
            "live_mesh_blocks_remeshed": self.blocks_remeshed,
            "live_mesh_update_ms_median": float(np.median(a)) if a.size else None,
            "live_mesh_update_ms_p95": float(np.percentile(a, 95)) if a.size else None,
        }
