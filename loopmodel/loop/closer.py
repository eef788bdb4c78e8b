"""Loop closing on the front end's stereo keyframes (seed 004, sections 4.2-4.3).

:class:`LoopCloser` keeps, per keyframe, descriptors of two kinds: features detected in
the rectified left image (for the bag of words and matching) and descriptors computed at
the keyframe's own stereo-triangulated features (3-D positions and landmark ids). A new
keyframe is checked for a revisit by :class:`~loopmodel.loop.closure.LoopDetector`
(place recognition, temporal consistency, forward and reverse P3P-bank verification).
A verified revisit is refined as in the seed: the old feature set's features are searched
in the current image by pyramidal KLT started at their positions predicted by the
descriptor pose, and the P3P bank on those correspondences gives the final pose and the
loop observations (old landmark ids seen in the current keyframe) that enter the global
hybrid BA (:func:`loopmodel.loop.global_ba.global_hybrid_ba`).

Keyframes are duck-typed (the front end's ``Keyframe``): ``id``, ``image`` (rectified left,
uint8), ``stereo_px`` (M, 3: u_left, u_right, v, rectified pixels), ``points_in_kf``
(M, 3, metres, keyframe camera frame), ``landmark_ids`` (M,), ``rect_from_cam`` (4x4).
Poses returned here are between rectified keyframe frames unless named otherwise.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.config import LoopConfig
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose
from loopmodel.loop.closure import LoopEvent, detector_from_config, relocalize_in_database
from loopmodel.loop.features import FeatureSet, describe_at, detect_and_describe, make_extractor
from loopmodel.loop.global_ba import GlobalBAResult, LoopObservations, global_hybrid_ba
from loopmodel.loop.pnp import solve_pnp_bank
from loopmodel.loop.refine import project_refiner
from loopmodel.loop.reloc import RelocParams, RelocResult
from loopmodel.loop.resume import retrack_keyframe_features
from loopmodel.loop.vocabulary import Vocabulary
from loopmodel.types import Keyframe, StereoCalibration

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass
class LoopClosure:
    """A verified loop: keyframe ``query_kf`` sees the feature set of keyframe ``match_kf``.

    ``query_from_match`` (4x4, metres) maps the old keyframe's rectified frame to the
    current one's; ``observations`` are the old landmarks' rectified pixels in the current
    keyframe's left image. ``n_descriptor_inliers`` from the descriptor stage,
    ``n_klt_inliers`` from the KLT stage (0 when it did not improve on the former)."""

    query_kf: int
    match_kf: int
    query_from_match: F64
    observations: LoopObservations
    n_descriptor_inliers: int
    n_klt_inliers: int
    event: LoopEvent | None
    detect_ms: float
    refine_ms: float
    info: dict[str, Any] = field(default_factory=dict)


@dataclass
class _KfData:
    image: NDArray[np.uint8]
    uv: F64  # (M, 2) rectified left pixels of the landmarks
    p_rect: F64  # (M, 3) landmarks in the rectified keyframe frame
    ids: NDArray[np.int64]


class LoopCloser:
    """Relocalization and loop detection over the front end's keyframes.

    ``calibration`` is the rectified calibration the keyframes' pixels refer to; ``vocabulary`` the
    place recognition's (None: trained on the fly from the keyframes)."""

    def __init__(
        self, calibration: StereoCalibration, config: LoopConfig | None = None, vocabulary: Vocabulary | None = None
    ) -> None:
        self.config = config if config is not None else LoopConfig()
        self.calibration = calibration
        self.camera: CentralCamera = calibration.left_camera()
        self.detector = detector_from_config(self.config, self.camera, float(calibration.image_size[0]), vocabulary)
        self._extractor = make_extractor(self.config.descriptor, self.config.n_features, self.config.surf)
        self._kf: dict[int, _KfData] = {}
        self.closures: list[LoopClosure] = []

    # ---------------------------------------------------------------- features
    def image_features(self, image: NDArray[np.uint8]) -> FeatureSet:
        """Descriptors detected in a (rectified, left) image, without 3-D positions."""
        return detect_and_describe(image, self.config.descriptor, self.config.n_features, self._extractor)

    def frame_features(self, image: NDArray[np.uint8]) -> FeatureSet:
        """Features of a non-keyframe image (relocalization query).

        Detected ones plus descriptors at Shi-Tomasi corners, the kind of point a keyframe's
        landmarks are.
        """
        det = self.image_features(image)
        corners = cv2.goodFeaturesToTrack(image, 400, 0.01, 8)
        if corners is None:
            return det
        extra, _ = describe_at(image, corners.reshape(-1, 2), self.config.descriptor, extractor=self._extractor)
        return FeatureSet.concat(det, extra) if len(det) else extra

    def keyframe_features(self, kf: Keyframe) -> FeatureSet:
        """Detected features plus descriptors at the keyframe's stereo features.

        The stereo features carry 3-D positions in the rectified keyframe frame and landmark ids.
        """
        det = self.image_features(kf.image)
        data = self._kf_data(kf)
        lm, kept = describe_at(kf.image, data.uv, self.config.descriptor, extractor=self._extractor)
        lm.points_in_kf = data.p_rect[kept]
        lm.ids = data.ids[kept]
        return FeatureSet.concat(det, lm) if len(det) else lm

    def remember(self, kf: Keyframe) -> None:
        """Keep what :meth:`track_old_features` needs of a keyframe (image, landmarks)."""
        self._kf[int(kf.id)] = self._kf_data(kf)

    @staticmethod
    def _kf_data(kf: Keyframe) -> _KfData:
        rect_from_cam = np.asarray(kf.rect_from_cam)
        pts = np.asarray(kf.points_in_kf, dtype=float).reshape(-1, 3)
        sp = np.asarray(kf.stereo_px, dtype=float).reshape(-1, 3)
        return _KfData(
            np.asarray(kf.image),
            sp[:, [0, 2]].copy(),
            pts @ rect_from_cam[:3, :3].T + rect_from_cam[:3, 3],
            np.asarray(kf.landmark_ids, dtype=np.int64),
        )

    # ---------------------------------------------------------------- loops
    def process_keyframe(
        self, kf: Keyframe, neighbours: set[int] | None = None, query: bool = True,
        features: FeatureSet | None = None,
    ) -> LoopClosure | None:
        """Store a new keyframe and check it for a verified revisit.

        ``neighbours``: temporal neighbours, never verified; ``query`` False: store only;
        ``features``: its :meth:`keyframe_features` when already computed.
        """
        t0 = time.perf_counter()
        fs = self.keyframe_features(kf) if features is None else features
        self.remember(kf)
        ev = self.detector.process(int(kf.id), fs, query=query, neighbours=neighbours)
        t1 = time.perf_counter()
        if ev is None or ev.match_from_query is None:
            return None
        query_from_match = invert_pose(ev.match_from_query)
        cand = self.detector.database.features(ev.match_id)
        # descriptor-stage observations: inlier matches onto the old keyframe's landmarks
        obs_ids = np.zeros(0, np.int64)
        obs_uv = np.zeros((0, 2))
        if ev.matches is not None and ev.inliers is not None:
            m = ev.matches[ev.inliers]
            lid = cand.ids[m[:, 1]]
            ok = lid >= 0
            obs_ids, obs_uv = lid[ok], fs.keypoints_px[m[ok, 0]]
        n_klt = 0
        refined = self.track_old_features(ev.match_id, kf.image, query_from_match)
        if refined is not None and refined[1].size >= max(obs_ids.size, self.config.min_inliers):
            query_from_match, obs_ids, obs_uv = refined[0], refined[1], refined[2]
            n_klt = int(obs_ids.size)
        closure = LoopClosure(
            int(kf.id),
            ev.match_id,
            query_from_match,
            LoopObservations(int(kf.id), obs_ids, obs_uv),
            ev.n_inliers,
            n_klt,
            ev,
            (t1 - t0) * 1e3,
            (time.perf_counter() - t1) * 1e3,
        )
        self.closures.append(closure)
        logger.info(
            "loop %d -> %d: %d descriptor inliers, %d KLT inliers",
            closure.query_kf,
            closure.match_kf,
            closure.n_descriptor_inliers,
            n_klt,
        )
        return closure

    def track_old_features(
        self, match_id: int, image: NDArray[np.uint8], query_from_match: F64
    ) -> tuple[F64, NDArray[np.int64], F64] | None:
        """Seed 004's accuracy stage: re-find the old set's features, then run the P3P bank on them.

        The old set's features are found again in the current image from their predicted positions.
        Two trackers run: templates warped by the predicted pose with an enlarged search region
        (:func:`loopmodel.loop.resume.retrack_keyframe_features`) and pyramidal KLT; the one whose
        features give more P3P inliers is kept. Returns (query_from_match, landmark ids, pixels) of
        the inliers.
        """
        old = self._kf.get(match_id)
        if old is None or old.ids.size < 6:
            return None
        if old.image.size == 0 or image.size == 0 or old.image.shape != image.shape:
            return None  # no image to track in (OpenCV's pyramidal KLT would spin on a 0x0 one)
        best: tuple[F64, NDArray[np.int64], F64] | None = None
        for uv, idx in (self._warped_old(old, image, query_from_match), self._klt_old(old, image, query_from_match)):
            if idx.size < 6:
                continue
            res = solve_pnp_bank(
                self.camera.lift(uv),
                old.p_rect[idx],
                self.config.threshold_px / self.camera.px,
                rng=np.random.default_rng(0),
                max_samples=self.config.max_samples,
                min_inliers=6,
                refiner=project_refiner(self.camera),
            )
            if res is not None and (best is None or res.n_inliers > best[1].size):
                inl = res.inliers
                best = (res.cam_from_world, old.ids[idx[inl]], uv[inl])
        return best

    def _warped_old(self, old: _KfData, image: NDArray[np.uint8], cur_from_old: F64) -> tuple[F64, NDArray[np.int64]]:
        """Old features re-tracked with warped templates: pixels (K, 2) and their indices."""
        pos = np.arange(old.ids.size, dtype=np.int64)
        rt = retrack_keyframe_features(self.camera, old.image, old.uv, old.p_rect, pos, image, cur_from_old, 16)
        return rt.uv_px, rt.ids

    def _klt_old(self, old: _KfData, image: NDArray[np.uint8], query_from_match: F64) -> tuple[F64, NDArray[np.int64]]:
        """Old features tracked by pyramidal KLT (forward-backward checked).

        Returns pixels (K, 2) and their indices.
        """
        none = (np.zeros((0, 2)), np.zeros(0, np.int64))
        p_q = old.p_rect @ query_from_match[:3, :3].T + query_from_match[:3, 3]
        front = p_q[:, 2] > 0.05
        pred = self.camera.project(np.where(front[:, None], p_q, 1.0))
        h, w = image.shape[:2]
        inside = front & np.all((pred >= 0) & (pred < [w - 1, h - 1]), axis=1)
        if inside.sum() < 6:
            return none
        src = old.uv[inside].astype(np.float32).reshape(-1, 1, 2)
        guess = pred[inside].astype(np.float32).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(
            old.image,
            image,
            src,
            guess.copy(),
            winSize=(21, 21),
            maxLevel=3,
            criteria=crit,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        back, st2, _ = cv2.calcOpticalFlowPyrLK(
            image,
            old.image,
            nxt,
            src.copy(),
            winSize=(21, 21),
            maxLevel=3,
            criteria=crit,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        ok = (st.ravel() == 1) & (st2.ravel() == 1)
        ok &= np.linalg.norm((back - src).reshape(-1, 2), axis=1) < 1.0
        if ok.sum() < 6:
            return none
        return nxt.reshape(-1, 2)[ok].astype(float), np.flatnonzero(inside)[ok]

    # ---------------------------------------------------------------- relocalization
    def relocalize(self, image: NDArray[np.uint8], exclude_after: int | None = None) -> tuple[int | None, RelocResult]:
        """Pose of a lost camera (rectified left image) against the stored keyframes.

        Returns (keyframe id, result with ``cam_from_map`` = rectified cam_from_kf).
        """
        return relocalize_in_database(
            self.frame_features(image),
            self.detector.database,
            self.camera,
            RelocParams.from_config(self.config),
            exclude_after=exclude_after,
        )

    # ---------------------------------------------------------------- correction
    def correction_problem(self, keyframes: Sequence[Keyframe], closure: LoopClosure) -> dict[str, Any]:
        """Arguments of :func:`global_hybrid_ba` for the loop's window, as plain arrays.

        Plain arrays can be sent to a worker process. Keyframes from the loop's old keyframe to the
        current one, every loop's observations among them, the old keyframe held fixed.
        """
        lo, hi = closure.match_kf, closure.query_kf
        window = [k.without_image() for k in keyframes if lo <= int(k.id) <= hi]
        loops = [c.observations for c in self.closures if lo <= c.match_kf and c.query_kf <= hi]
        K = self.calibration.K_left
        return {
            "keyframes": window,
            "loops": loops,
            "fx_px": float(K[0, 0]),
            "fy_px": float(K[1, 1]),
            "cx_px": float(K[0, 2]),
            "cy_px": float(K[1, 2]),
            "baseline_m": self.calibration.baseline_m,
            "fixed_kf_id": lo,
        }

    def correct(self, keyframes: Sequence[Keyframe], closure: LoopClosure, max_iterations: int = 20) -> GlobalBAResult:
        """Global hybrid BA over the keyframes from the loop's old keyframe to the current one.

        The old keyframe is held fixed; with every loop's observations among them.
        """
        return global_hybrid_ba(**self.correction_problem(keyframes, closure), max_iterations=max_iterations)
