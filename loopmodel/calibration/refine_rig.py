"""Self-calibration of a stereo rig in the final bundle adjustment (issue 31).

The front end measures in images rectified with the *recorded* calibration. Each measurement is
mapped back to the raw (distorted) pixel it came from with that recorded model, and a bundle
adjustment then estimates keyframe poses (``world_from_cam`` of the left camera), landmarks
(world, metres) and the raw calibration together: fx, fy, cx, cy, k1 (and k2 when asked) of each
camera, the stereo rotation and the baseline, each with a Gaussian prior at its recorded value.

Model of one observation of world point ``p_w`` by keyframe ``(R, t)`` (``world_from_cam``):
left camera ``p_l = R^T (p_w - t)``, right camera ``p_r = exp(phi) R_rl p_l + b t_dir`` (``R_rl``,
``t_dir``: the recorded ``right_from_left`` rotation and unit baseline direction, ``phi`` the
rotation correction in radians, ``b`` the baseline in metres), pixels through OpenCV's plumb-bob
distortion (k1, k2, p1, p2, k3; p1, p2, k3 stay at their recorded values). Pose increments are
``R <- R exp(w)``, ``t <- t + R v``.

The solver is Levenberg-Marquardt with a Huber loss; the landmarks are eliminated by their Schur
complement (block-diagonal 3x3), so each step solves a dense system in the poses and the
calibration. The first keyframe is held fixed (the gauge); the scale comes from the baseline
prior. The posterior covariance of the calibration is the inverse of that reduced system; a
parameter whose posterior standard deviation is not well below its prior's (``observable_ratio``)
is put back at its recorded value, held there, and reported as unobservable.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from numpy.typing import NDArray

from loopmodel.errors import CalibrationError
from loopmodel.geometry.se3 import cross_rows, so3_exp, so3_log_rows
from loopmodel.types import Keyframe, StereoCalibration

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: The calibration parameters, in the order of the parameter vector (units in the names; the
#: stereo rotation correction is stored in radians and reported in degrees).
PARAM_NAMES: tuple[str, ...] = (
    "fx_left_px",
    "fy_left_px",
    "cx_left_px",
    "cy_left_px",
    "k1_left",
    "k2_left",
    "fx_right_px",
    "fy_right_px",
    "cx_right_px",
    "cy_right_px",
    "k1_right",
    "k2_right",
    "rot_x_deg",
    "rot_y_deg",
    "rot_z_deg",
    "baseline_m",
)
N_PARAMS = len(PARAM_NAMES)
_ROT = slice(12, 15)
#: posterior over prior sigma above which a parameter is not informed by the data at all (held)
HOLD_RATIO = 0.99
_BASE = 15


# ----------------------------------------------------------------------------- the camera model


def distortion5(dist: F64) -> F64:
    """k1, k2, p1, p2, k3 of an OpenCV plumb-bob distortion vector (4, 5 or 8 coefficients).

    Raises :class:`CalibrationError` for a rational model whose k4..k6 are not zero.
    """
    d = np.asarray(dist, float).ravel()
    if d.size > 5 and np.any(np.abs(d[5:]) > 0):
        raise CalibrationError(None, "self-calibration supports the plumb-bob model (k1, k2, p1, p2, k3) only")
    out = np.zeros(5)
    out[: min(d.size, 5)] = d[:5]
    return out


def project_with_jacobians(p_cam: F64, intr: F64, dist: F64) -> tuple[F64, F64, F64]:
    """Pixels (N x 2) of camera-frame points (N x 3) and their Jacobians.

    ``intr`` = fx, fy, cx, cy (pixels), ``dist`` = k1, k2, p1, p2, k3. Returns ``uv``,
    ``d uv / d p_cam`` (N x 2 x 3) and ``d uv / d (fx, fy, cx, cy, k1, k2)`` (N x 2 x 6).
    """
    fx, fy, cx, cy = (float(v) for v in intr)
    k1, k2, p1, p2, k3 = (float(v) for v in dist)
    X, Y, Z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
    iz = 1.0 / np.where(np.abs(Z) > 1e-9, Z, 1e-9)
    x, y = X * iz, Y * iz
    r2 = x * x + y * y
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d rad / d r2
    xd = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    uv = np.column_stack([fx * xd + cx, fy * yd + cy])
    dxd_dx = rad + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dx = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dy = rad + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
    n = p_cam.shape[0]
    # d(x, y) / d(X, Y, Z)
    dn = np.zeros((n, 2, 3))
    dn[:, 0, 0] = iz
    dn[:, 0, 2] = -x * iz
    dn[:, 1, 1] = iz
    dn[:, 1, 2] = -y * iz
    dd = np.empty((n, 2, 2))
    dd[:, 0, 0], dd[:, 0, 1] = fx * dxd_dx, fx * dxd_dy
    dd[:, 1, 0], dd[:, 1, 1] = fy * dyd_dx, fy * dyd_dy
    J_p = dd @ dn
    J_i = np.zeros((n, 2, 6))
    J_i[:, 0, 0] = xd
    J_i[:, 1, 1] = yd
    J_i[:, 0, 2] = 1.0
    J_i[:, 1, 3] = 1.0
    J_i[:, 0, 4] = fx * x * r2
    J_i[:, 1, 4] = fy * y * r2
    J_i[:, 0, 5] = fx * x * r2 * r2
    J_i[:, 1, 5] = fy * y * r2 * r2
    return uv, J_p, J_i


def _project(p_cam: F64, K: F64, dist: F64) -> F64:
    uv, _, _ = project_with_jacobians(p_cam, np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]), distortion5(dist))
    return uv


@dataclass
class RigParameters:
    """The recorded calibration as a parameter vector, and back.

    ``values`` follow :data:`PARAM_NAMES` (rotation correction in radians).
    """

    recorded: StereoCalibration
    values: F64
    dist_left: F64 = field(repr=False)
    dist_right: F64 = field(repr=False)
    rot_right_from_left: F64 = field(repr=False)
    baseline_dir: F64 = field(repr=False)

    @classmethod
    def of(cls, cal: StereoCalibration) -> RigParameters:
        """The parameters of a (rectified or raw, plumb-bob) calibration."""
        if cal.camera_model != "pinhole":
            raise CalibrationError(None, f"self-calibration needs the pinhole model, not {cal.camera_model}")
        dl, dr = distortion5(cal.dist_left), distortion5(cal.dist_right)
        KL, KR = cal.K_left, cal.K_right
        b = cal.baseline_m
        v = np.array(
            [KL[0, 0], KL[1, 1], KL[0, 2], KL[1, 2], dl[0], dl[1],
             KR[0, 0], KR[1, 1], KR[0, 2], KR[1, 2], dr[0], dr[1], 0.0, 0.0, 0.0, b]
        )
        return cls(cal, v, dl, dr, cal.right_from_left[:3, :3].copy(), cal.right_from_left[:3, 3] / b)

    def intrinsics(self, theta: F64, side: int) -> tuple[F64, F64]:
        """``(fx, fy, cx, cy)`` and the 5 distortion terms of camera ``side`` (0 left, 1 right)."""
        o = 6 * side
        d = (self.dist_left if side == 0 else self.dist_right).copy()
        d[0], d[1] = theta[o + 4], theta[o + 5]
        return theta[o : o + 4].copy(), d

    def right_from_left(self, theta: F64) -> F64:
        """4x4 ``right_from_left`` (metres) of a parameter vector."""
        T = np.eye(4)
        T[:3, :3] = so3_exp(theta[_ROT]) @ self.rot_right_from_left
        T[:3, 3] = theta[_BASE] * self.baseline_dir
        return T

    def calibration(self, theta: F64) -> StereoCalibration:
        """The raw (unrectified) calibration of a parameter vector."""
        Ks, ds = [], []
        for side in (0, 1):
            i, d = self.intrinsics(theta, side)
            Ks.append(np.array([[i[0], 0.0, i[2]], [0.0, i[1], i[3]], [0.0, 0.0, 1.0]]))
            ds.append(d)
        rec = self.recorded
        return StereoCalibration(
            Ks[0], Ks[1], self.right_from_left(theta), rec.image_size, ds[0], ds[1], rectified=False
        )


def prior_sigmas(
    sigma_focal_px: float,
    sigma_principal_px: float,
    sigma_k1: float,
    sigma_k2: float,
    sigma_rotation_deg: float,
    sigma_baseline_m: float,
) -> F64:
    """Prior standard deviations in the order of :data:`PARAM_NAMES` (rotation in radians)."""
    cam = [sigma_focal_px, sigma_focal_px, sigma_principal_px, sigma_principal_px, sigma_k1, sigma_k2]
    return np.array(cam + cam + [np.radians(sigma_rotation_deg)] * 3 + [sigma_baseline_m], dtype=float)


# ----------------------------------------------------------------------------- observations


@dataclass
class RigObservations:
    """Raw-pixel observations: keyframe index, landmark index, camera (0 left, 1 right), pixel (N x 2).

    ``measure`` (N x 2 x 2) maps a raw-pixel difference to what was measured: the identity for a
    left-image point (u and v measured); for the right image only the rectified u is measured (the
    front end matches along the left point's row), so its first row is the gradient of the
    rectified u with respect to the raw pixel (the recorded model) and its second row is zero;
    where the right match's own row is given both rows are the rectified pixel's gradient.
    """

    pose_idx: I64
    point_idx: I64
    cam: I64
    uv_px: F64
    measure: F64
    # relative-pose (loop) constraints between keyframes: (pose index a, pose index b, a_from_b 4x4),
    # standard deviations (rad x3, m x3)
    loops: list[tuple[int, int, F64]] = field(default_factory=list)
    loop_sigmas: F64 = field(default_factory=lambda: np.array([0.01] * 3 + [0.01] * 3))

    def __len__(self) -> int:
        return int(self.pose_idx.size)

    @property
    def row_measured(self) -> NDArray[np.bool_]:
        """Observations whose row is measured: every left one, a right one where its row was given."""
        return (self.cam == 0) | np.any(self.measure[:, 1, :] != 0.0, axis=1)

    @property
    def residual_count(self) -> int:
        """Scalar measurements (2 per left point, 1 per right point, 2 where its row is measured)."""
        return int(len(self) + np.sum(self.row_measured))


def raw_from_rectified_px(uv_rect_px: F64, K_rect: F64, rect_from_cam_rot: F64, K: F64, dist: F64) -> F64:
    """Raw (distorted) pixels of rectified pixels, through the model they were rectified with.

    ``K_rect`` the rectified camera matrix, ``rect_from_cam_rot`` (3x3) the rectifying rotation of
    that camera, ``K``/``dist`` its raw intrinsics (OpenCV).
    """
    return _raw_and_gradient(uv_rect_px, K_rect, rect_from_cam_rot, K, dist)[0]


def _raw_and_gradient(
    uv_rect_px: F64, K_rect: F64, rect_from_cam_rot: F64, K: F64, dist: F64
) -> tuple[F64, F64]:
    """Raw pixels of rectified pixels and ``d rectified / d raw`` (N x 2 x 2) there."""
    uv = np.asarray(uv_rect_px, float).reshape(-1, 2)
    rays = np.column_stack([uv, np.ones(uv.shape[0])]) @ np.linalg.inv(K_rect).T
    p_cam = rays @ rect_from_cam_rot  # (R^T ray)^T = ray^T R
    raw, A, _ = project_with_jacobians(
        p_cam, np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]), distortion5(dist)
    )
    _, B, _ = project_with_jacobians(p_cam @ rect_from_cam_rot.T, np.array(
        [K_rect[0, 0], K_rect[1, 1], K_rect[0, 2], K_rect[1, 2]]), np.zeros(5))
    B = B @ rect_from_cam_rot  # d rect / d p_cam
    # both are blind along the ray: restrict to two directions across it
    n = p_cam / np.linalg.norm(p_cam, axis=1, keepdims=True)
    a = np.cross(n, np.array([0.0, 1.0, 0.0]))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    c = np.cross(n, a)
    T = np.stack([a, c], axis=2)  # N x 3 x 2
    grad = (B @ T) @ np.linalg.inv(A @ T)
    return raw, grad


def observations_from_keyframes(
    keyframes: list[Keyframe],
    cal_input: StereoCalibration,
    K_rect_left: F64,
    K_rect_right: F64,
    R_rect_left: F64,
    R_rect_right: F64,
    right_rows_px: dict[int, F64] | None = None,
) -> tuple[RigObservations, list[int], I64]:
    """The keyframes' stereo and monocular measurements as raw pixels of the recorded model.

    Returns the observations, the keyframe ids in pose order and the landmark ids in point order.
    A keyframe's monocular observation of a landmark it also measures in stereo is dropped (one
    measurement of one feature). ``right_rows_px`` (keyframe id -> rectified row of each stereo
    match in the right image, the order of ``stereo_px``): where given, the right image's row is
    measured too (both rectified coordinates), which makes the right camera's fy, cy and the
    rotation about the baseline observable; else only its rectified u at the left row.
    """
    kf_ids = [int(k.id) for k in keyframes]
    pose_of = {k: i for i, k in enumerate(kf_ids)}
    lm_rows: list[I64] = []
    pose_rows: list[I64] = []
    cam_rows: list[I64] = []
    uv_rect: list[F64] = []
    row_measured: list[NDArray[np.bool_]] = []
    for kf in keyframes:
        i = pose_of[int(kf.id)]
        ids = np.asarray(kf.landmark_ids, np.int64).ravel()
        st = np.asarray(kf.stereo_px, float).reshape(-1, 3)
        rows_r = None if right_rows_px is None else right_rows_px.get(int(kf.id))
        if ids.size:
            for side, col in ((0, 0), (1, 1)):
                lm_rows.append(ids)
                pose_rows.append(np.full(ids.size, i, np.int64))
                cam_rows.append(np.full(ids.size, side, np.int64))
                v = st[:, 2] if side == 0 or rows_r is None else np.asarray(rows_r, float).ravel()
                uv_rect.append(np.column_stack([st[:, col], v]))
                row_measured.append(np.full(ids.size, side == 0 or rows_r is not None))
        mono = np.asarray(kf.mono_obs, float).reshape(-1, 3)
        if mono.shape[0]:
            mids = mono[:, 0].astype(np.int64)
            keep = ~np.isin(mids, ids)
            lm_rows.append(mids[keep])
            pose_rows.append(np.full(int(keep.sum()), i, np.int64))
            cam_rows.append(np.zeros(int(keep.sum()), np.int64))
            uv_rect.append(mono[keep, 1:3])
            row_measured.append(np.ones(int(keep.sum()), bool))
    if not lm_rows:
        empty = np.zeros(0, np.int64)
        return RigObservations(empty, empty, empty, np.zeros((0, 2)), np.zeros((0, 2, 2))), kf_ids, empty
    lm = np.concatenate(lm_rows)
    pose = np.concatenate(pose_rows)
    cam = np.concatenate(cam_rows)
    uvr = np.concatenate(uv_rect)
    both = np.concatenate(row_measured)
    # one observation per (keyframe, landmark, camera): the first
    key = (pose * (lm.max() + 1) + lm) * 2 + cam
    _, first = np.unique(key, return_index=True)
    first = np.sort(first)
    lm, pose, cam, uvr, both = lm[first], pose[first], cam[first], uvr[first], both[first]
    lm_ids, point = np.unique(lm, return_inverse=True)
    uv = np.zeros_like(uvr)
    measure = np.zeros((uv.shape[0], 2, 2))
    measure[:, 0, 0] = measure[:, 1, 1] = 1.0
    for side, K_rect, R_rect in ((0, K_rect_left, R_rect_left), (1, K_rect_right, R_rect_right)):
        sel = cam == side
        K = cal_input.K_left if side == 0 else cal_input.K_right
        d = cal_input.dist_left if side == 0 else cal_input.dist_right
        uv[sel], grad = _raw_and_gradient(uvr[sel], K_rect, R_rect, K, d)
        if side == 1:
            m = grad.copy()  # the right row measured: both rectified coordinates
            m[~both[sel], 1, :] = 0.0  # else the rectified u only
            measure[sel] = m
    obs = RigObservations(pose, point.astype(np.int64), cam, uv, measure)
    return obs, kf_ids, lm_ids.astype(np.int64)


# ----------------------------------------------------------------------------- residuals


def residuals_and_jacobians(
    obs: RigObservations,
    rot_world_from_cam: F64,
    t_world_from_cam: F64,
    points_w: F64,
    rig: RigParameters,
    theta: F64,
) -> tuple[F64, F64, F64, F64]:
    """Predicted minus measured pixels (N x 2, through ``obs.measure``) and the Jacobians of every observation.

    ``d r / d (w, v)`` of its pose (N x 2 x 6), ``d r / d p_w`` (N x 2 x 3) and
    ``d r / d theta`` (N x 2 x 16, all calibration parameters).
    """
    n = len(obs)
    R = rot_world_from_cam[obs.pose_idx]
    t = t_world_from_cam[obs.pose_idx]
    pw = points_w[obs.point_idx]
    Rt = np.transpose(R, (0, 2, 1))
    p_l = np.einsum("nij,nj->ni", Rt, pw - t)  # R^T (p_w - t)
    R_rl = so3_exp(theta[_ROT]) @ rig.rot_right_from_left
    t_rl = theta[_BASE] * rig.baseline_dir
    res = np.zeros((n, 2))
    J_pose = np.zeros((n, 2, 6))
    J_pt = np.zeros((n, 2, 3))
    J_th = np.zeros((n, 2, N_PARAMS))
    for side in (0, 1):
        sel = np.flatnonzero(obs.cam == side)
        if sel.size == 0:
            continue
        intr, dist = rig.intrinsics(theta, side)
        pc = p_l[sel]
        q = pc @ R_rl.T + t_rl if side == 1 else pc
        uv, Jq, Ji = project_with_jacobians(q, intr, dist)
        d_uv = uv - obs.uv_px[sel]
        o = 6 * side
        if side == 1:
            # the rectified u (and the rectified v where the right row is measured, else a zero
            # row): the rows of m, the gradient of the rectified pixel by the raw pixel
            for row in (0, 1):
                m = obs.measure[sel, row, :]
                res[sel, row] = np.sum(m * d_uv, axis=1)
                jq = np.einsum("nk,nkj->nj", m, Jq)  # N x 3
                J_th[sel, row, o : o + 6] = np.einsum("nk,nkj->nj", m, Ji)
                J_th[sel, row, _ROT] = cross_rows(q - t_rl, jq)  # the row jq (-[q - t]x)
                J_th[sel, row, _BASE] = jq @ rig.baseline_dir
                jl = jq @ R_rl  # by p_l
                J_pose[sel, row, :3] = cross_rows(jl, pc)  # the row jl [p_l]x
                J_pose[sel, row, 3:] = -jl
                J_pt[sel, row] = np.einsum("nj,nkj->nk", jl, R[sel])
        else:
            res[sel] = d_uv
            J_th[sel, :, o : o + 6] = Ji
            # d p_l / d w = [p_l]x, d p_l / d v = -I, d p_l / d p_w = R^T
            for row in (0, 1):
                jl = Jq[:, row, :]
                J_pose[sel, row, :3] = cross_rows(jl, pc)
                J_pose[sel, row, 3:] = -jl
                J_pt[sel, row] = np.einsum("nj,nkj->nk", jl, R[sel])
    return res, J_pose, J_pt, J_th


def _camera_arrays(rig: RigParameters, theta: F64) -> tuple[F64, F64, F64, F64]:
    """``(fx, fy, cx, cy)`` (2 x 4) and the 5 distortion terms (2 x 5) of both cameras, ``R_rl``, ``t_rl`` (m)."""
    il, dl = rig.intrinsics(theta, 0)
    ir, dr = rig.intrinsics(theta, 1)
    R_rl = so3_exp(theta[_ROT]) @ rig.rot_right_from_left
    return np.array([il, ir]), np.array([dl, dr]), R_rl, theta[_BASE] * rig.baseline_dir


def residuals_and_jacobians_compiled(
    obs: RigObservations,
    rot_world_from_cam: F64,
    t_world_from_cam: F64,
    points_w: F64,
    rig: RigParameters,
    theta: F64,
    jacobians: bool = True,
) -> tuple[F64, F64, F64, F64]:
    """:func:`residuals_and_jacobians` by the compiled kernel (:mod:`._rig_kernels`): the same values.

    Without ``jacobians`` only the residuals are computed (the Jacobians returned as zeros).
    """
    from loopmodel.calibration import _rig_kernels

    n = len(obs)
    intr, dist, R_rl, t_rl = _camera_arrays(rig, theta)
    r = np.zeros((n, 2))
    Jp, Jl, Jt = np.zeros((n, 2, 6)), np.zeros((n, 2, 3)), np.zeros((n, 2, N_PARAMS))
    _rig_kernels.evaluate(
        np.ascontiguousarray(obs.pose_idx, np.int64), np.ascontiguousarray(obs.point_idx, np.int64),
        np.ascontiguousarray(obs.cam, np.int64), np.ascontiguousarray(obs.uv_px, np.float64),
        np.ascontiguousarray(obs.measure, np.float64), np.ascontiguousarray(rot_world_from_cam, np.float64),
        np.ascontiguousarray(t_world_from_cam, np.float64), np.ascontiguousarray(points_w, np.float64),
        intr, dist, R_rl, np.ascontiguousarray(t_rl), np.ascontiguousarray(rig.baseline_dir, np.float64), jacobians,
        r, Jp, Jl, Jt,
    )
    return r, Jp, Jl, Jt


def _loop_residuals(Ra: F64, ta: F64, Rb: F64, tb: F64, TR_t: F64, T_t: F64) -> F64:
    """``(log R, t)`` of ``a_from_b^-1 a_from_world b`` per loop (N rows; rad, m): zero when the poses agree.

    ``TR_t``: each loop's ``a_from_b`` rotation transposed, ``T_t`` its translation.
    """
    RaT = Ra.transpose(0, 2, 1)
    R = np.matmul(np.matmul(TR_t, RaT), Rb)
    t = np.matmul(TR_t, (np.matmul(RaT, (tb - ta)[:, :, None])[:, :, 0] - T_t)[:, :, None])[:, :, 0]
    return np.concatenate([so3_log_rows(R), t], axis=1)


def _loop_perturbations(h: float) -> tuple[F64, F64, F64, F64]:
    """The pose increments of :func:`loop_terms`' central differences, the unperturbed first.

    Per row (25: none, then each of the 12 coordinates of the poses (a, b) by +h and -h): the rotation
    each pose of a loop is multiplied by on the right and the offset its rotation maps (``R <- R exp(w)``,
    ``t <- t + R v``).
    """
    Ea, Eb = np.tile(np.eye(3), (25, 1, 1)), np.tile(np.eye(3), (25, 1, 1))
    Da, Db = np.zeros((25, 3)), np.zeros((25, 3))
    for k in range(12):
        which, j = divmod(k, 6)
        for m, sgn in enumerate((1.0, -1.0)):
            d = np.zeros(6)
            d[j] = sgn * h
            row = 1 + 2 * k + m
            (Ea if which == 0 else Eb)[row] = so3_exp(d[:3])
            (Da if which == 0 else Db)[row] = d[3:]
    return Ea, Da, Eb, Db


def loop_terms(st_R: F64, st_t: F64, obs: RigObservations) -> tuple[F64, F64, float]:
    """The loop constraints' whitened normal-equation block over all poses (6P x 6P), gradient, cost.

    Jacobians by central differences of the pose increments, every loop and increment in one batch
    (fin17: one at a time in Python was 45 % of the calibrating BA's CPU with 68 loops, 118 keyframes).
    """
    n = st_R.shape[0]
    H = np.zeros((6 * n, 6 * n))
    g = np.zeros(6 * n)
    if not obs.loops:
        return H, g, 0.0
    w = 1.0 / np.asarray(obs.loop_sigmas, float)
    h = 1e-7
    a = np.array([lp[0] for lp in obs.loops], np.int64)
    b = np.array([lp[1] for lp in obs.loops], np.int64)
    T = np.stack([np.asarray(lp[2], float) for lp in obs.loops])
    L = a.size
    Ea, Da, Eb, Db = _loop_perturbations(h)
    Ra, Rb = st_R[a][None], st_R[b][None]  # 1 x L x 3 x 3
    Ra_all = np.matmul(Ra, Ea[:, None]).reshape(-1, 3, 3)  # 25 L: increment-major
    Rb_all = np.matmul(Rb, Eb[:, None]).reshape(-1, 3, 3)
    ta_all = (st_t[a][None] + np.matmul(Ra, Da[:, None, :, None])[..., 0]).reshape(-1, 3)
    tb_all = (st_t[b][None] + np.matmul(Rb, Db[:, None, :, None])[..., 0]).reshape(-1, 3)
    TR_t = np.tile(T[:, :3, :3].transpose(0, 2, 1), (25, 1, 1))
    res = (_loop_residuals(Ra_all, ta_all, Rb_all, tb_all, TR_t, np.tile(T[:, :3, 3], (25, 1))) * w).reshape(25, L, 6)
    e = res[0]
    J = ((res[1::2] - res[2::2]) / (2 * h)).transpose(1, 2, 0)  # L x 6 x 12
    idx = np.concatenate([6 * a[:, None] + np.arange(6), 6 * b[:, None] + np.arange(6)], axis=1)  # L x 12
    # the blocks summed in the loops' order, as np.add.at would (np.bincount: faster on a 6P x 6P block)
    flat = (idx[:, :, None] * (6 * n) + idx[:, None, :]).ravel()
    H = np.bincount(flat, np.matmul(J.transpose(0, 2, 1), J).ravel(), minlength=H.size).astype(np.float64)
    g = np.bincount(idx.ravel(), np.einsum("nki,nk->ni", J, e).ravel(), minlength=g.size).astype(np.float64)
    return H.reshape(6 * n, 6 * n), g, float(np.sum(e * e))


def hat_batch(v: F64) -> F64:
    """Skew matrices (N x 3 x 3) of N x 3 vectors."""
    out = np.zeros((v.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def _huber_weights(r_norm: F64, k: float) -> F64:
    if k <= 0:
        return np.ones_like(r_norm)
    return np.where(r_norm <= k, 1.0, k / np.maximum(r_norm, 1e-12))


def _huber_cost(r_norm: F64, k: float) -> float:
    if k <= 0:
        return float(np.sum(r_norm**2))
    return float(np.sum(np.where(r_norm <= k, r_norm**2, 2.0 * k * r_norm - k * k)))


# ----------------------------------------------------------------------------- the solver


@dataclass
class RigRefinement:
    """The outcome of :func:`refine_rig`.

    ``world_from_kf`` (keyframe id -> 4x4), landmarks (ids and world points, metres), the refined
    raw calibration and its parameter vector, per-parameter prior and posterior standard deviations
    (the order of :data:`PARAM_NAMES`, rotation in radians), which parameters were estimated and
    which the data could not constrain, the image noise and fit statistics.
    """

    world_from_kf: dict[int, F64]
    landmark_ids: I64
    landmarks_in_world: F64
    calibration: StereoCalibration
    recorded_values: F64
    values: F64
    prior_sigma: F64
    posterior_sigma: F64
    estimated: NDArray[np.bool_]
    unobservable: list[str]
    pixel_sigma_px: float
    observations: int
    iterations: int
    rms_px_before: float
    rms_px_after: float
    #: the model's posterior (independent pixel errors), the track-robust (sandwich) one and the
    #: share of the held parameters (consider); with ``track_robust`` ``posterior_sigma`` is
    #: ``sqrt(max(model, robust)^2 + consider^2)``, else the model's
    posterior_sigma_model: F64 = field(default_factory=lambda: np.zeros(0))
    posterior_sigma_robust: F64 = field(default_factory=lambda: np.zeros(0))
    posterior_sigma_consider: F64 = field(default_factory=lambda: np.zeros(0))
    #: combinations held at the recorded values (``observable_direction_ratio``): each its posterior
    #: over prior sigma (``ratio``) and its largest weights by parameter (prior-whitened, unit length)
    unobservable_directions: list[dict[str, float]] = field(default_factory=list)
    #: the estimated parameters' posterior covariance in prior-whitened units, before any direction
    #: was held (their order in :data:`PARAM_NAMES`): ``u^T C u`` is a combination's (posterior/prior)^2
    whitened_posterior: F64 = field(default_factory=lambda: np.zeros((0, 0)))
    #: the held directions in full (16 x h, prior-whitened, zero on parameters not estimated)
    held_directions: F64 = field(default_factory=lambda: np.zeros((N_PARAMS, 0)))
    #: the left camera's parameters pinned in place of a held common principal point
    #: (:func:`anchored_held_directions`)
    anchored: list[str] = field(default_factory=list)

    def direction_ratio(self, weights: dict[str, float]) -> float:
        """Posterior over prior sigma of a combination of estimated parameters (prior-whitened weights)."""
        names = [n for n, a in zip(PARAM_NAMES, self.estimated, strict=True) if a]
        u = np.array([weights.get(n, 0.0) for n in names])
        u /= np.linalg.norm(u)
        return float(np.sqrt(u @ self.whitened_posterior @ u))

    def moved_sigma(self, posterior: bool = False) -> dict[str, float]:
        """How far each parameter moved from its recorded value, in units of its prior (or posterior) sigma."""
        s = np.where(self.estimated, self.posterior_sigma, self.prior_sigma) if posterior else self.prior_sigma
        d = (self.values - self.recorded_values) / s
        return {name: float(v) for name, v in zip(PARAM_NAMES, d, strict=True)}

    def values_named(self, theta: F64 | None = None) -> dict[str, float]:
        """Parameter values by name (rotation in degrees)."""
        v = (self.values if theta is None else theta).copy()
        v[_ROT] = np.degrees(v[_ROT])
        return {name: float(x) for name, x in zip(PARAM_NAMES, v, strict=True)}

    def sigma_named(self) -> dict[str, float]:
        """Posterior standard deviations by name (rotation in degrees); the prior's when not estimated."""
        s = np.where(self.estimated, self.posterior_sigma, self.prior_sigma)
        s = s.copy()
        s[_ROT] = np.degrees(s[_ROT])
        return {name: float(x) for name, x in zip(PARAM_NAMES, s, strict=True)}


@dataclass
class _State:
    R: F64
    t: F64
    pts: F64
    theta: F64
    #: residuals, Jacobians, normal equations and the landmarks' elimination by the compiled kernels
    #: (:mod:`._rig_kernels`) or by numpy (the reference form; the same values but for the sums' order)
    compiled: bool = True
    #: (observations, rig, residuals and Jacobians) of this state, once computed (:meth:`residuals`)
    _cache: tuple[object, object, tuple[F64, F64, F64, F64]] | None = field(default=None, repr=False, compare=False)

    def residuals(self, obs: RigObservations, rig: RigParameters) -> tuple[F64, F64, F64, F64]:
        """:func:`residuals_and_jacobians` of this state, computed once (read-only arrays; never change a state)."""
        c = self._cache
        if c is None or c[0] is not obs or c[1] is not rig:
            fn = residuals_and_jacobians_compiled if self.compiled else residuals_and_jacobians
            out = fn(obs, self.R, self.t, self.pts, rig, self.theta)
            for a in out:
                a.setflags(write=False)
            c = self._cache = (obs, rig, out)
        return c[2]


@dataclass
class _Layout:
    """The sparsity of a problem (fixed over the iterations): sums over groups as sparse 0/1 matrices.

    ``pair`` the distinct (pose, landmark) pairs of the observations; ``of_pose``/``of_point``/
    ``of_pair`` sum observation rows per pose, landmark and pair; ``pair_to_pose`` sums pair rows
    per free pose (the first is fixed), ``pair_to_point`` per landmark; ``combo_a``/``combo_b``
    every two pairs of one landmark, both with free poses, pose a not after pose b, and
    ``of_combo`` sums them into the (pose a, pose b) blocks of the reduced system (on and above
    its block diagonal).
    """

    pose_idx: I64
    point_idx: I64
    n_pose: int
    n_pt: int
    pair_pose: I64
    pair_point: I64
    of_pose: sp.csr_matrix
    of_point: sp.csr_matrix
    of_pair: sp.csr_matrix
    pair_to_pose: sp.csr_matrix
    pair_to_point: sp.csr_matrix
    combo_a: I64
    combo_b: I64
    of_combo: sp.csr_matrix
    #: the observations of each pose (indices), and the column of each landmark Jacobian entry
    #: (3 per residual row) in a sparse 2N x 3L matrix
    by_pose: list[I64]
    point_cols: I64
    #: the pair of each observation; the pairs grouped by landmark (``lm_pairs[lm_start[l]:lm_start[l + 1]]``)
    pair_of_obs: I64
    lm_start: I64
    lm_pairs: I64


def _summing(group: I64, n_groups: int) -> sp.csr_matrix:
    """The 0/1 matrix (groups x items) whose product sums the rows of each group (``group`` -1: none)."""
    keep = np.flatnonzero(group >= 0)
    return sp.csr_matrix((np.ones(keep.size), (group[keep], keep)), shape=(n_groups, group.size))


def _layout(obs: RigObservations, n_pose: int, n_pt: int) -> _Layout:
    """The problem's :class:`_Layout`, built once per observation set (cached on ``obs``)."""
    cached = obs.__dict__.get("_layout_cache")
    if (
        isinstance(cached, _Layout)
        and cached.pose_idx is obs.pose_idx
        and cached.point_idx is obs.point_idx
        and (cached.n_pose, cached.n_pt) == (n_pose, n_pt)
    ):
        return cached
    pairs, of_obs = np.unique(obs.pose_idx * n_pt + obs.point_idx, return_inverse=True)
    of_obs = of_obs.ravel()
    pair_pose, pair_point = pairs // n_pt, pairs % n_pt
    # every two pairs of one landmark: pairs sorted by landmark, each with all of its group
    order = np.argsort(pair_point, kind="stable")
    count = np.bincount(pair_point, minlength=n_pt)
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    m = count[pair_point[order]]
    a = np.repeat(order, m)
    offsets = np.arange(int(m.sum())) - np.repeat(np.cumsum(m) - m, m)
    b = order[np.repeat(first[pair_point[order]], m) + offsets]
    # both poses free; each two pairs once (the reduced system is symmetric: pose a <= pose b, the
    # blocks below the diagonal mirrored in _schur)
    free = (pair_pose[a] > 0) & (pair_pose[b] > 0) & (pair_pose[a] <= pair_pose[b])
    a, b = a[free], b[free]
    nf = n_pose - 1
    layout = _Layout(
        obs.pose_idx, obs.point_idx, n_pose, n_pt, pair_pose, pair_point,
        _summing(obs.pose_idx, n_pose), _summing(obs.point_idx, n_pt), _summing(of_obs, pairs.size),
        _summing(pair_pose - 1, max(nf, 0)), _summing(pair_point, n_pt), a, b,
        _summing((pair_pose[a] - 1) * nf + pair_pose[b] - 1, nf * nf),
        [np.flatnonzero(obs.pose_idx == i) for i in range(n_pose)],
        np.repeat(3 * obs.point_idx, 6) + np.tile(np.arange(3), 2 * obs.point_idx.size),
        np.ascontiguousarray(of_obs, np.int64), np.concatenate([[0], np.cumsum(count)]).astype(np.int64),
        np.ascontiguousarray(order, np.int64),
    )
    obs.__dict__["_layout_cache"] = layout
    return layout


@dataclass
class _Coupling:
    """The pose-landmark and calibration-landmark blocks of the normal equations.

    ``W`` (pairs x 6 x 3) of each (pose, landmark) pair, ``Y`` (landmarks x active x 3).
    """

    layout: _Layout
    W: F64
    Y: F64
    #: products and the elimination by the compiled kernels (:mod:`._rig_kernels`)
    compiled: bool = False


def _outer_sum(A: F64, B: F64) -> F64:
    """``A_n^T B_n`` of stacked blocks ``A`` (N x k x a), ``B`` (N x k x b): N x a x b."""
    return np.asarray(np.matmul(A.transpose(0, 2, 1), B))


def _outer_sum_t(A: F64, B: F64) -> F64:
    """``A_n B_n^T`` of stacked blocks ``A`` (N x a x k), ``B`` (N x b x k): N x a x b."""
    return np.asarray(np.matmul(A, B.transpose(0, 2, 1)))


def _times_3x3(A: F64, M: F64) -> F64:
    """``A_n M_n`` of stacked blocks ``A`` (N x a x 3) and ``M`` (N x 3 x 3)."""
    return np.asarray(np.matmul(A, M))


def _times_vec(M: F64, x: F64) -> F64:
    """``M_n x_n`` of 3x3 blocks ``M`` (N x 3 x 3) and a stacked vector ``x`` (3N): 3N."""
    return np.asarray(np.matmul(M, x.reshape(-1, 3, 1)).ravel())


def _flat(A: F64) -> F64:
    """Blocks ``A`` (N x a x 3) as one a x 3N matrix (the blocks side by side)."""
    return np.asarray(A.transpose(1, 0, 2).reshape(A.shape[1], 3 * A.shape[0]))


def _normal_equations(
    obs: RigObservations,
    st: _State,
    rig: RigParameters,
    prior_theta: F64,
    prior_sigma: F64,
    active: NDArray[np.bool_],
    sigma_px: float,
    huber_k: float,
    held_info: F64 | None = None,
) -> tuple[F64, F64, _Coupling, F64, F64, F64, float, F64]:
    """Whitened normal equations of the Huber-weighted problem.

    ``H_zz`` (poses but the first, then active parameters), ``b_z``, the pose/calibration-landmark
    coupling (:class:`_Coupling`), ``V`` (landmark 3x3 blocks), ``b_l``, the raw residuals, the
    robust cost and the normalised residual norms. ``held_info`` (16 x 16, in prior-whitened units)
    joins the prior's information: a stiff prior along held directions (:func:`held_directions`).
    Each observation touches one pose and one landmark: the blocks are summed per pose, landmark
    and pair (:class:`_Layout`), no sparse Jacobian is formed.
    """
    r, Jp, Jl, Jt = st.residuals(obs, rig)
    n_pose = st.R.shape[0]
    n_pt = st.pts.shape[0]
    lay = _layout(obs, n_pose, n_pt)
    nc = int(active.sum())
    npz = 6 * (n_pose - 1)
    N = npz + nc
    H = np.zeros((N, N))
    b = np.zeros(N)
    if st.compiled:
        from loopmodel.calibration import _rig_kernels

        W = np.zeros((lay.pair_pose.size, 6, 3))
        Y = np.zeros((n_pt, nc, 3))
        V = np.zeros((n_pt, 3, 3))
        bl = np.zeros((n_pt, 3))
        rn = np.zeros(len(obs))
        robust_cost = _rig_kernels.normal_equations(
            r, Jp, Jl, Jt, np.ascontiguousarray(lay.pose_idx, np.int64),
            np.ascontiguousarray(lay.point_idx, np.int64), lay.pair_of_obs, np.flatnonzero(active).astype(np.int64),
            float(sigma_px), float(huber_k), H, b, W, Y, V, bl, rn,
        )
    else:
        W, Y, V, bl, rn, robust_cost = _normal_equations_numpy(
            r, Jp, Jl, Jt, lay, active, sigma_px, huber_k, H, b, n_pose, n_pt
        )
    # priors on the active parameters
    ps = prior_sigma[active]
    dth = (st.theta - prior_theta)[active]
    H[npz:, npz:] += np.diag(1.0 / ps**2)
    b[npz:] -= dth / ps**2
    held_cost = 0.0
    if held_info is not None:
        E = held_info[np.ix_(active, active)]
        H[npz:, npz:] += E / np.outer(ps, ps)
        b[npz:] -= (E @ (dth / ps)) / ps
        held_cost = float((dth / ps) @ E @ (dth / ps))
    if obs.loops and npz:
        HL, gL, cL = loop_terms(st.R, st.t, obs)
        H[:npz, :npz] += HL[6:, 6:]  # the first pose is fixed
        b[:npz] -= gL[6:]
    else:
        cL = 0.0
    cost = robust_cost + float(np.sum((dth / ps) ** 2)) + cL + held_cost
    return H, b, _Coupling(lay, W, Y, st.compiled), V, bl.ravel(), r, cost, rn


def _normal_equations_numpy(
    r: F64,
    Jp: F64,
    Jl: F64,
    Jt: F64,
    lay: _Layout,
    active: NDArray[np.bool_],
    sigma_px: float,
    huber_k: float,
    H: F64,
    b: F64,
    n_pose: int,
    n_pt: int,
) -> tuple[F64, F64, F64, F64, F64, float]:
    """The observations' part of :func:`_normal_equations` by numpy, into ``H`` and ``b``.

    Returns ``W``, ``Y``, ``V``, ``bl``, the normalised residual norms and the robust cost.
    """
    rn = np.linalg.norm(r, axis=1) / sigma_px
    w = np.sqrt(_huber_weights(rn, huber_k)) / sigma_px
    rw = r * w[:, None]
    Jp = Jp * w[:, None, None]
    Jl = Jl * w[:, None, None]
    Jt = Jt[:, :, active] * w[:, None, None]
    n = r.shape[0]
    nc = int(active.sum())
    npz = 6 * (n_pose - 1)
    Jt2 = Jt.reshape(2 * n, nc)
    r2 = rw.ravel()
    if npz:
        for i in range(1, n_pose):
            sel = lay.by_pose[i]
            Ji = Jp[sel].reshape(-1, 6)
            o = 6 * (i - 1)
            H[o : o + 6, o : o + 6] = Ji.T @ Ji
            H[o : o + 6, npz:] = Ji.T @ Jt[sel].reshape(Ji.shape[0], nc)
            b[o : o + 6] = -(Ji.T @ rw[sel].ravel())
        H[npz:, :npz] = H[:npz, npz:].T
    H[npz:, npz:] = Jt2.T @ Jt2
    b[npz:] = -(Jt2.T @ r2)
    W = np.asarray(lay.of_pair @ _outer_sum(Jp, Jl).reshape(n, 18)).reshape(-1, 6, 3)
    Jl_sp = sp.csr_matrix((Jl.ravel(), lay.point_cols, np.arange(0, 6 * n + 1, 3)), shape=(2 * n, 3 * n_pt))
    Y = np.asarray(Jl_sp.T @ Jt2).reshape(n_pt, 3, nc).transpose(0, 2, 1)
    V = np.asarray(lay.of_point @ _outer_sum(Jl, Jl).reshape(n, 9)).reshape(n_pt, 3, 3)
    bl = -np.asarray(lay.of_point @ (Jl[:, 0] * rw[:, :1] + Jl[:, 1] * rw[:, 1:]))
    return W, Y, V, bl, rn, _huber_cost(rn, huber_k)


def _schur(H: F64, Hzl: _Coupling, V: F64, damping: float) -> tuple[F64, F64]:
    """The reduced system ``H - Hzl V^-1 Hlz`` and ``V^-1`` (both with LM damping on the diagonals).

    The pose blocks of ``Hzl V^-1 Hlz`` are summed over every two (pose, landmark) pairs of one
    landmark (:class:`_Layout`).
    """
    if Hzl.compiled:
        from loopmodel.calibration import _rig_kernels

        lay = Hzl.layout
        S = np.empty_like(H)
        Vinv = np.empty_like(V)
        ok = _rig_kernels.schur(H, Hzl.W, Hzl.Y, V, float(damping), lay.pair_pose, lay.lm_start, lay.lm_pairs, S, Vinv)
        if not ok:
            raise np.linalg.LinAlgError("a landmark's block of the calibrating bundle adjustment is singular")
        return S, Vinv
    Vd = V.copy()
    idx = np.arange(3)
    Vd[:, idx, idx] *= 1.0 + damping
    Vd[:, idx, idx] += 1e-12
    Vinv = np.asarray(np.linalg.inv(Vd), dtype=np.float64)
    lay, W, Y = Hzl.layout, Hzl.W, Hzl.Y
    nc = Y.shape[1]
    npz = 6 * (lay.n_pose - 1)
    S = H.copy()
    d = np.arange(S.shape[0])
    S[d, d] *= 1.0 + damping
    YV = _times_3x3(Y, Vinv)
    S[npz:, npz:] -= _flat(YV) @ _flat(Y).T
    if npz:
        WV = _times_3x3(W, Vinv[lay.pair_point])
        nf = lay.n_pose - 1
        Spp = np.asarray(lay.of_combo @ _outer_sum_t(WV[lay.combo_a], W[lay.combo_b]).reshape(-1, 36))
        upper = Spp.reshape(nf, nf, 6, 6).transpose(0, 2, 1, 3).reshape(npz, npz)  # blocks a <= b
        blk = np.arange(npz) // 6
        off = np.where(blk[:, None] < blk[None, :], upper, 0.0)  # above the diagonal blocks (those whole, symmetric)
        S[:npz, :npz] -= upper + off.T
        Spc = np.asarray(lay.pair_to_pose @ _outer_sum_t(WV, Y[lay.pair_point]).reshape(W.shape[0], 6 * nc))
        S[:npz, npz:] -= Spc.reshape(npz, nc)
        S[npz:, :npz] = S[:npz, npz:].T
    return S, Vinv


def _hzl_dot(Hzl: _Coupling, x: F64) -> F64:
    """``Hzl x`` for a landmark vector ``x`` (3L): the free poses' rows, then the calibration's."""
    lay = Hzl.layout
    xl = x.reshape(-1, 3)
    if Hzl.compiled:
        from loopmodel.calibration import _rig_kernels

        out = np.empty(6 * (lay.n_pose - 1) + Hzl.Y.shape[1])
        _rig_kernels.hzl_dot(Hzl.W, Hzl.Y, lay.pair_pose, lay.pair_point, np.ascontiguousarray(xl), out)
        return out
    top = np.asarray(lay.pair_to_pose @ np.matmul(Hzl.W, xl[lay.pair_point][:, :, None])[:, :, 0]).ravel()
    return np.concatenate([top, _flat(Hzl.Y) @ xl.ravel()])


def _hlz_dot(Hzl: _Coupling, y: F64) -> F64:
    """``Hlz y`` for a vector ``y`` of the free poses and the calibration: a landmark vector (3L)."""
    lay = Hzl.layout
    npz = 6 * (lay.n_pose - 1)
    if Hzl.compiled:
        from loopmodel.calibration import _rig_kernels

        res = np.empty((Hzl.Y.shape[0], 3))
        _rig_kernels.hlz_dot(Hzl.W, Hzl.Y, lay.pair_pose, lay.pair_point, np.ascontiguousarray(y, np.float64), res)
        return res.ravel()
    yp = np.concatenate([np.zeros(6), y[:npz]]).reshape(-1, 6)
    out = np.tensordot(Hzl.Y, y[npz:], axes=([1], [0]))
    out += np.asarray(lay.pair_to_point @ np.matmul(yp[lay.pair_pose][:, None, :], Hzl.W)[:, 0, :])
    return np.asarray(out.ravel(), dtype=np.float64)


def _apply(st: _State, dz: F64, dl: F64, active: NDArray[np.bool_]) -> _State:
    n_pose = st.R.shape[0]
    npz = 6 * (n_pose - 1)
    d = dz[:npz].reshape(-1, 6)
    R = st.R.copy()
    t = st.t.copy()
    for i in range(1, n_pose):
        w, v = d[i - 1, :3], d[i - 1, 3:]
        t[i] = t[i] + st.R[i] @ v
        R[i] = st.R[i] @ so3_exp(w)
    theta = st.theta.copy()
    theta[active] += dz[npz:]
    return _State(R, t, st.pts + dl.reshape(-1, 3), theta, st.compiled)


def _solve(
    obs: RigObservations,
    st: _State,
    rig: RigParameters,
    prior_theta: F64,
    prior_sigma: F64,
    active: NDArray[np.bool_],
    sigma_px: float,
    huber_k: float,
    max_iterations: int,
    held_info: F64 | None = None,
    rough_sigma: float = 0.0,
) -> tuple[_State, int]:
    """Levenberg-Marquardt from ``st``; returns the solution and the iterations taken.

    It stops when the cost falls by less than :data:`MIN_REL` (relative), or once a step moved no
    parameter by :data:`STEP_TOL_SIGMA` of its prior and the cost by less than :data:`STEP_TOL_REL`;
    with ``rough_sigma`` > 0 already once a step moved no parameter by that share of its prior (a
    start for a later solve, not a solution).
    """
    lam = 1e-4
    H, b, Hzl, V, bl, _r, cost, _ = _normal_equations(
        obs, st, rig, prior_theta, prior_sigma, active, sigma_px, huber_k, held_info
    )
    it = 0
    nc = int(active.sum())
    npz = 6 * (st.R.shape[0] - 1)
    for _ in range(max_iterations):
        it += 1
        improved = False
        step_sigma = np.inf
        for _ in range(8):
            S, Vinv = _schur(H, Hzl, V, lam)
            rhs = b - _hzl_dot(Hzl, _times_vec(Vinv, bl))
            try:
                dz = scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), rhs)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            dl = _times_vec(Vinv, bl - _hlz_dot(Hzl, dz))
            cand = _apply(st, dz, dl, active)
            H2, b2, Hzl2, V2, bl2, _r2, cost2, _ = _normal_equations(
                obs, cand, rig, prior_theta, prior_sigma, active, sigma_px, huber_k, held_info
            )
            if cost2 < cost:
                rel = (cost - cost2) / max(cost, 1e-300)
                st, H, b, Hzl, V, bl, cost = cand, H2, b2, Hzl2, V2, bl2, cost2
                lam = max(lam / 10.0, 1e-9)
                improved = True
                step_sigma = float(np.max(np.abs(dz[npz:]) / prior_sigma[active])) if nc else 0.0
                break
            lam *= 10.0
        # the Huber weights make the tail converge linearly (ratio 0.6-0.9 per step): stop once a
        # step moves no parameter by STEP_TOL_SIGMA of its prior and the cost by STEP_TOL_REL (the
        # posterior does not need more: _posterior_sigma takes the remaining step in its linearization)
        if not improved or rel < MIN_REL or (rel < STEP_TOL_REL and step_sigma < STEP_TOL_SIGMA):
            break
        if step_sigma < rough_sigma:
            break
    return st, it


