"""How a run relates to earlier sessions: a saved map to localize in or extend (issue 20), a run to resume.

Small objects the pipeline's recipe (:mod:`loopmodel.pipeline`) calls at fixed points. A plain run
makes its own map (:class:`OwnMap`) and resumes nothing (``None``).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import Config
from loopmodel.errors import InputError, LoopmodelError
from loopmodel.types import StereoCalibration, StereoFrame, Trajectory

if TYPE_CHECKING:
    from loopmodel.config import SelfCalibrationConfig
    from loopmodel.frontend import FrameResult
    from loopmodel.loop.localize import MapLocalizationStage
    from loopmodel.loop.session_map import MapCalibration, ResumePoint, SessionMap
    from loopmodel.result import RunResult

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


def localize_config(config: Config) -> Config:
    """``config`` for localization in a map: the tracker's poses (no back end), no map of its own."""
    out = config.model_copy(deep=True)
    out.backend.kind = "none"
    out.output.write_map = False
    return out


def rig_difference_sigma(
    recorded: StereoCalibration, map_calibration: MapCalibration, config: SelfCalibrationConfig
) -> dict[str, float]:
    """Each parameter's difference between a session's recorded rig and a map's refined one, in combined sigmas.

    Parameters as :data:`~loopmodel.calibration.refine_rig.PARAM_NAMES` (rotation: the angle of the
    relative stereo rotation about each axis, degrees); the recorded calibration's sigma is the
    configured prior (``calibration.sigma_*``), the map's its posterior. Empty when the two cannot be
    compared (image size or camera model differ: then they are different rigs).
    """
    from loopmodel.calibration.refine_rig import PARAM_NAMES, RigParameters, prior_sigmas
    from loopmodel.geometry.se3 import so3_log

    ref = map_calibration.refined
    if tuple(recorded.image_size) != tuple(ref.image_size) or recorded.camera_model != ref.camera_model:
        return {}
    try:
        a, b = RigParameters.of(recorded).values, RigParameters.of(ref).values
    except LoopmodelError:
        return {}
    diff = a - b
    R = np.asarray(recorded.right_from_left, float)[:3, :3] @ np.asarray(ref.right_from_left, float)[:3, :3].T
    rot = PARAM_NAMES.index("rot_x_deg")  # rot_x, rot_y, rot_z
    diff[rot : rot + 3] = np.degrees(so3_log(R))
    prior = prior_sigmas(
        config.sigma_focal_px, config.sigma_principal_px, config.sigma_k1, config.sigma_k2,
        config.sigma_rotation_deg, config.sigma_baseline_m,
    )
    prior[rot : rot + 3] = config.sigma_rotation_deg
    out = {}
    for i, name in enumerate(PARAM_NAMES):
        post = map_calibration.sigma.get(name, float(prior[i]))
        out[name] = float(abs(diff[i]) / np.hypot(prior[i], post))
    return out


def session_calibration(
    recorded: StereoCalibration, base_map: SessionMap, config: SelfCalibrationConfig, same_rig_sigma: float = 4.0
) -> tuple[StereoCalibration, dict[str, object]]:
    """The calibration a session in ``base_map`` starts from, and what was decided (for ``metrics.json``).

    The map's refined calibration when the map has one and the session's recorded rig is the same
    (every parameter within ``same_rig_sigma``, ``session.same_rig_sigma``, of
    :func:`rig_difference_sigma`); else the session's own, and the log says why. ``recorded`` is the
    session's raw calibration.
    """
    mc = base_map.refined_calibration
    if mc is None:
        return recorded, {"session_calibration": "own", "session_calibration_why": "the map has no refined calibration"}
    diff = rig_difference_sigma(recorded, mc, config)
    if not diff:
        logger.info("calibration: the map's rig has another image size or camera model; this session keeps its own")
        return recorded, {"session_calibration": "own", "session_calibration_why": "image size or camera model differ"}
    worst = max(diff, key=lambda k: diff[k])
    info: dict[str, object] = {
        "session_calibration_max_sigma": round(diff[worst], 3),
        "session_calibration_worst": worst,
    }
    if same_rig_sigma <= 0 or diff[worst] > same_rig_sigma:
        logger.info(
            "calibration: the map was made with another rig (%s differs by %.1f sigma): this session keeps its own",
            worst, diff[worst],
        )
        return recorded, {"session_calibration": "own", "session_calibration_why": "another rig", **info}
    logger.info(
        "calibration: the map's refined calibration (the same rig: largest difference %.1f sigma, %s)",
        diff[worst], worst,
    )
    return mc.refined, {"session_calibration": "map", **info}


