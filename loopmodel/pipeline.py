"""Wiring of the stages, as a recipe.

A sequence's frames go through the front end; each keyframe goes through loop closing, the anchored
trajectory and the back end; corrections flow back to the front end and the map by one mechanism; at
the end the back end and the mapping finish, and the result is returned (and written by
:func:`loopmodel.io.results.write_results`).

Stages and their one entry point per event (all declared on their protocols):

* front end  ``FrontEnd.process(frame) -> FrameResult`` (a keyframe when it makes one);
* loop stage ``LoopStage.on_keyframe(keyframe, MapState) -> LoopOutcome`` (the keyframe to
  pass on, loop constraints, pose corrections), ``close(MapState)``, ``metrics()``;
  :class:`~loopmodel.stages.NullLoopStage` when loop closing is off;
* back end   ``Backend.add_keyframe``, ``add_loop_constraint``, ``estimate``, and at the end
  ``final_estimate(RefineConfig | None)``, ``metrics()``;
* mapping    ``AnchoredTrajectory.set_keyframe`` / ``add_frame`` / ``update_keyframes`` (frame
  poses anchored to keyframes; the live :class:`StripeMap` follows them),
  ``LiveMapping.feed`` / ``on_keyframe`` / ``close`` / ``mesh`` /
  ``metrics``; :func:`loopmodel.mapping.final.start_final_mesh` at the end (in the run's process, or
  in the live mesh's idle worker process while the session map is made).

A stop request (:class:`StopFlag`, set by the signal handlers of :func:`stop_on_signals`)
is checked between frames, so every frame's and keyframe's bookkeeping is done whole.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import gc
import importlib
import itertools
import logging
import multiprocessing as mp
import queue
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import numpy.ma  # noqa: F401 - np.median's lazy import, else 126 ms of frame 0 (KITTI clip, issue 33)

from loopmodel.backend import Backend, BackendEstimate, create_backend
from loopmodel.backend.worker import settle, start_backend
from loopmodel.config import Config
from loopmodel.errors import LoopmodelError, RunInterrupted
from loopmodel.frontend import FrameResult, FrontEnd, Keyframe
from loopmodel.frontend.metrics import frontend_metrics, percentile_or_none
from loopmodel.io.base import Sequence
from loopmodel.io.results import EarlyFiles, LogCapture, ResultsFolder, write_results, write_results_early
from loopmodel.listener import RunListener
from loopmodel.mapping.anchored import AnchoredTrajectory
from loopmodel.mapping.extraction import StripeExtractor
from loopmodel.mapping.final import (
    FinalMeshJob,
    FinalMeshWorker,
    MovedMeshJob,
    end_pool,
    load_mesh_modules,
    start_final_mesh,
)
from loopmodel.mapping.live import LiveMapping
from loopmodel.mapping.stripe_map import StripeMap
from loopmodel.open3d_import import load_open3d, without_plotly_viewer
from loopmodel.result import RunResult
from loopmodel.sessions import Resumed, map_session
from loopmodel.stages import LoopConstraint, LoopStage, MapState, NullLoopStage
from loopmodel.types import ScanFrame, StereoCalibration, StereoFrame, StripeProfile, Trajectory

if TYPE_CHECKING:
    from loopmodel.calibration.retrack import RetrackedFrames
    from loopmodel.eval.of_run import Evaluation, Prepared
    from loopmodel.loop.session_map import ResumePoint, SessionMap
    from loopmodel.loop.vocabulary import Vocabulary
    from loopmodel.mapping.stripe_feed import ExtractionWorker

logger = logging.getLogger(__name__)

# progress(frames_done, frames_total, frames_per_second)
ProgressFn = Callable[[int, int, float], None]
# progress(frames_done, frames_total, frames_per_second, keyframes)
PipelineProgressFn = Callable[[int, int, float, int], None]
# finishing(step, seconds): a finishing step starts (seconds None) or is done (its wall time);
# steps in order: FINISH_STEPS
FinishFn = Callable[[str, float | None], None]

#: The steps after the last frame, in order (``metrics.json`` ``finish_s`` keys): the loop and mesh
#: workers stopped (pending loop detections drained), the back end's final refinement (the final
#: mesh started at its end), the session map (with ``mapping.final_mesh_in_live_worker`` made while
#: the live mesh's idle worker meshes; a localization's or an extension's results), the final mesh
#: (made here, or waited for), the evaluation
#: against ground truth (by the callers of :func:`process`, when asked), the results files (not in
#: ``metrics.json``, which is one of them). Each step's time is the run's own wall time in it, so
#: they add up to the finish (the mesh's own time in its process: ``final_mesh_s``).
FINISH_STEPS = ("workers", "final_refinement", "map", "mesh", "evaluation", "write")

#: The result of :func:`run_pipeline` (the name of earlier versions).
RunOutput = RunResult

__all__ = [
    "FINISH_STEPS",
    "FinishFn",
    "RunOutput",
    "RunResult",
    "StopFlag",
    "frontend_metrics",
    "frontend_only",
    "interrupted_error",
    "process",
    "run",
    "run_frontend",
    "run_pipeline",
    "stop_on_signals",
    "timed_step",
]

F64 = np.ndarray
#: a sequence's laser data as the run receives it
LaserKind = Literal["none", "stripes", "images"]


# --------------------------------------------------------------------------- metrics
def _online_trajectory(frames: list[FrameResult]) -> Trajectory:
    ok = [f for f in frames if f.ok]
    if not ok:
        return Trajectory(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))
    return Trajectory(np.array([f.timestamp_ns for f in ok]), np.stack([f.world_from_cam for f in ok]))


def _quantiles(values: list[float], prefix: str) -> dict[str, float | None]:
    a = np.asarray(values, dtype=float)
    return {f"{prefix}_median": percentile_or_none(a, 50), f"{prefix}_p95": percentile_or_none(a, 95)}


# --------------------------------------------------------------------------- stopping
class StopFlag:
    """A request to stop the run after the current frame.

    Thread- and signal-safe: a signal handler only sets it; the frame loop checks it between frames.
    """

    def __init__(self) -> None:
        self._event = threading.Event()
        self.reason = ""
        # what the run does once its frames are done (reliab2, issue 24: said to a second signal)
        self.finishing = "the results are being written"

    def set(self, reason: str = "stop requested") -> None:
        """Ask the run to stop after the current frame."""
        if not self._event.is_set():
            self.reason = reason
        self._event.set()

    def is_set(self) -> bool:
        """Whether a stop was requested."""
        return self._event.is_set()


@contextlib.contextmanager
def stop_on_signals(stop: StopFlag) -> Iterator[StopFlag]:
    """While the block runs, SIGINT (Ctrl-C) and SIGTERM only set ``stop``.

    Main thread only; elsewhere nothing is installed. The previous handlers come back afterwards.
    """
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def _request(signum: int, frame: object) -> None:
        if stop.is_set():
            logger.warning("signal %d: already stopping, please wait: %s", signum, stop.finishing)
        stop.set(f"signal {signum}")

    previous = {s: signal.signal(s, _request) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


# --------------------------------------------------------------------------- the run
def _loop_on(config: Config) -> bool:
    """Whether the run closes loops (loop closing on and a back end that takes constraints)."""
    return config.loop.enabled and config.backend.kind != "none"


def _loop_stage(config: Config, calibration: StereoCalibration, vocabulary: Vocabulary | None) -> LoopStage:
    """Loop closing when it is on (with ``vocabulary``, None: trained on the fly); else the null stage."""
    if not _loop_on(config):
        return NullLoopStage()
    from loopmodel.loop.stage import LoopClosingStage

    return LoopClosingStage.from_config(config.loop, calibration, vocabulary)


@contextlib.contextmanager
def timed_step(
    name: str, seconds: dict[str, float], finishing: FinishFn | None, cpu_s: dict[str, float] | None = None
) -> Iterator[None]:
    """Time one finishing step into ``seconds[name]`` and tell ``finishing`` when it starts and ends.

    ``cpu_s[name]`` (when given): the CPU seconds of this process (all its threads; not its worker
    processes) in the step: on the shared machine the wall time follows the load, the CPU time less.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    try:  # a KeyboardInterrupt in the telling is the step's too (its time kept)
        if finishing is not None:
            finishing(name, None)
        yield
    finally:
        seconds[name] = time.perf_counter() - t0
        if cpu_s is not None:
            cpu_s[name] = time.process_time() - c0
        if finishing is not None:
            finishing(name, seconds[name])


@dataclasses.dataclass
class _Times:
    """A run's timings: from its start, each frame's and each back-end call's (ms), each finishing step's (s)."""

    t_start: float = dataclasses.field(default_factory=time.perf_counter)
    frame_ms: list[float] = dataclasses.field(default_factory=list)
    backend_ms: list[float] = dataclasses.field(default_factory=list)
    finish_s: dict[str, float] = dataclasses.field(default_factory=dict)
    finish_cpu_s: dict[str, float] = dataclasses.field(default_factory=dict)  # this process's CPU in each step
    frames_s: float | None = None  # from the start to the last frame (set when the finish starts)

    def since_start_s(self) -> float:
        """Seconds since the run started."""
        return time.perf_counter() - self.t_start


