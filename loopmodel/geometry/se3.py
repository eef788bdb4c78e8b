"""SO(3)/SE(3) helpers on 4x4 homogeneous matrices.

Conventions: a pose ``a_from_b`` maps points in frame b to frame a; twists are ordered
translation first, ``xi = (v_x, v_y, v_z, w_x, w_y, w_z)`` (as in visual servoing), and
``se3_exp`` is the exact exponential of SE(3). Quaternions are ``(w, x, y, z)``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


def hat(w: ArrayLike) -> F64:
    """Skew-symmetric matrix [w]x with [w]x v = w x v."""
    x, y, z = np.asarray(w, dtype=float).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def cross_rows(a: F64, b: F64) -> F64:
    """Cross products along the last axis of broadcast (..., 3) arrays (cheaper than ``np.cross`` for small arrays)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def so3_exp(w: ArrayLike) -> F64:
    """Rotation matrix of the rotation vector w (axis times angle, radians)."""
    w = np.asarray(w, dtype=float).reshape(3)
    theta2 = float(w @ w)
    K = hat(w)
    if theta2 < 1e-16:
        return np.eye(3) + K + 0.5 * (K @ K)
    theta = np.sqrt(theta2)
    return np.eye(3) + (np.sin(theta) / theta) * K + ((1.0 - np.cos(theta)) / theta2) * (K @ K)


def so3_log(R: ArrayLike) -> F64:
    """Rotation vector (radians) of a rotation matrix; exact near 0 and near pi."""
    R = np.asarray(R, dtype=float)
    cos_theta = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos_theta))
    vee = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-7:
        return 0.5 * vee
    if np.pi - theta < 1e-4:
        # Near pi: axis from the symmetric part, sign from the antisymmetric part.
        B = (R + R.T) / 2.0 - cos_theta * np.eye(3)
        k = int(np.argmax(np.diag(B)))
        axis = B[:, k] / np.sqrt(max(B[k, k], 1e-300))
        if axis @ vee < 0:
            axis = -axis
        return theta * axis / np.linalg.norm(axis)
    return theta / (2.0 * np.sin(theta)) * vee


def so3_log_rows(R: F64) -> F64:
    """:func:`so3_log` of each of N rotation matrices (N x 3 x 3 -> N x 3, radians)."""
    cos_theta = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos_theta)
    vee = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    small = theta < 1e-7
    scale = np.where(small, 0.5, theta / (2.0 * np.sin(np.where(small, 1.0, theta))))
    out = scale[:, None] * vee
    for i in np.flatnonzero(np.pi - theta < 1e-4):  # near pi: the axis from the symmetric part
        out[i] = so3_log(R[i])
    return np.asarray(out, dtype=np.float64)


def _left_jacobian_so3(w: F64) -> F64:
    theta2 = float(w @ w)
    K = hat(w)
    if theta2 < 1e-12:
        return np.eye(3) + 0.5 * K + (K @ K) / 6.0
    theta = np.sqrt(theta2)
    return np.eye(3) + ((1.0 - np.cos(theta)) / theta2) * K + ((theta - np.sin(theta)) / (theta2 * theta)) * (K @ K)


def se3_exp(xi: ArrayLike) -> F64:
    """4x4 pose of the twist ``xi = (v, w)`` (metres, radians)."""
    xi = np.asarray(xi, dtype=float).reshape(6)
    T = np.eye(4)
    T[:3, :3] = so3_exp(xi[3:])
    T[:3, 3] = _left_jacobian_so3(xi[3:]) @ xi[:3]
    return T


def se3_log(T: ArrayLike) -> F64:
    """Twist ``(v, w)`` of a 4x4 pose, inverse of :func:`se3_exp`."""
    T = np.asarray(T, dtype=float)
    w = so3_log(T[:3, :3])
    v = np.linalg.solve(_left_jacobian_so3(w), T[:3, 3])
    return np.concatenate([v, w])


def nearest_rigid(T: ArrayLike) -> F64:
    """The rigid transform nearest to a 4x4 matrix whose rotation block drifted from SO(3).

    Drift from rounding in long products of poses; rotation projected by SVD, translation kept.
    """
    T = np.asarray(T, dtype=float)
    U, _s, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return make_pose(R, T[:3, 3])