def _posterior_sigma(
    obs: RigObservations,
    st: _State,
    rig: RigParameters,
    prior_theta: F64,
    prior_sigma: F64,
    active: NDArray[np.bool_],
    sigma_px: float,
    huber_k: float,
    consider: NDArray[np.bool_] | None = None,
    held_info: F64 | None = None,
    sandwich: bool = True,
) -> tuple[F64, F64, F64, F64]:
    """Posterior std. devs. of the active parameters: the model's, track-robust, the held ones' variance.

    And the reduced system of the free poses and the active parameters it inverted. Without
    ``sandwich`` the model's alone (the other two zero).

    The model's: the inverse of the reduced system (independent pixel errors of ``sigma_px``). The
    track-robust one: the sandwich ``S^-1 (sum_l g_l g_l^T + prior + loops) S^-1`` with one cluster
    per landmark (``g_l`` the whitened gradient of the poses and parameters from the landmark's
    observations), which admits any correlation of a track's errors (KLT follows a feature from
    frame to frame: its errors in successive keyframes are not independent), scaled by the
    redundancy ``n / (n - unknowns)``. The variance the held (``consider``) parameters add
    (Schmidt's consider covariance): held at a wrong recorded value, their error goes into the
    estimated ones by ``-S^-1 S_h``, so ``(X^T S_h) diag(sigma_h^2) (X^T S_h)^T`` joins.
    """
    nc = int(active.sum())
    if nc == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0), np.zeros((0, 0))
    held = np.zeros_like(active) if consider is None else (np.asarray(consider, bool) & ~active)
    both = active | held
    H, b, Hzl, V, bl, _r, _c, _ = _normal_equations(
        obs, st, rig, prior_theta, prior_sigma, both, sigma_px, huber_k, held_info
    )
    S_all, Vinv = _schur(H, Hzl, V, 0.0)
    npz0 = S_all.shape[0] - int(both.sum())
    keep = np.concatenate([np.ones(npz0, bool), active[both]])
    S = S_all[np.ix_(keep, keep)]
    S_h = S_all[np.ix_(keep, ~keep)]
    N = S.shape[0]
    E = np.zeros((N, nc))
    E[N - nc :, :] = np.eye(nc)
    cf = scipy.linalg.cho_factor(S)
    X = scipy.linalg.cho_solve(cf, E)  # S^-1 E: N x nc
    model = np.sqrt(np.maximum(np.diag(X[N - nc :, :]), 0.0))
    if not sandwich:
        return model, np.zeros(nc), np.zeros(nc), S
    # per-observation whitened gradients, projected on X, summed per landmark
    r, Jp, Jl, Jt = st.residuals(obs, rig)
    w = _huber_weights(np.linalg.norm(r, axis=1) / sigma_px, huber_k) / sigma_px**2
    npz = N - nc
    # the residuals one Gauss-Newton step (these weights) further: the Huber tail converges
    # linearly, and a solution stopped in it would add its remaining gradient to every landmark's
    # share (test_selfcal's right-rows scene, rel. stop 1e-5: robust sigma 1.18 instead of 0.86)
    dz = np.zeros(S_all.shape[0])
    dz[keep] = scipy.linalg.cho_solve(cf, (b - _hzl_dot(Hzl, _times_vec(Vinv, bl)))[keep])
    dl = _times_vec(Vinv, bl - _hlz_dot(Hzl, dz)).reshape(-1, 3)
    r = r + np.einsum("nkc,c->nk", Jt[:, :, both], dz[npz:]) + np.einsum("nkj,nj->nk", Jl, dl[obs.point_idx])
    if npz:
        dp = np.concatenate([np.zeros(6), dz[:npz]]).reshape(-1, 6)
        r = r + np.einsum("nki,ni->nk", Jp, dp[obs.pose_idx])
    proj = np.einsum("nkc,cj->nkj", Jt[:, :, active], X[npz:, :])  # N_obs x 2 x nc
    pm = obs.pose_idx > 0
    if npz:
        Xp = X[:npz, :].reshape(-1, 6, nc)
        proj[pm] += np.einsum("nki,nij->nkj", Jp[pm], Xp[obs.pose_idx[pm] - 1])
    score = np.einsum("nkj,nk->nj", proj, w[:, None] * r)  # each observation's share of X^T g
    per_lm = np.zeros((st.pts.shape[0], nc))
    np.add.at(per_lm, obs.point_idx, score)
    meat = per_lm.T @ per_lm
    Xc = X[npz:, :]
    ps = prior_sigma[active]
    meat += Xc.T @ (Xc / ps[:, None] ** 2)  # the prior, a measurement of its own
    if held_info is not None:
        meat += Xc.T @ (held_info[np.ix_(active, active)] / np.outer(ps, ps)) @ Xc
    if obs.loops and npz:
        HL, _g, _cL = loop_terms(st.R, st.t, obs)
        Xp2 = X[:npz, :]
        meat += Xp2.T @ HL[6:, 6:] @ Xp2
    n_res = obs.residual_count
    unknowns = npz + 3 * st.pts.shape[0] + nc
    if n_res > unknowns:
        meat *= n_res / (n_res - unknowns)
    robust = np.sqrt(np.maximum(np.diag(meat), 0.0))
    Mh = X.T @ S_h  # nc x held
    consider_var = np.sum(Mh**2 * (prior_sigma[held] ** 2)[None, :], axis=1)
    return model, robust, consider_var, S