class _LaserFeed:
    """A run's laser profiles, from the frames' stripes or laser-line images, in the order they arrive.

    Laser-line images are extracted in a worker process (issue 33: 40-50 ms per image); a daemonic
    process (a batch task) may not start one and extracts them itself. :attr:`stripes` holds every
    profile so far (meshed at the end), :meth:`new_profiles` those not yet handed on (the live map).
    """

    def __init__(self, extractor: StripeExtractor) -> None:
        self.extractor = extractor
        self.stripes: list[StripeProfile] = []
        self.ms: list[float] = []  # per frame with laser data: the time it took here
        self._unfed: list[StripeProfile] = []
        self._worker: ExtractionWorker | None = None  # made at the first laser-line image

    def start(self) -> None:
        """Start the extraction worker now (a sequence with laser-line images), not at the first image."""
        if self._worker is None and not mp.current_process().daemon:
            from loopmodel.mapping.stripe_feed import ExtractionWorker

            self._worker = ExtractionWorker(self.extractor)

    def wait_started(self, timeout_s: float | None = None) -> None:
        """Wait until the extraction worker (if any) has started."""
        if self._worker is not None:
            self._worker.wait_started(timeout_s)

    def take(self, scan: ScanFrame) -> None:
        """A frame's laser data: its profiles join :attr:`stripes` (those of images when extracted)."""
        if not scan.stripes and not scan.laser_images:
            return
        t0 = time.perf_counter()
        if scan.laser_images:
            self.start()
        if self._worker is not None:
            profiles = list(scan.stripes)
            for t_ns, image in scan.laser_images:
                self._worker.submit(t_ns, image)
            profiles += self._worker.ready()
        else:
            profiles = self.extractor.profiles(scan)
        self.stripes.extend(profiles)
        self._unfed.extend(profiles)
        self.ms.append((time.perf_counter() - t0) * 1e3)

    def new_profiles(self) -> list[StripeProfile]:
        """The profiles taken since the last call."""
        out, self._unfed = self._unfed, []
        return out

    @property
    def has_process(self) -> bool:
        """Whether the laser images are extracted in a process of their own (running)."""
        return self._worker is not None

    def wait(self, keep_process: bool = False) -> Any:
        """The profiles of the last laser images join :attr:`stripes` (waited for); the worker stops.

        With ``keep_process`` its idle process pool is returned for other work (None without one).
        """
        if self._worker is None:
            return None
        worker, self._worker = self._worker, None
        self.stripes.extend(worker.wait(keep_process))
        return worker.take_pool() if keep_process else None


class _MapRecord:
    """What a run keeps for its session map (``output.write_map``; issue 20).

    Each keyframe with its image; its map content (loop features, PNG) is prepared off the
    tracking thread as it arrives (:class:`~loopmodel.loop.session_map.KeyframeArchiver`).
    """

    def __init__(
        self, calibration: StereoCalibration, config: Config, vocabulary: Vocabulary | None, source: str
    ) -> None:
        from loopmodel.loop.session_map import KeyframeArchiver

        self.calibration, self.config, self.vocabulary, self.source = calibration, config, vocabulary, source
        self.keyframes: dict[int, Keyframe] = {}
        self.archiver = KeyframeArchiver(calibration, config.loop)

    def add(self, kf: Keyframe, detection: Future[Any] | None = None) -> None:
        """A keyframe (with its image) for the map; ``detection``: the loop stage's of it, if any."""
        self.keyframes[kf.id] = kf
        self.archiver.add(kf, detection)

    def build(
        self,
        result: RunResult,
        frames: list[FrameResult],
        world_from_kf: Mapping[int, F64],
        constraints: list[LoopConstraint],
    ) -> SessionMap | None:
        """The session map of the run (None without keyframes or when it fails: logged).

        ``world_from_kf``: the final keyframe poses; ``constraints``: the loops the back end took.
        """
        prepared = self.archiver.take()
        if not self.keyframes:
            return None
        from loopmodel.config import dump_config, pipeline_sections
        from loopmodel.loop.session_map import MapInputs, build_session_map
        from loopmodel.mapping.final import anchor_stripes

        config = self.config
        kfs = [self.keyframes[k] for k in sorted(self.keyframes)]
        tracked = [f for f in frames if f.ok]
        anchors = anchor_stripes(
            result.stripes,
            result.final,
            np.array([f.timestamp_ns for f in tracked], np.int64),
            np.array([f.keyframe_id for f in tracked], np.int64),
            world_from_kf,
            config.mapping,
        )
        map_inputs = MapInputs(
            self.calibration,
            kfs,
            {k: world_from_kf[k] for k in self.keyframes if k in world_from_kf},
            result.landmark_ids,
            result.landmarks_in_world,
            [(c.kf_a, c.kf_b, c.a_from_b) for c in constraints],
            anchors,
            dump_config(config, pipeline_sections()),
            {"sequence": self.source},
        )
        try:
            return build_session_map(map_inputs, config.loop, prepared, self.vocabulary)
        except LoopmodelError as exc:
            logger.error("no session map: %s", exc)
            return None


def _import_beside(*modules: str, warm: tuple[str, ...] = ()) -> None:
    """Import ``modules`` in a thread (issue 32: open3d for the final mesh while the back end refines).

    ``warm``: kernel modules whose ``warm_up()`` (numba's cached machine code loaded) runs there after the imports.

    Importing open3d took 4.8 s of the 17 s final-mesh step (150-frame realistic orbit, load 15);
    the final refinement runs in the back-end worker meanwhile, the tracking thread only waits.
    Not before the loop drain: the loop worker thread needs the interpreter then (drain 0.3-0.6 s ->
    4.5-5 s with the import beside it).
    """
    def _load() -> None:
        for module in modules:
            importlib.import_module(module)
        for module in warm:
            importlib.import_module(module).warm_up()

    threading.Thread(target=_load, name="loopmodel-import", daemon=True).start()


