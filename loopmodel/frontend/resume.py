"""The old feature set the tracker goes on tracking after a closure (seed 004, section 5).

After a relocalization or a verified revisit the loop stage finds an old keyframe's features
again in the current keyframe (:class:`loopmodel.stages.ResumeFeatures`); the front end then
tracks them on, frame after frame, beside its own current set: pyramidal KLT started at the
positions the tracked pose predicts (from the loop's relative pose), kept while they stay
within the prediction gate. At every new keyframe each one is measured again against its own
keyframe's template, warped by the affine map the predicted pose implies
(:mod:`loopmodel.frontend.affine_klt`), and the features found become that keyframe's
monocular observations of the old landmarks (same landmark ids), which carry the loop into
the back end's global optimisation.

Frames: rectified left cameras; ``kf_from_match`` maps the old keyframe's rectified frame into
the active keyframe's; pixels are rectified.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from loopmodel.frontend.affine_klt import predicted_affine, refine_affine
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose
from loopmodel.imaging.klt import Pyramid, track_klt
from loopmodel.stages import ResumeFeatures

F64 = NDArray[np.float64]


@dataclass
class ResumedSet:
    """An old keyframe's features being tracked again.

    ``ids`` (K,) their landmark ids, ``points`` (K, 3) metres in the old keyframe's rectified
    frame, ``match_uv`` (K, 2) their pixels in the old keyframe's image ``match_image``,
    ``uv`` (K, 2) where they are in the last tracked frame, ``kf_from_match`` the old
    keyframe's rectified frame in the active keyframe's. ``at_keyframes``: how many were
    observed at each keyframe since the closure (its own first).
    """

    match_keyframe: int
    ids: NDArray[np.int64]
    points: F64
    match_uv: F64
    match_image: NDArray[np.uint8]
    uv: F64
    kf_from_match: F64
    at_keyframes: list[int] = field(default_factory=list)

    @classmethod
    def from_request(cls, req: ResumeFeatures) -> ResumedSet:
        """The set as the loop stage hands it over (found in the current keyframe)."""
        ids = np.asarray(req.landmark_ids, np.int64).reshape(-1)
        return cls(
            int(req.match_keyframe),
            ids,
            np.asarray(req.points_in_match, float).reshape(-1, 3),
            np.asarray(req.match_uv_px, float).reshape(-1, 2),
            np.asarray(req.match_image),
            np.asarray(req.uv_px, float).reshape(-1, 2),
            np.asarray(req.kf_from_match, float).reshape(4, 4),
            [int(ids.size)],
        )

    def __len__(self) -> int:
        return int(self.ids.size)

    def _keep(self, sel: NDArray[np.bool_] | NDArray[np.int64], uv: F64) -> None:
        self.ids, self.points, self.match_uv = self.ids[sel], self.points[sel], self.match_uv[sel]
        self.uv = uv

    def predict(self, camera: CentralCamera, cur_from_kf: F64) -> tuple[F64, NDArray[np.bool_]]:
        """Pixels (K, 2) the pose ``cur_from_kf`` (active keyframe -> current, rectified) predicts; in front."""
        cur_from_match = cur_from_kf @ self.kf_from_match
        p = self.points @ cur_from_match[:3, :3].T + cur_from_match[:3, 3]
        front = camera.in_front(p)
        pred = self.uv.copy()
        if np.any(front):
            pred[front] = camera.project(p[front])
        return pred, front

    def track(
        self,
        camera: CentralCamera,
        prev: Pyramid,
        cur: Pyramid,
        kf_from_cur: F64,
        gate_px: float,
        klt: tuple[int, int, float, int],
        image_size: tuple[int, int],
    ) -> int:
        """KLT from the previous frame to ``cur``, started at the predicted pixels; keep those within ``gate_px``.

        ``kf_from_cur``: the current frame's tracked pose (rectified, active keyframe frame);
        ``klt``: window (px), pyramid levels, forward-backward tolerance (px), iterations.
        Returns how many remain.
        """
        if not len(self):
            return 0
        pred, _front = self.predict(camera, invert_pose(kf_from_cur))
        window, levels, fb_px, iterations = klt
        uv, ok, _ = track_klt(prev, cur, self.uv, pred, window, levels, fb_px, iterations, image_size)
        return self.keep_tracked(camera, kf_from_cur, uv, ok, gate_px)

    def keep_tracked(
        self, camera: CentralCamera, kf_from_cur: F64, uv: F64, ok: NDArray[np.bool_], gate_px: float
    ) -> int:
        """Take a frame's KLT of the set (``uv`` (K, 2) px, valid ``ok``): those within ``gate_px`` of the prediction.

        ``kf_from_cur``: the frame's solved pose (rectified, active keyframe frame); a point it puts
        behind the camera is dropped. The KLT may have started elsewhere (the frame's motion-model
        prediction, fr16: one KLT call with the frame's other points). Returns how many remain.
        """
        pred, front = self.predict(camera, invert_pose(kf_from_cur))
        keep = ok & front & (np.linalg.norm(uv - pred, axis=1) < gate_px)
        self._keep(keep, uv[keep])
        return len(self)

    def observe_at_keyframe(
        self,
        camera: CentralCamera,
        left: NDArray[np.uint8],
        kf_from_cur: F64,
        kf_from_new: F64,
        half_window_px: int,
        min_ncc: float,
        max_shift_px: float,
    ) -> F64:
        """Measure the set in a new keyframe's image ``left`` against the old keyframe's warped templates.

        ``kf_from_cur``: the tracked pose of the new keyframe (rectified, active keyframe frame),
        ``kf_from_new`` the one after the local BA; the set moves to the new keyframe. Returns rows
        (landmark_id, u, v) of the features found; the others are dropped.
        """
        if not len(self):
            return np.zeros((0, 3))
        cur_from_match = invert_pose(kf_from_cur) @ self.kf_from_match
        match = refine_affine(
            self.match_image,
            left,
            self.match_uv,
            self.uv,
            predicted_affine(camera, self.points, cur_from_match),
            half_window_px,
            min_ncc=min_ncc,
            max_shift_px=max_shift_px,
        )
        ok = match.ok
        self._keep(ok, match.uv_px[ok])
        self.kf_from_match = invert_pose(kf_from_new) @ self.kf_from_match
        self.at_keyframes.append(len(self))
        return np.column_stack([self.ids.astype(float), self.uv])