#: prior-whitened sigma of a held direction's stiff prior (holds it at the recorded values)
_HELD_SIGMA = 1e-3
#: Levenberg-Marquardt stops when an accepted step moved no active parameter by more than this
#: share of its prior sigma and lowered the cost by less than STEP_TOL_REL (relative)
STEP_TOL_SIGMA = 0.01
STEP_TOL_REL = 1e-4
#: ... or by less than this, whatever the step
MIN_REL = 1e-5
#: the rough solves stop once a step moved no active parameter by this share of its prior sigma:
#: the noise and the observability judged there (the last solve converges from it; calib7, the KITTI
#: clip: parameters within 0.005 prior sigma, pixel sigma 0.19904 -> 0.19951 px of two full rounds)
ROUGH_STEP_SIGMA = 0.05
#: the noise is re-estimated after each rough solve until it changes by less than this (relative),
#: at most SIGMA_ROUNDS times (the 150-frame realistic orbit: 0.169 -> 0.0944 -> 0.0915 -> 0.0914 px)
SIGMA_REL_TOL = 0.01
SIGMA_ROUNDS = 4


def _reduced_system(
    obs: RigObservations,
    st: _State,
    rig: RigParameters,
    prior_theta: F64,
    prior_sigma: F64,
    active: NDArray[np.bool_],
    sigma_px: float,
    huber_k: float,
) -> F64:
    """The reduced system (poses but the first, then the active parameters; landmarks eliminated)."""
    H, _b, Hzl, V, _bl, _r, _c, _ = _normal_equations(obs, st, rig, prior_theta, prior_sigma, active, sigma_px, huber_k)
    return _schur(H, Hzl, V, 0.0)[0]