def refined_map_points(
    smap: SessionMap,
    recorded: StereoCalibration,
    refined: StereoCalibration,
    keyframe_points: Mapping[int, F64] | None = None,
) -> SessionMap:
    """``smap`` with its keyframes' stereo points placed as the refined calibration places them (issue 31).

    The front end triangulated each keyframe's points with the recorded calibration; a later
    session relocalizes against them (:class:`~loopmodel.loop.localize.MapLocalizationStage`: P3P and
    the KLT stage on one map keyframe's points), so their error becomes the localization's. Each point
    becomes its refined landmark (``smap.landmarks_in_world``, the calibrating bundle adjustment's)
    seen from its refined keyframe, or, for a landmark the refinement did not hold, the keyframe's
    stereo match triangulated with the refined rig: ``keyframe_points`` (keyframe id -> its rows, the
    run's one triangulation, :func:`~loopmodel.calibration.retrack.refined_stereo_points`, keyed by
    this map's keyframe ids) where it has the keyframe, else triangulated here in one batch
    (:func:`~loopmodel.calibration.retrack.refined_stereo_px_points`); one that does not converge keeps
    its point. The loop features' 3-D points (``features.points_in_kf``, rectified keyframe frame)
    follow their landmarks. Frames: keyframe = the raw left camera (``world_from_kf``), metres.
    """
    import dataclasses

    from loopmodel.calibration.retrack import refined_stereo_px_points
    from loopmodel.geometry.se3 import invert_pose

    held = np.asarray(smap.landmark_ids, np.int64).ravel()
    order = np.argsort(held, kind="stable")
    held_sorted, held_pts = held[order], np.asarray(smap.landmarks_in_world, float).reshape(-1, 3)[order]
    pts = np.array(smap.lm_points_in_kf, dtype=float, copy=True)
    new = np.full(pts.shape, np.nan)
    lm_ids = np.asarray(smap.lm_ids, np.int64)
    at = np.minimum(np.searchsorted(held_sorted, lm_ids), max(held_sorted.size - 1, 0))
    known = (held_sorted.size > 0) & (held_sorted[at] == lm_ids)
    todo = np.zeros(pts.shape[0], bool)  # rows to triangulate here (no shared point for their keyframe)
    shared = keyframe_points or {}
    for i in range(len(smap)):
        a, b = int(smap.lm_offsets[i]), int(smap.lm_offsets[i + 1])
        if b <= a:
            continue
        kf_from_world = invert_pose(np.asarray(smap.world_from_kf[i], float))
        k = known[a:b]
        new[a:b][k] = held_pts[at[a:b][k]] @ kf_from_world[:3, :3].T + kf_from_world[:3, 3]
        p = shared.get(int(smap.keyframe_ids[i]))
        if p is not None and p.shape[0] == b - a:
            new[a:b][~k] = p[~k]
        else:
            todo[a:b] = ~k
    if todo.any():
        new[todo] = refined_stereo_px_points(np.asarray(smap.lm_stereo_px, float)[todo], recorded, refined)
    ok = np.all(np.isfinite(new), axis=1) & (new[:, 2] > 0)
    pts[ok] = new[ok]
    # the loop features at their keyframe's landmarks, in the rectified keyframe frame
    f = smap.features
    fpts = np.array(f.points_in_kf, dtype=float, copy=True)
    for i in range(len(smap)):
        a, b = int(smap.lm_offsets[i]), int(smap.lm_offsets[i + 1])
        lo, hi = int(f.offsets[i]), int(f.offsets[i + 1])
        if b <= a or hi <= lo:
            continue
        ids = lm_ids[a:b]
        srt = np.argsort(ids, kind="stable")
        fid = np.asarray(f.ids[lo:hi], np.int64)
        pos = np.minimum(np.searchsorted(ids[srt], fid), b - a - 1)
        row = srt[pos]
        hit = (fid >= 0) & (ids[row] == fid) & ok[a + row]
        rect = np.asarray(smap.rect_from_cam[i], float)
        fpts[lo:hi][hit] = pts[a + row[hit]] @ rect[:3, :3].T + rect[:3, 3]
    logger.info("map: %d of %d keyframe points placed with the refined calibration", int(ok.sum()), pts.shape[0])
    features = dataclasses.replace(f, points_in_kf=fpts)
    return dataclasses.replace(smap, lm_points_in_kf=pts, features=features)


class OwnMap:
    """A run that makes its own map (no saved map): the recipe as it is."""

    #: the loop stage of a localization (every keyframe, and frames until in the map, relocalized)
    localizer: MapLocalizationStage | None = None
    #: what :meth:`calibration` decided (``metrics.json``)
    calibration_info: dict[str, object] = {}

    def run_config(self, config: Config) -> Config:
        """The configuration the run uses."""
        return config

    def calibration(self, recorded: StereoCalibration, config: Config) -> StereoCalibration:
        """The raw calibration the run starts from (the sequence's ``recorded`` one, or a map's refined one)."""
        return recorded

    def setup(self, config: Config, calibration: StereoCalibration) -> None:
        """Build what the session needs once the run's configuration and calibration are known."""

    def finish(self, result: RunResult, frames: list[FrameResult], config: Config) -> None:
        """Complete ``result`` once the run's own map is made."""


