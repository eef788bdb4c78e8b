"""Drift-free re-measurement of tracked features against their keyframe's template.

Frame-to-frame KLT follows a feature through many small steps; under the viewpoint change
of a keyframe interval (tens of degrees around an object) the tracked position slides off
the keyframe's pixel (seed 004's tracking sets: up to ~0.3 px after 30 frames on the
simulator's orbit), and those end-of-track positions are what links consecutive keyframes.
:func:`refine_affine` measures each feature again directly against the keyframe's patch
with an affine warp and an affine brightness model (Gauss-Newton, all features at once),
started from the tracked position and from the warp that the relative pose predicts for a
small plane facing the keyframe camera through the feature's stereo point.

Pixels are those of the images given (rectified); points in the reference camera frame
(metres); ``cur_from_ref`` maps reference-camera points into the current camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.camera import CentralCamera

F64 = NDArray[np.float64]



@dataclass
class AffineMatch:
    """Re-measured positions ``uv_px`` (N, 2) in the current image, ``ok`` flags and ``ncc`` per feature.

    ``ok`` where the match converged, stayed within the shift limit and correlates (NCC) above the
    threshold.
    """

    uv_px: F64
    ok: NDArray[np.bool_]
    ncc: F64


def predicted_affine(
    camera: CentralCamera, points_ref: F64, cur_from_ref: F64
) -> F64:
    """(N, 2, 2) pixel Jacobians d uv_cur / d uv_ref of the plane through each reference point.

    The plane faces the reference camera (normal along the viewing ray) and is moved by
    ``cur_from_ref``; identity where the point is behind either camera.
    """
    X = np.asarray(points_ref, dtype=float).reshape(-1, 3)
    n = X.shape[0]
    out = np.tile(np.eye(2), (n, 1, 1))
    if n == 0:
        return out
    R, t = cur_from_ref[:3, :3], cur_from_ref[:3, 3]
    Xc = X @ R.T + t
    ok = camera.in_front(X) & camera.in_front(Xc) & np.isfinite(X).all(axis=1)
    if not np.any(ok):
        return out
    ray = X[ok] / np.linalg.norm(X[ok], axis=1)[:, None]
    # two tangent directions of the plane perpendicular to the viewing ray
    helper = np.where(np.abs(ray[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(ray, helper)
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(ray, e1)
    E = np.stack([e1, e2], axis=2)  # (m, 3, 2)
    J_ref = camera.project_jacobian(X[ok]) @ E  # (m, 2, 2)
    J_cur = camera.project_jacobian(Xc[ok]) @ (R @ E)
    det = np.linalg.det(J_ref)
    good = np.abs(det) > 1e-9
    M = np.tile(np.eye(2), (J_ref.shape[0], 1, 1))
    M[good] = J_cur[good] @ np.linalg.inv(J_ref[good])
    out[ok] = M
    return out


def _sample(img: NDArray[np.float32], x: F64, y: F64) -> F64:
    return cv2.remap(
        img, x.astype(np.float32), y.astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    ).astype(np.float64)


def image_gradients(img: NDArray) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Horizontal and vertical intensity gradients (grey levels per pixel; 3x3 Sobel / 8) of ``img``.

    An 8-bit image is filtered as it is (the same values as its float32 copy: integer sums, scaled
    last; checked on the KITTI clip's images), without the copy.
    """
    cur = img if img.dtype == np.uint8 else np.asarray(img, dtype=np.float32)
    return (
        cv2.Sobel(cur, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8),
        cv2.Sobel(cur, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8),
    )


def refine_affine(
    img_ref: NDArray[np.uint8],
    img_cur: NDArray[np.uint8],
    uv_ref_px: F64,
    uv_guess_px: F64,
    affine_guess: F64 | None = None,
    half_window_px: int = 7,
    iterations: int = 10,
    min_ncc: float = 0.8,
    max_shift_px: float = 2.0,
    cur_gradients: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None,
) -> AffineMatch:
    """Positions in ``img_cur`` of the features at ``uv_ref_px`` (N, 2) of ``img_ref``.

    Each feature's (2 h + 1)^2 patch of the reference image is matched in the current
    image by Gauss-Newton over ``uv + A s`` (s: offset in the patch, A: 2 x 2) and a gain
    and offset of brightness, starting at ``uv_guess_px`` and ``affine_guess`` (N, 2, 2;
    identity when None). ``ok`` is False where the solution moved more than
    ``max_shift_px`` from the guess, left the image, or correlates below ``min_ncc``.
    ``cur_gradients``: :func:`image_gradients` of ``img_cur`` when already computed (several
    calls on one image).
    """
    uv_ref = np.asarray(uv_ref_px, dtype=float).reshape(-1, 2)
    c = np.asarray(uv_guess_px, dtype=float).reshape(-1, 2).copy()
    n = uv_ref.shape[0]
    if n == 0:
        return AffineMatch(np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0))
    guess = c.copy()
    A = np.tile(np.eye(2), (n, 1, 1)) if affine_guess is None else np.array(affine_guess, dtype=float, order="C")
    gx, gy = image_gradients(img_cur) if cur_gradients is None else cur_gradients
    # per feature, compiled (issue 33's cost: the numpy form took 15 ms a call on the KITTI clip)
    from loopmodel.frontend._affine_kernels import refine_features  # numba: imported when first needed

    ncc, finite = refine_features(np.asarray(img_ref), np.asarray(img_cur), gx, gy, np.ascontiguousarray(uv_ref),
                                  c, A, half_window_px, iterations, max_shift_px)
    h, w = np.shape(img_cur)[:2]
    inside = (c[:, 0] >= 0) & (c[:, 0] <= w - 1) & (c[:, 1] >= 0) & (c[:, 1] <= h - 1)
    ok = finite & inside & (ncc >= min_ncc) & (np.linalg.norm(c - guess, axis=1) <= max_shift_px)
    return AffineMatch(c, ok, ncc)


def warm_up() -> None:
    """Load (or compile) :func:`refine_affine`'s kernel now (numba's cache: 0.3-0.8 s of CPU), not in a frame."""
    from loopmodel.frontend._affine_kernels import warm_up as load

    load()
