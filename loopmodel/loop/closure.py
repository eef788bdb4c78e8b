"""Loop detection with verification: place recognition, then geometry, then acceptance.

:class:`LoopDetector` takes keyframes one by one. For each it queries the
:class:`~loopmodel.loop.database.KeyframeDatabase`; temporally consistent candidate islands
are verified geometrically, best member first:

* stereo keyframes (features with 3-D positions) and a camera: relocalization of the
  query against the candidate's 3-D features with the P3P bank, and — when the query has
  3-D features too — the reverse relocalization, whose pose must agree with the forward
  one (``max_cycle_*``);
* monocular images: a fundamental matrix by RANSAC with enough inliers.

A verified revisit becomes an accepted :class:`LoopEvent` (with the relative pose for
stereo keyframes); a candidate that fails is logged and kept in ``rejected``, never used.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.config import LoopConfig
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose, so3_log
from loopmodel.loop.database import KeyframeDatabase, PlaceCandidate, PlaceParams
from loopmodel.loop.features import FeatureSet, match_descriptors
from loopmodel.loop.refine import PoseRefiner
from loopmodel.loop.reloc import RelocParams, RelocResult, inlier_spread_px, localize
from loopmodel.loop.vocabulary import Vocabulary

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


_LOOP = LoopConfig.model_fields


@dataclass
class LoopParams:
    """Loop detection and verification parameters (defaults: those of :class:`loopmodel.config.LoopConfig`)."""

    place: PlaceParams = field(default_factory=PlaceParams)
    reloc: RelocParams = field(default_factory=RelocParams)
    ratio: float = _LOOP["ratio"].default
    epipolar_threshold_px: float = _LOOP["epipolar_threshold_px"].default
    min_epipolar_inliers: int = _LOOP["min_epipolar_inliers"].default
    min_epipolar_inlier_ratio: float = _LOOP["min_epipolar_inlier_ratio"].default
    min_epipolar_spread_frac: float = _LOOP["min_epipolar_spread_frac"].default
    max_cycle_rot_deg: float = _LOOP["max_cycle_rot_deg"].default
    max_cycle_trans_m: float = _LOOP["max_cycle_trans_m"].default
    max_members_verified: int = _LOOP["max_members_verified"].default


@dataclass
class LoopEvent:
    """A verified (``accepted``) or rejected loop candidate.

    ``match_from_query`` (4x4, metres) maps points from the query keyframe's left-camera
    frame to the matched keyframe's, when the verification was metric."""

    query_id: int
    match_id: int
    accepted: bool
    reason: str
    score: float
    consistent: int
    n_matches: int = 0
    n_inliers: int = 0
    match_from_query: F64 | None = None
    matches: NDArray[np.int64] | None = None
    inliers: NDArray[np.bool_] | None = None
    verify_s: float = 0.0


def verify_epipolar(
    query: FeatureSet, candidate: FeatureSet, params: LoopParams, image_width_px: float
) -> tuple[bool, str, NDArray[np.int64], NDArray[np.bool_]]:
    """Geometric check of two monocular views: fundamental matrix by RANSAC (pixels)."""
    pairs = match_descriptors(query, candidate, ratio=params.ratio)
    none = np.zeros(pairs.shape[0], bool)
    if pairs.shape[0] < max(params.min_epipolar_inliers, 8):
        return False, f"{pairs.shape[0]} matches", pairs, none
    F, mask = cv2.findFundamentalMat(
        query.keypoints_px[pairs[:, 0]],
        candidate.keypoints_px[pairs[:, 1]],
        cv2.FM_RANSAC,
        params.epipolar_threshold_px,
        0.999,
        2000,
    )
    if F is None or mask is None:
        return False, "no fundamental matrix", pairs, none
    inl = mask.ravel().astype(bool)
    n = int(inl.sum())
    ratio = n / pairs.shape[0]
    if n < params.min_epipolar_inliers or ratio < params.min_epipolar_inlier_ratio:
        return False, f"{n} epipolar inliers of {pairs.shape[0]}", pairs, inl
    spread = min(
        inlier_spread_px(query.keypoints_px[pairs[inl, 0]]),
        inlier_spread_px(candidate.keypoints_px[pairs[inl, 1]]),
    )
    if spread < params.min_epipolar_spread_frac * image_width_px:
        return False, f"epipolar inliers clustered (spread {spread:.1f} px)", pairs, inl
    return True, "ok", pairs, inl


