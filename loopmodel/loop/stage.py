"""Loop closing as a pipeline stage: a keyframe in, constraints and corrections out.

:class:`LoopClosingStage` is fed every new keyframe of the front end through one entry
point, :meth:`LoopClosingStage.on_keyframe`, and never changes another stage: it returns a
:class:`LoopOutcome` that the pipeline applies. It

* relocalizes the first keyframe of a new segment (the front end starts one, unconnected,
  after tracking was lost) against the stored keyframes and, when that succeeds, returns
  the new segment's keyframe pose in the old map as a correction;
* checks every keyframe for a verified revisit (:class:`~loopmodel.loop.closer.LoopCloser`)
  and, on one, either (``via_backend``, the pipeline's way) adds the loop's observations of
  old landmarks to the keyframe's monocular observations and returns the loop's relative
  pose as a :class:`LoopConstraint` for the back end, or (standalone) runs the global
  hybrid BA over the loop — in a worker process by default, so tracking does not wait — and
  returns the corrected keyframe poses when it is done. Keyframes created while the BA ran
  move rigidly with the loop's current keyframe;
* hands the old features a closure found again in the current keyframe to the front end
  (``LoopOutcome.resume``, seed 004 section 5), which tracks them on; the closure's record
  says how many (``old_features_resumed``) and how many each later keyframe observed
  (``old_features_tracked_on``, read from the keyframes' ``ba_info``).

Place recognition and verification run in a worker (``loop.detection_worker``: a process
by default, which holds the keyframe database; a thread; or inline): a keyframe never waits
for them. A loop found for an earlier keyframe is applied at the
next keyframe that arrives after it: the old keyframe's features are tracked (KLT) into
that keyframe's image from the pose the tracker and the loop predict, and the loop's
observations and relative pose are those of the new keyframe. Candidates co-visible with
the query's local map (its temporal neighbours) are never verified.

Each closure and relocalization is recorded as a plain dict (for ``metrics.json``):
keyframes and frames involved, inliers, correction size, optimisation time. The back end's
effect on a loop (how far it moved the keyframe, how long the update took) is read from the
:class:`MapState` the pipeline hands to the next call.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import multiprocessing as mp
import time
from collections import deque
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.backend.robust_posegraph import GateSigmas, gate_keyframe_loop, keyframe_loop_inliers
from loopmodel.config import LoopConfig
from loopmodel.errors import LoopmodelError
from loopmodel.geometry.se3 import invert_pose, so3_log
from loopmodel.loop.closer import LoopCloser, LoopClosure
from loopmodel.loop.closure import LoopEvent
from loopmodel.loop.features import FeatureSet
from loopmodel.loop.global_ba import GlobalBAResult, LoopObservations, global_hybrid_ba
from loopmodel.loop.vocabulary import Vocabulary
from loopmodel.priority import low_priority_pool, lower_thread_priority
from loopmodel.stages import LoopConstraint, LoopOutcome, LoopStage, MapState, NullLoopStage, ResumeFeatures
from loopmodel.types import Keyframe, StereoCalibration

__all__ = ["LoopClosingStage", "LoopConstraint", "LoopOutcome", "LoopStage", "MapState", "NullLoopStage"]

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass
class Detection:
    """What place recognition and verification of one keyframe produced.

    The closure (or None), the candidates rejected, how many temporal neighbours were skipped and
    the detection's wall time (s).
    """

    closure: LoopClosure | None
    rejected: list[LoopEvent]
    neighbours_skipped: int
    detect_s: float
    #: the keyframe's loop features (the session map's archiver takes them instead of detecting again)
    features: FeatureSet | None = None


def _moved_closure(closure: LoopClosure, kf_id: int, tracked: tuple[F64, NDArray[np.int64], F64]) -> LoopClosure:
    """``closure`` moved to keyframe ``kf_id``.

    ``tracked``: (``kf_from_match``, landmark ids, pixels) of the old features found in that keyframe
    (:meth:`LoopCloser.track_old_features`).
    """
    kf_from_match, ids, uv = tracked
    return LoopClosure(
        kf_id,
        closure.match_kf,
        kf_from_match,
        LoopObservations(kf_id, ids, uv),
        closure.n_descriptor_inliers,
        int(ids.size),
        closure.event,
        closure.detect_ms,
        closure.refine_ms,
        {**closure.info, "verified_at_keyframe": closure.query_kf},
    )


@dataclass
class _Moved:
    """A late loop after the apply worker (``loop.apply_worker: thread``).

    ``closure``: the loop as it is applied — moved to keyframe ``at_kf`` (``moved``: its old
    features tracked into that keyframe's image) or the detection's own; ``accepted``: the robust
    gate kept it.
    """

    closure: LoopClosure
    moved: bool
    accepted: bool
    at_kf: int


def detect_keyframe(closer: LoopCloser, kf: Keyframe, neighbours: set[int], query: bool) -> Detection:
    """Store ``kf`` in ``closer``'s database and look for a verified revisit."""
    det = closer.detector
    n_rej, n_skip = len(det.rejected), det.neighbours_skipped
    t0 = time.perf_counter()
    features = closer.keyframe_features(kf)
    closure = closer.process_keyframe(kf, neighbours=neighbours, query=query, features=features)
    return Detection(closure, det.rejected[n_rej:], det.neighbours_skipped - n_skip, time.perf_counter() - t0,
                     features)


#: The worker process's own loop closer (its keyframe database), made by :func:`_worker_start`.
_WORKER_CLOSER: LoopCloser | None = None


def _worker_start(calibration: StereoCalibration, config: LoopConfig, vocabulary: Vocabulary | None) -> None:
    global _WORKER_CLOSER
    _WORKER_CLOSER = LoopCloser(calibration, config, vocabulary)
    _warm_up_kernels()
    lower_thread_priority(config.worker_nice)  # its start at the run's priority, its detections below (kf12)


def _after(before: Future[Detection] | None, call: Callable[[], Detection]) -> Detection:
    """``call()`` once ``before`` (when given) has finished, whichever way."""
    if before is not None:
        wait_futures([before])
    return call()


def _worker_detect(kf: Keyframe, neighbours: set[int], query: bool) -> Detection:
    assert _WORKER_CLOSER is not None
    return dataclasses.replace(detect_keyframe(_WORKER_CLOSER, kf, neighbours, query), features=None)


def _worker_relocalize(image: NDArray[np.uint8], exclude_after: int) -> tuple[int | None, Any]:
    assert _WORKER_CLOSER is not None
    return _WORKER_CLOSER.relocalize(image, exclude_after=exclude_after)


def _warm_up_kernels() -> None:
    """Load the compiled kernels of detection and verification (vocabulary descent, P3P bank)."""
    from loopmodel.loop._vocabulary_kernels import warm_up as warm_up_vocabulary
    from loopmodel.loop.pnp import warm_up as warm_up_pnp

    warm_up_vocabulary()
    warm_up_pnp()


def _warm_up_gate() -> None:
    """One robust gate solve on a three-keyframe graph: the first one's set-up, off the tracking thread.

    bench scale (5,000-frame modeler, quiet machine): the first gate of a run took 949 ms (3.7 s at
    load 8; mostly the solver's lazy ``scipy.stats`` import), later ones 5-30 ms.
    """
    poses = {k: np.eye(4) for k in range(3)}
    for k in poses:
        poses[k][0, 3] = 0.05 * k
    loop = (2, 0, invert_pose(poses[2]) @ poses[0])
    try:
        keyframe_loop_inliers(poses, [(0, 1), (1, 2)], [loop], 1.0, 0.02, 1.0, 0.03, 0.99)
    except Exception:  # noqa: BLE001 - a warm-up only; the real gate reports its own errors
        logger.debug("loop gate warm-up failed", exc_info=True)


def _done(d: Detection) -> Future[Detection]:
    f: Future[Detection] = Future()
    f.set_result(d)
    return f


def _motion(a: F64, b: F64) -> tuple[float, float]:
    d = invert_pose(a) @ b
    return float(np.linalg.norm(d[:3, 3])), float(np.degrees(np.linalg.norm(so3_log(d[:3, :3]))))


def _new_observations(kf: Keyframe, obs: LoopObservations) -> F64:
    """Rows (landmark id, u, v) of the loop's observations of old landmarks that ``kf`` does not have yet."""
    mono = np.asarray(kf.mono_obs, dtype=float).reshape(-1, 3)
    have = set(mono[:, 0].astype(np.int64).tolist())
    keep = np.array([int(i) not in have for i in obs.landmark_ids], dtype=bool)
    return np.column_stack([obs.landmark_ids[keep].astype(float), np.asarray(obs.uv_px, float).reshape(-1, 2)[keep]])


def _with_observations(kf: Keyframe, obs: LoopObservations) -> Keyframe:
    """The keyframe with the loop's observations of old landmarks appended to its monocular observations.

    Those it has already are kept as they are.
    """
    if not obs.landmark_ids.size:
        return kf
    mono = np.asarray(kf.mono_obs, dtype=float).reshape(-1, 3)
    return dataclasses.replace(kf, mono_obs=np.vstack([mono, _new_observations(kf, obs)]))


class LoopClosingStage:
    """Relocalization and loop closing over the keyframes of a run (:class:`LoopStage`).

    ``calibration`` is the rectified calibration of the keyframes' pixels. ``via_backend``
    (the pipeline): loops become back-end constraints; otherwise the stage corrects them
    itself by the global hybrid BA, in a worker process when ``background``. ``vocabulary``: place
    recognition's (:func:`loopmodel.io.vocabulary_file.loop_vocabulary` reads the configured one;
    None: trained on the fly from the keyframes)."""

    def __init__(
        self,
        calibration: StereoCalibration,
        config: LoopConfig | None = None,
        *,
        vocabulary: Vocabulary | None = None,
        via_backend: bool = True,
        background: bool = True,
    ) -> None:
        self.config = config if config is not None else LoopConfig()
        self.closer = LoopCloser(calibration, self.config, vocabulary)
        self._vocabulary = vocabulary  # the detection worker's too
        self.keyframes: dict[int, Keyframe] = {}
        self.events: list[dict[str, Any]] = []
        self.rejected: list[dict[str, Any]] = []
        self.via_backend = via_backend
        #: Run the global BA in a worker process (GTSAM holds the GIL while optimising,
        #: so a thread would stall tracking) and apply it when done (:meth:`poll`).
        self.background = background
        self._pool: ProcessPoolExecutor | None = None
        self._pending: tuple[Future[GlobalBAResult], LoopClosure, dict[int, F64], float] | None = None
        self._rerun: LoopClosure | None = None
        #: records of the last outcome's constraints, completed from the next MapState
        self._awaiting: list[dict[str, Any]] = []
        #: loops the robust gate accepted, ``(query_kf, match_kf, kf_query_from_kf_match)`` (left camera
        #: frames; they join later gates' pose graphs)
        self._gated: list[tuple[int, int, F64]] = []
        #: Place recognition and verification in a worker (``detection_worker``); in the
        #: process variant the database lives there and ``self.closer`` keeps only the
        #: keyframes' images and landmarks (KLT stage, corrections)
        self._detect_pool: ThreadPoolExecutor | ProcessPoolExecutor | None = None
        self._inflight: deque[tuple[int, Future[Detection]]] = deque()
        # with loop.worker_nice, the thread worker's detections by keyframe until taken: those not started at
        # the end move to a thread at the run's priority (_take_back_queued)
        self._calls: dict[int, Callable[[], Detection]] = {}
        #: late loops being moved to their current keyframe and gated (``apply_worker: thread``)
        self._apply_pool: ThreadPoolExecutor | None = None
        self._moving: deque[Future[_Moved]] = deque()
        self.applied_between_frames = 0
        self._detections: list[tuple[int, Future[Detection]]] = []  # the last keyframe's (detection())
        self.neighbours_skipped = 0
        self.detect_s: list[float] = []
        if self.config.detection_worker == "process":
            self._workers().submit(int, 0)  # start the worker now, while tracking starts
        else:  # issue 33: the detection's compiled kernels loaded before the first frame, not in one
            _warm_up_kernels()
        if self.config.robust != "none":  # the gate runs on the tracking thread: warmed before the first frame
            _warm_up_gate()  # (issue 33: 0.25 s of CPU; beside the tracker it held the interpreter lock in frame 0)
        self.keyframes_not_queried = 0
        self.late_closures = 0
        self.detections_unapplied = 0
        self.detections_abandoned = 0
        self._final_constraints: list[LoopConstraint] = []
        # covisibility: (first, last landmark id, keyframe) per keyframe
        self._lm_ranges: list[tuple[int, int, int]] = []
        #: the record of the last closure whose old features the front end was asked to resume
        self._resume_record: dict[str, Any] | None = None

    @classmethod
    def from_config(
        cls, config: LoopConfig, calibration: StereoCalibration, vocabulary: Vocabulary | None = None
    ) -> LoopClosingStage:
        """The pipeline's stage: loops go to the back end as constraints."""
        return cls(calibration, config, vocabulary=vocabulary, via_backend=True)

    # ------------------------------------------------------------------ keyframes
    def on_keyframe(self, keyframe: Keyframe, state: MapState) -> LoopOutcome:
        """Process a new keyframe.

        Complete the records of the previous keyframe's loops from ``state``, apply a finished
        background correction, relocalize a new segment, look for a revisit. ``state.world_from_kf``
        must hold the new keyframe.
        """
        self._note_backend(state)
        self._note_resumed(keyframe)
        out = LoopOutcome(keyframe)
        self.keyframes[int(keyframe.id)] = keyframe
        self._collect(self.poll(state), out)
        self._apply_detections(out, state, wait=False)
        neighbours = self._temporal_neighbours(keyframe)
        if not keyframe.connected and len(self.keyframes) > 1:
            self._apply_detections(out, state, wait=True)  # relocalization reads the database
            self._relocalize_segment(out, state)
        mode = self.config.detection_worker
        if mode == "none":
            d = detect_keyframe(self.closer, out.keyframe, neighbours, True)
            self._detections = [(int(keyframe.id), _done(d))]
            closure = self._note(d)
            if closure is not None:
                self._close(closure, out, state)
        else:
            query = len(self._inflight) < self.config.max_queued_keyframes
            self.keyframes_not_queried += not query
            if mode == "process":
                self.closer.remember(out.keyframe)
                fut = self._workers().submit(_worker_detect, out.keyframe, neighbours, query)
            else:
                call = functools.partial(detect_keyframe, self.closer, out.keyframe, neighbours, query)
                if self.config.worker_nice > 0:
                    self._calls[int(keyframe.id)] = call
                fut = self._workers().submit(call)
            self._inflight.append((int(keyframe.id), fut))
            self._detections = [(int(keyframe.id), fut)]
        self.keyframes[int(keyframe.id)] = out.keyframe
        return out

    def detection(self, kf_id: int) -> Future[Detection] | None:
        """The detection of the last keyframe given to :meth:`on_keyframe` when it is ``kf_id``.

        Its ``features`` are the keyframe's loop features (None from a detection process).
        """
        return next((f for k, f in self._detections if k == kf_id), None)

    def _workers(self) -> ThreadPoolExecutor | ProcessPoolExecutor:
        if self._detect_pool is None:
            if self.config.detection_worker == "process":
                self._detect_pool = ProcessPoolExecutor(
                    1,
                    mp_context=mp.get_context("spawn"),
                    initializer=_worker_start,
                    initargs=(self.closer.calibration, self.config, self._vocabulary),
                )
            else:
                self._detect_pool = low_priority_pool("loop-detect", self.config.worker_nice)
        return self._detect_pool

    def _note(self, d: Detection) -> LoopClosure | None:
        """Record a detection's rejected candidates and counts, and its closure.

        The process worker's closures join this closer's list.
        """
        for ev in d.rejected:
            self.rejected.append({"query_kf": ev.query_id, "match_kf": ev.match_id, "reason": ev.reason})
        self.neighbours_skipped += d.neighbours_skipped
        self.detect_s.append(d.detect_s)
        if d.closure is not None and self.config.detection_worker == "process":
            self.closer.closures.append(d.closure)
        return d.closure

    def _apply_detections(self, out: LoopOutcome, state: MapState, wait: bool) -> None:
        """The worker's finished detections, in keyframe order (``wait``: all of them).

        A loop found for an earlier keyframe is applied at ``out``'s keyframe.
        """
        while self._inflight and (wait or self._inflight[0][1].done()):
            kf_id, fut = self._inflight.popleft()
            self._calls.pop(kf_id, None)
            try:
                closure = self._note(fut.result())
            except LoopmodelError as exc:  # a failed detection is logged, never applied
                logger.warning("loop detection of keyframe %d failed (%s)", kf_id, exc)
                continue
            if closure is None:
                continue
            self.late_closures += 1
            if self.via_backend and self.config.apply_worker == "thread" and closure.query_kf != int(out.keyframe.id):
                self._submit_move(closure, out.keyframe, state)
            else:
                self._close_late(closure, out, state)

    def _predicted_from_match(self, closure: LoopClosure, cur: Keyframe, state: MapState) -> F64:
        """``current_from_match`` (rectified frames) the tracker's poses and the loop's pose predict."""
        world = state.world_from_kf
        w_q = np.asarray(world[closure.query_kf]) @ invert_pose(self.keyframes[closure.query_kf].rect_from_cam)
        w_c = np.asarray(cur.world_from_kf) @ invert_pose(cur.rect_from_cam)
        return invert_pose(w_c) @ w_q @ closure.query_from_match

    def _submit_move(self, closure: LoopClosure, cur: Keyframe, state: MapState) -> None:
        """Hand a late loop to the apply worker: moved to keyframe ``cur`` and gated there, beside tracking.

        The worker gets copies of the poses and the keyframe table as they are now; the result is
        applied between frames (:meth:`between_frames`).
        """
        pred = self._predicted_from_match(closure, cur, state)
        world = {k: np.array(v, dtype=float) for k, v in state.world_from_kf.items()}
        if self._apply_pool is None:
            self._apply_pool = low_priority_pool("loop-apply", self.config.worker_nice)
        job = self._apply_pool.submit(
            self._move, closure, int(cur.id), np.asarray(cur.image), pred, world, dict(self.keyframes)
        )
        self._moving.append(job)

    def _move(
        self,
        closure: LoopClosure,
        cur_id: int,
        image: NDArray[np.uint8],
        pred: F64,
        world_from_kf: dict[int, F64],
        keyframes: dict[int, Keyframe],
    ) -> _Moved:
        """The apply worker's job: the old features tracked into keyframe ``cur_id``'s ``image``, the gate.

        ``pred``: the predicted ``current_from_match`` (rectified); ``world_from_kf`` and
        ``keyframes``: the stage's as they were when the job was given (read only).
        """
        tr = self.closer.track_old_features(closure.match_kf, image, pred)
        if tr is None or tr[1].size < self.config.min_inliers:
            return _Moved(closure, False, self._robust_gate(closure, world_from_kf, keyframes), cur_id)
        moved = _moved_closure(closure, cur_id, tr)
        accepted = self._robust_gate(moved, world_from_kf, keyframes)
        if accepted:
            self.closer.closures.append(moved)
        return _Moved(moved, True, accepted, cur_id)

    def between_frames(self, state: MapState) -> LoopOutcome | None:
        """The late loops the apply worker finished since the last call, or None (never waits).

        Each accepted loop becomes a constraint whose keyframe (already with the back end) brings
        its observations of the old landmarks (``LoopConstraint.kf_a_mono_obs``); while that keyframe
        is still the latest one, the old features go to the front end (``resume``, with
        ``loop.late_resume``). The outcome's
        ``keyframe`` is the stage's latest keyframe.
        """
        if not self._moving or not self._moving[0].done():
            return None
        self._note_backend(state)
        out = LoopOutcome(self.keyframes[max(self.keyframes)])
        while self._moving and self._moving[0].done():
            moved = self._take_move(self._moving.popleft(), None)
            if moved is not None:
                self._apply_moved(moved, out, state, resume=self.config.late_resume)
        return out

    def _take_move(self, job: Future[_Moved], timeout_s: float | None) -> _Moved | None:
        """A move job's result (waiting at most ``timeout_s``); None when it failed (logged)."""
        try:
            return job.result(timeout=timeout_s)
        except LoopmodelError as exc:
            logger.warning("late loop not applied (%s)", exc)
            return None

    def _apply_moved(self, moved: _Moved, out: LoopOutcome, state: MapState, resume: bool) -> None:
        """An accepted late loop into ``out``: its record and constraint (``resume``: old features too)."""
        self.applied_between_frames += moved.accepted
        if not moved.accepted:
            return
        closure = moved.closure
        if not moved.moved:
            with_obs = self.config.late_loop_observations
            out.constraints.append(self._constraint_only(closure, state, moved.at_kf, observations=with_obs))
            out.events.append(self.events[-1])
            return
        record = self._loop_record(closure)
        record["applied_at_keyframe"] = moved.at_kf
        record["applied_between_frames"] = True
        self.events.append(record)
        out.events.append(record)
        record["old_features_resumed"] = 0
        if resume and moved.at_kf == max(self.keyframes):  # still the front end's active keyframe
            request = self._resume_request(closure)
            if request is not None and (out.resume is None or len(request) > len(out.resume)):
                if self._resume_record is not None and out.resume is not None:
                    self._resume_record["old_features_resumed"] = 0
                out.resume = request
                record["old_features_resumed"] = len(request)
                self._resume_record = record
        record["pose_before"] = np.asarray(state.world_from_kf[moved.at_kf]).copy()
        self._awaiting.append(record)
        kf, m = self.keyframes[moved.at_kf], self.keyframes[closure.match_kf]
        q_from_m = invert_pose(kf.rect_from_cam) @ closure.query_from_match @ m.rect_from_cam
        rows = _new_observations(kf, closure.observations)
        out.constraints.append(LoopConstraint(moved.at_kf, closure.match_kf, q_from_m, rows if rows.size else None))

    def _finish_moves(self, state: MapState) -> None:
        """The apply worker's pending loops, waited for (``drain_timeout_s``); their constraints are final."""
        deadline = time.perf_counter() + self.config.drain_timeout_s
        out = LoopOutcome(self.keyframes[max(self.keyframes)]) if self.keyframes else None
        while self._moving and out is not None:
            job = self._moving.popleft()
            try:
                moved = self._take_move(job, max(deadline - time.perf_counter(), 0.0))
            except TimeoutError:
                logger.warning("loop apply worker: %d late loops not done, left out", 1 + len(self._moving))
                self.detections_abandoned += 1 + len(self._moving)
                self._moving.clear()
                break
            if moved is not None:
                self._apply_moved(moved, out, state, resume=False)
        self._moving.clear()
        if out is not None:
            self._final_constraints.extend(out.constraints)
        if self._apply_pool is not None:
            self._apply_pool.shutdown(wait=False, cancel_futures=True)
            self._apply_pool = None

    def _close_late(self, closure: LoopClosure, out: LoopOutcome, state: MapState) -> None:
        """A loop verified for an earlier keyframe, applied at the current one.

        The old keyframe's features are tracked into the current image from the predicted
        ``current_from_match`` (tracker poses times the loop's pose) and the loop is closed from the
        current keyframe; when too few are found, the loop's own relative pose becomes the
        constraint (with the query keyframe's observations of the old landmarks when
        ``late_loop_observations``, as inline detection would have given them).
        """
        cur = out.keyframe
        c, q = int(cur.id), closure.query_kf
        pred = self._predicted_from_match(closure, cur, state)
        tr = self.closer.track_old_features(closure.match_kf, cur.image, pred) if c != q else None
        if tr is not None and tr[1].size >= self.config.min_inliers:
            moved = _moved_closure(closure, c, tr)
            self.closer.closures.append(moved)
            self._close(moved, out, state)
            return
        if not self.via_backend or c == q:
            self._close(closure, out, state)
            return
        if not self._robust_gate(closure, state.world_from_kf):
            return
        with_obs = self.config.late_loop_observations
        out.constraints.append(self._constraint_only(closure, state, c, observations=with_obs))
        out.events.append(self.events[-1])

    def _constraint_only(
        self, closure: LoopClosure, state: MapState, at_keyframe: int | None, observations: bool = False
    ) -> LoopConstraint:
        """The record and the relative-pose constraint of a loop whose query keyframe is already in the back end.

        ``observations``: the constraint carries the query keyframe's observations of the old
        landmarks (``LoopConstraint.kf_a_mono_obs``); otherwise the loop goes without them.
        """
        q = closure.query_kf
        record = self._loop_record(closure)
        record["applied_at_keyframe"] = at_keyframe
        obs = closure.observations
        with_obs = observations and obs.kf_id == q and obs.landmark_ids.size > 0
        record["loop_observations"] = int(obs.landmark_ids.size) if with_obs else 0
        self.events.append(record)
        record["pose_before"] = np.asarray(state.world_from_kf[q]).copy()
        self._awaiting.append(record)
        m = self.keyframes[closure.match_kf]
        q_from_m = invert_pose(self.keyframes[q].rect_from_cam) @ closure.query_from_match @ m.rect_from_cam
        rows = np.column_stack([obs.landmark_ids.astype(float), np.asarray(obs.uv_px, float).reshape(-1, 2)])
        return LoopConstraint(q, closure.match_kf, q_from_m, rows if with_obs else None)

    def _temporal_neighbours(self, kf: Keyframe) -> set[int]:
        """Keyframes co-visible with the new keyframe: those whose landmarks it observes.

        Its stereo and monocular observations, as ORB-SLAM's loop detection excludes the current
        keyframe's covisible ones: the front end and the back end link these already, and a loop with
        them adds nothing (``min_gap_keyframes`` keeps the recent ones out as well). One level only:
        with local-map tracking (issue 36) a keyframe observes the last ``frontend.local_map_keyframes``
        keyframes' landmarks, and a second level (theirs) excluded true revisits 8 keyframes back on
        the rendered revisit sequences of the loop tests. Landmarks are found by each keyframe's id range.
        """
        q = int(kf.id)
        ids = np.asarray(kf.landmark_ids, dtype=np.int64).ravel()
        mono = np.asarray(kf.mono_obs, dtype=float).reshape(-1, 3)
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
        return direct

    @staticmethod
    def _collect(done: tuple[dict[str, Any], dict[int, F64]] | None, out: LoopOutcome) -> None:
        if done is not None:
            out.events.append(done[0])
            out.corrections.update(done[1])

    def _note_backend(self, state: MapState) -> None:
        """Record how the back end handled the keyframes of the previous keyframe's loops.

        How far it moved them, how long that took, and the ids of their constraints.
        """
        ids = list(state.last_constraint_ids)
        for record in self._awaiting:
            before = record.pop("pose_before", None)
            k = record["keyframe"]
            if before is not None and k in state.world_from_kf:
                key = "correction" if record["type"] == "loop" else "backend_correction"
                record[key + "_m"], record[key + "_deg"] = _motion(before, np.asarray(state.world_from_kf[k]))
            record["constraint_id"] = ids.pop(0) if ids else None
            record["optimise_ms"] = state.last_update_ms
        self._awaiting = []

    def _relocalize_segment(self, out: LoopOutcome, state: MapState) -> None:
        """Place the first keyframe of a new segment in the old map.

        Descriptors and the P3P bank against the stored keyframes, or — when that fails — the latest
        keyframes' features searched by KLT from the rough (motion-model) pose; then the KLT
        accuracy stage. The observations link the segments in later global BAs.
        """
        t0 = time.perf_counter()
        kf = out.keyframe
        new_id = int(kf.id)
        world = state.world_from_kf

        def world_from_rect(k: int) -> F64:
            return np.asarray(world[k]) @ invert_pose(self.keyframes[k].rect_from_cam)

        found = self._find_old_keyframe(kf, world_from_rect)
        if found is None:
            return
        kf_id, new_from_old, inliers, method = found
        tr = self.closer.track_old_features(kf_id, kf.image, new_from_old)
        obs_ids, obs_uv = np.zeros(0, np.int64), np.zeros((0, 2))
        if tr is not None and tr[1].size >= self.config.min_inliers:
            new_from_old, obs_ids, obs_uv = tr
        closure = LoopClosure(
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
        self.closer.closures.append(closure)
        world_from_new = world_from_rect(kf_id) @ invert_pose(new_from_old) @ kf.rect_from_cam
        trans, rot = _motion(np.asarray(world[new_id]), world_from_new)
        out.corrections[new_id] = world_from_new
        out.keyframe = dataclasses.replace(kf, world_from_kf=world_from_new)  # the back end's initial guess
        record = {
            "type": "relocalization",
            "method": method,
            "keyframe": new_id,
            "frame": kf.frame_index,
            "match_keyframe": int(kf_id),
            "match_frame": self.keyframes[kf_id].frame_index,
            "inliers": inliers,
            "klt_inliers": int(obs_ids.size),
            "correction_m": trans,
            "correction_deg": rot,
            "time_ms": (time.perf_counter() - t0) * 1e3,
        }
        self.events.append(record)
        out.events.append(record)
        if self.via_backend:
            self._to_backend(closure, record, out)
        logger.info("keyframe %d relocalized against keyframe %d (%s)", new_id, kf_id, method)

    def _find_old_keyframe(self, kf: Keyframe, world_from_rect: Any) -> tuple[int, F64, int, str] | None:
        """An old keyframe and ``new_from_old`` (rectified frames) for a relocalization.

        With its inlier count and the method that found it; None when both methods fail.
        """
        new_id = int(kf.id)
        if self.config.detection_worker == "process":  # the database is in the worker
            kf_id, res = self._workers().submit(_worker_relocalize, kf.image, new_id - 1).result()
        else:
            kf_id, res = self.closer.relocalize(kf.image, exclude_after=new_id - 1)
        if kf_id is not None and res.cam_from_map is not None:
            return kf_id, res.cam_from_map, res.n_inliers, "descriptors"
        older = sorted(k for k in self.keyframes if k < new_id)[-3:][::-1]
        for cand in older:
            pred = invert_pose(world_from_rect(new_id)) @ world_from_rect(cand)
            tr = self.closer.track_old_features(cand, kf.image, pred)
            if tr is not None and tr[1].size >= self.config.min_inliers:
                return cand, tr[0], int(tr[1].size), "klt from predicted pose"
        logger.info("keyframe %d: relocalization failed (%s)", new_id, res.reason)
        return None

    def _close(self, closure: LoopClosure, out: LoopOutcome, state: MapState) -> None:
        """Hand a verified loop to the back end, or start its correction.

        The correction runs in the worker process when ``background``; a finished one lands in
        ``out``. A loop the robust gate rejects (:meth:`_robust_gate`) is recorded in ``rejected``
        and never applied.
        """
        if not self._robust_gate(closure, state.world_from_kf):
            return
        if self.via_backend:
            record = self._loop_record(closure)
            record["applied_at_keyframe"] = max(self.keyframes)
            self.events.append(record)
            out.events.append(record)
            self._to_backend(closure, record, out)
            return
        if self._pending is not None:
            self._rerun = closure  # the running BA finishes first; then this loop's window
            return
        self._collect(self._submit(closure, dict(state.world_from_kf)), out)

    def _cam_from_cam(self, closure: LoopClosure, keyframes: Mapping[int, Keyframe] | None = None) -> F64:
        """The closure's ``kf_query_from_kf_match`` between left camera (not rectified) frames."""
        kfs = self.keyframes if keyframes is None else keyframes
        q, m = kfs[closure.query_kf], kfs[closure.match_kf]
        return invert_pose(q.rect_from_cam) @ closure.query_from_match @ m.rect_from_cam

    def _robust_gate(
        self, closure: LoopClosure, world_from_kf: Mapping[int, F64], keyframes: Mapping[int, Keyframe] | None = None
    ) -> bool:
        """GNC-TLS on the keyframe pose graph from the loop's old keyframe to the current one.

        Edges: the current relative poses of consecutive connected keyframes (known inliers), the
        loops accepted before (at most ``loop.robust_max_loops``: those that leave the least odometry
        between this loop's keyframes) and this one; only the loops' keyframes are nodes, each chain
        between two of them one odometry edge of the chain's information (:func:`gate_keyframe_loop`). False
        when this loop is an outlier (it is then kept in ``rejected``, with the reason). A window
        that a new segment (unconnected keyframe) breaks is not gated. ``keyframes``: the stage's
        keyframe table or a copy of it (the apply worker's).
        """
        if self.config.robust == "none":
            return True
        kfs = self.keyframes if keyframes is None else keyframes
        lo, hi = closure.match_kf, closure.query_kf
        ids = sorted(k for k in kfs if lo <= k <= hi and k in world_from_kf)
        if len(ids) < 2 or ids[0] != lo or ids[-1] != hi:
            return True
        if not all(kfs[k].connected for k in ids[1:]):
            return True
        cfg = self.config
        earlier = [g for g in self._gated if lo <= g[1] and g[0] <= hi and g[0] in kfs and g[1] in kfs]
        loop = (hi, lo, self._cam_from_cam(closure, kfs))
        t0 = time.perf_counter()
        sigmas = GateSigmas(
            cfg.robust_odometry_sigma_deg,
            cfg.robust_odometry_sigma_m,
            cfg.robust_loop_sigma_deg,
            cfg.robust_loop_sigma_m,
        )
        accepted, res, n_loops = gate_keyframe_loop(
            world_from_kf,
            ids,
            earlier,
            loop,
            sigmas,
            cfg.robust_probability,
            cfg.robust_max_loops or None,
        )
        gate_ms = (time.perf_counter() - t0) * 1e3
        closure.info["robust_gate_loops"] = n_loops
        if accepted:
            self._gated.append(loop)
            closure.info["robust_gate_ms"] = gate_ms
            return True
        # (by identity, in place: the detection thread may append meanwhile)
        gone = [i for i, c in enumerate(self.closer.closures) if c is closure]
        for i in reversed(gone):
            del self.closer.closures[i]
        weight = float(res.weights[-1])
        reason = f"robust gate: inconsistent with odometry and earlier loops (GNC weight {weight:.2f})"
        self.rejected.append({"query_kf": hi, "match_kf": lo, "reason": reason, "gate_ms": gate_ms})
        logger.info("loop %d -> %d rejected by the robust gate", hi, lo)
        return False

    def _note_resumed(self, kf: Keyframe) -> None:
        """Add to the last resumption's record how many old features the front end observed in ``kf``."""
        rec = self._resume_record
        info = kf.ba_info
        if rec is None or "resumed_features" not in info:
            return
        if int(info.get("resumed_from_keyframe", -1)) != rec["match_keyframe"]:
            return
        rec.setdefault("old_features_tracked_on", []).append(int(info["resumed_features"]))

    def _resume_request(self, closure: LoopClosure) -> ResumeFeatures | None:
        """The closure's old features found in its query keyframe, for the front end to track on."""
        obs = closure.observations
        old = self.keyframes.get(closure.match_kf)
        if old is None or not obs.landmark_ids.size or not np.asarray(old.image).size:
            return None
        ids = np.asarray(old.landmark_ids, np.int64).reshape(-1)
        order = np.argsort(ids)
        pos = np.searchsorted(ids[order], obs.landmark_ids)
        pos = np.minimum(pos, ids.size - 1)
        found = ids[order][pos] == obs.landmark_ids
        idx = order[pos[found]]
        rect_from_cam = np.asarray(old.rect_from_cam)
        pts = np.asarray(old.points_in_kf, float).reshape(-1, 3)[idx]
        return ResumeFeatures(
            keyframe=closure.query_kf,
            match_keyframe=closure.match_kf,
            landmark_ids=ids[idx],
            uv_px=np.asarray(obs.uv_px, float).reshape(-1, 2)[found],
            points_in_match=pts @ rect_from_cam[:3, :3].T + rect_from_cam[:3, 3],
            match_uv_px=np.asarray(old.stereo_px, float).reshape(-1, 3)[idx][:, [0, 2]],
            match_image=np.asarray(old.image),
            kf_from_match=np.asarray(closure.query_from_match, float),
        )

    def _to_backend(self, closure: LoopClosure, record: dict[str, Any], out: LoopOutcome) -> None:
        """Append the closure's observations of old landmarks to the keyframe's monocular observations.

        Returns its relative pose (left camera frames) as a constraint, and asks the front end to
        track the old features on (``out.resume``).
        """
        out.keyframe = _with_observations(out.keyframe, closure.observations)
        record["old_features_resumed"] = 0
        if closure.query_kf == int(out.keyframe.id):
            resume = self._resume_request(closure)
            # several closures at one keyframe: the front end resumes the largest old set
            if resume is not None and (out.resume is None or len(resume) > len(out.resume)):
                if self._resume_record is not None and out.resume is not None:
                    self._resume_record["old_features_resumed"] = 0
                out.resume = resume
                record["old_features_resumed"] = len(resume)
                self._resume_record = record
        record["pose_before"] = np.asarray(out.keyframe.world_from_kf).copy()
        self._awaiting.append(record)
        q, m = self.keyframes[closure.query_kf], self.keyframes[closure.match_kf]
        q_from_m = invert_pose(q.rect_from_cam) @ closure.query_from_match @ m.rect_from_cam
        out.constraints.append(LoopConstraint(closure.query_kf, closure.match_kf, q_from_m))

    def _loop_record(self, closure: LoopClosure) -> dict[str, Any]:
        return {
            "type": "loop",
            "keyframe": closure.query_kf,
            "frame": self.keyframes[closure.query_kf].frame_index,
            "match_keyframe": closure.match_kf,
            "match_frame": self.keyframes[closure.match_kf].frame_index,
            "inliers": closure.n_descriptor_inliers,
            "klt_inliers": closure.n_klt_inliers,
            "loop_observations": int(closure.observations.landmark_ids.size),
            "correction_m": 0.0,
            "correction_deg": 0.0,
            "optimise_ms": 0.0,
            "robust_gate_ms": closure.info.get("robust_gate_ms"),
            "via": "backend",
        }

    # ------------------------------------------------------------------ standalone global BA
    def _submit(self, closure: LoopClosure, before: dict[int, F64]) -> tuple[dict[str, Any], dict[int, F64]] | None:
        # the BA starts from the current estimate
        kfs = [
            dataclasses.replace(k, world_from_kf=np.asarray(before.get(k.id, k.world_from_kf)))
            for k in (self.keyframes[i] for i in sorted(self.keyframes))
        ]
        problem = self.closer.correction_problem(kfs, closure)
        t0 = time.perf_counter()
        if not self.background:
            return self._finish(closure, global_hybrid_ba(**problem), before, t0, before)
        if self._pool is None:
            self._pool = ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"))
        self._pending = (self._pool.submit(global_hybrid_ba, **problem), closure, before, t0)
        return None

    def poll(self, state: MapState, wait: bool = False) -> tuple[dict[str, Any], dict[int, F64]] | None:
        """A finished background correction as its record and the corrected poses, or None.

        ``wait``: block until it is done.
        """
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
            done = None
        else:
            done = self._finish(closure, res, before, t0, state.world_from_kf)
        if self._rerun is not None:
            again, self._rerun = self._rerun, None
            now = dict(state.world_from_kf)
            if done is not None:
                now.update(done[1])
            self._submit(again, now)
        return done

    def close(self, state: MapState) -> dict[int, F64]:
        """Complete the last records; wait for every pending correction; stop the worker process.

        Returns the corrections that arrived meanwhile.
        """
        self._note_backend(state)
        self._finish_moves(state)
        corrected = self._drain(state)
        world = {**state.world_from_kf, **corrected}
        while self._pending is not None:
            done = self.poll(MapState(world), wait=True)
            if done is not None:
                corrected.update(done[1])
                world.update(done[1])
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        return corrected

    def _take_back_queued(self) -> ThreadPoolExecutor | None:
        """The thread worker's detections not started yet, moved to a thread at the run's priority.

        Taken back from the last one until one has started (the worker takes them front first, so it
        never starts one after a later one was taken back); the new thread runs them in order, its
        first after the worker's last: the database sees the keyframes in order. The new thread.
        """
        calls, self._calls = self._calls, {}
        if self.config.worker_nice <= 0:  # the worker runs at the run's priority already
            return None
        back: list[int] = []
        for i in reversed(range(len(self._inflight))):
            kf_id, fut = self._inflight[i]
            if kf_id not in calls or not fut.cancel():
                break
            back.append(i)
        if not back:
            return None
        pool = ThreadPoolExecutor(1, thread_name_prefix="loop-detect-drain")  # this thread's priority
        before = self._inflight[back[-1] - 1][1] if back[-1] > 0 else None
        for i in reversed(back):
            kf_id = self._inflight[i][0]
            self._inflight[i] = (kf_id, pool.submit(_after, before, calls[kf_id]))
            before = None  # one thread: the others follow the first
        return pool

    def _drain(self, state: MapState) -> dict[int, F64]:
        """Wait for the worker's pending detections (``drain_timeout_s`` in all), then stop it.

        Their loops have no later keyframe to be applied at. With the back end each becomes a
        constraint (:meth:`final_constraints`), which with ``late_loop_observations`` carries its
        query keyframe's observations of the old landmarks: the back end then holds what inline
        detection would have given it. Without the back end their global BA runs now; the
        corrections are returned. Detections still running at the deadline are abandoned
        (``loop_detections_abandoned``). The thread worker's detections it has not started move to a
        thread at the run's priority (kf12: the worker's is ``loop.worker_nice`` below it).
        """
        deadline = time.perf_counter() + self.config.drain_timeout_s
        corrected: dict[int, F64] = {}
        moved = self._take_back_queued()
        while self._inflight:
            kf_id, fut = self._inflight.popleft()
            try:
                closure = self._note(fut.result(timeout=max(deadline - time.perf_counter(), 0.0)))
            except TimeoutError:
                self.detections_abandoned = 1 + len(self._inflight)
                logger.warning(
                    "loop detection: %d keyframes not done after %.0f s, left out",
                    self.detections_abandoned,
                    self.config.drain_timeout_s,
                )
                for _, rest in self._inflight:
                    rest.cancel()
                self._inflight.clear()
                break
            except LoopmodelError as exc:
                logger.warning("loop detection of keyframe %d failed (%s)", kf_id, exc)
                continue
            if closure is None:
                continue
            self.detections_unapplied += 1
            if self.via_backend:
                if self._robust_gate(closure, state.world_from_kf):
                    with_obs = self.config.late_loop_observations
                    self._final_constraints.append(self._constraint_only(closure, state, None, observations=with_obs))
            else:
                last = LoopOutcome(self.keyframes[max(self.keyframes)])
                self._close(closure, last, state)
                corrected.update(last.corrections)
        for pool in (self._detect_pool, moved):
            if pool is not None:
                pool.shutdown(wait=not self.detections_abandoned, cancel_futures=True)
        self._detect_pool = None
        return corrected

    def final_constraints(self) -> list[LoopConstraint]:
        """Constraints of the loops whose detection finished after the last keyframe."""
        out, self._final_constraints = self._final_constraints, []
        return out

    def _finish(
        self,
        closure: LoopClosure,
        res: GlobalBAResult,
        before: dict[int, F64],
        t0: float,
        now: Mapping[int, F64],
    ) -> tuple[dict[str, Any], dict[int, F64]]:
        corrected = dict(res.world_from_kf)
        # keyframes created while the BA ran move with the loop's current keyframe
        # (through their measured relative transforms when they have them)
        delta = corrected[closure.query_kf] @ invert_pose(before[closure.query_kf])
        for k in sorted(now):
            if k <= closure.query_kf or k not in self.keyframes:
                continue
            kf = self.keyframes[k]
            prev = kf.prev_keyframe_id
            rel = kf.kf_prev_from_kf
            if kf.connected and rel is not None and prev in corrected:
                corrected[k] = corrected[prev] @ np.asarray(rel)
            else:
                corrected[k] = delta @ np.asarray(now[k])
        trans, rot = _motion(before[closure.query_kf], res.world_from_kf[closure.query_kf])
        record = {
            "type": "loop",
            "keyframe": closure.query_kf,
            "frame": self.keyframes[closure.query_kf].frame_index,
            "match_keyframe": closure.match_kf,
            "match_frame": self.keyframes[closure.match_kf].frame_index,
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
        return record, corrected

    # ------------------------------------------------------------------ metrics
    def metrics(self) -> dict[str, Any]:
        """Summary for ``metrics.json``."""
        for record in self._awaiting:  # loops given to the back end at the end: no later state to read
            record.pop("pose_before", None)
        loops = [e for e in self.events if e["type"] == "loop"]
        return {
            "loop_closure_count": len(loops),
            "relocalization_count": len(self.events) - len(loops),
            "loop_events": self.events,
            "loop_candidates_rejected": len(self.rejected),
            "loop_neighbours_skipped": self.neighbours_skipped,
            "loop_keyframes_not_queried": self.keyframes_not_queried,
            "loop_closures_late": self.late_closures,
            "loop_closures_applied_between_frames": self.applied_between_frames,
            "loop_closures_after_last_keyframe": self.detections_unapplied,
            "loop_detections_abandoned": self.detections_abandoned,
            "loop_detect_ms_median": float(np.median(self.detect_s) * 1e3) if self.detect_s else None,
            "loop_detection_worker": self.config.detection_worker,
        }