def calibration_covariance(S: F64, nc: int) -> F64:
    """The last ``nc`` x ``nc`` block of ``S^-1`` (the calibration's covariance; ``S`` symmetric positive definite).

    By a Cholesky solve for the last ``nc`` columns, not the whole inverse (fin17: 6P x 6P with 349
    keyframes, 0.7 s CPU an inverse); by the inverse when ``S`` is not numerically positive definite.
    """
    N = S.shape[0]
    E = np.zeros((N, nc))
    E[N - nc :, :] = np.eye(nc)
    try:
        return np.asarray(scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), E)[N - nc :, :], dtype=np.float64)
    except np.linalg.LinAlgError:
        return np.asarray(np.linalg.inv(S)[-nc:, -nc:], dtype=np.float64)


def posterior_directions(S: F64, prior_sigma_active: F64) -> tuple[F64, F64]:
    """Posterior over prior standard deviation along the principal directions of the calibration.

    ``S`` the reduced system (the calibration last), ``prior_sigma_active`` the active parameters'
    prior sigmas. Returns the ratios (ascending) and the directions (columns, in prior-whitened
    units of the active parameters): a ratio near 1 is a combination the data hardly inform. A
    common vertical principal point of both cameras, for one, is nearly a rotation of the rig about
    x, which the free keyframe poses absorb: a per-parameter ratio does not see it.
    """
    C = calibration_covariance(S, prior_sigma_active.size)
    Cw = C / np.outer(prior_sigma_active, prior_sigma_active)
    lam, U = np.linalg.eigh(0.5 * (Cw + Cw.T))
    return np.sqrt(np.maximum(lam, 0.0)), U


