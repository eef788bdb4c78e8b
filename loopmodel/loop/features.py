"""Appearance features for relocalization and loop closing, of any kind of :mod:`loopmodel.loop.descriptors`.

A :class:`FeatureSet` holds keypoints (pixels), descriptors and, for stereo keyframes, the
3-D position of each feature in the keyframe's left-camera frame (seed 004, eq. 5;
``NaN`` where a feature has no stereo match). The kinds (ORB, SIFT, SURF) are one module each
behind the registry :data:`~loopmodel.loop.descriptors.DESCRIPTORS`. SURF features also carry the
sign of the Laplacian, and only features of the same sign are matched.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.config import SurfConfig
from loopmodel.errors import InputError
from loopmodel.loop.descriptors import DESCRIPTORS, Described, descriptor
from loopmodel.types import StereoCalibration

F64 = NDArray[np.float64]

#: The descriptor kinds (the registry's names).
KINDS = tuple(DESCRIPTORS)


@dataclass
class FeatureSet:
    """Loop-closing features of one image: keypoints, descriptors, 3-D points, kind, ids, Laplacian signs.

    Keypoints ``keypoints_px`` (N, 2), descriptors (N, D: uint8 for ORB, float32 for SIFT/SURF),
    ``points_in_kf`` (N, 3) metres in the keyframe's left-camera frame (NaN rows where unknown),
    ``kind`` the descriptor name, ``ids`` (N,) landmark ids (-1: none), ``laplacian`` (N,) int8 sign
    of the Laplacian of SURF features (0: unknown / not SURF).
    """

    keypoints_px: F64
    descriptors: NDArray[Any]
    kind: str
    points_in_kf: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    laplacian: NDArray[np.int8] = field(default_factory=lambda: np.zeros(0, np.int8))

    def __post_init__(self) -> None:
        self.keypoints_px = np.asarray(self.keypoints_px, dtype=float).reshape(-1, 2)
        n = self.keypoints_px.shape[0]
        if self.points_in_kf.shape[0] != n:
            self.points_in_kf = np.full((n, 3), np.nan)
        if self.ids.shape[0] != n:
            self.ids = np.full(n, -1, np.int64)
        if self.laplacian.shape[0] != n:
            self.laplacian = np.zeros(n, np.int8)
        if self.descriptors.shape[0] != n:
            raise InputError("FeatureSet", f"{n} keypoints but {self.descriptors.shape[0]} descriptors")

    def __len__(self) -> int:
        return int(self.keypoints_px.shape[0])

    @property
    def binary(self) -> bool:
        """Whether the descriptors are binary strings (Hamming distance)."""
        return self.descriptors.dtype == np.uint8

    @property
    def has_3d(self) -> NDArray[np.bool_]:
        """Mask of the features with a 3-D position."""
        return np.all(np.isfinite(self.points_in_kf), axis=1)

    def subset(self, mask: NDArray[Any]) -> FeatureSet:
        """The features selected by a boolean mask or index array."""
        return FeatureSet(
            self.keypoints_px[mask],
            self.descriptors[mask],
            self.kind,
            self.points_in_kf[mask],
            self.ids[mask],
            self.laplacian[mask],
        )

    @staticmethod
    def concat(a: FeatureSet, b: FeatureSet) -> FeatureSet:
        """Both sets' features in one (same descriptor kind)."""
        return FeatureSet(
            np.concatenate([a.keypoints_px, b.keypoints_px]),
            np.concatenate([a.descriptors, b.descriptors]),
            a.kind,
            np.concatenate([a.points_in_kf, b.points_in_kf]),
            np.concatenate([a.ids, b.ids]),
            np.concatenate([a.laplacian, b.laplacian]),
        )


def make_extractor(kind: str = "orb", n_features: int = 2000, surf: SurfConfig | None = None) -> Any:
    """The extractor of ``kind`` (:data:`~loopmodel.loop.descriptors.DESCRIPTORS`); ``surf``: SURF settings."""
    return descriptor(kind).extractor(n_features, surf)


def _grey(image: NDArray[Any]) -> NDArray[np.uint8]:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        raise InputError("image", f"expected uint8 pixels, got {img.dtype}")
    return img


def _feature_set(kind: str, described: Described) -> FeatureSet:
    uv, desc, laplacian = described
    if laplacian is None:
        return FeatureSet(uv, desc, kind)
    return FeatureSet(uv, desc, kind, laplacian=laplacian)