class _Run:
    """The stages of one run and what it has produced so far.

    :meth:`step` handles one frame whole, :meth:`finish` turns the state into a :class:`RunResult`.
    It never sees the sequence: frames and their laser profiles are handed to it as values.
    """

    def __init__(
        self,
        calibration: StereoCalibration,
        config: Config,
        listeners: list[RunListener],
        base_map: SessionMap | None = None,
        resume: ResumePoint | None = None,
        source: str = "",
        finishing: FinishFn | None = None,
        laser: LaserKind = "none",
    ) -> None:
        self.source = source  # the sequence's name, for metrics.json and the session map
        # continue an interrupted run from its last keyframe
        self.resume = Resumed(resume) if resume is not None else None
        # a session in a saved map (issue 20): localize in it, or extend it (merged at the end)
        self.session = map_session(config, base_map)
        config = self.session.run_config(config)
        calibration = self.session.calibration(calibration, config)  # issue 31 item 4: a map's refined rig
        self.config = config
        self.listeners = listeners
        self.finishing = finishing
        # the laser profiles of the frames read so far (meshed at the end; the live map takes the new
        # ones at the next tracked frame); the extraction worker's start (numba's kernels, 1.2 s of
        # CPU) beside the run's own set-up, not beside its first frames (tail11)
        self.laser = _LaserFeed(StripeExtractor(calibration, config.mapping))
        if laser == "images":
            self.laser.start()
        # issue 31: while refining, right-image columns read at their own rows (calibration.stereo_subpixel)
        self.frontend = FrontEnd(
            calibration, config.calibration.frontend_config(config.frontend),
            keep_observations=config.calibration.retracks,  # issue 31: re-solved after refining
            warm=False,
        )
        # issue 33: in a worker beside the tracker (config.backend.worker); started before the front end's
        # warm-ups, which then run beside its start-up (cpu17: on the KITTI clip the run waited 0.11 s for
        # its "ready" at the first frame after 0.11 s of warm-ups with the second core idle)
        make = functools.partial(create_backend, config.backend, self.frontend.calibration, config.givens)
        self.backend: Backend = start_backend(config.backend, make)
        self.frontend.warm_up()
        # finish11: the evaluation's and the writes' modules too (0.02 s of the KITTI clip's finish in a new process)
        later = ["loopmodel.eval.of_run", "loopmodel.eval.trajectory_metrics", "loopmodel.io.map_file",
                 "loopmodel.io.calib_files"]
        if config.calibration.refine != "none":  # calib7: the self-calibration's modules, not after the last frame
            later.insert(0, "loopmodel.calibration.retrack")
        _import_beside(*later)
        self.session.setup(config, self.frontend.calibration)
        self.localizer = self.session.localizer
        # the place-recognition vocabulary of the loop stage and the session map, read here (issue 32)
        vocabulary: Vocabulary | None = None
        if self.localizer is None and (_loop_on(config) or config.output.write_map):
            from loopmodel.io.vocabulary_file import loop_vocabulary

            vocabulary = loop_vocabulary(config.loop)
        self.loop: LoopStage = self.localizer or _loop_stage(config, self.frontend.calibration, vocabulary)
        # frame poses anchored to their keyframes (corrections reach every frame), and the stripes
        # placed with them (the stripe map follows every change of the anchored poses)
        self.anchored = AnchoredTrajectory()
        # placed in one batch when the live mesh takes its points, not on the tracking thread each frame (issue 33)
        self.stripe_map = StripeMap(config.mapping, self.anchored, place_when_read=True)
        m = config.mapping
        self.live = LiveMapping(self.stripe_map, m.live_mesh_every_kf, m.live_mesh_worker, m.live_mesh_nice)
        if laser != "none":  # open3d's import in the live mesh's worker, beside the set-up as well
            self.live.start()
        self.frames: list[FrameResult] = []
        self.keyframes: dict[int, int] = {}  # keyframe id -> timestamp_ns, in order
        # keyframe -> (previous keyframe, the tracker's pose of it there): drift per interval
        self.tracked_links: dict[int, tuple[int, F64]] = {}
        self.times = _Times()
        # for the session map (issue 20): keyframes with their images
        self.map_record: _MapRecord | None = None
        if config.output.write_map:
            self.map_record = _MapRecord(self.frontend.calibration, config, vocabulary, source)
        # issue 31: the keyframes' measurements (no images) for the final self-calibration
        self.selfcal_keyframes: dict[int, Keyframe] = {}
        self.selfcal: Any = None
        self.retracked: RetrackedFrames | None = None  # the frames between keyframes re-solved after refining
        self.mesh_worker: FinalMeshWorker | None = None  # the final mesh's process, during the finish
        self.early_mesh: MovedMeshJob | None = None  # the final mesh started before the frames' re-solve
        self.beside_mesh: Callable[[RunResult], None] | None = None  # process()'s: while the final mesh is made
        self.total_frames: int | None = None  # process()'s: the frames the run is to take, when known
        self.frame_starts_s: collections.deque[float] = collections.deque(maxlen=21)  # the last frames' starts (s)
        self.helper: Any = None  # the idle stripe-extraction process pool, during the finish (the re-solve's share)
        # the keyframes' stereo points triangulated with the refined rig (the re-solve's and the map's)
        self.refined_points: dict[int, F64] | None = None
        self.loop_constraints: list[LoopConstraint] = []
        self.online: Any = None  # issue 31, calibration.refine online: calibration/online.py
        if config.calibration.refine == "online" and self.localizer is None:
            from loopmodel.calibration.online import OnlineCalibration

            self.online = OnlineCalibration(self.frontend.input_calibration, config.calibration)
        # the back end's last call (ms) and the ids of the loop constraints it was given (MapState)
        self._last: tuple[float, tuple[int | None, ...]] = (0.0, ())

    def wait_for_workers(self, timeout_s: float = 60.0) -> None:
        """Before the first frame: the worker processes started with the run have done their imports.

        Their start-up (the back end's GTSAM, the extraction's compiled kernels, the live mesh's open3d:
        each 0.5-1.5 s of a core) otherwise shares the 2-core machine with the first hundred frames
        (tail11). A worker that does not start in ``timeout_s`` is not waited for further.
        """
        waits = (self.laser.wait_started, self.live.wait_started, getattr(self.backend, "wait_started", None))
        for wait in waits:
            if wait is not None:
                wait(timeout_s)

    # ------------------------------------------------------------------ per frame
    def step(self, frame: StereoFrame) -> FrameResult:
        """Track one frame.

        A keyframe goes through loop closing and the back end; the frame joins the anchored
        trajectory, and the stripes taken up to it the live map.
        """
        t0 = time.perf_counter()
        self.frame_starts_s.append(t0)
        late = self._hand_waiting_keyframes()
        self._loops_between_frames()
        if self.online is not None:
            self._online_between_frames(frame.timestamp_ns)
        res = self.frontend.process(frame)
        if res.is_keyframe and res.keyframe is None:  # (local_ba_beside) its frame anchors to it already
            self.anchored.set_keyframe(res.keyframe_id, res.world_from_cam)
        if not res.ok:
            logger.info("frame %d LOST: %s", frame.index, res.reason)
        kf = res.keyframe
        if kf is None and self.localizer is not None and self.localizer.wants_frame(res):
            # issue 20: every frame is relocalized until its segment is in the map
            self._correct(self.localizer.on_frame(res, self.frontend.rectifier.left(frame.left), self._state()))
        if kf is not None:
            world_from_cam = self._keyframe_step(kf, res) @ res.kf_from_cam
            # do not hold every keyframe image; a resumed run's first pose is the old keyframe's
            res = dataclasses.replace(res, keyframe=None, world_from_cam=world_from_cam)
        self.frames.append(res)
        if res.ok:
            self.anchored.add_frame(res.timestamp_ns, kf_id=res.keyframe_id, kf_from_cam=res.kf_from_cam)
            self.live.feed(self.laser.new_profiles())
        if kf is not None or late:
            updates = len(self.live.update_ms)
            self.live.on_keyframe(self._seconds_left())
            if self.listeners and len(self.live.update_ms) > updates:
                mesh = self.live.mesh()
                for listener in self.listeners:
                    listener.on_live_mesh(mesh)
        self.times.frame_ms.append((time.perf_counter() - t0) * 1e3)
        if self.listeners:
            tracks = self.frontend.tracked_features()
            for listener in self.listeners:
                listener.on_frame(frame, res, tracks)
        return res

    def _hand_waiting_keyframes(self) -> bool:
        """frontend.local_ba_beside: the last frame's keyframe, its local BA (run beside since) taken.

        It reaches the loop stage and back end before the next frame is tracked, as it would have in
        its own frame, and its frame's online pose becomes the BA's (the inline one). Whether one came.
        """
        late = self.frontend.finish_keyframes()
        for kf in late:
            self._keyframe_step(kf, self.frames[-1])
            last = self.frames[-1]
            if last.is_keyframe and last.keyframe_id == kf.id:
                self.frames[-1] = dataclasses.replace(last, world_from_cam=np.asarray(kf.world_from_kf).copy())
        return bool(late)

    def _online_between_frames(self, timestamp_ns: int) -> None:
        """``calibration.refine: online``: a moved online calibration becomes the front end's rectification."""
        from loopmodel.imaging.rectify import Rectifier

        model = self.online.poll(timestamp_ns)
        if model is not None:
            fe = self.frontend
            fe.rectifier = Rectifier.following(fe.rectifier, model.raw, *model.rot_rect_from_cam)

    def _loops_between_frames(self) -> None:
        """Loops the loop stage's workers finished since the last frame (issue 33): to the back end and front end."""
        out = self.loop.between_frames(self._state())
        if out is None:
            return
        self._correct(out.corrections)
        if out.resume is not None:
            self.frontend.resume_features(out.resume)
        tb = time.perf_counter()
        ids = self._add_constraints(out.constraints)
        self._last = ((time.perf_counter() - tb) * 1e3, ids)
        for listener in self.listeners:
            if out.events:
                listener.on_loop_events(out.events)

    def _state(self) -> MapState:
        return MapState(self.frontend.world_from_kf, *self._last)

    def skips(self, frame: StereoFrame) -> bool:
        """Whether a resumed run skips this frame (before the interrupted run's last keyframe)."""
        return self.resume is not None and self.resume.skips(frame)

    def _resumed(self, kf: Keyframe) -> Keyframe:
        """A resumed run's first keyframe at the pose of the interrupted run's last one."""
        if self.resume is None or self.keyframes:
            return kf
        pose = self.resume.world_from_first_kf
        self.frontend.apply_correction({kf.id: pose})
        return dataclasses.replace(kf, world_from_kf=pose.copy())

    def _keyframe_step(self, kf: Keyframe, res: FrameResult) -> F64:
        """Loop closing, then the back end; returns the keyframe's pose as the frame had it.

        The keyframe is recorded last, once the map holds it, so an interruption never leaves it
        half registered.
        """
        kf = self._resumed(kf)
        tracked_pose = res.world_from_cam if self.resume is None or self.keyframes else kf.world_from_kf
        out = self.loop.on_keyframe(kf, self._state())
        kf = out.keyframe
        self.anchored.set_keyframe(kf.id, kf.world_from_kf)
        self._correct(out.corrections)
        if out.resume is not None:  # seed 004 section 5: track the old feature set on
            self.frontend.resume_features(out.resume)
        tb = time.perf_counter()
        self.backend.add_keyframe(kf)
        ids = self._add_constraints(out.constraints)
        estimate = self.backend.estimate(landmarks=False)
        self._last = ((time.perf_counter() - tb) * 1e3, ids)
        self.times.backend_ms.append(self._last[0])
        self._correct({k: estimate.world_from_kf[k] for k in estimate.changed_keyframes if k in estimate.world_from_kf})
        if kf.connected and kf.prev_keyframe_id is not None and kf.kf_prev_from_kf_tracked is not None:
            self.tracked_links[kf.id] = (kf.prev_keyframe_id, kf.kf_prev_from_kf_tracked)
        self.keyframes[kf.id] = kf.timestamp_ns
        if self.map_record is not None:  # its loop features are the loop stage's, not detected twice
            self.map_record.add(kf, self.loop.detection(kf.id))
        if self.config.calibration.refine != "none":
            self.selfcal_keyframes[kf.id] = kf.without_image()
            if self.online is not None:
                self.online.add_keyframe(self.selfcal_keyframes[kf.id], self.anchored.keyframe_poses)
        for listener in self.listeners:
            if out.events:
                listener.on_loop_events(out.events)
            listener.on_keyframe(kf, res)
        return np.asarray(tracked_pose)

    def _add_constraints(self, constraints: list[LoopConstraint]) -> tuple[int | None, ...]:
        ids: list[int | None] = []
        for c in constraints:
            try:
                if c.kf_a_mono_obs is not None:  # a loop found after its keyframe reached the back end
                    self.backend.add_observations(c.kf_a, c.kf_a_mono_obs)
                    self._selfcal_observations(c.kf_a, c.kf_a_mono_obs)
                ids.append(int(self.backend.add_loop_constraint(c.kf_a, c.kf_b, c.a_from_b)))
                self.loop_constraints.append(c)
            except LoopmodelError as exc:  # e.g. a back end without relative-pose factors
                logger.info("loop %d -> %d: no loop constraint (%s)", c.kf_a, c.kf_b, exc)
                ids.append(None)
        return tuple(ids)

    def _selfcal_observations(self, kf_id: int, mono_obs: F64) -> None:
        """A late loop's observations of old landmarks join the keyframe kept for the self-calibration."""
        kf = self.selfcal_keyframes.get(kf_id)
        if kf is not None:
            old = np.asarray(kf.mono_obs, float).reshape(-1, 3)
            rows = np.vstack([old, np.asarray(mono_obs, float).reshape(-1, 3)])
            self.selfcal_keyframes[kf_id] = dataclasses.replace(kf, mono_obs=rows)

    def _calibrating(self, interrupted: bool) -> bool:
        """Whether the finish runs the calibrating bundle adjustment (``calibration.refine: final``, issue 31)."""
        return self.config.calibration.refine != "none" and not interrupted and self.localizer is None

    def _calibration_keyframes(self) -> list[Keyframe]:
        """The calibrating BA's keyframes, their right columns at the latest disparity offset (issue 36)."""
        from loopmodel.types import at_latest_disparity_offset

        return at_latest_disparity_offset(list(self.selfcal_keyframes.values()))

    def _observe_beside(self, interrupted: bool) -> tuple[list[Keyframe], Future[Any]] | None:
        """The calibrating bundle adjustment's keyframes and their observations, made on a thread (or None).

        fin19 (issue 32): :func:`~loopmodel.calibration.selfcal.final_observations` needs no estimate: it is
        made while this thread waits for the back end's final estimate (made in its worker process).
        Not with ``calibration.refine: online`` (its keyframes are re-expressed after its last window).
        """
        if not self._calibrating(interrupted) or self.online is not None or not self.keyframes:
            return None
        from loopmodel.calibration.selfcal import final_observations

        kfs = self._calibration_keyframes()
        pool = ThreadPoolExecutor(1, thread_name_prefix="loopmodel-selfcal")
        job = pool.submit(final_observations, kfs, self.frontend.input_calibration, self.config.calibration)
        pool.shutdown(wait=False)
        return kfs, job

    def _self_calibration(
        self,
        estimate: BackendEstimate | None,
        interrupted: bool,
        observed: tuple[list[Keyframe], Future[Any]] | None = None,
    ) -> BackendEstimate | None:
        """``calibration.refine: final`` (issue 31): the calibrating bundle adjustment.

        Then the stripes moved to the refined left camera and light plane (laser-stereo scale); the
        anchored frames follow the refined keyframes. Returns the refined estimate (the input when
        off, interrupted, localizing or failing: logged); :attr:`selfcal` keeps the report.
        ``observed``: :meth:`_observe_beside`'s keyframes and observations.
        """
        if not self._calibrating(interrupted) or estimate is None:
            return estimate
        from loopmodel.calibration.selfcal import apply_laser_scale, close_loops, refine_final, restripe
        from loopmodel.mapping.extraction import LightPlane

        plane = LightPlane.from_config(self.config.mapping)
        start = None
        if self.online is not None:  # measurements after a switch back to the recorded rectification
            self.online.close()
            self.selfcal_keyframes = {
                int(k.id): k for k in self.online.keyframes_as_recorded(list(self.selfcal_keyframes.values()))
            }
            start = self.online.latest_values
        kfs = observed[0] if observed is not None else self._calibration_keyframes()
        loops = [(c.kf_a, c.kf_b, c.a_from_b) for c in self.loop_constraints]
        b = self.config.backend
        try:
            sc = refine_final(
                kfs, estimate.world_from_kf, estimate.landmark_ids, estimate.landmarks_in_world,
                self.frontend.input_calibration, self.config.calibration, plane.normal_in_cam, plane.d_m,
                loops, np.array([b.loop_sigma_rad] * 3 + [b.loop_sigma_m] * 3), start,
                observed=observed[1].result() if observed is not None else None,
            )
        except (LoopmodelError, np.linalg.LinAlgError, ValueError) as exc:
            logger.warning("self-calibration not done: %s", exc)
            return estimate
        if self.config.calibration.close_loops:  # as the back end's final estimate
            r = self.config.refine
            close_loops(
                sc, kfs, loops, r.loop_odometry_sigma_deg, r.loop_odometry_sigma_m,
                float(np.degrees(b.loop_sigma_rad)), b.loop_sigma_m,
            )
        recorded = self.frontend.input_calibration
        stripes = restripe(self.laser.stripes, recorded, sc.calibration, plane.normal_in_cam, plane.d_m)
        self.laser.stripes = apply_laser_scale(sc, kfs, stripes, self.config.calibration.sigma_plane_tilt_deg)
        self.anchored.update_keyframes(sc.world_from_kf)
        self._start_mesh_before_resolve()  # the stripes and the keyframes are final here
        if self.config.calibration.retracks or self.map_record is not None:  # issue 32: one triangulation for both
            from loopmodel.calibration.retrack import refined_stereo_points

            t0 = time.perf_counter()
            placed = [k for k in kfs if int(k.id) in sc.world_from_kf]
            try:  # else the re-solve and the map triangulate their own
                self.refined_points = refined_stereo_points(placed, sc.landmark_ids, recorded, sc.calibration)
            except (LoopmodelError, np.linalg.LinAlgError, ValueError) as exc:
                logger.warning("keyframe points not triangulated with the refined rig: %s", exc)
            sc.extra["calibration_refined_points_s"] = time.perf_counter() - t0
        if self.config.calibration.retracks:
            try:
                self._retrack(sc, recorded, {int(k.id): k for k in kfs})
            except (LoopmodelError, np.linalg.LinAlgError, ValueError) as exc:  # the bridged frames stay
                logger.warning("frames between keyframes not re-solved: %s", exc)
        if self.online is not None:
            sc.extra.update(self.online.metrics())
        self.selfcal = sc
        return BackendEstimate(dict(sc.world_from_kf), sc.landmark_ids, sc.landmarks_in_world, set(sc.world_from_kf))

    def _retrack(self, sc: Any, recorded: StereoCalibration, keyframes: Mapping[int, Keyframe]) -> None:
        """The frames between keyframes solved again with the refined calibration (issue 31; final trajectory)."""
        from loopmodel.calibration.retrack import retrack_frames

        t0 = time.perf_counter()
        frames = self.frames if self.online is None else self.online.observations_as_recorded(self.frames)
        self.retracked = retrack_frames(
            frames, self._final_trajectory(), keyframes, sc.world_from_kf, sc.landmark_ids,
            sc.landmarks_in_world, recorded, sc.calibration, self.frontend.pose_options,
            self.config.calibration.retrack_min_points,
            disparity_sigma_px=fc.disparity_sigma_px if (fc := self.frontend.config).depth_weighting else None,
            keyframe_points=self.refined_points,
            helper=self.helper,
            helper_share=self.config.calibration.retrack_helper_share,
        )
        self._close_helper()
        sc.extra.update({f"calibration_retrack_{k}": v for k, v in self.retracked.stats.items()})
        sc.extra["calibration_retrack_s"] = time.perf_counter() - t0

    def _correct(self, world_from_kf: Mapping[int, F64]) -> None:
        """The one way corrections flow back: to the tracker and to the anchored frames."""
        if world_from_kf:
            self.frontend.apply_correction(dict(world_from_kf))
            self.anchored.update_keyframes(world_from_kf)
            for listener in self.listeners:
                listener.on_correction(world_from_kf)

    # ------------------------------------------------------------------ end of run
    def _final_estimate(self, interrupted: bool) -> BackendEstimate | None:
        """The back end's end-of-run solution (refined unless interrupted), applied to the anchored frames.

        None without keyframes or when the back end fails (logged: the front end's keyframes are
        kept).
        """
        if not self.keyframes:
            return None
        refine = None if interrupted else self.config.refine
        if refine is not None and self.config.calibration.refine != "none" and self.localizer is None:
            # the calibrating bundle adjustment re-solves every keyframe and landmark: the batch BA
            # before it changes nothing (calib6: KITTI clip and 150-frame orbit bit-identical results,
            # the finish 0.6 s / 2.4 s shorter at load 20-22), nor do iSAM2's extra relinearising
            # updates (fin17: 33.5 s CPU of the 349-keyframe scale scan's finish, keyframes moved by
            # 0.06 mm at most; CHANGELOG fin17)
            refine = refine.model_copy(update={"batch_ba": False, "extra_iterations": 0})
        try:
            estimate = self.backend.final_estimate(refine)
            if self.localizer is None:  # a localization's poses are the tracker's, corrected into the map
                self.anchored.update_keyframes(estimate.world_from_kf)
        except Exception as exc:  # keep the front end's keyframes; still write everything
            logger.error("back end failed at the end of the run: %s", exc)
            return None
        return estimate

    def _final_trajectory(self) -> Trajectory:
        if self.config.refine.bridge_frames:
            final = self.anchored.bridged_trajectory(self.keyframes, self.tracked_links)
        else:
            final = self.anchored.trajectory()
        return final if self.retracked is None else self.retracked.over(final)

    def _keyframe_trajectory(self) -> Trajectory:
        poses = self.anchored.keyframe_poses
        ids = list(self.keyframes)
        return Trajectory(
            np.array([self.keyframes[k] for k in ids], dtype=np.int64),
            np.stack([poses[k] for k in ids]) if ids else np.zeros((0, 4, 4)),
        )

    def _seconds_left(self) -> float | None:
        """The frames still to come in seconds at the recent frames' rate; None when unknown or no final mesh follows.

        For the live mesh (mesh14): an update that would end after the last frame is abandoned for the
        final mesh, whose process it would hold up.
        """
        starts = self.frame_starts_s
        if self.total_frames is None or len(starts) < 2 or not self.config.mapping.write_mesh:
            return None
        left = max(self.total_frames - len(self.frames), 0)
        return left * (starts[-1] - starts[0]) / (len(starts) - 1)  # at the last 20 frames' rate

    def finishing_note(self) -> str:
        """What :meth:`finish` and the writes will do, with the mesh time estimated from the live mesher's rate."""
        n = self.live.point_count
        if not self.config.mapping.write_mesh or n == 0:
            return "the results are being written (a few seconds)"
        est = self.live.mesh_seconds_estimate()
        when = f"about {est:.0f} s at this run's live-mesh rate" if est is not None else "no rate measured yet"
        return f"the final mesh of {n} stripe points ({when}), then the results files"

    def finish(self, interrupted: bool) -> RunResult:
        """The steps after the last frame (:data:`FINISH_STEPS`), each timed and told to ``finishing``.

        Stop the workers, refine, start the final mesh (made here in the mesh step, or with
        ``mapping.final_mesh_in_live_worker`` in the live mesh's idle worker process while the session
        map is made), make the session map, take the mesh, gather the metrics. A
        ``KeyboardInterrupt`` in a step ends the finish: the final mesh's process is stopped and it
        is raised (:func:`process` keeps the results so far).
        """
        frames_s = self.times.frames_s = self.times.since_start_s()
        steps, cpu = self.times.finish_s, self.times.finish_cpu_s
        # the live map's last update has its points already (the finish takes no new one) and the
        # final mesh places the stripes itself: the live map no longer follows the corrections
        # (finish9: re-placing its stripes for the finish's three corrections took 0.31 s CPU on the
        # 600-frame sample, 0.04 s on the 150-frame orbit)
        self.anchored.unwatch(self.stripe_map)
        if not interrupted and self.config.calibration.refine != "none" and self.localizer is None:
            # fin12: the calibrating BA's compiled kernels loaded from numba's cache (0.05 s, 0.035 s CPU) while
            # this thread waits for the back end's last corrections and final estimate; not beside the frames
            _import_beside(warm=("loopmodel.calibration._rig_kernels",))
        try:
            with timed_step("workers", steps, self.finishing, cpu):
                self._hand_waiting_keyframes()  # frontend.local_ba_beside: the last keyframe
                self._stop_workers(interrupted)
            if self.map_record is not None:  # fe8: the map's keyframe PNGs beside the final refinement
                self.map_record.archiver.encode_images()
            with timed_step("final_refinement", steps, self.finishing, cpu):
                result = self._estimate(interrupted)
                # the refined stripes and poses to the mesh's process as soon as they are known
                if self.early_mesh is not None and result.stripes is self.early_mesh.stripes:
                    job: FinalMeshJob | MovedMeshJob = self.early_mesh.moved_to(result.final)
                else:
                    job = start_final_mesh(result.stripes, result.final, self.config.mapping, self.mesh_worker)
            result.metrics = self._metrics(result, frames_s)
            if self.selfcal is not None:  # issue 31
                result.metrics.update(self.selfcal.metrics())
                result.calibration_refined = self.selfcal.calibration
                result.calibration_report = self.selfcal.report()
            final = result.final
            with timed_step("map", steps, self.finishing, cpu):  # while the mesh is made
                result.session_map = self._session_map(result)
                self.session.finish(result, self.frames, self.config)
            with timed_step("mesh", steps, self.finishing, cpu):
                # an extension merged into its base map has the mesh of both sessions (in that world)
                result.metrics.update(self._mesh(result, job, own=result.final is final))
        finally:
            self._close_mesh_worker()
        result.metrics["finish_s"] = dict(steps)
        result.metrics["finish_cpu_s"] = dict(cpu)
        result.metrics["wall_s"] = frames_s + sum(steps.values())
        for listener in self.listeners:
            listener.on_finish(result)
        return result

    def _close_mesh_worker(self) -> None:
        if self.mesh_worker is not None:
            self.mesh_worker.close()
            self.mesh_worker = None
        self._close_helper()

    def _close_helper(self) -> None:
        helper, self.helper = self.helper, None
        end_pool(helper)

    def _stop_workers(self, interrupted: bool) -> None:
        """Stop the workers: the last laser profiles join the stripes, late loops reach the back end.

        With ``mapping.final_mesh_in_live_worker`` an idle live-mesh worker process is kept for the
        final mesh (:attr:`mesh_worker`; a busy one too when the mesh starts before the re-solve).
        """
        cc, mc = self.config.calibration, self.config.mapping
        early = not interrupted and self._mesh_before_resolve(any_worker=True)
        in_helper = False  # mesh14: the final mesh in the idle extraction process (the live worker busy)
        if mc.final_mesh_in_live_worker and mc.write_mesh and self.laser.stripes:
            # open3d loaded there: no new process to start. With the mesh started before the re-solve
            # (a refinement after this) also a busy one: its last update ends by then (finish11) unless
            # the extraction process takes the mesh (mapping.final_mesh_in_helper_when_busy)
            in_helper = early and mc.final_mesh_in_helper_when_busy and self.laser.has_process and self.live.busy
            idle = self.live.take_idle_worker(busy=early and not in_helper)
            in_helper = in_helper and idle is None
            if idle is not None:
                logger.info("final mesh in the live mesh's worker process")
                self.mesh_worker = FinalMeshWorker(idle)
        # issue 32 (finish10): the idle extraction process takes a share of the frames' re-solve,
        # its imports (0.85 s CPU) beside the back end's final estimate and the calibrating BA;
        # not while the mesh's process meshes beside the re-solve (finish11: the mesh is then the
        # longer path, and a third busy process on two cores slows it)
        keep = cc.retracks and cc.retrack_helper_share > 0 and not interrupted and self.localizer is None
        keep = keep and len(self.frames) >= cc.retrack_helper_min_frames and not self._mesh_before_resolve()
        self.helper = self.laser.wait(keep_process=keep or in_helper)
        if in_helper:
            self._mesh_in_helper()
        if self.helper is not None:
            from loopmodel.calibration.retrack import warm_up

            try:
                self.helper.submit(warm_up)
            except RuntimeError:  # a broken pool: the re-solve runs here alone
                self._close_helper()
        if interrupted or (self.config.mapping.write_mesh and self.laser.stripes):
            # the live mesh's last update abandoned, its worker process ended: the final mesh supersedes
            # it (issue 32: else it takes the second core beside the final refinement and the final
            # mesh); without a final mesh it is waited for in the mesh step (_mesh)
            self.live.close(wait=False)
        if self.online is not None:  # its windows left unfinished are not waited for
            self.online.close()
        self._correct(settle(self.backend))  # issue 33: the back-end worker's last corrections
        self._correct(self.loop.close(self._state()))
        # perf (issue 26): loops whose (background) detection finished after the last keyframe
        if self._add_constraints(self.loop.final_constraints()):
            moved = self.backend.estimate(landmarks=False)
            self._correct({k: moved.world_from_kf[k] for k in moved.changed_keyframes})

    def _mesh_in_helper(self) -> None:
        """The idle extraction process made the final mesh's (open3d loaded there now, beside the refinement).

        mesh14 (issue 32): the live mesh's update still running at the last frame is abandoned and its
        process ended (:meth:`_stop_workers`) instead of the final mesh waiting for it. Without the
        process (gone), the busy live worker is taken as before.
        """
        helper, self.helper = self.helper, None
        if helper is not None:
            try:
                helper.submit(load_mesh_modules)
                logger.info("final mesh in the extraction process: the live mesh's worker is busy")
                self.mesh_worker = FinalMeshWorker(helper)
                return
            except RuntimeError:  # a broken pool
                end_pool(helper)
        idle = self.live.take_idle_worker(busy=True)
        if idle is not None:
            self.mesh_worker = FinalMeshWorker(idle)

    def _mesh_before_resolve(self, any_worker: bool = False) -> bool:
        """Whether the final mesh starts before the frames' re-solve (``mapping.final_mesh_before_resolve``).

        Only into a mesh process (:attr:`mesh_worker`, or before it is taken with ``any_worker``), for
        a run that refines and re-solves its frames (not a resumed or localizing one).
        """
        c = self.config
        return (
            c.mapping.final_mesh_before_resolve and (any_worker or self.mesh_worker is not None)
            and c.calibration.retracks and c.calibration.refine != "none" and self.resume is None
            and self.localizer is None
        )

    def _start_mesh_before_resolve(self) -> None:
        """The final mesh started with the refined keyframes, moved to the re-solved frames when taken (finish11)."""
        if not self._mesh_before_resolve() or not self.laser.stripes:
            return
        mc = self.config.mapping
        self.early_mesh = MovedMeshJob(self.laser.stripes, self._final_trajectory(), mc, self.mesh_worker)

    def _mesh(self, result: RunResult, job: FinalMeshJob | MovedMeshJob, own: bool = True) -> dict[str, Any]:
        """The final mesh of ``job`` (``result.mesh`` when ``own``) and the live mesh; their metrics.

        The live mesh's last update is waited for here only when no final mesh is made
        (:meth:`_stop_workers` abandons it otherwise).
        """
        if self.mesh_worker is not None:  # open3d here (loaded beside the final estimate: _load_open3d_beside)
            load_open3d()
            if own:  # the live mesh's last update ended at the workers step: its mesh for the writes beside
                result.live_mesh = self.live.mesh()
            if self.beside_mesh is not None and own:
                try:  # e.g. the evaluation's part that needs no mesh (finish11)
                    self.beside_mesh(result)
                except Exception as exc:  # noqa: BLE001 - the caller's; the run's results come first
                    logger.error("beside the mesh: %s", exc)
        mesh, mesh_metrics = job.result()
        if own:
            result.mesh = mesh
        t0 = time.perf_counter()
        if not result.interrupted:
            self.live.close(wait=True)
        if result.live_mesh is None:
            result.live_mesh = self.live.mesh()
        if self.live.enabled:  # of the mesh step: the wait for the live mesh's last update and its install
            mesh_metrics["live_mesh_wait_s"] = time.perf_counter() - t0
        return mesh_metrics

    def _load_open3d_beside(self, after: Future[Any] | None) -> None:
        """open3d loaded on a thread while the back end's worker makes its final estimate (after ``after``).

        fin21 (issue 32): without its plotly viewer (1.15-1.23 -> 0.31 s CPU in the sample's run, no bytecode
        written), for the final mesh made here (with the meshing module) or, with a mesh worker, its arrays, the
        evaluation and the writes: its import was the mesh step's, on the finish's longest path. ``after``: the
        calibrating BA's observations, wanted when the estimate comes: the import holds the interpreter for up
        to about 0.1 s at a time. Not in a new process: its start (1.5 s CPU: the interpreter, numpy, open3d)
        was not repaid on the loaded machine (150-frame orbit, load 10-13, 3 alternating runs: 1.633 -> 1.670).
        """
        if not (self.config.mapping.write_mesh and self.laser.stripes):
            return
        without_plotly_viewer()
        module = "open3d" if self.mesh_worker is not None else "loopmodel.mapping.meshing"
        if after is None:
            _import_beside(module)
        else:
            after.add_done_callback(lambda _done: _import_beside(module))

    def _estimate(self, interrupted: bool) -> RunResult:
        """The back end's final estimate (refined unless interrupted): trajectories, keyframes, landmarks."""
        observed = self._observe_beside(interrupted)  # while the back end's worker makes its final estimate
        self._load_open3d_beside(observed[1] if observed is not None else None)
        estimate = self._self_calibration(self._final_estimate(interrupted), interrupted, observed)
        result = RunResult(
            config=self.config,
            frames=self.frames,
            online=_online_trajectory(self.frames),
            final=self._final_trajectory(),
            keyframes=self._keyframe_trajectory(),
            keyframe_ids=np.array(list(self.keyframes), dtype=np.int64),
            interrupted=interrupted,
        )
        result.stripes = self.laser.stripes
        if estimate is not None:
            result.landmark_ids, result.landmarks_in_world = estimate.landmark_ids, estimate.landmarks_in_world
        if self.resume is not None:
            self.resume.join_result(result)
        return result

    def partial_result(self, interrupted: bool) -> RunResult:
        """The frames' trajectories and metrics without the end-of-run steps (after :meth:`finish` failed).

        ``finish_s``: the finishing steps begun (the last one cut short).
        """
        self.live.close(wait=False)
        self._close_mesh_worker()
        online = _online_trajectory(self.frames)
        try:
            final, keyframes = self._final_trajectory(), self._keyframe_trajectory()
        except Exception:  # the anchored poses themselves are damaged: the live ones
            final, keyframes = online, Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        result = RunResult(
            config=self.config,
            frames=self.frames,
            online=online,
            final=final,
            keyframes=keyframes,
            keyframe_ids=np.array(list(self.keyframes) if len(keyframes) else [], dtype=np.int64),
            interrupted=interrupted,
        )
        busy_s = sum(self.times.frame_ms) / 1e3
        result.metrics = {"sequence": self.source, "interrupted": interrupted}
        result.metrics.update(frontend_metrics(self.frames, self.times.since_start_s()))
        result.metrics.update(fps=len(self.frames) / busy_s if busy_s > 0 else None, backend=self.config.backend.kind)
        result.metrics["landmarks"] = 0
        result.metrics["keyframes"] = len(keyframes)  # those the run took (a last one may be waiting)
        steps = dict(self.times.finish_s)
        frames_s = self.times.frames_s if self.times.frames_s is not None else self.times.since_start_s()
        result.metrics.update(frames_s=frames_s, finish_s=steps, wall_s=frames_s + sum(steps.values()))
        result.metrics["finish_cpu_s"] = dict(self.times.finish_cpu_s)
        return result

    def _session_map(self, result: RunResult) -> SessionMap | None:
        """The run's map for later sessions (``output.write_map``; None without keyframes or when it fails)."""
        if self.map_record is None:
            return None
        smap = self.map_record.build(result, self.frames, self.anchored.keyframe_poses, self.loop_constraints)
        if smap is not None and self.resume is not None:
            smap = self.resume.join_map(smap)
        if smap is not None and result.calibration_refined is not None:  # issue 31 item 4: for a later session
            from loopmodel.loop.session_map import MapCalibration
            from loopmodel.sessions import refined_map_points

            recorded = self.frontend.input_calibration
            # a resumed run's map renumbers this run's keyframes (loop.merge.append_session): its own triangulation
            shared = self.refined_points if self.resume is None else None
            smap = refined_map_points(smap, recorded, result.calibration_refined, shared)
            smap.refined_calibration = MapCalibration.from_report(
                result.calibration_refined, recorded, result.calibration_report
            )
        return smap

    def _metrics(self, result: RunResult, frames_s: float) -> dict[str, Any]:
        """``metrics.json``: each stage's own figures and the run's timings (no grading: :mod:`loopmodel.eval`).

        ``frames_s``: wall time of the frame loop (from the run's start to the last frame).
        """
        t = self.times
        busy_s = sum(t.frame_ms) / 1e3
        m: dict[str, Any] = {"sequence": self.source, "interrupted": result.interrupted}
        m.update(frontend_metrics(self.frames, frames_s))
        m["fps"] = len(self.frames) / busy_s if busy_s > 0 else None
        m["frames_s"] = frames_s
        m["backend"] = self.config.backend.kind
        m["final_refine_s"] = t.finish_s.get("final_refinement", 0.0)
        m.update(self.loop.metrics())
        m.update(self.live.metrics())
        m.update(self.backend.metrics())
        m["landmarks"] = int(result.landmark_ids.size)
        m["stripe_profiles"] = len(self.laser.stripes)
        m.update(_quantiles(t.frame_ms, "frame_total_ms"))
        m.update(_quantiles(self.laser.ms, "stripe_extraction_ms"))
        # issue 33: the worst frames (frame 0 makes the first keyframe; the first 10 warm up)
        fm = t.frame_ms
        m["frame_total_ms_first"] = fm[0] if fm else None
        m["frame_total_ms_max_after_first"] = max(fm[1:]) if len(fm) > 1 else None
        m["frame_total_ms_max_after_warmup"] = max(fm[10:]) if len(fm) > 10 else None
        m.update(_quantiles(t.backend_ms, "backend_ms"))
        return m


