"""Loop closing as a pipeline stage: keyframes in, corrections out to the tracker.

:class:`LoopClosingStage` is fed every new keyframe of the front end. It

* relocalizes the first keyframe of a new segment (the front end starts one, unconnected,
  after tracking was lost) against the stored keyframes and, when that succeeds, moves
  the new segment into the old map;
* checks every keyframe for a verified revisit (:class:`~loopmodel.loop.closer.LoopCloser`)
  and, on one, runs the global hybrid BA over the loop — in a worker process by default,
  so tracking does not wait — and feeds the corrected keyframe poses back to the tracker
  (``apply_correction``) and to optional listeners (mesher, back end). Keyframes created
  while the BA ran move rigidly with the loop's current keyframe.

Each closure and relocalization is recorded as a plain dict (for ``metrics.json``):
keyframes and frames involved, inliers, correction size, optimisation time.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import LoopConfig
from loopmodel.errors import LoopmodelError
from loopmodel.geometry.se3 import invert_pose, so3_log
from loopmodel.loop.closer import LoopCloser, LoopClosure
from loopmodel.loop.closure import LoopEvent
from loopmodel.loop.global_ba import GlobalBAResult, LoopObservations, global_hybrid_ba
from loopmodel.types import StereoCalibration

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
#: Called with the corrected ``world_from_kf`` of every keyframe that moved.
CorrectionListener = Callable[[dict[int, F64]], None]


class Tracker(Protocol):
    """What the stage needs from the front end."""

    @property
    def world_from_kf(self) -> dict[int, F64]: ...

    def apply_correction(self, world_from_kf: dict[int, F64]) -> None: ...


def _motion(a: F64, b: F64) -> tuple[float, float]:
    d = invert_pose(a) @ b
    return float(np.linalg.norm(d[:3, 3])), float(np.degrees(np.linalg.norm(so3_log(d[:3, :3]))))


class LoopClosingStage:
    """Relocalization and loop closing wired to a tracker.

    ``calibration`` is the rectified calibration of the keyframes' pixels."""

    def __init__(
        self,
        tracker: Tracker,
        calibration: StereoCalibration,
        config: LoopConfig | None = None,
        listeners: list[CorrectionListener] | None = None,
        background: bool | None = None,
        backend: Any | None = None,
    ) -> None:
        self.tracker = tracker
        self.config = config if config is not None else LoopConfig()
        self.closer = LoopCloser(calibration, self.config)
        self.listeners = listeners or []
        self.keyframes: dict[int, Any] = {}
        self.events: list[dict[str, Any]] = []
        self.rejected: list[dict[str, Any]] = []
        #: Run the global BA in a worker process (GTSAM holds the GIL while optimising,
        #: so a thread would stall tracking) and apply it when done (:meth:`poll`).
        self.background = self.config.background_ba if background is None else background
        self._pool: ProcessPoolExecutor | None = None
        self._pending: tuple[Future[GlobalBAResult], LoopClosure, dict[int, F64], float] | None = None
        self._rerun: LoopClosure | None = None
        #: With a back end the loop's observations join the keyframe's monocular
        #: observations (seed 004 eq. 6 inside the incremental graph) and a relative-pose
        #: constraint is added; the pipeline's back-end update then does the correction.
        self.backend = backend
        self._queued: list[tuple[LoopClosure, dict[str, Any]]] = []
        self._awaiting: list[dict[str, Any]] = []
        #: Place recognition and verification in a worker thread (``background_detection``):
        #: OpenCV's detection and KLT and numpy's large array operations release the GIL; a
        #: keyframe never waits for them, their result is applied at a later keyframe.
        self._detect_pool: ThreadPoolExecutor | None = None
        self._inflight: deque[tuple[int, Future[tuple[LoopClosure | None, list[LoopEvent]]]]] = deque()
        self.keyframes_not_queried = 0
        self.late_closures = 0
        # covisibility: (first, last landmark id, keyframe) per keyframe; direct neighbours
        self._lm_ranges: list[tuple[int, int, int]] = []
        self._covisible_of: dict[int, set[int]] = {}

    # ------------------------------------------------------------------ keyframes
    def on_keyframe(self, kf: Any) -> dict[str, Any] | None:
        """Process a new keyframe; returns the event record of a closure or
        relocalization it caused (None otherwise)."""
        self.keyframes[int(kf.id)] = kf
        event = self.poll()
        event = self._collect(wait=False) or event
        neighbours = self._temporal_neighbours(kf)
        if not getattr(kf, "connected", True) and len(self.keyframes) > 1:
            self._collect(wait=True)  # relocalization reads the database the worker writes
            event = self._relocalize_segment(kf) or event
        if not self.config.background_detection:
            closure, rejected = self._detect(kf, neighbours, True)
            self._note_rejected(rejected)
            if closure is not None:
                event = self._close(closure) or event
            return event
        if self._detect_pool is None:
            self._detect_pool = ThreadPoolExecutor(1, thread_name_prefix="loop-detect")
        query = len(self._inflight) < self.config.max_queued_keyframes
        self.keyframes_not_queried += not query
        self._inflight.append((int(kf.id), self._detect_pool.submit(self._detect, kf, neighbours, query)))
        return event

    def _detect(
        self, kf: Any, neighbours: set[int], query: bool
    ) -> tuple[LoopClosure | None, list[LoopEvent]]:
        """Place recognition and verification of one keyframe (worker thread when
        ``background_detection``): the closure found and the candidates rejected."""
        rejected = self.closer.detector.rejected
        n = len(rejected)
        closure = self.closer.process_keyframe(kf, neighbours=neighbours, query=query)
        return closure, rejected[n:]

    def _note_rejected(self, rejected: list[LoopEvent]) -> None:
        for ev in rejected:
            self.rejected.append({"query_kf": ev.query_id, "match_kf": ev.match_id, "reason": ev.reason})

    def _collect(self, wait: bool) -> dict[str, Any] | None:
        """Apply the worker's finished detections in keyframe order (``wait``: all of them);
        returns the record of the last closure applied."""
        event = None
        while self._inflight and (wait or self._inflight[0][1].done()):
            _kf_id, fut = self._inflight.popleft()
            try:
                closure, rejected = fut.result()
            except LoopmodelError as exc:  # a failed detection is logged, never applied
                logger.warning("loop detection of keyframe %d failed (%s)", _kf_id, exc)
                continue
            self._note_rejected(rejected)
            if closure is not None:
                self.late_closures += 1
                event = self._close(closure, late=True) or event
        return event

    def _temporal_neighbours(self, kf: Any) -> set[int]:
        """Keyframes co-visible with the new keyframe's local map (the covisibility graph of
        ORB-SLAM, two levels): those whose landmarks it observes (its stereo and monocular
        observations), and theirs. The front end and the back end link these already; a
        loop with them adds nothing. Landmark ids are looked up by each keyframe's id range."""
        q = int(kf.id)
        ids = np.asarray(kf.landmark_ids, dtype=np.int64).ravel()
        mono = np.asarray(getattr(kf, "mono_obs", np.zeros((0, 3))), dtype=float).reshape(-1, 3)
        seen = np.concatenate([ids, mono[:, 0].astype(np.int64)])
        direct: set[int] = set()
        if seen.size and self._lm_ranges:
            lo = np.array([r[0] for r in self._lm_ranges])
            hi = np.array([r[1] for r in self._lm_ranges])
            owners = np.array([r[2] for r in self._lm_ranges])
            j = np.searchsorted(lo, seen, side="right") - 1
            ok = (j >= 0) & (seen <= hi[np.maximum(j, 0)])
            direct = set(owners[j[ok]].tolist()) - {q}
        if ids.size and (not self._lm_ranges or ids.min() > self._lm_ranges[-1][1]):
            self._lm_ranges.append((int(ids.min()), int(ids.max()), q))
        self._covisible_of[q] = direct
        out = set(direct)
        for k in direct:
            out |= self._covisible_of.get(k, set())
        return out - {q}

    def _relocalize_segment(self, kf: Any) -> dict[str, Any] | None:
        """Place the first keyframe of a new segment in the old map: descriptors and the
        P3P bank against the stored keyframes, or — when that fails — the latest keyframes'
        features searched by KLT from the rough (motion-model) pose; then the KLT accuracy
        stage. The observations link the segments in later global BAs."""
        t0 = time.perf_counter()
        new_id = int(kf.id)
        world = self.tracker.world_from_kf

        def world_from_rect(k: int) -> F64:
            rect_from_cam = np.asarray(getattr(self.keyframes[k], "rect_from_cam", np.eye(4)))
            return world[k] @ invert_pose(rect_from_cam)

        method = "descriptors"
        kf_id, res = self.closer.relocalize(kf.image, exclude_after=new_id - 1)
        new_from_old: F64 | None = None
        inliers = 0
        if kf_id is not None and res.cam_from_map is not None:
            new_from_old, inliers = res.cam_from_map, res.n_inliers
        else:
            method = "klt from predicted pose"
            older = sorted(k for k in self.keyframes if k < new_id)[-3:][::-1]
            for cand in older:
                pred = invert_pose(world_from_rect(new_id)) @ world_from_rect(cand)
                tr = self.closer.track_old_features(cand, kf.image, pred)
                if tr is not None and tr[1].size >= self.config.min_inliers:
                    kf_id, new_from_old, inliers = cand, tr[0], int(tr[1].size)
                    break
        if kf_id is None or new_from_old is None:
            logger.info("keyframe %d: relocalization failed (%s)", new_id, res.reason)
            return None
        tr = self.closer.track_old_features(kf_id, kf.image, new_from_old)
        obs_ids, obs_uv = np.zeros(0, np.int64), np.zeros((0, 2))
        if tr is not None and tr[1].size >= self.config.min_inliers:
            new_from_old, obs_ids, obs_uv = tr
        self.closer.closures.append(
            LoopClosure(
                new_id,
                kf_id,
                new_from_old,
                LoopObservations(new_id, obs_ids, obs_uv),
                inliers,
                int(obs_ids.size),
                None,
                0.0,
                (time.perf_counter() - t0) * 1e3,
                {"relocalization": method},
            )
        )
        rect_from_cam = np.asarray(getattr(kf, "rect_from_cam", np.eye(4)))
        world_from_new = world_from_rect(kf_id) @ invert_pose(new_from_old) @ rect_from_cam
        before = world[new_id]
        self._apply({new_id: world_from_new})
        kf.world_from_kf = world_from_new  # the back end's initial guess
        trans, rot = _motion(before, world_from_new)
        record = {
            "type": "relocalization",
            "method": method,
            "keyframe": new_id,
            "frame": int(getattr(kf, "frame_index", -1)),
            "match_keyframe": int(kf_id),
            "match_frame": int(getattr(self.keyframes[kf_id], "frame_index", -1)),
            "inliers": inliers,
            "klt_inliers": int(obs_ids.size),
            "correction_m": trans,
            "correction_deg": rot,
            "time_ms": (time.perf_counter() - t0) * 1e3,
        }
        self.events.append(record)
        if self.backend is not None:
            self._to_backend(kf, self.closer.closures[-1], record)
        logger.info("keyframe %d relocalized against keyframe %d (%s)", new_id, kf_id, method)
        return record

    def _close(self, closure: LoopClosure, late: bool = False) -> dict[str, Any] | None:
        """Start the correction of a verified loop (in the worker process when
        ``background``); returns the record when it was applied right away. ``late``: the
        query keyframe is already in the back end (detection ran in the worker), so its
        loop observations go in by ``add_observations``."""
        if self.backend is not None:
            record = self._loop_record(closure)
            record["applied_at_keyframe"] = max(self.keyframes)
            self.events.append(record)
            if late:
                self._late_to_backend(closure, record)
            else:
                self._to_backend(self.keyframes[closure.query_kf], closure, record)
            return record
        if self._pending is not None:
            self._rerun = closure  # the running BA finishes first; then this loop's window
            return None
        return self._submit(closure)

    def _to_backend(self, kf: Any, closure: LoopClosure, record: dict[str, Any]) -> None:
        """Append the closure's observations of old landmarks to the keyframe's monocular
        observations (before the pipeline adds it to the back end) and queue its relative
        pose as a loop constraint for :meth:`update_backend`."""
        obs = closure.observations
        if obs.landmark_ids.size:
            have = set(np.asarray(kf.mono_obs, dtype=float).reshape(-1, 3)[:, 0].astype(np.int64).tolist())
            keep = np.array([int(i) not in have for i in obs.landmark_ids], dtype=bool)
            extra = np.column_stack([obs.landmark_ids[keep].astype(float), obs.uv_px[keep]])
            kf.mono_obs = np.vstack([np.asarray(kf.mono_obs, dtype=float).reshape(-1, 3), extra])
        record["pose_before"] = np.asarray(self.tracker.world_from_kf[closure.query_kf]).copy()
        self._queued.append((closure, record))

    def _late_to_backend(self, closure: LoopClosure, record: dict[str, Any]) -> None:
        """A loop found after its query keyframe went into the back end: its observations of
        old landmarks join that keyframe now; its relative pose is queued as for
        :meth:`_to_backend`."""
        obs = closure.observations
        add = getattr(self.backend, "add_observations", None)
        record["loop_observations_added"] = 0
        if obs.landmark_ids.size and callable(add):
            rows = np.column_stack([obs.landmark_ids.astype(float), obs.uv_px])
            try:
                record["loop_observations_added"] = int(add(closure.query_kf, rows))
            except LoopmodelError as exc:
                logger.info("loop %d -> %d: observations not added (%s)", closure.query_kf, closure.match_kf, exc)
        record["pose_before"] = np.asarray(self.tracker.world_from_kf[closure.query_kf]).copy()
        self._queued.append((closure, record))

    def update_backend(self, backend: Any | None = None) -> int:
        """After the pipeline added the keyframe to the back end: add the queued loop
        constraints (``kf_query_from_kf_match``, camera frames). Returns how many."""
        be = backend if backend is not None else self.backend
        if be is None:
            return 0
        n = 0
        for closure, record in self._queued:
            q, m = self.keyframes[closure.query_kf], self.keyframes[closure.match_kf]
            rq = np.asarray(getattr(q, "rect_from_cam", np.eye(4)))
            rm = np.asarray(getattr(m, "rect_from_cam", np.eye(4)))
            q_from_m = invert_pose(rq) @ closure.query_from_match @ rm
            t0 = time.perf_counter()
            try:
                record["constraint_id"] = int(be.add_loop_constraint(closure.query_kf, closure.match_kf, q_from_m))
                n += 1
            except LoopmodelError as exc:  # e.g. a back end without relative-pose factors
                record["constraint_id"] = None
                logger.info("loop %d -> %d: no loop constraint (%s)", closure.query_kf, closure.match_kf, exc)
            record["optimise_ms"] = (time.perf_counter() - t0) * 1e3
        self._awaiting = [r for _, r in self._queued]
        self._queued = []
        return n

    def note_estimate(self, world_from_kf: dict[int, F64], update_ms: float = 0.0) -> None:
        """Record how far the back end moved the keyframes of the loops just added."""
        for record in self._awaiting:
            before = record.pop("pose_before", None)
            k = record["keyframe"]
            if before is not None and k in world_from_kf:
                key = "correction" if record["type"] == "loop" else "backend_correction"
                record[key + "_m"], record[key + "_deg"] = _motion(before, world_from_kf[k])
            record["optimise_ms"] = record.get("optimise_ms", 0.0) + update_ms
        self._awaiting = []

    def _loop_record(self, closure: LoopClosure) -> dict[str, Any]:
        return {
            "type": "loop",
            "keyframe": closure.query_kf,
            "frame": int(getattr(self.keyframes[closure.query_kf], "frame_index", -1)),
            "match_keyframe": closure.match_kf,
            "match_frame": int(getattr(self.keyframes[closure.match_kf], "frame_index", -1)),
            "inliers": closure.n_descriptor_inliers,
            "klt_inliers": closure.n_klt_inliers,
            "loop_observations": int(closure.observations.landmark_ids.size),
            "correction_m": 0.0,
            "correction_deg": 0.0,
            "optimise_ms": 0.0,
            "via": "backend",
        }

    def _submit(self, closure: LoopClosure) -> dict[str, Any] | None:
        before = dict(self.tracker.world_from_kf)
        kfs = [self.keyframes[k] for k in sorted(self.keyframes)]
        for k in kfs:  # the BA starts from the tracker's current estimate
            k.world_from_kf = before.get(int(k.id), k.world_from_kf)
        problem = self.closer.correction_problem(kfs, closure)
        t0 = time.perf_counter()
        if not self.background:
            return self._finish(closure, global_hybrid_ba(**problem), before, t0)
        if self._pool is None:
            self._pool = ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"))
        self._pending = (self._pool.submit(global_hybrid_ba, **problem), closure, before, t0)
        return None

    def poll(self, wait: bool = False) -> dict[str, Any] | None:
        """Apply a finished background correction (``wait``: block until it is done);
        returns its record. Call once per frame."""
        if self._pending is None:
            return None
        fut, closure, before, t0 = self._pending
        if not wait and not fut.done():
            return None
        self._pending = None
        try:
            res = fut.result()
        except Exception as exc:  # a failed correction is logged, never applied
            logger.warning("loop %d -> %d: correction failed (%s)", closure.query_kf, closure.match_kf, exc)
            record = None
        else:
            record = self._finish(closure, res, before, t0)
        if self._rerun is not None:
            again, self._rerun = self._rerun, None
            self._submit(again)
        return record

    def finish(self) -> None:
        """Wait for and apply every pending detection and correction; stop the workers."""
        self._collect(wait=True)
        if self._queued:
            self.update_backend()
        if self._detect_pool is not None:
            self._detect_pool.shutdown()
            self._detect_pool = None
        while self._pending is not None:
            self.poll(wait=True)
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def _finish(self, closure: LoopClosure, res: GlobalBAResult, before: dict[int, F64], t0: float) -> dict[str, Any]:
        corrected = dict(res.world_from_kf)
        # keyframes created while the BA ran move with the loop's current keyframe
        # (through their measured relative transforms when they have them)
        now = self.tracker.world_from_kf
        delta = corrected[closure.query_kf] @ invert_pose(before[closure.query_kf])
        for k in sorted(now):
            if k <= closure.query_kf or k not in self.keyframes:
                continue
            kf = self.keyframes[k]
            prev = getattr(kf, "prev_keyframe_id", None)
            rel = getattr(kf, "kf_prev_from_kf", None)
            if getattr(kf, "connected", False) and rel is not None and prev in corrected:
                corrected[k] = corrected[prev] @ np.asarray(rel)
            else:
                corrected[k] = delta @ now[k]
        self._apply(corrected)
        trans, rot = _motion(before[closure.query_kf], res.world_from_kf[closure.query_kf])
        record = {
            "type": "loop",
            "keyframe": closure.query_kf,
            "frame": int(getattr(self.keyframes[closure.query_kf], "frame_index", -1)),
            "match_keyframe": closure.match_kf,
            "match_frame": int(getattr(self.keyframes[closure.match_kf], "frame_index", -1)),
            "inliers": closure.n_descriptor_inliers,
            "klt_inliers": closure.n_klt_inliers,
            "loop_observations": int(closure.observations.landmark_ids.size),
            "correction_m": trans,
            "correction_deg": rot,
            "optimise_ms": (res.solve_s + res.build_s) * 1e3,
            "applied_after_ms": (time.perf_counter() - t0) * 1e3,
            "applied_at_keyframe": max(self.keyframes),
            "parameters": res.n_parameters,
            "residuals": res.n_residuals,
            "keyframes_optimised": len(res.world_from_kf),
            "keyframes_moved_along": len(corrected) - len(res.world_from_kf),
        }
        self.events.append(record)
        logger.info(
            "loop %d -> %d corrected: %.3f m / %.2f deg, BA %.0f ms",
            closure.query_kf,
            closure.match_kf,
            trans,
            rot,
            record["optimise_ms"],
        )
        return record

    def _apply(self, corrected: dict[int, F64]) -> None:
        for k, T in corrected.items():
            if k in self.keyframes:
                self.keyframes[k].world_from_kf = T
        self.tracker.apply_correction(corrected)
        for fn in self.listeners:
            fn(corrected)

    # ------------------------------------------------------------------ metrics
    def metrics(self) -> dict[str, Any]:
        """Summary for ``metrics.json`` (waits for the detections still running)."""
        self._collect(wait=True)
        loops = [e for e in self.events if e["type"] == "loop"]
        det = self.closer.detector
        return {
            "loop_closure_count": len(loops),
            "relocalization_count": len(self.events) - len(loops),
            "loop_events": self.events,
            "loop_candidates_rejected": len(self.rejected),
            "loop_neighbours_skipped": det.neighbours_skipped,
            "loop_keyframes_not_queried": self.keyframes_not_queried,
            "loop_detect_ms_median": float(np.median(det.query_s) * 1e3) if det.query_s else None,
        }