def verify_metric(
    query: FeatureSet,
    candidate: FeatureSet,
    camera: CentralCamera,
    params: LoopParams,
    refiner: PoseRefiner | None = None,
) -> tuple[bool, str, RelocResult, F64 | None]:
    """Geometric check of two stereo keyframes.

    The query camera relocalized against the candidate's 3-D features, and (when the query has 3-D
    features) the reverse, which must agree. Returns (ok, reason, forward result,
    ``candidate_from_query``).
    """
    fwd = localize(query, candidate, camera, params.reloc, refiner)
    if not fwd.success or fwd.cam_from_map is None:
        return False, f"relocalization failed: {fwd.reason}", fwd, None
    cand_from_query = invert_pose(fwd.cam_from_map)
    if query.has_3d.sum() >= params.reloc.min_inliers:
        back = localize(candidate, query, camera, params.reloc, refiner)
        if not back.success or back.cam_from_map is None:
            return False, f"reverse relocalization failed: {back.reason}", fwd, None
        cycle = back.cam_from_map @ fwd.cam_from_map  # query <- cand <- query
        rot = float(np.degrees(np.linalg.norm(so3_log(cycle[:3, :3]))))
        trans = float(np.linalg.norm(cycle[:3, 3]))
        if rot > params.max_cycle_rot_deg or trans > params.max_cycle_trans_m:
            return (
                False,
                f"forward/reverse poses disagree ({rot:.2f} deg, {trans:.3f} m)",
                fwd,
                None,
            )
    return True, "ok", fwd, cand_from_query


class LoopDetector:
    """Place recognition plus verification over a growing keyframe database."""

    def __init__(
        self,
        camera: CentralCamera | None = None,
        params: LoopParams | None = None,
        vocabulary: Vocabulary | None = None,
        refiner: PoseRefiner | None = None,
        image_width_px: float | None = None,
    ) -> None:
        self.params = params if params is not None else LoopParams()
        self.camera = camera
        self.refiner = refiner
        self.database = KeyframeDatabase(vocabulary, self.params.place)
        self.accepted: list[LoopEvent] = []
        self.rejected: list[LoopEvent] = []
        if image_width_px is None:
            image_width_px = 2.0 * camera.u0 + 1.0 if camera is not None else 640.0
        self.image_width_px = image_width_px
        self.query_s: list[float] = []
        #: candidate keyframes not verified because they were temporal neighbours
        self.neighbours_skipped = 0

    def process(
        self,
        kf_id: int,
        features: FeatureSet,
        add: bool = True,
        query: bool = True,
        neighbours: set[int] | None = None,
    ) -> LoopEvent | None:
        """Query with a new keyframe, verify consistent candidates, then store it.

        ``neighbours``: keyframes co-visible with the query's local map (temporal
        neighbours), never verified; ``query`` False only stores the keyframe. Returns the
        accepted loop event (or ``None``)."""
        t0 = time.perf_counter()
        candidates = self.database.query(kf_id, features) if query else []
        event = None
        for cand in candidates:
            if not cand.accepted:
                continue
            if neighbours:
                kept = [m for m in cand.members if m not in neighbours]
                self.neighbours_skipped += len(cand.members) - len(kept)
                if not kept:
                    continue
                if cand.best_id not in kept:
                    cand.best_id = kept[0]
                cand.members = kept
            event = self._verify(kf_id, features, cand)
            if event is not None:
                break
        if add:
            self.database.add(kf_id, features)
        self.query_s.append(time.perf_counter() - t0)
        return event

    def _verify(self, kf_id: int, features: FeatureSet, cand: PlaceCandidate) -> LoopEvent | None:
        p = self.params
        members = sorted(cand.members, key=lambda m: -1 if m == cand.best_id else abs(m - cand.best_id))
        for mid in members[: p.max_members_verified]:
            t0 = time.perf_counter()
            other = self.database.features(mid)
            metric = self.camera is not None and other.has_3d.sum() >= p.reloc.min_inliers
            if metric:
                assert self.camera is not None
                ok, reason, res, cfq = verify_metric(features, other, self.camera, p, self.refiner)
                ev = LoopEvent(
                    kf_id,
                    mid,
                    ok,
                    reason,
                    cand.score,
                    cand.consistent,
                    res.n_matches,
                    res.n_inliers,
                    cfq,
                    res.matches,
                    res.inliers,
                    time.perf_counter() - t0,
                )
            else:
                ok, reason, pairs, inl = verify_epipolar(features, other, p, self.image_width_px)
                ev = LoopEvent(
                    kf_id,
                    mid,
                    ok,
                    reason,
                    cand.score,
                    cand.consistent,
                    int(pairs.shape[0]),
                    int(inl.sum()),
                    None,
                    pairs,
                    inl,
                    time.perf_counter() - t0,
                )
            if ok:
                self.accepted.append(ev)
                logger.info("loop %d -> %d accepted (%d inliers)", kf_id, mid, ev.n_inliers)
                return ev
            self.rejected.append(ev)
            logger.info("loop candidate %d -> %d rejected: %s", kf_id, mid, reason)
        return None


