"""Relocalization: pose of a query image against a set of features with known 3-D points.

The query's descriptors are matched to the map's (ratio test, mutual), the matches go
through the P3P bank (:func:`loopmodel.loop.pnp.solve_pnp_bank`) and the robust refiner;
a result is accepted only with enough inliers and a sufficient inlier ratio.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import LoopConfig
from loopmodel.geometry.camera import CentralCamera
from loopmodel.loop.features import FeatureSet, match_descriptors
from loopmodel.loop.pnp import PnPResult, solve_pnp_bank
from loopmodel.loop.refine import PoseRefiner

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
_LOOP = LoopConfig.model_fields


@dataclass
class RelocParams:
    """Thresholds of relocalization and geometric verification.

    Defaults: those of :class:`loopmodel.config.LoopConfig`.
    """

    ratio: float = _LOOP["ratio"].default
    threshold_px: float = _LOOP["threshold_px"].default
    min_inliers: int = _LOOP["min_inliers"].default
    min_inlier_ratio: float = _LOOP["min_inlier_ratio"].default
    max_samples: int = _LOOP["max_samples"].default
    confidence: float = _LOOP["confidence"].default
    #: The inliers' smaller principal standard deviation in the image must reach this
    #: fraction of the image width (rejects poses supported by one small patch).
    min_inlier_spread_frac: float = _LOOP["min_inlier_spread_frac"].default
    seed: int = 0

    @classmethod
    def from_config(cls, cfg: LoopConfig) -> RelocParams:
        """The thresholds of the ``loop`` configuration section."""
        return cls(
            ratio=cfg.ratio,
            threshold_px=cfg.threshold_px,
            min_inliers=cfg.min_inliers,
            min_inlier_ratio=cfg.min_inlier_ratio,
            max_samples=cfg.max_samples,
            confidence=cfg.confidence,
            min_inlier_spread_frac=cfg.min_inlier_spread_frac,
        )


@dataclass
class RelocResult:
    """Outcome of one relocalization attempt.

    ``cam_from_map`` is the 4x4 pose of the query camera w.r.t. the frame the map points
    are expressed in (metres) when ``success``; ``reason`` says why it failed otherwise.
    ``matches`` (K, 2) are ``(i_query, i_map)`` pairs and ``inliers`` a mask over them.
    """

    success: bool
    reason: str
    cam_from_map: F64 | None = None
    matches: NDArray[np.int64] | None = None
    inliers: NDArray[np.bool_] | None = None
    pnp: PnPResult | None = None
    match_s: float = 0.0
    total_s: float = 0.0

    @property
    def n_inliers(self) -> int:
        """Number of inlier matches (0 on failure before the P3P bank)."""
        return int(self.inliers.sum()) if self.inliers is not None else 0

    @property
    def n_matches(self) -> int:
        """Number of descriptor matches fed to the P3P bank."""
        return int(self.matches.shape[0]) if self.matches is not None else 0


def localize(
    query: FeatureSet,
    landmarks: FeatureSet,
    camera: CentralCamera,
    params: RelocParams | None = None,
    refiner: PoseRefiner | None = None,
    matches: NDArray[np.int64] | None = None,
) -> RelocResult:
    """Pose of the camera that saw ``query`` w.r.t. the frame of ``landmarks.points_in_kf``.

    ``camera`` models the query image (pinhole or unified). Only landmarks with a 3-D
    position take part. Precomputed ``matches`` (query index, landmark index) skip the
    descriptor matching.
    """
    p = params if params is not None else RelocParams()
    t0 = time.perf_counter()
    has3d = np.flatnonzero(landmarks.has_3d)
    if matches is None:
        if has3d.size < 3 or len(query) < 3:
            return RelocResult(False, "too few features", total_s=time.perf_counter() - t0)
        pairs = match_descriptors(query, landmarks.subset(has3d), ratio=p.ratio)
        pairs[:, 1] = has3d[pairs[:, 1]]
    else:
        pairs = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
        pairs = pairs[landmarks.has_3d[pairs[:, 1]]]
    t_match = time.perf_counter() - t0
    if pairs.shape[0] < max(p.min_inliers, 3):
        return RelocResult(
            False,
            f"{pairs.shape[0]} matches < {p.min_inliers}",
            matches=pairs,
            match_s=t_match,
            total_s=time.perf_counter() - t0,
        )
    rays = camera.lift(query.keypoints_px[pairs[:, 0]])
    pts = landmarks.points_in_kf[pairs[:, 1]]
    thr = p.threshold_px / max(camera.px, camera.py)
    res = solve_pnp_bank(
        rays,
        pts,
        thr,
        rng=np.random.default_rng(p.seed),
        max_samples=sample_bound(p),
        confidence=p.confidence,
        min_inliers=3,
        refiner=refiner,
    )
    total = time.perf_counter() - t0
    if res is None:
        return RelocResult(False, "P3P bank found no pose", matches=pairs, match_s=t_match, total_s=total)
    n_in = res.n_inliers
    ratio = n_in / pairs.shape[0]
    if n_in < p.min_inliers or ratio < p.min_inlier_ratio:
        return RelocResult(
            False,
            f"{n_in} inliers of {pairs.shape[0]} matches (need {p.min_inliers} and ratio {p.min_inlier_ratio})",
            matches=pairs,
            inliers=res.inliers,
            pnp=res,
            match_s=t_match,
            total_s=total,
        )
    spread = inlier_spread_px(query.keypoints_px[pairs[res.inliers, 0]])
    width = 2.0 * camera.u0 + 1.0
    if spread < p.min_inlier_spread_frac * width:
        return RelocResult(
            False,
            f"inliers cover too small an image region (spread {spread:.1f} px)",
            matches=pairs,
            inliers=res.inliers,
            pnp=res,
            match_s=t_match,
            total_s=total,
        )
    return RelocResult(True, "ok", res.cam_from_world, pairs, res.inliers, res, t_match, total)


def sample_bound(p: RelocParams) -> int:
    """Minimal samples to draw, at least 64 and at most ``max_samples``.

    The number after which a pose with the minimum acceptable inlier ratio has been drawn with the
    given confidence (more would only serve poses that are rejected anyway), at least 64 and at most
    ``max_samples``.
    """
    w3 = min(max(p.min_inlier_ratio, 1e-3), 1.0) ** 3
    bound = np.log(1 - p.confidence) / np.log(1 - w3) if w3 < 1 else 1.0
    return int(min(p.max_samples, max(64, np.ceil(bound))))


def inlier_spread_px(uv_px: F64) -> float:
    """Smaller principal standard deviation (pixels) of a set of image points (N, 2)."""
    uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
    if uv.shape[0] < 3:
        return 0.0
    ev = np.linalg.eigvalsh(np.cov(uv.T))
    return float(np.sqrt(max(ev[0], 0.0)))
