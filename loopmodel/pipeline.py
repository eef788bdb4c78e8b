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
  ``metrics``; :func:`loopmodel.mapping.final.final_mesh` at the end.

A stop request (:class:`StopFlag`, set by the signal handlers of :func:`stop_on_signals`)
is checked between frames, so every frame's and keyframe's bookkeeping is done whole.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from loopmodel.backend import Backend, BackendEstimate, create_backend
from loopmodel.config import Config
from loopmodel.errors import LoopmodelError
from loopmodel.frontend import FrameResult, FrontEnd, Keyframe
from loopmodel.frontend.metrics import frontend_metrics, percentile_or_none
from loopmodel.io.base import Sequence
from loopmodel.io.results import LogCapture, ResultsFolder, write_results
from loopmodel.listener import RunListener
from loopmodel.mapping.anchored import AnchoredTrajectory
from loopmodel.mapping.final import final_mesh, live_stripes, run_stripes
from loopmodel.mapping.live import LiveMapping
from loopmodel.mapping.stripe_map import StripeMap
from loopmodel.result import RunResult
from loopmodel.stages import LoopConstraint, LoopStage, MapState, NullLoopStage
from loopmodel.types import StereoCalibration, Trajectory

if TYPE_CHECKING:
    from loopmodel.loop.localize import MapLocalizationStage
    from loopmodel.loop.session_map import ResumePoint, SessionMap

logger = logging.getLogger(__name__)

# progress(frames_done, frames_total, frames_per_second)
ProgressFn = Callable[[int, int, float], None]
# progress(frames_done, frames_total, frames_per_second, keyframes)
PipelineProgressFn = Callable[[int, int, float, int], None]

#: The result of :func:`run_pipeline` (the name of earlier versions).
RunOutput = RunResult

__all__ = [
    "RunOutput",
    "RunResult",
    "StopFlag",
    "frontend_metrics",
    "frontend_only",
    "process",
    "run",
    "run_frontend",
    "run_pipeline",
    "stop_on_signals",
]

F64 = np.ndarray


# --------------------------------------------------------------------------- metrics
def _online_trajectory(frames: list[FrameResult]) -> Trajectory:
    ok = [f for f in frames if f.ok]
    if not ok:
        return Trajectory(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))
    return Trajectory(np.array([f.timestamp_ns for f in ok]), np.stack([f.world_from_cam for f in ok]))


