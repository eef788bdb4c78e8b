"""Laser-stereo consistency: the stereo scale (baseline) and the light plane's offset together (issue 31).

A stripe point's depth comes from the light plane (``n . p + d = 0``): scaling ``d`` scales every
stripe point about the camera centre. A stereo landmark's depth scales with the baseline. Where a
stripe falls on a surface the landmarks also see, the two must agree: at each (subsampled) stripe
pixel of a keyframe, the inverse depth of the surface is interpolated from the keyframe's landmarks
within ``radius_px`` (a quadratic in normalised image coordinates: unbiased on a curved surface), and
``log(z_stripe / z_stereo)`` is the discrepancy. Per keyframe the median of them, over keyframes
the median ``m`` with its robust standard error.

Unknowns ``x_b = log(b' / b)`` and ``x_d = log(d' / d)`` (relative corrections of the baseline and
of the plane offset) and the plane's tilt ``t`` (radians, about two axes in the plane: the normal
becomes ``n + t1 e1 + t2 e2``), with Gaussian priors from their recorded standard deviations. A
stripe point ``p`` moves by ``x_d + (t1 e1 . p + t2 e2 . p) / d`` in log depth, a landmark by
``x_b``, so each pair gives ``x_b - x_d - (t . E p) / d = log(z_stripe / z_stereo)``: a tilt shows
as a gradient along the stripe and is told apart; the constant part fixes only the ratio of the two
scales, and the priors share it out. Pairs of one keyframe share its errors (its landmark fit, its
pose): their information is divided by the mean number of pairs per keyframe (as if each keyframe
gave one), so the posterior is not over-confident.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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
    tilt_rad: F64 = field(default_factory=lambda: np.zeros(2))
    sigma_tilt_rad: F64 = field(default_factory=lambda: np.zeros(2))
    tilt_axes: F64 = field(default_factory=lambda: np.zeros((2, 3)))

    @property
    def baseline_factor(self) -> float:
        """Refined over current baseline."""
        return float(np.exp(self.log_baseline))

    @property
    def plane_offset_factor(self) -> float:
        """Refined over current plane offset."""
        return float(np.exp(self.log_plane_offset))

    def refined_plane(self, normal_in_cam: F64, d_m: float) -> tuple[F64, float]:
        """The refined plane ``(n, d)`` of the current one (unit normal, ``n . p + d = 0``)."""
        n = np.asarray(normal_in_cam, float) + self.tilt_rad @ self.tilt_axes
        return n / np.linalg.norm(n), float(d_m * self.plane_offset_factor)


def _normalised(p_cam: F64) -> F64:
    return p_cam[:, :2] / p_cam[:, 2:3]


def keyframe_discrepancies(
    stripe_in_cam: F64,
    landmarks_in_cam: F64,
    fx_px: float,
    radius_px: float = 40.0,
    every: int = 4,
    min_landmarks: int = 10,
    max_fit_rel: float = 0.003,
) -> tuple[F64, F64]:
    """``log(z_stripe / z_stereo)`` at the stripe points of one keyframe (camera frame, metres), and those points.

    At every ``every``-th stripe point, the landmarks within ``radius_px`` in the (normalised,
    times ``fx_px``) image give a quadratic fit of inverse depth about the point; a fit with fewer
    than ``min_landmarks`` or a relative RMS above ``max_fit_rel`` gives nothing. Quadratic, not
    affine: inverse depth is affine in the image only on a plane, and on a curved surface an affine
    fit over the disc is off at its centre by the surface's sag (a surface bulging towards the
    camera lies in front of it). Measured on the realistic orbit, seed 1 (the stripes' true depths
    from the scene mesh against the refined landmarks, whose own depth error is +0.021 %): affine
    over 25 px -0.028 % median / -0.062 % mean over keyframes, quadratic over 40 px -0.022 / -0.033 %.
    """
    S = np.asarray(stripe_in_cam, float).reshape(-1, 3)[::every]
    L = np.asarray(landmarks_in_cam, float).reshape(-1, 3)
    S = S[S[:, 2] > 1e-3]
    L = L[L[:, 2] > 1e-3]
    if S.shape[0] == 0 or L.shape[0] < min_landmarks:
        return np.zeros(0), np.zeros((0, 3))
    s_xy, l_xy = _normalised(S), _normalised(L)
    l_inv = 1.0 / L[:, 2]
    r = radius_px / fx_px
    # the two coordinates' squares added (not an S x L x 2 array summed: most of this function's time)
    near = (s_xy[:, 0, None] - l_xy[None, :, 0]) ** 2 + (s_xy[:, 1, None] - l_xy[None, :, 1]) ** 2 < r * r
    count = near.sum(axis=1)
    fit_at = np.flatnonzero(count >= min_landmarks)
    if fit_at.size == 0:
        return np.zeros(0), np.zeros((0, 3))
    coef, rms = _quadratic_fits(s_xy[fit_at], l_xy, l_inv, near[fit_at], r)
    ok = (rms <= max_fit_rel * np.abs(coef[:, 0])) & (coef[:, 0] > 0)
    i = fit_at[ok]
    return np.log(S[i, 2] * coef[ok, 0]), S[i].reshape(-1, 3)  # z_stripe / z_stereo = z_stripe * (1 / z_stereo)


def _quadratic_fits(
    centre_xy: F64, l_xy: F64, l_inv: F64, near: NDArray[np.bool_], r: float
) -> tuple[F64, F64]:
    """Least-squares quadratics of ``l_inv`` about each centre over its ``near`` landmarks: (C x 6 coefficients, C rms).

    Normalised image coordinates scaled by ``r`` (within the unit disc: well conditioned). Every
    centre's fit at once (fin15, issue 32: a ``lstsq`` per stripe point was most of the laser-stereo
    scale's 0.1 s CPU before the final mesh starts): its rows gathered into a zero-padded stack (zero
    rows change no least-squares solution) solved by its normal equations; a fit whose normal matrix is
    ill-conditioned (condition above 1e8, e.g. landmarks on one line) by ``lstsq`` on its rows, as before.
    """
    m = int(near.sum(axis=1).max())
    order = np.argsort(~near, axis=1, kind="stable")[:, :m]  # each centre's near landmarks first, in order
    valid = np.take_along_axis(near, order, axis=1)
    q = (l_xy[order] - centre_xy[:, None, :]) / r
    qx, qy = q[..., 0], q[..., 1]
    A = np.stack([np.ones_like(qx), qx, qy, qx**2, qx * qy, qy**2], axis=-1) * valid[..., None]
    b = l_inv[order] * valid
    N, rhs = np.einsum("cmi,cmj->cij", A, A), np.einsum("cmi,cm->ci", A, b)
    with np.errstate(all="ignore"):
        good = np.linalg.cond(N) < 1e8  # False for a singular one (inf) too
    coef = np.zeros((A.shape[0], 6))
    if np.any(good):
        coef[good] = np.linalg.solve(N[good], rhs[good][..., None])[..., 0]
    for c in np.flatnonzero(~good):
        coef[c] = np.linalg.lstsq(A[c], b[c], rcond=None)[0]
    res = (np.einsum("cmi,ci->cm", A, coef) - b) * valid
    return coef, np.sqrt(np.sum(res**2, axis=1) / valid.sum(axis=1))


def stripe_camera_sensitivity(
    stripe_in_cam: F64, calibration: StereoCalibration, plane_normal_in_cam: F64, plane_d_m: float, sigma_left: F64
) -> F64:
    """N x 5: the log-depth change of each stripe point when the left camera's fx, fy, cx, cy (px) and k1 move.

    Each point goes to its raw pixel through the left camera (pinhole, OpenCV plumb-bob) and back along
    the ray of the camera with one parameter moved by its ``sigma_left`` to the light plane
    (``n . p + d = 0``, camera frame, metres). Zero columns for a fisheye (equidistant) model.
    """
    import cv2

    P = np.asarray(stripe_in_cam, float).reshape(-1, 3)
    out = np.zeros((P.shape[0], 5))
    if P.shape[0] == 0 or calibration.camera_model == "equidistant":
        return out
    K = calibration.K_left
    dist = np.zeros(5) if calibration.rectified else np.asarray(calibration.dist_left, float)
    uv, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    n = np.asarray(plane_normal_in_cam, float)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    for j, (row, col) in enumerate(((0, 0), (1, 1), (0, 2), (1, 2), (-1, 0))):
        K2, d2 = K.copy(), dist.copy()
        if row >= 0:
            K2[row, col] += sigma_left[j]
        else:
            d2[0] += sigma_left[j]
        xy = cv2.undistortPoints(uv, K2, d2, criteria=crit).reshape(-1, 2)
        ray = np.column_stack([xy, np.ones(xy.shape[0])])
        z = ray[:, 2] * (-plane_d_m / (ray @ n))
        out[:, j] = np.log(z / P[:, 2])
    return out


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
    plane_normal_in_cam: F64,
    plane_d_m: float,
    sigma_tilt_rad: float,
    radius_px: float = 40.0,
    sigma_left_camera: F64 | None = None,
) -> LaserStereoScale | None:
    """The joint estimate of the module docstring; None when no keyframe has a stripe on seen surfaces.

    ``keyframe_landmarks``: the landmark ids each keyframe observed; stripes are matched to keyframes
    by exact timestamp. ``sigma_left_camera``: the left camera's remaining uncertainty (fx, fy, cx,
    cy in px, k1; the calibrating bundle adjustment's posterior), whose effect on the stripes' depth
    (:func:`stripe_camera_sensitivity`) enters as five nuisance unknowns with unit priors: without
    them a stripe depth error of the camera is shared out to the baseline and the plane.
    """
    by_stamp = {s.timestamp_ns: s for s in stripes}
    pos = {int(i): k for k, i in enumerate(np.asarray(landmark_ids).tolist())}
    pts = np.asarray(landmarks_in_world, float).reshape(-1, 3)
    n = np.asarray(plane_normal_in_cam, float) / np.linalg.norm(plane_normal_in_cam)
    e1 = np.cross(n, [0.0, 1.0, 0.0] if abs(n[1]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    per_kf: list[float] = []
    rows: list[F64] = []
    vals: list[F64] = []
    for kf, stamp in keyframe_stamps_ns.items():
        stripe = by_stamp.get(stamp)
        if stripe is None or kf not in world_from_kf or stripe.points_in_cam.shape[0] < 3:
            continue
        idx = [pos[i] for i in np.asarray(keyframe_landmarks.get(kf, []), np.int64).tolist() if i in pos]
        if len(idx) < 5:
            continue
        kf_from_world = invert_pose(world_from_kf[kf])
        L = pts[idx] @ kf_from_world[:3, :3].T + kf_from_world[:3, 3]
        d, P = keyframe_discrepancies(stripe.points_in_cam, L, calibration.fx_px, radius_px)
        if d.size >= 3:
            per_kf.append(float(np.median(d)))
            vals.append(d)
            tilt = -np.column_stack([P @ e1, P @ e2]) / plane_d_m
            cam = (
                -stripe_camera_sensitivity(P, calibration, n, plane_d_m, np.asarray(sigma_left_camera, float))
                if sigma_left_camera is not None
                else np.zeros((d.size, 0))
            )
            rows.append(np.column_stack([np.ones(d.size), -np.ones(d.size), tilt, cam]))
    if len(per_kf) < 3:
        return None
    v = np.asarray(per_kf)
    m = float(np.median(v))
    sm = max(1.4826 * float(np.median(np.abs(v - m))) * 1.2533 / np.sqrt(v.size), 1e-6)
    A = np.vstack(rows)
    y = np.concatenate(vals)
    per_kf_pairs = A.shape[0] / len(rows)
    prior_sd = np.array([sigma_log_baseline, sigma_log_plane_offset, sigma_tilt_rad, sigma_tilt_rad])
    prior_sd = np.concatenate([prior_sd, np.ones(A.shape[1] - 4)])  # the camera's, in its sigmas
    prior_info = np.diag(1.0 / prior_sd**2)
    x = np.zeros(A.shape[1])
    w = np.ones(y.size)
    sigma = 1.4826 * float(np.median(np.abs(y - np.median(y)))) + 1e-9
    for _ in range(5):  # Huber re-weighting, the pair noise from the residuals' MAD
        scale = 1.0 / (sigma**2 * per_kf_pairs)  # a keyframe's pairs count as one
        H = prior_info + scale * (A.T * w) @ A
        x = np.linalg.solve(H, scale * (A.T * w) @ y)
        r = y - A @ x
        sigma = max(1.4826 * float(np.median(np.abs(r))), 1e-6)
        w = np.minimum(1.0, 1.345 * sigma / np.maximum(np.abs(r), 1e-12))
    cov = np.linalg.inv(H)
    s = np.sqrt(np.diag(cov))
    return LaserStereoScale(
        float(x[0]), float(x[1]), float(s[0]), float(s[1]), float(cov[0, 1] / (s[0] * s[1])), m, sm,
        int(y.size), int(v.size), x[2:4].copy(), s[2:4].copy(), np.vstack([e1, e2]),
    )