def relocalize_in_database(
    query: FeatureSet,
    database: KeyframeDatabase,
    camera: CentralCamera,
    params: RelocParams | None = None,
    max_candidates: int = 3,
    exclude_after: int | None = None,
    refiner: PoseRefiner | None = None,
) -> tuple[int | None, RelocResult]:
    """Relocalize a lost camera.

    The ``max_candidates`` best-scoring stored keyframes (ids up to ``exclude_after`` when given)
    are tried with the P3P bank against their 3-D features; the first success wins. Returns
    (keyframe id, result) where ``result.cam_from_map`` is ``cam_from_kf``; (None, last failure)
    when none succeeds.
    """
    p = params if params is not None else RelocParams()
    ids, scores = database.score_all(query, max_id=exclude_after)
    last = RelocResult(False, "no keyframe in the database")
    for k in np.argsort(-scores)[:max_candidates]:
        kf_id = int(ids[k])
        res = localize(query, database.features(kf_id), camera, p, refiner)
        if res.success:
            return kf_id, res
        last = res
    return None, last


def params_from_config(cfg: LoopConfig) -> LoopParams:
    """Loop parameters from the ``loop`` configuration section."""
    reloc = RelocParams.from_config(cfg)
    place = PlaceParams.from_config(cfg)
    return LoopParams(
        place=place,
        reloc=reloc,
        ratio=cfg.ratio,
        epipolar_threshold_px=cfg.epipolar_threshold_px,
        min_epipolar_inliers=cfg.min_epipolar_inliers,
        min_epipolar_inlier_ratio=cfg.min_epipolar_inlier_ratio,
        min_epipolar_spread_frac=cfg.min_epipolar_spread_frac,
        max_cycle_rot_deg=cfg.max_cycle_rot_deg,
        max_cycle_trans_m=cfg.max_cycle_trans_m,
        max_members_verified=cfg.max_members_verified,
    )


def detector_from_config(
    cfg: LoopConfig,
    camera: CentralCamera | None,
    image_width_px: float | None = None,
    vocabulary: Vocabulary | None = None,
) -> LoopDetector:
    """A :class:`LoopDetector` set up from the ``loop`` configuration section.

    ``vocabulary``: the caller's (:func:`loopmodel.io.vocabulary_file.loop_vocabulary` reads the
    configured or shipped one); None: one trained on the fly from the keyframes.
    """
    return LoopDetector(camera, params_from_config(cfg), vocabulary, image_width_px=image_width_px)