def empty_features(kind: str) -> FeatureSet:
    """No features of descriptor ``kind`` (descriptors shaped (0, its length))."""
    d = descriptor(kind)
    return FeatureSet(np.zeros((0, 2)), d.empty(), d.name)


def detect_and_describe(
    image: NDArray[Any], kind: str = "orb", n_features: int = 2000, extractor: Any = None
) -> FeatureSet:
    """Detect keypoints and compute descriptors in one image (uint8 grey or BGR)."""
    d = descriptor(kind)
    ex = extractor if extractor is not None else d.extractor(n_features)
    return _feature_set(d.name, d.detect(ex, _grey(image)))


def describe_at(
    image: NDArray[Any], keypoints_px: F64, kind: str = "orb", size_px: float = 31.0, extractor: Any = None
) -> tuple[FeatureSet, NDArray[np.int64]]:
    """Descriptors at given pixel positions (e.g. a keyframe's tracked features).

    Returns the feature set and the indices (into ``keypoints_px``) that were kept (OpenCV drops
    keypoints too close to the border). For SURF, ``size_px`` is the side of the box filter the
    scale corresponds to (scale ``1.2 size_px / 9``); the orientation and the sign of the Laplacian
    are computed at that scale. ``extractor``: the detector to describe with (default: ``kind``'s
    with the default settings)."""
    d = descriptor(kind)
    ex = extractor if extractor is not None else d.extractor(2000)
    uv = np.asarray(keypoints_px, dtype=float).reshape(-1, 2)
    described, kept = d.describe_at(ex, _grey(image), uv, size_px)
    return _feature_set(d.name, described), kept


def match_descriptors(
    query: FeatureSet,
    train: FeatureSet,
    ratio: float = 0.8,
    mask: NDArray[np.uint8] | None = None,
    mutual: bool = True,
) -> NDArray[np.int64]:
    """Nearest-neighbour matches with Lowe's ratio test, optionally mutual.

    ``mask`` (len(query) x len(train), uint8) restricts the allowed pairs. When both sets
    carry Laplacian signs (SURF), only features of the same sign are compared (the ratio
    test then runs within each sign). Returns (K, 2) index pairs ``(i_query, i_train)``."""
    if np.all(query.laplacian != 0) and np.all(train.laplacian != 0) and len(query) and len(train):
        out = []
        for sign in (-1, 1):
            qi = np.flatnonzero(query.laplacian == sign)
            ti = np.flatnonzero(train.laplacian == sign)
            sub = None if mask is None else np.ascontiguousarray(mask[np.ix_(qi, ti)])
            pairs = _match(query.descriptors[qi], train.descriptors[ti], query.binary, ratio, sub, mutual)
            out.append(np.column_stack([qi[pairs[:, 0]], ti[pairs[:, 1]]]))
        res = np.concatenate(out).astype(np.int64)
        return res[np.argsort(res[:, 0], kind="stable")]
    return _match(query.descriptors, train.descriptors, query.binary, ratio, mask, mutual)


def _match(
    qd: NDArray[Any],
    td: NDArray[Any],
    binary: bool,
    ratio: float,
    mask: NDArray[np.uint8] | None,
    mutual: bool,
) -> NDArray[np.int64]:
    """Ratio-test (and mutual) matches between two descriptor arrays -> (K, 2) indices."""
    if qd.shape[0] < 2 or td.shape[0] < 2:
        return np.zeros((0, 2), np.int64)
    if binary and mask is None and qd.shape[1] % 8 == 0:
        return _match_binary(qd, td, ratio, mutual)
    norm = cv2.NORM_HAMMING if binary else cv2.NORM_L2
    matcher = cv2.BFMatcher(norm)
    knn = matcher.knnMatch(qd, td, k=2, mask=mask)
    pairs = []
    for m in knn:
        if len(m) == 0:
            continue
        if len(m) == 1 or m[0].distance < ratio * m[1].distance:
            pairs.append((m[0].queryIdx, m[0].trainIdx))
    out = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    if mutual and out.shape[0]:
        back = matcher.match(td, qd, mask=None if mask is None else mask.T.copy())
        best_q = np.full(td.shape[0], -1, np.int64)
        for bm in back:
            best_q[bm.queryIdx] = bm.trainIdx
        out = out[best_q[out[:, 1]] == out[:, 0]]
    return out


