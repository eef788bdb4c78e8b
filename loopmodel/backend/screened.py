"""Back ends built on the Givens blunder screen (seed 000).

``backend.kind: both`` — every keyframe's observations pass the sequential Givens estimator
with Baarda data snooping first; rejected observations never reach the inner back end
(iSAM2), and earlier observations rejected later are removed from it.
``backend.kind: givens`` — the sequential estimator itself is the back end (keyframe poses
and landmarks from its current solution; it takes no loop constraints).

The screen works in the rectified left camera of each keyframe (the frame of the pixels).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable
from typing import Any

import numpy as np

from loopmodel.backend.base import F64, Backend, BackendEstimate, BackendUpdate, Observation
from loopmodel.backend.givens_bundle import GivensScreen
from loopmodel.config import RefineConfig
from loopmodel.errors import EstimationError
from loopmodel.types import Keyframe


def _rectified_view(kf: Keyframe) -> Keyframe:
    """The keyframe with its pose and points expressed in its rectified left camera."""
    rect_from_cam = np.asarray(kf.rect_from_cam, dtype=float)
    pts = np.asarray(kf.points_in_kf, dtype=float).reshape(-1, 3)
    return dataclasses.replace(
        kf,
        world_from_kf=kf.world_from_rect,
        points_in_kf=pts @ rect_from_cam[:3, :3].T + rect_from_cam[:3, 3],
        rect_from_cam=np.eye(4),
    )


def _subset(kf: Keyframe, keep_stereo: np.ndarray, keep_mono: np.ndarray) -> Keyframe:
    """A copy of the keyframe without the rejected observations.

    A landmark whose first, stereo observation is rejected is dropped altogether.
    """
    return dataclasses.replace(
        kf,
        landmark_ids=np.asarray(kf.landmark_ids)[keep_stereo],
        points_in_kf=np.asarray(kf.points_in_kf)[keep_stereo],
        stereo_px=np.asarray(kf.stereo_px)[keep_stereo],
        mono_obs=np.asarray(kf.mono_obs).reshape(-1, 3)[keep_mono],
    )


def _screen_metrics(screen: GivensScreen) -> dict[str, Any]:
    stats = screen.stats
    return {"givens_tested_observations": stats.tested, "givens_rejected_observations": stats.rejected}


class ScreenedBackend:
    """Any :class:`Backend` behind the Givens screen (``backend.kind: both``)."""

    def __init__(self, inner: Backend, screen: GivensScreen) -> None:
        self.inner = inner
        self.screen = screen

    def add_keyframe(self, keyframe: Keyframe) -> BackendUpdate:
        """Screen the keyframe's observations, pass the accepted ones on, remove late rejections."""
        keep_st, keep_mono = self.screen.screen_keyframe(_rectified_view(keyframe))
        update = self.inner.add_keyframe(_subset(keyframe, keep_st, keep_mono))
        update.rejected_observations += int((~keep_st).sum() + (~keep_mono).sum())
        late = self.screen.late_rejections()
        if late:
            pairs = [(int(f), int(p)) for f, p in late]  # type: ignore[call-overload]
            update.removed_blunders += self.inner.remove_observations(pairs)
        return update

    def add_observations(self, keyframe_id: int, mono_obs: F64) -> BackendUpdate:
        """Passed to the inner back end unscreened.

        A loop's observations, verified by the loop stage; the sequential screen takes a keyframe's
        observations only when the keyframe is inserted.
        """
        return self.inner.add_observations(keyframe_id, mono_obs)

    def add_loop_constraint(self, kf_a: int, kf_b: int, a_from_b: F64, sigmas: F64 | None = None) -> int:
        """Passed to the inner back end."""
        return self.inner.add_loop_constraint(kf_a, kf_b, a_from_b, sigmas)

    def remove_observations(self, observations: Iterable[Observation]) -> int:
        """Passed to the inner back end."""
        return self.inner.remove_observations(observations)

    def estimate(self, landmarks: bool = True) -> BackendEstimate:
        """The inner back end's estimate."""
        return self.inner.estimate(landmarks)

    def final_estimate(self, refine: RefineConfig | None) -> BackendEstimate:
        """The inner back end's end-of-run solution."""
        return self.inner.final_estimate(refine)

    def screen_stats(self) -> dict[str, int]:
        """Tested, rejected and not-yet-tested observation counts."""
        return dataclasses.asdict(self.screen.stats)

    def metrics(self) -> dict[str, Any]:
        """The screen's observation counts and the inner back end's figures."""
        return {**self.inner.metrics(), **_screen_metrics(self.screen)}