def _held_direction_variance(S: F64, nc: int, prior_sigma_active: F64, U_o: F64, U_h: F64) -> F64:
    """Per active parameter, the variance that holding the directions ``U_h`` at their prior adds.

    Schmidt's consider covariance in the rotated coordinates ``[U_o U_h]`` (prior-whitened): held at
    the recorded value, a direction keeps its prior error (variance 1) and passes it into the
    estimated ones by ``-S_oo^-1 S_oh``; the parameters' extra covariance is
    ``D (U_h - U_o G) (U_h - U_o G)^T D`` with ``G`` those rows.
    """
    npz = S.shape[0] - nc
    W = np.concatenate([U_o, U_h], axis=1) * prior_sigma_active[:, None]  # parameter = W z
    # T^T S T with T = diag(I, W): only the calibration's rows and columns change (fin17: not two dense
    # products of the whole system, 0.7 s CPU with 349 keyframes)
    Sz = S.copy()
    Sz[:npz, npz:] = S[:npz, npz:] @ W
    Sz[npz:, :npz] = Sz[:npz, npz:].T
    Sz[npz:, npz:] = W.T @ S[npz:, npz:] @ W
    no = npz + U_o.shape[1]
    G = np.linalg.solve(Sz[:no, :no], Sz[:no, no:])[npz:, :]
    A = (U_h - U_o @ G) * prior_sigma_active[:, None]
    return np.asarray(np.sum(A**2, axis=1), dtype=np.float64)