def _match_binary(qd: NDArray[np.uint8], td: NDArray[np.uint8], ratio: float, mutual: bool) -> NDArray[np.int64]:
    """:func:`_match` of unmasked binary descriptors from one pass over their Hamming distances.

    The pairs OpenCV's ``knnMatch(k=2)`` with the ratio test and, when ``mutual``, the reverse
    ``match`` give (ties to the first index, as there), without the second pass (kf15)."""
    from loopmodel.loop._vocabulary_kernels import nearest_both_ways

    q = np.ascontiguousarray(qd, dtype=np.uint8).view(np.uint64)
    t = np.ascontiguousarray(td, dtype=np.uint8).view(np.uint64)
    best, d_best, d_second, back = nearest_both_ways(q, t)
    rows = np.flatnonzero(d_best < ratio * d_second)
    if mutual:
        rows = rows[back[best[rows]] == rows]
    return np.column_stack([rows, best[rows]]).astype(np.int64)


def fundamental_from_poses(K1: F64, cam1_from_world: F64, K2: F64, cam2_from_world: F64) -> F64:
    """F with ``x2ᵀ F x1 = 0`` for pixels x1 (camera 1) and x2 (camera 2)."""
    T21 = cam2_from_world @ np.linalg.inv(cam1_from_world)
    R, t = T21[:3, :3], T21[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return np.linalg.inv(K2).T @ tx @ R @ np.linalg.inv(K1)


def epipolar_mask(uv1: F64, uv2: F64, F: F64, max_dist_px: float) -> NDArray[np.uint8]:
    """(N1, N2) uint8 mask of pairs within ``max_dist_px`` of each other's epipolar lines."""
    h1 = np.column_stack([uv1, np.ones(len(uv1))]).astype(np.float32)
    h2 = np.column_stack([uv2, np.ones(len(uv2))]).astype(np.float32)
    l2 = h1 @ F.T.astype(np.float32)  # lines in image 2 (N1, 3)
    l1 = h2 @ F.astype(np.float32)  # lines in image 1 (N2, 3)
    n2 = np.maximum(np.linalg.norm(l2[:, :2], axis=1), 1e-12)[:, None]
    n1 = np.maximum(np.linalg.norm(l1[:, :2], axis=1), 1e-12)[None, :]
    out = np.zeros((len(uv1), len(uv2)), np.uint8)
    for r in range(0, len(uv1), 1024):
        d2 = np.abs(l2[r : r + 1024] @ h2.T) / n2[r : r + 1024]
        d1 = np.abs(h1[r : r + 1024] @ l1.T) / n1
        out[r : r + 1024] = (d1 < max_dist_px) & (d2 < max_dist_px)
    return out


def triangulate(
    K1: F64,
    cam1_from_world: F64,
    K2: F64,
    cam2_from_world: F64,
    uv1: F64,
    uv2: F64,
    max_reproj_px: float = 2.0,
) -> tuple[F64, NDArray[np.bool_]]:
    """Linear triangulation of matched pixels (N, 2) seen by two calibrated cameras.

    Returns world points (N, 3, metres) and a mask of the valid ones (in front of both
    cameras, reprojection within ``max_reproj_px`` in both images)."""
    P1 = K1 @ cam1_from_world[:3]
    P2 = K2 @ cam2_from_world[:3]
    uv1 = np.asarray(uv1, dtype=float).reshape(-1, 2)
    uv2 = np.asarray(uv2, dtype=float).reshape(-1, 2)
    if uv1.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    Xh = cv2.triangulatePoints(P1, P2, uv1.T, uv2.T)
    w = Xh[3]
    ok = np.abs(w) > 1e-12
    X = (Xh[:3] / np.where(ok, w, 1.0)).T
    valid = ok.copy()
    for P, uv in ((P1, uv1), (P2, uv2)):
        x = np.column_stack([X, np.ones(len(X))]) @ P.T
        valid &= x[:, 2] > 0
        proj = x[:, :2] / np.where(np.abs(x[:, 2:]) > 1e-12, x[:, 2:], 1.0)
        valid &= np.linalg.norm(proj - uv, axis=1) < max_reproj_px
    return X, valid


def refine_rectified_match(
    left: NDArray[np.uint8],
    right: NDArray[np.uint8],
    uv_left: F64,
    u_right: F64,
    half_px: int = 5,
    search_px: int = 3,
) -> tuple[F64, NDArray[np.bool_]]:
    """Sub-pixel right-image column of rectified stereo matches.

    The left patch around each match is compared (sum of absolute differences) with right patches
    shifted along the row by up to ``search_px`` around ``u_right``, and a parabola through the best
    cost and its neighbours gives the sub-pixel minimum. Returns the refined columns and a mask of
    the matches whose minimum lies inside the search window.
    """
    h, w = left.shape
    L = left.astype(np.float32)
    Rt = right.astype(np.float32)
    out = np.asarray(u_right, dtype=float).copy()
    good = np.zeros(out.shape[0], bool)
    offs = np.arange(-search_px, search_px + 1)
    for k in range(out.shape[0]):
        ul, vl = int(round(uv_left[k, 0])), int(round(uv_left[k, 1]))
        ur0 = int(round(out[k] + (ul - uv_left[k, 0])))
        if (
            vl - half_px < 0
            or vl + half_px >= h
            or ul - half_px < 0
            or ul + half_px >= w
            or ur0 - half_px - search_px < 0
            or ur0 + half_px + search_px >= w
        ):
            continue
        patch = L[vl - half_px : vl + half_px + 1, ul - half_px : ul + half_px + 1]
        patch = patch - patch.mean()
        strip = Rt[
            vl - half_px : vl + half_px + 1,
            ur0 - half_px - search_px : ur0 + half_px + search_px + 1,
        ]
        costs = np.empty(offs.size)
        for j in range(offs.size):
            cand = strip[:, j : j + 2 * half_px + 1]
            costs[j] = np.abs(patch - (cand - cand.mean())).sum()
        j = int(np.argmin(costs))
        if j == 0 or j == offs.size - 1:
            continue
        c0, c1, c2 = costs[j - 1], costs[j], costs[j + 1]
        den = c0 - 2 * c1 + c2
        delta = 0.5 * (c0 - c2) / den if den > 0 else 0.0
        if abs(delta) > 1.0:
            continue
        # the refined right column for the (unrounded) left keypoint
        out[k] = ur0 + offs[j] + delta - (ul - uv_left[k, 0])
        good[k] = True
    return out, good


def stereo_keyframe_features(
    left: NDArray[Any],
    right: NDArray[Any],
    calib: StereoCalibration,
    kind: str = "orb",
    n_features: int = 2000,
    ratio: float = 0.8,
    max_epipolar_px: float = 1.5,
    max_reproj_px: float = 1.5,
    min_depth_m: float = 0.05,
    max_depth_m: float = 50.0,
) -> FeatureSet:
    """Features of a stereo keyframe.

    All left-image features, with 3-D positions (left camera frame, metres) for those matched in the
    right image along the epipolar lines of the calibration. Pixel coordinates are undistorted when
    the calibration has distortion.
    """
    ex = make_extractor(kind, n_features)
    fl = detect_and_describe(left, kind, n_features, ex)
    fr = detect_and_describe(right, kind, n_features, ex)
    if len(fl) == 0:
        return fl
    uvl, uvr = fl.keypoints_px, fr.keypoints_px
    if np.any(calib.dist_left != 0):
        uvl = cv2.undistortPoints(uvl.reshape(-1, 1, 2), calib.K_left, calib.dist_left, P=calib.K_left).reshape(-1, 2)
    if len(fr) and np.any(calib.dist_right != 0):
        uvr = cv2.undistortPoints(uvr.reshape(-1, 1, 2), calib.K_right, calib.dist_right, P=calib.K_right).reshape(
            -1, 2
        )
    if len(fr) < 2:
        return FeatureSet(uvl, fl.descriptors, fl.kind, laplacian=fl.laplacian)
    F = fundamental_from_poses(calib.K_left, np.eye(4), calib.K_right, calib.right_from_left)
    mask = epipolar_mask(uvl, uvr, F, max_epipolar_px)
    pairs = match_descriptors(fl, fr, ratio=ratio, mask=mask)
    pts = np.full((len(fl), 3), np.nan)
    if pairs.shape[0]:
        ul, ur = uvl[pairs[:, 0]], uvr[pairs[:, 1]].copy()
        if calib.rectified and not np.any(calib.dist_left) and not np.any(calib.dist_right):
            ur[:, 0], good = refine_rectified_match(_grey(left), _grey(right), ul, ur[:, 0])
            ur[:, 1] = ul[:, 1]
            pairs, ul, ur = pairs[good], ul[good], ur[good]
        X, ok = triangulate(
            calib.K_left,
            np.eye(4),
            calib.K_right,
            calib.right_from_left,
            ul,
            ur,
            max_reproj_px,
        )
        ok &= (X[:, 2] > min_depth_m) & (X[:, 2] < max_depth_m)
        pts[pairs[ok, 0]] = X[ok]
    return FeatureSet(uvl, fl.descriptors, fl.kind, pts, laplacian=fl.laplacian)
