"""Loop closing as a pipeline stage: keyframes in, corrections out to the tracker.

:class:`LoopClosingStage` is fed every new keyframe of the front end. It

* relocalizes the first keyframe of a new segment (the front end starts one, unconnected,
  after tracking was lost) against the stored keyframes and, when that succeeds, moves
  the new segment into the old map;
* checks every keyframe for a verified revisit (:class:`~loopmodel.loop.closer.LoopCloser`)
  and, on one, runs the global hybrid BA over the loop and feeds the corrected keyframe
  poses back to the tracker (``apply_correction``) and to an optional listener (mesher,
  back end).

Each closure and relocalization is recorded as a plain dict (for ``metrics.json``):
keyframes and frames involved, inliers, correction size, optimisation time.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import LoopConfig
from loopmodel.geometry.se3 import invert_pose, so3_log
from loopmodel.loop.closer import LoopCloser, LoopClosure
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
    ) -> None:
        self.tracker = tracker
        self.config = config if config is not None else LoopConfig()
        self.closer = LoopCloser(calibration, self.config)
        self.listeners = listeners or []
        self.keyframes: dict[int, Any] = {}
        self.events: list[dict[str, Any]] = []
        self.rejected: list[dict[str, Any]] = []

    # ------------------------------------------------------------------ keyframes
    def on_keyframe(self, kf: Any) -> dict[str, Any] | None:
        """Process a new keyframe; returns the event record of a closure or
        relocalization it caused (None otherwise)."""
        self.keyframes[int(kf.id)] = kf
        event = None
        if not getattr(kf, "connected", True) and len(self.keyframes) > 1:
            event = self._relocalize_segment(kf)
        n_rej = len(self.closer.detector.rejected)
        closure = self.closer.process_keyframe(kf)
        for ev in self.closer.detector.rejected[n_rej:]:
            self.rejected.append({"query_kf": ev.query_id, "match_kf": ev.match_id, "reason": ev.reason})
        if closure is not None:
            event = self._close(closure)
        return event

    def _relocalize_segment(self, kf: Any) -> dict[str, Any] | None:
        """Place the first keyframe of a new segment in the old map."""
        t0 = time.perf_counter()
        kf_id, res = self.closer.relocalize(kf.image, exclude_after=int(kf.id) - 1)
        if kf_id is None or res.cam_from_map is None:
            logger.info("keyframe %d: relocalization failed (%s)", kf.id, res.reason)
            return None
        old = self.keyframes[kf_id]
        rect_from_cam = np.asarray(getattr(kf, "rect_from_cam", np.eye(4)))
        old_rect_from_cam = np.asarray(getattr(old, "rect_from_cam", np.eye(4)))
        world_from_old_rect = self.tracker.world_from_kf[kf_id] @ invert_pose(old_rect_from_cam)
        world_from_new = world_from_old_rect @ invert_pose(res.cam_from_map) @ rect_from_cam
        before = self.tracker.world_from_kf[int(kf.id)]
        corrected = {int(kf.id): world_from_new}
        self._apply(corrected)
        trans, rot = _motion(before, world_from_new)
        record = {
            "type": "relocalization",
            "keyframe": int(kf.id),
            "frame": int(getattr(kf, "frame_index", -1)),
            "match_keyframe": int(kf_id),
            "match_frame": int(getattr(old, "frame_index", -1)),
            "inliers": res.n_inliers,
            "correction_m": trans,
            "correction_deg": rot,
            "time_ms": (time.perf_counter() - t0) * 1e3,
        }
        self.events.append(record)
        logger.info("keyframe %d relocalized against keyframe %d", kf.id, kf_id)
        return record

    def _close(self, closure: LoopClosure) -> dict[str, Any]:
        kfs = [self.keyframes[k] for k in sorted(self.keyframes)]
        before = dict(self.tracker.world_from_kf)
        for k in kfs:  # the BA starts from the tracker's current estimate
            k.world_from_kf = before.get(int(k.id), k.world_from_kf)
        t0 = time.perf_counter()
        res = self.closer.correct(kfs, closure)
        opt_ms = (time.perf_counter() - t0) * 1e3
        self._apply(res.world_from_kf)
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
            "optimise_ms": opt_ms,
            "parameters": res.n_parameters,
            "residuals": res.n_residuals,
            "keyframes_optimised": len(res.world_from_kf),
        }
        self.events.append(record)
        logger.info(
            "loop %d -> %d closed: correction %.3f m / %.2f deg, BA %.0f ms",
            closure.query_kf,
            closure.match_kf,
            trans,
            rot,
            opt_ms,
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