#: the principal-point pairs (left, right) whose common move rotates the output frame
_PRINCIPAL_PAIRS = (("cx_left_px", "cx_right_px"), ("cy_left_px", "cy_right_px"))
#: a common principal point counts as held when this share of it (squared projection) lies in the held directions
ANCHOR_MIN_SHARE = 0.5


def anchored_held_directions(U_h: F64, names: list[str]) -> tuple[F64, F64, list[str]]:
    """The held directions with a held common principal point pinned on the left camera instead.

    A common principal-point shift of both cameras is nearly a rotation of every pose (the data do
    not tell them apart, so it is held). Held as the sum of both (the prior-whitened eigenvector),
    a determined left-right difference is split between the cameras by their priors, and the left
    camera's share turns the reported camera frame, and the whole trajectory with it, by
    ``share / f``. Pinning the left (reference) camera's principal point instead holds the same
    unobservable combination while the right camera carries the difference, the frame staying the
    recorded one. ``U_h`` (active x h, orthonormal, prior-whitened) and the active parameters'
    ``names``; returns the new held directions, their orthonormal complement (the directions
    estimated) and the left parameters pinned.
    """
    n = U_h.shape[0]
    pinned: list[str] = []
    H = U_h.copy()
    for left, right in _PRINCIPAL_PAIRS:
        if left not in names or right not in names or H.shape[1] == 0:
            continue
        c = np.zeros(n)
        c[names.index(left)] = c[names.index(right)] = np.sqrt(0.5)
        a = H.T @ c  # the common shift in held coordinates
        held_left = H[names.index(left)]  # the left coordinate in held coordinates
        if float(a @ a) < ANCHOR_MIN_SHARE or float(held_left @ held_left) > 1.0 - 1e-9:
            continue  # not held, or held through the left camera already
        # the held vector nearest the common shift, replaced by the left camera's own coordinate
        h = H @ (a / np.linalg.norm(a))
        rest = H - np.outer(h, h @ H)
        u, sv, _ = np.linalg.svd(rest, full_matrices=False)
        kept = u[:, sv > 1e-9]
        e = np.zeros(n)
        e[names.index(left)] = 1.0
        e -= kept @ (kept.T @ e)
        H = np.column_stack([kept, e / np.linalg.norm(e)])
        pinned.append(left)
    if not pinned:
        return U_h, _complement(U_h), pinned
    return H, _complement(H), pinned


