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
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from loopmodel.backend.robust_posegraph import keyframe_loop_inliers
from loopmodel.config import LoopConfig
from loopmodel.errors import LoopmodelError
from loopmodel.geometry.se3 import invert_pose, so3_log
from loopmodel.loop.closer import LoopCloser, LoopClosure
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
        #: loops the robust gate accepted (they join later gates' pose graphs)
        self._gated: list[LoopClosure] = []
        self._awaiting: list[dict[str, Any]] = []

    # ------------------------------------------------------------------ keyframes
    def on_keyframe(self, kf: Any) -> dict[str, Any] | None:
        """Process a new keyframe; returns the event record of a closure or
        relocalization it caused (None otherwise)."""
        self.keyframes[int(kf.id)] = kf
        event = self.poll()
        if not getattr(kf, "connected", True) and len(self.keyframes) > 1:
            event = self._relocalize_segment(kf)
        n_rej = len(self.closer.detector.rejected)
        closure = self.closer.process_keyframe(kf)
        for ev in self.closer.detector.rejected[n_rej:]:
            self.rejected.append({"query_kf": ev.query_id, "match_kf": ev.match_id, "reason": ev.reason})
        if closure is not None:
            event = self._close(closure) or event
        return event

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

    def _close(self, closure: LoopClosure) -> dict[str, Any] | None:
        """Start the correction of a verified loop (in the worker process when
        ``background``); returns the record when it was applied right away. A loop the
        robust gate rejects (:meth:`_robust_gate`) is recorded and never applied."""
        if not self._robust_gate(closure):
            return None
        if self.backend is not None:
            record = self._loop_record(closure)
            self.events.append(record)
            self._to_backend(self.keyframes[closure.query_kf], closure, record)
            return record
        if self._pending is not None:
            self._rerun = closure  # the running BA finishes first; then this loop's window
            return None
        return self._submit(closure)

    def _cam_from_cam(self, closure: LoopClosure) -> F64:
        """The closure's ``kf_query_from_kf_match`` between camera (not rectified) frames."""
        q, m = self.keyframes[closure.query_kf], self.keyframes[closure.match_kf]
        rq = np.asarray(getattr(q, "rect_from_cam", np.eye(4)))
        rm = np.asarray(getattr(m, "rect_from_cam", np.eye(4)))
        return invert_pose(rq) @ closure.query_from_match @ rm

    def _robust_gate(self, closure: LoopClosure) -> bool:
        """GNC-TLS on the keyframe pose graph from the loop's old keyframe to the current
        one: the tracker's relative poses between consecutive connected keyframes (known
        inliers), the loops accepted before and this one. False when this loop is an
        outlier (it is then kept in ``rejected``, with the reason). A window that a new
        segment (unconnected keyframe) breaks is not gated."""
        if self.config.robust == "none":
            return True
        lo, hi = closure.match_kf, closure.query_kf
        world = self.tracker.world_from_kf
        ids = sorted(k for k in self.keyframes if lo <= k <= hi and k in world)
        if len(ids) < 2 or ids[0] != lo or ids[-1] != hi:
            return True
        if not all(getattr(self.keyframes[k], "connected", True) for k in ids[1:]):
            return True
        cfg = self.config
        loops = [
            (c.query_kf, c.match_kf, self._cam_from_cam(c))
            for c in self._gated
            if lo <= c.match_kf and c.query_kf <= hi
        ] + [(hi, lo, self._cam_from_cam(closure))]
        t0 = time.perf_counter()
        inlier, res = keyframe_loop_inliers(
            {k: np.asarray(world[k], float) for k in ids},
            list(zip(ids[:-1], ids[1:], strict=True)),
            loops,
            cfg.robust_odometry_sigma_deg,
            cfg.robust_odometry_sigma_m,
            cfg.robust_loop_sigma_deg,
            cfg.robust_loop_sigma_m,
            cfg.robust_probability,
        )
        gate_ms = (time.perf_counter() - t0) * 1e3
        if bool(inlier[-1]):
            self._gated.append(closure)
            closure.info["robust_gate_ms"] = gate_ms
            return True
        self.closer.closures.remove(closure)
        self.rejected.append(
            {
                "query_kf": hi,
                "match_kf": lo,
                "reason": f"robust gate: inconsistent with odometry (GNC weight {float(res.weights[-1]):.2f})",
                "gate_ms": gate_ms,
            }
        )
        logger.info("loop %d -> %d rejected by the robust gate", hi, lo)
        return False

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

    def update_backend(self, backend: Any | None = None) -> int:
        """After the pipeline added the keyframe to the back end: add the queued loop
        constraints (``kf_query_from_kf_match``, camera frames). Returns how many."""
        be = backend if backend is not None else self.backend
        if be is None:
            return 0
        n = 0
        for closure, record in self._queued:
            q_from_m = self._cam_from_cam(closure)
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
        """Wait for and apply every pending correction; stop the worker process."""
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
        """Summary for ``metrics.json``."""
        loops = [e for e in self.events if e["type"] == "loop"]
        return {
            "loop_closure_count": len(loops),
            "relocalization_count": len(self.events) - len(loops),
            "loop_events": self.events,
            "loop_candidates_rejected": len(self.rejected),
        }
