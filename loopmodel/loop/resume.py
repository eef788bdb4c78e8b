"""Resuming an old feature set after a verified revisit (seed 004, section 5).

When relocalization or a verified loop gives the current camera's pose in an old
keyframe's frame, the old keyframe's stereo features (3-D points in its left-camera
frame) are predicted into the current image; each feature's template is warped by the
affine map the predicted pose implies (:func:`loopmodel.frontend.affine_klt.predicted_affine`),
searched by normalised cross-correlation in an enlarged region around the prediction (the
pose after relocalization is off by millimetres to centimetres, i.e. several pixels), and
refined with the affine KLT of :func:`loopmodel.frontend.affine_klt.refine_affine`.
The features found can be tracked on as the old set; their ids are the old landmark ids.

Pixels: rectified images of the keyframe and of the current frame (same camera);
``cur_from_kf`` maps points of the old keyframe's camera frame into the current camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.frontend.affine_klt import predicted_affine, refine_affine
from loopmodel.geometry.camera import CentralCamera

F64 = NDArray[np.float64]


@dataclass
class Retracked:
    """Old features found again: ids, positions, predicted positions and NCC.

    ``ids`` (K,) landmark ids, ``uv_px`` (K, 2) positions in the current image, ``predicted_px``
    (K, 2) where the pose put them, ``ncc`` (K,).
    """

    ids: NDArray[np.int64]
    uv_px: F64
    predicted_px: F64
    ncc: F64

    def __len__(self) -> int:
        return int(self.ids.shape[0])


def retrack_keyframe_features(
    camera: CentralCamera,
    kf_image: NDArray[np.uint8],
    kf_uv_px: F64,
    kf_points: F64,
    kf_ids: NDArray[np.int64],
    cur_image: NDArray[np.uint8],
    cur_from_kf: F64,
    search_px: int = 12,
    half_window_px: int = 7,
    min_ncc: float = 0.85,
) -> Retracked:
    """Find the old keyframe's features in the current image, given the predicted pose ``cur_from_kf``.

    Features: pixels ``kf_uv_px`` (N, 2), points ``kf_points`` (N, 3) metres in its camera frame,
    ids (N,); ``cur_from_kf`` is 4x4. Each warped template is searched within ``search_px`` of its
    prediction (NCC), then refined by the affine KLT (converged, NCC >= ``min_ncc``).
    """
    uv0 = np.asarray(kf_uv_px, float).reshape(-1, 2)
    X = np.asarray(kf_points, float).reshape(-1, 3)
    ids = np.asarray(kf_ids, np.int64).reshape(-1)
    Xc = X @ cur_from_kf[:3, :3].T + cur_from_kf[:3, 3]
    h, w = cur_image.shape[:2]
    r = half_window_px
    margin = r + search_px + 2
    vis = camera.in_front(Xc) & np.isfinite(X).all(axis=1)
    pred = np.full((uv0.shape[0], 2), np.nan)
    pred[vis] = camera.project(Xc[vis])
    hk, wk = kf_image.shape[:2]
    ok = (
        vis
        & (pred[:, 0] >= margin)
        & (pred[:, 0] <= w - 1 - margin)
        & (pred[:, 1] >= margin)
        & (pred[:, 1] <= h - 1 - margin)
        & (uv0[:, 0] >= 2 * r)
        & (uv0[:, 0] <= wk - 1 - 2 * r)
        & (uv0[:, 1] >= 2 * r)
        & (uv0[:, 1] <= hk - 1 - 2 * r)
    )
    idx = np.flatnonzero(ok)
    empty = Retracked(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))
    if idx.size == 0:
        return empty
    A = predicted_affine(camera, X[idx], cur_from_kf)  # d uv_cur / d uv_kf
    cur = cur_image.astype(np.float32)
    tpls, textured = _warped_templates(kf_image.astype(np.float32), uv0[idx], A, r)
    coarse = np.full((idx.size, 2), np.nan)
    # issue 33: only the search is left per feature (the templates above are made in one pass: this
    # loop runs on the loop workers' threads, and its Python holds the interpreter lock the tracker needs)
    centre = np.rint(pred[idx]).astype(np.int64)  # (Python's round and NumPy's rint both round half to even)
    for n in np.flatnonzero(textured).tolist():
        cx, cy = int(centre[n, 0]), int(centre[n, 1])
        win = cur[cy - r - search_px : cy + r + search_px + 1, cx - r - search_px : cx + r + search_px + 1]
        _, best, _, loc = cv2.minMaxLoc(cv2.matchTemplate(win, tpls[n], cv2.TM_CCOEFF_NORMED))
        if best >= min_ncc - 0.1:
            coarse[n] = (cx - search_px + loc[0], cy - search_px + loc[1])
    have = np.isfinite(coarse).all(axis=1)
    if not np.any(have):
        return empty
    sel = idx[have]
    m = refine_affine(
        kf_image,
        cur_image,
        uv0[sel],
        coarse[have],
        affine_guess=A[have],
        half_window_px=half_window_px,
        min_ncc=min_ncc,
        max_shift_px=2.0,
    )
    good = m.ok
    return Retracked(ids[sel[good]], m.uv_px[good], pred[sel[good]], m.ncc[good])


def _warped_templates(
    ref: NDArray[np.float32], uv: F64, A: F64, r: int
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Each feature's (2r+1)-pixel template in current-image geometry, and whether it has texture.

    Template n samples the keyframe image ``ref`` at ``uv[n] + A[n]^-1 s`` for the window's offsets
    ``s`` (bilinear, replicated border); ``A`` (N, 2, 2) maps keyframe to current pixels. Textured:
    ``A[n]`` invertible and a standard deviation of at least 1 grey level. One remap for all of them
    (the per-feature remaps gave the same pixels: remap is pointwise).
    """
    n, size = uv.shape[0], 2 * r + 1
    s = np.arange(-r, r + 1, dtype=float)
    sx, sy = np.meshgrid(s, s)
    try:
        Ainv = np.linalg.inv(A)
        invertible = np.ones(n, dtype=bool)
    except np.linalg.LinAlgError:  # a singular one among them: each on its own
        Ainv = np.zeros((n, 2, 2))
        invertible = np.zeros(n, dtype=bool)
        for k in range(n):
            try:
                Ainv[k] = np.linalg.inv(A[k])
                invertible[k] = True
            except np.linalg.LinAlgError:
                pass
    a = Ainv[:, :, :, None, None]
    mx = (uv[:, 0, None, None] + a[:, 0, 0] * sx + a[:, 0, 1] * sy).astype(np.float32)
    my = (uv[:, 1, None, None] + a[:, 1, 0] * sx + a[:, 1, 1] * sy).astype(np.float32)
    chunk = max(1, 30000 // size)  # (OpenCV's remap takes maps below 32767 rows)
    tpls = np.concatenate([
        cv2.remap(
            ref, mx[k : k + chunk].reshape(-1, size), my[k : k + chunk].reshape(-1, size), cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ).reshape(-1, size, size)
        for k in range(0, n, chunk)
    ])
    textured = invertible & (tpls.reshape(n, -1).std(axis=1) >= 1.0)
    return tpls, textured