def process(
    sequence: Sequence,
    config: Config,
    *,
    progress: PipelineProgressFn | None = None,
    max_frames: int | None = None,
    listeners: list[RunListener] | None = None,
    stop: StopFlag | None = None,
    base_map: SessionMap | None = None,
    resume: ResumePoint | None = None,
    finishing: FinishFn | None = None,
    beside_mesh: Callable[[RunResult], None] | None = None,
) -> RunResult:
    """Reader -> front end -> loop closing -> back end -> mapping, writing nothing and grading nothing.

    Reads the sequence once (:meth:`~loopmodel.io.base.Sequence.scan`: each frame with its laser
    data). Runs until the sequence ends, ``max_frames`` frames are done, ``stop`` is set (checked
    between frames) or a ``KeyboardInterrupt`` arrives (the last two: ``interrupted``). An
    error while processing a frame ends the run too: the result of the frames before it is
    returned with the error in ``error`` (and ``metrics["stopped_by"]``), for the caller to
    raise once it has kept what it wants. With ``base_map`` the session localizes in that map or
    extends it (``config.session.mode``); with ``resume`` it continues an interrupted run from its
    last keyframe (frames before it are skipped and keep the interrupted run's poses).
    ``finishing`` is told each step after the last frame (:data:`FINISH_STEPS`) as it starts and
    ends. The errors against ground truth are :func:`loopmodel.eval.of_run.evaluate`'s.
    ``beside_mesh`` is called with the result (its trajectories final, no mesh yet) while another
    process makes the final mesh (e.g. :func:`loopmodel.eval.of_run.prepare`)."""
    # the laser data the scan delivers (Sequence.scan's choice): read here, in the run's one reader
    laser: LaserKind = "stripes" if sequence.stripe_count() else "images" if sequence.laser_image_count() else "none"
    run = _Run(
        sequence.calibration, config, listeners or [], base_map, resume, str(sequence.path), finishing, laser
    )
    run.beside_mesh = beside_mesh
    total = len(sequence) if max_frames is None else min(len(sequence), max_frames)
    run.total_frames = total
    stop = stop if stop is not None else StopFlag()
    logger.info("pipeline on %s (%d frames, back end %s)", sequence.path, total, config.backend.kind)
    interrupted, error = _frame_loop(run, sequence.scan(), total, stop, progress)
    if interrupted:
        logger.warning("interrupted after %d frames", len(run.frames))
    if error is not None:
        logger.error("stopped after %d frames: %s", len(run.frames), error)
    stop.finishing = run.finishing_note()
    try:
        result = run.finish(interrupted)
    except KeyboardInterrupt:  # a Ctrl-C while finishing without signal handlers (the API): what exists
        interrupted = True
        logger.warning("interrupted after %d frames, while finishing: the results so far", len(run.frames))
        result = run.partial_result(interrupted)
    except Exception as exc:  # (issue 34) a bad value found after the frames: keep what they gave
        if not run.frames:
            raise
        logger.error("stopped while finishing %d frames: %s", len(run.frames), exc)
        result = run.partial_result(interrupted)
        error = error or exc
    if error is not None:
        result.error = error
        result.metrics["stopped_by"] = str(error).splitlines()[0] if str(error) else type(error).__name__
    fps = result.metrics["fps"]
    logger.info(
        "done: %d frames, %d keyframes, %s fps", len(run.frames), len(run.keyframes), f"{fps:.1f}" if fps else "-"
    )
    return result


