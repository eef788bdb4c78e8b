"""How a run relates to earlier sessions: a saved map to localize in or extend (issue 20), a run to resume.

Small objects the pipeline's recipe (:mod:`loopmodel.pipeline`) calls at fixed points. A plain run
makes its own map (:class:`OwnMap`) and resumes nothing (``None``).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import Config
from loopmodel.errors import InputError
from loopmodel.types import StereoCalibration, StereoFrame, Trajectory

if TYPE_CHECKING:
    from loopmodel.frontend import FrameResult
    from loopmodel.loop.localize import MapLocalizationStage
    from loopmodel.loop.session_map import ResumePoint, SessionMap
    from loopmodel.result import RunResult

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


def localize_config(config: Config) -> Config:
    """``config`` for localization in a map: the tracker's poses (no back end), no map of its own."""
    out = config.model_copy(deep=True)
    out.backend.kind = "none"
    out.output.write_map = False
    return out


class OwnMap:
    """A run that makes its own map (no saved map): the recipe as it is."""

    #: the loop stage of a localization (every keyframe, and frames until in the map, relocalized)
    localizer: MapLocalizationStage | None = None

    def run_config(self, config: Config) -> Config:
        """The configuration the run uses."""
        return config

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
        m["localization_status"] = status
        m["localized_frames"] = len(in_map)
        if not localizer.events:
            logger.warning("never relocalized in the map: the poses are in this session's own frame")


class Extend(OwnMap):
    """A normal run whose map is merged into ``base_map`` at the end, with the mesh of both sessions' stripes."""

    def __init__(self, base_map: SessionMap) -> None:
        self.base_map = base_map

    def finish(self, result: RunResult, frames: list[FrameResult], config: Config) -> None:
        """The session's map merged into the base map (its world); a session sharing no view keeps its own."""
        from loopmodel.loop.merge import merge_maps
        from loopmodel.mapping.final import posed_stripes_mesh

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