def _complement(H: F64) -> F64:
    """An orthonormal basis of the directions orthogonal to the orthonormal columns of ``H``."""
    q, _ = np.linalg.qr(np.column_stack([H, np.eye(H.shape[0])]))
    return q[:, H.shape[1] : H.shape[0]]


def robust_sigma_px(r: F64, unknowns: int, obs: RigObservations | None = None) -> float:
    """Pixel noise of residuals (N x 2): 1.4826 MAD of the measured components, corrected for the redundancy."""
    comp = np.abs(r).ravel()
    if obs is not None:
        comp = np.concatenate([np.abs(r[:, 0]), np.abs(r[obs.row_measured, 1])])
    n = comp.size
    mad = 1.4826 * float(np.median(comp)) if n else float("nan")
    red = n - unknowns
    return mad * float(np.sqrt(n / red)) if red > 0 else mad


def huber_sigma_px(r: F64, unknowns: int, obs: RigObservations, huber_k: float, start_px: float) -> float:
    """Pixel noise as the Huber-weighted residuals give it: ``sigma^2 = sum w r^2 / (n - u)``.

    ``w`` the Huber weights at ``huber_k`` sigmas, iterated from ``start_px`` (the MAD's value). Real
    image residuals have heavier tails than a Gaussian, which the MAD alone leaves out: the
    posterior would be too confident.
    """
    rn2 = np.sum(r**2, axis=1)
    red = obs.residual_count - unknowns
    if red <= 0:
        return start_px
    sigma = start_px
    for _ in range(10):
        w = _huber_weights(np.sqrt(rn2) / sigma, huber_k)
        new = float(np.sqrt(np.sum(w * rn2) / red))
        if abs(new - sigma) < 1e-4 * sigma:
            return new
        sigma = new
    return sigma


def _rms(r: F64, obs: RigObservations) -> float:
    n = obs.residual_count
    return float(np.sqrt(np.sum(r**2) / n)) if n else float("nan")


_BLAS_THREAD_SYMBOLS = (
    ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
    ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
    ("openblas_get_num_threads", "openblas_set_num_threads"),
)


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """OpenBLAS (numpy's and scipy's, as loaded) on one thread inside the block, restored after.

    The refinement's dense systems are small (a few hundred unknowns): a 145 x 145 Cholesky took
    0.9 ms on one thread and 18-215 ms on OpenBLAS's default two at load 10-20 on the 2-core machine
    (the threads spin for each other; calib5). No-op where the libraries or ``/proc`` are not found.
    """
    libs = []
    with contextlib.suppress(OSError):
        with open("/proc/self/maps") as f:
            paths = sorted({ln.split()[-1] for ln in f if "openblas" in ln.lower() and ln.rstrip().endswith(".so")})
        for path in paths:
            lib = ctypes.CDLL(path)
            for get, put in _BLAS_THREAD_SYMBOLS:
                if hasattr(lib, get) and hasattr(lib, put):
                    libs.append((getattr(lib, get), getattr(lib, put)))
                    break
    before = [int(get()) for get, _put in libs]
    try:
        for _get, put in libs:
            put(ctypes.c_int(1))
        yield
    finally:
        for (_get, put), n in zip(libs, before, strict=True):
            put(ctypes.c_int(n))


