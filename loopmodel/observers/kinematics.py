"""Image-space kinematics of a static feature seen by a moving camera (seed 003 eq. 11-19).

Sign convention (stated because the seed's OCR is ambiguous): ``v = (v_s, w_s)`` is the
velocity of the static scene relative to the camera, expressed in the current camera frame,
so a scene point moves as ``d m_bar/dt = v_s + w_s x m_bar``; for a camera moving with
linear velocity ``v_cam`` and angular velocity ``w_cam`` (camera frame), ``v_s = -v_cam`` and
``w_s = -w_cam``. With ``R_bar = cur_from_ref`` rotation, ``dR_bar/dt = [w_s]x R_bar``.
Signals: ``e_v = (u - u*, v - v*, -ln alpha)``, ``alpha = z*/z``, ``e_w = u*phi = log(R_bar)``.
Then ``de_i/dt = J_i (v_s / z*_i, w_s)`` with
``J_i = [[alpha_i A_ei, -A_ei [m_i]x], [0, L_w]]``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from loopmodel.geometry.se3 import hat, so3_log

F64 = NDArray[np.float64]


def l_omega(e_w: ArrayLike) -> F64:
    """``L_w = I - (phi/2)[u]x + (1 - sinc(phi)/sinc^2(phi/2)) [u]x^2`` for ``e_w = u*phi`` (radians).

    The map from ``w_s`` to ``d(u*phi)/dt``.
    """
    ew = np.asarray(e_w, dtype=float).reshape(3)
    phi = float(np.linalg.norm(ew))
    if phi < 1e-9:
        return np.eye(3) - 0.5 * hat(ew)
    u = hat(ew / phi)
    coeff = 1.0 - np.sinc(phi / np.pi) / np.sinc(phi / (2 * np.pi)) ** 2
    return np.eye(3) - (phi / 2.0) * u + coeff * (u @ u)


def a_e(A: ArrayLike, p_px: ArrayLike) -> F64:
    """``A_e = A - [[0,0,u],[0,0,v],[0,0,0]]`` for each pixel ``p = (u, v)``: N x 3 x 3."""
    A = np.asarray(A, dtype=float)
    p = np.asarray(p_px, dtype=float).reshape(-1, 2)
    out = np.repeat(A[None], p.shape[0], axis=0)
    out[:, 0, 2] -= p[:, 0]
    out[:, 1, 2] -= p[:, 1]
    return out


def feature_jacobian(A: ArrayLike, p_px: ArrayLike, alpha: float, e_w: ArrayLike) -> F64:
    """6 x 6 ``J_i`` of one feature (pixel ``p_px``, depth ratio ``alpha = z*/z``), acting on
    ``(v_s / z*_i, w_s)``."""
    A = np.asarray(A, dtype=float)
    p = np.asarray(p_px, dtype=float).reshape(2)
    m = np.linalg.solve(A, np.array([p[0], p[1], 1.0]))
    Ae = a_e(A, p)[0]
    J = np.zeros((6, 6))
    J[:3, :3] = alpha * Ae
    J[:3, 3:] = -Ae @ hat(m)
    J[3:, 3:] = l_omega(e_w)
    return J


def error_signals(p_px: ArrayLike, p_ref_px: ArrayLike, alpha: ArrayLike, cur_from_ref_rot: ArrayLike) -> F64:
    """N x 6 signals ``e_i = (u - u*, v - v*, -ln alpha, u*phi)`` of N features."""
    p = np.asarray(p_px, dtype=float).reshape(-1, 2)
    pr = np.asarray(p_ref_px, dtype=float).reshape(-1, 2)
    al = np.asarray(alpha, dtype=float).reshape(-1)
    ew = so3_log(cur_from_ref_rot)
    return np.column_stack([p - pr, -np.log(al), np.repeat(ew[None], p.shape[0], axis=0)])
