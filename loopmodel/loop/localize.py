"""Localization in a saved map (``loopmodel run --map MAP --mode localize``, issue 20).

A :class:`~loopmodel.stages.LoopStage` whose database is the saved map's keyframes (their feature
sets, vocabulary and bags of words, :meth:`~loopmodel.loop.session_map.SessionMap.database`).
Every keyframe the front end makes is relocalized against the map (descriptors and the P3P bank,
then seed 004's KLT stage on the matched map keyframe's image); a success returns the keyframe's
pose in the map's world as a correction, so the tracker goes on in the map's frame. The first
success of a tracking segment (the start, or after a loss) moves the segment's earlier keyframes
rigidly with it; later ones replace the tracked pose when they agree with it within the gate
(``max_correction_m`` / ``_deg``), so one false match cannot throw the session away. Nothing is
added to the map. A segment that never relocalizes keeps the session's own frame.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any

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

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


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
    def on_keyframe(self, keyframe: Keyframe, state: MapState) -> LoopOutcome:
        """Relocalize the keyframe in the map; a success is a correction into the map's frame."""
        kf = keyframe
        kid, seg = int(kf.id), int(kf.segment)
        self._segment_kfs.setdefault(seg, []).append(kid)
        out = LoopOutcome(kf)
        t0 = time.perf_counter()
        found = self.relocalize(kf.image) if kf.image.size else None
        self.attempt_ms.append((time.perf_counter() - t0) * 1e3)
        self.in_map[kid] = seg in self._segment_in_map
        if found is None:
            return out
        map_kf, new_from_map, inliers, method = found
        world_from_new = self._map_world_from_rect(map_kf) @ invert_pose(new_from_map) @ kf.rect_from_cam
        tracked = np.asarray(state.world_from_kf.get(kid, kf.world_from_kf))
        trans, rot = _motion(tracked, world_from_new)
        first = seg not in self._segment_in_map
        if not first and (trans > self.max_correction_m or rot > self.max_correction_deg):
            self.gated += 1
            logger.info("keyframe %d: relocalization %.3f m / %.2f deg off the track: not applied", kid, trans, rot)
            return out
        if first:
            delta = world_from_new @ invert_pose(tracked)
            for k in self._segment_kfs[seg]:
                if k != kid and k in state.world_from_kf:
                    out.corrections[k] = delta @ np.asarray(state.world_from_kf[k])
                    self.in_map[k] = True
            self._segment_in_map.add(seg)
            logger.info("keyframe %d (frame %d) localized in the map at keyframe %d", kid, kf.frame_index, map_kf)
        out.corrections[kid] = world_from_new
        out.keyframe = dataclasses.replace(kf, world_from_kf=world_from_new)
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
        return out

    def close(self, state: MapState) -> dict[int, F64]:
        """Nothing pending."""
        return {}

    def final_constraints(self) -> list[LoopConstraint]:
        """None: nothing is added to the map."""
        return []

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
            "loop_events": self.events,
        }