class Localize(OwnMap):
    """Every keyframe relocalized in ``base_map``; the poses are the tracker's, corrected into the map."""

    def __init__(self, base_map: SessionMap) -> None:
        self.base_map = base_map

    def run_config(self, config: Config) -> Config:
        return localize_config(config)

    def calibration(self, recorded: StereoCalibration, config: Config) -> StereoCalibration:
        """The map's refined calibration when the rig is the same (issue 31 item 4), else ``recorded``."""
        cal, self.calibration_info = session_calibration(
            recorded, self.base_map, config.calibration, config.session.same_rig_sigma
        )
        return cal

    def setup(self, config: Config, calibration: StereoCalibration) -> None:
        from loopmodel.loop.localize import MapLocalizationStage

        s = config.session
        self.localizer = MapLocalizationStage(
            self.base_map, calibration, config.loop, s.max_correction_m, s.max_correction_deg
        )

    def finish(self, result: RunResult, frames: list[FrameResult], config: Config) -> None:
        """Per-frame status in the map (``MAP``, ``OWN`` frame, ``LOST``) and the frames localized in it."""
        localizer = self.localizer
        assert localizer is not None
        status = [
            "LOST" if not f.ok else ("MAP" if localizer.in_map.get(f.keyframe_id, False) else "OWN") for f in frames
        ]
        in_map = {f.timestamp_ns for f, st in zip(frames, status, strict=True) if st == "MAP"}
        result.localized = result.final.slice(np.isin(result.final.timestamps_ns, list(in_map)))
        m = result.metrics
        m.update(self.calibration_info)
        m["localization_status"] = status
        m["localized_frames"] = len(in_map)
        if not localizer.events:
            logger.warning("never relocalized in the map: the poses are in this session's own frame")


class Extend(OwnMap):
    """A normal run whose map is merged into ``base_map`` at the end, with the mesh of both sessions' stripes."""

    def __init__(self, base_map: SessionMap) -> None:
        self.base_map = base_map

    def calibration(self, recorded: StereoCalibration, config: Config) -> StereoCalibration:
        """The map's refined calibration when the rig is the same (issue 31 item 4), else ``recorded``.

        With ``calibration.refine`` this session refines it again (priors: the configured sigmas).
        """
        cal, self.calibration_info = session_calibration(
            recorded, self.base_map, config.calibration, config.session.same_rig_sigma
        )
        return cal

    def finish(self, result: RunResult, frames: list[FrameResult], config: Config) -> None:
        """The session's map merged into the base map (its world); a session sharing no view keeps its own."""
        from loopmodel.loop.merge import merge_maps
        from loopmodel.mapping.final import posed_stripes_mesh

        result.metrics.update(self.calibration_info)

        if result.session_map is None:
            logger.warning("no map of this session: nothing to merge")
            return
        s = config.session
        try:
            merged, report = merge_maps(
                self.base_map, result.session_map, config.loop, s.merge_agree_m, s.merge_agree_deg
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
        result.mesh = posed_stripes_mesh(stripes, poses, config.mapping)
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


def map_session(config: Config, base_map: SessionMap | None) -> OwnMap:
    """The session of a run: its own map, or localizing in / extending ``base_map`` (``session.mode``)."""
    if base_map is None:
        return OwnMap()
    return Localize(base_map) if config.session.mode == "localize" else Extend(base_map)


class Resumed:
    """A run that continues an interrupted one from its last keyframe (``loopmodel run --resume``).

    Frames before that keyframe are skipped and keep the interrupted run's poses; the first keyframe
    takes the old last keyframe's pose; the maps and trajectories are joined at the end.
    """

    def __init__(self, point: ResumePoint) -> None:
        self.point = point

    def skips(self, frame: StereoFrame) -> bool:
        """Whether the frame is before the interrupted run's last keyframe."""
        return int(frame.timestamp_ns) < self.point.timestamp_ns

    @property
    def world_from_first_kf(self) -> F64:
        """The pose of the resumed run's first keyframe (the interrupted run's last one)."""
        return self.point.world_from_kf

    def join_result(self, result: RunResult) -> None:
        """The interrupted run's frames and keyframes before the resumed run's first one, then the new ones."""
        resume = self.point

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

    def join_map(self, smap: SessionMap) -> SessionMap:
        """The interrupted run's map with this run's appended."""
        from loopmodel.loop.merge import append_session

        return append_session(self.point.map, smap)