def refine_rig(
    obs: RigObservations,
    world_from_cam: F64,
    points_w: F64,
    recorded: StereoCalibration,
    prior_sigma: F64,
    estimate: NDArray[np.bool_] | None = None,
    observable_ratio: float = 0.9,
    huber_k: float = 1.345,
    max_iterations: int = 15,
    track_robust: bool = True,
    consider: NDArray[np.bool_] | None = None,
    observable_direction_ratio: float = 1.0,
    start_values: F64 | None = None,
    anchor_principal_point: bool = False,
    compiled: bool = True,
) -> tuple[F64, F64, RigRefinement]:
    """Bundle adjustment of poses, landmarks and the rig calibration; see the module docstring.

    ``world_from_cam`` (P x 4 x 4, the first held fixed), ``points_w`` (L x 3) start values;
    ``prior_sigma`` in the order of :data:`PARAM_NAMES`; ``estimate`` which parameters are
    unknowns (default: all but k2). A combination of the parameters whose posterior sigma stays
    above ``observable_direction_ratio`` of its prior (:func:`posterior_directions`; 1: none) is
    held at its recorded value and reported unobservable (``unobservable_directions``), its prior
    variance passed on to the others' sigmas. Returns the refined poses, points and the report (its
    ``world_from_kf`` and ``landmark_ids`` are left empty for the caller to fill). ``start_values``:
    the calibration to start from (the order of :data:`PARAM_NAMES`, e.g. the online estimate; the
    priors stay at the recorded values). ``anchor_principal_point``: a held common principal point is
    held through the left camera's (:func:`anchored_held_directions`). The dense algebra runs on one
    BLAS thread (:func:`one_blas_thread`). ``compiled``: the residuals, Jacobians, normal equations and
    the landmarks' elimination by the compiled kernels (:mod:`._rig_kernels`), else by numpy (the same
    values but for the order of the sums; fin12).
    """
    with one_blas_thread():
        return _refine_rig(
            obs, world_from_cam, points_w, recorded, prior_sigma, estimate, observable_ratio, huber_k,
            max_iterations, track_robust, consider, observable_direction_ratio, start_values,
            anchor_principal_point, compiled,
        )


def _refine_rig(
    obs: RigObservations,
    world_from_cam: F64,
    points_w: F64,
    recorded: StereoCalibration,
    prior_sigma: F64,
    estimate: NDArray[np.bool_] | None,
    observable_ratio: float,
    huber_k: float,
    max_iterations: int,
    track_robust: bool,
    consider: NDArray[np.bool_] | None,
    observable_direction_ratio: float,
    start_values: F64 | None = None,
    anchor_principal_point: bool = False,
    compiled: bool = True,
) -> tuple[F64, F64, RigRefinement]:
    rig = RigParameters.of(recorded)
    prior_theta = rig.values.copy()
    active = np.ones(N_PARAMS, bool) if estimate is None else np.asarray(estimate, bool).copy()
    if estimate is None:
        active[[5, 11]] = False
    start = prior_theta.copy()
    if start_values is not None:  # a warm start (the online estimate)
        start = np.where(active, np.asarray(start_values, float), prior_theta)
    st = _State(
        world_from_cam[:, :3, :3].copy(), world_from_cam[:, :3, 3].copy(), np.asarray(points_w, float).copy(), start,
        compiled,
    )
    unknowns = 6 * (st.R.shape[0] - 1) + 3 * st.pts.shape[0]
    r0 = st.residuals(obs, rig)[0]
    rms0 = _rms(r0, obs)
    sigma = max(robust_sigma_px(r0, unknowns, obs), 1e-3)
    # rough solutions, each with the noise re-estimated from the last one's residuals (the Huber
    # weights move the solution, the solution the noise) until the noise changes by less than
    # SIGMA_REL_TOL; the observability is judged there and the last solve below converges from it
    iterations = 0
    u = unknowns + int(active.sum())
    for _round in range(SIGMA_ROUNDS):
        st, it = _solve(
            obs, st, rig, prior_theta, prior_sigma, active, sigma, huber_k, max_iterations,
            rough_sigma=ROUGH_STEP_SIGMA,
        )
        iterations += it
        r = st.residuals(obs, rig)[0]
        new = max(huber_sigma_px(r, u, obs, huber_k, max(robust_sigma_px(r, u, obs), 1e-3)), 1e-3)
        settled = abs(new - sigma) < SIGMA_REL_TOL * sigma
        sigma = new
        if settled:
            break
    post = np.array(prior_sigma, float).copy()
    S = _reduced_system(obs, st, rig, prior_theta, prior_sigma, active, sigma, huber_k)
    nc = int(active.sum())
    if nc:
        post[active] = np.sqrt(np.maximum(np.diag(calibration_covariance(S, nc)), 0.0))
    weak = active & (post > observable_ratio * prior_sigma)
    blind = active & (post > HOLD_RATIO * prior_sigma)
    if np.any(blind):
        # not informed at all (the baseline without the laser): back to the recorded value, held
        # there (the rest is solved below). Weakly informed ones stay in the joint estimate: held at
        # a wrong recorded value, their error would go into the parameters the data do constrain
        # (a 20-keyframe synthetic scan: k1_right 24 sigma off)
        theta = st.theta.copy()
        theta[blind] = prior_theta[blind]
        st = _State(st.R, st.t, st.pts, theta, st.compiled)
        keep = np.concatenate([np.ones(S.shape[0] - nc, bool), ~blind[active]])
        S = S[np.ix_(keep, keep)]  # held: conditioned on, its rows out of the information
        active = active & ~blind
    held_info, U_h, U_o, directions = None, None, None, []
    anchored: list[str] = []
    whitened, Uh16 = np.zeros((0, 0)), np.zeros((N_PARAMS, 0))
    if np.any(active):
        ps_a = prior_sigma[active]
        ratios, U = posterior_directions(S, ps_a)
        whitened = (U * ratios**2) @ U.T
        names_a = [PARAM_NAMES[i] for i in np.flatnonzero(active)]
        hold = ratios > observable_direction_ratio
        for k in np.flatnonzero(hold):
            top = np.argsort(-np.abs(U[:, k]))
            directions.append({"ratio": float(ratios[k]), **{names_a[i]: round(float(U[i, k]), 3) for i in top[:4]}})
        if np.any(hold):
            # held at the recorded values: the move along them taken out, a stiff prior keeps them there
            U_h, U_o = U[:, hold], U[:, ~hold]
            if anchor_principal_point:  # a held common principal point pinned on the left camera
                U_h, U_o, anchored = anchored_held_directions(U_h, names_a)
            Uh16 = np.zeros((N_PARAMS, U_h.shape[1]))
            Uh16[active] = U_h
            held_info = Uh16 @ Uh16.T / _HELD_SIGMA**2
    # the solution: no projection of the start onto the held directions (the stiff prior is
    # quadratic, so the first step takes the move along them out with the poses and landmarks
    # following it)
    st, it = _solve(obs, st, rig, prior_theta, prior_sigma, active, sigma, huber_k, max_iterations, held_info)
    iterations += it
    post = np.array(prior_sigma, float).copy()
    robust = post.copy()
    consider_var = np.zeros_like(post)
    if np.any(active):
        held = ~active if consider is None else np.asarray(consider, bool)  # default: every held parameter
        post[active], robust[active], consider_var[active], S = _posterior_sigma(
            obs, st, rig, prior_theta, prior_sigma, active, sigma, huber_k, held if track_robust else None,
            held_info,
        )
        if U_h is not None and U_o is not None and held_info is not None:
            nc, ps_a = int(active.sum()), prior_sigma[active]
            S[-nc:, -nc:] -= held_info[np.ix_(active, active)] / np.outer(ps_a, ps_a)  # without the stiff prior
            consider_var[active] += _held_direction_variance(S, nc, ps_a, U_o, U_h)
    honest = np.where(active, np.sqrt(np.maximum(post, robust) ** 2 + consider_var), post)
    r = st.residuals(obs, rig)[0]
    poses = np.tile(np.eye(4), (st.R.shape[0], 1, 1))
    poses[:, :3, :3], poses[:, :3, 3] = st.R, st.t
    report = RigRefinement(
        world_from_kf={},
        landmark_ids=np.zeros(0, np.int64),
        landmarks_in_world=st.pts,
        calibration=rig.calibration(st.theta),
        recorded_values=prior_theta,
        values=st.theta.copy(),
        prior_sigma=np.asarray(prior_sigma, float),
        posterior_sigma=honest if track_robust else post,
        posterior_sigma_model=post,
        posterior_sigma_robust=robust,
        posterior_sigma_consider=np.sqrt(consider_var),
        estimated=active,
        unobservable=[PARAM_NAMES[i] for i in np.flatnonzero(weak)],
        pixel_sigma_px=float(sigma),
        observations=len(obs),
        iterations=iterations,
        rms_px_before=rms0,
        rms_px_after=_rms(r, obs),
        unobservable_directions=directions,
        whitened_posterior=whitened,
        held_directions=Uh16,
        anchored=anchored,
    )
    return poses, st.pts, report


__all__ = [
    "PARAM_NAMES",
    "RigObservations",
    "RigParameters",
    "RigRefinement",
    "anchored_held_directions",
    "observations_from_keyframes",
    "posterior_directions",
    "prior_sigmas",
    "project_with_jacobians",
    "raw_from_rectified_px",
    "refine_rig",
    "residuals_and_jacobians",
]