def _ground_truth_errors(est: Trajectory, gt: Trajectory | None) -> dict[str, float]:
    """ATE RMSE after SE(3) alignment and drift, computed by :mod:`loopmodel.eval`.

    Drift: end-point error with the first poses aligned, percent of the ground-truth path.
    """
    if gt is None or len(est) < 3:
        return {}
    from loopmodel.eval.trajectory_metrics import EvalInputError, evaluate_pair

    try:
        ev = evaluate_pair(
            gt.timestamps_ns,
            gt.world_from_cam,
            est.timestamps_ns,
            est.world_from_cam,
            max_dt_ns=1_000_000,
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
def _loop_stage(config: Config, calibration: StereoCalibration) -> LoopStage:
    """Loop closing when it is on and the back end can take constraints; else the null stage."""
    if not config.loop.enabled or config.backend.kind == "none":
        return NullLoopStage()
    from loopmodel.loop.stage import LoopClosingStage

    return LoopClosingStage.from_config(config.loop, calibration)


def _localizer(config: Config, calibration: StereoCalibration, base_map: SessionMap | None) -> MapLocalizationStage:
    """The loop stage of a localization run: every keyframe relocalized in ``base_map``."""
    from loopmodel.loop.localize import MapLocalizationStage

    assert base_map is not None
    s = config.session
    return MapLocalizationStage(base_map, calibration, config.loop, s.max_correction_m, s.max_correction_deg)


def localize_config(config: Config) -> Config:
    """``config`` for localization in a map: the tracker's poses (no back end), no map of its own."""
    out = config.model_copy(deep=True)
    out.backend.kind = "none"
    out.output.write_map = False
    return out


def _prepend_resumed(result: RunResult, resume: ResumePoint) -> None:
    """The interrupted run's frames and keyframes before the resumed run's first one, then the new ones."""

    def joined(old: Trajectory, new: Trajectory) -> Trajectory:
        before = old.slice(old.timestamps_ns < resume.timestamp_ns)
        return Trajectory(
            np.concatenate([before.timestamps_ns, new.timestamps_ns]),
            np.concatenate([before.world_from_cam, new.world_from_cam]),
        )

    result.online = joined(resume.online, result.online)
    result.final = joined(resume.final, result.final)
    result.keyframes = joined(resume.keyframes, result.keyframes)
    old_ids = resume.map.keyframe_ids[:-1]
    shift = int(resume.map.keyframe_ids.max()) + 1
    result.keyframe_ids = np.concatenate([old_ids, result.keyframe_ids + shift])


class _Run:
    """The stages of one run and what it has produced so far.

    :meth:`step` handles one frame whole, :meth:`finish` turns the state into a :class:`RunResult`.
    """

    def __init__(
        self,
        sequence: Sequence,
        config: Config,
        listeners: list[RunListener],
        base_map: SessionMap | None = None,
        resume: ResumePoint | None = None,
    ) -> None:
        self.sequence = sequence
        self.resume = resume  # continue an interrupted run from its last keyframe
        # a session in a saved map (issue 20): localize in it, or extend it (merged at the end)
        self.base_map = base_map
        self.mode = config.session.mode if base_map is not None else None
        config = localize_config(config) if self.mode == "localize" else config
        self.config = config
        self.listeners = listeners
        self.frontend = FrontEnd(sequence.calibration, config.frontend)
        self.backend: Backend = create_backend(config.backend, self.frontend.calibration, config.givens)
        self.localizer = _localizer(config, self.frontend.calibration, base_map) if self.mode == "localize" else None
        self.loop: LoopStage = self.localizer or _loop_stage(config, self.frontend.calibration)
        # frame poses anchored to their keyframes (corrections reach every frame), and the stripes
        # placed with them (the stripe map follows every change of the anchored poses)
        self.anchored = AnchoredTrajectory()
        self.stripe_map = StripeMap(config.mapping, self.anchored)
        every_kf = config.mapping.live_mesh_every_kf
        stripes = live_stripes(sequence, config.mapping) if every_kf > 0 else iter(())
        self.live = LiveMapping(self.stripe_map, stripes, every_kf)
        self.frames: list[FrameResult] = []
        self.keyframes: dict[int, int] = {}  # keyframe id -> timestamp_ns, in order
        # keyframe -> (previous keyframe, the tracker's pose of it there): drift per interval
        self.tracked_links: dict[int, tuple[int, F64]] = {}
        self.backend_ms: list[float] = []
        self.frame_ms: list[float] = []
        # for the session map (issue 20): keyframes with their images, the loop constraints
        self.map_keyframes: dict[int, Keyframe] = {}
        # issue 31: the keyframes' measurements (no images) for the final self-calibration
        self.selfcal_keyframes: dict[int, Keyframe] = {}
        self.loop_constraints: list[LoopConstraint] = []
        self._last_ms = 0.0
        self._last_ids: tuple[int | None, ...] = ()
        self.t_start = time.perf_counter()

    # ------------------------------------------------------------------ per frame
    def step(self, frame: Any) -> FrameResult:
        """Track one frame.

        A keyframe goes through loop closing and the back end; the frame joins the anchored
        trajectory and the live map.
        """
        t0 = time.perf_counter()
        res = self.frontend.process(frame)
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
            self.live.feed(res.timestamp_ns)
        if kf is not None:
            updates = len(self.live.update_ms)
            self.live.on_keyframe()
            if self.listeners and len(self.live.update_ms) > updates:
                mesh = self.live.mesh()
                for listener in self.listeners:
                    listener.on_live_mesh(mesh)
        self.frame_ms.append((time.perf_counter() - t0) * 1e3)
        if self.listeners:
            tracks = self.frontend.tracked_features()
            for listener in self.listeners:
                listener.on_frame(frame, res, tracks)
        return res

    def _state(self) -> MapState:
        return MapState(self.frontend.world_from_kf, self._last_ms, self._last_ids)

    def skips(self, frame: Any) -> bool:
        """Whether a resumed run skips this frame (before the interrupted run's last keyframe)."""
        return self.resume is not None and int(frame.timestamp_ns) < self.resume.timestamp_ns

    def _resumed(self, kf: Keyframe) -> Keyframe:
        """A resumed run's first keyframe at the pose of the interrupted run's last one."""
        if self.resume is None or self.keyframes:
            return kf
        pose = self.resume.world_from_kf
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
        self._last_ids = self._add_constraints(out.constraints)
        estimate = self.backend.estimate(landmarks=False)
        self._last_ms = (time.perf_counter() - tb) * 1e3
        self.backend_ms.append(self._last_ms)
        self._correct({k: estimate.world_from_kf[k] for k in estimate.changed_keyframes if k in estimate.world_from_kf})
        if kf.connected and kf.prev_keyframe_id is not None and kf.kf_prev_from_kf_tracked is not None:
            self.tracked_links[kf.id] = (kf.prev_keyframe_id, kf.kf_prev_from_kf_tracked)
        self.keyframes[kf.id] = kf.timestamp_ns
        if self.config.output.write_map:
            self.map_keyframes[kf.id] = kf
        if self.config.calibration.refine != "none":
            self.selfcal_keyframes[kf.id] = kf.without_image()
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
        try:
            estimate = self.backend.final_estimate(None if interrupted else self.config.refine)
            if self.localizer is None:  # a localization's poses are the tracker's, corrected into the map
                self.anchored.update_keyframes(estimate.world_from_kf)
        except Exception as exc:  # keep the front end's keyframes; still write everything
            logger.error("back end failed at the end of the run: %s", exc)
            return None
        return estimate

    def _self_calibration(
        self, estimate: BackendEstimate | None, interrupted: bool, last_ns: int | None
    ) -> tuple[BackendEstimate | None, list[Any] | None, Any]:
        """``calibration.refine: final`` (issue 31): the calibrating bundle adjustment.

        Then the stripes extracted with the refined left camera and the laser-stereo scale; the
        anchored frames follow the refined keyframes.

        Returns the refined estimate, the stripes and the :class:`SelfCalibration` (the inputs, None
        and None when off, interrupted, localizing or failing: logged).
        """
        if self.config.calibration.refine == "none" or estimate is None or interrupted or self.localizer is not None:
            return estimate, None, None
        from loopmodel.calibration.selfcal import apply_laser_scale, close_loops, refine_final
        from loopmodel.mapping.extraction import LightPlane

        plane = LightPlane.from_config(self.config.mapping)
        kfs = list(self.selfcal_keyframes.values())
        try:
            sc = refine_final(
                kfs, estimate.world_from_kf, estimate.landmark_ids, estimate.landmarks_in_world,
                self.sequence.calibration, self.config.calibration, plane.normal_in_cam, plane.d_m,
                [(c.kf_a, c.kf_b, c.a_from_b) for c in self.loop_constraints],
                np.array([self.config.backend.loop_sigma_rad] * 3 + [self.config.backend.loop_sigma_m] * 3),
            )
        except (LoopmodelError, np.linalg.LinAlgError, ValueError) as exc:
            logger.warning("self-calibration not done: %s", exc)
            return estimate, None, None
        if self.config.calibration.close_loops:  # as the back end's final estimate
            r, b = self.config.refine, self.config.backend
            close_loops(
                sc, kfs, [(c.kf_a, c.kf_b, c.a_from_b) for c in self.loop_constraints],
                r.loop_odometry_sigma_deg, r.loop_odometry_sigma_m, float(np.degrees(b.loop_sigma_rad)), b.loop_sigma_m,
            )
        stripes = run_stripes(self.sequence, last_ns, self.config.mapping, sc.calibration)
        stripes = apply_laser_scale(sc, kfs, stripes, self.config.calibration.sigma_plane_tilt_deg)
        self.anchored.update_keyframes(sc.world_from_kf)
        moved = BackendEstimate(dict(sc.world_from_kf), sc.landmark_ids, sc.landmarks_in_world, set(sc.world_from_kf))
        return moved, stripes, sc

    def _final_trajectory(self) -> Trajectory:
        if self.config.refine.bridge_frames:
            return self.anchored.bridged_trajectory(self.keyframes, self.tracked_links)
        return self.anchored.trajectory()

    def _keyframe_trajectory(self) -> Trajectory:
        poses = self.anchored.keyframe_poses
        ids = list(self.keyframes)
        return Trajectory(
            np.array([self.keyframes[k] for k in ids], dtype=np.int64),
            np.stack([poses[k] for k in ids]) if ids else np.zeros((0, 4, 4)),
        )

    def finishing_note(self) -> str:
        """What :meth:`finish` and the writes will do, with the mesh time estimated from the live mesher's rate."""
        n = self.stripe_map.point_count
        if not self.config.mapping.write_mesh or n == 0:
            return "the results are being written (a few seconds)"
        est = self.live.mesh_seconds_estimate()
        when = f"about {est:.0f} s at this run's live-mesh rate" if est is not None else "no rate measured yet"
        return f"the final mesh of {n} stripe points ({when}), then the results files"

    def finish(self, interrupted: bool) -> RunResult:
        """Stop the workers, refine, place the stripes, mesh, gather the metrics."""
        wall = time.perf_counter() - self.t_start
        self.live.close(wait=not interrupted)
        self._correct(self.loop.close(self._state()))
        # perf (issue 26): loops whose (background) detection finished after the last keyframe
        if self._add_constraints(self.loop.final_constraints()):
            moved = self.backend.estimate(landmarks=False)
            self._correct({k: moved.world_from_kf[k] for k in moved.changed_keyframes})
        t_final = time.perf_counter()
        estimate = self._final_estimate(interrupted)
        last_ns = self.frames[-1].timestamp_ns if self.frames else None
        estimate, stripes, selfcal = self._self_calibration(estimate, interrupted, last_ns)
        result = RunResult(
            config=self.config,
            frames=self.frames,
            online=_online_trajectory(self.frames),
            final=self._final_trajectory(),
            keyframes=self._keyframe_trajectory(),
            keyframe_ids=np.array(list(self.keyframes), dtype=np.int64),
            interrupted=interrupted,
        )
        if estimate is not None:
            result.landmark_ids, result.landmarks_in_world = estimate.landmark_ids, estimate.landmarks_in_world
        if self.resume is not None:
            _prepend_resumed(result, self.resume)
        final_refine_s = time.perf_counter() - t_final
        result.stripes = stripes if stripes is not None else run_stripes(self.sequence, last_ns, self.config.mapping)
        result.mesh, mesh_metrics = final_mesh(
            self.sequence, result.stripes, result.online, result.final, self.config.mapping
        )
        result.live_mesh = self.live.mesh()
        result.metrics = self._metrics(result, wall, final_refine_s, mesh_metrics)
        if selfcal is not None:
            result.metrics.update(selfcal.metrics())
            result.calibration_refined = selfcal.calibration
            result.calibration_report = selfcal.report()
        result.session_map = self._session_map(result)
        if self.localizer is not None:
            self._localization(result, self.localizer)
        if self.mode == "extend":
            self._extend(result)
        for listener in self.listeners:
            listener.on_finish(result)
        return result

    def _session_map(self, result: RunResult) -> SessionMap | None:
        """The run's map for later sessions (``output.write_map``; None without keyframes or when it fails)."""
        if not self.config.output.write_map or not self.map_keyframes:
            return None
        from loopmodel.config import dump_config, pipeline_sections
        from loopmodel.loop.session_map import MapInputs, build_session_map
        from loopmodel.mapping.final import anchor_stripes

        poses = self.anchored.keyframe_poses
        kfs = [self.map_keyframes[k] for k in sorted(self.map_keyframes)]
        frames = [f for f in self.frames if f.ok]
        anchors = anchor_stripes(
            result.stripes,
            result.final,
            np.array([f.timestamp_ns for f in frames], np.int64),
            np.array([f.keyframe_id for f in frames], np.int64),
            poses,
            self.config.mapping,
        )
        inputs = MapInputs(
            self.frontend.calibration,
            kfs,
            {k: poses[k] for k in self.map_keyframes if k in poses},
            result.landmark_ids,
            result.landmarks_in_world,
            [(c.kf_a, c.kf_b, c.a_from_b) for c in self.loop_constraints],
            anchors,
            dump_config(self.config, pipeline_sections()),
            {"sequence": str(self.sequence.path)},
        )
        try:
            smap = build_session_map(inputs, self.config.loop)
        except LoopmodelError as exc:
            logger.error("no session map: %s", exc)
            return None
        if self.resume is not None:
            from loopmodel.loop.merge import append_session

            smap = append_session(self.resume.map, smap)
        return smap

    def _localization(self, result: RunResult, localizer: MapLocalizationStage) -> None:
        """Per-frame status in the map (``MAP``, ``OWN`` frame, ``LOST``) and the frames localized in it."""
        status = [
            "LOST" if not f.ok else ("MAP" if localizer.in_map.get(f.keyframe_id, False) else "OWN")
            for f in self.frames
        ]
        in_map = {f.timestamp_ns for f, st in zip(self.frames, status, strict=True) if st == "MAP"}
        result.localized = result.final.slice(np.isin(result.final.timestamps_ns, list(in_map)))
        m = result.metrics
        m["localization_status"] = status
        m["localized_frames"] = len(in_map)
        if not localizer.events:
            logger.warning("never relocalized in the map: the poses are in this session's own frame")
        gt = self.sequence.ground_truth
        m.update({k + "_localized": v for k, v in _ground_truth_errors(result.localized, gt).items()})

    def _extend(self, result: RunResult) -> None:
        """The session's map merged into the base map; the mesh of both sessions' stripes.

        A session that shares no view with the map says so and keeps its own frame and map.
        """
        from loopmodel.errors import InputError
        from loopmodel.loop.merge import merge_maps
        from loopmodel.mapping.final import posed_stripes_mesh

        assert self.base_map is not None
        if result.session_map is None:
            logger.warning("no map of this session: nothing to merge")
            return
        s = self.config.session
        try:
            merged, report = merge_maps(
                self.base_map, result.session_map, self.config.loop, s.merge_agree_m, s.merge_agree_deg
            )
        except InputError as exc:
            logger.warning("session not merged, it keeps its own frame: %s", exc)
            result.metrics["merged"] = False
            return
        result.session_map = merged
        T = report.world_a_from_world_b
        result.final = Trajectory(result.final.timestamps_ns, T[None] @ result.final.world_from_cam)
        result.keyframes = Trajectory(result.keyframes.timestamps_ns, T[None] @ result.keyframes.world_from_cam)
        stripes, poses = merged.stripes_with_poses()
        result.mesh = posed_stripes_mesh(stripes, poses, self.config.mapping)
        result.metrics.update(
            {
                "merged": True,
                "merge_links": report.links,
                "merge_candidates": report.candidates,
                "merge_offset_m": report.offset_m,
                "merge_offset_deg": report.offset_deg,
                "merged_keyframes": len(merged),
            }
        )

    def _metrics(
        self, result: RunResult, wall_s: float, final_refine_s: float, mesh_metrics: dict[str, Any]
    ) -> dict[str, Any]:
        """``metrics.json``.

        Each stage's own figures, the run's timings, the errors against the ground truth of the
        online and the final trajectories.
        """
        busy_s = sum(self.frame_ms) / 1e3
        m: dict[str, Any] = {"sequence": str(self.sequence.path), "interrupted": result.interrupted}
        m.update(mesh_metrics)
        m.update(frontend_metrics(self.frames, wall_s))
        m["fps"] = len(self.frames) / busy_s if busy_s > 0 else None
        m["backend"] = self.config.backend.kind
        m["final_refine_s"] = final_refine_s
        m.update(self.loop.metrics())
        m.update(self.live.metrics())
        m.update(self.backend.metrics())
        m["landmarks"] = int(result.landmark_ids.size)
        m.update(_quantiles(self.frame_ms, "frame_total_ms"))
        m.update(_quantiles(self.backend_ms, "backend_ms"))
        gt = self.sequence.ground_truth
        for suffix, traj in (("_online", result.online), ("", result.final)):
            m.update({k + suffix: v for k, v in _ground_truth_errors(traj, gt).items()})
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
) -> RunResult:
    """Reader -> front end -> loop closing -> back end -> mapping, writing nothing.

    Runs until the sequence ends, ``max_frames`` frames are done, ``stop`` is set (checked
    between frames) or a ``KeyboardInterrupt`` arrives (the last two: ``interrupted``). An
    error while processing a frame ends the run too: the result of the frames before it is
    returned with the error in ``error`` (and ``metrics["stopped_by"]``), for the caller to
    raise once it has kept what it wants. With ``base_map`` the session localizes in that map or
    extends it (``config.session.mode``); with ``resume`` it continues an interrupted run from its
    last keyframe (frames before it are skipped and keep the interrupted run's poses)."""
    run = _Run(sequence, config, listeners or [], base_map, resume)
    total = len(sequence) if max_frames is None else min(len(sequence), max_frames)
    stop = stop if stop is not None else StopFlag()
    logger.info("pipeline on %s (%d frames, back end %s)", sequence.path, total, config.backend.kind)
    interrupted, error = _frame_loop(run, total, stop, progress)
    if interrupted:
        logger.warning("interrupted after %d frames", len(run.frames))
    if error is not None:
        logger.error("stopped after %d frames: %s", len(run.frames), error)
    stop.finishing = run.finishing_note()
    result = run.finish(interrupted)
    if error is not None:
        result.error = error
        result.metrics["stopped_by"] = str(error).splitlines()[0] if str(error) else type(error).__name__
    fps = result.metrics["fps"]
    logger.info(
        "done: %d frames, %d keyframes, %s fps", len(run.frames), len(run.keyframes), f"{fps:.1f}" if fps else "-"
    )
    return result