class _ReadAhead:
    """The scans of ``scans`` read and decoded on a thread of their own, at most ``depth`` ahead (issue 33, orb13).

    The reader's work (the MCAP chunks' decompression, the PNG inflate, the laser images) then runs beside
    the tracking instead of between its frames; it releases the interpreter lock for most of it. They come
    out in order, an error where its scan would have been. ``depth`` 0 (the default): read on the caller's thread.
    :meth:`close` stops the thread (after the scan it is reading) before the caller closes ``scans``.
    """

    def __init__(self, scans: Iterator[ScanFrame], depth: int) -> None:
        self._scans = scans
        self._queue: queue.Queue[tuple[ScanFrame | None, BaseException | None]] = queue.Queue(max(depth, 1))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if depth > 0:
            self._thread = threading.Thread(target=self._feed, name="read-ahead", daemon=True)
            self._thread.start()

    def _put(self, item: tuple[ScanFrame | None, BaseException | None]) -> bool:
        """Queue ``item`` unless stopped meanwhile; whether it was queued."""
        while not self._stop.is_set():
            with contextlib.suppress(queue.Full):
                self._queue.put(item, timeout=0.05)
                return True
        return False

    def _feed(self) -> None:
        try:
            for scan in self._scans:
                if not self._put((scan, None)):
                    return
        except BaseException as exc:  # raised on the caller's thread, in its place
            self._put((None, exc))
            return
        self._put((None, None))

    def __iter__(self) -> Iterator[ScanFrame]:
        return self

    def __next__(self) -> ScanFrame:
        if self._thread is None:
            return next(self._scans)
        scan, error = self._queue.get()
        if error is not None:
            raise error
        if scan is None:
            self._queue.put((None, None))  # stays ended
            raise StopIteration
        return scan

    def close(self, timeout_s: float = 10.0) -> bool:
        """Stop reading ahead; whether the reading thread has ended (the scans may then be closed)."""
        self._stop.set()
        if self._thread is None:
            return True
        self._thread.join(timeout_s)
        return not self._thread.is_alive()