class GivensBackend:
    """The sequential Givens estimator as the back end (``backend.kind: givens``)."""

    def __init__(self, screen: GivensScreen, change_tol_m: float = 1e-4) -> None:
        self.screen = screen
        self.change_tol_m = change_tol_m
        self._rect_from_cam: dict[int, F64] = {}
        self._last: dict[int, F64] = {}

    def add_keyframe(self, keyframe: Keyframe) -> BackendUpdate:
        """Insert the keyframe's observations point by point, testing each for blunders."""
        t0 = time.perf_counter()
        n_points = len(self.screen.bundle.points)
        keep_st, keep_mono = self.screen.screen_keyframe(_rectified_view(keyframe))
        self._rect_from_cam[int(keyframe.id)] = np.asarray(keyframe.rect_from_cam, dtype=float)
        late = self.screen.late_rejections()
        removed = self.remove_observations((int(f), int(p)) for f, p in late)  # type: ignore[call-overload,operator]
        return BackendUpdate(
            int(keyframe.id),
            new_factors=int(keep_st.size + keep_mono.size),
            new_landmarks=len(self.screen.bundle.points) - n_points,
            rejected_observations=int((~keep_st).sum() + (~keep_mono).sum()),
            removed_blunders=removed,
            update_ms=(time.perf_counter() - t0) * 1e3,
        )

    def add_observations(self, keyframe_id: int, mono_obs: F64) -> BackendUpdate:
        """Not supported: the sequential estimator takes a frame's image points when it is inserted."""
        raise EstimationError(
            "the Givens back end takes no observations of an inserted keyframe; use backend.kind 'isam2' or 'both'"
        )

    def add_loop_constraint(self, kf_a: int, kf_b: int, a_from_b: F64, sigmas: F64 | None = None) -> int:
        """Not supported: the sequential estimator takes image points only."""
        raise EstimationError(
            "the Givens back end takes no relative-pose loop constraints; use backend.kind 'isam2' or 'both'"
        )

    def remove_observations(self, observations: Iterable[Observation]) -> int:
        """Downdate the named observations (blunders already deleted by snooping are skipped)."""
        wanted = set(observations)
        bundle = self.screen.bundle
        hits = [oid for oid, o in bundle.image_obs.items() if (o.frame, o.point) in wanted]
        for oid in hits:
            bundle.delete_image_point(oid)
        return len(hits)

    def estimate(self, landmarks: bool = True) -> BackendEstimate:
        """Keyframe poses (left camera) and landmarks from the current sequential solution."""
        bundle = self.screen.bundle
        poses = {
            int(fid): np.asarray(bundle.world_from_cam(fid)) @ self._rect_from_cam.get(int(fid), np.eye(4))  # type: ignore[call-overload,operator]
            for fid in bundle.frames
        }
        changed = {
            k
            for k, T in poses.items()
            if k not in self._last or np.abs(T[:3, 3] - self._last[k][:3, 3]).max() > self.change_tol_m
        }
        self._last = poses
        est = BackendEstimate(poses, changed_keyframes=changed)
        if landmarks and bundle.points:
            ids = np.array(sorted(bundle.points), dtype=np.int64)  # type: ignore[type-var]
            est.landmark_ids = ids
            est.landmarks_in_world = np.array([bundle.point(int(i)) for i in ids])
        return est

    def screen_stats(self) -> dict[str, int]:
        """Tested, rejected and not-yet-tested observation counts (for metrics.json)."""
        return dataclasses.asdict(self.screen.stats)

    def final_estimate(self, refine: RefineConfig | None) -> BackendEstimate:
        """The current sequential solution (it is the least-squares solution already)."""
        return self.estimate()

    def metrics(self) -> dict[str, Any]:
        """Tested and rejected observation counts."""
        return _screen_metrics(self.screen)