def _frame_loop(
    run: _Run, total: int, stop: StopFlag, progress: PipelineProgressFn | None
) -> tuple[bool, Exception | None]:
    """Feed the frames to ``run`` one whole step at a time.

    Returns whether it was stopped early (stop flag, ``KeyboardInterrupt``) and the error that ended
    it, if any.
    """
    try:
        for i, frame in enumerate(run.sequence.frames()):
            if i >= total:
                break
            if stop.is_set():
                return True, None
            if run.skips(frame):
                continue
            run.step(frame)
            if progress is not None:
                el = time.perf_counter() - run.t_start
                progress(i + 1, total, (i + 1) / el if el > 0 else 0.0, len(run.keyframes))
    except KeyboardInterrupt:
        return True, None
    except Exception as exc:  # the frames before it still give a result
        return False, exc
    return False, None


def _process_and_write(
    folder: ResultsFolder, sequence: Sequence, config: Config, handle_signals: bool, **kwargs: Any
) -> RunResult:
    """Run :func:`process` under a log capture, then write the results into ``folder``.

    :func:`process` runs under a log capture (and the signal handlers when asked), then
    :func:`~loopmodel.io.results.write_results` writes into ``folder``.
    """
    stop = StopFlag()
    signals = stop_on_signals(stop) if handle_signals else contextlib.nullcontext(stop)
    with LogCapture() as log, signals:
        result = process(sequence, config, stop=stop, **kwargs)
        result.log = log.text()
        result.folder = write_results(folder, result)
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
) -> RunResult:
    """:func:`process` the sequence and write the results folder ``<out_dir>/<name>/``.

    By :func:`loopmodel.io.results.write_results`; ``out_dir`` defaults to ``output.out_dir``.

    Every keyframe first goes to loop closing (``config.loop``: relocalization of a new
    segment, verified revisits whose observations of old landmarks join the keyframe's
    monocular observations, plus a relative-pose loop constraint), then to the back end
    (``config.backend.kind``); keyframes it moves are handed back to the front end and to
    the anchored trajectory, in which every frame is stored relative to its keyframe.
    ``metrics.json`` lists each closure under ``loop_events``. With ``handle_signals``
    Ctrl-C or SIGTERM stops the run after the current frame; everything up to it is
    written, then ``KeyboardInterrupt`` is raised (an error ending the run early is raised
    after the write as well). With ``base_map`` (a loaded
    :class:`~loopmodel.loop.session_map.SessionMap`) the session localizes in it or extends it
    (``config.session.mode``); with ``resume`` (:func:`~loopmodel.loop.session_map.read_resume_point`)
    it continues an interrupted run from its last keyframe.
    """
    folder = ResultsFolder(out_dir if out_dir is not None else config.output.out_dir, name)
    kwargs: dict[str, Any] = {"progress": progress, "max_frames": max_frames, "listeners": listeners}
    kwargs.update(base_map=base_map, resume=resume)
    result = _process_and_write(folder, sequence, config, handle_signals, **kwargs)
    if result.error is not None:
        raise result.error
    if result.interrupted:
        raise KeyboardInterrupt
    return result


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
) -> RunResult:
    """Run the whole pipeline over a sequence and return what it produced.

    ``source``: an MCAP file, a EuRoC or KITTI folder, or an opened sequence;
    ``config``: a :class:`~loopmodel.config.Config`, the path of a YAML file, a (partial)
    nested dict, or None for the defaults. Writes nothing unless ``out_dir`` is given (then
    the results folder ``<out_dir>/<name>/``). Installs no signal handler unless
    ``handle_signals`` (Ctrl-C and SIGTERM then stop it after the current frame); an
    interrupted run returns its result with ``interrupted`` True; an error is raised (after
    the write when ``out_dir`` is given). ``listeners`` are told every event
    (:class:`~loopmodel.listener.RunListener`: visualisation, recording)."""
    from loopmodel.config import config_from_dict, load_config
    from loopmodel.io.sequence import open_sequence

    if isinstance(config, Mapping):
        cfg = config_from_dict(dict(config))
    else:
        cfg = config if isinstance(config, Config) else load_config(config)
    seq = source if isinstance(source, Sequence) else open_sequence(source, cfg.sequence)
    kwargs: dict[str, Any] = {"progress": progress, "max_frames": max_frames, "listeners": listeners}
    if out_dir is not None:
        result = _process_and_write(ResultsFolder(out_dir, name), seq, cfg, handle_signals, **kwargs)
    else:
        stop = StopFlag()
        with stop_on_signals(stop) if handle_signals else contextlib.nullcontext(stop):
            result = process(seq, cfg, stop=stop, **kwargs)
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