def _one_ahead(scans: Iterator[ScanFrame]) -> Iterator[tuple[ScanFrame, ScanFrame | None]]:
    """Each scan with the next one (None at the end), read before the scan is handed on.

    An error reading the next one comes after the scan it follows, as without reading ahead.
    """
    scan = next(scans, None)
    while scan is not None:
        try:
            coming = next(scans, None)
        except Exception:
            yield scan, None
            raise
        yield scan, coming
        scan = coming


def _frame_loop(
    run: _Run, scans: Iterator[ScanFrame], total: int, stop: StopFlag, progress: PipelineProgressFn | None
) -> tuple[bool, Exception | None]:
    """Feed the frames (with their laser data) to ``run`` one whole step at a time.

    Returns whether it was stopped early (stop flag, ``KeyboardInterrupt``) and the error that ended
    it, if any.
    """
    # sequence.read_ahead_frames > 0: the reader's decoding on a thread of its own (issue 33, orb13)
    ahead = _ReadAhead(itertools.islice(scans, total), run.config.sequence.read_ahead_frames)
    try:
        run.wait_for_workers()  # their start-up not beside the first frames (tail11)
        # fr16 (issue 33): the objects made so far (modules, compiled kernels' dispatchers, the set-up:
        # 110,000 after the pipeline's imports) left out of the garbage collector's full passes during
        # the frames; such a pass over them alone took 54 ms of CPU (180 ms at load 15) in one frame.
        # Given back after the last frame (gc.unfreeze), so a process running many runs keeps none of them.
        gc.freeze()
        for i, (scan, coming) in enumerate(_one_ahead(ahead)):
            if stop.is_set():
                return True, None
            if run.skips(scan.frame):
                run.laser.take(scan)
                continue
            # a keyframe's right image decoded with its reading (fe7); the run's last frame a keyframe (tail14)
            run.frontend.prepare(scan.frame, last=coming is None)
            run.step(scan.frame)
            # the side jobs after the frame (orb13): its laser data to the extraction process, the coming
            # left image's rectification (issue 33) run while the next frame is read, not beside this
            # frame's KLT on the second core. The rectification first (orb21): started before the laser
            # hand-off's Python and its pool threads' wake-ups, the next step waited less for it (orbit,
            # 3 alternated pairs at load 7-8: 1.94 -> 1.30, 2.61 -> 2.40, 0.96 -> 0.57 ms a frame)
            if coming is not None:
                run.frontend.left_ahead(coming.frame.left)  # and its image check (cpu15)
            run.laser.take(scan)
            if progress is not None:
                el = run.times.since_start_s()
                progress(i + 1, total, (i + 1) / el if el > 0 else 0.0, len(run.keyframes))
    except KeyboardInterrupt:
        return True, None
    except Exception as exc:  # the frames before it still give a result
        return False, exc
    finally:
        gc.unfreeze()
        close = getattr(scans, "close", None)
        if ahead.close() and close is not None:  # not while the reading thread is in it
            close()
    return False, None


