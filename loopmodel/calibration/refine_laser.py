"""Laser-stereo consistency: the stereo scale (baseline) and the light plane's offset together (issue 31).

A stripe point's depth comes from the light plane (``n . p + d = 0``): scaling ``d`` scales every
stripe point about the camera centre. A stereo landmark's depth scales with the baseline. Where a
stripe falls on a surface the landmarks also see, the two must agree: at each (subsampled) stripe
pixel of a keyframe, the inverse depth of the surface is interpolated from the keyframe's landmarks
within ``radius_px`` (inverse depth is affine in normalised image coordinates on a plane), and
``log(z_stripe / z_stereo)`` is the discrepancy. Per keyframe the median of them, over keyframes
the median ``m`` with its robust standard error.

Unknowns ``x_b = log(b' / b)`` and ``x_d = log(d' / d)`` (relative corrections of the baseline and
of the plane offset), Gaussian priors from their recorded standard deviations, and the one
observation ``x_b - x_d = m``: the data fix the ratio of the two scales, the priors share it out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import invert_pose
from loopmodel.types import StereoCalibration, StripeProfile

F64 = NDArray[np.float64]


@dataclass
class LaserStereoScale:
    """Relative corrections of the baseline (``log_baseline``) and the plane offset (``log_plane_offset``).

    Their posterior standard deviations and correlation, the measured discrepancy ``m`` (log, stripe
    over stereo depth) with its standard error, and the pairs and keyframes behind it.
    """

    log_baseline: float
    log_plane_offset: float
    sigma_log_baseline: float
    sigma_log_plane_offset: float
    correlation: float
    discrepancy_log: float
    discrepancy_sigma: float
    pairs: int
    keyframes: int

    @property
    def baseline_factor(self) -> float:
        """Refined over current baseline."""
        return float(np.exp(self.log_baseline))

    @property
    def plane_offset_factor(self) -> float:
        """Refined over current plane offset."""
        return float(np.exp(self.log_plane_offset))


def _normalised(p_cam: F64) -> F64:
    return p_cam[:, :2] / p_cam[:, 2:3]


def keyframe_discrepancies(
    stripe_in_cam: F64,
    landmarks_in_cam: F64,
    fx_px: float,
    radius_px: float = 25.0,
    every: int = 4,
    min_landmarks: int = 5,
    max_fit_rel: float = 0.003,
) -> F64:
    """``log(z_stripe / z_stereo)`` at the stripe points of one keyframe (camera frame, metres).

    At every ``every``-th stripe point, the landmarks within ``radius_px`` in the (normalised,
    times ``fx_px``) image give an affine fit of inverse depth; a fit with fewer than
    ``min_landmarks`` or a relative RMS above ``max_fit_rel`` (not a plane) gives nothing.
    """
    S = np.asarray(stripe_in_cam, float).reshape(-1, 3)[::every]
    L = np.asarray(landmarks_in_cam, float).reshape(-1, 3)
    S = S[S[:, 2] > 1e-3]
    L = L[L[:, 2] > 1e-3]
    if S.shape[0] == 0 or L.shape[0] < min_landmarks:
        return np.zeros(0)
    s_xy, l_xy = _normalised(S), _normalised(L)
    l_inv = 1.0 / L[:, 2]
    r = radius_px / fx_px
    d2 = np.sum((s_xy[:, None, :] - l_xy[None, :, :]) ** 2, axis=2)
    out = []
    for i in range(S.shape[0]):
        near = np.flatnonzero(d2[i] < r * r)
        if near.size < min_landmarks:
            continue
        A = np.column_stack([l_xy[near] - s_xy[i], np.ones(near.size)])
        coef, *_ = np.linalg.lstsq(A, l_inv[near], rcond=None)
        fit = A @ coef
        if np.sqrt(np.mean((fit - l_inv[near]) ** 2)) > max_fit_rel * abs(coef[2]) or coef[2] <= 0:
            continue
        out.append(np.log(S[i, 2] * coef[2]))  # z_stripe / z_stereo = z_stripe * (1 / z_stereo)
    return np.asarray(out, float)


def laser_stereo_scale(
    stripes: list[StripeProfile],
    keyframe_stamps_ns: dict[int, int],
    world_from_kf: dict[int, F64],
    keyframe_landmarks: dict[int, NDArray[np.int64]],
    landmark_ids: NDArray[np.int64],
    landmarks_in_world: F64,
    calibration: StereoCalibration,
    sigma_log_baseline: float,
    sigma_log_plane_offset: float,
    radius_px: float = 25.0,
) -> LaserStereoScale | None:
    """The joint estimate of the module docstring; None when no keyframe has a stripe on seen surfaces.

    ``keyframe_landmarks``: the landmark ids each keyframe observed; stripes are matched to keyframes
    by exact timestamp.
    """
    by_stamp = {s.timestamp_ns: s for s in stripes}
    pos = {int(i): k for k, i in enumerate(np.asarray(landmark_ids).tolist())}
    pts = np.asarray(landmarks_in_world, float).reshape(-1, 3)
    per_kf: list[float] = []
    pairs = 0
    for kf, stamp in keyframe_stamps_ns.items():
        stripe = by_stamp.get(stamp)
        if stripe is None or kf not in world_from_kf or stripe.points_in_cam.shape[0] < 3:
            continue
        idx = [pos[i] for i in np.asarray(keyframe_landmarks.get(kf, []), np.int64).tolist() if i in pos]
        if len(idx) < 5:
            continue
        kf_from_world = invert_pose(world_from_kf[kf])
        L = pts[idx] @ kf_from_world[:3, :3].T + kf_from_world[:3, 3]
        d = keyframe_discrepancies(stripe.points_in_cam, L, calibration.fx_px, radius_px)
        if d.size >= 3:
            per_kf.append(float(np.median(d)))
            pairs += int(d.size)
    if len(per_kf) < 3:
        return None
    v = np.asarray(per_kf)
    m = float(np.median(v))
    # robust standard error of the median of the keyframes' medians
    sm = max(1.4826 * float(np.median(np.abs(v - m))) * 1.2533 / np.sqrt(v.size), 1e-6)
    A = np.array(
        [
            [1 / sigma_log_baseline**2 + 1 / sm**2, -1 / sm**2],
            [-1 / sm**2, 1 / sigma_log_plane_offset**2 + 1 / sm**2],
        ]
    )
    rhs = np.array([m / sm**2, -m / sm**2])
    cov = np.linalg.inv(A)
    x = cov @ rhs
    s = np.sqrt(np.diag(cov))
    return LaserStereoScale(
        float(x[0]), float(x[1]), float(s[0]), float(s[1]), float(cov[0, 1] / (s[0] * s[1])), m, sm, pairs, v.size
    )