def make_pose(R: ArrayLike, t: ArrayLike) -> F64:
    """4x4 pose from a 3x3 rotation and a translation (metres)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert_pose(T: ArrayLike) -> F64:
    """Inverse of a 4x4 rigid transform (``b_from_a`` from ``a_from_b``); batches allowed."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def rotation_from_quat_wxyz(q: ArrayLike) -> F64:
    """Rotation matrix (or a batch) of unit quaternions ordered (w, x, y, z)."""
    qa = np.asarray(q, dtype=float)
    qa = qa / np.linalg.norm(qa, axis=-1, keepdims=True)
    w, x, y, z = qa[..., 0], qa[..., 1], qa[..., 2], qa[..., 3]
    R = np.empty(qa.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def quat_wxyz_from_rotation(R: ArrayLike) -> F64:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix or a batch of them."""
    R = np.asarray(R, dtype=float)
    batch = R.reshape(-1, 3, 3)
    out = np.empty((batch.shape[0], 4))
    for k, m in enumerate(batch):
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        if tr > 0:
            s = np.sqrt(tr + 1.0) * 2
            q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
            q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif m[1, 1] > m[2, 2]:
            s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
            q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        else:
            s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
            q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
        qa = np.asarray(q)
        qa /= np.linalg.norm(qa)
        out[k] = -qa if qa[0] < 0 else qa
    return out.reshape(R.shape[:-2] + (4,))


def interpolate_pose(a_from_b0: ArrayLike, a_from_b1: ArrayLike, alpha: float) -> F64:
    """Pose at fraction ``alpha`` in [0, 1] between two poses.

    Rotation along the geodesic of SO(3), translation linear. Returns an exact SE(3) element.
    """
    T0 = np.asarray(a_from_b0, dtype=float)
    T1 = np.asarray(a_from_b1, dtype=float)
    R0 = T0[:3, :3]
    dR = so3_exp(alpha * so3_log(R0.T @ T1[:3, :3]))
    return make_pose(R0 @ dR, (1.0 - alpha) * T0[:3, 3] + alpha * T1[:3, 3])


_EYE3 = np.eye(3)


def is_rotation(R: ArrayLike, tol: float = 1e-6) -> bool:
    """True when R is a proper rotation (orthonormal, det +1) within ``tol``."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        return False
    # np.allclose(R.T @ R, I, atol=tol) (its rtol 1e-5 on the diagonal's ones) in one pass: a tenth of
    # its time, checked every tracked frame (AnchoredTrajectory.add_frame; cpu15)
    off = np.abs(R.T @ R - _EYE3) - _EYE3 * 1e-5
    return bool(off.max() <= tol and abs(np.linalg.det(R) - 1) < tol)


def interpolate_poses(a_from_b0: ArrayLike, a_from_b1: ArrayLike, alpha: ArrayLike) -> F64:
    """Vectorised :func:`interpolate_pose` for N pose pairs (N x 4 x 4 each) and N fractions.

    Rotation along the SO(3) geodesic, translation linear. Returns N x 4 x 4 poses.
    """
    from scipy.spatial.transform import Rotation

    T0 = np.asarray(a_from_b0, dtype=float).reshape(-1, 4, 4)
    T1 = np.asarray(a_from_b1, dtype=float).reshape(-1, 4, 4)
    a = np.asarray(alpha, dtype=float).reshape(-1)
    R0 = T0[:, :3, :3]
    R_rel = np.einsum("nji,njk->nik", R0, T1[:, :3, :3])
    rotvec = Rotation.from_matrix(R_rel).as_rotvec()
    dR = Rotation.from_rotvec(rotvec * a[:, None]).as_matrix()
    out = np.zeros((T0.shape[0], 4, 4))
    out[:, :3, :3] = np.einsum("nij,njk->nik", R0, dR)
    out[:, :3, 3] = (1.0 - a)[:, None] * T0[:, :3, 3] + a[:, None] * T1[:, :3, 3]
    out[:, 3, 3] = 1.0
    return out


#: ``up_world`` of worlds whose y axis points down like a camera's (image y along world +y)
Y_DOWN_UP = np.array([0.0, -1.0, 0.0])


def look_at(position_world: ArrayLike, target_world: ArrayLike, up_world: ArrayLike | None = None) -> F64:
    """``world_from_cam`` of a camera at ``position_world`` looking at ``target_world`` (metres).

    Z towards the target, image y down, i.e. against ``up_world`` (default +z).
    """
    up = np.array([0.0, 0.0, 1.0]) if up_world is None else np.asarray(up_world, float)
    z = np.asarray(target_world, float) - np.asarray(position_world, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise ValueError("look_at: viewing direction parallel to up")
    x /= nx
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = np.asarray(position_world, float)
    return T


def up_from_poses(world_from_cam: ArrayLike) -> F64:
    """The up direction (unit vector, world frame) of a camera path without gravity: its principal axes.

    A hand-held orbit or a car's path lies near a horizontal plane: its smallest-variance axis,
    signed like the cameras' mean "up" (-y, image up; cameras are held roughly level), is taken when
    the path spans a plane (middle variance over 4x the smallest) and that axis is within 45 degrees
    of the cameras' mean up. Otherwise (a line, a vertical sweep) the cameras' mean up; the first
    camera's -y when those cancel out. Measured on a simulated 60-frame orbit in its run's world:
    1.0 degree from the true up (the first camera's -y: 11 degrees).
    """
    T = np.asarray(world_from_cam, float).reshape(-1, 4, 4)
    if len(T) == 0:
        return Y_DOWN_UP.copy()
    cam_up = -T[:, :3, 1].mean(axis=0)
    n = float(np.linalg.norm(cam_up))
    cam_up = cam_up / n if n > 0.5 else -T[0, :3, 1]
    p = T[:, :3, 3]
    if len(p) >= 3:
        var, axes = np.linalg.eigh(np.cov((p - p.mean(axis=0)).T))
        normal = axes[:, 0] * (1.0 if axes[:, 0] @ cam_up >= 0 else -1.0)
        if var[1] > 4.0 * var[0] and normal @ cam_up > np.cos(np.radians(45.0)):
            return np.asarray(normal / np.linalg.norm(normal), float)
    return np.asarray(cam_up / np.linalg.norm(cam_up), float)


def world_up(world_from_cam: ArrayLike) -> F64:
    """The up direction (unit vector) of the world of a trajectory (``world_from_cam``, any units).

    A world that starts at its first camera (a run's, KITTI's ground truth: y down) has no known
    gravity: :func:`up_from_poses`. Other ground-truth worlds (simulator, motion capture, EuRoC) are
    z up, the convention of :func:`loopmodel.eval.plots.resolve_plot_mode` too.
    """
    T = np.asarray(world_from_cam, float).reshape(-1, 4, 4)
    if len(T) and not np.allclose(T[0], np.eye(4), atol=1e-6):
        return np.array([0.0, 0.0, 1.0])
    return up_from_poses(T)