def evaluated(
    result: RunResult, sequence: Sequence, finishing: FinishFn | None = None, prepared: Prepared | None = None
) -> Evaluation | None:
    """:func:`loopmodel.eval.of_run.evaluate` of ``result`` merged into its metrics (``finish_s``, ``wall_s``).

    None (and no step) when the sequence has no ground truth. ``prepared``: its part made while the
    mesh was made (:func:`loopmodel.eval.of_run.prepare`; then in the ``mesh`` step's time).
    """
    if sequence.ground_truth is None:
        return None
    from loopmodel.eval.of_run import evaluate

    seconds = result.metrics.setdefault("finish_s", {})
    with timed_step("evaluation", seconds, finishing, result.metrics.setdefault("finish_cpu_s", {})):
        evaluation = evaluate(result, sequence, prepared=prepared)
    result.metrics.update(evaluation.metrics)
    result.metrics["wall_s"] = result.metrics.get("wall_s", 0.0) + seconds["evaluation"]
    return evaluation


def _process_and_write(
    folder: ResultsFolder,
    sequence: Sequence,
    config: Config,
    handle_signals: bool,
    evaluate: bool = True,
    finishing: FinishFn | None = None,
    **kwargs: Any,
) -> RunResult:
    """:func:`process` under a log capture (and the signal handlers when asked), evaluate, write ``folder``.

    The evaluation (when ``evaluate`` and the sequence has ground truth) runs after
    :func:`process`, before :func:`~loopmodel.io.results.write_results` writes the results. While
    another process makes the final mesh, the files that need neither it nor the metrics are written
    (:func:`~loopmodel.io.results.write_results_early`, ``write_beside_mesh_s``) and the evaluation's
    part that needs no mesh is made.
    """
    stop = StopFlag()
    signals = stop_on_signals(stop) if handle_signals else contextlib.nullcontext(stop)
    write_s: dict[str, float] = {}
    write_cpu_s: dict[str, float] = {}
    prepared: list[Prepared] = []
    early: list[EarlyFiles | None] = []
    kitti_input = sequence.format_name == "kitti"
    grade = evaluate and sequence.ground_truth is not None

    def beside(result: RunResult) -> None:  # while another process makes the final mesh
        # pre16 (issue 32): the results files that need neither the mesh nor the metrics
        early.append(write_results_early(folder, result, kitti_input))
        if grade:  # the evaluation's part that needs no mesh (finish11)
            from loopmodel.eval.of_run import prepare

            prepared.append(prepare(result, sequence))

    try:
        with LogCapture() as log, signals:
            result = process(sequence, config, stop=stop, finishing=finishing, beside_mesh=beside, **kwargs)
            written = early[-1] if early else None
            if written is not None and written.holds_for(result):
                result.metrics["write_beside_mesh_s"] = written.seconds
            if evaluate:
                try:
                    evaluated(result, sequence, finishing, prepared[-1] if prepared else None)
                except (LoopmodelError, ValueError, OSError) as exc:  # grading must never lose the run's results
                    logger.error("evaluation failed: %s", exc)
                    result.metrics["evaluation_error"] = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            with timed_step("write", write_s, finishing, write_cpu_s):
                result.log = log.text()
                result.folder = write_results(folder, result, kitti_input=kitti_input, early=written)
    except BaseException:  # e.g. a second Ctrl-C before the writes: no staged folder or lock left behind
        folder.abandon()
        raise
    # the writes' time in the returned metrics only (metrics.json is one of the files written)
    result.metrics.setdefault("finish_s", {}).update(write_s)
    result.metrics.setdefault("finish_cpu_s", {}).update(write_cpu_s)
    result.metrics["wall_s"] = result.metrics.get("wall_s", 0.0) + write_s["write"]
    return result


