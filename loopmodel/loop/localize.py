"""Localization in a saved map (``loopmodel run --map MAP --mode localize``, issue 20).

A :class:`~loopmodel.stages.LoopStage` whose database is the saved map's keyframes (their feature
sets, vocabulary and bags of words, :meth:`~loopmodel.loop.session_map.SessionMap.database`).
Until a tracking segment is in the map (at the start, and after every loss) every tracked frame
is relocalized (:meth:`MapLocalizationStage.on_frame`), not only the keyframes. Every keyframe the
front end makes is relocalized against the map (descriptors and the P3P bank,
then seed 004's KLT stage on the matched map keyframe's image; in a worker process once the
segment is in the map); a success returns the keyframe's pose in the map's world as a
correction, so the tracker goes on in the map's frame. The first
success of a tracking segment (the start, or after a loss) moves the segment's earlier keyframes
rigidly with it; later ones replace the tracked pose when they agree with it within the gate
(``max_correction_m`` / ``_deg``), so one false match cannot throw the session away. Nothing is
added to the map. A segment that never relocalizes keeps the session's own frame.
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing as mp
import time
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import LoopConfig
from loopmodel.geometry.se3 import invert_pose, so3_log
from loopmodel.loop.closer import LoopCloser
from loopmodel.loop.closure import relocalize_in_database
from loopmodel.loop.database import PlaceParams
from loopmodel.loop.reloc import RelocParams
from loopmodel.loop.session_map import SessionMap
from loopmodel.stages import LoopConstraint, LoopOutcome, MapState
from loopmodel.types import Keyframe, StereoCalibration

if TYPE_CHECKING:
    from loopmodel.frontend.keyframe import FrameResult

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


#: a relocalization: map keyframe, ``rect_from_map_rect``, inliers, method
Found = tuple[int, F64, int, str]

#: the worker process's own stage (its map database), made by :func:`_worker_start`
_WORKER: MapLocalizationStage | None = None


def _worker_start(smap: SessionMap, calibration: StereoCalibration, config: LoopConfig) -> None:
    global _WORKER
    _WORKER = MapLocalizationStage(smap, calibration, config)


def _worker_relocalize(image: NDArray[np.uint8]) -> tuple[Found | None, float]:
    assert _WORKER is not None
    t0 = time.perf_counter()
    found = _WORKER.relocalize(image) if image.size else None
    return found, (time.perf_counter() - t0) * 1e3


def _motion(a: F64, b: F64) -> tuple[float, float]:
    d = invert_pose(a) @ b
    return float(np.linalg.norm(d[:3, 3])), float(np.degrees(np.linalg.norm(so3_log(d[:3, :3]))))


class MapLocalizationStage:
    """Relocalize every keyframe of a session in a saved map (a :class:`~loopmodel.stages.LoopStage`).

    ``calibration``: the rectified calibration of the session's keyframe pixels (the map's
    keyframes were taken with the same camera)."""

    def __init__(
        self,
        smap: SessionMap,
        calibration: StereoCalibration,
        config: LoopConfig | None = None,
        max_correction_m: float = 0.05,
        max_correction_deg: float = 5.0,
    ) -> None:
        self.config = config if config is not None else LoopConfig()
        self.map = smap
        self.closer = LoopCloser(calibration, self.config)
        self.database = smap.database(PlaceParams.from_config(self.config))
        self.params = RelocParams.from_config(self.config)
        self._row = smap.row_of()
        self._remembered: set[int] = set()
        self.max_correction_m = max_correction_m
        self.max_correction_deg = max_correction_deg
        self.events: list[dict[str, Any]] = []
        #: keyframe id -> whether its pose is in the map's frame
        self.in_map: dict[int, bool] = {}
        self._segment_kfs: dict[int, list[int]] = {}
        self._segment_in_map: set[int] = set()
        self.attempt_ms: list[float] = []
        self.gated = 0
        self._keyframes: dict[int, Keyframe] = {}
        self._executor: ProcessPoolExecutor | None = None
        # submits to the worker process and waits for it: starting the process (its imports, the
        # map sent through a pipe) takes seconds, and tracking must not wait for it
        self._dispatch: ThreadPoolExecutor | None = None
        self._inflight: deque[tuple[int, Future[tuple[Found | None, float]]]] = deque()
        self.warmup_s = self._warm_up()

    def _warm_up(self) -> float:
        """Relocalize the map's first keyframe image in the map once, before the first frame (seconds).

        The first relocalization imports its modules and loads the P3P bank's compiled code (about a
        second); done here, the session's first frames do not wait for it.
        """
        t0 = time.perf_counter()
        image = self.map.image(0) if len(self.map) else np.zeros((0, 0), np.uint8)
        if image.size:
            self.relocalize(image)
        return time.perf_counter() - t0

    # ------------------------------------------------------------------ relocalization
    def _map_world_from_rect(self, map_kf: int) -> F64:
        i = self._row[map_kf]
        return np.asarray(self.map.world_from_kf[i]) @ invert_pose(self.map.rect_from_cam[i])

    def _remember(self, map_kf: int) -> None:
        if map_kf not in self._remembered:
            self.closer.remember(self.map.keyframe(self._row[map_kf]))
            self._remembered.add(map_kf)

    def relocalize(self, image: NDArray[np.uint8]) -> tuple[int, F64, int, str] | None:
        """The map keyframe and ``rect_from_map_rect`` (4x4, metres) of a rectified left image, or None.

        With the inlier count and the method (``descriptors`` or ``klt``: seed 004's KLT stage
        improved on the descriptor pose).
        """
        query = self.closer.frame_features(image)
        map_kf, res = relocalize_in_database(query, self.database, self.closer.camera, self.params)
        if map_kf is None or res.cam_from_map is None:
            return None
        self._remember(map_kf)
        cur_from_map = np.asarray(res.cam_from_map)
        tr = self.closer.track_old_features(map_kf, image, cur_from_map)
        if tr is not None and tr[1].size >= max(self.config.min_inliers, res.n_inliers):
            return map_kf, tr[0], int(tr[1].size), "klt"
        return map_kf, cur_from_map, res.n_inliers, "descriptors"

    # ------------------------------------------------------------------ the stage
    def _timed_relocalize(self, image: NDArray[np.uint8]) -> tuple[int, F64, int, str] | None:
        t0 = time.perf_counter()
        found = self.relocalize(image) if image.size else None
        self.attempt_ms.append((time.perf_counter() - t0) * 1e3)
        return found

    def on_keyframe(self, keyframe: Keyframe, state: MapState) -> LoopOutcome:
        """Relocalize the keyframe in the map; a success is a correction into the map's frame.

        A keyframe of a segment not yet in the map is relocalized at once; once the segment is in
        the map, relocalization runs in a worker process and its correction (of that keyframe, and
        the later ones rigidly with it) is applied at the next keyframe, so tracking does not wait.
        """
        kf = keyframe
        kid, seg = int(kf.id), int(kf.segment)
        self._segment_kfs.setdefault(seg, []).append(kid)
        self._keyframes[kid] = kf
        out = LoopOutcome(kf)
        self._collect(out, state, wait=False)
        self.in_map[kid] = seg in self._segment_in_map
        if seg in self._segment_in_map:
            self._inflight.append((kid, self._dispatcher().submit(self._in_worker, kf.image)))
            return out
        self._apply(kid, self._timed_relocalize(kf.image), out, state)
        if seg in self._segment_in_map:
            self._dispatcher().submit(self._pool)  # start the worker while tracking goes on
        return out

    def wants_frame(self, result: FrameResult) -> bool:
        """Whether a tracked frame between keyframes should be relocalized (its segment is not in the map yet)."""
        seg = int(result.segment)
        return result.ok and seg not in self._segment_in_map and int(result.keyframe_id) in self._keyframes

    def on_frame(self, result: FrameResult, image: NDArray[np.uint8], state: MapState) -> dict[int, F64]:
        """Relocalize a tracked frame of a segment not yet in the map (at the start and after a loss).

        ``image``: the frame's rectified left image. A success moves the segment's keyframes
        rigidly into the map's frame (the returned corrections, ``world_from_kf``); the frame's
        own pose follows them through its keyframe.
        """
        found = self._timed_relocalize(image)
        if found is None:
            return {}
        anchor = self._keyframes[int(result.keyframe_id)]
        seg = int(result.segment)
        map_kf, new_from_map, inliers, method = found
        world_from_new = self._map_world_from_rect(map_kf) @ invert_pose(new_from_map) @ anchor.rect_from_cam
        world = state.world_from_kf
        tracked = np.asarray(world.get(anchor.id, anchor.world_from_kf)) @ np.asarray(result.kf_from_cam)
        trans, rot = _motion(tracked, world_from_new)
        delta = world_from_new @ invert_pose(tracked)
        corrections = {k: delta @ np.asarray(world[k]) for k in self._segment_kfs[seg] if k in world}
        for k in corrections:
            self.in_map[k] = True
        self._segment_in_map.add(seg)
        logger.info("frame %d localized in the map at keyframe %d", result.frame_index, map_kf)
        self.events.append(
            {
                "type": "map_relocalization",
                "keyframe": int(anchor.id),
                "frame": int(result.frame_index),
                "match_keyframe": map_kf,
                "method": method,
                "inliers": inliers,
                "correction_m": trans,
                "correction_deg": rot,
                "first_of_segment": True,
                "between_keyframes": True,
            }
        )
        return corrections

    def _dispatcher(self) -> ThreadPoolExecutor:
        if self._dispatch is None:
            self._dispatch = ThreadPoolExecutor(1, thread_name_prefix="map-relocalization")
        return self._dispatch

    def _in_worker(self, image: NDArray[np.uint8]) -> tuple[Found | None, float]:
        """One relocalization in the worker process (called on the dispatch thread)."""
        return self._pool().submit(_worker_relocalize, image).result()

    def _pool(self) -> ProcessPoolExecutor:
        """The worker process holding its own copy of the map's database (started at the first use)."""
        if self._executor is None:
            self._executor = ProcessPoolExecutor(
                1,
                mp_context=mp.get_context("spawn"),
                initializer=_worker_start,
                initargs=(self.map, self.closer.calibration, self.config),
            )
        return self._executor

    def _collect(self, out: LoopOutcome, state: MapState, wait: bool) -> None:
        """Apply the finished relocalizations of earlier keyframes (``wait``: all of them)."""
        while self._inflight and (wait or self._inflight[0][1].done()):
            kid, fut = self._inflight.popleft()
            found, ms = fut.result()
            self.attempt_ms.append(ms)
            self._apply(kid, found, out, state)

    def _apply(
        self, kid: int, found: tuple[int, F64, int, str] | None, out: LoopOutcome, state: MapState
    ) -> None:
        """Correct keyframe ``kid`` (and the keyframes after it, rigidly) by a relocalization."""
        if found is None:
            return
        kf = self._keyframes[kid]
        seg = int(kf.segment)
        map_kf, new_from_map, inliers, method = found
        world_from_new = self._map_world_from_rect(map_kf) @ invert_pose(new_from_map) @ kf.rect_from_cam
        world = {**state.world_from_kf, **out.corrections}
        tracked = np.asarray(world.get(kid, kf.world_from_kf))
        trans, rot = _motion(tracked, world_from_new)
        first = seg not in self._segment_in_map
        if not first and (trans > self.max_correction_m or rot > self.max_correction_deg):
            self.gated += 1
            logger.info("keyframe %d: relocalization %.3f m / %.2f deg off the track: not applied", kid, trans, rot)
            return
        delta = world_from_new @ invert_pose(tracked)
        # the segment's earlier keyframes when it enters the map, the later ones always
        moved = [k for k in self._segment_kfs[seg] if k != kid and (first or k > kid) and k in world]
        for k in moved:
            out.corrections[k] = delta @ np.asarray(world[k])
            self.in_map[k] = True
        if first:
            self._segment_in_map.add(seg)
            logger.info("keyframe %d (frame %d) localized in the map at keyframe %d", kid, kf.frame_index, map_kf)
        out.corrections[kid] = world_from_new
        if kid == int(out.keyframe.id):
            out.keyframe = dataclasses.replace(out.keyframe, world_from_kf=world_from_new)
        elif int(out.keyframe.id) in out.corrections:
            out.keyframe = dataclasses.replace(out.keyframe, world_from_kf=out.corrections[int(out.keyframe.id)])
        self.in_map[kid] = True
        record = {
            "type": "map_relocalization",
            "keyframe": kid,
            "frame": kf.frame_index,
            "match_keyframe": map_kf,
            "method": method,
            "inliers": inliers,
            "correction_m": trans,
            "correction_deg": rot,
            "first_of_segment": first,
        }
        self.events.append(record)
        out.events.append(record)

    def close(self, state: MapState) -> dict[int, F64]:
        """Apply the relocalizations still running; stop the worker process."""
        out = LoopOutcome(self._keyframes[max(self._keyframes)]) if self._keyframes else None
        if out is not None:
            self._collect(out, state, wait=True)
        if self._dispatch is not None:
            self._dispatch.shutdown()
            self._dispatch = None
        if self._executor is not None:
            self._executor.shutdown()
            self._executor = None
        return out.corrections if out is not None else {}

    def final_constraints(self) -> list[LoopConstraint]:
        """None: nothing is added to the map."""
        return []

    def between_frames(self, state: MapState) -> LoopOutcome | None:
        """None: its relocalizations are applied at keyframes."""
        return None

    def detection(self, kf_id: int) -> Future[Any] | None:
        """None: a localizing run detects no loops."""
        return None

    def metrics(self) -> dict[str, Any]:
        """Relocalizations in the map for ``metrics.json``."""
        first = [e for e in self.events if e["first_of_segment"]]
        return {
            "map_keyframes": len(self.map),
            "map_relocalizations": len(self.events),
            "map_relocalizations_gated": self.gated,
            "map_first_localized_frame": first[0]["frame"] if first else None,
            "map_localized": bool(first),
            "map_relocalize_ms_median": float(np.median(self.attempt_ms)) if self.attempt_ms else None,
            "map_warmup_s": self.warmup_s,
            "loop_events": self.events,
        }