def run_pipeline(
    sequence: Sequence,
    config: Config,
    out_dir: str | Path | None = None,
    name: str = "run",
    progress: PipelineProgressFn | None = None,
    max_frames: int | None = None,
    listeners: list[RunListener] | None = None,
    handle_signals: bool = True,
    base_map: SessionMap | None = None,
    resume: ResumePoint | None = None,
    evaluate: bool = True,
    finishing: FinishFn | None = None,
) -> RunResult:
    """:func:`process` the sequence, evaluate it, and write the results folder ``<out_dir>/<name>/``.

    By :func:`loopmodel.io.results.write_results`; ``out_dir`` defaults to ``output.out_dir``.

    Every keyframe first goes to loop closing (``config.loop``: relocalization of a new
    segment, verified revisits whose observations of old landmarks join the keyframe's
    monocular observations, plus a relative-pose loop constraint), then to the back end
    (``config.backend.kind``); keyframes it moves are handed back to the front end and to
    the anchored trajectory, in which every frame is stored relative to its keyframe.
    ``metrics.json`` lists each closure under ``loop_events``; with ``evaluate`` and ground truth
    it also holds the errors of :func:`loopmodel.eval.of_run.evaluate`. With ``handle_signals``
    Ctrl-C or SIGTERM stops the run after the current frame; everything up to it is
    written, then ``KeyboardInterrupt`` is raised (an error ending the run early is raised
    after the write as well). With ``base_map`` (a loaded
    :class:`~loopmodel.loop.session_map.SessionMap`) the session localizes in it or extends it
    (``config.session.mode``); with ``resume`` (:func:`~loopmodel.io.map_file.read_resume_point`)
    it continues an interrupted run from its last keyframe. ``finishing`` is told each step after
    the last frame (:data:`FINISH_STEPS`).
    """
    out = out_dir if out_dir is not None else config.output.out_dir
    result = run(
        sequence, config, out, name=name, max_frames=max_frames, progress=progress, handle_signals=handle_signals,
        listeners=listeners, evaluate=evaluate, finishing=finishing, base_map=base_map, resume=resume,
    )
    if result.interrupted:
        raise interrupted_error(result, Path(out) / name)
    return result


def interrupted_error(result: RunResult, requested: Path) -> RunInterrupted:
    """The :class:`RunInterrupted` of an interrupted ``result`` written for the folder ``requested``.

    Its note says where the results are when they were kept beside an older complete run (issue 34).
    """
    beside = result.folder is not None and result.folder != requested
    return RunInterrupted(result.folder, _kept_beside(result.folder, requested) if beside else "")


def _kept_beside(where: Path | None, old: Path) -> str:
    return f"the results so far are in {where} ({old} was not replaced)"


def run(
    source: str | Path | Sequence,
    config: Config | str | Path | Mapping[str, Any] | None = None,
    out_dir: str | Path | None = None,
    *,
    name: str = "run",
    max_frames: int | None = None,
    progress: PipelineProgressFn | None = None,
    handle_signals: bool = False,
    listeners: list[RunListener] | None = None,
    evaluate: bool = True,
    finishing: FinishFn | None = None,
    base_map: SessionMap | None = None,
    resume: ResumePoint | None = None,
) -> RunResult:
    """Run the whole pipeline over a sequence and return what it produced.

    ``source``: an MCAP file, a EuRoC or KITTI folder, or an opened sequence;
    ``config``: a :class:`~loopmodel.config.Config`, the path of a YAML file, a (partial)
    nested dict, or None for the defaults. Writes nothing unless ``out_dir`` is given (then
    the results folder ``<out_dir>/<name>/``). Installs no signal handler unless
    ``handle_signals`` (Ctrl-C and SIGTERM then stop it after the current frame); an
    interrupted run returns its result with ``interrupted`` True; an error is raised (after
    the write when ``out_dir`` is given). ``listeners`` are told every event
    (:class:`~loopmodel.listener.RunListener`: visualisation, recording). With ``evaluate`` (and
    ground truth in the sequence) the metrics hold the errors of :func:`loopmodel.evaluate`, run
    after the pipeline. With ``base_map`` (a loaded :class:`~loopmodel.loop.session_map.SessionMap`)
    the session localizes in it or extends it (``config.session.mode``); with ``resume``
    (:func:`~loopmodel.io.map_file.read_resume_point`) it continues an interrupted run from its last
    keyframe. With ``out_dir``, an error of a run kept beside an older complete one (issue 34) says
    where it is; :func:`interrupted_error` says it for an interrupted one."""
    from loopmodel.config import config_from_dict, load_config
    from loopmodel.io.sequence import open_sequence

    if isinstance(config, Mapping):
        cfg = config_from_dict(dict(config))
    else:
        cfg = config if isinstance(config, Config) else load_config(config)
    seq = open_sequence(source, cfg.sequence) if isinstance(source, str | Path) else source
    kwargs: dict[str, Any] = {"progress": progress, "max_frames": max_frames, "listeners": listeners}
    kwargs.update(base_map=base_map, resume=resume)
    if out_dir is not None:
        folder = ResultsFolder(out_dir, name)
        result = _process_and_write(folder, seq, cfg, handle_signals, evaluate, finishing, **kwargs)
        if result.error is not None and result.folder is not None and result.folder != folder.requested:
            # (issue 34) the older complete run stays; say where this one is
            result.error.args = (f"{result.error}; {_kept_beside(result.folder, folder.requested)}",)
    else:
        stop = StopFlag()
        with stop_on_signals(stop) if handle_signals else contextlib.nullcontext(stop):
            result = process(seq, cfg, stop=stop, finishing=finishing, **kwargs)
            if evaluate:
                evaluated(result, seq, finishing)
    if result.error is not None:
        raise result.error
    return result


def run_frontend(
    sequence: Sequence,
    config: Config,
    out_dir: str | Path | None = None,
    name: str = "run",
    progress: ProgressFn | None = None,
    max_frames: int | None = None,
    listeners: list[RunListener] | None = None,
    evaluate: bool = True,
    finishing: FinishFn | None = None,
) -> RunResult:
    """The front end alone over ``sequence``.

    :func:`run_pipeline` with ``backend.kind: none`` (keyframes keep the tracked poses), no loop
    closing and no mesh. Writes the same results folder (``trajectory_final.tum`` equals the online
    trajectory). An interrupted run still writes what it has, then re-raises.
    """
    return run_pipeline(
        sequence,
        frontend_only(config),
        out_dir,
        name,
        None if progress is None else (lambda i, n, fps, _kf: progress(i, n, fps)),
        max_frames,
        listeners,
        evaluate=evaluate,
        finishing=finishing,
    )


def frontend_only(config: Config) -> Config:
    """``config`` for a front-end-only run: no back end, no loop closing, no meshes, no session map."""
    fe_config = config.model_copy(deep=True)
    fe_config.backend.kind = "none"
    fe_config.loop.enabled = False
    fe_config.mapping.write_mesh = False
    fe_config.mapping.live_mesh_every_kf = 0
    fe_config.output.write_map = False
    return fe_config
